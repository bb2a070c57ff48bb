"""The rclpy edge (docs/interface.md §5): depth image in -> labels, status, overlay, markers out.

The node converts messages to arrays and back. Each frame goes through
``frames.process_frame``, the step ``outcome_bag`` shares (decode, camera_info, segment, status
fields, overlay), so the node itself only holds parameters, QoS, threading and publishing.
Besides this module only the DDS tools (replay.py, live_bag.py, client.py) import rclpy.

Real time: the subscription callback only keeps the newest image (an overwritten, never
processed one counts as dropped); one worker thread processes whatever is newest, so a slow
model lags by at most one frame and memory never grows. Bad frames are reported (throttled
warning + ERROR status with the frame's header) and skipped; bad parameters or a bad model stop
the node at start-up with a FATAL message naming what to fix.
"""

from __future__ import annotations

import array
import signal
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import ColorRGBA, Header
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker, MarkerArray

from task_outcome_ros import labels as L
from task_outcome_ros import outcome_report as R
from task_outcome_ros.bag_io import stamp_to_ns
from task_outcome_ros.check import CheckBook, frame_answer
from task_outcome_ros.fragments import FRAGMENT_MAX_PIXELS
from task_outcome_ros.frames import NO_CAMERA_INFO_NOTE, FrameOutputs, process_frame, since_ms
from task_outcome_ros.topics import (
    CAMERA_INFO_TOPIC,
    CHECK_SERVICE,
    DEPTH_TOPIC,
    LABELS_TOPIC,
    MARKERS_TOPIC,
    OVERLAY_TOPIC,
    STATUS_TOPIC,
)
from task_outcome_ros.transport import TransportMonitor

NODE_NAME = "outcome_node"
STATUS_NAME = R.STATUS_NAME
QOS_CHOICES = ("sensor_data", "reliable")
DEVICE_CHOICES = ("cpu", "cuda", "auto")
BACKEND_CHOICES = ("auto", "torch", "onnx")
WARN_THROTTLE_S = 2.0
ENVELOPE_THROTTLE_S = 10.0
# While outcome/check requests wait, rclpy re-runs their coroutines on every spin and a spin
# returns at once: the main loop then pauses this long between spins (the answer is at most
# this much later) instead of taking a core from inference.
CHECK_SPIN_PAUSE_S = 0.002
MARKER_DIAMETER_M = 0.1


class StartupError(Exception):
    """A parameter or model problem that must stop the node; the text says what to fix."""


@dataclass(frozen=True)
class _ParamSpec:
    default: Any
    description: str
    read_only: bool
    hint: str  # what a valid value looks like, for the FATAL message
    value_range: tuple[Any, Any] | None = None  # inclusive; int or float like the default


PARAMS: dict[str, _ParamSpec] = {
    "model_path": _ParamSpec(
        "", "A shipped model's name (default, tote, ...) or a checkpoint (.pt) file; '' = the "
            "default task's shipped model. Its ONNX export beside it is used by backend auto.",
        True, "a shipped model's name, a readable checkpoint file, or '' for the default"),
    "device": _ParamSpec(
        "cpu", "Torch device: 'cpu', 'cuda' or 'auto' (cuda when available).",
        True, f"one of {', '.join(DEVICE_CHOICES)}"),
    "backend": _ParamSpec(
        "auto", "Inference backend: 'auto', 'torch' or 'onnx' (onnxruntime).",
        True, f"one of {', '.join(BACKEND_CHOICES)}"),
    "presence_min_pixels": _ParamSpec(
        L.PRESENCE_MIN_PIXELS,
        "Pixels an outcome needs to count as present at 640x480 (scaled with image area).",
        True, "an integer >= 1 (default 50)", (1, 1_000_000)),
    "fragment_max_pixels": _ParamSpec(
        FRAGMENT_MAX_PIXELS,
        "One object, one outcome: an outcome fragment smaller than this many pixels at 640x480 "
        "(scaled with image area) that touches another outcome takes that outcome; 0 = off.",
        True, f"an integer >= 0 (default {FRAGMENT_MAX_PIXELS})", (0, 1_000_000)),
    "reuse_floor_fit": _ParamSpec(
        True, "Static camera: keep the support-plane fit of one frame for the next while it "
              "still fits (checked on 400 pixels; refitted when the camera moves or "
              "camera_info changes). Status value support_plane says kept or fitted.",
        True, "true or false"),
    "threads": _ParamSpec(
        1, "CPU threads for inference (torch and onnxruntime). 1 is the measured best on a "
           "2-core machine shared with other work (bench/inference.py).",
        True, "an integer >= 1 (default 1)", (1, 256)),
    "publish_overlay": _ParamSpec(
        True, "Publish outcome/overlay (rgb8 colourised depth with the labels blended in).",
        False, "true or false"),
    "overlay_alpha": _ParamSpec(
        R.DEFAULT_OVERLAY_ALPHA,
        "Weight of the label colours in outcome/overlay, 0 (depth only) to 1 (labels only).",
        False, "a floating-point number in [0.0, 1.0], e.g. 0.5", (0.0, 1.0)),
    "publish_markers": _ParamSpec(
        True, "Publish outcome/markers: a sphere at each failure object's 3-D centroid "
              "(needs depth/camera_info).",
        False, "true or false"),
    "check_timeout_s": _ParamSpec(
        2.0, "outcome/check waits at most this long for a frame stamped after the request; "
             "then it answers success=false, 'no frame within N s'.",
        False, "a floating-point number of seconds in [0.05, 60.0], e.g. 2.0", (0.05, 60.0)),
    "qos": _ParamSpec(
        "sensor_data", "QoS of the depth/image_raw and depth/camera_info subscriptions: "
                       "'sensor_data' (best effort, keep last 5) or 'reliable' (keep last 5). "
                       "Outputs are always reliable (keep last 5) so any subscriber matches.",
        True, f"one of {', '.join(QOS_CHOICES)}"),
}


