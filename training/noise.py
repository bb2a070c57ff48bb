"""Kinect-v1 structured-light depth noise: clean rendered depth in, sensor-like depth out.

The model runs at full resolution, in this order (docs/interface.md §4):

1. **Lateral edge jitter** (Handa et al. 2014, ICL-NUIM; lateral noise as in Nguyen, Izadi &
   Lovell 2012): depth, labels and incidence are resampled at pixel coordinates shifted by
   N(0, ``lateral_sigma_px``) with nearest-neighbour lookup, so labels stay exact and aligned
   with depth. Only the rounded shift matters for a nearest lookup, so the shift is drawn as a
   rounded Gaussian directly (see *Random draws*).
2. **Projector shadows** (the triangulation geometry of Khoshelham & Elberink 2012): the IR
   projector sits ``baseline`` m to the camera's **right** (+x of the optical frame), as on the
   Kinect v1 (seen from the front: projector, RGB camera, IR camera). In the rectified
   camera/projector pair a pixel at column u with disparity d = fx*b/z is lit by projector
   column p(u) = u - d(u). The projector cannot see a pixel's surface point when a pixel nearer
   the projector in the same row (to its right) maps to a smaller projector column, i.e. when
   p(u) > min_{u' > u} p(u') + tol: a running extremum along each row (``np.fmax.accumulate``).
   Shadow bands therefore appear on the **left** edges of foreground objects, as on a Kinect.
3. **Grazing dropout** (Nguyen et al. 2012: no valid returns near 90 degrees): a pixel is
   dropped with probability ramping linearly from 0 at ``grazing_start_deg`` to 1 at
   ``grazing_full_deg``, angle = arccos(cos_incidence).
4. **Axial noise in disparity space** (Khoshelham & Elberink 2012; Handa et al. 2014):
   d = fx*b/z, d += N(0, sigma_d), d is quantised to 1/``disparity_subpixel`` px, z = fx*b/d.
   To first order sigma_z = z^2 sigma_d / (fx b) (:func:`sigma_z`) and one disparity step is
   z^2 / (fx b n) in depth (:func:`quantisation_step`). Near grazing angles sigma_d grows by
   Nguyen's angular term, ``grazing_sigma``/sqrt(z) * theta^2/(pi/2 - theta)^2 metres, converted
   to disparity (theta capped at ``grazing_full_deg`` and at 85 degrees).
   Calibration drift, when the spec asks for it: a per-frame disparity offset
   N(0, ``bias_disparity_px``) and a smooth random field of sd ``lowfreq_disparity_px`` (a
   4 x 3 grid of normals, bicubically upsampled: a few cycles across the image).
5. **Speckle holes**: seeds at rate ``speckle_rate`` per pixel grown to discs of radius
   0..``speckle_max_radius_px`` (one ``cv2.dilate`` per radius).
6. **Range limits**: noisy depth outside [``min_range``, ``max_range``] is invalid.

Invalid pixels are NaN in depth and :data:`~task_outcome_ros.labels.IGNORE` (255) in labels.

Defaults (b = 0.075 m, 1/8 px steps, sigma_d = 0.055 px; fx = 557.5, the middle of the
envelope): noise alone gives sigma_z = 1.3 mm at 1 m, 5.3 mm at 2 m, 11.8 mm at 3 m; with the
1/8 px quantisation (variance step^2/12) the effective spread is 1.6 / 6.3 / 14.2 mm. Nguyen's
fit 0.0012 + 0.0019 (z - 0.4)^2 gives 1.9 / 6.1 / 14.0 mm, and Khoshelham & Elberink report
the random error growing quadratically to ~4 cm at 5 m (this model: 3.9 cm). A pure z^2 model
cannot follow Nguyen's constant term, so it is tuned to the 1.6-3 m range the camera works at.

Random draws: every draw comes from the ``rng`` passed in, in a fixed order, so the same seed
gives the same bytes. Gaussian draws use inverse-CDF lookup of 16-bit uniform integers (a
65,536-entry quantile table, truncated at +-4.3 sigma): ``Generator.standard_normal`` costs
~14 ns a sample on the 2-core target, which alone would take 9 ms of the 15 ms budget.
"""

