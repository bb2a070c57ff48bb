"""The FCN and the one preprocessing path from depth metres to network input.

The network is a compact U-Net: ``levels`` stride-2 stages, skip connections, and a 1x1 head
with one logit per class of the task's label table (``labels.LabelTable``, which the checkpoint
carries). It takes any input size (padded to the stride and cropped back), but it is trained
and run at a fixed working size stored in the checkpoint.

Input channels (see ``DEFAULT_NORMALISATION``; the dict is stored in every checkpoint):

0. depth: ``clip((z - offset_m) / scale_m, -clip, clip)``; invalid pixels are 0.
1. validity: fraction of valid input pixels under each working-size pixel, in [0, 1].
2. height above the floor (``floor.height_above_floor``) / ``height_scale_m``, clipped like
   depth; invalid pixels are 0. Present when the dict has ``height_scale_m`` (checkpoints
   from before it have two channels and keep working). With ``"intrinsics": "camera_info"``
   in the dict the network was trained on heights from each image's own intrinsics, and the
   callers pass them when they know them (camera_info on the robot); without the key, or
   without intrinsics, heights come from the envelope's nominal camera. ``floor_fit`` is the
   version of ``floor.fit_floor`` the network was trained on; a checkpoint without it was
   trained on version 1 (models up to 0.1.7) and keeps getting it. ``support_above_floor``
   (tasks on a table): heights from the table top when the room floor is in view too.
3. local relief (``relief.local_relief``): the height above the morphological opening of the
   heights with a square window of ``relief_window_px`` working pixels, / ``height_scale_m``,
   in [0, clip]. Present when the dict has ``relief_window_px`` (with a height channel). Why: the
   height channel measures from one support plane, so a 3 cm box on the room floor 0.75 m
   below a table reads -0.72 next to the floor's -0.75, a contrast lost in the table-to-floor
   step, while the same box on the table reads 0.03 against 0. The relief reads 0.03 for
   both: a small object stands out the same on any surface, by construction. Surfaces wider
   than the window (a table top, a tote's floor) read 0 up to their edges; narrow ones (walls)
   read their height. With ``relief_smoothing_px`` it is the relief of the heights' mean over
   a square of valid pixels (``relief.valid_mean``), so that sensor noise does not read as relief.
   With ``"relief_beneath_support": True`` (and ``support_above_floor``), what lies more
   than 5 cm below the table top is measured from the room floor beneath it first
   (``floor.heights_beneath_support``): an object on the room floor seen right beside the
   table top otherwise belongs to a surface the opening fits in, and reads no relief.
4. near-side height: the height of the near side of each working pixel (``nearest_depth``:
   the nearest of its block's four cells' mean depths), measured from the same support plane
   as channel 2, / ``height_scale_m``, clipped like it. Present when the dict has
   ``"nearest_height": True`` (with a height channel). Why: the area resize averages a
   block's depths, so a tote's 1 cm rim, about one working pixel wide, reads somewhere
   between its top and the floor beside it, and so does the top edge of an object leaning
   on it; whether the object's top rises above the rim (stuck) or not (inside) is a matter
   of millimetres. The near side of a block seen from above is its highest, which keeps the
   rim's and the object's tops at their true height in every working pixel whose cell they
   fill. It comes last, after the relief when both are on.

The channels are computed in one place, ``network_input`` (torch), after the one resize,
``resize_depth`` (numpy, NaN-aware area average; the near-side depth, ``nearest_depth``, is
a second one, to twice the working size). ``preprocess`` (one numpy image) and
``preprocess_batch`` (N torch images) both end in ``network_input``; a test proves they agree.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from task_outcome_ros.depth import sanitize_depth
from task_outcome_ros.floor import (
    BENEATH_SUPPORT_M,
    FLOOR_FIT,
    FLOOR_FITS,
    FOCAL_OVER_WIDTH,
    LEGACY_FLOOR_FIT,
    SUPPORT_MARGIN_M,
    FloorTracker,
    height_above_floor,
    heights_beneath_support,
)
from task_outcome_ros.labels import DEFAULT_TABLE
from task_outcome_ros.relief import local_relief

IN_CHANNELS = 3
# Cameras sit 1.6-2.4 m from the container (docs/interface.md §4): 2 m maps to 0, a metre to 1.
# Clip keeps a stray far return (Kinect range tops out at 4.5 m) from dominating activations.
# Heights are scaled by the wall height (0.25 m), so the rim sits at 1.
DEFAULT_NORMALISATION: dict[str, Any] = {
    "mode": "fixed", "offset_m": 2.0, "scale_m": 1.0, "clip": 4.0, "invalid_value": 0.0,
    "height_scale_m": 0.25, "focal_over_width": FOCAL_OVER_WIDTH,
    "floor_fit": FLOOR_FIT}
_DEPTH_FIELDS = ("offset_m", "scale_m", "clip", "invalid_value")  # every normalisation's
_HEIGHT_FIELDS = ("height_scale_m", "focal_over_width")
NEAREST_HEIGHT = "nearest_height"   # normalisation key of the near-side height (value True)
# normalisation key (value True): the relief of what lies below a table top measured from
# the room floor beneath it (floor.heights_beneath_support)
RELIEF_BENEATH_SUPPORT = "relief_beneath_support"
RELIEF_WINDOW_RANGE = (3, 63)  # odd working pixels: a window centred on its pixel
RELIEF_SMOOTHING_RANGE = (3, 15)  # odd working pixels of the relief's mean (local_relief)
RELIEF_NOISE_SDS_MAX = 10.0  # local noise deviations the relief may be lowered by
_FLOOR_FITS = FLOOR_FITS
# Every key a normalisation may carry. An unknown one is refused: it would be an input this
# code does not build (a checkpoint from a newer version), and the network would run blind.
NORMALISATION_KEYS = frozenset({
    "mode", *_DEPTH_FIELDS, *_HEIGHT_FIELDS, "floor_fit", "intrinsics", "support_above_floor",
    "relief_window_px", "relief_smoothing_px", "relief_base_px", "relief_noise_sds",
    RELIEF_BENEATH_SUPPORT, NEAREST_HEIGHT})
# normalisation["intrinsics"]: where the height channel's camera comes from in training.
INTRINSICS_FROM_CAMERA_INFO = "camera_info"
DEFAULT_INPUT_SIZE: tuple[int, int] = (160, 120)  # (W, H) working resolution
SPACE_TO_DEPTH_FACTORS = (1, 2)  # OutcomeFCN's input folding (1 = none)
DEFAULT_MODEL_ARGS: dict[str, Any] = {
    "in_channels": IN_CHANNELS, "num_classes": DEFAULT_TABLE.num_classes, "base_width": 8,
    "levels": 5, "decoder_convs": 1, "max_width": 128}  # no fold, no full-size head
FULL_SIZE_HEAD_MAX = 32  # channels of OutcomeFCN's optional full-size head
HEAD_WIDTH_MAX = 64  # channels of OutcomeFCN's last decoder block when widened (head_width)


def check_normalisation(norm: dict[str, Any]) -> dict[str, Any]:
    """Validate a normalisation dict (from code or a checkpoint); returns it as plain floats."""
    if not isinstance(norm, dict) or norm.get("mode") != "fixed":
        raise ValueError(f"normalisation must be a dict with mode 'fixed', got {norm!r}")
    unknown = sorted(set(norm) - NORMALISATION_KEYS)
    if unknown:
        raise ValueError(f"normalisation has fields this version does not know: {unknown} "
                         f"(a checkpoint from a newer task_outcome_ros?), got {norm!r}")
    try:
        out = {"mode": "fixed", **{k: float(norm[k]) for k in _DEPTH_FIELDS}}
        if any(k in norm for k in _HEIGHT_FIELDS):
            out.update({k: float(norm[k]) for k in _HEIGHT_FIELDS})
            out["floor_fit"] = norm.get("floor_fit", LEGACY_FLOOR_FIT)
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"normalisation {norm!r} lacks a numeric field: {exc}") from None
    fit = out.get("floor_fit")
    if "floor_fit" in norm and (type(fit) is not int or fit not in _FLOOR_FITS):
        raise ValueError(f"normalisation 'floor_fit' must be one of {_FLOOR_FITS} with a height "
                         f"channel, got {norm!r}")
    if "intrinsics" in norm:
        if norm["intrinsics"] != INTRINSICS_FROM_CAMERA_INFO or "height_scale_m" not in out:
            raise ValueError(f"normalisation 'intrinsics' must be "
                             f"{INTRINSICS_FROM_CAMERA_INFO!r} with a height channel, got "
                             f"{norm!r}")
        out["intrinsics"] = INTRINSICS_FROM_CAMERA_INFO
    if "support_above_floor" in norm:
        band = norm["support_above_floor"]
        if ("height_scale_m" not in out or not isinstance(band, (list, tuple))
                or len(band) != 2 or not 0 < float(band[0]) <= float(band[1])):
            raise ValueError(f"normalisation 'support_above_floor' must be a (min, max) height "
                             f"in metres with a height channel, got {norm!r}")
        out["support_above_floor"] = [float(band[0]), float(band[1])]
    if "relief_window_px" in norm:
        if "height_scale_m" not in out:
            raise ValueError(f"normalisation 'relief_window_px' needs a height channel, got "
                             f"{norm!r}")
        out["relief_window_px"] = check_relief_window(norm["relief_window_px"])
    for key, check in (("relief_smoothing_px", check_relief_smoothing),
                       ("relief_base_px", check_relief_base),
                       ("relief_noise_sds", check_relief_noise_sds)):
        if key in norm:
            if "relief_window_px" not in out:
                raise ValueError(f"normalisation {key!r} needs 'relief_window_px', "
                                 f"got {norm!r}")
            out[key] = check(norm[key])
    if RELIEF_BENEATH_SUPPORT in norm:
        if (norm[RELIEF_BENEATH_SUPPORT] is not True or "relief_window_px" not in out
                or "support_above_floor" not in out
                or out["support_above_floor"][0] <= SUPPORT_MARGIN_M + BENEATH_SUPPORT_M):
            raise ValueError(f"normalisation {RELIEF_BENEATH_SUPPORT!r} must be true, with "
                             f"'relief_window_px' and a 'support_above_floor' over "
                             f"{SUPPORT_MARGIN_M + BENEATH_SUPPORT_M:g} m, got {norm!r}")
        out[RELIEF_BENEATH_SUPPORT] = True
    if "relief_noise_sds" in out and "relief_smoothing_px" not in out:
        raise ValueError(f"normalisation 'relief_noise_sds' needs 'relief_smoothing_px' (the "
                         f"noise is that of the heights' mean), got {norm!r}")
    if NEAREST_HEIGHT in norm:
        if norm[NEAREST_HEIGHT] is not True or "height_scale_m" not in out:
            raise ValueError(f"normalisation {NEAREST_HEIGHT!r} must be true, with a height "
                             f"channel, got {norm!r}")
        out[NEAREST_HEIGHT] = True
    if not all(out.get(k, 1.0) > 0 for k in ("scale_m", "clip", *_HEIGHT_FIELDS)):
        raise ValueError(f"normalisation needs positive scales and clip, got {norm!r}")
    return out


def check_relief_window(window: Any) -> int:
    """The relief channel's window (``local_relief``): an odd int in ``RELIEF_WINDOW_RANGE``,
    so that it is centred on its pixel."""
    return _check_odd_window("relief_window_px", window, RELIEF_WINDOW_RANGE)


def check_relief_smoothing(window: Any) -> int:
    """The relief's smoothing window (``local_relief``): an odd int in
    ``RELIEF_SMOOTHING_RANGE``."""
    return _check_odd_window("relief_smoothing_px", window, RELIEF_SMOOTHING_RANGE)


def check_relief_base(window: Any) -> int:
    """The window of the mean the relief's surface is found on (``local_relief``): an odd
    int in ``RELIEF_SMOOTHING_RANGE``."""
    return _check_odd_window("relief_base_px", window, RELIEF_SMOOTHING_RANGE)


def check_relief_noise_sds(sds: Any) -> float:
    """How many local noise deviations the relief is lowered by (``local_relief``): a number
    in (0, ``RELIEF_NOISE_SDS_MAX``]."""
    if (isinstance(sds, bool) or not isinstance(sds, (int, float))
            or not 0 < sds <= RELIEF_NOISE_SDS_MAX):
        raise ValueError(f"relief_noise_sds must be a number in (0, {RELIEF_NOISE_SDS_MAX}], "
                         f"got {sds!r}")
    return float(sds)


def _check_odd_window(name: str, window: Any, bounds: tuple[int, int]) -> int:
    lo, hi = bounds
    if type(window) is not int or not lo <= window <= hi or window % 2 == 0:
        raise ValueError(f"{name} must be an odd int in [{lo}, {hi}] (a window centred on "
                         f"its pixel), got {window!r}")
    return window


def input_channels(normalisation: dict[str, Any]) -> int:
    """How many channels ``network_input`` makes with this normalisation (2 to 5)."""
    norm = check_normalisation(normalisation)
    return (2 + ("height_scale_m" in norm) + ("relief_window_px" in norm)
            + (NEAREST_HEIGHT in norm))


def check_input_size(size: Any) -> tuple[int, int]:
    """(W, H) of positive ints."""
    try:
        w, h = (int(v) for v in size)
    except (TypeError, ValueError):
        raise ValueError(f"input_size must be (W, H), got {size!r}") from None
    if w < 1 or h < 1:
        raise ValueError(f"input_size must be positive, got {size!r}")
    return w, h


def resize_depth(depth_m: np.ndarray, input_size: tuple[int, int],
                 ) -> tuple[np.ndarray, np.ndarray]:
    """NaN-aware area resize: (mean of the valid depths, valid fraction) per output pixel.

    ``depth_m`` must already be sanitised (float32, NaN invalid). Invalid output pixels (no
    valid input under them) get depth 0 and fraction 0.
    """
    w, h = input_size
    # 0 where invalid, the depth (> 0) elsewhere (sanitised input has no inf), and the valid
    # mask as float32: OpenCV's NaN patch and threshold, one SIMD pass each (numpy's fmax and
    # isfinite-then-convert took about twice as long).
    filled = np.array(depth_m, np.float32)
    cv2.patchNaNs(filled, 0)
    mask = cv2.threshold(filled, 0, 1.0, cv2.THRESH_BINARY)[1]
    if depth_m.shape != (h, w):
        # INTER_AREA averages when shrinking; on enlargement it is bilinear, still NaN-aware.
        filled = cv2.resize(filled, (w, h), interpolation=cv2.INTER_AREA)
        mask = cv2.resize(mask, (w, h), interpolation=cv2.INTER_AREA)
    frac = np.clip(mask, 0.0, 1.0)
    has = frac > 1e-6
    depth = np.zeros_like(filled)
    np.divide(filled, frac, out=depth, where=has)
    frac = np.where(has, frac, np.float32(0))
    return depth, frac.astype(np.float32, copy=False)


def preprocess(depth_m: np.ndarray, input_size: tuple[int, int],
               normalisation: dict[str, Any] | None = None,
               intrinsics: np.ndarray | None = None) -> np.ndarray:
    """Depth image (H x W metres, NaN/<=0/inf invalid) -> network input (C, h, w) float32.
    ``intrinsics``: the image's ``camera.Intrinsics.normalised()`` (4,), or None."""
    return preprocess_sanitized(sanitize_depth(depth_m), input_size, normalisation, intrinsics)


