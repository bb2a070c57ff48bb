"""Label-honest augmentation of working-size training images, and the batches it makes.

Everything here changes the sensor's picture of a scene, never the scene: a mirror, a shift
and a roll move the labels with the depth, a distance change scales the depth alone, and
re-drawn noise, dropped pixels, holes, outlier islands and the range limit's band change the
depth and keep the labels (ignored only in holes and in the border a shift or roll
uncovers). ``Augmentations`` says how much of each a run draws (``TrainConfig``'s ``aug_*``
fields); ``augment`` draws it on a batch of whole images, ``gather_batch`` gathers cached
images into that batch, and ``crops.crop_batch`` does the same for crops. In ``augment``
the holes, islands and band are drawn after everything else (in ``crop_batch`` the holes
before the mirror's draw), and each draws nothing when off, so a run without them draws as
runs did before they existed.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np
import torch

from task_outcome_ros.labels import IGNORE
from training.holes import punch_holes
from training.islands import working_islands
from training.range_limit import range_limit_band
from training.redrawn_noise import axial_noise, drop_pixels, noise_levels
from training.roll import draw_roll, measure_images, roll_images


@dataclasses.dataclass(frozen=True)
class Augmentations:
    """How much of each augmentation a batch draws; the fields are ``augment``'s keywords.
    The default is ``augment``'s own: re-drawn noise up to 1x, the rest off."""
    noise_level: float = 1.0
    holes: float = 0.0
    roll_deg: float = 0.0
    islands: float = 0.0
    island_discs: bool = False
    range_limit: float = 0.0

    @classmethod
    def of_config(cls, cfg, noise_level: float) -> Augmentations:
        """A ``TrainConfig``'s augmentations at ``noise_level`` (the run's ``aug_noise``,
        scaled to its task's sensor)."""
        return cls(noise_level=noise_level, holes=cfg.aug_holes, roll_deg=cfg.aug_roll_deg,
                   islands=cfg.aug_islands, island_discs=cfg.aug_islands_discs,
                   range_limit=cfg.aug_range_limit)


class Batch(NamedTuple):
    """Working-size training images: depth (N, h, w) metres, valid fraction, labels (long),
    intrinsics (N, 4) or None, near-side depth (N, h, w) or None, object distances (N, h, w,
    ``overlaps.object_distance``) or None."""
    depth: torch.Tensor
    valid: torch.Tensor
    labels: torch.Tensor
    intrinsics: torch.Tensor | None = None
    nearest: torch.Tensor | None = None
    object_distance: torch.Tensor | None = None


