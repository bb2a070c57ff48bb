"""Camera roll as a training augmentation: the image turned about its principal point.

Turning a camera about its optical axis changes no depth along that axis: every point keeps
its z and only moves in the image, by a rotation about the principal point (in focal units,
which are square pixels when fx = fy). So a rolled frame can be made from any rendered one,
exactly but for the corners that come into view, which have no depth and no label.

The specs draw a little roll per episode (``camera.roll_deg``, ±8°); the robustness suite's
``camera_roll_deg`` points go to 20°. ``TrainConfig.aug_roll_deg`` adds a roll of
U(-aug_roll_deg, aug_roll_deg) per training image on top, at no cost in rendering.

Depths between pixels are interpolated, and interpolation averages the image's own noise
away: on 128 shelf training images a turn of even 2° halved the pixel-to-pixel noise
(``pixel_noise``, median 0.00061 -> 0.00031 z²; white noise keeps 0.67 of its deviation),
and the shelf trained on such turns lost 3× noise and 320 × 240 beyond chance
(docs/experiments.md). So the turn puts back the variance it removed: each pixel gets fresh
noise of the image's own measured level times sqrt(1 - the sum of its squared interpolation
weights), which gives white noise its deviation back exactly and the shelf images 0.94 of
their pixel-to-pixel noise (median; the blended part stays correlated between neighbours).

Interpolation also blends across depth edges: on 128 shelf training images, of the pixels
whose row neighbours differ by more than 5 cm, 49 % lie between the two (by over a tenth of
the step) as rendered and 67-69 % after a turn of 2-15° blended everywhere, and the shelf
trained on such turns made more mistakes 5-20 mm from the board's edge (56 against 34
without the roll). So next to a detected edge (``depth_edges``) the turn takes the nearest
pixel for depth, valid fraction and near-side depth, as for the labels (45-49 %), and
blends only where the surface is smooth; the shelf trained so (shelf model 0.14.0) made 44
such mistakes, hanging_over_edge recall 0.915 against the blend's 0.857
(docs/experiments.md).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from task_outcome_ros.labels import IGNORE


def principal_points(intrinsics: torch.Tensor | None, n: int, h: int, w: int
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, 2) principal points (u, v) in pixels at this size and (N, 2) focal lengths
    (fx, fy) in pixels, from ``camera.Intrinsics.normalised`` rows; without intrinsics the
    image centre and square pixels (the focal length then cancels out)."""
    if intrinsics is None:
        centre = torch.tensor([(w - 1) / 2, (h - 1) / 2]).expand(n, 2)
        return centre, torch.ones(n, 2)
    centre = torch.stack([intrinsics[:, 2] * w + (w - 1) / 2,
                          intrinsics[:, 3] * h + (h - 1) / 2], 1)
    return centre, torch.stack([intrinsics[:, 0] * w, intrinsics[:, 1] * h], 1)


