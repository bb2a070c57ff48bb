"""Self-describing checkpoints: round trip, atomic write, and every way load() refuses."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
from model_helpers import SHELF_TABLE
from test_floor import TWO_CHANNEL_NORMALISATION, _container_floor_scene

from task_outcome_ros import checkpoint
from task_outcome_ros.checkpoint import CheckpointError
from task_outcome_ros.labels import DEFAULT_TABLE, LEGACY_DEFAULT_IDS
from task_outcome_ros.model import (
    DEFAULT_NORMALISATION,
    IN_CHANNELS,
    NORMALISATION_KEYS,
    OutcomeFCN,
)

pytestmark = pytest.mark.unit

ARGS = {"in_channels": IN_CHANNELS, "num_classes": 5, "base_width": 4, "levels": 2,
        "decoder_convs": 1}


@dataclasses.dataclass(frozen=True)
class _TrainConfig:
    lr: float = 1e-3
    sizes: tuple[int, int] = (160, 120)
    out: Path = Path("/tmp/run")


def _save(path: Path, **overrides) -> OutcomeFCN:
    torch.manual_seed(0)
    model = OutcomeFCN(**overrides.get("model_args", ARGS))
    # Non-trivial BN statistics, so a lost buffer would change the outputs.
    model.train()
    with torch.no_grad():
        model(torch.randn(2, IN_CHANNELS, 24, 32))
    kwargs = dict(model_args=ARGS, input_size=(32, 24), normalisation=DEFAULT_NORMALISATION,
                  train_config=_TrainConfig(), metrics={"miou": np.float32(0.5), "epoch": 3})
    kwargs.update(overrides)
    checkpoint.save(path, model, **kwargs)
    return model.eval()


def _rewrite(path: Path, **changes) -> None:
    payload = torch.load(path, weights_only=True)
    payload.update(changes)
    torch.save(payload, path)


def test_round_trip_rebuilds_identical_model(tmp_path: Path) -> None:
    path = tmp_path / "sub" / "m.pt"
    model = _save(path, optimizer_state=torch.optim.Adam(OutcomeFCN(**ARGS).parameters())
                  .state_dict(), extra={"note": "x"})
    loaded = checkpoint.load(path)
    assert not loaded.model.training
    x = torch.randn(1, IN_CHANNELS, 24, 32)
    with torch.inference_mode():
        assert torch.equal(model(x), loaded.model(x))
    assert loaded.model_args == ARGS
    assert loaded.input_size == (32, 24)
    assert loaded.normalisation == DEFAULT_NORMALISATION
    assert loaded.label_table == DEFAULT_TABLE
    assert loaded.train_config == {"lr": 1e-3, "sizes": [160, 120], "out": "/tmp/run"}
    assert loaded.metrics == {"miou": 0.5, "epoch": 3}
    assert loaded.extra == {"note": "x"} and loaded.optimizer_state is not None
    assert loaded.format_version == checkpoint.FORMAT_VERSION
    assert loaded.sha256 == checkpoint.file_sha256(path)
    assert sorted(p.name for p in path.parent.iterdir()) == ["m.pt"]  # no temp files left


def test_save_refuses_non_plain_values(tmp_path: Path) -> None:
    with pytest.raises(TypeError, match="metrics.bad"):
        _save(tmp_path / "m.pt", metrics={"bad": object()})
    assert not any(tmp_path.iterdir())


def _assert_error(path: Path, *fragments: str) -> None:
    with pytest.raises(CheckpointError) as info:
        checkpoint.load(path)
    assert isinstance(info.value, ValueError)
    assert str(path) in str(info.value)
    for fragment in fragments:
        assert fragment in str(info.value)


def test_missing_file(tmp_path: Path) -> None:
    _assert_error(tmp_path / "nope.pt", "not found")


def test_truncated_file(tmp_path: Path) -> None:
    path = tmp_path / "m.pt"
    _save(path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    _assert_error(path, "cannot be read")


def test_random_bytes(tmp_path: Path) -> None:
    path = tmp_path / "m.pt"
    path.write_bytes(np.random.default_rng(0).bytes(4096))
    _assert_error(path, "cannot be read")


@pytest.mark.parametrize("payload", [{"weight": torch.zeros(3)}, torch.zeros(3), [1, 2]])
def test_foreign_torch_file(tmp_path: Path, payload) -> None:
    path = tmp_path / "foreign.pt"
    torch.save(payload, path)
    _assert_error(path, "not a task_outcome_ros checkpoint")


def test_pickled_code_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "evil.pt"
    torch.save({"format": checkpoint.FORMAT, "obj": _TrainConfig()}, path)
    _assert_error(path, "cannot be read")


def test_a_table_of_another_task_round_trips(tmp_path: Path) -> None:
    """A shelf model (6 classes): the table comes back as saved and names the outputs."""
    from task_outcome_ros.inference import OutcomeSegmenter

    path = tmp_path / "shelf.pt"
    _save(path, model_args={**ARGS, "num_classes": 6}, label_table=SHELF_TABLE)
    loaded = checkpoint.load(path)
    assert loaded.label_table == SHELF_TABLE
    assert loaded.label_table.failures == ("fell_off", "hanging_over_edge", "tipped")
    assert loaded.label_table.fixture_name == "shelf"
    assert torch.load(path, weights_only=True)["label_table"] == SHELF_TABLE.to_dict()
    segmenter = OutcomeSegmenter(path, backend="torch")
    result = segmenter.segment(np.full((48, 64), 2.0, np.float32))
    assert segmenter.table == SHELF_TABLE
    assert tuple(result.present) == ("on_shelf", "fell_off", "hanging_over_edge", "tipped")
    assert int(result.labels.max()) < 6


def test_legacy_name_id_table_loads_as_the_default_table(tmp_path: Path) -> None:
    """Checkpoints from before tables travelled as data hold {name: id} of the default task."""
    path = tmp_path / "m.pt"
    _save(path)
    _rewrite(path, label_table=dict(LEGACY_DEFAULT_IDS))
    assert checkpoint.load(path).label_table is DEFAULT_TABLE


def _swapped_legacy_ids() -> dict[str, int]:
    table = dict(LEGACY_DEFAULT_IDS)
    table["success"], table["fell_outside"] = table["fell_outside"], table["success"]
    return table


@pytest.mark.parametrize("table", [
    _swapped_legacy_ids(),                                     # {name: id}, not the default's
    {"classes": "background,container"},
    {"classes": [{"id": 0, "name": "background"}]},            # no colour
    {"classes": [{"id": i, "name": "x", "colour": [0, 0, 0]} for i in range(3)]},  # same names
    {"classes": [{"id": i + 1, "name": f"c{i}", "colour": [0, 0, 0]} for i in range(3)]},
], ids=["swapped_legacy", "not_rows", "no_colour", "same_names", "ids_from_1"])
def test_malformed_label_table(tmp_path: Path, table) -> None:
    path = tmp_path / "m.pt"
    _save(path)
    _rewrite(path, label_table=table)
    _assert_error(path, "label table")


def test_table_and_model_outputs_must_agree(tmp_path: Path) -> None:
    """One output channel per class: saving or loading a mismatch is refused, naming both."""
    with pytest.raises(ValueError, match="num_classes=5 but the label table has 6 classes"):
        _save(tmp_path / "m.pt", label_table=SHELF_TABLE)
    with pytest.raises(ValueError, match="weights have 5 outputs"):   # model_args lie
        checkpoint.save(tmp_path / "m.pt", OutcomeFCN(**ARGS),
                        model_args={**ARGS, "num_classes": 6}, input_size=(32, 24),
                        normalisation=DEFAULT_NORMALISATION, train_config={}, metrics={},
                        label_table=SHELF_TABLE)
    assert not any(tmp_path.iterdir())
    path = tmp_path / "m.pt"
    _save(path)
    _rewrite(path, label_table=SHELF_TABLE.to_dict())         # 5 outputs, 6 classes
    _assert_error(path, "num_classes=5", "6 classes")
    _save(path)
    _rewrite(path, label_table=SHELF_TABLE.to_dict(), model_args={**ARGS, "num_classes": 6})
    _assert_error(path, "classifier's weights have 5 outputs", "6 classes")


@pytest.mark.parametrize("version", [2, 0, "1", None])
def test_unsupported_format_version(tmp_path: Path, version) -> None:
    path = tmp_path / "m.pt"
    _save(path)
    _rewrite(path, format_version=version)
    _assert_error(path, "format_version")


def test_weights_that_do_not_fit(tmp_path: Path) -> None:
    path = tmp_path / "m.pt"
    _save(path)
    _rewrite(path, model_args={**ARGS, "base_width": 6})
    _assert_error(path, "weights do not fit")


def test_bad_model_args_and_fields(tmp_path: Path) -> None:
    path = tmp_path / "m.pt"
    _save(path)
    _rewrite(path, model_args={**ARGS, "colour": "red"})
    _assert_error(path, "model_args")
    _save(path)
    _rewrite(path, input_size=[0, 10])
    _assert_error(path, "input_size")
    payload = torch.load(path, weights_only=True)
    del payload["normalisation"]
    payload["input_size"] = [32, 24]
    torch.save(payload, path)
    _assert_error(path, "'normalisation' is missing")


def test_cuda_device_without_cuda(tmp_path: Path) -> None:
    if torch.cuda.is_available():
        pytest.skip("CUDA is available here; the refusal path cannot be exercised")
    path = tmp_path / "m.pt"
    _save(path)
    with pytest.raises(ValueError, match="CUDA is not available"):
        checkpoint.load(path, device="cuda")
    assert checkpoint.load(path, device="auto").model is not None


def test_channel_count_must_match_the_normalisation(tmp_path: Path) -> None:
    path = tmp_path / "m.pt"
    _save(path)
    # 2-channel preprocessing for a 3-channel net
    _rewrite(path, normalisation=TWO_CHANNEL_NORMALISATION)
    with pytest.raises(CheckpointError, match="input channels"):
        checkpoint.load(path)


def test_two_channel_checkpoint_from_before_heights_still_segments(tmp_path: Path) -> None:
    from task_outcome_ros.inference import OutcomeSegmenter

    path = tmp_path / "legacy.pt"
    torch.manual_seed(0)
    model = OutcomeFCN(**{**ARGS, "in_channels": 2})
    checkpoint.save(path, model, model_args={**ARGS, "in_channels": 2}, input_size=(32, 24),
                    normalisation=TWO_CHANNEL_NORMALISATION, train_config={}, metrics={})
    result = OutcomeSegmenter(path, backend="torch").segment(np.full((48, 64), 2.0, np.float32))
    assert result.labels.shape == (48, 64)


def test_checkpoint_keeps_the_floor_fit_it_was_trained_on(tmp_path: Path) -> None:
    from task_outcome_ros.floor import FLOOR_FIT, LEGACY_FLOOR_FIT
    from task_outcome_ros.inference import OutcomeSegmenter

    new, old = tmp_path / "new.pt", tmp_path / "old.pt"
    _save(new, input_size=(160, 120))
    _save(old, input_size=(160, 120))
    _rewrite(old, normalisation={k: v for k, v in DEFAULT_NORMALISATION.items()
                                 if k != "floor_fit"})          # saved by models up to 0.1.7
    assert checkpoint.load(new).normalisation["floor_fit"] == FLOOR_FIT
    assert checkpoint.load(old).normalisation["floor_fit"] == LEGACY_FLOOR_FIT
    # The segmenter's height channel follows: on a scene whose inner floor misleads fit
    # version 1, the old checkpoint sees the floor millimetres off, the new one does not.
    depth, valid, outer = _container_floor_scene()
    depth = np.where(valid[0].numpy(), depth[0].numpy(), np.nan).astype(np.float32)
    scale = DEFAULT_NORMALISATION["height_scale_m"]
    for path, off_m in ((new, False), (old, True)):
        segmenter = OutcomeSegmenter(path, backend="torch")
        floor_height = np.median(segmenter.prepare(depth)[2][outer]) * scale
        assert (abs(floor_height) > 0.003) == off_m


def test_normalisation_field_this_version_does_not_know_is_refused(tmp_path: Path) -> None:
    """A checkpoint whose inputs include one this code cannot build (a newer version's
    channel) is refused by name, not run with that channel missing."""
    path = tmp_path / "m.pt"
    _save(path)
    _rewrite(path, normalisation={**DEFAULT_NORMALISATION, "edge_channel_px": 3})
    _assert_error(path, "does not know", "edge_channel_px")
    _save(path)
    assert checkpoint.load(path).normalisation.keys() <= NORMALISATION_KEYS
