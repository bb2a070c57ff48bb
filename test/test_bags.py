"""Bags end to end: ``training export-bag`` -> ``outcome_bag`` (offline, rosbags only) and
``outcome_replay`` -> the real outcome_node over DDS.

One tiny generated dataset run and the depth-band checkpoint (model_helpers) serve the
module. Exports cover both storages and both encodings; outcome_bag runs once through its
console script and once with rclpy blocked (the offline path must not need ROS); the replay
test checks that the node answers every replayed frame and that its answers equal
outcome_bag's for the same frames.
"""

from __future__ import annotations

import json
import random
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags", reason="rosbags is not installed")
pytest.importorskip("torch", reason="torch is not installed")
pytest.importorskip("rclpy", reason="ROS 2 rclpy is not installed (node_helpers and replay)")

import node_helpers as nh  # noqa: E402
from model_helpers import SHELF_TABLE  # noqa: E402

from task_outcome_ros import bag_io, ground_truth  # noqa: E402
from task_outcome_ros import bag_tools as B  # noqa: E402
from task_outcome_ros import labels as L  # noqa: E402
from task_outcome_ros import outcome_report as R  # noqa: E402
from task_outcome_ros.depth import decode_depth  # noqa: E402

pytestmark = pytest.mark.ros

N_FRAMES = 6
RATE_HZ = 5.0
FRAME_ID = "camera_depth_optical_frame"
EXPORTS = {"mcap_32FC1": ("mcap", "32FC1", ""), "sqlite3_16UC1": ("sqlite3", "16UC1", "/cam1")}
TIMING_KEYS = ("inference_ms", "latency_ms", "dropped_frames")


def _run(cmd: list[str], timeout: float = 120, **kw) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout,
                          env=kw.pop("env", nh.ros_env()), **kw)


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    """A 12-episode dataset run, its bags (CLI) and the depth-band checkpoint."""
    tmp = tmp_path_factory.mktemp("bags")
    result = _run([sys.executable, "-m", "training", "dataset", "--episodes", "12",
                   "--chunk-size", "6", "--out", str(tmp / "run")], cwd=tmp)
    assert result.returncode == 0, result.stderr
    for name, (storage, encoding, namespace) in EXPORTS.items():
        result = _run([sys.executable, "-m", "training", "export-bag", "--out",
                       str(tmp / "run"), "--bag", str(tmp / name), "--split", "all",
                       "--limit", str(N_FRAMES), "--rate", str(RATE_HZ), "--encoding", encoding,
                       "--storage", storage, "--namespace", namespace, "--with-labels"])
        assert result.returncode == 0, result.stderr
        assert f"{N_FRAMES} frames" in result.stdout, result.stdout
    nh.make_depth_band_checkpoint(tmp / "depth_band.pt")
    return tmp


def read_bag(path: Path) -> dict[str, list[tuple[int, object]]]:
    """topic -> [(log time, deserialized message)] in log-time order."""
    out: dict[str, list[tuple[int, object]]] = {}
    reader = bag_io.open_reader(path)
    try:
        for conn, log_time, raw in reader.messages():
            msg = bag_io.deserialize(raw, conn.msgtype)
            out.setdefault(conn.topic, []).append((log_time, msg))
    finally:
        reader.close()
    return out


def key(header) -> tuple[int, int, str]:
    return int(header.stamp.sec), int(header.stamp.nanosec), header.frame_id


def mono8(msg) -> np.ndarray:
    assert msg.encoding == "mono8"
    return np.asarray(msg.data, np.uint8).reshape(msg.height, msg.step)[:, :msg.width]


def check_status(status_array, labels: np.ndarray,
                 table: L.LabelTable = L.DEFAULT_TABLE) -> dict[str, str]:
    """One task_outcome status whose level, message and values agree with ``labels`` in the
    classes of ``table`` (the model's), which the status carries too."""
    (status,) = status_array.status
    assert status.name == R.STATUS_NAME and status.hardware_id == status_array.header.frame_id
    values = {kv.key: kv.value for kv in status.values}
    assert values["label_table"] == R.label_table_value(table)
    h, w = labels.shape
    threshold = L.presence_threshold(h, w)
    present = {}
    for name, class_id in table.outcome_ids.items():
        count = int(np.count_nonzero(labels == class_id))
        assert int(values[f"{name}.pixels"]) == count
        present[name] = values[f"{name}.present"] == "true"
        assert present[name] == (count >= threshold)
    names = sorted(n for n, p in present.items() if p)
    assert status.message == (",".join(names) or "none")
    failure = any(present[n] for n in table.failures)
    assert status.level == (R.WARN if failure else R.OK)
    assert float(values["inference_ms"]) >= 0 and int(values["dropped_frames"]) == 0
    return values


