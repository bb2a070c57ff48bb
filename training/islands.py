"""Outlier islands: small patches of wrong depth, nearer or farther than what lies there.

Disparity sensors match a patch wrongly now and then and keep the match: a few pixels read a
depth tens of centimetres off. The bundled real tote frames show about ten such islands
nearer than their surroundings per frame (4-21 px at 640 x 480, some 30 cm nearer than a
tote's floor at 0.7 m), and the active-stereo model makes them (``stereo.py``). Neither of
the sensor models the bundled specs train on does, and on frames from the active-stereo
model default model 0.13.0 drops from 0.98 to 0.29, most of it to these islands
(docs/evaluation.md). Two forms of one shape (``ISLAND_*``):

- ``disparity_islands``: a full-resolution field of islands, each off by its own disparity,
  for ``stereo.py``'s mismatches and, through ``add_islands``, the robustness suite's
  ``outlier_islands`` points;
- ``working_islands``: islands drawn at the working size, for training
  (``TrainConfig.aug_islands``), on whole images and on crops of them alike.

Labels stay the truth of what lies there: an island is the sensor's error, not an object.
"""

from __future__ import annotations

import functools
import math

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from task_outcome_ros.floor import FOCAL_OVER_WIDTH
from training.noise import speckle_holes

# The islands' shape at 640 x 480, for the suite and for training alike.
ISLAND_MAX_RADIUS_PX = 3
ISLAND_MAX_DISPARITY_PX = 4.0
ISLAND_BASELINE_M = 0.075   # the disparity-to-depth baseline of the suite's and training's islands
REFERENCE_WIDTH = 640


def disparity_islands(shape: tuple[int, int], rate: float, max_radius_px: int,
                      max_disparity_px: float, rng: np.random.Generator
                      ) -> np.ndarray | np.float32:
    """(h, w) disparity offsets (px) of islands seeded at ``rate`` per pixel and grown to
    discs of radius 0..``max_radius_px`` (``noise.speckle_holes``), each connected island off
    by its own U(-1, 1) x ``max_disparity_px``, 0 elsewhere. Draws nothing at a zero rate or
    offset."""
    if rate <= 0 or max_disparity_px <= 0:
        return np.float32(0.0)
    islands = speckle_holes(shape, rate, max_radius_px, rng)
    count, ids = cv2.connectedComponents(islands.astype(np.uint8), connectivity=8)
    offsets = rng.uniform(-1.0, 1.0, size=count).astype(np.float32)
    offsets *= np.float32(max_disparity_px)
    offsets[0] = 0.0                                     # id 0: no island
    return offsets[ids]


def add_islands(depth: np.ndarray, fx: float, rate: float, rng: np.random.Generator,
                baseline_m: float = ISLAND_BASELINE_M) -> np.ndarray:
    """A frame (metres, NaN invalid) with outlier islands at ``rate`` per pixel: each
    island's depth is what a disparity ``ISLAND_MAX_DISPARITY_PX`` x U(-1, 1) off gives, for
    a camera of focal length ``fx`` px and ``baseline_m``. An island that would lie behind
    the camera loses its depth."""
    offsets = disparity_islands(depth.shape, rate, ISLAND_MAX_RADIUS_PX,
                                ISLAND_MAX_DISPARITY_PX, rng)
    fb = np.float32(fx * baseline_m)
    with np.errstate(invalid="ignore", divide="ignore"):
        moved = fb / (fb / depth + offsets)
    out = np.where(offsets != 0, moved, depth).astype(np.float32)
    out[~(out > 0)] = np.nan
    return out


@functools.lru_cache(maxsize=8)
def disc_kernels(pixel_scale: float, samples: int = 8) -> torch.Tensor:
    """(R + 1, 1, S, S) share of each working pixel an island of radius 0..R
    (``ISLAND_MAX_RADIUS_PX``) covers when seeded at the centre pixel: a disc of the island's
    area at 640 x 480 (1 + pi r^2 pixels) scaled by ``pixel_scale`` (working pixels per 640 x
    480 pixel), each working pixel sampled ``samples`` x ``samples`` times."""
    radii = [math.sqrt((1.0 + math.pi * r * r) / math.pi) * pixel_scale
             for r in range(ISLAND_MAX_RADIUS_PX + 1)]
    size = 2 * math.ceil(max(radii) + 0.5) + 1
    at = (torch.arange(size * samples, dtype=torch.float64) + 0.5) / samples - size / 2
    yy, xx = torch.meshgrid(at, at, indexing="ij")
    inside = torch.stack([(xx ** 2 + yy ** 2 <= rho * rho) for rho in radii]).double()
    return inside.reshape(len(radii), size, samples, size, samples).mean((2, 4))[:, None].float()


