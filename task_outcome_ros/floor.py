"""Height above the floor, per pixel, from one depth image (the network's third input channel).

Why: telling ``success`` from ``stuck_on_rim`` means asking whether a box's top is above the
container's rim (CONTRACTS §2) and telling ``fell_outside`` apart means asking whether it lies
on the floor. Both are questions about height above the floor, which a small CNN cannot
easily recover from raw depth when the camera pose changes from image to image (the floor's
depth runs in a different ramp in every view). Depth CNNs commonly get it handed in instead
(Gupta et al. 2014, "HHA" encoding); so do we.

How: back-project the working-size depth with the image's own intrinsics when they are known
(``camera.Intrinsics.normalised``: from camera_info on the robot, from the dataset's camera
records in training), else with the envelope's nominal pinhole camera (fx = fy somewhere in
[525, 590] px at 640 px width, so the centre of that range: a 6 % focal error scales heights
by up to ~6 %, about 1.5 cm at the rim, as much as a near-rim box's whole margin), find the
dominant plane
(the floor fills most of every view in the envelope) by RANSAC over a fixed set of pixel
triples, refine it by least squares on its inliers, and measure every point's signed distance
to it, positive towards the camera.

Deterministic: the triples come from a generator with a fixed seed, so training, evaluation
and the node compute the same heights for the same depth. Torch only, batched: training runs
it on augmented batches and inference on a batch of one.
"""

from __future__ import annotations

import torch

# Nominal focal length over image width: fx in [525, 590] px at 640 px (CONTRACTS §4).
FOCAL_OVER_WIDTH = (525.0 + 590.0) / 2.0 / 640.0
HYPOTHESES = 96               # RANSAC triples; with >= 40 % floor pixels, P(miss) < 1e-6
INLIER_M = 0.015              # plane inlier band (the container's inner floor is 0.02 m up)
SCORE_STRIDE = 3              # score hypotheses on every 3rd pixel per axis (speed)
_SEED = 20141


def backproject(depth: torch.Tensor, focal_over_width: float = FOCAL_OVER_WIDTH,
                intrinsics: torch.Tensor | None = None) -> torch.Tensor:
    """(N, h, w) depth in metres -> (N, h, w, 3) camera-frame points (x right, y down).

    ``intrinsics``: (N, 4) per image, as ``camera.Intrinsics.normalised`` gives them (fx / W,
    fy / H, principal-point offsets from the centre in widths and heights); None: the nominal
    camera, fx = fy = ``focal_over_width`` x w, principal point at the centre."""
    n, h, w = depth.shape
    u = torch.arange(w, dtype=depth.dtype, device=depth.device) - (w - 1) / 2
    v = torch.arange(h, dtype=depth.dtype, device=depth.device) - (h - 1) / 2
    if intrinsics is None:
        f = focal_over_width * w
        x, y = u[None, None, :] / f, v[None, :, None] / f
    else:
        k = intrinsics.to(device=depth.device, dtype=depth.dtype)
        fx, fy = (k[:, 0] * w)[:, None, None], (k[:, 1] * h)[:, None, None]
        cx, cy = (k[:, 2] * w)[:, None, None], (k[:, 3] * h)[:, None, None]
        x, y = (u[None, None, :] - cx) / fx, (v[None, :, None] - cy) / fy
    return torch.stack([depth * x, depth * y, depth.expand(n, h, w)], dim=-1)


def _plane_through(p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(..., 3, 3) point triples -> unit normals (..., 3) and offsets (...): n . x = c."""
    normal = torch.linalg.cross(p[..., 1, :] - p[..., 0, :], p[..., 2, :] - p[..., 0, :])
    length = normal.norm(dim=-1, keepdim=True)
    normal = normal / length.clamp_min(1e-9)
    return normal, (normal * p[..., 0, :]).sum(-1)


def fit_floor(points: torch.Tensor, valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Dominant plane per image: (N, h, w, 3) points, (N, h, w) bool -> normals (N, 3) pointing
    towards the camera and offsets (N,), so that height = points . normal - offset."""
    n, h, w, _ = points.shape
    gen = torch.Generator().manual_seed(_SEED)
    idx = torch.randint(0, h * w, (HYPOTHESES, 3), generator=gen).to(points.device)
    flat_p, flat_v = points.reshape(n, h * w, 3), valid.reshape(n, h * w)
    triples = flat_p[:, idx]                                     # (N, H, 3, 3)
    usable = flat_v[:, idx].all(-1)                              # (N, H)
    normal, offset = _plane_through(triples)
    # Score on a sparse grid of valid pixels: inlier counts within the band.
    sp = points[:, ::SCORE_STRIDE, ::SCORE_STRIDE].reshape(n, -1, 3)
    sv = valid[:, ::SCORE_STRIDE, ::SCORE_STRIDE].reshape(n, -1)
    dist = (torch.einsum("nhc,npc->nhp", normal, sp) - offset[..., None]).abs()
    score = ((dist < INLIER_M) & sv[:, None, :]).sum(-1)
    score = torch.where(usable, score, torch.full_like(score, -1))
    best = score.argmax(1)
    take = torch.arange(n, device=points.device)
    normal, offset = normal[take, best], offset[take, best]
    # Least-squares refinement on all inliers: the normal is the covariance's smallest axis.
    dist = ((flat_p * normal[:, None]).sum(-1) - offset[:, None]).abs()
    weight = ((dist < INLIER_M) & flat_v).to(points.dtype)
    total = weight.sum(1).clamp_min(1.0)
    centre = (flat_p * weight[..., None]).sum(1) / total[:, None]
    centred = (flat_p - centre[:, None]) * weight[..., None].sqrt()
    cov = centred.transpose(1, 2) @ centred / total[:, None, None]
    refined = torch.linalg.eigh(cov.double()).eigenvectors[..., 0].to(points.dtype)
    ok = (weight.sum(1) >= 3)[:, None]
    normal = torch.where(ok, refined, normal)
    offset = torch.where(ok[:, 0], (normal * centre).sum(-1), offset)
    # Orient towards the camera (the origin): the camera's own height must be positive.
    flip = (-offset < 0)[:, None]
    return torch.where(flip, -normal, normal), torch.where(flip[:, 0], -offset, offset)


def height_above_floor(depth: torch.Tensor, valid: torch.Tensor,
                       focal_over_width: float = FOCAL_OVER_WIDTH,
                       intrinsics: torch.Tensor | None = None) -> torch.Tensor:
    """(N, h, w) depth (metres) and validity (bool) -> (N, h, w) height in metres; 0 where
    invalid, and everywhere in an image with fewer than three valid pixels. ``intrinsics``:
    see ``backproject``."""
    points = backproject(depth.float(), focal_over_width, intrinsics)
    normal, offset = fit_floor(points, valid)
    height = (points * normal[:, None, None]).sum(-1) - offset[:, None, None]
    return torch.where(valid, height, torch.zeros_like(height))