# --- export-bag ----------------------------------------------------------------------------------

@pytest.mark.parametrize("name", EXPORTS)
def test_export_bag_topics_stamps_camera_info_and_ground_truth(work, name):
    from training.dataset import load_manifest
    from training.export_bag import EPOCH_NS
    from training.render import read_pair, reported_camera

    storage, encoding, namespace = EXPORTS[name]
    bag = work / name
    meta = (bag / "metadata.yaml").read_text()
    assert f"storage_identifier: {storage}" in meta
    assert bag_io.bag_storage(bag) == storage
    topics = read_bag(bag)
    assert sorted(topics) == [f"{namespace}/depth/camera_info", f"{namespace}/depth/image_raw"]
    images = topics[f"{namespace}/depth/image_raw"]
    infos = topics[f"{namespace}/depth/camera_info"]
    assert len(images) == len(infos) == N_FRAMES
    run = load_manifest(work / "run")
    manifest = run["images"][:N_FRAMES]
    run_table = L.LabelTable.from_dict(run["label_table"])  # what the run discovered
    truth = json.loads((bag / ground_truth.GROUND_TRUTH_FILE).read_text())
    assert truth["n_frames"] == N_FRAMES and truth["encoding"] == encoding
    for i, ((t_img, img), (t_info, info), im, gt) in enumerate(
            zip(images, infos, manifest, truth["frames"])):
        stamp = EPOCH_NS + int(round(i * 1e9 / RATE_HZ))
        assert t_img == t_info == stamp == bag_io.stamp_to_ns(img.header.stamp) == gt["stamp_ns"]
        assert key(img.header) == key(info.header) and img.header.frame_id == FRAME_ID
        assert img.encoding == encoding and not img.is_bigendian
        depth, labels = read_pair(work / "run", im["episode"])
        got = decode_depth(img.encoding, img.height, img.width, img.step, False, img.data)
        np.testing.assert_allclose(got, depth, rtol=0, atol=1e-6)  # NaN where NaN
        cam = reported_camera(im)   # what the camera driver says, calibration error included
        assert (info.width, info.height) == (img.width, img.height) == (cam["width"],
                                                                         cam["height"])
        np.testing.assert_allclose(info.k, [cam["fx"], 0, cam["cx"], 0, cam["fy"], cam["cy"],
                                            0, 0, 1])
        np.testing.assert_allclose(info.p, [cam["fx"], 0, cam["cx"], 0, 0, cam["fy"],
                                            cam["cy"], 0, 0, 0, 1, 0])
        assert info.distortion_model == "plumb_bob" and not np.any(info.d)
        assert gt["episode"] == im["episode"] and gt["present"] == im["present"]
        assert gt["pixel_counts"] == L.outcome_pixel_counts(labels, run_table)
        assert (bag / gt["labels_png"]).is_file()


def test_export_bag_is_deterministic_and_refuses_to_overwrite(work, tmp_path):
    from training.export_bag import export_bag

    a = export_bag(work / "run", tmp_path / "a", split="val", progress=False)
    b = export_bag(work / "run", tmp_path / "b", split="val", progress=False)
    assert a["frames"] == b["frames"]

    def raw(path):
        reader = bag_io.open_reader(path)
        try:
            return [(c.topic, t, bytes(d)) for c, t, d in reader.messages()]
        finally:
            reader.close()
    assert raw(tmp_path / "a") == raw(tmp_path / "b")
    with pytest.raises(ValueError, match="exists"):
        export_bag(work / "run", tmp_path / "a", split="val", progress=False)
    export_bag(work / "run", tmp_path / "a", split="val", overwrite=True, progress=False)