def preprocess_sanitized(depth_m: np.ndarray, input_size: tuple[int, int],
                         normalisation: dict[str, Any] | None = None,
                         intrinsics: np.ndarray | None = None,
                         floor_tracker: FloorTracker | None = None) -> np.ndarray:
    """``preprocess`` for a depth image already through ``depth.sanitize_depth``.
    ``floor_tracker``: keep the support plane across a static camera's frames (floor.py)."""
    size = check_input_size(input_size)
    norm = normalisation or DEFAULT_NORMALISATION
    depth, frac = resize_depth(depth_m, size)
    k = None if intrinsics is None else torch.as_tensor(intrinsics, dtype=torch.float32)[None]
    nearest = (torch.from_numpy(nearest_depth(depth_m, size))[None] if NEAREST_HEIGHT in norm
               else None)
    x = network_input(torch.from_numpy(depth)[None], torch.from_numpy(frac)[None],
                      norm, k, floor_tracker, nearest)
    return x[0].numpy()


def preprocess_batch(depth_m: torch.Tensor, input_size: tuple[int, int],
                     normalisation: dict[str, Any] | None = None,
                     intrinsics: torch.Tensor | None = None) -> torch.Tensor:
    """Torch twin of ``preprocess`` for (N, H, W) or (H, W) metre tensors -> (N, C, h, w).

    Identical to ``preprocess`` when the size is unchanged or shrinks by an integer factor
    (e.g. 640 x 480 -> 160 x 120); for other factors torch's area resize differs from
    OpenCV's by the resampling kernel only. Use ``preprocess`` in datasets when in doubt.
    """
    norm = check_normalisation(normalisation or DEFAULT_NORMALISATION)
    w, h = check_input_size(input_size)
    d = depth_m.float()
    if d.dim() == 2:
        d = d[None]
    if d.dim() != 3:
        raise ValueError(f"depth batch must be (N, H, W), got shape {tuple(depth_m.shape)}")
    valid = torch.isfinite(d) & (d > 0)
    filled = torch.where(valid, d, torch.zeros_like(d))[:, None]
    mask = valid.float()[:, None]
    if tuple(d.shape[-2:]) != (h, w):
        filled = F.interpolate(filled, size=(h, w), mode="area")
        mask = F.interpolate(mask, size=(h, w), mode="area")
    frac = mask.clamp(0.0, 1.0)
    has = frac > 1e-6
    depth = torch.where(has, filled / frac.clamp_min(1e-6), torch.zeros_like(filled))
    nearest = None
    if NEAREST_HEIGHT in norm:
        images = torch.where(valid, d, torch.tensor(float("nan"))).cpu().numpy()
        nearest = torch.from_numpy(np.stack([nearest_depth(i, (w, h)) for i in images])
                                   ).to(d.device)
    return network_input(depth[:, 0], frac[:, 0], norm, intrinsics, nearest=nearest)


