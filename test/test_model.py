"""The FCN and the one preprocessing path (model.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from task_outcome_ros.labels import DEFAULT_TABLE
from task_outcome_ros.model import (
    DEFAULT_MODEL_ARGS,
    DEFAULT_NORMALISATION,
    IN_CHANNELS,
    OutcomeFCN,
    build_model,
    preprocess,
    preprocess_batch,
    resize_depth,
)

pytestmark = pytest.mark.unit


@pytest.mark.parametrize("h,w", [(48, 64), (33, 97), (37, 53), (16, 16)])
def test_any_input_size_keeps_size(h: int, w: int) -> None:
    model = OutcomeFCN(base_width=4, levels=3).eval()
    with torch.inference_mode():
        out = model(torch.randn(2, IN_CHANNELS, h, w))
    assert out.shape == (2, DEFAULT_TABLE.num_classes, h, w)


@pytest.mark.parametrize("h,w", [(48, 64), (33, 97), (17, 16)])
def test_space_to_depth_keeps_size_and_doubles_the_stride(h: int, w: int) -> None:
    model = OutcomeFCN(base_width=4, levels=3, space_to_depth=2).eval()
    assert model.stride == 16 and model.stem[0].in_channels == 4 * IN_CHANNELS
    with torch.inference_mode():
        out = model(torch.randn(2, IN_CHANNELS, h, w))
    assert out.shape == (2, DEFAULT_TABLE.num_classes, h, w)


def test_space_to_depth_sees_sub_pixel_detail() -> None:
    """Each of the 4 pixels of a 2 x 2 block reaches the stem through its own weights: a
    change of one fine pixel changes the logits (an average-pool stem could not tell which
    of the four changed)."""
    torch.manual_seed(0)
    model = OutcomeFCN(base_width=4, levels=2, space_to_depth=2).eval()
    x = torch.zeros(1, IN_CHANNELS, 16, 16)
    outs = []
    for dy, dx in ((0, 0), (0, 1), (1, 0), (1, 1)):
        xi = x.clone()
        xi[0, 0, 8 + dy, 8 + dx] = 1.0
        with torch.inference_mode():
            outs.append(model(xi))
    for i in range(4):
        for j in range(i + 1, 4):
            assert not torch.allclose(outs[i], outs[j])


@pytest.mark.parametrize("h,w", [(48, 64), (33, 97)])
def test_full_size_head_keeps_size_and_works_at_full_size(h: int, w: int) -> None:
    """With the coarse path cut (its upsampling zeroed), one input pixel moves exactly its
    full-size 3 x 3 neighbourhood: the head runs on the unfolded grid, not the coarse one.
    With the path in place, the same pixel also moves logits far outside that neighbourhood."""
    torch.manual_seed(0)
    model = OutcomeFCN(base_width=4, levels=2, space_to_depth=2, full_size_head=4).eval()
    assert model.stride == 8
    x = torch.zeros(1, IN_CHANNELS, h, w)
    xi = x.clone()
    xi[0, 0, 11, 11] = 1.0  # odd coordinates: the last pixel of its 2 x 2 block

    def moved() -> torch.Tensor:
        with torch.inference_mode():
            return (model(xi) - model(x)).abs().sum(1)[0] > 1e-6

    with_context = moved()
    with torch.no_grad():
        model.fine_up.weight.zero_()
        model.fine_up.bias.zero_()
    local = moved()
    neighbourhood = torch.zeros_like(local)
    neighbourhood[10:13, 10:13] = True
    assert torch.equal(local, neighbourhood)
    assert (with_context & ~neighbourhood).sum() > 20
    assert model(x).shape == (1, DEFAULT_TABLE.num_classes, h, w)


def test_build_model_from_default_args() -> None:
    model = build_model(DEFAULT_MODEL_ARGS)
    assert model.stride == 2 ** DEFAULT_MODEL_ARGS["levels"]


@pytest.mark.parametrize("kwargs", [{"levels": 0}, {"base_width": 1}, {"decoder_convs": 3},
                                    {"space_to_depth": 3}, {"full_size_head": 4},
                                    {"space_to_depth": 2, "full_size_head": 33},
                                    {"space_to_depth": 2, "full_size_head": -1},
                                    {"base_width": 8, "head_width": 8}, {"head_width": 65},
                                    {"head_width": True},
                                    {"space_to_depth": 2, "full_size_head": 4, "head_width": 16}])
def test_bad_constructor_args(kwargs: dict) -> None:
    with pytest.raises(ValueError):
        OutcomeFCN(**kwargs)


def test_head_width_widens_only_the_last_block_the_head_reads() -> None:
    thin = OutcomeFCN(base_width=4, levels=3, head_width=8).eval()
    assert thin.head.in_channels == 8 and thin.stem[0].out_channels == 4
    plain = OutcomeFCN(base_width=4, levels=3).eval()
    assert plain.head.in_channels == 4
    x = torch.randn(1, IN_CHANNELS, 48, 40)
    with torch.no_grad():
        assert thin(x).shape == plain(x).shape == (1, DEFAULT_TABLE.num_classes, 48, 40)


def test_preprocess_normalisation_and_validity() -> None:
    depth = np.full((8, 8), 3.0, np.float32)
    depth[:4, :4] = np.nan          # top-left output pixel entirely invalid
    depth[4:, 4:6] = 0.0            # bottom-right output pixel half valid (0 = no return)
    x = preprocess(depth, (2, 2))
    assert x.shape == (IN_CHANNELS, 2, 2) and x.dtype == np.float32
    norm = DEFAULT_NORMALISATION
    expected = (3.0 - norm["offset_m"]) / norm["scale_m"]
    np.testing.assert_allclose(x[1], [[0.0, 1.0], [1.0, 0.5]])
    np.testing.assert_allclose(x[0], [[norm["invalid_value"], expected], [expected, expected]],
                               rtol=1e-6)


def test_preprocess_clips_and_handles_all_invalid() -> None:
    far = preprocess(np.full((10, 10), 500.0, np.float32), (5, 5))
    assert np.all(far[0] == DEFAULT_NORMALISATION["clip"])
    empty = preprocess(np.full((10, 12), np.nan, np.float32), (6, 5))
    assert empty.shape == (IN_CHANNELS, 5, 6) and not np.any(empty) and np.isfinite(empty).all()
    inf = preprocess(np.full((4, 4), np.inf, np.float32), (4, 4))
    assert not np.any(inf)


def test_resize_depth_is_nan_aware() -> None:
    depth = np.array([[1.0, np.nan], [3.0, np.nan]], np.float32)
    d, frac = resize_depth(depth, (1, 1))
    assert d[0, 0] == pytest.approx(2.0) and frac[0, 0] == pytest.approx(0.5)


@pytest.mark.parametrize("size_in,size_out", [((640, 480), (160, 120)), ((64, 48), (64, 48)),
                                              ((320, 240), (160, 120))])
def test_numpy_and_torch_preprocess_agree(size_in, size_out) -> None:
    rng = np.random.default_rng(1)
    w, h = size_in
    depths = (1.0 + 2.0 * rng.random((3, h, w))).astype(np.float32)
    depths[rng.random(depths.shape) < 0.2] = np.nan
    depths[:, :10, :10] = 0.0
    ref = np.stack([preprocess(d, size_out) for d in depths])
    got = preprocess_batch(torch.from_numpy(depths), size_out).numpy()
    assert got.shape == ref.shape
    np.testing.assert_allclose(got, ref, atol=1e-5)


def _box_scenes(n: int, h: int, w: int, rng: np.random.Generator):
    """Floor at 2 m, container-ish ring, one box of a random outcome class; labels to match."""
    depths = np.full((n, h, w), 2.0, np.float32)
    labels = np.zeros((n, h, w), np.int64)
    for i in range(n):
        y, x = rng.integers(4, h - 14), rng.integers(4, w - 14)
        cls = int(rng.integers(1, DEFAULT_TABLE.num_classes))
        depths[i, y:y + 10, x:x + 10] = 2.0 - 0.1 * cls
        labels[i, y:y + 10, x:x + 10] = cls
    return depths, labels


@pytest.mark.parametrize("space_to_depth,full_size_head", [(1, 0), (2, 0), (2, 8)])
def test_model_overfits_tiny_batch(space_to_depth: int, full_size_head: int) -> None:
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    depths, labels = _box_scenes(4, 48, 64, rng)
    x = preprocess_batch(torch.from_numpy(depths), (64, 48))
    y = torch.from_numpy(labels)
    model = OutcomeFCN(base_width=8, levels=3, space_to_depth=space_to_depth,
                       full_size_head=full_size_head)
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    losses = []
    for _ in range(150):
        opt.zero_grad()
        loss = F.cross_entropy(model(x), y)
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.1 * losses[0], (losses[0], losses[-1])
    model.eval()
    with torch.inference_mode():
        pred = model(x).argmax(1)
    objects = y > 0
    assert (pred[objects] == y[objects]).float().mean() > 0.9
    success = DEFAULT_TABLE.outcome_ids["success"]
    assert (pred == success).any() or not (y == success).any()


def test_training_defaults_build_the_default_architecture():
    """The architecture is written in two places (model.py for inference-side tools, TrainConfig
    for training, which must not import torch at config time): they must agree."""
    from training.config import TrainConfig

    assert TrainConfig().model_args == DEFAULT_MODEL_ARGS


def test_max_width_caps_the_deep_levels_only():
    capped = build_model({**DEFAULT_MODEL_ARGS, "levels": 5, "base_width": 8, "max_width": 32})
    assert [m.out_channels for m in (capped.down[i][0] for i in range(5))] == [16, 32, 32, 32, 32]
    x = torch.zeros(1, DEFAULT_MODEL_ARGS["in_channels"], 37, 53)
    assert capped(x).shape == (1, DEFAULT_MODEL_ARGS["num_classes"], 37, 53)
    with pytest.raises(ValueError, match="max_width"):
        build_model({**DEFAULT_MODEL_ARGS, "base_width": 16, "max_width": 8})