# --- outcome_bag ---------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def processed(work) -> dict[str, tuple[Path, subprocess.CompletedProcess]]:
    """Both bags through outcome_bag: the console script, and -c with rclpy blocked."""
    out = {}
    ckpt = str(work / "depth_band.pt")
    mcap = work / "mcap_32FC1_outcome"
    out["mcap_32FC1"] = mcap, _run(nh.script_command("outcome_bag", "task_outcome_ros.bag_tools")
                                   + [str(work / "mcap_32FC1"), "--model", ckpt, "--out",
                                      str(mcap), "--no-progress"])
    sqlite = work / "sqlite3_16UC1_outcome"
    code = ("import sys; sys.modules['rclpy'] = None\n"
            "from task_outcome_ros.bag_tools import offline_main\n"
            "sys.exit(offline_main(sys.argv[1:]))")
    out["sqlite3_16UC1"] = sqlite, _run(
        [sys.executable, "-c", code, str(work / "sqlite3_16UC1"), "--model", ckpt, "--out",
         str(sqlite), "--namespace", "/cam1", "--no-progress"])
    for _, result in out.values():
        assert result.returncode == 0, result.stderr
    return out


@pytest.mark.parametrize("name", EXPORTS)
def test_outcome_bag_outputs_match_the_input_frames(work, processed, name):
    _, encoding, namespace = EXPORTS[name]
    out_bag, result = processed[name]
    assert f"outcome_bag: {N_FRAMES} frames, 0 errors" in result.stdout, result.stdout
    assert "image all-correct" in result.stdout
    topics = read_bag(out_bag)
    inputs = read_bag(work / name)
    assert sorted(topics) == sorted([*inputs, f"{namespace}/outcome/labels",
                                     f"{namespace}/outcome/overlay",
                                     f"{namespace}/outcome/status"])
    for topic, msgs in inputs.items():  # copied unchanged
        assert [(t, key(m.header)) for t, m in topics[topic]] == \
            [(t, key(m.header)) for t, m in msgs]
    depth_msgs = inputs[f"{namespace}/depth/image_raw"]
    outputs = [topics[f"{namespace}/outcome/{n}"] for n in ("labels", "status", "overlay")]
    assert all(len(o) == N_FRAMES for o in outputs)
    for (t_in, depth), (t_l, lab), (t_s, status), (t_o, overlay) in zip(depth_msgs, *outputs):
        assert t_in == t_l == t_s == t_o  # message log time = input log time
        assert key(depth.header) == key(lab.header) == key(status.header) == key(overlay.header)
        assert (lab.encoding, lab.height, lab.width, lab.step) == \
            ("mono8", depth.height, depth.width, depth.width)
        assert (overlay.encoding, overlay.height, overlay.width, overlay.step) == \
            ("rgb8", depth.height, depth.width, 3 * depth.width)
        labels = mono8(lab)
        assert set(np.unique(labels)) <= set(range(L.DEFAULT_TABLE.num_classes))
        check_status(status, labels)

    summary = json.loads((out_bag / B.SUMMARY_FILE).read_text())
    assert summary["frames"] == N_FRAMES and summary["errors"] == 0
    score = json.loads((out_bag / B.SCORE_FILE).read_text())
    assert score["n_missing"] == score["n_errors"] == 0
    # The score, recomputed from the status messages and the ground truth's pixel counts.
    truth = ground_truth.load_ground_truth(work / name)
    right = []
    for frame, (_, status) in zip(truth["frames"], outputs[1]):
        values = {kv.key: kv.value for kv in status.status[0].values}
        threshold = L.presence_threshold(frame["height"], frame["width"])
        # Scored on every outcome the model knows: one the small run did not find is absent
        # in its truth.
        right.append(all((values[f"{n}.present"] == "true")
                         == (frame["pixel_counts"].get(n, 0) >= threshold)
                         for n in L.DEFAULT_TABLE.outcome_names))
    assert score["n_images"] == N_FRAMES
    assert score["image_all_correct"] == pytest.approx(sum(right) / N_FRAMES)
    assert len(score["mistakes"]) == right.count(False)
    assert set(ground_truth.truth_outcomes(truth)) <= set(L.DEFAULT_TABLE.outcome_names)
    assert set(score["presence_recall"]) == set(L.DEFAULT_TABLE.outcome_names)


