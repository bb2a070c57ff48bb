"""Training on crops of a finer working size (``TrainConfig.train_crop``).

Why: the shelf's mistakes sit within one working pixel of the board's front edge at
160 x 120 (docs/evaluation.md), but a network trained on whole images at a finer size
fits too few epochs into the hour: each step pays the floor fit, the augmentation and the
loss on every pixel (240 x 180: 4 epochs, validation 0.902 against 0.920). Trained on
crops, the network sees the finer pixels at the coarse size's cost per step, and being
fully convolutional it runs on the whole image at inference.

A crop may hold too little of the floor to fit the support plane on, so each cached image's
plane is fitted once, on the whole image, before training (``measure_planes``: the plane
``model.network_input`` fits). A pixel's height above it is linear in its depth along its
ray, ``h = z (n . r(u, v)) - c`` (``floor.backproject``'s rays), so a crop's heights are
computed from its depths after every augmentation: re-drawn noise, lost depth, outlier
islands, and a roll, which moves each pixel's ray to the one it was turned from
(``roll.roll_sources``).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from task_outcome_ros.floor import backproject, pixel_rays, support_plane
from task_outcome_ros.labels import FIRST_OUTCOME_ID, IGNORE
from task_outcome_ros.model import INTRINSICS_FROM_CAMERA_INFO, network_input
from training.augment import Augmentations
from training.holes import punch_holes
from training.islands import working_islands
from training.range_limit import range_limit_band
from training.redrawn_noise import axial_noise, drop_pixels, noise_levels
from training.roll import draw_roll, roll_images, roll_sources

PLANE_NORMAL_KEY, PLANE_OFFSET_KEY = "plane_normal", "plane_offset"
# Share of crops centred (with jitter) on a pixel of an outcome: most of a scene is floor and
# fixture, which a crop anywhere shows often enough; the rest are drawn anywhere, so that
# crops without objects teach the network not to invent them.
ON_OUTCOME_SHARE = 0.75


def measure_planes(arrays: dict, norm: dict, chunk: int = 128) -> None:
    """Adds each cached image's support plane, fitted on the whole image as
    ``model.network_input`` fits it (``floor.support_plane``), to ``arrays``: unit normals
    (``PLANE_NORMAL_KEY``, (N, 3)) and offsets (``PLANE_OFFSET_KEY``, (N,))."""
    depth_all, valid_all = arrays["depth"], arrays["valid"]
    normals = np.zeros((len(depth_all), 3), np.float32)
    offsets = np.zeros(len(depth_all), np.float32)
    for start in range(0, len(depth_all), chunk):
        part = slice(start, start + chunk)
        depth = torch.from_numpy(depth_all[part].astype(np.float32))
        has = torch.from_numpy(valid_all[part].astype(np.float32)) > 1e-6
        points = backproject(depth, norm["focal_over_width"], image_intrinsics(arrays, part, norm))
        normal, offset = support_plane(points, has, norm["floor_fit"],
                                       norm.get("support_above_floor"))
        normals[part], offsets[part] = normal.numpy(), offset.numpy()
    arrays[PLANE_NORMAL_KEY], arrays[PLANE_OFFSET_KEY] = normals, offsets


def image_intrinsics(arrays: dict, rows, norm: dict) -> torch.Tensor | None:
    """The images' own intrinsics when the heights are measured with them, else None (the
    nominal camera), as ``model.network_input`` chooses."""
    if norm.get("intrinsics") != INTRINSICS_FROM_CAMERA_INFO:
        return None
    return torch.from_numpy(np.asarray(arrays["intrinsics"][rows], np.float32))


def heights_along_rays(depth: torch.Tensor, has: torch.Tensor, u: torch.Tensor,
                       v: torch.Tensor, size: tuple[int, int], normal: torch.Tensor,
                       offset: torch.Tensor, intrinsics: torch.Tensor | None,
                       focal_over_width: float) -> torch.Tensor:
    """(N, h, w) heights above the planes (``normal`` (N, 3), ``offset`` (N,)) of the points
    at ``depth`` along the rays of the whole image's pixels (``u``, ``v``) (N, h, w), for a
    whole image of ``size`` (w, h): what ``floor.height_above_floor`` gives for those pixels
    (``floor.pixel_rays``: ``backproject``'s camera); 0 where ``has`` is False."""
    x, y = pixel_rays(u, v, size, focal_over_width, intrinsics)
    n = normal[:, :, None, None]
    h = depth * (n[:, 0] * x + n[:, 1] * y + n[:, 2]) - offset[:, None, None]
    return torch.where(has, h, torch.zeros_like(h))


def crop_origins(labels: np.ndarray, crop: tuple[int, int], gen: torch.Generator
                 ) -> np.ndarray:
    """(N, 2) top-left corners (x, y) of one ``crop`` (w, h) per image of ``labels`` (N, H,
    W): ``ON_OUTCOME_SHARE`` of them centred on a random outcome pixel, moved by up to a
    quarter of the crop either way; the others, and those of images without an outcome,
    anywhere. Every crop lies inside its image."""
    n, height, width = labels.shape
    cw, ch = crop
    # Drawn all at once, five per image of which four are read (the runs documented on
    # 2026-12-06 drew five: keep it so they reproduce).
    draws = torch.rand(n, 5, generator=gen).numpy()
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


def roll_margins(crop: tuple[int, int], max_deg: float) -> tuple[int, int]:
    """Pixels to add on each side of a crop so that the crop turned by up to ``max_deg``
    still reads only from inside the window."""
    a = math.radians(min(max_deg, 90.0))
    cw, ch = crop
    turned_w, turned_h = cw * math.cos(a) + ch * math.sin(a), cw * math.sin(a) + ch * math.cos(a)
    return math.ceil((turned_w - cw) / 2) + 1, math.ceil((turned_h - ch) / 2) + 1


def cut(array: np.ndarray, rows, origins: np.ndarray, size: tuple[int, int], fill
        ) -> torch.Tensor:
    """(N, h, w) windows of ``size`` (w, h) at ``origins`` (x, y) of the images ``rows`` of
    ``array``; what lies outside an image is ``fill``."""
    w, h = size
    height, width = array.shape[1:]
    out = np.full((len(origins), h, w), fill, array.dtype)
    for k, (r, (x, y)) in enumerate(zip(rows, origins)):
        x0, y0, x1, y1 = max(x, 0), max(y, 0), min(x + w, width), min(y + h, height)
        if x1 > x0 and y1 > y0:
            out[k, y0 - y:y1 - y, x0 - x:x1 - x] = array[r, y0:y1, x0:x1]
    return torch.from_numpy(out)


def crop_batch(arrays: dict, idx: np.ndarray, crop: tuple[int, int], gen: torch.Generator,
               norm: dict, aug: Augmentations) -> tuple[torch.Tensor, torch.Tensor]:
    """The network input (N, C, h, w) and labels (N, h, w) of one ``crop`` (w, h) of each
    cached image ``idx``, augmented by ``aug`` as ``augment.augment`` augments whole images,
    without its shift and distance change: turned as by a camera rolled
    U(-``aug.roll_deg``, ``aug.roll_deg``) more (``roll.roll_images``, about the crop's
    centre), re-drawn axial noise of U(0, ``aug.noise_level``) times the sensor's at the
    cache's working size (``redrawn_noise.noise_levels``), 0-3 % of pixels dropped,
    ``aug.holes`` of the crops losing depth in blobs (``holes.punch_holes``), mirrored half
    the time, then outlier islands at up to ``aug.islands`` per 640 x 480 pixel
    (``islands.working_islands``, scaled by the whole image's width, as discs of their own
    size with ``aug.island_discs``; drawn after the mirror's draw, so 0 leaves the stream as
    it was) and ``aug.range_limit`` of the crops cut at a range limit with the truncation
    their noise gives (``range_limit.range_limit_band``, drawn after the islands). The
    heights come last, from the augmented depths (module docstring): an island moves its
    pixel's height as a sensor's would.
    ``arrays`` must hold ``measure_planes``' answers."""
    idx = np.asarray(idx)
    n, (cw, ch) = len(idx), crop
    full_h, full_w = arrays["depth"].shape[1:]
    origins = crop_origins(arrays["labels"][idx], crop, gen)
    mx, my = roll_margins(crop, aug.roll_deg) if aug.roll_deg > 0 else (0, 0)
    window = (cw + 2 * mx, ch + 2 * my)
    corners = origins - np.array([mx, my])
    depth = cut(arrays["depth"], idx, corners, window, 0).float()
    valid = cut(arrays["valid"], idx, corners, window, 0).float()
    labels = cut(arrays["labels"], idx, corners, window, IGNORE).long()
    grid_v, grid_u = torch.meshgrid(torch.arange(window[1], dtype=torch.float32),
                                    torch.arange(window[0], dtype=torch.float32), indexing="ij")
    u, v = grid_u.expand(n, -1, -1), grid_v.expand(n, -1, -1)
    if aug.roll_deg > 0:
        angles = draw_roll(n, aug.roll_deg, gen)
        centre = torch.tensor([(window[0] - 1) / 2, (window[1] - 1) / 2]).expand(n, 2)
        depth, valid, labels, _ = roll_images(angles, None, depth, valid, labels, gen=gen)
        source = roll_sources(angles, centre, torch.ones(n, 2), window[1], window[0])
        u, v = source[..., 0], source[..., 1]
    inner = (slice(None), slice(my, my + ch), slice(mx, mx + cw))
    depth, valid, labels, u, v = (t[inner] for t in (depth, valid, labels, u, v))
    u = u + torch.from_numpy(corners[:, 0]).float()[:, None, None]
    v = v + torch.from_numpy(corners[:, 1]).float()[:, None, None]
    level = noise_levels(n, (full_h, full_w), aug.noise_level, gen)
    depth = depth + axial_noise(depth, level, gen)
    valid = drop_pixels(valid, gen)
    if aug.holes > 0:
        valid, labels = punch_holes(valid, labels, aug.holes, gen)
    # The mirror is drawn before the islands, so that they leave it as it was.
    flip = (torch.rand(n, generator=gen) < 0.5)[:, None, None]
    camera = image_intrinsics(arrays, idx, norm)     # the islands' focal length and the heights'
    if aug.islands > 0:
        depth = working_islands(depth, valid, camera, aug.islands, gen, image_width=full_w,
                                discs=aug.island_discs)
    if aug.range_limit > 0:
        depth, valid = range_limit_band(depth, valid, level, aug.range_limit, gen,
                                        (full_h, full_w))
    height = heights_along_rays(depth, valid > 1e-6, u, v, (full_w, full_h),
                                torch.from_numpy(arrays[PLANE_NORMAL_KEY][idx]),
                                torch.from_numpy(arrays[PLANE_OFFSET_KEY][idx]),
                                camera, norm["focal_over_width"])
    depth, valid, height, labels = (torch.where(flip, t.flip(-1), t)
                                    for t in (depth, valid, height, labels))
    return network_input(depth, valid, norm, height_m=height), labels