def augment(depth: torch.Tensor, valid: torch.Tensor, labels: torch.Tensor,
            gen: torch.Generator, noise_level: float = 1.0,
            intrinsics: torch.Tensor | None = None, nearest: torch.Tensor | None = None,
            holes: float = 0.0, roll_deg: float = 0.0,
            roll_measured: tuple[torch.Tensor, torch.Tensor] | None = None,
            object_distance: torch.Tensor | None = None, islands: float = 0.0,
            island_discs: bool = False, range_limit: float = 0.0) -> Batch:
    """Batch augmentation that keeps labels honest. depth/valid float (N,h,w), labels long.

    ``noise_level`` (``TrainConfig.aug_noise``): each image gets re-drawn axial noise of
    U(0, noise_level) times the sensor's own noise at this size; 0 turns it off.

    ``intrinsics`` (N, 4, ``camera.Intrinsics.normalised``), when the heights are computed
    from them, move with the image: a mirror mirrors the principal point, a shift shifts it.
    The whole-scene distance change is then left out: it would scale every height (the rim
    would no longer sit at the wall height), which is what exact intrinsics are there to
    avoid.

    ``nearest`` (N, h, w), the near-side depths, moves with ``depth`` (mirror, shift,
    distance change) and gets noise of the same level drawn on its own after the depth's
    noise and dropout (before the holes, islands and band).

    ``holes`` (``TrainConfig.aug_holes``): that share of the images loses its depth over
    ``holes.no_return_holes``, labels ignored there; drawn after the noise (before the
    islands and band), so 0 leaves the stream as it was.

    ``roll_deg`` (``TrainConfig.aug_roll_deg``): each image first turned as by a camera
    rolled U(-roll_deg, roll_deg) about its optical axis (``roll.roll_images``: about the
    principal point, corners coming into view without depth or label); drawn only when
    above 0, so 0 leaves the stream as it was. ``roll_measured``: the images'
    ``roll.measure_images``, if already at hand.

    ``object_distance`` (N, h, w), the auxiliary target, moves as the labels do (mirror,
    shift; 0 where the shift uncovers); it draws nothing. Not with the roll
    (``TrainConfig.validate`` refuses the pair).

    ``islands`` (``TrainConfig.aug_islands``): outlier islands of wrong depth at up to this
    rate per 640 x 480 pixel (``islands.working_islands``; as discs of their own size with
    ``island_discs``), labels kept; drawn after the holes (before the band), so 0 leaves
    the stream as it was.

    ``range_limit`` (``TrainConfig.aug_range_limit``): that share of the images cut at a
    range limit in their far depths with the truncation their noise gives
    (``range_limit.range_limit_band``), labels kept; drawn after the islands, so 0 leaves
    the stream as it was."""
    n = depth.shape[0]
    if roll_deg > 0:  # first, so that its interpolation does not smooth the noise drawn below
        depth, valid, labels, nearest = roll_images(draw_roll(n, roll_deg, gen), intrinsics,
                                                    depth, valid, labels, nearest, gen,
                                                    roll_measured)
    flip = torch.rand(n, generator=gen) < 0.5           # a mirrored scene is a valid scene
    depth = torch.where(flip[:, None, None], depth.flip(-1), depth)
    if nearest is not None:
        nearest = torch.where(flip[:, None, None], nearest.flip(-1), nearest)
    valid = torch.where(flip[:, None, None], valid.flip(-1), valid)
    labels = torch.where(flip[:, None, None], labels.flip(-1), labels)
    if object_distance is not None:
        object_distance = torch.where(flip[:, None, None], object_distance.flip(-1),
                                      object_distance)
    if intrinsics is not None:
        intrinsics = intrinsics.clone()
        intrinsics[:, 2] = torch.where(flip, -intrinsics[:, 2], intrinsics[:, 2])
    # Shift by a few pixels (camera aim jitter); uncovered border = no depth, ignored label.
    dy, dx = (int(v) for v in torch.randint(-6, 7, (2,), generator=gen))
    if dy or dx:
        depth, valid = depth.roll((dy, dx), (1, 2)), valid.roll((dy, dx), (1, 2))
        labels = labels.roll((dy, dx), (1, 2))
        moved = [(depth, 0.0), (valid, 0.0), (labels, IGNORE)]
        if nearest is not None:
            nearest = nearest.roll((dy, dx), (1, 2))
            moved.append((nearest, 0.0))
        if object_distance is not None:
            object_distance = object_distance.roll((dy, dx), (1, 2))
            moved.append((object_distance, 0.0))
        for t, fill in moved:
            if dy > 0:
                t[:, :dy] = fill
            elif dy < 0:
                t[:, dy:] = fill
            if dx > 0:
                t[:, :, :dx] = fill
            elif dx < 0:
                t[:, :, dx:] = fill
        if intrinsics is not None:  # content moved by (dx, dy) pixels: so did the centre
            intrinsics[:, 2] += dx / depth.shape[2]
            intrinsics[:, 3] += dy / depth.shape[1]
    # Whole-scene distance change (+-4 %) and re-drawn axial noise growing with z^2: up to
    # the sensor's own noise at this working size (0 to 1x per image by default), on top of
    # the noise already in the image. (Before model 0.1.5 this was 0.003 z^2 per working pixel,
    # about 7x the real noise at 160 x 120, which buried the millimetres that tell stuck from
    # success.)
    scale = 1.0 + 0.08 * (torch.rand(n, 1, 1, generator=gen) - 0.5)
    if intrinsics is not None:
        scale = torch.ones_like(scale)  # drawn all the same: the random stream stays aligned
    level = noise_levels(n, depth.shape[1:], noise_level, gen)
    depth = depth * scale + axial_noise(depth, level, gen)
    valid = drop_pixels(valid, gen)
    if nearest is not None:
        nearest = nearest * scale + axial_noise(nearest, level, gen)
    if holes > 0:
        valid, labels = punch_holes(valid, labels, holes, gen)
    if islands > 0:
        depth = working_islands(depth, valid, intrinsics, islands, gen, discs=island_discs)
    if range_limit > 0:
        depth, valid = range_limit_band(depth, valid, level, range_limit, gen)
    return Batch(depth, valid, labels, intrinsics, nearest, object_distance)