def test_outcome_bag_no_overlay_no_copy_and_bad_frames(work, tmp_path):
    """Undecodable frames get an ERROR status with their header (no labels) and the run goes
    on; --no-overlay / --no-copy-input write only labels and status."""
    writer = bag_io.open_writer(tmp_path / "in", "sqlite3")
    conn = writer.add_connection("/depth/image_raw", bag_io.IMAGE, typestore=bag_io.typestore())
    cases = [("32FC1", np.full((48, 64), 2.0, "<f4").tobytes(), 64 * 4),
             ("rgb8", bytes(64 * 48 * 3), 64 * 3),
             ("16UC1", bytes(10), 64 * 2)]
    for i, (encoding, data, step) in enumerate(cases):
        header = bag_io.make_header(1_000_000_000 * (i + 1), "cam")
        msg = bag_io.msg_class(bag_io.IMAGE)(header=header, height=48, width=64,
                                             encoding=encoding, is_bigendian=0, step=step,
                                             data=np.frombuffer(data, np.uint8))
        writer.write(conn, 1_000_000_000 * (i + 1), bag_io.serialize(msg, bag_io.IMAGE))
    writer.close()
    band = str(work / "depth_band.pt")
    summary = B.process_bag(tmp_path / "in", tmp_path / "out", model=band,
                            overlay=False, copy_input=False, progress=False)
    assert summary["frames"] == 3 and summary["errors"] == 2 and summary["levels"]["ERROR"] == 2
    topics = read_bag(tmp_path / "out")
    assert sorted(topics) == ["/outcome/labels", "/outcome/status"]
    assert [bag_io.stamp_to_ns(m.header.stamp) for _, m in topics["/outcome/labels"]] == [10**9]
    statuses = [m for _, m in topics["/outcome/status"]]
    assert [s.status[0].level for s in statuses[1:]] == [R.ERROR, R.ERROR]
    assert all(s.status[0].message.startswith("bad depth image") for s in statuses[1:])
    assert [key(s.header) for s in statuses] == [(1, 0, "cam"), (2, 0, "cam"), (3, 0, "cam")]
    assert not (tmp_path / "out" / B.SCORE_FILE).exists()  # no ground truth beside the input


def test_outcome_bag_errors_name_what_to_fix(work, tmp_path):
    cmd = nh.script_command("outcome_bag", "task_outcome_ros.bag_tools")
    result = _run(cmd + [str(work / "mcap_32FC1"), "--out", str(tmp_path / "o"),
                         "--topic", "camera/depth"])
    assert result.returncode == 2 and "/camera/depth" in result.stderr
    assert "/depth/image_raw" in result.stderr and "Traceback" not in result.stderr
    result = _run(cmd + [str(tmp_path / "nope")])
    assert result.returncode == 2 and "no bag at" in result.stderr
    result = _run(cmd + [str(work / "mcap_32FC1"), "--fragment-max-pixels", "-1"])
    assert result.returncode == 2 and "--fragment-max-pixels" in result.stderr


def test_scoring_counts_missing_and_error_frames_as_wrong():
    gt = {"frames": [{"stamp_ns": s, "width": 640, "height": 480,
                      "pixel_counts": {"success": c, "fell_outside": 0, "stuck_on_rim": 0}}
                     for s, c in ((1, 500), (2, 0), (3, 500), (4, 0))]}
    yes = {"success": True, "fell_outside": False, "stuck_on_rim": False}
    no = dict.fromkeys(L.DEFAULT_TABLE.outcome_names, False)
    report = ground_truth.score(gt, {1: yes, 2: yes, 3: None})
    assert report["n_images"] == 4 and report["image_all_correct"] == 0.25
    assert (report["n_errors"], report["n_missing"]) == (1, 1)
    assert report["presence_precision"]["success"] == 0.5
    assert report["presence_recall"]["success"] == 0.5
    assert ground_truth.score(gt, {1: yes, 2: no, 3: yes, 4: no})["image_all_correct"] == 1.0
    # the truth follows the presence threshold asked for
    assert ground_truth.score(gt, {1: no, 2: no, 3: no, 4: no}, presence_min_pixels=600)[
        "image_all_correct"] == 1.0