from __future__ import annotations

import functools
import math
import statistics
from pathlib import Path

import cv2
import numpy as np

from task_outcome_ros.labels import DEFAULT_TABLE, IGNORE, LabelTable, colourise
from training.config import NoiseConfig, StereoConfig

# Projector at +x (camera's right): projector column p = u - PROJECTOR_SIDE * d.
PROJECTOR_SIDE = 1
# A pixel is shadowed only when a nearer pixel hides it by more than this many projector
# columns; absorbs the +-1 px swaps lateral jitter makes on steep (but lit) surfaces.
SHADOW_TOLERANCE_PX = 0.25
# Nguyen's angular term diverges at 90 deg; it is evaluated at most at this angle (and at most
# at grazing_full_deg, beyond which every pixel is dropped anyway).
NGUYEN_MAX_ANGLE_DEG = 85.0

_N_U16 = 1 << 16


@functools.lru_cache(maxsize=1)
def _normal_quantiles() -> np.ndarray:
    """Standard-normal quantiles at (k + 0.5) / 2^16, k = 0..2^16-1 (read-only, float32)."""
    nd = statistics.NormalDist()
    q = np.array([nd.inv_cdf((k + 0.5) / _N_U16) for k in range(_N_U16)], dtype=np.float32)
    q.flags.writeable = False
    return q


@functools.lru_cache(maxsize=8)
def _rounded_shift_table(sigma_px: float) -> np.ndarray:
    """Quantiles of round(N(0, sigma_px)): the pixel shift a nearest-neighbour lookup sees."""
    t = np.rint(np.float32(sigma_px) * _normal_quantiles()).astype(np.float32)
    t.flags.writeable = False
    return t


