"""The one inference path: OutcomeSegmenter, presence, objects, and the ONNX backend."""

from __future__ import annotations

import importlib.util
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from task_outcome_ros import checkpoint, inference
from task_outcome_ros.camera import Intrinsics
from task_outcome_ros.checkpoint import CheckpointError
from task_outcome_ros.depth import sanitize_depth
from task_outcome_ros.inference import (
    OutcomeSegmenter,
    class_ids,
    count_objects,
    default_model_path,
    predict_labels,
)
from task_outcome_ros.labels import BACKGROUND, DEFAULT_TABLE, LabelTable, outcomes_present
from task_outcome_ros.model import (
    DEFAULT_NORMALISATION,
    IN_CHANNELS,
    INTRINSICS_FROM_CAMERA_INFO,
    OutcomeFCN,
    check_normalisation,
    preprocess,
)

pytestmark = pytest.mark.unit

ARGS = {"in_channels": IN_CHANNELS, "num_classes": 5, "base_width": 4, "levels": 3,
        "decoder_convs": 1}
INPUT_SIZE = (160, 120)
# The default task's outcome ids, for hand-made label images.
SUCCESS_ID, FELL_ID, STUCK_ID = (DEFAULT_TABLE.outcome_ids[name] for name in
                                 ("success", "fell_outside", "stuck_on_rim"))


def _make_checkpoint(path: Path, seed: int = 0, normalisation: dict = DEFAULT_NORMALISATION,
                     table: LabelTable = DEFAULT_TABLE, input_size: tuple[int, int] = INPUT_SIZE,
                     **model_args) -> Path:
    torch.manual_seed(seed)
    args = {**ARGS, "num_classes": table.num_classes, **model_args}
    model = OutcomeFCN(**args)
    # BN statistics from real inputs, so random-init labels vary over the image (a
    # backend comparison on a constant label image would prove nothing).
    batch = torch.from_numpy(np.stack([preprocess(_scene(120, 160, s), input_size)
                                       for s in range(4)]))
    model.train()
    with torch.no_grad():
        model.head.bias.zero_()
        for _ in range(20):
            model(batch)
    return checkpoint.save(path, model, model_args=args, input_size=input_size,
                           normalisation=normalisation, train_config={}, metrics={},
                           label_table=table)


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory) -> Path:
    return _make_checkpoint(tmp_path_factory.mktemp("ckpt") / "outcome_fcn.pt")


@pytest.fixture(scope="module")
def segmenter(ckpt: Path) -> OutcomeSegmenter:
    return OutcomeSegmenter(ckpt, backend="torch")


