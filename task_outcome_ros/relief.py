"""The local relief input channel (``local_relief``) and the square filters it is made of.

What the channel is and why: ``model`` (its docstring, channel 3). How it is computed: on
the CPU, in numpy and OpenCV, one image plane at a time: the relief of a 160 x 120 image is
about twenty small array operations, and torch spent 0.8 ms on them against 0.3 for numpy,
with the same values (the same IEEE operations and OpenCV filters). Inputs on another device
are copied to the CPU for it, as they carry no gradient. The optional noise deviation
(``local_noise_sd``) and the majority of valid pixels (``majority_valid``) stay in torch,
with OpenCV on the CPU and torch's own filters elsewhere.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import torch
import torch.nn.functional as F

NOISE_STEP_M = 0.001  # local_noise_sd's median works on |residuals| in these steps ...
NOISE_STEPS = 255     # ... up to this many (uint8, so OpenCV's median takes any window)


def local_relief(height: torch.Tensor, valid: torch.Tensor, window: int,
                 smoothing: int = 1, base: int | None = None,
                 noise_sds: float = 0.0) -> torch.Tensor:
    """(N, h, w) heights (metres) and validity -> height above their morphological opening
    with a ``window`` x ``window`` square (metres, >= 0; 0 where invalid).

    The opening (erosion, then dilation) keeps every surface a window fits on and flattens
    what is narrower, so what remains is each small object's or wall's height above the
    surface around it, whichever surface that is. Beyond the frame there is no support (the
    erosion sees -inf there), so an object cut by the frame reads its height like one in
    full view, while a surface reaching the frame still reads 0 up to its last pixel, carried
    in by the dilation from half a window inside. Invalid pixels neither lower the erosion nor
    raise the dilation; a window with no valid pixel leaves its pixel's relief 0. Inputs
    carry no gradient.

    ``smoothing`` > 1: the relief of the heights' mean over a ``smoothing`` x ``smoothing``
    square of valid pixels (``valid_mean``). Why: the erosion is a minimum over a window's
    pixels, so on a noisy flat surface it sits in the noise's low tail and the surface reads
    a relief that grows with the noise (docs/experiments.md); the mean narrows that tail.

    ``base``: the surface (the opening) is found on the heights' mean over a ``base`` x
    ``base`` square instead, while each pixel's own height stays the ``smoothing`` mean. Why:
    the erosion's low tail is what grows with the noise (far floor at 3x noise), and a wider
    mean narrows it further without blurring a small object's own top as much. Measured on the
    default task with base 7, it did not hold 3x noise better (docs/experiments.md).

    ``noise_sds`` > 0 (with ``smoothing`` > 1): the relief minus that many deviations of the
    smoothed heights' own noise, measured around each pixel (``local_noise_sd``). Why: on a
    flat surface the relief is the erosion's low tail, a few noise deviations wide whatever
    the noise, so subtracting a few measured deviations makes a noisy floor read about as
    flat as a quiet one, while a small object keeps nearly all of its height (the noise is
    measured by a median, which an object's edges barely move). A pixel whose ``smoothing``
    square is not mostly valid reads no relief and holds up no surface (``majority_valid``):
    there the mean averages little and an isolated pixel, its own mean, shows no residual for
    the median to measure, so where a far floor fades out of range its isolated pixels read
    their raw noise as relief (found at 3x noise)."""
    raw = height.float()
    if noise_sds:
        valid = majority_valid(valid, smoothing)
    if len(raw) == 0:
        return torch.zeros_like(raw)
    heights, valids = raw.detach().cpu().numpy(), valid.detach().cpu().numpy()
    planes = [_plane_relief(h, v, window, smoothing, base) for h, v in zip(heights, valids)]
    relief = np.stack([r for r, _ in planes])
    if noise_sds:
        smoothed = torch.from_numpy(np.stack([m for _, m in planes])).to(raw.device)
        sd = local_noise_sd(raw, smoothed, valid, window, smoothing)
        relief = relief - np.float32(noise_sds) * sd.cpu().numpy()
    keep = valids & np.isfinite(relief)   # +inf where no window around held a valid pixel
    out = np.where(keep, np.maximum(relief, np.float32(0)), np.float32(0))
    return torch.from_numpy(out.astype(np.float32, copy=False)).to(raw.device)


def _plane_relief(height: np.ndarray, valid: np.ndarray, window: int, smoothing: int,
                  base: int | None) -> tuple[np.ndarray, np.ndarray]:
    """``local_relief`` of one (h, w) plane before its last step: (height above the opening,
    +inf where no support is seen; the ``smoothing`` mean of the heights)."""
    mean = _plane_valid_mean(height, valid, smoothing)
    surface = mean if base is None else _plane_valid_mean(height, valid, base)
    kernel = np.ones((window, window), np.uint8)
    # The erosion (a minimum, -inf beyond the frame) as the dilation of the negated heights
    # with +inf beyond it; invalid pixels read -inf there, so they never lower it.
    eroded = -cv2.dilate(np.where(valid, -surface, np.float32(-np.inf)), kernel,
                         borderType=cv2.BORDER_CONSTANT, borderValue=np.inf)
    eroded[np.isinf(eroded)] = -np.inf   # no support under the window: never wins below
    opened = cv2.dilate(eroded, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=-np.inf)
    return mean - opened, mean


def _plane_valid_mean(x: np.ndarray, valid: np.ndarray, window: int) -> np.ndarray:
    """``valid_mean`` of one (h, w) float32 plane (``window`` 1: the plane itself)."""
    if window <= 1:
        return x
    box = (window, window)
    total = cv2.boxFilter(np.where(valid, x, np.float32(0)), -1, box, normalize=False,
                          borderType=cv2.BORDER_CONSTANT)
    count = cv2.boxFilter(valid.astype(np.float32), -1, box, normalize=False,
                          borderType=cv2.BORDER_CONSTANT)
    return np.where(valid, total / np.maximum(count, np.float32(1)), x)


def majority_valid(valid: torch.Tensor, window: int) -> torch.Tensor:
    """Valid pixels more than half of whose centred ``window`` x ``window`` square, within
    the frame, is valid."""
    count = square_sum(valid.float(), window)
    in_frame = square_sum(torch.ones_like(valid, dtype=torch.float32), window)
    return valid & (count > in_frame / 2)


def local_noise_sd(raw: torch.Tensor, smoothed: torch.Tensor, valid: torch.Tensor,
                   window: int, smoothing: int) -> torch.Tensor:
    """(N, h, w) heights, their ``smoothing`` x ``smoothing`` mean over valid pixels and the
    validity -> a robust estimate of the noise deviation of each pixel's mean (metres).

    The pixels' own deviation is the median over a ``window`` x ``window`` square of
    |height - mean|, scaled to a deviation for Gaussian noise (1.4826, and sqrt(1 - 1/n) for
    the mean's share of its own pixel, n = smoothing² as inside a valid surface); a pixel's
    mean of k valid pixels has that divided by sqrt(k) (independent noise), so pixels with
    fewer valid neighbours get the larger deviation they have. Invalid pixels enter the median
    as a checkerboard of the lowest and highest steps, which cancel in pairs, so a window that
    is partly invalid still measures its valid pixels' noise rather than sliding towards 0.
    The median works on millimetre steps up to 255 mm (``NOISE_STEP_M``, ``NOISE_STEPS``):
    uint8, which OpenCV's median filter takes at any window size."""
    n = smoothing * smoothing
    residual = torch.nan_to_num((raw - smoothed).abs(), nan=0.0, posinf=0.0)
    steps = (residual / NOISE_STEP_M).round().clamp(0, NOISE_STEPS).to(torch.uint8)
    h, w = raw.shape[-2:]
    rows = torch.arange(h, device=raw.device)[:, None]
    cols = torch.arange(w, device=raw.device)[None, :]
    checkerboard = ((rows + cols) % 2).to(torch.uint8) * NOISE_STEPS
    steps = torch.where(valid, steps, checkerboard.expand_as(steps))
    median = square_median_u8(steps, window).float()
    count = square_sum(valid.float(), smoothing).clamp_min(1.0)   # the mean's own pixels
    pixel_sd = median * (NOISE_STEP_M * 1.4826 / math.sqrt(1.0 - 1.0 / n))
    return pixel_sd / count.sqrt()


def square_median_u8(x: torch.Tensor, window: int) -> torch.Tensor:
    """(N, h, w) uint8 -> the median over the centred ``window`` x ``window`` square, the
    border replicated. On the CPU OpenCV's median filter (0.5 ms at 160 x 120 for a 15 x 15
    window); elsewhere ``square_median_torch``, which gives the same values."""
    if x.device.type != "cpu" or len(x) == 0:
        return square_median_torch(x, window)
    return _per_plane(x, lambda plane: cv2.medianBlur(plane, window))


def square_median_torch(x: torch.Tensor, window: int) -> torch.Tensor:
    """``square_median_u8`` in torch: the median over the unfolded squares, one image at a
    time (the squares of one 160 x 120 image at window 15 take 17 MB)."""
    pad = window // 2

    def one(image: torch.Tensor) -> torch.Tensor:
        padded = F.pad(image[None, None].float(), (pad, pad, pad, pad), mode="replicate")
        squares = F.unfold(padded, window)  # (1, window², h * w)
        return squares.median(dim=1).values.reshape(image.shape).to(torch.uint8)

    if len(x) == 0:
        return x.clone()
    return torch.stack([one(image) for image in x])


def valid_mean(x: torch.Tensor, valid: torch.Tensor, window: int) -> torch.Tensor:
    """(N, h, w) values and validity -> each valid pixel's mean over the valid pixels of the
    centred ``window`` x ``window`` square (the frame's outside counts as invalid); invalid
    pixels keep their value. The relief's own mean (``_plane_valid_mean``), for torch
    callers."""
    if len(x) == 0:
        return x.clone()
    planes = [_plane_valid_mean(p, v, window) for p, v in
              zip(x.detach().float().cpu().numpy(), valid.detach().cpu().numpy())]
    return torch.from_numpy(np.stack(planes)).to(x.device)


def square_sum(x: torch.Tensor, window: int) -> torch.Tensor:
    """(N, h, w) float32 -> the sum over the centred ``window`` x ``window`` square, zeros
    beyond the frame. On the CPU OpenCV's box filter (cheaper than torch's average pool at
    160 x 120), elsewhere an average pool times the window's area."""
    if x.device.type != "cpu" or len(x) == 0:
        pad = window // 2
        pooled = F.avg_pool2d(x[:, None], window, stride=1, padding=pad,
                              count_include_pad=True)
        return pooled[:, 0] * float(window * window)
    return _per_plane(x, lambda plane: cv2.boxFilter(
        plane, -1, (window, window), normalize=False, borderType=cv2.BORDER_CONSTANT))


def _per_plane(x: torch.Tensor, opencv_op) -> torch.Tensor:
    """An OpenCV filter applied to each (h, w) plane of a CPU (N, h, w) tensor."""
    planes = x.detach().contiguous().numpy()
    return torch.from_numpy(np.stack([opencv_op(plane) for plane in planes])
                            .reshape(planes.shape))