def _standard_normal(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """float32 N(0, 1) samples by table lookup (truncated at +-4.3 sigma)."""
    return np.take(_normal_quantiles(), rng.integers(0, _N_U16, size=shape, dtype=np.uint16))


def sigma_z(z, fx: float, cfg: NoiseConfig, *, include_quantisation: bool = False
            ) -> np.ndarray:
    """Axial standard deviation (m) of a fronto-parallel surface at range ``z`` (m).

    The first-order disparity model sigma_z = z^2 sigma_d / (fx b) (Khoshelham & Elberink 2012).
    With ``include_quantisation`` the 1/n px rounding is added in quadrature (variance
    step^2 / 12), which is the spread a flat plane actually shows.
    """
    z = np.asarray(z, dtype=np.float64)
    sigma_d = cfg.sigma_disparity_px
    if include_quantisation:
        sigma_d = math.hypot(sigma_d, 1.0 / (cfg.disparity_subpixel * math.sqrt(12.0)))
    return z * z * sigma_d / (fx * cfg.baseline)


def quantisation_step(z, fx: float, cfg: NoiseConfig) -> np.ndarray:
    """Depth difference (m) between neighbouring 1/n px disparity levels at range ``z`` (m)."""
    z = np.asarray(z, dtype=np.float64)
    return z * z / (fx * cfg.baseline * cfg.disparity_subpixel)


def nguyen_sigma_z(z, theta_rad=0.0) -> np.ndarray:
    """Nguyen, Izadi & Lovell 2012 empirical axial sigma (m), for docs and tests."""
    z = np.asarray(z, dtype=np.float64)
    theta = np.asarray(theta_rad, dtype=np.float64)
    return (0.0012 + 0.0019 * (z - 0.4) ** 2
            + 0.0001 / np.sqrt(z) * theta ** 2 / (np.pi / 2 - theta) ** 2)


def apply_kinect_noise(depth: np.ndarray, labels: np.ndarray, cos_incidence: np.ndarray,
                       fx: float, cfg: NoiseConfig, rng: np.random.Generator
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Turn a clean rendered depth image into a Kinect-v1-like one (see the module docstring).

    depth: float32 HxW metres along the optical axis, NaN where the ray hit nothing.
    labels: uint8 HxW class ids (0..4). cos_incidence: float32 HxW, |cos| of the angle between
    the viewing ray and the surface normal (1 = facing the camera, 0 = grazing), NaN/0 where no
    hit (NaN on a hit pixel is read as 1: no dropout). Returns (noisy depth float32 with
    NaN = invalid, labels uint8 with 255 where depth is invalid). Inputs are not modified; every
    random draw comes from ``rng``. With ``cfg.enabled`` False the depth is returned unchanged
    (non-finite or non-positive values still become NaN / 255) and nothing is drawn.
    """
    depth, labels, cos_incidence = _check_inputs(depth, labels, cos_incidence, fx)
    h, w = depth.shape
    fb = np.float32(fx * cfg.baseline)

    if not cfg.enabled:
        z = depth.astype(np.float32, copy=True)
        invalid = ~(np.isfinite(z) & (z > 0))
        z[invalid] = np.nan
        lab = labels.copy()
        lab[invalid] = IGNORE
        return z, lab

    # 1. Lateral edge jitter (Handa et al. 2014): the same integer shift for all three maps.
    if cfg.lateral_sigma_px > 0:
        shift = np.take(_rounded_shift_table(float(cfg.lateral_sigma_px)),
                        rng.integers(0, _N_U16, size=(2, h, w), dtype=np.uint16))
        map_x = shift[0]
        map_x += np.arange(w, dtype=np.float32)
        map_y = shift[1]
        map_y += np.arange(h, dtype=np.float32)[:, None]
        remap = functools.partial(cv2.remap, map1=map_x, map2=map_y,
                                  interpolation=cv2.INTER_NEAREST,
                                  borderMode=cv2.BORDER_REPLICATE)
        z = remap(depth)
        lab = remap(labels)
        cos = remap(cos_incidence)
    else:
        z = depth.copy()
        lab = labels.copy()
        cos = cos_incidence.copy()

    with np.errstate(invalid="ignore", divide="ignore"):
        valid = np.isfinite(z) & (z > 0)
        z[~valid] = np.nan
        disparity = fb / z                                     # px; NaN where no hit

        # 2. Projector shadows.
        valid &= ~projector_shadow(disparity)

        # 3. Grazing dropout; theta also drives Nguyen's angular growth of the axial noise.
        theta = incidence_angle(cos)                           # rad, in cos's memory
        start = np.float32(math.radians(cfg.grazing_start_deg))
        full = np.float32(math.radians(cfg.grazing_full_deg))
        drop_grazing(valid, theta, start, full, rng)

        # 4. Axial noise in disparity space, then 1/n px quantisation.
        sigma_d = np.full((h, w), cfg.sigma_disparity_px, dtype=np.float32)
        if cfg.grazing_sigma > 0:
            th = np.minimum(theta, min(full, np.float32(math.radians(NGUYEN_MAX_ANGLE_DEG))))
            grazing_m = (np.float32(cfg.grazing_sigma) * th * th
                         / ((np.float32(np.pi / 2) - th) ** 2 * np.sqrt(z)))
            sigma_d += grazing_m * disparity / z               # dz -> dd: d(fb/z) = fb/z^2 dz
        noisy = disparity + _standard_normal(rng, (h, w)) * sigma_d
        noisy += calibration_drift((h, w), cfg, rng)
        z_out, matched = quantised_depth(noisy, fb, cfg.disparity_subpixel)
        valid &= matched

        # 5. Speckle holes.
        valid &= ~speckle_holes((h, w), cfg.speckle_rate, cfg.speckle_max_radius_px, rng)

        # 6. Range limits.
        valid &= (z_out >= cfg.min_range) & (z_out <= cfg.max_range)

    z_out[~valid] = np.nan
    lab[~valid] = IGNORE
    return z_out.astype(np.float32, copy=False), lab


def incidence_angle(cos: np.ndarray) -> np.ndarray:
    """The angle (rad) between the viewing ray and the surface normal from |cos| of it,
    computed in place in ``cos`` (pass a copy you own): NaN (no hit, or unknown) reads as
    facing the camera, so it is never dropped as grazing."""
    np.copyto(cos, np.float32(1.0), where=np.isnan(cos))
    return np.arccos(np.clip(np.abs(cos, out=cos), 0.0, 1.0, out=cos), out=cos)


def drop_grazing(valid: np.ndarray, theta: np.ndarray, start: float, full: float,
                 rng: np.random.Generator) -> None:
    """Grazing dropout, in place on ``valid``: a valid pixel whose incidence ``theta`` (rad)
    exceeds ``start`` is dropped with a probability ramping to 1 at ``full`` (Nguyen et al.
    2012); one uniform draw per such pixel, in raster order."""
    candidates = np.flatnonzero(valid & (theta > start))
    if candidates.size:
        t = theta.ravel()[candidates]
        if full > start:
            p_drop = np.clip((t - start) / (full - start), 0.0, 1.0)
        else:
            p_drop = np.ones_like(t)
        dropped = candidates[rng.random(candidates.size, dtype=np.float32) < p_drop]
        valid.ravel()[dropped] = False


def quantised_depth(disparity: np.ndarray, fb: np.float32, subpixel: int
                    ) -> tuple[np.ndarray, np.ndarray]:
    """(depth, positive) of a noisy disparity image quantised to 1 / ``subpixel`` px:
    z = fb / d, and where d stayed positive (elsewhere the depth is meaningless)."""
    n = np.float32(subpixel)
    quantised = np.rint(disparity * n) / n
    return fb / quantised, quantised > 0


def calibration_drift(shape: tuple[int, int], cfg: NoiseConfig | StereoConfig,
                      rng: np.random.Generator) -> np.ndarray | np.float32:
    """Disparity error (px) common to many pixels: a per-frame offset plus a smooth field.
    Draws nothing when both are 0, so specs without drift make the frames they always made."""
    drift = np.float32(0.0)
    if cfg.bias_disparity_px > 0:
        drift = np.float32(rng.normal(0.0, cfg.bias_disparity_px))
    if cfg.lowfreq_disparity_px > 0:
        grid = rng.normal(0.0, cfg.lowfreq_disparity_px, size=(3, 4)).astype(np.float32)
        drift = drift + cv2.resize(grid, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)
    return drift


def projector_shadow(disparity: np.ndarray, tolerance_px: float = SHADOW_TOLERANCE_PX
                     ) -> np.ndarray:
    """Pixels the projector cannot light, from a disparity image (px, NaN = no surface).

    The projector column of pixel u is p(u) = u - d(u) (projector on the camera's right). A
    surface point is hidden from the projector when a pixel to its right in the same row has a
    projector column smaller by more than ``tolerance_px``. Rows are flipped so the projector
    side comes first and q = -p is compared with its running maximum (NaN never occludes).
    """
    h, w = disparity.shape
    u = np.arange(w, dtype=np.float32)
    p = u - PROJECTOR_SIDE * disparity
    q = np.ascontiguousarray(-p[:, ::-1] if PROJECTOR_SIDE > 0 else p)
    running = np.fmax.accumulate(q, axis=1)
    hidden = np.zeros((h, w), dtype=bool)
    with np.errstate(invalid="ignore"):
        hidden[:, 1:] = q[:, 1:] < running[:, :-1] - np.float32(tolerance_px)
    return hidden[:, ::-1] if PROJECTOR_SIDE > 0 else hidden


def speckle_holes(shape: tuple[int, int], rate: float, max_radius_px: int,
                  rng: np.random.Generator) -> np.ndarray:
    """Boolean mask of random disc-shaped holes: seeds at ``rate`` per pixel, radius 0..max."""
    h, w = shape
    n_seeds = int(rng.binomial(h * w, rate)) if rate > 0 else 0
    holes = np.zeros((h, w), dtype=np.uint8)
    if n_seeds == 0:
        return holes.astype(bool)
    seeds = rng.integers(0, h * w, size=n_seeds)
    radii = rng.integers(0, max_radius_px + 1, size=n_seeds)
    for r in range(max_radius_px + 1):
        at_r = seeds[radii == r]
        if at_r.size == 0:
            continue
        seed_mask = np.zeros((h, w), dtype=np.uint8)
        seed_mask.ravel()[at_r] = 1
        if r > 0:
            kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
            seed_mask = cv2.dilate(seed_mask, kernel)
        holes |= seed_mask
    return holes.astype(bool)


def _check_inputs(depth, labels, cos_incidence, fx, who: str = "apply_kinect_noise"
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    depth = np.ascontiguousarray(depth, dtype=np.float32)
    labels = np.ascontiguousarray(labels)
    cos_incidence = np.ascontiguousarray(cos_incidence, dtype=np.float32)
    if depth.ndim != 2:
        raise ValueError(f"{who}: depth must be HxW, got shape {depth.shape}")
    if labels.shape != depth.shape or labels.dtype != np.uint8:
        raise ValueError(f"{who}: labels must be uint8 {depth.shape}, "
                         f"got {labels.dtype} {labels.shape}")
    if cos_incidence.shape != depth.shape:
        raise ValueError(f"{who}: cos_incidence must have shape {depth.shape}, "
                         f"got {cos_incidence.shape}")
    if not (math.isfinite(fx) and fx > 0):
        raise ValueError(f"{who}: fx must be a positive number of pixels, got {fx}")
    return depth, labels, cos_incidence


def save_clean_vs_noisy_figure(path, clean_depth: np.ndarray, noisy_depth: np.ndarray,
                               labels_noisy: np.ndarray, table: LabelTable = DEFAULT_TABLE
                               ) -> None:
    """Clean depth, noisy depth, their difference and the noisy labels, as one PNG.

    Uses the Agg canvas directly (no pyplot state), so it is safe in worker processes.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    clean = np.asarray(clean_depth, dtype=np.float32)
    noisy = np.asarray(noisy_depth, dtype=np.float32)
    finite = clean[np.isfinite(clean)]
    vmin, vmax = (np.percentile(finite, [1, 99]) if finite.size else (0.0, 1.0))
    diff_mm = (noisy - clean) * 1000.0
    both = np.isfinite(diff_mm)
    lim = float(np.percentile(np.abs(diff_mm[both]), 99)) if both.any() else 1.0
    lim = max(lim, 1e-3)
    lost = np.isfinite(clean) & ~np.isfinite(noisy)

    fig = Figure(figsize=(12, 9.5), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(2, 2)
    depth_cmap = _cmap("turbo", bad="black")
    im = axes[0, 0].imshow(clean, cmap=depth_cmap, vmin=vmin, vmax=vmax)
    axes[0, 0].set_title("clean depth (m)")
    fig.colorbar(im, ax=axes[0, 0], shrink=0.8)
    im = axes[0, 1].imshow(noisy, cmap=depth_cmap, vmin=vmin, vmax=vmax)
    axes[0, 1].set_title(f"noisy depth (m), black = invalid ({100 * lost.mean():.1f}% lost)")
    fig.colorbar(im, ax=axes[0, 1], shrink=0.8)
    im = axes[1, 0].imshow(diff_mm, cmap=_cmap("RdBu_r", bad="black"), vmin=-lim, vmax=lim)
    axes[1, 0].set_title("noisy - clean (mm), black = invalid")
    fig.colorbar(im, ax=axes[1, 0], shrink=0.8)
    axes[1, 1].imshow(colourise(labels_noisy, table))
    axes[1, 1].set_title(f"noisy labels, grey = ignore ({IGNORE})")
    for ax in axes.ravel():
        ax.set_axis_off()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)


def _cmap(name: str, bad: str):
    from matplotlib import colormaps

    return colormaps[name].with_extremes(bad=bad)