def nearest_depth(depth_m: np.ndarray, input_size: tuple[int, int]) -> np.ndarray:
    """Sanitised (H, W) depth (metres, NaN invalid) -> (h, w) float32: the depth of the near
    side of each working pixel, 0 where nothing is valid (for ``network_input``'s near-side
    height channel).

    Each working pixel's block of input pixels is split 2 x 2; each cell's valid depths are
    averaged (``resize_depth`` to twice the working size) and the nearest cell is kept. A rim
    or an edge that fills a cell (1 cm at 1.3 m fills a column of cells at 640 x 480 -> 160 x
    120) keeps its depth, which the block's average would mix with the floor beside it, while
    a stray return (noise tail, flying pixel) is averaged with the rest of its cell rather
    than taken as it is, as a block minimum would. About 0.5 ms a frame (two OpenCV
    resizes)."""
    w, h = check_input_size(input_size)
    cells, frac = resize_depth(depth_m, (2 * w, 2 * h))
    cells = np.where(frac > 0, cells, np.float32(np.inf))
    # Four strided views: numpy's min over two strided axes at once is about 8x slower.
    near = np.minimum(np.minimum(cells[0::2, 0::2], cells[0::2, 1::2]),
                      np.minimum(cells[1::2, 0::2], cells[1::2, 1::2]))
    return np.where(np.isfinite(near), near, np.float32(0)).astype(np.float32, copy=False)