def _disc_cover(seeds: torch.Tensor, radius: torch.Tensor, offset: torch.Tensor,
                pixel_scale: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(cover, offset) per working pixel of islands drawn as discs (``disc_kernels``): the
    share of the pixel the islands cover (at most 1) and their offsets' cover-weighted mean."""
    kernels = disc_kernels(pixel_scale)
    pad = kernels.shape[-1] // 2
    cover, shift = torch.zeros_like(offset), torch.zeros_like(offset)
    for r in range(ISLAND_MAX_RADIUS_PX + 1):
        at = (seeds & (radius == r)).float()[:, None]
        kernel = kernels[r:r + 1]
        cover += F.conv2d(at, kernel, padding=pad)[:, 0]
        shift += F.conv2d(at * offset[:, None], kernel, padding=pad)[:, 0]
    mean_offset = torch.where(cover > 0, shift / cover.clamp_min(1e-9), torch.zeros_like(shift))
    return cover.clamp(max=1.0), mean_offset


def working_islands(depth: torch.Tensor, valid: torch.Tensor, intrinsics: torch.Tensor | None,
                    max_rate: float, gen: torch.Generator, image_width: int | None = None,
                    discs: bool = False) -> torch.Tensor:
    """Training images (N, h, w) at the working size with outlier islands: per image a rate
    U(0, ``max_rate``) of islands per 640 x 480 pixel, each falling in one working pixel and
    moving its depth by the share of it the island covers (an island of radius r covers
    1 + pi r^2 of the 640 x 480 pixels the working pixel averages) towards the depth its
    disparity offset gives. ``intrinsics``: the images' normalised camera (fx / W first),
    else the envelope's nominal focal length. ``image_width``: the whole working image's width
    when ``depth`` holds crops of it (``crops.crop_batch``), so that a working pixel stands for
    as many 640 x 480 pixels in a crop as in the whole image; else ``depth``'s own width.
    ``discs`` (``TrainConfig.aug_islands_discs``): each island instead covers a disc of its
    own area in working pixels (``disc_kernels``), over several pixels at finer working sizes
    as the suite's islands do once averaged (at 320 x 240 a median 6 working pixels), not
    one. Draws a fixed number of values for a batch, the same with or without ``discs``."""
    n, h, w = depth.shape
    per_working_pixel = (REFERENCE_WIDTH / (image_width or w)) ** 2   # 640 x 480 pixels in one
    rate = max_rate * torch.rand(n, generator=gen)
    seeds = torch.rand((n, h, w), generator=gen) < (rate * per_working_pixel)[:, None, None]
    radius = torch.randint(0, ISLAND_MAX_RADIUS_PX + 1, (n, h, w), generator=gen)
    offset = (2.0 * torch.rand((n, h, w), generator=gen) - 1.0) * ISLAND_MAX_DISPARITY_PX
    if discs:
        usable_seeds = seeds & (valid > 0)      # a seed where the sensor saw nothing: none
        cover, offset = _disc_cover(usable_seeds, radius, offset, per_working_pixel ** -0.5)
        seeds = cover > 0
    else:
        cover = ((1.0 + math.pi * radius.float() ** 2) / per_working_pixel).clamp(max=1.0)
    fx_over_width = (intrinsics[:, 0] if intrinsics is not None
                     else torch.full((n,), FOCAL_OVER_WIDTH))
    fb = (fx_over_width * REFERENCE_WIDTH * ISLAND_BASELINE_M)[:, None, None]
    moved = fb / (fb / depth.clamp_min(1e-3) + offset)
    usable = seeds & (valid > 0) & (moved > 0) & torch.isfinite(moved)
    return torch.where(usable, depth + cover * (moved - depth), depth)
