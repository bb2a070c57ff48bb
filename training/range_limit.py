"""The range limit's band, re-drawn on training images at the noise the augmentation gives.

A depth sensor drops every reading beyond its maximum range (``noise.py`` step 6). Near that
range the readings that survive are the ones the noise pulled nearer, so a working pixel
averaged over them reads nearer than the surface, and by more the noisier the sensor: on a
default validation frame whose floor reaches 4 m, the first 12 working rows read 3-54 mm
nearer than the clean floor at the spec's noise and 13-118 mm nearer at twice that noise, a
band of raised "floor" that default model 0.17.0 calls fell_outside in 5 of its 12 mistakes
at the robustness suite's 2x noise point. The augmentation's re-drawn noise
(``redrawn_noise.axial_noise``) is symmetric and cannot make that band; this module makes it.

For a working pixel of depth z covering k full-resolution readings of sd s = c z^2 and a
limit z_max, each reading survives with probability Phi(a), a = (z_max - z) / s, and the
survivors' mean is z - s lambda(a), lambda = phi(a) / Phi(a), with variance
s^2 (1 - a lambda - lambda^2) (the normal distribution truncated above). The survivors are
drawn as Binomial(k, Phi(a)); a pixel none survive in loses its depth. Labels stay the
truth: the band is the sensor's error, not an object (as ``islands.py``'s islands).

Check: frame 4458 of the default validation split rendered at 1x, cut here at its own limit
(4.00 m) with its own far-floor noise doubled (0.0060 z^2), reads 96 / 74 / 48 / 54 / 38 mm
nearer in its first five working rows (valid 0.25-0.69); rendered at the suite's 2x noise
it reads 118 / 84 / 57 / 53 / 37 mm nearer (valid 0.31-0.69).

Where it is rougher than the sensor (as measured in the default run of 2026-12-07; a change
here changes that recipe): the survivors' spread is drawn on top of the noise the working
pixel already carries, so within ``UNTOUCHED_SDS`` of the limit a pixel gets up to s / sqrt(k)
more noise than the sensor would give it (about 1.5x the sd inside the band) and the noise
steps at ``UNTOUCHED_SDS``; there the valid fraction is also rounded to whole readings. The
limit is drawn from the image's own depths with no floor at the spec's range, so on scenes
whose far depths lie well inside it (the tote's, or crops of a scene's near part) it cuts
where no sensor of the spec would: meant for scenes whose far floor reaches the range.
"""

from __future__ import annotations

import math

import torch

from task_outcome_ros.labels import REFERENCE_PIXELS
from training.redrawn_noise import SENSOR_NOISE_PER_Z2

# Where in the image's own depths a limit is drawn: between this quantile of its valid
# depths and its farthest, so the band falls on the far part of the scene, as it does when
# a camera's floor reaches its range.
LIMIT_FROM_QUANTILE = 0.75
QUANTILE_STRIDE = 7
# The full-resolution readings' sd / z^2 on far floors, where the limit falls: the default
# spec's sensors draw their disparity noise per frame (0.03-0.12 px) and grow it at grazing
# angles, and four default validation frames measured 0.0029-0.0062 on floors at 3-4 m
# (robust sd of the 1x render minus the noiseless one), against the 0.0016 of
# ``SENSOR_NOISE_PER_Z2`` measured nearer. Drawn per image from this span.
FAR_NOISE_PER_Z2 = (0.001, 0.0065)
# Beyond this many sds nearer than the limit a reading survives with probability
# 1 - 1e-9: the pixel is left exactly as it was.
UNTOUCHED_SDS = 6.0


def readings_per_pixel(depth: torch.Tensor, size: tuple[int, int] | None) -> float:
    """How many 640 x 480 readings a working pixel of ``depth`` (N, h, w) averages; ``size``
    (h, w) is the whole image's working size when ``depth`` holds crops of it."""
    h, w = size if size is not None else depth.shape[1:]
    return REFERENCE_PIXELS / (h * w)


