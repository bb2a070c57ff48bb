"""Regions without depth, larger than any our sensor models make.

Real depth frames lose far more than our sensor models drop: the six bundled real frames of
totes (training/real_frames/arc2017) have 24-38 % of their pixels without depth, in large
regions (dark plastic, shiny metal, what lies beyond the projector's field, the frame's
edges), where the tote spec's renders have 6 % (median; 15 % at the 95th percentile),
mostly speckles and shadows. What is left between such regions is fragments of surfaces,
which a network that never saw them reads as objects. ``no_return_holes`` makes such
regions for training (``TrainConfig.aug_holes``), ``lose_depth`` for the robustness suite's
``lost_depth_share`` points: smooth blobs, the top of a coarse random field upsampled.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from task_outcome_ros.labels import IGNORE

HOLE_MAX_SHARE = 0.35        # of the image, at most, per training image that gets holes
HOLE_GRID_CELLS = (3, 12)    # the random field's cells across the image: the blobs' scale


def blob_field(n: int, h: int, w: int, gen: torch.Generator) -> torch.Tensor:
    """(n, h, w) smooth random field: uniform values on a grid of ``HOLE_GRID_CELLS`` cells
    across (one size for all n), upsampled bicubically."""
    cols = int(torch.randint(HOLE_GRID_CELLS[0], HOLE_GRID_CELLS[1] + 1, (1,), generator=gen))
    rows = max(2, round(cols * h / w))
    field = torch.rand(n, 1, rows + 1, cols + 1, generator=gen)
    return F.interpolate(field, size=(h, w), mode="bicubic", align_corners=True)[:, 0]


def above_share(field: torch.Tensor, cover: torch.Tensor) -> torch.Tensor:
    """(n, h, w) bool: each image's ``cover[i]`` share of pixels where its field is highest."""
    n, h, w = field.shape
    ranked = field.reshape(n, -1).sort(dim=1).values
    keep = ((1.0 - cover) * (h * w - 1)).round().long().clamp(0, h * w - 1)
    threshold = ranked.gather(1, keep[:, None])[:, 0]
    return field > threshold[:, None, None]


def no_return_holes(shape: tuple[int, int, int], share: float, gen: torch.Generator
                    ) -> torch.Tensor:
    """(N, h, w) bool: regions without depth in ``share`` of the images, each covering
    U(0, HOLE_MAX_SHARE) of its image."""
    n, h, w = shape
    field = blob_field(n, h, w, gen)
    has_holes = torch.rand(n, generator=gen) < share
    cover = HOLE_MAX_SHARE * torch.rand(n, generator=gen) * has_holes
    return above_share(field, cover) & has_holes[:, None, None]


def punch_holes(valid: torch.Tensor, labels: torch.Tensor, share: float, gen: torch.Generator
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """``valid`` and ``labels`` (N, h, w) with ``no_return_holes`` punched in ``share`` of the
    images: no depth there, labels ignored (nothing tells the network what lies there)."""
    gone = no_return_holes(valid.shape, share, gen)
    return (torch.where(gone, torch.zeros_like(valid), valid),
            torch.where(gone, torch.full_like(labels, IGNORE), labels))


def lose_depth(depth: np.ndarray, labels: np.ndarray, share: float, seed: int
               ) -> tuple[np.ndarray, np.ndarray]:
    """A rendered frame (depth with NaN invalid, labels with IGNORE there) with ``share`` of
    its pixels in blobs without depth; the same ``seed`` gives the same blobs."""
    gen = torch.Generator().manual_seed(seed)
    h, w = depth.shape
    gone = above_share(blob_field(1, h, w, gen), torch.tensor([float(share)]))[0].numpy()
    depth, labels = depth.copy(), labels.copy()
    depth[gone] = np.nan
    labels[gone] = IGNORE
    return depth, labels