def _flat_depth_bag(path: Path, n: int = 2) -> list[int]:
    """A bag of ``n`` flat 64 x 48 depth frames (2 m) on /depth/image_raw; their stamps."""
    writer = bag_io.open_writer(path, "mcap")
    conn = writer.add_connection("/depth/image_raw", bag_io.IMAGE, typestore=bag_io.typestore())
    stamps = [1_000_000_000 * (i + 1) for i in range(n)]
    for stamp in stamps:
        msg = bag_io.depth_image_message(bag_io.make_header(stamp, "cam"),
                                         np.full((48, 64), 2.0, np.float32), "32FC1")
        writer.write(conn, stamp, bag_io.serialize(msg, bag_io.IMAGE))
    writer.close()
    return stamps


def _write_truth(bag: Path, stamps: list[int], pixel_counts: dict[str, int]) -> None:
    frames = [{"stamp_ns": s, "width": 64, "height": 48, "pixel_counts": pixel_counts}
              for s in stamps]
    (bag / ground_truth.GROUND_TRUTH_FILE).write_text(json.dumps({"frames": frames}))


def test_outcome_bag_with_a_model_of_another_task(tmp_path):
    """A shelf model (fell_off everywhere): the statuses, the summary and the score are in its
    outcomes; a bag whose ground truth is the default task's is refused before any frame."""
    fell_off = SHELF_TABLE.outcome_ids["fell_off"]
    shelf = str(nh.make_checkpoint(tmp_path / "shelf.pt", favour=fell_off, table=SHELF_TABLE))
    stamps = _flat_depth_bag(tmp_path / "in")
    summary = B.process_bag(tmp_path / "in", tmp_path / "out", model=shelf, progress=False)
    assert summary["present_counts"] == {"on_shelf": 0, "fell_off": 2,
                                         "hanging_over_edge": 0, "tipped": 0}
    assert summary["levels"] == {"OK": 0, "WARN": 2, "ERROR": 0}
    topics = read_bag(tmp_path / "out")
    for (_, labels), (_, status) in zip(topics["/outcome/labels"], topics["/outcome/status"]):
        assert (mono8(labels) == fell_off).all()
        check_status(status, mono8(labels), SHELF_TABLE)
        assert status.status[0].message == "fell_off"

    _write_truth(tmp_path / "in", stamps, {"success": 0, "fell_outside": 3072,
                                           "stuck_on_rim": 0})
    with pytest.raises(B.BagToolError, match="a model of another task"):
        B.process_bag(tmp_path / "in", tmp_path / "out_default_truth", model=shelf,
                      progress=False)
    assert not (tmp_path / "out_default_truth").exists()

    _write_truth(tmp_path / "in", stamps, {"on_shelf": 0, "fell_off": 3072,
                                           "hanging_over_edge": 0, "tipped": 0})
    summary = B.process_bag(tmp_path / "in", tmp_path / "out_scored", model=shelf,
                            progress=False)
    assert summary["score"]["image_all_correct"] == 1.0
    assert list(summary["score"]["presence_recall"]) == list(SHELF_TABLE.outcome_names)


def test_scoring_uses_the_ground_truths_outcomes_and_names_a_mismatch():
    gt = {"frames": [{"stamp_ns": 1, "width": 640, "height": 480,
                      "pixel_counts": {"on_shelf": 0, "fell_off": 0,
                                       "hanging_over_edge": 500, "tipped": 0}}]}
    assert ground_truth.truth_outcomes(gt) == SHELF_TABLE.outcome_names
    # A table in the file wins over the pixel counts' keys.
    assert ground_truth.truth_outcomes({**gt, "label_table": L.DEFAULT_TABLE.to_dict()}) \
        == L.DEFAULT_TABLE.outcome_names
    answer = {**dict.fromkeys(SHELF_TABLE.outcome_names, False), "hanging_over_edge": True}
    report = ground_truth.score(gt, {1: answer})
    assert report["image_all_correct"] == 1.0
    assert report["presence_recall"]["hanging_over_edge"] == 1.0
    with pytest.raises(B.BagToolError, match="different outcomes"):
        ground_truth.score(gt, {1: dict.fromkeys(L.DEFAULT_TABLE.outcome_names, False)})
    # A model knowing an outcome the truth's small run never found: absent in the truth, so
    # reporting it is a mistake (a false positive), not ignored.
    two = {"label_table": L.LabelTable.build("shelf", [("on_shelf", False),
                                                       ("fell_off", True)]).to_dict(),
           "frames": [{**gt["frames"][0], "pixel_counts": {"on_shelf": 900, "fell_off": 0}}]}
    said = {**dict.fromkeys(SHELF_TABLE.outcome_names, False), "on_shelf": True}
    assert ground_truth.score(two, {1: said})["image_all_correct"] == 1.0
    wrong = ground_truth.score(two, {1: {**said, "tipped": True}})
    assert wrong["image_all_correct"] == 0.0 and wrong["tipped"]["false_positives"] == 1