def subscription_qos(name: str) -> QoSProfile:
    """The input QoS for the `qos` parameter value."""
    if name == "sensor_data":
        return qos_profile_sensor_data
    if name == "reliable":
        return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5,
                          reliability=ReliabilityPolicy.RELIABLE)
    raise ValueError(f"qos must be one of {QOS_CHOICES}, got {name!r}")


OUTPUT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5,
                        reliability=ReliabilityPolicy.RELIABLE)


# --- the node ---------------------------------------------------------------------------------

class OutcomeNode(Node):
    """Parameters, QoS and message conversion around an ``OutcomeSegmenter``."""

    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__(NODE_NAME, **node_kwargs)
        self._params = self._declare_and_validate()
        self._segmenter = self._load_segmenter()

        in_qos = subscription_qos(self._params["qos"])
        self._pub_labels = self.create_publisher(Image, LABELS_TOPIC, OUTPUT_QOS)
        self._pub_status = self.create_publisher(DiagnosticArray, STATUS_TOPIC, OUTPUT_QOS)
        self._pub_overlay = self.create_publisher(Image, OVERLAY_TOPIC, OUTPUT_QOS)
        self._pub_markers = self.create_publisher(MarkerArray, MARKERS_TOPIC, OUTPUT_QOS)

        self._lock = threading.Condition()
        self._pending: tuple[Image, float] | None = None  # newest unprocessed (msg, t_received)
        self._dropped = 0
        self._camera_info: CameraInfo | None = None
        self._transport = TransportMonitor()  # callbacks only: the executor's one thread
        self._stop = False

        # outcome/check: requests wait, as coroutines, for a newer frame. A waiting coroutine
        # holds its callback group, hence a reentrant group of its own: concurrent requests
        # all wait, and the subscriptions (default group) keep running.
        self._checks = CheckBook()
        self.create_service(Trigger, CHECK_SERVICE, self._on_check,
                            callback_group=ReentrantCallbackGroup())
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.create_subscription(Image, DEPTH_TOPIC, self._on_image, in_qos)
        self.create_subscription(CameraInfo, CAMERA_INFO_TOPIC, self._on_camera_info, in_qos)
        self._worker = threading.Thread(target=self._work, name="outcome_worker", daemon=True)
        self._worker.start()
        heights = (f"heights from {self.resolve_topic_name('depth/camera_info')} (the "
                   "nominal camera until it arrives)" if self._segmenter.uses_intrinsics
                   else "heights from the nominal camera")
        self.get_logger().info(
            f"ready: model {self._model_desc} ({_outcomes_desc(self._segmenter.table)}), "
            f"device {self._params['device']}, "
            f"backend {self._params['backend']}, qos {self._params['qos']}, {heights}; "
            f"listening on {self.resolve_topic_name('depth/image_raw')}")

    # parameters and model ------------------------------------------------------------------
    def _declare_and_validate(self) -> dict[str, Any]:
        values: dict[str, Any] = {}
        for name, spec in PARAMS.items():
            desc = ParameterDescriptor(name=name, description=spec.description,
                                       read_only=spec.read_only,
                                       additional_constraints=f"valid: {spec.hint}")
            if spec.value_range is not None:
                lo, hi = spec.value_range
                if isinstance(spec.default, int):
                    desc.integer_range = [IntegerRange(from_value=lo, to_value=hi, step=1)]
                else:
                    desc.floating_point_range = [
                        FloatingPointRange(from_value=lo, to_value=hi, step=0.0)]
            try:
                values[name] = self.declare_parameter(name, spec.default, desc).value
            except Exception as exc:  # rclpy raises several types for wrong type / range
                raise StartupError(f"parameter '{name}' has an invalid value: must be "
                                   f"{spec.hint} ({_exc_reason(exc)})") from None
        for name, choices in (("device", DEVICE_CHOICES), ("backend", BACKEND_CHOICES),
                              ("qos", QOS_CHOICES)):
            if values[name] not in choices:
                raise StartupError(f"parameter '{name}' is {values[name]!r}: must be "
                                   f"{PARAMS[name].hint}")
        return values

    def _load_segmenter(self) -> Any:
        # Imported here (after parameter checks) so a broken torch install is one FATAL line.
        try:
            from task_outcome_ros.checkpoint import CheckpointError
            from task_outcome_ros.inference import OutcomeSegmenter, resolve_model_path
        except ImportError as exc:
            raise StartupError(f"cannot import the inference stack: {exc}. Install the "
                               "package's requirements (torch, numpy, opencv).") from None
        model_path = self._params["model_path"] or None  # None: the segmenter's default
        try:
            self._model_desc = str(resolve_model_path(model_path))
        except CheckpointError as exc:
            raise StartupError(f"cannot use model '{model_path}': {exc}") from None
        try:
            seg = OutcomeSegmenter(model_path, device=self._params["device"],
                                   presence_min_pixels=self._params["presence_min_pixels"],
                                   fragment_max_pixels=self._params["fragment_max_pixels"],
                                   num_threads=self._params["threads"],
                                   backend=self._params["backend"],
                                   reuse_floor_fit=self._params["reuse_floor_fit"])
            seg.warmup()
        except (CheckpointError, ValueError, RuntimeError, OSError, ImportError) as exc:
            raise StartupError(
                f"cannot use model '{self._model_desc}' (device '{self._params['device']}', "
                f"backend '{self._params['backend']}'): {exc}. Fix model_path (a shipped "
                "model's name, a checkpoint written by `python -m training train`, or '' for "
                "the default), device or backend.") from None
        self._model_desc += f" [{seg.backend}: {getattr(seg, 'backend_reason', '')}]"
        return seg

    # outcome/check (executor thread) ---------------------------------------------------------
    async def _on_check(self, request: Trigger.Request, response: Trigger.Response
                        ) -> Trigger.Response:
        """Wait for the first frame stamped after now. A coroutine: while it waits the
        executor goes on receiving frames and other calls, resuming it on each spin (the
        main loop paces those spins while checks wait, see ``main``)."""
        timeout_s = float(self._params["check_timeout_s"])
        token = self._checks.ask(self.get_clock().now().nanoseconds)
        deadline = time.monotonic() + timeout_s
        while (answer := self._checks.poll(token, time.monotonic() >= deadline,
                                           timeout_s)) is None:
            await _next_spin()
        response.success, response.message = answer.success, answer.message
        return response

    def checks_waiting(self) -> bool:
        return self._checks.pending() > 0

    def _answer_checks(self, header: Header, frame: FrameOutputs) -> None:
        """Worker thread: a processed frame answers the requests that arrived before it."""
        if not self._checks.pending():
            return
        result = frame.result
        answer = frame_answer((header.stamp.sec, header.stamp.nanosec), header.frame_id,
                              frame.fields, result.outside_envelope if result else None,
                              bool(result and result.envelope_checked))
        self._checks.on_frame(stamp_to_ns(header.stamp), answer)

    def _on_set_parameters(self, params: list) -> SetParametersResult:
        for p in params:
            if p.name == "overlay_alpha" and not 0.0 <= float(p.value) <= 1.0:
                return SetParametersResult(successful=False, reason="overlay_alpha in [0, 1]")
        for p in params:
            if p.name in ("publish_overlay", "overlay_alpha", "publish_markers",
                          "check_timeout_s"):
                self._params[p.name] = p.value
        return SetParametersResult(successful=True)

    # callbacks (executor thread): store and return ----------------------------------------
    def _on_image(self, msg: Image) -> None:
        self._transport.on_image()
        with self._lock:
            if self._pending is not None:
                self._dropped += 1
            self._pending = (msg, time.monotonic())
            self._lock.notify()

    def _on_camera_info(self, msg: CameraInfo) -> None:
        warning = self._transport.on_camera_info()
        if warning:
            self.get_logger().warning(warning)
        with self._lock:
            self._camera_info = msg

    # worker thread ---------------------------------------------------------------------------
    def _work(self) -> None:
        while True:
            with self._lock:
                while self._pending is None and not self._stop:
                    self._lock.wait(timeout=0.5)
                if self._stop:
                    return
                (msg, t_received), self._pending = self._pending, None
                camera_info, dropped = self._camera_info, self._dropped
            try:
                self._process(msg, t_received, camera_info, dropped)
            except Exception as exc:  # never let one frame kill the worker
                if self._stop or not self.context.ok():
                    return  # shutting down: publishers may already be gone
                self.get_logger().error(f"unexpected error on a frame: {exc!r}",
                                        throttle_duration_sec=WARN_THROTTLE_S)
                try:
                    why = f"internal error: {exc}"
                    fields = R.error_fields(why, dropped=dropped,
                                            latency_ms=since_ms(t_received))
                    self._publish_status(msg.header, fields)
                    self._answer_checks(msg.header, FrameOutputs(msg.header, fields, error=why))
                except Exception:  # already logged; keep the worker alive
                    pass

    def _process(self, msg: Image, t_received: float, camera_info: CameraInfo | None,
                 dropped: int) -> None:
        # No work nobody asked for: the overlay and the markers only while someone listens.
        overlay_alpha = (float(self._params["overlay_alpha"])
                         if self._params["publish_overlay"]
                         and self._pub_overlay.get_subscription_count() > 0 else None)
        frame = process_frame(self._segmenter, msg, camera_info, overlay_alpha=overlay_alpha,
                              t_start=t_received, dropped=dropped)
        log = self.get_logger()
        for note in frame.notes:
            if note == NO_CAMERA_INFO_NOTE:
                log.warning(f"{note} (README: camera_info)", once=True)
            else:
                log.warning(note, throttle_duration_sec=WARN_THROTTLE_S)
        if frame.error is not None:
            log.warning(f"skipping depth frame (frame_id '{msg.header.frame_id}'): "
                        f"{frame.error}", throttle_duration_sec=WARN_THROTTLE_S)
            self._publish_status(msg.header, frame.fields)
            self._answer_checks(msg.header, frame)
            return
        if frame.result.outside_envelope:
            log.warning(
                "frame outside what the model was trained for ("
                f"{'; '.join(frame.result.outside_envelope)}): its answer cannot be trusted. "
                "Use the shipped model for this kind of cell (model_path:=NAME) or train one "
                "for it (README: Retraining)", throttle_duration_sec=ENVELOPE_THROTTLE_S)
        # Labels and status first: they are what a manipulation stack waits for.
        self._pub_labels.publish(_image_msg(msg.header, frame.labels, "mono8"))
        self._publish_status(msg.header, frame.fields)
        self._answer_checks(msg.header, frame)
        if frame.overlay is not None:
            self._pub_overlay.publish(_image_msg(msg.header, frame.overlay, "rgb8"))
        if self._params["publish_markers"] and self._pub_markers.get_subscription_count() > 0:
            table = self._segmenter.table
            centroids = R.object_centroids(frame.result, frame.intrinsics, table)
            self._pub_markers.publish(_markers(msg.header, centroids, table))

    # publishing ------------------------------------------------------------------------------
    def _publish_status(self, header: Header, fields: R.StatusFields) -> None:
        self._pub_status.publish(status_array(header, fields))

    def release_checks(self) -> None:
        """Answer waiting outcome/check requests now, so the executor can shut down."""
        self._checks.release_all("outcome_node is shutting down")

    def destroy_node(self) -> None:
        self.release_checks()
        with self._lock:
            self._stop = True
            self._lock.notify_all()
        if self._worker.is_alive():
            self._worker.join(timeout=5.0)
        super().destroy_node()