def network_input(depth: torch.Tensor, valid_fraction: torch.Tensor,
                  normalisation: dict[str, Any] | None = None,
                  intrinsics: torch.Tensor | None = None,
                  floor_tracker: FloorTracker | None = None,
                  nearest: torch.Tensor | None = None,
                  height_m: torch.Tensor | None = None) -> torch.Tensor:
    """(N, h, w) working-size depth (metres, as ``resize_depth`` gives) and valid fraction ->
    (N, C, h, w) network input (C = 2, 3 with heights, +1 with their local relief, +1 with
    the near-side heights). Training uses this on its cached ``resize_depth`` output,
    after augmentation, so heights follow the augmented depth. ``nearest``: (N, h, w)
    ``nearest_depth`` of the same images, required when the normalisation has
    ``nearest_height``.

    ``intrinsics`` (N, 4), ``camera.Intrinsics.normalised`` per image, are used for the heights
    only when the normalisation says the network was trained with them; else the nominal
    camera is (a network trained on nominal heights must see nominal heights).

    ``height_m`` (N, h, w): heights above the support plane already measured (metres), used
    instead of fitting the plane on ``depth``; for training on crops of an image
    (training/crops.py), which may hold too little of the floor to fit it. Only for a
    normalisation whose heights are the plain height channel (no relief, no near side)."""
    norm = check_normalisation(normalisation or DEFAULT_NORMALISATION)
    depth, valid_fraction = depth.float(), valid_fraction.float()
    has = valid_fraction > 1e-6
    z = ((depth - norm["offset_m"]) / norm["scale_m"]).clamp(-norm["clip"], norm["clip"])
    z = torch.where(has, z, torch.full_like(z, norm["invalid_value"]))
    channels = [z, torch.where(has, valid_fraction, torch.zeros_like(z))]
    if height_m is not None:
        if "height_scale_m" not in norm or "relief_window_px" in norm or NEAREST_HEIGHT in norm:
            raise ValueError("network_input: precomputed heights fit only a normalisation "
                             "with the plain height channel (no relief, no near side)")
        if height_m.shape != depth.shape:
            raise ValueError(f"network_input: heights of shape {tuple(height_m.shape)} for "
                             f"depth of shape {tuple(depth.shape)}")
        height = torch.where(has, height_m.float(), torch.zeros_like(z))
        channels.append((height / norm["height_scale_m"]).clamp(-norm["clip"], norm["clip"]))
    elif "height_scale_m" in norm:
        use = intrinsics if norm.get("intrinsics") == INTRINSICS_FROM_CAMERA_INFO else None
        wants_nearest = NEAREST_HEIGHT in norm
        if wants_nearest and (nearest is None or nearest.shape != depth.shape):
            raise ValueError(f"this normalisation has {NEAREST_HEIGHT!r}: network_input needs "
                             f"the near-side depth (model.nearest_depth) of shape "
                             f"{tuple(depth.shape)}, got "
                             f"{None if nearest is None else tuple(nearest.shape)}")
        height = height_above_floor(depth, has, norm["focal_over_width"], use,
                                    norm["floor_fit"], norm.get("support_above_floor"),
                                    floor_tracker, nearest if wants_nearest else None)
        if wants_nearest:
            height, nearest_height = height
        clip = norm["clip"]
        channels.append((height / norm["height_scale_m"]).clamp(-clip, clip))
        if "relief_window_px" in norm:
            surface_heights = (heights_beneath_support(height, has, norm["support_above_floor"])
                               if norm.get(RELIEF_BENEATH_SUPPORT) else height)
            relief = local_relief(surface_heights, has, norm["relief_window_px"],
                                  norm.get("relief_smoothing_px", 1),
                                  norm.get("relief_base_px"),
                                  norm.get("relief_noise_sds", 0.0))
            channels.append((relief / norm["height_scale_m"]).clamp(0.0, clip))
        if wants_nearest:
            channels.append((nearest_height / norm["height_scale_m"]).clamp(-clip, clip))
    return torch.stack(channels, dim=1)