def test_live_status_outcomes_come_from_the_status():
    """live_bag reads which outcomes a node's status is about from the status itself, and an
    ERROR status (level bytes, as rclpy gives it) is no answer."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

    from task_outcome_ros.live_bag import status_present

    present = {**dict.fromkeys(SHELF_TABLE.outcome_names, False), "tipped": True}
    values = [KeyValue(key="label_table", value=R.label_table_value(SHELF_TABLE))] + [
        KeyValue(key=f"{n}.present", value=str(p).lower()) for n, p in present.items()]
    ok = DiagnosticArray(status=[DiagnosticStatus(level=bytes([R.WARN]), values=values)])
    assert status_present(ok) == present
    error = DiagnosticArray(status=[DiagnosticStatus(level=bytes([R.ERROR]), message="x")])
    assert status_present(error) is None


# --- outcome_replay -> outcome_node ----------------------------------------------------------

def test_replay_to_the_real_node_answers_every_frame_like_outcome_bag(work, processed, tmp_path):
    domain = random.randint(1, 200)
    proc = nh.NodeProcess(["-p", f"model_path:={work / 'depth_band.pt'}", "-p",
                           "qos:=reliable"],
                          domain, tmp_path / "node.log")
    client = nh.OutcomeClient(domain)
    replay = None
    try:
        client.wait_for_node(proc)
        replay = subprocess.Popen(
            nh.script_command("outcome_replay", "task_outcome_ros.replay")
            + [str(work / "mcap_32FC1"), "--qos", "reliable", "--rate-factor", "1"],
            env=nh.ros_env(domain), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        expected = {key(m.header) for _, m in read_bag(work / "mcap_32FC1")["/depth/image_raw"]}

        def answered() -> set:
            return {k for k, r in client.replies.items()
                    if r.labels is not None and r.status is not None and r.overlay is not None}
        client.spin_until(lambda: replay.poll() is not None and expected <= answered(), 60)
        output = replay.communicate(timeout=10)[0]
        assert replay.returncode == 0, output
        assert f"published {N_FRAMES} images and {N_FRAMES} camera_info" in output, output
        assert expected <= answered(), (sorted(answered()), proc.log())
        # Real time: the node's answers to 6 frames played at 5 Hz spread over about 1 s
        # (0.7 s allows for a late first answer); a replay ignoring the rate sends them at once.
        arrived = sorted(client.replies[k].status_arrived for k in expected)
        assert arrived[-1] - arrived[0] >= 0.7 * (N_FRAMES - 1) / RATE_HZ, arrived
    finally:
        if replay is not None and replay.poll() is None:
            replay.kill()
            replay.wait()
        client.close()
        proc.stop()

    # The node's answers are outcome_bag's: same labels, overlay and status (timing aside).
    offline = read_bag(processed["mcap_32FC1"][0])
    by_key = {name: {key(m.header): m for _, m in offline[f"/outcome/{name}"]}
              for name in ("labels", "status", "overlay")}
    for k in expected:
        reply = client.replies[k]
        assert np.array_equal(np.frombuffer(bytes(reply.labels.data), np.uint8),
                              np.asarray(by_key["labels"][k].data))
        assert np.array_equal(np.frombuffer(bytes(reply.overlay.data), np.uint8),
                              np.asarray(by_key["overlay"][k].data))
        live = nh.status_values(reply.status)
        (status,) = by_key["status"][k].status
        bag_values = {kv.key: kv.value for kv in status.values}
        for name in (live.keys() | bag_values.keys()) - set(TIMING_KEYS):
            if name.endswith("centroid_m") and name not in live:
                continue  # the node may see an image before its camera_info
            assert live[name] == bag_values[name], name
        assert (reply.status.status[0].message, reply.status.status[0].level) == \
            (status.message, bytes([status.level]))
