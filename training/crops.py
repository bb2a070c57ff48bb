"""Training on crops of a finer working size (``TrainConfig.train_crop``).

Why: the shelf's mistakes sit within one working pixel of the board's front edge at
160 x 120 (docs/evaluation.md), but a network trained on whole images at a finer size
fits too few epochs into the hour: each step pays the floor fit, the augmentation and the
loss on every pixel (240 x 180: 4 epochs, validation 0.902 against 0.920). Trained on
crops, the network sees the finer pixels at the coarse size's cost per step, and being
fully convolutional it runs on the whole image at inference.

A crop may hold too little of the floor to fit the support plane on, so each cached image's
heights are measured once, on the whole image, before training (``measure_heights``), and
cropped with the depth. The augmentations a crop gets keep those heights exact: a shift (the
crop's own position), a mirror, and re-drawn axial noise whose effect on the height follows
from the plane (along a pixel's ray, a depth change dz moves the height by dz (h + c) / z,
with c the plane's offset: ``h = n . (z r) - c``). Holes and roll are not supported here.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from task_outcome_ros.floor import backproject, support_plane
from task_outcome_ros.labels import FIRST_OUTCOME_ID, IGNORE, REFERENCE_PIXELS
from task_outcome_ros.model import INTRINSICS_FROM_CAMERA_INFO, network_input

HEIGHT_KEY, PLANE_OFFSET_KEY = "height_m", "plane_offset"
# Share of crops centred (with jitter) on a pixel of an outcome: most of a scene is floor and
# fixture, which a crop anywhere shows often enough; the rest are drawn anywhere, so that
# crops without objects teach the network not to invent them.
ON_OUTCOME_SHARE = 0.75


def measure_heights(arrays: dict, norm: dict, chunk: int = 128) -> None:
    """Adds each cached image's heights above its support plane (``HEIGHT_KEY``, (N, h, w)
    float16 metres, 0 without depth) and the plane's offset (``PLANE_OFFSET_KEY``, (N,)) to
    ``arrays``: the same plane and heights ``model.network_input`` measures on the whole
    image (``floor.height_above_floor``)."""
    depth_all, valid_all = arrays["depth"], arrays["valid"]
    heights = np.zeros(depth_all.shape, np.float16)
    offsets = np.zeros(len(depth_all), np.float32)
    use_info = norm.get("intrinsics") == INTRINSICS_FROM_CAMERA_INFO
    for start in range(0, len(depth_all), chunk):
        part = slice(start, start + chunk)
        depth = torch.from_numpy(depth_all[part].astype(np.float32))
        has = torch.from_numpy(valid_all[part].astype(np.float32)) > 1e-6
        intrinsics = (torch.from_numpy(arrays["intrinsics"][part]) if use_info else None)
        points = backproject(depth, norm["focal_over_width"], intrinsics)
        normal, offset = support_plane(points, has, norm["floor_fit"],
                                       norm.get("support_above_floor"))
        height = (points * normal[:, None, None]).sum(-1) - offset[:, None, None]
        heights[part] = torch.where(has, height, torch.zeros_like(height)).numpy()
        offsets[part] = offset.numpy()
    arrays[HEIGHT_KEY], arrays[PLANE_OFFSET_KEY] = heights, offsets


def crop_origins(labels: np.ndarray, crop: tuple[int, int], gen: torch.Generator
                 ) -> np.ndarray:
    """(N, 2) top-left corners (x, y) of one ``crop`` (w, h) per image of ``labels`` (N, H,
    W): ``ON_OUTCOME_SHARE`` of them centred on a random outcome pixel, moved by up to a
    quarter of the crop either way; the others, and those of images without an outcome,
    anywhere. Every crop lies inside its image."""
    n, height, width = labels.shape
    cw, ch = crop
    draws = torch.rand(n, 5, generator=gen).numpy()  # drawn all at once: one stream per batch
    origins = np.zeros((n, 2), np.int64)
    for i in range(n):
        outcome = np.flatnonzero((labels[i] >= FIRST_OUTCOME_ID) & (labels[i] != IGNORE))
        if draws[i, 0] < ON_OUTCOME_SHARE and len(outcome):
            pixel = outcome[min(len(outcome) - 1, int(draws[i, 1] * len(outcome)))]
            cy, cx = divmod(int(pixel), width)
            x = cx - cw // 2 + int((draws[i, 2] - 0.5) * cw / 2)
            y = cy - ch // 2 + int((draws[i, 3] - 0.5) * ch / 2)
        else:
            x = int(draws[i, 2] * (width - cw + 1))
            y = int(draws[i, 3] * (height - ch + 1))
        origins[i] = (min(max(x, 0), width - cw), min(max(y, 0), height - ch))
    return origins


def move_along_rays(depth: torch.Tensor, has: torch.Tensor, height: torch.Tensor,
                    offset: torch.Tensor, dz: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Depths moved by ``dz`` along their pixels' rays, and their heights above the same plane
    (offset ``offset``, broadcast per image): ``h = n . (z r) - c`` is linear in z, so the
    height moves by dz (h + c) / z. Pixels without depth (``has`` False) keep height 0."""
    moved = height + dz * (height + offset) / depth.clamp_min(1e-3)
    return depth + dz, torch.where(has, moved, height)


def crop_batch(arrays: dict, idx: np.ndarray, crop: tuple[int, int], gen: torch.Generator,
               noise_level: float, norm: dict) -> tuple[torch.Tensor, torch.Tensor]:
    """The network input (N, C, h, w) and labels (N, h, w) of one ``crop`` (w, h) of each
    cached image ``idx``, augmented: re-drawn axial noise of U(0, ``noise_level``) times the
    sensor's at the cache's working size (``train.SENSOR_NOISE_PER_Z2``), 0-3 % of pixels
    dropped, mirrored half the time. ``arrays`` must hold ``measure_heights``' answers."""
    from training.train import SENSOR_NOISE_PER_Z2  # train imports this module

    labels_all = arrays["labels"][idx]
    origins = crop_origins(labels_all, crop, gen)
    cw, ch = crop

    def cut(array: np.ndarray, rows) -> torch.Tensor:
        return torch.from_numpy(np.stack([array[r, y:y + ch, x:x + cw]
                                          for r, (x, y) in zip(rows, origins)]))

    depth = cut(arrays["depth"], idx).float()
    valid = cut(arrays["valid"], idx).float()
    height = cut(arrays[HEIGHT_KEY], idx).float()
    labels = cut(labels_all, range(len(idx))).long()
    offset = torch.from_numpy(arrays[PLANE_OFFSET_KEY][idx])[:, None, None]
    n = len(idx)
    full_pixels = arrays["depth"].shape[1] * arrays["depth"].shape[2]
    per_pixel = SENSOR_NOISE_PER_Z2 * math.sqrt(full_pixels / REFERENCE_PIXELS)
    level = per_pixel * noise_level * torch.rand(n, 1, 1, generator=gen)
    dz = torch.randn(depth.shape, generator=gen) * level * depth ** 2
    depth, height = move_along_rays(depth, valid > 1e-6, height, offset, dz)
    drop = torch.rand(depth.shape, generator=gen) < 0.03 * torch.rand(n, 1, 1, generator=gen)
    valid = torch.where(drop, torch.zeros_like(valid), valid)
    flip = (torch.rand(n, generator=gen) < 0.5)[:, None, None]
    depth, valid, height, labels = (torch.where(flip, t.flip(-1), t)
                                    for t in (depth, valid, height, labels))
    return network_input(depth, valid, norm, height_m=height), labels

