"""The real outcome_node (subprocess, console script) exchanging real messages over DDS.

Two node processes serve the whole module (module-scoped fixtures):

- ``session``: the shipped YAML plus a checkpoint whose head bias makes ``fell_outside`` win
  on every pixel, so the answer is known by construction (one object covering the image) and
  the WARN level, 3-D centroids and markers can be checked exactly;
- ``band_session``: a depth-band checkpoint (``model_helpers``: success beyond 2 m,
  fell_outside nearer), so its labels follow the depth values and a decoding mistake shows;
  in namespace /cam1 with qos:=reliable and no overlay.

Everything else asserts structure and consistency (sizes, headers, status fields agreeing with
the labels received, in the model's label table), which must hold for any model; one more node
serves a model of another task (a shelf's outcomes). Tests with the shipped checkpoint and
known-truth images live elsewhere."""

from __future__ import annotations

import json
import random
import re
import subprocess
import sys
import time
from xml.etree import ElementTree

import numpy as np
import pytest

pytest.importorskip("rclpy", reason="ROS 2 rclpy is not installed")
pytest.importorskip("torch", reason="torch is not installed")

import cv2  # noqa: E402
import node_helpers as nh  # noqa: E402
import rcl_interfaces.srv as rcl_srv  # noqa: E402
from diagnostic_msgs.msg import DiagnosticStatus  # noqa: E402
from model_helpers import (  # noqa: E402
    BAND_FAR,
    BAND_NEAR,
    BAND_SPLIT_M,
    DEFAULT_ENVELOPE_CONFIG,
    SHELF_TABLE,
)
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import Image  # noqa: E402
from visualization_msgs.msg import Marker  # noqa: E402

from task_outcome_ros import labels as L  # noqa: E402
from task_outcome_ros.fragments import FRAGMENT_MAX_PIXELS  # noqa: E402
from task_outcome_ros.outcome_report import label_table_value  # noqa: E402

pytestmark = pytest.mark.ros

DOMAIN_ID = random.randint(1, 200)
CONFIG = nh.REPO / "config" / "outcome_node.yaml"
ALL_OUTPUTS = ("status", "labels", "overlay", "markers")
BURST = 24  # 640 x 480 frames published back to back: ~1 ms each, the model takes ~10
FELL_ID = L.DEFAULT_TABLE.outcome_ids["fell_outside"]


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("outcome_node")
    ckpt = nh.make_checkpoint(tmp / "fell_everywhere.pt", favour=FELL_ID)
    # The shipped YAML (so rcl must parse it) with the test checkpoint on top.
    proc = nh.NodeProcess(["--params-file", str(CONFIG), "-p", f"model_path:={ckpt}"],
                          DOMAIN_ID, tmp / "node.log")
    client = nh.OutcomeClient(DOMAIN_ID)
    try:
        client.wait_for_node(proc)
        # First exchange: the node's reader may match our writer a moment after we see it.
        client.request(nh.depth_msg(np.full((8, 8), 2.0, np.float32), stamp=client.next_stamp()),
                       timeout=30.0, resend_every=0.5)
        yield client, proc
    finally:
        client.close()
        proc.stop()


@pytest.fixture(scope="module")
def band_session(tmp_path_factory):
    """A second node: the depth-band model (labels follow depth), namespace /cam1,
    qos:=reliable, publish_overlay:=false."""
    tmp = tmp_path_factory.mktemp("outcome_node_band")
    domain = DOMAIN_ID % 200 + 1
    ckpt = nh.make_depth_band_checkpoint(tmp / "depth_band.pt")
    proc = nh.NodeProcess(["-r", "__ns:=/cam1", "-p", f"model_path:={ckpt}", "-p",
                           "qos:=reliable", "-p", "publish_overlay:=false"],
                          domain, tmp / "node.log")
    client = nh.OutcomeClient(domain, namespace="/cam1")
    try:
        client.wait_for_node(proc)
        yield client, proc
    finally:
        client.close()
        proc.stop()