def status_array(header: Header, fields: R.StatusFields) -> DiagnosticArray:
    """outcome_report.StatusFields -> the DiagnosticArray of outcome/status."""
    status = DiagnosticStatus(level=bytes([fields.level]), name=STATUS_NAME,
                              message=fields.message, hardware_id=header.frame_id,
                              values=[KeyValue(key=k, value=v) for k, v in fields.values])
    return DiagnosticArray(header=header, status=[status])


class _NextSpin:
    """Awaitable that gives control back to the executor until its next spin."""

    def __await__(self):
        yield


def _next_spin() -> _NextSpin:
    return _NextSpin()


def _image_msg(header: Header, pixels: np.ndarray, encoding: str) -> Image:
    """uint8 H x W (mono8) or H x W x 3 (rgb8) array -> Image with the given header."""
    height, width = pixels.shape[:2]
    channels = 1 if pixels.ndim == 2 else pixels.shape[2]
    # array('B') is the fast path of the generated uint8[] setter (no per-element checks).
    data = array.array("B", np.ascontiguousarray(pixels, dtype=np.uint8).tobytes())
    return Image(header=header, height=height, width=width, encoding=encoding,
                 is_bigendian=0, step=width * channels, data=data)


def _markers(header: Header, centroids: list[R.Centroid], table: L.LabelTable) -> MarkerArray:
    """DELETEALL (clears the previous frame's spheres) then one sphere per 3-D centroid, in
    its outcome's colour of ``table`` (the overlay's)."""
    markers = [Marker(header=header, action=Marker.DELETEALL)]
    for name, k, (x, y, z) in centroids:
        r, g, b = table.colours[table.outcome_ids[name]]
        m = Marker(header=header, ns=name, id=k, type=Marker.SPHERE, action=Marker.ADD,
                   color=ColorRGBA(r=r / 255.0, g=g / 255.0, b=b / 255.0, a=0.8))
        m.pose.position.x, m.pose.position.y, m.pose.position.z = x, y, z
        m.pose.orientation.w = 1.0
        m.scale.x = m.scale.y = m.scale.z = MARKER_DIAMETER_M
        markers.append(m)
    return MarkerArray(markers=markers)


