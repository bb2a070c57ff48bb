"""The node's topic and service names (docs/interface.md §5), in one place: the node, its
clients, the bag tools and the demo all take them from here. Relative names, so a namespace
or remapping at launch moves them all."""

DEPTH_TOPIC = "depth/image_raw"
CAMERA_INFO_TOPIC = "depth/camera_info"
LABELS_TOPIC = "outcome/labels"
STATUS_TOPIC = "outcome/status"
OVERLAY_TOPIC = "outcome/overlay"
MARKERS_TOPIC = "outcome/markers"
CHECK_SERVICE = "outcome/check"