def scene(h: int = 480, w: int = 640) -> np.ndarray:
    """Floor plane, a box, invalid rows and columns (NaN)."""
    d = np.full((h, w), 2.2, np.float32)
    d[h // 4: h // 2, w // 4: w // 2] = 1.9
    if h >= 20 and w >= 30:
        d[: h // 20] = np.nan
        d[:, -(w // 30):] = np.nan
    return d


def labels_array(msg) -> np.ndarray:
    return np.frombuffer(bytes(msg.data), np.uint8).reshape(msg.height, msg.step)[:, :msg.width]


def check_reply(request, reply, table: L.LabelTable = L.DEFAULT_TABLE) -> np.ndarray:
    """Sizes, encodings and headers of labels/status/overlay; status consistent with labels
    in the classes of ``table`` (the node's model's), which the status also carries."""
    key = nh.header_key(request.header)
    h, w = request.height, request.width
    lab = reply.labels
    assert (lab.encoding, lab.height, lab.width, lab.step) == ("mono8", h, w, w)
    assert nh.header_key(lab.header) == key and len(lab.data) == h * w
    labels = labels_array(lab)
    assert set(np.unique(labels)) <= set(range(table.num_classes))
    if reply.overlay is not None:
        ov = reply.overlay
        assert (ov.encoding, ov.height, ov.width, ov.step) == ("rgb8", h, w, 3 * w)
        assert nh.header_key(ov.header) == key and len(ov.data) == 3 * h * w

    assert nh.header_key(reply.status.header) == key
    (status,) = reply.status.status
    assert status.name == "task_outcome" and status.hardware_id == request.header.frame_id
    values = nh.status_values(reply.status)
    assert values["label_table"] == label_table_value(table)
    threshold = L.presence_threshold(h, w)
    present = {}
    for name, class_id in table.outcome_ids.items():
        pixels = int(values[f"{name}.pixels"])
        assert pixels == int(np.count_nonzero(labels == class_id))
        assert values[f"{name}.present"] in ("true", "false")
        present[name] = values[f"{name}.present"] == "true"
        assert present[name] == (pixels >= threshold)
        n_objects = int(values[f"{name}.objects"])
        assert 0 <= n_objects <= (pixels // threshold if present[name] else 0)
        if name in table.failures:
            for k in range(n_objects):
                u, v = (float(c) for c in values[f"{name}.{k}.centroid_px"].split(","))
                assert 0 <= u <= w - 1 and 0 <= v <= h - 1
            assert f"{name}.{n_objects}.centroid_px" not in values
    expected = ",".join(sorted(n for n, p in present.items() if p)) or "none"
    failure = any(present[n] for n in table.failures)
    outside = values["envelope"].startswith("outside: ")
    if outside:  # never OK, and the message says why
        assert status.message == f"{expected}; outside the trained envelope: " \
            + values["envelope"].removeprefix("outside: ")
    else:
        assert status.message == expected
        assert values["envelope"] in ("ok", "unchecked: the checkpoint records no training "
                                              "envelope")
    assert status.level == (DiagnosticStatus.WARN if failure or outside
                            else DiagnosticStatus.OK)
    # latency runs from the frame's arrival to its status, so it holds the inference
    assert 0 <= float(values["inference_ms"]) <= float(values["latency_ms"])
    assert int(values["dropped_frames"]) >= 0
    # reuse_floor_fit (default true): every frame with depth says what its plane was.
    assert values.get("support_plane", "fitted") in ("kept", "fitted")
    return labels


def test_parameters_declared_with_descriptions_and_defaults(session):
    client, _ = session
    names = ["model_path", "device", "backend", "presence_min_pixels", "fragment_max_pixels",
             "publish_overlay", "overlay_alpha", "publish_markers", "qos", "reuse_floor_fit"]
    describe = client.node.create_client(rcl_srv.DescribeParameters,
                                         "/outcome_node/describe_parameters")
    get = client.node.create_client(rcl_srv.GetParameters, "/outcome_node/get_parameters")
    try:
        assert client.spin_until(lambda: describe.service_is_ready() and get.service_is_ready(),
                                 20.0)
        fut_d = describe.call_async(rcl_srv.DescribeParameters.Request(names=names))
        fut_g = get.call_async(rcl_srv.GetParameters.Request(names=names))
        assert client.spin_until(lambda: fut_d.done() and fut_g.done(), 20.0)
    finally:
        client.node.destroy_client(describe)
        client.node.destroy_client(get)
    descriptors = fut_d.result().descriptors
    assert [d.name for d in descriptors] == names
    assert all(len(d.description) > 20 for d in descriptors)
    values = dict(zip(names, fut_g.result().values))
    assert values["device"].string_value == "cpu"
    assert values["backend"].string_value == "auto"
    assert values["qos"].string_value == "sensor_data"
    assert values["presence_min_pixels"].integer_value == L.PRESENCE_MIN_PIXELS
    assert values["fragment_max_pixels"].integer_value == FRAGMENT_MAX_PIXELS
    assert values["publish_overlay"].bool_value is True
    assert 0.0 <= values["overlay_alpha"].double_value <= 1.0
    assert values["model_path"].string_value.endswith("fell_everywhere.pt")
    assert values["publish_markers"].bool_value is True
    assert values["reuse_floor_fit"].bool_value is True


def _set_parameters(client, params) -> list:
    srv = client.node.create_client(rcl_srv.SetParameters, "/outcome_node/set_parameters")
    try:
        assert client.spin_until(srv.service_is_ready, 20.0)
        future = srv.call_async(rcl_srv.SetParameters.Request(
            parameters=[Parameter(name, value=value).to_parameter_msg()
                        for name, value in params]))
        assert client.spin_until(future.done, 20.0)
        return [r.successful for r in future.result().results]
    finally:
        client.node.destroy_client(srv)


def test_runtime_parameters(session):
    """overlay_alpha is live and range-checked; start-up-only parameters are read-only."""
    client, _ = session
    assert _set_parameters(client, [("overlay_alpha", 1.5), ("qos", "reliable"),
                                    ("model_path", "/tmp/x.pt")]) == [False, False, False]
    assert _set_parameters(client, [("overlay_alpha", 1.0)]) == [True]
    try:
        msg = nh.depth_msg(scene(48, 64), stamp=client.next_stamp())
        reply = client.request(msg, ("status", "labels", "overlay"))
        check_reply(msg, reply)
        overlay = np.frombuffer(bytes(reply.overlay.data), np.uint8).reshape(48, 64, 3)
        labels = np.frombuffer(bytes(reply.labels.data), np.uint8).reshape(48, 64)
        # alpha 1: pure label colours. This checkpoint labels every pixel fell_outside, except
        # where the depth is invalid (no measurement -> background, shown as depth only).
        fell = labels == FELL_ID
        assert fell.mean() > 0.5 and (labels[~fell] == L.BACKGROUND).all()
        colour = L.DEFAULT_TABLE.colours[FELL_ID]
        assert (overlay[fell] == colour).all()
        assert not (overlay[~fell] == colour).all(axis=-1).any()
    finally:
        assert _set_parameters(client, [("overlay_alpha", 0.5)]) == [True]


def test_float_depth_640x480(session):
    client, _ = session
    msg = nh.depth_msg(scene(), "32FC1", stamp=client.next_stamp(), frame_id="cam_a_optical")
    reply = client.request(msg, ALL_OUTPUTS)
    check_reply(msg, reply)
    # Known by construction of the test checkpoint: fell_outside everywhere -> WARN.
    (status,) = reply.status.status
    assert status.level == DiagnosticStatus.WARN and status.message == "fell_outside"
    assert nh.status_values(reply.status)["fell_outside.objects"] == "1"


def test_inf_and_negative_depth_are_invalid(band_session):
    client, _ = band_session
    base = scene(96, 128)
    weird = base.copy()
    weird[40:50, 10:40] = np.inf
    weird[60:70, 10:40] = -1.5
    weird[80:90, 10:40] = 0.0
    nan = base.copy()
    nan[40:50, 10:40] = nan[60:70, 10:40] = nan[80:90, 10:40] = np.nan
    got = []
    for depth in (weird, nan):
        msg = nh.depth_msg(depth, stamp=client.next_stamp())
        got.append(check_reply(msg, client.request(msg, ("status", "labels"))))
    np.testing.assert_array_equal(got[0], got[1])


# (encoding, big-endian, row padding in bytes, (height, width))
VARIANTS = [
    ("16UC1", False, 0, (480, 640)),
    ("32FC1", True, 0, (480, 640)),
    ("16UC1", True, 0, (480, 640)),
    ("32FC1", False, 12, (480, 640)),
    ("16UC1", True, 6, (480, 640)),
    ("32FC1", False, 0, (77, 101)),
    ("16UC1", False, 2, (3, 500)),
    ("32FC1", True, 0, (1, 1)),
]


@pytest.mark.parametrize("encoding,bigendian,pad,size", VARIANTS,
                         ids=[f"{e}-{'be' if b else 'le'}-pad{p}-{s[1]}x{s[0]}"
                              for e, b, p, s in VARIANTS])
def test_encodings_endianness_padding_sizes(band_session, encoding, bigendian, pad, size):
    """Every variant keeps size and header and gives the labels of the depth it encodes: the
    depth-band model's fell_outside on the near box, success on the far floor, and the same
    labels as its plain little-endian twin."""
    client, _ = band_session
    depth = scene(*size)
    plain = nh.depth_msg(depth, encoding, stamp=client.next_stamp(), frame_id="plain")
    msg = nh.depth_msg(depth, encoding, stamp=client.next_stamp(), frame_id="variant_frame",
                       bigendian=bigendian, pad=pad)
    assert msg.step == size[1] * (4 if encoding == "32FC1" else 2) + pad
    ref = check_reply(plain, client.request(plain, ("status", "labels")))
    got = check_reply(msg, client.request(msg, ("status", "labels")))
    np.testing.assert_array_equal(got, ref)
    valid = np.isfinite(depth)
    far = valid & (depth > BAND_SPLIT_M)
    # Away from the box's edges (the network works at a quarter of the size).
    interior = cv2.erode(far.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
    assert (got[interior] == BAND_FAR).all()
    near = cv2.erode((valid & ~far).astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
    assert (got[near] == BAND_NEAR).all()
    if size[0] * size[1] >= 64 * 64:  # the scene has a box big enough to be its own class
        assert {BAND_FAR, BAND_NEAR} <= set(np.unique(got))


@pytest.mark.parametrize("encoding,fill", [("32FC1", np.nan), ("16UC1", 0.0),
                                           ("32FC1", -np.inf)])
def test_no_valid_depth_is_a_valid_frame(session, encoding, fill):
    client, _ = session
    msg = nh.depth_msg(np.full((48, 64), fill, np.float32), encoding, stamp=client.next_stamp())
    reply = client.request(msg, ("status", "labels", "overlay"))
    labels = check_reply(msg, reply)
    (status,) = reply.status.status
    assert status.level == DiagnosticStatus.OK and status.message == "none"
    assert not labels.any()


BAD_FRAMES = {
    # name: (encoding, height, width, step, n_bytes, big-endian, words the status must contain)
    "rgb8": ("rgb8", 24, 32, 96, 96 * 24, False, "encoding"),
    "8UC1": ("8UC1", 24, 32, 32, 32 * 24, False, "encoding"),
    "64FC1": ("64FC1", 24, 32, 256, 256 * 24, False, "encoding"),
    "empty-encoding": ("", 24, 32, 128, 128 * 24, False, "encoding"),
    "data-too-short": ("32FC1", 24, 32, 128, 128 * 24 - 1, False, "bytes"),
    "data-too-long": ("32FC1", 24, 32, 128, 128 * 24 + 4, True, "bytes"),
    "step-smaller-than-row": ("16UC1", 24, 32, 60, 60 * 24, False, "step"),
    "zero-width": ("32FC1", 24, 0, 0, 0, False, "size"),
    "zero-height": ("16UC1", 0, 32, 64, 0, False, "size"),
    "huge": ("32FC1", 1, 100_000, 400_000, 64, False, "limit"),
}


@pytest.mark.parametrize("name", list(BAD_FRAMES))
def test_bad_frame_gives_error_status_and_node_goes_on(session, name):
    client, proc = session
    encoding, h, w, step, n_bytes, big, words = BAD_FRAMES[name]
    bad = nh.raw_image(encoding, h, w, step, bytes(n_bytes), stamp=client.next_stamp(),
                    frame_id=f"bad_{name}", bigendian=big)
    reply = client.request(bad)
    assert nh.header_key(reply.status.header) == nh.header_key(bad.header)
    (status,) = reply.status.status
    assert status.level == DiagnosticStatus.ERROR and status.name == "task_outcome"
    assert status.hardware_id == f"bad_{name}"
    assert words in status.message, status.message
    assert "dropped_frames" in nh.status_values(reply.status)

    good = nh.depth_msg(scene(24, 32), stamp=client.next_stamp())
    check_reply(good, client.request(good, ("status", "labels")))
    # Outputs are in order per topic: had the bad frame produced labels, they came first.
    assert client.replies[nh.header_key(bad.header)].labels is None
    assert proc.alive()
    # The warning is throttled (WARN_THROTTLE_S) and the node serves every case of this test,
    # so the log shows the first bad frame's skip; each frame's own evidence is its ERROR status.
    assert re.search(r"skipping depth frame \(frame_id 'bad_\w+'\): bad depth image",
                     proc.log()), proc.log()


def _request_until(client, make_msg, predicate, timeout: float = 15.0):
    """Send fresh frames until a reply satisfies ``predicate`` (camera_info is best effort)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        msg = make_msg()
        reply = client.request(msg, ALL_OUTPUTS)
        if predicate(nh.status_values(reply.status)):
            return msg, reply
    raise TimeoutError("the node never reflected the camera_info that was sent")


def test_camera_info_gives_3d_centroids_and_markers(session):
    client, _ = session
    h, w, z = 48, 64, 2.0
    fx, cx, cy = 60.0, 30.0, 26.0

    def make_msg():
        client.info_pub.publish(nh.camera_info(w, h, fx, cx, cy))
        return nh.depth_msg(np.full((h, w), z, np.float32), stamp=client.next_stamp())

    msg, reply = _request_until(client, make_msg, lambda v: "fell_outside.0.centroid_m" in v)
    check_reply(msg, reply)
    values = nh.status_values(reply.status)
    u, v = (float(c) for c in values["fell_outside.0.centroid_px"].split(","))
    assert (u, v) == pytest.approx(((w - 1) / 2, (h - 1) / 2), abs=0.05)
    xyz = [float(c) for c in values["fell_outside.0.centroid_m"].split(",")]
    assert xyz == pytest.approx([(u - cx) * z / fx, (v - cy) * z / fx, z], abs=2e-3)
    assert "camera_info" not in values

    markers = reply.markers.markers
    assert markers[0].action == Marker.DELETEALL
    (sphere,) = markers[1:]
    assert (sphere.type, sphere.ns, sphere.id) == (Marker.SPHERE, "fell_outside", 0)
    assert nh.header_key(sphere.header) == nh.header_key(msg.header)
    p = sphere.pose.position
    assert [p.x, p.y, p.z] == pytest.approx(xyz, abs=2e-3)


def test_camera_info_of_another_size_is_ignored_and_reported(session):
    client, _ = session

    def make_msg():
        client.info_pub.publish(nh.camera_info(640, 480, 570.0, 320.0, 240.0))
        return nh.depth_msg(np.full((48, 64), 2.0, np.float32), stamp=client.next_stamp())

    msg, reply = _request_until(client, make_msg, lambda v: "camera_info" in v)
    values = nh.status_values(reply.status)
    assert "does not match" in values["camera_info"] and "640 x 480" in values["camera_info"]
    assert not any(k.endswith("centroid_m") for k in values)
    assert "fell_outside.0.centroid_px" in values
    assert reply.markers.markers[0].action == Marker.DELETEALL
    assert len(reply.markers.markers) == 1


def test_burst_keeps_only_the_newest_and_counts_drops(session):
    """A burst faster than the model: frames that wait are overwritten (counted), so only a
    few are processed and the last is answered. A node that queued every frame would answer
    them all and count no drop."""
    client, proc = session
    before = client.request(nh.depth_msg(scene(24, 32), stamp=client.next_stamp()))
    dropped_before = int(nh.status_values(before.status)["dropped_frames"])
    burst = [nh.depth_msg(scene(), stamp=client.next_stamp(), frame_id="burst")
             for _ in range(BURST)]
    for msg in burst[:-1]:
        client.image_pub.publish(msg)
    last = client.request(burst[-1], ("status", "labels"), resend_every=5.0)
    check_reply(burst[-1], last)
    client.spin_until(lambda: False, 1.0)  # late answers to earlier frames, if any
    processed = sum(nh.header_key(m.header) in client.replies for m in burst)
    dropped = int(nh.status_values(last.status)["dropped_frames"]) - dropped_before
    assert dropped >= 1, "no frame was overwritten: the node queued the burst"
    assert processed <= BURST - dropped  # each frame processed, overwritten or lost, once
    assert processed < BURST, f"all {BURST} burst frames were processed: queued, not dropped"
    assert proc.alive()


def test_namespace_reliable_qos_and_no_overlay(band_session):
    """Relative topic names follow the namespace; qos:=reliable and publish_overlay:=false."""
    client, proc = band_session
    assert client.image_pub.topic_name == "/cam1/depth/image_raw"
    msgs = [nh.depth_msg(scene(60, 80), "16UC1", stamp=client.next_stamp()) for _ in range(2)]
    for msg in msgs:  # reliable input: no resend needed, even for the first frame
        check_reply(msg, client.request(msg, ("status", "labels"), resend_every=20.0))
    # Outputs are published in order labels, status, (overlay), markers: had an overlay been
    # published for the first frame, it would be here by the time the second one is answered.
    assert all(client.replies[nh.header_key(m.header)].overlay is None for m in msgs)
    assert "qos reliable" in proc.log()


@pytest.mark.parametrize("case", ["qos", "presence_min_pixels", "fragment_max_pixels",
                                  "overlay_alpha", "missing_model",
                                  "corrupt_model", "not_a_checkpoint"])
def test_bad_parameter_or_model_stops_node_with_clear_message(tmp_path, case):
    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(bytes(random.Random(0).randrange(256) for _ in range(4096)))
    foreign = tmp_path / "foreign.pt"
    import torch
    torch.save({"weights": torch.zeros(3)}, foreign)
    args, needle = {
        "qos": (["-p", "qos:=bogus"], "'qos'"),
        "presence_min_pixels": (["-p", "presence_min_pixels:=0"], "presence_min_pixels"),
        "fragment_max_pixels": (["-p", "fragment_max_pixels:=-1"], "fragment_max_pixels"),
        "overlay_alpha": (["-p", "overlay_alpha:=1.5"], "overlay_alpha"),
        "missing_model": (["-p", "model_path:=/nonexistent/outcome.pt"],
                          "/nonexistent/outcome.pt"),
        "corrupt_model": (["-p", f"model_path:={corrupt}"], str(corrupt)),
        "not_a_checkpoint": (["-p", f"model_path:={foreign}"], str(foreign)),
    }[case]
    result = nh.run_node_expect_exit(args, timeout=45.0)
    assert result.returncode != 0
    err = result.stderr + result.stdout
    assert "FATAL" in err and needle in err, err
    assert "Traceback" not in err, err


def test_config_yaml_lists_every_declared_parameter():
    yaml = pytest.importorskip("yaml")
    from task_outcome_ros.node import PARAMS

    params = yaml.safe_load(CONFIG.read_text())["outcome_node"]["ros__parameters"]
    assert params == {name: spec.default for name, spec in PARAMS.items()}


def test_launch_file_compiles():
    source = (nh.REPO / "launch" / "outcome.launch.py").read_text()
    compile(source, "outcome.launch.py", "exec")
    assert "outcome_node.yaml" in source and "def generate_launch_description" in source


def test_fastdds_profile_is_valid_and_loads_without_errors():
    root = ElementTree.parse(nh.SHM_PROFILE).getroot()
    ns = {"f": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
    shm = [t for t in root.iterfind(".//f:transport_descriptor", ns)
           if t.findtext("f:type", namespaces=ns) == "SHM"]
    assert len(shm) == 1
    assert int(shm[0].findtext("f:segment_size", namespaces=ns)) >= 8 * 640 * 480 * 4
    participant = root.find(".//f:participant[@is_default_profile='true']", ns)
    assert participant.findtext("f:rtps/f:useBuiltinTransports", namespaces=ns) == "false"
    # Fast DDS reports a bad profile on stderr ("XMLPARSER Error") and silently falls back.
    code = ("import rclpy; from rclpy.node import Node; rclpy.init(); n = Node('xml_probe'); "
            "n.destroy_node(); rclpy.shutdown(); print('ok')")
    result = subprocess.run([sys.executable, "-c", code], env=nh.ros_env(),
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and result.stdout.strip() == "ok", result.stderr
    assert "Error" not in result.stdout + result.stderr


def test_package_imports_without_rclpy():
    code = (
        "import sys, importlib, pkgutil\n"
        "sys.modules['rclpy'] = None\n"  # any `import rclpy` now raises ImportError
        "import task_outcome_ros, training\n"
        "mods = ['task_outcome_ros.inference', 'task_outcome_ros.labels',\n"
        "        'task_outcome_ros.depth', 'task_outcome_ros.model',\n"
        "        'task_outcome_ros.checkpoint', 'training.config']\n"
        "mods += ['task_outcome_ros.' + m.name for m in\n"
        "         pkgutil.iter_modules(task_outcome_ros.__path__)\n"
        "         if m.name not in ('node', 'bag_tools') and not m.name.startswith('_')]\n"
        "for name in dict.fromkeys(mods):\n"
        "    importlib.import_module(name)\n"
        "try:\n"
        "    importlib.import_module('task_outcome_ros.node')\n"
        "except ImportError:\n"
        "    pass\n"
        "else:\n"
        "    raise SystemExit('task_outcome_ros.node imported although rclpy is blocked')\n"
        "print('ok', len(mods))\n")
    result = subprocess.run([sys.executable, "-c", code], cwd=nh.REPO, env=nh.ros_env(),
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("ok")


def test_overlay_listener_leaving_and_returning_keeps_the_outputs_coming(session):
    """Nobody on outcome/overlay: labels and status still come; a subscriber that joins
    later gets overlays again (the node checks for listeners per frame). That the overlay is
    then not made cannot be seen from outside the node: nobody is there to receive it."""
    client, proc = session
    overlay_sub = client.subs[2]
    client.node.destroy_subscription(overlay_sub)
    try:
        assert client.spin_until(
            lambda: client.node.count_subscribers("outcome/overlay") == 0, 10.0)
        client.spin_until(lambda: False, 0.5)  # the node's side of discovery catches up
        msg = nh.depth_msg(scene(), stamp=client.next_stamp())
        reply = client.request(msg, ("status", "labels"))
        check_reply(msg, reply)  # labels and status come without an overlay listener
    finally:
        client.subs[2] = client.node.create_subscription(
            Image, "outcome/overlay", client._store("overlay"), nh.RELIABLE)
    assert client.spin_until(lambda: client.subs[2].get_publisher_count() >= 1, 10.0)
    client.spin_until(lambda: False, 0.5)
    again = nh.depth_msg(scene(), stamp=client.next_stamp())
    check_reply(again, client.request(again, ALL_OUTPUTS))
    assert proc.alive()


def test_a_static_camera_keeps_its_support_plane_and_a_moved_one_refits(session):
    """reuse_floor_fit: the same view again keeps the plane (same labels); another view
    (the camera 20 cm higher) is fitted afresh."""
    client, proc = session
    view = scene()
    replies = []
    for _ in range(2):
        msg = nh.depth_msg(view, stamp=client.next_stamp())
        reply = client.request(msg, ("status", "labels"))
        replies.append((labels_array(reply.labels), nh.status_values(reply.status)))
    assert replies[1][1]["support_plane"] == "kept"
    assert np.array_equal(replies[0][0], replies[1][0])
    moved = nh.depth_msg(view + np.float32(0.2), stamp=client.next_stamp())
    assert nh.status_values(client.request(moved).status)["support_plane"] == "fitted"
    assert proc.alive()


# What a robot does not install: the simulator, the clustering, the plots, the training code.
TRAINING_ONLY = ("pybullet", "sklearn", "matplotlib", "training")


def test_node_without_training_dependencies_flags_frames_outside_its_envelope(tmp_path):
    """The node imports and answers in a process where pybullet, scikit-learn, matplotlib and
    ``training`` cannot be imported; its model knows its training envelope, so a frame with no
    container in it is WARN with the reason, although only success is present."""
    code = ("import sys\n"
            f"for name in {TRAINING_ONLY!r}:\n"
            "    sys.modules[name] = None\n"
            "from task_outcome_ros.node import main\n"
            "sys.exit(main(sys.argv))\n")
    domain = (DOMAIN_ID + 50) % 200 + 1
    ckpt = nh.make_checkpoint(tmp_path / "success_everywhere.pt",
                              favour=L.DEFAULT_TABLE.outcome_ids["success"],
                              dataset=DEFAULT_ENVELOPE_CONFIG)
    proc = nh.NodeProcess(["-p", f"model_path:={ckpt}"], domain, tmp_path / "node.log",
                          command=[sys.executable, "-c", code, "outcome_node"])
    client = nh.OutcomeClient(domain)
    try:
        client.wait_for_node(proc)
        msg = nh.depth_msg(scene(60, 80), stamp=client.next_stamp())
        reply = client.request(msg, ("status", "labels"), resend_every=0.5)
        check_reply(msg, reply)
        (status,) = reply.status.status
        assert status.level == DiagnosticStatus.WARN
        assert status.message.startswith("success; outside the trained envelope: ")
        assert "fixture not seen" in nh.status_values(reply.status)["envelope"]
        client.spin_until(lambda: "outside what the model was trained for" in proc.log(), 5.0)
        assert "Use the shipped model for this kind of cell" in proc.log()
        # camera_info keeps coming, images do not: the node says they are being lost.
        for _ in range(40):
            client.info_pub.publish(nh.camera_info(80, 60, 70.0, 39.5, 29.5))
            client.spin_until(lambda: False, 0.01)
        assert client.spin_until(lambda: "large images are being lost" in proc.log(), 10.0)
        assert "fastdds_shm.xml" in proc.log()
        modules = subprocess.run(
            [sys.executable, "-c", "import sys; import task_outcome_ros.node, "
             "task_outcome_ros.bag_tools, task_outcome_ros.replay, task_outcome_ros.live_bag; "
             f"print(sorted(m for m in {TRAINING_ONLY!r} if m in sys.modules))"],
            cwd=nh.REPO, env=nh.ros_env(), capture_output=True, text=True, timeout=120)
        assert modules.returncode == 0, modules.stderr
        assert modules.stdout.strip() == "[]", modules.stdout  # nothing pulled in indirectly
    finally:
        client.close()
        assert proc.stop() == 0
    assert "Traceback" not in proc.log(), proc.log()


def test_shipped_tote_model_loads_by_name_and_knows_its_envelope(tmp_path):
    """model_path:=tote starts the shipped tote model; a frame of the default task's scene
    (a floor 2.2 m away) is outside the tote's envelope, so never OK. Its median depth lies
    within what a tote on a table shows (the room floor 0.8 m below the table top), but the
    tote model sees no fixture in it."""
    domain = (DOMAIN_ID + 70) % 200 + 1
    proc = nh.NodeProcess(["-p", "model_path:=tote"], domain, tmp_path / "node.log")
    client = nh.OutcomeClient(domain)
    try:
        client.wait_for_node(proc)
        # The start-up line may reach the log file after the topics are matched.
        assert client.spin_until(lambda: "outcome_fcn_tote.pt" in proc.log(), 10.0), \
            proc.log()
        msg = nh.depth_msg(scene(), stamp=client.next_stamp())
        reply = client.request(msg, ("status", "labels"), resend_every=0.5)
        check_reply(msg, reply)
        (status,) = reply.status.status
        assert status.level == DiagnosticStatus.WARN
        envelope = nh.status_values(reply.status)["envelope"]
        assert envelope.startswith("outside: ") and "fixture" in envelope, envelope
    finally:
        client.close()
        assert proc.stop() == 0


def test_shipped_shelf_model_lists_the_shelfs_outcomes(tmp_path):
    """model_path:=shelf starts the shipped shelf model, a task whose outcomes discovery
    found: its status names them and carries its label table."""
    import json

    from task_outcome_ros import checkpoint
    from task_outcome_ros.inference import resolve_model_path

    shelf = checkpoint.load(resolve_model_path("shelf")).label_table
    domain = (DOMAIN_ID + 71) % 200 + 1
    proc = nh.NodeProcess(["-p", "model_path:=shelf"], domain, tmp_path / "node.log")
    client = nh.OutcomeClient(domain)
    try:
        client.wait_for_node(proc)
        msg = nh.depth_msg(scene(), stamp=client.next_stamp())
        reply = client.request(msg, ("status", "labels"), resend_every=0.5)
        check_reply(msg, reply, shelf)
        assert client.spin_until(lambda: "outcome_fcn_shelf.pt" in proc.log()
                                 and "hanging_over_edge (failure)" in proc.log(), 10.0), \
            proc.log()
        values = nh.status_values(reply.status)
        present = {k.removesuffix(".present") for k in values if k.endswith(".present")}
        assert present == {"on_shelf", "fell_off", "hanging_over_edge"}
        table = json.loads(values["label_table"])
        assert [c["name"] for c in table] == ["background", "shelf", "on_shelf", "fell_off",
                                              "hanging_over_edge"]
        assert [c["failure"] for c in table][2:] == [False, True, True]
    finally:
        client.close()
        assert proc.stop() == 0


def _check_with_fresh_frames(client, checker, depth: np.ndarray, timeout: float = 15.0):
    """Call outcome/check and publish frames stamped now (the node's clock) until it answers."""
    from task_outcome_ros.client import parse

    future = checker.call_async()
    deadline = time.monotonic() + timeout
    while not future.done() and time.monotonic() < deadline:
        ns = client.node.get_clock().now().nanoseconds
        client.image_pub.publish(nh.depth_msg(depth, stamp=(ns // 10**9, ns % 10**9)))
        client.spin_until(future.done, 0.1)
    assert future.done(), "outcome/check did not answer"
    return parse(future.result().success, future.result().message)


def test_a_model_of_another_task_speaks_its_own_outcomes(tmp_path):
    """A shelf model (on_shelf, fell_off, hanging_over_edge, tipped; its head makes tipped, id
    5, win everywhere): the status names the shelf's outcomes and carries its table, tipped
    (a failure mode of that table) is WARN, the overlay and the markers take its colour, and
    outcome/check reports it as a failure."""
    from task_outcome_ros.client import OutcomeCheckClient

    domain = (DOMAIN_ID + 90) % 200 + 1
    tipped = SHELF_TABLE.outcome_ids["tipped"]
    ckpt = nh.make_checkpoint(tmp_path / "shelf_tipped.pt", favour=tipped, table=SHELF_TABLE)
    proc = nh.NodeProcess(["-p", f"model_path:={ckpt}", "-p", "overlay_alpha:=1.0"], domain,
                          tmp_path / "node.log")
    client = nh.OutcomeClient(domain)
    try:
        client.wait_for_node(proc)
        outcomes = ("outcomes on_shelf, fell_off (failure), hanging_over_edge (failure), "
                    "tipped (failure)")  # logged at start-up, maybe after the topics match
        assert client.spin_until(lambda: outcomes in proc.log(), 10.0), proc.log()
        h, w = 48, 64
        depth = np.full((h, w), 2.0, np.float32)

        def make_msg():
            client.info_pub.publish(nh.camera_info(w, h, 60.0, 30.0, 26.0))
            return nh.depth_msg(depth, stamp=client.next_stamp())

        msg, reply = _request_until(client, make_msg, lambda v: "tipped.0.centroid_m" in v)
        labels = check_reply(msg, reply, SHELF_TABLE)
        (status,) = reply.status.status
        assert status.level == DiagnosticStatus.WARN and status.message == "tipped"
        values = nh.status_values(reply.status)
        assert json.loads(values["label_table"]) == SHELF_TABLE.to_dict()["classes"]
        assert values["tipped.present"] == "true" and values["on_shelf.present"] == "false"
        assert not any(k.startswith(("success.", "fell_outside.", "stuck_on_rim."))
                       for k in values)
        assert (labels == tipped).all()
        colour = SHELF_TABLE.colours[tipped]
        overlay = np.frombuffer(bytes(reply.overlay.data), np.uint8).reshape(h, w, 3)
        assert (overlay == colour).all()
        (sphere,) = reply.markers.markers[1:]
        assert sphere.ns == "tipped"
        assert [sphere.color.r, sphere.color.g, sphere.color.b] == pytest.approx(
            [c / 255.0 for c in colour], abs=1e-6)

        checker = OutcomeCheckClient(client.node)
        assert checker.wait_for_service(20.0), proc.log()
        answer = _check_with_fresh_frames(client, checker, depth)
        assert not answer.success and answer.outcomes == ("tipped",), answer
        assert [f.outcome for f in answer.failures] == ["tipped"]
    finally:
        client.close()
        assert proc.stop() == 0
    assert "Traceback" not in proc.log(), proc.log()


def test_shutdown_is_clean(session, band_session):
    """Last: SIGINT ends both nodes with exit code 0 and no traceback."""
    for _, proc in (session, band_session):
        assert proc.alive()
        assert proc.stop() == 0
        assert "Traceback" not in proc.log(), proc.log()