def _outcomes_desc(table: L.LabelTable) -> str:
    """E.g. 'outcomes success, fell_outside (failure), stuck_on_rim (failure)'."""
    return "outcomes " + ", ".join(
        f"{name} (failure)" if name in table.failures else name for name in table.outcome_names)


def _exc_reason(exc: Exception) -> str:
    text = str(exc).strip().splitlines()
    return text[-1] if text else type(exc).__name__


def _interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


def interrupt_on_signals() -> None:
    """SIGINT and SIGTERM raise KeyboardInterrupt (also when started with SIGINT ignored).

    For processes that init rclpy with SignalHandlerOptions.NO: rclpy's own handler shuts the
    context down at once, under a publish in progress (seen: a segfault at exit).
    """
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, _interrupt)


def main(args: list[str] | None = None) -> int:
    """Console script ``outcome_node``; returns the process exit code."""
    try:
        # Our own SIGINT/SIGTERM handling: rclpy's handler shuts the context down at once,
        # while the worker thread may be publishing (seen: a segfault at exit). Raising
        # KeyboardInterrupt instead lets main stop the worker first, then shut down.
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
        interrupt_on_signals()
    except Exception as exc:  # malformed --ros-args: rcl's message says which
        print(f"[FATAL] [{NODE_NAME}]: cannot start: {_exc_reason(exc)}", file=sys.stderr)
        return 2
    node = executor = None
    try:
        # One try from here on: a signal at any moment (even while the model loads or right
        # after "ready") must still end in a clean shutdown, never an uncaught interrupt.
        node = OutcomeNode()
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        # Short waits: without rclpy's signal handler nothing else wakes a blocked wait set,
        # and Python runs our SIGINT handler only between waits.
        while rclpy.ok():
            executor.spin_once(timeout_sec=0.1)
            if node.checks_waiting():
                time.sleep(CHECK_SPIN_PAUSE_S)
    except StartupError as exc:
        rclpy.logging.get_logger(NODE_NAME).fatal(f"cannot start: {exc}")
        return 1
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.release_checks()
            if executor is not None:  # let the released requests send their replies
                for _ in range(20):
                    executor.spin_once(timeout_sec=0.0)
        if executor is not None:
            executor.shutdown()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