def draw_limits(depth: torch.Tensor, valid: torch.Tensor, share: float,
                gen: torch.Generator) -> torch.Tensor:
    """(N, 1, 1) a range limit per image (metres), inf for the images left alone: ``share``
    of them get one drawn uniformly between ``LIMIT_FROM_QUANTILE`` of their valid depths
    (every ``QUANTILE_STRIDE``-th one: the draw needs no more) and their farthest. Draws
    2 N uniforms whatever the images hold."""
    n = depth.shape[0]
    chosen = torch.rand(n, generator=gen) < share
    where = torch.rand(n, generator=gen)
    limits = torch.full((n, 1, 1), math.inf)
    for i in torch.nonzero(chosen).flatten().tolist():
        z = depth[i][valid[i] > 0]
        if z.numel():
            low = torch.quantile(z[::QUANTILE_STRIDE].float(), LIMIT_FROM_QUANTILE)
            limits[i] = low + where[i] * (z.max() - low)
    return limits


def truncate_at_limit(depth: torch.Tensor, valid: torch.Tensor, limits: torch.Tensor,
                      noise_per_z2: torch.Tensor, gen: torch.Generator,
                      size: tuple[int, int] | None = None
                      ) -> tuple[torch.Tensor, torch.Tensor]:
    """(depth, valid) of working-size images (N, h, w; metres, 0 where invalid; valid the
    fraction of full-resolution readings) as a sensor with full-resolution noise sd
    ``noise_per_z2`` (N, 1, 1) x z^2 and range ``limits`` (N, 1, 1) would leave them.
    ``size`` (h, w): the whole image's working size when these are crops of it (how many
    readings a working pixel averages). Only the pixels within ``UNTOUCHED_SDS`` of their
    limit change, and only they draw (one binomial and one normal each)."""
    readings = readings_per_pixel(depth, size)
    sd_all = (noise_per_z2 * depth ** 2).clamp_min(1e-6)
    near_limit = (valid > 0) & (limits - depth < UNTOUCHED_SDS * sd_all)
    z, sd = depth[near_limit], sd_all[near_limit]
    a = ((limits.expand_as(depth)[near_limit] - z) / sd).clamp_min(-UNTOUCHED_SDS)
    log_keep = torch.special.log_ndtr(a)
    ratio = torch.exp(-0.5 * a ** 2 - 0.5 * math.log(2 * math.pi) - log_keep)  # phi / Phi
    count = torch.round(valid[near_limit] * readings)
    survivors = torch.binomial(count, log_keep.exp(), generator=gen)
    spread = (1.0 - a * ratio - ratio ** 2).clamp_min(0.0).sqrt() * sd
    jitter = torch.randn(z.shape, generator=gen) * spread / survivors.clamp_min(1.0).sqrt()
    new_depth, new_valid = depth.clone(), valid.clone()
    new_depth[near_limit] = torch.where(survivors > 0, z - sd * ratio + jitter,
                                        torch.zeros_like(z))
    new_valid[near_limit] = survivors / readings
    return new_depth, new_valid


def range_limit_band(depth: torch.Tensor, valid: torch.Tensor, level: torch.Tensor,
                     share: float, gen: torch.Generator,
                     size: tuple[int, int] | None = None
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """``share`` of the images cut at a range limit (``draw_limits``) with the truncation
    their noise gives: a far-floor noise drawn from ``FAR_NOISE_PER_Z2`` grown as the
    re-drawn ``level`` (N, 1, 1; sd / z^2 per working pixel of ``size``,
    ``redrawn_noise.noise_levels``) grows the image's noise: x sqrt(1 + u^2), u the re-drawn
    noise over the sensor's own."""
    n = depth.shape[0]
    redrawn = level * math.sqrt(readings_per_pixel(depth, size)) / SENSOR_NOISE_PER_Z2
    low, high = FAR_NOISE_PER_Z2
    far = low + (high - low) * torch.rand(n, 1, 1, generator=gen)
    limits = draw_limits(depth, valid, share, gen)
    return truncate_at_limit(depth, valid, limits, far * torch.sqrt(1.0 + redrawn ** 2), gen,
                             size)