def gather_batch(arrays: dict, idx: np.ndarray, gen: torch.Generator | None,
                 aug: Augmentations = Augmentations()) -> Batch:
    """The cached images ``idx`` as a ``Batch``, augmented by ``aug`` unless ``gen`` is None
    (the training loop's data step; bench/train_step.py times this very function). intrinsics and
    nearest are None unless ``arrays`` holds them (``TrainConfig.camera_intrinsics``,
    ``TrainConfig.nearest_height``); the roll reads ``arrays``' ``measure_for_roll`` when
    there."""
    def tensor(key: str, dtype) -> torch.Tensor | None:
        return torch.from_numpy(arrays[key][idx].astype(dtype)) if key in arrays else None

    batch = Batch(tensor("depth", np.float32), tensor("valid", np.float32),
                  tensor("labels", np.int64), tensor("intrinsics", np.float32),
                  tensor("nearest", np.float32), tensor(OBJECT_DISTANCE, np.float32))
    if gen is not None:
        measured = ((tensor(ROLL_NOISE, np.float32), cached_edges(arrays, idx))
                    if aug.roll_deg > 0 and ROLL_NOISE in arrays and ROLL_EDGES in arrays
                    else None)
        batch = augment(*batch[:3], gen, intrinsics=batch.intrinsics, nearest=batch.nearest,
                        roll_measured=measured, object_distance=batch.object_distance,
                        **dataclasses.asdict(aug))
    return batch


ROLL_NOISE, ROLL_EDGES = "roll_noise", "roll_edges"
OBJECT_DISTANCE = "object_distance"  # the cached arrays' key of the auxiliary target


def measure_for_roll(arrays: dict, chunk: int = 256) -> None:
    """Adds each cached image's ``roll.measure_images`` (noise level, depth edges) to
    ``arrays``: they depend only on the image, and measuring them once instead of at every
    turn takes about 30 % off the roll's cost per batch (bench/roll_step.py)."""
    depth, valid = arrays["depth"], arrays["valid"]
    noise = np.zeros(len(depth), np.float32)
    # The edges are kept 8 to a byte along each row (19,000 tote images: 46 MB, not 365).
    edges = np.zeros((*depth.shape[:-1], (depth.shape[-1] + 7) // 8), np.uint8)
    for start in range(0, len(depth), chunk):
        part = slice(start, start + chunk)
        level, edge = measure_images(torch.from_numpy(depth[part].astype(np.float32)),
                                     torch.from_numpy(valid[part].astype(np.float32)))
        noise[part], edges[part] = level.numpy(), np.packbits(edge.numpy(), axis=-1)
    arrays[ROLL_NOISE], arrays[ROLL_EDGES] = noise, edges


def cached_edges(arrays: dict, idx: np.ndarray) -> torch.Tensor:
    """The depth edges ``measure_for_roll`` kept for the images ``idx``, unpacked (bool)."""
    width = arrays["depth"].shape[-1]
    return torch.from_numpy(np.unpackbits(arrays[ROLL_EDGES][idx], axis=-1,
                                          count=width).view(bool))