def source_terms(angles_rad: torch.Tensor, centre: torch.Tensor, focal: torch.Tensor,
                 h: int, w: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``roll_sources`` as the sum of a per-column part (N, 1, w, 2) and a per-row part
    (N, h, 1, 2): the turn is linear in the pixel's column and row, so one broadcast add
    makes any whole-batch coordinate map instead of a dozen passes over it."""
    fx, fy = focal[:, 0, None], focal[:, 1, None]
    cu, cv = centre[:, 0, None], centre[:, 1, None]
    x = (torch.arange(w, dtype=torch.float32)[None] - cu) / fx   # (N, w)
    y = (torch.arange(h, dtype=torch.float32)[None] - cv) / fy   # (N, h)
    cos, sin = angles_rad.cos()[:, None], angles_rad.sin()[:, None]
    columns = torch.stack([cos * x * fx + cu, sin * x * fy], -1)[:, None]
    rows = torch.stack([-sin * y * fx, cos * y * fy + cv], -1)[:, :, None]
    return columns, rows


def roll_sources(angles_rad: torch.Tensor, centre: torch.Tensor, focal: torch.Tensor,
                 h: int, w: int) -> torch.Tensor:
    """(N, h, w, 2) pixel coordinates (u, v): where each pixel of the image seen by a camera
    rolled by ``angles_rad`` (``render.look_at``'s sense) lies in the unrolled image. In
    focal units a pixel at (x', y') of the rolled camera is the point at
    (cos a x' - sin a y', sin a x' + cos a y') of the unrolled one."""
    columns, rows = source_terms(angles_rad, centre, focal, h, w)
    return columns + rows


def second_difference(t: torch.Tensor, ok: torch.Tensor, dim: int
                      ) -> tuple[torch.Tensor, torch.Tensor]:
    """``t``'s second difference along ``dim`` at each interior pixel (one shorter at either
    end) and whether ``ok`` holds for all three pixels it reads."""
    n = t.shape[dim]
    before, mid, after = (t.narrow(dim, k, n - 2) for k in range(3))
    both = ok.narrow(dim, 0, n - 2) & ok.narrow(dim, 1, n - 2) & ok.narrow(dim, 2, n - 2)
    return before - 2 * mid + after, both


def pixel_noise(depth: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """(N,) each image's pixel-to-pixel depth noise as sd / z²: the median absolute second
    difference along rows (over three fully valid pixels, relative to z², edges over 5 %
    of z² left out) as a Gaussian's deviation, / sqrt(6) for a second difference of three
    independent pixels. Surfaces are nearly linear over three pixels, so what remains is
    noise; 0 for an image with nothing to measure."""
    second, ok = second_difference(depth, valid > 0.99, 2)
    second = (second / depth[:, :, 1:-1].clamp_min(1e-3) ** 2).abs()
    ok &= second < 0.05
    median = torch.where(ok, second, torch.nan).flatten(1).nanmedian(dim=1).values
    return torch.nan_to_num(median, nan=0.0) * 1.4826 / math.sqrt(6.0)


# A pixel whose inverse depth bends by more than this many deviations of its image's noise
# (the second difference's, sqrt(6) times the pixel noise) sits at a depth edge. A plane's
# inverse depth is affine in the image, so a floor seen at any slant bends by nothing and
# stays blended. On 128 shelf training images 3.7 % of pixels are flagged (2.5 % along
# columns, 2.7 % along rows, whose noise reads alike: median 0.73 and 0.71 deviations);
# Gaussian noise alone would flag fewer than one in 10^8. The limit scales with the noise:
# at the shelf's median a 5 cm step is an edge nearer than about 2.4 m, 2 cm nearer than 1.5 m.
EDGE_SIGMAS = 6.0
# The noise level assumed for an image too clean to measure (a noise-free render), 1/m.
MIN_EDGE_NOISE = 1e-4


def depth_edges(depth: torch.Tensor, valid: torch.Tensor, level: torch.Tensor) -> torch.Tensor:
    """(N, h, w) bool: pixels at a depth edge, where the inverse depth's second difference
    along the row or the column (over three valid pixels) exceeds ``EDGE_SIGMAS`` deviations
    of that difference's noise, sqrt(6) times the image's pixel noise ``level`` ((N,),
    ``pixel_noise``). Both sides of a step are flagged, and the pixels beside a mixed pixel
    inside it."""
    limit = EDGE_SIGMAS * math.sqrt(6.0) * level.clamp_min(MIN_EDGE_NOISE)[:, None, None]
    has = valid > 1e-6
    inverse = torch.where(has, 1 / depth.clamp_min(1e-3), torch.zeros_like(depth))
    edges = torch.zeros_like(has)
    for dim in (1, 2):
        second, ok = second_difference(inverse, has, dim)
        edges.narrow(dim, 1, depth.shape[dim] - 2).logical_or_(ok & (second.abs() > limit))
    return edges


def measure_images(depth: torch.Tensor, valid: torch.Tensor
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """What ``roll_images`` reads off the unturned images: (N,) ``pixel_noise`` and (N, h, w)
    ``depth_edges`` at that noise. About 30 % of a turn's time on a training batch; a
    cached image's are the same at every turn, so the training loop measures them once."""
    noise = pixel_noise(depth, valid)
    return noise, depth_edges(depth, valid, noise)


def roll_images(angles_rad: torch.Tensor, intrinsics: torch.Tensor | None,
                depth: torch.Tensor, valid: torch.Tensor, labels: torch.Tensor,
                nearest: torch.Tensor | None = None, gen: torch.Generator | None = None,
                measured: tuple[torch.Tensor, torch.Tensor] | None = None
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """(N, h, w) depth, valid fraction, labels (long) and optional near-side depths as the
    camera would have seen them rolled by ``angles_rad`` (N,). The intrinsics do not change:
    the turn is about the principal point.

    Depths are interpolated bilinearly among the valid neighbours, except where one of the
    four neighbours is at a depth edge (``depth_edges``): there depth, valid fraction and
    near-side depth take the nearest pixel, as the labels do everywhere. Nearest everywhere
    would turn a sloped floor into steps of half a working pixel's slope (about 5 mm at 2 m,
    three times the sensor's noise there); a blend everywhere adds mixed pixels across every
    object's edge to those the area resize already made (module docstring). With ``gen``
    the noise the blend averaged away is drawn again where it blended (module docstring);
    without it the blended depths keep less noise than the image had. Labels take the
    nearest pixel, so every label stays a label; pixels that come from outside the frame get
    no depth and the ignored label. ``measured``, the images' ``measure_images`` when the
    caller has them at hand (the training loop measures its cached images once), saves
    measuring them again: they depend on nothing but the unturned image."""
    n, h, w = depth.shape
    centre, focal = principal_points(intrinsics, n, h, w)
    columns, rows = source_terms(angles_rad.float(), centre.float(), focal.float(), h, w)
    to_grid = torch.tensor([2 / (w - 1), 2 / (h - 1)])                      # align_corners
    grid = (columns * to_grid - 1) + rows * to_grid
    su, sv = (columns[..., k] + rows[..., k] for k in (0, 1))               # (N, h, w) each
    noise, edges = measured if measured is not None else measure_images(depth, valid)
    has = (valid > 1e-6).float()
    # Every plane turned in one grid_sample per mode: the weights are found once per pixel.
    extra = [] if nearest is None else [nearest]
    blended_planes = [has, depth * has, valid, edges.float()] + [t * has for t in extra]
    nearest_planes = [torch.ones_like(depth), labels.float(), has, depth, valid] + extra
    bilinear = F.grid_sample(torch.stack(blended_planes, 1).float(), grid, mode="bilinear",
                             padding_mode="zeros", align_corners=True)
    nearest_pixel = F.grid_sample(torch.stack(nearest_planes, 1).float(), grid,
                                  mode="nearest", padding_mode="zeros", align_corners=True)
    weight, sharp = bilinear[:, 0], bilinear[:, 3] > 1e-6
    inside = nearest_pixel[:, 0] > 0.5
    labels = torch.where(inside, nearest_pixel[:, 1].round().long(),
                         torch.full_like(labels, IGNORE))
    # Any of the four neighbours at an edge: the whole pixel is taken from the nearest one.
    seen = inside & torch.where(sharp, nearest_pixel[:, 2] > 0.5, weight > 1e-6)
    # The blend's sum of squared weights (all four neighbours counted as valid): 1 on a
    # pixel centre, 1/4 half-way between four; 1 where the nearest pixel is taken.
    fu, fv = su - su.floor(), sv - sv.floor()
    kept = torch.where(sharp, 1.0, ((1 - fu) ** 2 + fu**2) * ((1 - fv) ** 2 + fv**2))
    restore = None
    if gen is not None:
        level = noise[:, None, None] * (1 - kept).clamp_min(0).sqrt()
        restore = level * torch.randn(depth.shape, generator=gen)

    def blend(summed: torch.Tensor, nearest_value: torch.Tensor) -> torch.Tensor:
        blended = summed / weight.clamp_min(1e-6)
        if restore is not None:
            blended = blended + restore * blended**2
        blended = torch.where(sharp, nearest_value, blended)
        return torch.where(seen, blended, torch.zeros_like(blended))

    valid_out = torch.where(sharp, nearest_pixel[:, 4], bilinear[:, 2])
    valid_out = torch.where(seen, valid_out, torch.zeros_like(weight))
    near_out = blend(bilinear[:, 4], nearest_pixel[:, 5]) if nearest is not None else None
    return blend(bilinear[:, 1], nearest_pixel[:, 3]), valid_out, labels, near_out


def draw_roll(n: int, max_deg: float, gen: torch.Generator) -> torch.Tensor:
    """(N,) rolls in radians, U(-max_deg, max_deg) degrees each."""
    return (torch.rand(n, generator=gen) * 2 - 1) * math.radians(max_deg)