def _scene(h: int, w: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    depth = (2.0 + 0.05 * rng.standard_normal((h, w))).astype(np.float32)
    depth[h // 3: h // 2, w // 3: w // 2] = 1.7
    depth[rng.random((h, w)) < 0.05] = np.nan
    return depth


@pytest.mark.parametrize("h,w", [(480, 640), (479, 641), (33, 97), (1, 1), (120, 160)])
def test_output_keeps_input_size(segmenter: OutcomeSegmenter, h: int, w: int) -> None:
    depth = _scene(h, w)
    start = time.perf_counter()
    result = segmenter.segment(depth)
    call_ms = (time.perf_counter() - start) * 1000
    assert result.labels.shape == (h, w) and result.labels.dtype == np.uint8
    assert result.labels.max() < 5
    assert set(result.present) == set(DEFAULT_TABLE.outcome_names) == set(result.objects)
    # presence is decided on the labels returned (after fragments are absorbed), not before
    assert result.present == outcomes_present(result.labels, segmenter.presence_min_pixels)
    assert 0 < result.inference_ms <= call_ms  # milliseconds, and of this call


@pytest.mark.parametrize("fill", [np.nan, 0.0, np.inf, -1.0])
def test_all_invalid_depth_means_nothing_present(segmenter: OutcomeSegmenter, fill) -> None:
    result = segmenter.segment(np.full((480, 640), fill, np.float32))
    assert not result.labels.any()
    assert not any(result.present.values())
    assert all(n == 0 for n in result.pixel_counts.values())
    assert all(objs == [] for objs in result.objects.values())


def test_pixels_without_depth_are_background(segmenter: OutcomeSegmenter) -> None:
    """Whatever the network says there, a pixel without depth comes out background: here
    every working-size pixel is an outcome, and exactly the invalid ones must turn 0."""
    depth = _scene(480, 640, 5)  # 5 % of the pixels NaN
    depth[100:200, 300:400] = np.nan  # and a block without returns
    w, h = segmenter.input_size
    small = np.full((h, w), DEFAULT_TABLE.outcome_ids["success"], np.uint8)
    small[: h // 2] = DEFAULT_TABLE.outcome_ids["fell_outside"]
    for valid in (None, np.isfinite(depth)):
        labels = segmenter.postprocess(small, depth, valid).labels
        assert np.array_equal(labels == 0, np.isnan(depth))
    assert small.min() > 0  # the caller's working-size labels are left alone


@pytest.mark.parametrize("bad", [np.zeros((4, 4, 1), np.float32), np.zeros(16, np.float32),
                                 np.zeros((4, 4), bool), np.array([["a", "b"]]),
                                 np.zeros((0, 5), np.float32), np.float32(2.0)])
def test_bad_input_raises_value_error(segmenter: OutcomeSegmenter, bad) -> None:
    with pytest.raises(ValueError):
        segmenter.segment(bad)


def test_integer_millimetre_like_input_is_accepted(segmenter: OutcomeSegmenter) -> None:
    result = segmenter.segment(np.full((48, 64), 2, np.uint16))
    assert result.labels.shape == (48, 64)


def test_presence_threshold_is_on_full_size_labels(segmenter: OutcomeSegmenter,
                                                   monkeypatch) -> None:
    """2x2 working pixels -> 64 full-size px (present); 1x3 -> 48 px (absent, < 50)."""
    small = np.zeros((120, 160), np.uint8)
    small[10:12, 10:12] = SUCCESS_ID
    small[50, 50:53] = FELL_ID
    small[80:90, 100:110] = STUCK_ID
    monkeypatch.setattr(segmenter, "_predict_small", lambda x: small)
    depth = np.full((480, 640), 2.0, np.float32)
    depth[320:360, 400:440] = 1.5
    result = segmenter.segment(depth)
    assert result.pixel_counts == {"success": 64, "fell_outside": 48, "stuck_on_rim": 1600}
    assert result.present == {"success": True, "fell_outside": False, "stuck_on_rim": True}
    assert result.objects["fell_outside"] == []
    [stuck] = result.objects["stuck_on_rim"]
    assert stuck.pixel_count == 1600 and stuck.outcome == "stuck_on_rim"
    assert stuck.centroid_px == pytest.approx((419.5, 339.5))
    assert stuck.median_depth_m == pytest.approx(1.5)
    # Half the size: the threshold scales with the area (50 / 4 -> 12 px).
    half = segmenter.segment(np.full((240, 320), 2.0, np.float32))
    assert half.pixel_counts["fell_outside"] == 12 and half.present["fell_outside"]


def test_count_objects_on_hand_made_labels() -> None:
    labels = np.zeros((100, 120), np.uint8)
    labels[10:20, 10:20] = SUCCESS_ID          # 100 px
    labels[50:55, 50:55] = SUCCESS_ID          # 25 px, below 50
    labels[60:80, 90:100] = SUCCESS_ID         # 200 px
    labels[80:81, 100:101] = SUCCESS_ID        # diagonal neighbour: joins the 200 px object
    labels[0:30, 60:70] = FELL_ID
    depth = np.full((100, 120), 2.0, np.float32)
    depth[10:20, 10:20] = 1.25
    depth[60:81, 90:101] = np.nan
    objs = count_objects(labels, SUCCESS_ID, 50, depth)
    assert [o.pixel_count for o in objs] == [201, 100]
    assert all(o.outcome == "success" for o in objs)
    assert objs[0].median_depth_m is None  # no valid depth under it
    assert objs[1].median_depth_m == pytest.approx(1.25)
    assert objs[1].centroid_px == pytest.approx((14.5, 14.5))
    assert len(count_objects(labels, SUCCESS_ID, 1)) == 3
    assert count_objects(labels, STUCK_ID, 1) == []
    assert count_objects(labels, FELL_ID, 50)[0].median_depth_m is None  # no depth given
    with pytest.raises(ValueError):
        count_objects(labels, 9, 1)


def test_count_objects_matches_whole_frame_labelling() -> None:
    """count_objects labels only the class's bounding box; it must equal labelling it all."""
    rng = np.random.default_rng(3)
    labels = np.zeros((120, 160), np.uint8)
    for _ in range(6):
        y, x = rng.integers(30, 100), rng.integers(40, 140)
        labels[y:y + rng.integers(3, 15), x:x + rng.integers(3, 15)] = SUCCESS_ID
    depth = rng.uniform(1.5, 2.5, labels.shape).astype(np.float32)
    n, cc, stats, centroids = cv2.connectedComponentsWithStats(
        (labels == SUCCESS_ID).astype(np.uint8), connectivity=8)
    expected = sorted(((int(stats[k, cv2.CC_STAT_AREA]), tuple(centroids[k]),
                        float(np.median(depth[cc == k]))) for k in range(1, n)
                       if stats[k, cv2.CC_STAT_AREA] >= 10), key=lambda e: -e[0])
    found = count_objects(labels, SUCCESS_ID, 10, depth)
    assert len(found) == len(expected) > 1
    for obj, (area, centroid, median) in zip(found, expected):
        assert obj.pixel_count == area
        assert obj.centroid_px == pytest.approx(centroid)
        assert obj.median_depth_m == pytest.approx(median)


def test_predict_labels_shape_and_dtype(segmenter: OutcomeSegmenter) -> None:
    batch = torch.from_numpy(np.stack([preprocess(_scene(120, 160, s), INPUT_SIZE)
                                       for s in range(2)]))
    labels = predict_labels(segmenter.model, batch)
    assert labels.shape == (2, 120, 160) and labels.dtype == torch.uint8
    assert labels.is_inference()  # run without autograd bookkeeping, as the node runs it
    with pytest.raises(ValueError):
        predict_labels(segmenter.model, batch[0])


def test_warmup_and_constructor_checks(ckpt: Path) -> None:
    seg = OutcomeSegmenter(ckpt, backend="torch", presence_min_pixels=10)
    seg.warmup()
    for kwargs in ({"backend": "tensorrt"}, {"presence_min_pixels": 0},
                   {"device": "tpu"}):
        with pytest.raises(ValueError):
            OutcomeSegmenter(ckpt, **kwargs)
    with pytest.raises(CheckpointError, match="not found"):
        OutcomeSegmenter(ckpt.parent / "missing.pt")


def test_missing_default_model_names_path_and_command(tmp_path: Path, monkeypatch) -> None:
    assert default_model_path().parts[-3:] == ("task_outcome_ros", "models", "outcome_fcn.pt")
    missing = tmp_path / "models" / "outcome_fcn.pt"
    monkeypatch.setattr(inference, "default_model_path", lambda: missing)
    with pytest.raises(CheckpointError) as info:
        OutcomeSegmenter()
    assert str(missing) in str(info.value) and "python -m training train" in str(info.value)


def test_shipped_models_are_found_by_name(tmp_path: Path, monkeypatch) -> None:
    """model_path takes a shipped model's name (its file beside the default one) or a path."""
    models = tmp_path / "models"
    _make_checkpoint(models / "outcome_fcn.pt")
    _make_checkpoint(models / "outcome_fcn_tote.pt")
    monkeypatch.setattr(inference, "models_dir", lambda: models)
    monkeypatch.setattr(inference, "default_model_path", lambda: models / "outcome_fcn.pt")
    assert inference.shipped_models() == ["default", "tote"]
    assert inference.resolve_model_path("tote") == models / "outcome_fcn_tote.pt"
    assert inference.resolve_model_path("default") == models / "outcome_fcn.pt"
    assert inference.resolve_model_path("") == inference.resolve_model_path(None)
    own = tmp_path / "mine.pt"
    assert inference.resolve_model_path(str(own)) == own  # a path, even a missing one
    with pytest.raises(CheckpointError) as info:
        inference.resolve_model_path("shelf")
    assert "no shipped model named 'shelf'" in str(info.value)
    assert "default, tote" in str(info.value) and "--scene shelf --ship" in str(info.value)
    assert OutcomeSegmenter("tote").model_path == models / "outcome_fcn_tote.pt"


@pytest.fixture(scope="module")
def onnx_ckpt(tmp_path_factory) -> Path:
    pytest.importorskip("onnx")
    pytest.importorskip("onnxruntime")
    from task_outcome_ros.onnx_export import export_onnx

    path = _make_checkpoint(tmp_path_factory.mktemp("onnx") / "outcome_fcn.pt", seed=1)
    assert export_onnx(path) == path.with_suffix(".onnx")
    return path


def test_onnx_and_torch_backends_agree(onnx_ckpt: Path) -> None:
    seg_onnx = OutcomeSegmenter(onnx_ckpt, backend="auto")
    seg_torch = OutcomeSegmenter(onnx_ckpt, backend="torch")
    assert seg_onnx.backend == "onnx" and seg_torch.backend == "torch"
    agree, total = 0, 0
    for seed, (h, w) in enumerate([(480, 640), (479, 641), (120, 160)]):
        depth = _scene(h, w, seed)
        a, b = seg_onnx.segment(depth), seg_torch.segment(depth)
        agree += int((a.labels == b.labels).sum())
        total += a.labels.size
        assert len(np.unique(b.labels)) > 1  # a meaningful comparison, not all background
    assert agree / total >= 0.999


@pytest.mark.parametrize("full_size_head", [0, 8])
def test_a_space_to_depth_network_exports_and_agrees(tmp_path: Path,
                                                      full_size_head: int) -> None:
    """Pixel unshuffle, the bilinear logit upsampling and the full-size head survive the
    ONNX export: both backends label a frame alike at 320 x 240."""
    pytest.importorskip("onnxruntime")
    from task_outcome_ros.onnx_export import export_onnx

    path = _make_checkpoint(tmp_path / "outcome_fcn.pt", seed=3, input_size=(320, 240),
                            space_to_depth=2, full_size_head=full_size_head)
    export_onnx(path)
    seg_onnx = OutcomeSegmenter(path, backend="onnx")
    seg_torch = OutcomeSegmenter(path, backend="torch")
    depth = _scene(480, 640, 5)
    a, b = seg_onnx.segment(depth), seg_torch.segment(depth)
    assert a.labels.shape == (480, 640) and len(np.unique(b.labels)) > 1
    assert (a.labels == b.labels).mean() >= 0.999


def test_auto_backend_falls_back_when_onnx_is_stale(onnx_ckpt: Path, tmp_path: Path) -> None:
    stale = tmp_path / "outcome_fcn.pt"
    _make_checkpoint(stale, seed=2)
    (tmp_path / "outcome_fcn.onnx").write_bytes(onnx_ckpt.with_suffix(".onnx").read_bytes())
    seg = OutcomeSegmenter(stale, backend="auto")
    assert seg.backend == "torch" and "hash differs" in seg.backend_reason
    with pytest.raises(CheckpointError, match="hash differs"):
        OutcomeSegmenter(stale, backend="onnx")
    (tmp_path / "outcome_fcn.onnx").unlink()
    assert OutcomeSegmenter(stale, backend="auto").backend == "torch"
    with pytest.raises(CheckpointError, match="no ONNX file"):
        OutcomeSegmenter(stale, backend="onnx")


def test_a_model_of_another_task_reports_its_own_outcomes(tmp_path: Path,
                                                          monkeypatch) -> None:
    """A shelf model: presence, counts, objects and fragments follow its table, not the
    default task's (ids 2..5 are on_shelf, fell_off, hanging_over_edge, tipped)."""
    from model_helpers import SHELF_TABLE

    seg = OutcomeSegmenter(_make_checkpoint(tmp_path / "shelf.pt", table=SHELF_TABLE),
                           backend="torch")
    assert seg.table == SHELF_TABLE
    ids = SHELF_TABLE.outcome_ids
    small = np.zeros((120, 160), np.uint8)
    small[10:40, 10:40] = ids["hanging_over_edge"]
    small[10:12, 38:40] = ids["tipped"]      # a 4-pixel fringe on it: absorbed (fragments.py)
    small[80:90, 100:110] = ids["tipped"]    # an object of its own
    monkeypatch.setattr(seg, "_predict_small", lambda x: small.copy())
    result = seg.segment(np.full((480, 640), 2.0, np.float32))
    assert tuple(result.present) == tuple(result.pixel_counts) == tuple(result.objects) \
        == ("on_shelf", "fell_off", "hanging_over_edge", "tipped")
    assert result.present == {"on_shelf": False, "fell_off": False, "hanging_over_edge": True,
                              "tipped": True}
    assert result.pixel_counts["hanging_over_edge"] == 30 * 30 * 16  # the fringe joined it
    [tipped] = result.objects["tipped"]
    assert tipped.outcome == "tipped" and tipped.pixel_count == 1600
    assert result.present == outcomes_present(result.labels, table=SHELF_TABLE)


def _strip_label_table(onnx_path: Path) -> None:
    """Make ``onnx_path`` look like an export from before tables travelled as data."""
    import onnx

    from task_outcome_ros.onnx_export import META_LABEL_TABLE

    proto = onnx.load(str(onnx_path))
    kept = [(e.key, e.value) for e in proto.metadata_props if e.key != META_LABEL_TABLE]
    del proto.metadata_props[:]
    for key, value in kept:
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.save(proto, str(onnx_path))


def test_onnx_export_records_the_label_table(tmp_path: Path) -> None:
    """The export carries the table; an export without one is the default task's, so it
    serves a default-task checkpoint and is refused (torch instead) for another task's."""
    pytest.importorskip("onnx")
    pytest.importorskip("onnxruntime")
    from model_helpers import SHELF_TABLE

    from task_outcome_ros.onnx_export import export_onnx, metadata_label_table, read_metadata

    shelf = _make_checkpoint(tmp_path / "shelf" / "outcome_fcn.pt", table=SHELF_TABLE)
    onnx_path = export_onnx(shelf, verify=False)
    assert metadata_label_table(read_metadata(onnx_path)) == SHELF_TABLE
    seg = OutcomeSegmenter(shelf, backend="auto")
    assert seg.backend == "onnx" and seg.table == SHELF_TABLE
    _strip_label_table(onnx_path)
    assert metadata_label_table(read_metadata(onnx_path)) == DEFAULT_TABLE
    seg = OutcomeSegmenter(shelf, backend="auto")
    assert seg.backend == "torch" and "names its classes" in seg.backend_reason
    assert seg.table == SHELF_TABLE

    default = _make_checkpoint(tmp_path / "default" / "outcome_fcn.pt")
    _strip_label_table(export_onnx(default, verify=False))
    assert OutcomeSegmenter(default, backend="onnx").table == DEFAULT_TABLE


def test_shipped_models_load_with_their_tables() -> None:
    """The default and tote models were shipped before tables travelled as data (a {name: id}
    table in the checkpoint, none in the ONNX export): both still serve, as the default
    task's. Every shipped model serves through ONNX, with the checkpoint's table."""
    for name in ("default", "tote"):
        assert OutcomeSegmenter(name, backend="torch").table == DEFAULT_TABLE
    for name in inference.shipped_models():
        seg = OutcomeSegmenter(name, backend="auto")
        assert seg.table.outcome_names and seg.table.classes[0] == "background"
        if importlib.util.find_spec("onnxruntime") is not None:
            assert seg.backend == "onnx", seg.backend_reason


def test_background_only_labels_are_not_present() -> None:
    labels = np.full((480, 640), BACKGROUND, np.uint8)
    assert not any(outcomes_present(labels).values())


def test_intrinsics_reach_only_a_network_trained_with_them(ckpt: Path, tmp_path: Path,
                                                            monkeypatch) -> None:
    from test_floor import EDGE_CAMERA as camera
    from test_floor import _tilted_scene

    # A tilted floor and a box at the rim's height, seen by a camera at the envelope's edge:
    # there the camera model changes the heights by millimetres.
    depth = _tilted_scene(h=480, w=640, box_height=0.25, camera=camera)
    nominal = OutcomeSegmenter(ckpt, backend="torch")
    assert not nominal.uses_intrinsics
    np.testing.assert_array_equal(nominal.segment(depth, camera).labels,
                                  nominal.segment(depth).labels)

    own_norm = dict(DEFAULT_NORMALISATION, intrinsics=INTRINSICS_FROM_CAMERA_INFO)
    own = OutcomeSegmenter(_make_checkpoint(tmp_path / "own.pt", normalisation=own_norm),
                           backend="torch")
    assert own.uses_intrinsics and own.normalisation["intrinsics"] == INTRINSICS_FROM_CAMERA_INFO
    inputs = []
    predict = own._predict_small
    monkeypatch.setattr(own, "_predict_small", lambda x: inputs.append(x) or predict(x))
    own.segment(depth, camera)
    own.segment(depth)
    heights_own, heights_nominal = inputs[0][2], inputs[1][2]
    np.testing.assert_array_equal(inputs[0][:2], inputs[1][:2])   # depth, validity: same
    # heights (in units of 0.25 m): the camera's, a few mm apart on the box
    assert np.abs(heights_own - heights_nominal).max() * 0.25 > 0.003
    with pytest.raises(ValueError, match="intrinsics are for a 320 x 240 image"):
        own.segment(depth, Intrinsics(320, 240, 295.0, 295.0, 159.5, 119.5))


def test_normalisation_intrinsics_field_is_checked() -> None:
    with pytest.raises(ValueError, match="intrinsics"):
        check_normalisation(dict(DEFAULT_NORMALISATION, intrinsics="tf"))
    from test_floor import TWO_CHANNEL_NORMALISATION

    with pytest.raises(ValueError, match="height channel"):
        check_normalisation(dict(TWO_CHANNEL_NORMALISATION,
                                 intrinsics=INTRINSICS_FROM_CAMERA_INFO))


def test_reuse_floor_fit_reports_what_each_frame_did(ckpt: Path) -> None:
    """A stream's segmenter keeps the plane of a repeated view, and a frame without depth
    (no heights computed) reports nothing rather than an earlier frame's answer."""
    from test_floor import _tilted_scene

    seg = OutcomeSegmenter(ckpt, backend="torch", reuse_floor_fit=True)
    seg.warmup()
    depth = _tilted_scene(h=480, w=640)
    assert seg.segment(depth).support_plane == "fitted"
    assert seg.segment(depth).support_plane == "kept"
    assert seg.segment(np.full_like(depth, np.nan)).support_plane is None
    assert OutcomeSegmenter(ckpt, backend="torch").segment(depth).support_plane is None


def test_a_sanitised_frame_is_segmented_as_it_is(segmenter: OutcomeSegmenter) -> None:
    """``sanitized=True`` (the node's decoded frames) skips the copy, not the answer."""
    raw = _scene(480, 640, seed=3)
    raw[0, :7] = [0.0, -1.0, np.inf, -np.inf, np.nan, 1e-9, 2.5]
    clean = sanitize_depth(raw)
    before = clean.copy()
    got = segmenter.segment(clean, sanitized=True)
    want = segmenter.segment(raw)
    np.testing.assert_array_equal(got.labels, want.labels)
    assert got.pixel_counts == want.pixel_counts and got.stats == want.stats
    np.testing.assert_array_equal(clean, before)  # used, not written
    # The envelope's valid share is the full frame's (5 % holes), not the working size's,
    # where almost every pixel has some valid depth under it.
    assert got.stats.valid_fraction == pytest.approx(np.isfinite(clean).mean(), abs=1e-9)
    assert got.stats.valid_fraction < 0.97


@pytest.mark.parametrize("classes", [1, 2, 5, 7])
def test_class_ids_answer_as_argmax_over_the_channels_ties_to_the_first(classes):
    rng = np.random.default_rng(classes)
    logits = rng.normal(size=(classes, 30, 40)).astype(np.float32)
    logits[:, :10] = rng.integers(0, 3, size=(classes, 10, 40))   # many exact ties
    ids = class_ids(logits)
    assert ids.dtype == np.uint8 and ids.shape == (30, 40)
    assert np.array_equal(ids, np.argmax(logits, axis=0))