def _conv_block(c_in: int, c_out: int, n_convs: int = 2) -> nn.Sequential:
    """n x (3x3 conv + BatchNorm + ReLU); BN runs in eval mode at inference, ORT fuses it."""
    layers: list[nn.Module] = []
    for i in range(n_convs):
        layers += [nn.Conv2d(c_in if i == 0 else c_out, c_out, 3, padding=1, bias=False),
                   nn.BatchNorm2d(c_out), nn.ReLU(inplace=True)]
    return nn.Sequential(*layers)


class OutcomeFCN(nn.Module):
    """U-Net-style FCN: depth + validity in, ``num_classes`` logits per pixel out.

    Widths double per level, base_width * 2**i for i in 0..levels, up to ``max_width`` (None:
    no cap). The cap is for the deepest levels, which hold most of the weights but, at a few
    pixels across, almost none of the compute. Encoder blocks have two convs, decoder blocks
    ``decoder_convs`` (one keeps the net inside the CPU budget). The input is zero-padded
    (zero = invalid) to a multiple of ``stride`` and the logits are cropped back.

    ``space_to_depth`` = 2 folds each 2 x 2 block of input pixels into channels before the
    first conv (pixel unshuffle) and upsamples the logits bilinearly back to the input size:
    a working size twice as fine in each direction for about the network cost of the coarser
    one, since every conv runs on the coarser grid. The fine input keeps sub-pixel detail (a
    shelf overhang of 10 mm is under one pixel at 160 x 120 and 2 m) that an area resize
    averages away. Neither use (finer input, or a cheaper network at the same input) has beaten
    the plain network in an hour of training (docs/experiments.md); no shipped model uses it.

    ``head_width`` = k > ``base_width`` widens the last decoder block to k channels, so that the
    1x1 head reads k features a pixel. Why: the head separates ``num_classes`` outcomes with one
    linear map of the last block's ReLU features; at ``base_width`` 4 (a thin first level at a
    finer working size) two training runs with five classes each scored IoU 0 on one class
    at their third epoch (docs/experiments.md). 0 = ``base_width``.

    ``full_size_head`` = k > 0 (with ``space_to_depth`` > 1) gives the folded network a thin
    head at the input size: one 3x3 conv of k channels on the unfolded input, concatenated with
    the decoder's last features upsampled by a 2x2 transposed conv to k channels, and a 1x1
    conv of k channels before the 1x1 logits. The encoder and decoder run on the coarse grid;
    only this head sees each input pixel's neighbours at full size, so outcome boundaries are
    drawn from full-size evidence rather than interpolated. On the default task it matched the
    plain network on validation but split more objects between two outcomes on the
    independent set (docs/experiments.md); no shipped model uses it.
    """

    def __init__(self, in_channels: int = IN_CHANNELS,
                 num_classes: int = DEFAULT_TABLE.num_classes, base_width: int = 8,
                 levels: int = 4, decoder_convs: int = 1,
                 max_width: int | None = None, space_to_depth: int = 1,
                 full_size_head: int = 0, head_width: int = 0) -> None:
        super().__init__()
        if not (1 <= levels <= 6 and 2 <= base_width <= 256 and 1 <= decoder_convs <= 2
                and (max_width is None or max_width >= base_width)
                and space_to_depth in SPACE_TO_DEPTH_FACTORS):
            raise ValueError(f"need 1 <= levels <= 6, 2 <= base_width <= 256, decoder_convs "
                             f"in (1, 2), max_width >= base_width and space_to_depth in "
                             f"{SPACE_TO_DEPTH_FACTORS}, got levels={levels} "
                             f"base_width={base_width} decoder_convs={decoder_convs} "
                             f"max_width={max_width} space_to_depth={space_to_depth!r}")
        if not (isinstance(full_size_head, int) and not isinstance(full_size_head, bool)
                and 0 <= full_size_head <= FULL_SIZE_HEAD_MAX
                and (full_size_head == 0 or space_to_depth > 1)):
            raise ValueError(f"full_size_head must be an int in [0, {FULL_SIZE_HEAD_MAX}], and "
                             f"0 without space_to_depth (nothing to refine), got "
                             f"{full_size_head!r} with space_to_depth={space_to_depth}")
        if not (isinstance(head_width, int) and not isinstance(head_width, bool)
                and (head_width == 0 or base_width < head_width <= HEAD_WIDTH_MAX)
                and not (head_width and full_size_head)):
            raise ValueError(f"head_width must be 0 or an int in (base_width, {HEAD_WIDTH_MAX}] "
                             f"without a full_size_head, got {head_width!r} with "
                             f"base_width={base_width} full_size_head={full_size_head}")
        self.levels = levels
        self.space_to_depth = space_to_depth
        cap = max_width or base_width * 2 ** levels
        widths = [min(base_width * 2 ** i, cap) for i in range(levels + 1)]
        self.stem = _conv_block(in_channels * space_to_depth ** 2, widths[0])
        self.down = nn.ModuleList(_conv_block(widths[i], widths[i + 1]) for i in range(levels))
        self.up = nn.ModuleList(
            nn.ConvTranspose2d(widths[i + 1], widths[i], 2, stride=2) for i in range(levels))
        last = head_width or widths[0]   # the last decoder block's width, read by the head
        self.fuse = nn.ModuleList(_conv_block(2 * widths[i], last if i == 0 else widths[i],
                                              decoder_convs) for i in range(levels))
        self.full_size_head = full_size_head
        if full_size_head:
            k = full_size_head
            self.fine_stem = _conv_block(in_channels, k, 1)
            self.fine_up = nn.ConvTranspose2d(widths[0], k, space_to_depth,
                                              stride=space_to_depth)
            # 1x1: a 3x3 fuse cost 0.6 ms more at 160 x 120 (ONNX, 1 thread); the stem's 3x3
            # already gives each full-size pixel its neighbours.
            self.fine_fuse = nn.Sequential(nn.Conv2d(2 * k, k, 1, bias=False),
                                           nn.BatchNorm2d(k), nn.ReLU(inplace=True))
        self.head = nn.Conv2d(full_size_head or last, num_classes, 1)

    @property
    def stride(self) -> int:
        return (1 << self.levels) * self.space_to_depth

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2], x.shape[-1]
        s = self.stride
        pad_h, pad_w = (s - h % s) % s, (s - w % s) % s
        if pad_h or pad_w:
            x = F.pad(x, (0, pad_w, 0, pad_h))
        full = x
        if self.space_to_depth > 1:
            x = F.pixel_unshuffle(x, self.space_to_depth)
        skips = [self.stem(x)]
        for block in self.down:
            skips.append(block(F.max_pool2d(skips[-1], 2)))
        y = skips.pop()
        for i in reversed(range(self.levels)):
            y = self.fuse[i](torch.cat([self.up[i](y), skips[i]], dim=1))
        if self.full_size_head:
            y = self.fine_fuse(torch.cat([self.fine_up(y), self.fine_stem(full)], dim=1))
            return self.head(y)[..., :h, :w]
        logits = self.head(y)
        if self.space_to_depth > 1:
            logits = F.interpolate(logits, scale_factor=float(self.space_to_depth),
                                   mode="bilinear", align_corners=False)
        return logits[..., :h, :w]


def build_model(model_args: dict[str, Any]) -> OutcomeFCN:
    """Rebuild the network from the constructor arguments stored in a checkpoint."""
    return OutcomeFCN(**model_args)


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())
