"""Height above the floor, per pixel, from one depth image (the network's third input channel).

Why: telling ``success`` from ``stuck_on_rim`` means asking whether a box's top is above the
container's rim (docs/interface.md §2) and telling ``fell_outside`` apart means asking
whether it lies on the floor. Both are questions about height above the floor, which a small
CNN cannot easily recover from raw depth when the camera pose changes from image to image (the
floor's depth runs in a different ramp in every view). Depth CNNs commonly get it handed in instead
(Gupta et al. 2014, "HHA" encoding); so do we.

How: back-project the working-size depth with the image's own intrinsics when they are known
(``camera.Intrinsics.normalised``: from camera_info on the robot, from the dataset's camera
records in training), else with the envelope's nominal pinhole camera (fx = fy somewhere in
[525, 590] px at 640 px width, so the centre of that range: a 6 % focal error scales heights
by up to ~6 %, about 1.5 cm at the rim, as much as a near-rim box's whole margin), find the
floor by RANSAC over pixel triples, refine it by least squares on its inliers, and measure
every point's signed distance to it, positive towards the camera.

The floor is not simply the dominant plane: the container's inner floor lies parallel to it
only 0.02 m up and can fill as much of the view. Fit version 1 (models up to 0.1.7)
drew triples among all pixels, kept the plane with the most inliers within 0.015 m, and so
often settled on a plane tilted through both floors: on 500 validation images the rim came
out 2.3 mm low on average, more than 3 mm off in 128 of them and up to 24 mm off, while a
near-rim box's whole margin is millimetres. Version 2 draws triples among valid pixels only
(in far-floor views most pixels are invalid and few triples landed on the floor), narrows the
band to 0.008 m (2 sd of the working-size noise at 3.25 m) and scores a plane by its inliers
minus the points beneath it (nothing lies beneath the floor; a tilted plane has one floor
half under it). On the same images and 500 of the seed-1 set, no image is off by more than
0.14 mm, and leaving out any one of the three changes leaves images 17-23 mm off or many
over 3 mm (``bench/heights.py`` repeats the check on 200 validation images). Checkpoints
record their version (``model`` normalisation ``floor_fit``); older ones keep version 1.
Version 2 scores on a sparser grid in one float pass, so it also costs less than version 1.

**Fixtures on a table.** With a table and the room floor below it in view, the lowest plane
is the room floor, and heights from it would put the rim 0.7 m higher in some frames than in
others. A checkpoint trained on such a task records ``support_above_floor``, the table-top
heights its spec draws; the fit then looks again, among the points whose height above the
first plane lies in that band (+-5 cm), for the plane the fixture stands on, and uses it when
it holds at least ``SUPPORT_MIN_SHARE`` of the valid points. Without a room floor in view the
first plane already is the table top and nothing lies in the band.

**Walls.** A shelf hung on a wall puts the wall in front of the camera, up to two thirds of
the frame and nothing beneath it: version 2 took it for the floor in 42 of 150 validation
views of the shelf task (every one wall-mounted), so heights there were distances from the
wall. Version 3 (new checkpoints) keeps only planes facing up in the image
(``MAX_SUPPORT_NORMAL_Y``) and draws 128 triples instead of 96: on 400 such views it finds
the floor in every one (within 0.2 degrees). On 200 default and 200 tote renders it finds
the support within 1.8 degrees in every one, where version 2 took a wall once (a tote view,
89 degrees off); with 96 triples that view still came out 31 degrees off. Checkpoints keep
the version they were trained on.

Deterministic: the triples come from a generator with a fixed seed, so training, evaluation
and the node compute the same heights for the same depth. Batched torch: training runs it on
augmented batches and inference on a batch of one. Two steps go through numpy on the CPU,
where a batch of one spent most of its time in torch's per-operation overhead: counting each
hypothesis's votes (exact integers, so the same plane is chosen) and the least-squares refit
on the chosen plane's inliers (float64, image by image). Against the float32 torch refit
before it (package 0.16.0), heights moved by at most 0.08 mm on 600 run frames and the
shipped models' validation answers did not change; one frame's fit costs about 60 % of what
it did (``bench/revision.py`` times the whole ``segment()`` against an older revision).
"""

from __future__ import annotations

import numpy as np
import torch

# Nominal focal length over image width: fx in [525, 590] px at 640 px (docs/interface.md §4).
FOCAL_OVER_WIDTH = (525.0 + 590.0) / 2.0 / 640.0
# Triples per version; a floor on >= 44 % of the valid pixels: P(no floor triple) < 3e-4 at
# 96. Version 3 draws 128, for views where a wall or a table takes most of the frame.
HYPOTHESES = {1: 96, 2: 96, 3: 128}
_SCORE_STRIDE = {1: 3, 2: 4, 3: 4}  # score hypotheses on every k-th pixel per axis (speed)
_SEED = 20141
FLOOR_FIT = 3                 # the fit new checkpoints are trained on (see above)
LEGACY_FLOOR_FIT = 1          # checkpoints that do not record one
FLOOR_FITS = (1, 2, 3)
_INLIER_M = {1: 0.015, 2: 0.008, 3: 0.008}   # plane inlier band per version
# Version 3: the support faces up in the image. Oriented towards the camera, a floor's normal
# has image-y component -cos(roll) cos(elevation) (y points down in the image), a wall facing
# the camera +sin(elevation). Planes whose normal points further down the image than this are
# walls, never the support; it admits straight-down views (0) with several degrees of tilt.
MAX_SUPPORT_NORMAL_Y = 0.26   # sin 15 deg
SUPPORT_MARGIN_M = 0.05       # around a table-top band (support_above_floor)
SUPPORT_MIN_SHARE = 0.10      # of the valid points, for a table top to count as seen
# heights_beneath_support: points this far below the table top are measured from the room
# floor (every object a spec drops is under 0.3 m, a table 0.7 m or more); and the room
# floor's level needs this share of the image's pixels in view.
BENEATH_SUPPORT_M = 0.05
BENEATH_MIN_SHARE = 50 / (160 * 120)   # of the image's pixels: 50 at the 160 x 120 working size


def backproject(depth: torch.Tensor, focal_over_width: float = FOCAL_OVER_WIDTH,
                intrinsics: torch.Tensor | None = None) -> torch.Tensor:
    """(N, h, w) depth in metres -> (N, h, w, 3) camera-frame points (x right, y down).

    ``intrinsics``: (N, 4) per image, as ``camera.Intrinsics.normalised`` gives them (fx / W,
    fy / H, principal-point offsets from the centre in widths and heights); None: the nominal
    camera, fx = fy = ``focal_over_width`` x w, principal point at the centre."""
    n, h, w = depth.shape
    u = torch.arange(w, dtype=depth.dtype, device=depth.device)[None, None, :]
    v = torch.arange(h, dtype=depth.dtype, device=depth.device)[None, :, None]
    if intrinsics is not None:
        intrinsics = intrinsics.to(device=depth.device, dtype=depth.dtype)
    x, y = pixel_rays(u, v, (w, h), focal_over_width, intrinsics)
    # Written into place: torch.stack along the last axis costs three times as much.
    points = torch.empty((n, h, w, 3), dtype=depth.dtype, device=depth.device)
    torch.mul(depth, x, out=points[..., 0])
    torch.mul(depth, y, out=points[..., 1])
    points[..., 2] = depth
    return points


def pixel_rays(u: torch.Tensor, v: torch.Tensor, size: tuple[int, int],
               focal_over_width: float = FOCAL_OVER_WIDTH,
               intrinsics: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The rays (x / z, y / z) through pixel columns ``u`` and rows ``v`` (any shapes that
    broadcast against (N, 1, 1), fractional pixels allowed) of an image of ``size`` (w, h),
    for ``backproject``'s camera (``intrinsics`` (N, 4) or the nominal one)."""
    w, h = size
    u, v = u - (w - 1) / 2, v - (h - 1) / 2
    if intrinsics is None:
        f = focal_over_width * w
        return u / f, v / f
    k = intrinsics
    fx, fy = (k[:, 0] * w)[:, None, None], (k[:, 1] * h)[:, None, None]
    cx, cy = (k[:, 2] * w)[:, None, None], (k[:, 3] * h)[:, None, None]
    return (u - cx) / fx, (v - cy) / fy


def _plane_through(p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(..., 3, 3) point triples -> unit normals (..., 3) and offsets (...): n . x = c."""
    normal = torch.linalg.cross(p[..., 1, :] - p[..., 0, :], p[..., 2, :] - p[..., 0, :])
    length = normal.norm(dim=-1, keepdim=True)
    normal = normal / length.clamp_min(1e-9)
    return normal, (normal * p[..., 0, :]).sum(-1)


def fit_floor(points: torch.Tensor, valid: torch.Tensor, version: int = FLOOR_FIT,
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """Floor plane per image: (N, h, w, 3) points, (N, h, w) bool -> normals (N, 3) pointing
    towards the camera and offsets (N,), so that height = points . normal - offset.
    ``version``: which fit (module docstring)."""
    if version not in _INLIER_M:
        raise ValueError(f"unknown floor fit version {version!r}; known: {sorted(_INLIER_M)}")
    inlier_m = _INLIER_M[version]
    hypotheses = HYPOTHESES[version]
    n, h, w, _ = points.shape
    flat_p, flat_v = points.reshape(n, h * w, 3), valid.reshape(n, h * w)
    gen = torch.Generator().manual_seed(_SEED)
    if version == 1:
        idx = torch.randint(0, h * w, (hypotheses, 3), generator=gen).to(points.device)
        idx = idx[None].expand(n, -1, -1)
    else:
        # Fixed uniform draws pick ranks among each image's valid pixels (1-based).
        draws = torch.rand((hypotheses * 3,), generator=gen, dtype=torch.float64)
        running = flat_v.cumsum(1)                               # valid pixels so far
        rank = (draws.to(points.device)[None] * running[:, -1:]).long() + 1
        idx = torch.searchsorted(running, rank).clamp_max(h * w - 1).reshape(n, hypotheses, 3)
    take = torch.arange(n, device=points.device)
    triples = flat_p[take[:, None, None], idx]                   # (N, H, 3, 3)
    usable = flat_v[take[:, None, None], idx].all(-1)            # (N, H)
    normal, offset = _plane_through(triples)
    # Orient every hypothesis towards the camera (the origin): "beneath" is then height < 0.
    flip = offset > 0
    normal = torch.where(flip[..., None], -normal, normal)
    offset = torch.where(flip, -offset, offset)
    # Score on a sparse grid of valid pixels; the others are NaN, which no band holds.
    stride = _SCORE_STRIDE[version]
    sp = points[:, ::stride, ::stride].reshape(n, -1, 3)
    sv = valid[:, ::stride, ::stride].reshape(n, -1, 1)
    sp = torch.where(sv, sp, torch.tensor(float("nan"), dtype=sp.dtype, device=sp.device))
    signed = torch.einsum("nhc,npc->nhp", normal, sp) - offset[..., None]
    score = _plane_scores(signed, inlier_m, version).to(points.dtype)
    if version >= 3:  # a wall is never the support
        usable = usable & (normal[..., 1] <= MAX_SUPPORT_NORMAL_Y)
    score = torch.where(usable, score, torch.full_like(score, -float("inf")))
    best = score.argmax(1)
    normal, offset = _refine(flat_p, flat_v, normal[take, best], offset[take, best], inlier_m)
    # Orient towards the camera (the origin): the camera's own height must be positive.
    flip = (-offset < 0)[:, None]
    return torch.where(flip, -normal, normal), torch.where(flip[:, 0], -offset, offset)


def _plane_scores(signed: torch.Tensor, inlier_m: float, version: int) -> torch.Tensor:
    """(N, H, P) signed distances of the scored points to each hypothesis (NaN: not scored) ->
    (N, H) integer scores. Version 1: the points within the band. Later versions: +1 per
    point within the band, -1 per point beneath it (nothing lies beneath the floor), which is
    [s < band] - 2 [s < -band]. Counts are exact, so every way of counting picks the same
    plane; on the CPU numpy counts a 128 x 1,200 block in about a fifth of the time of torch's
    compare, convert and sum."""
    if version == 1:
        inside = signed.abs() < inlier_m
        return inside.sum(-1)
    if signed.device.type == "cpu":
        s = signed.detach().numpy()
        # Each point's vote as int8 (-1, 0, +1) from the two comparisons' bytes, summed in
        # int32: half the time of count_nonzero along an axis.
        votes = (s < inlier_m).view(np.int8) - 2 * (s < -inlier_m).view(np.int8)
        return torch.from_numpy(votes.sum(-1, dtype=np.int32))
    return (signed < inlier_m).sum(-1) - 2 * (signed < -inlier_m).sum(-1)


def _refine(flat_p: torch.Tensor, flat_v: torch.Tensor, normal: torch.Tensor,
            offset: torch.Tensor, inlier_m: float) -> tuple[torch.Tensor, torch.Tensor]:
    """One least-squares pass on the plane's inliers: the normal is their covariance's smallest
    axis (kept on the incoming normal's side); an image with under three inliers keeps its
    plane.

    In numpy, image by image, on the inliers only and in float64: a few small array calls on
    a few thousand points cost about a fifth of the masked float32 sums over every pixel
    that torch made of it (0.18 against 0.9 ms a 160 x 120 image, one core), and float64 is
    the more exact of the two. Other devices hand the points over to the CPU for it."""
    points = flat_p.detach().cpu().numpy()
    valid = flat_v.detach().cpu().numpy()
    normals = normal.detach().cpu().numpy().astype(np.float64)
    offsets = offset.detach().cpu().numpy().astype(np.float64)
    for i, (p, v) in enumerate(zip(points, valid)):
        inlier = v & (np.abs(p @ normals[i].astype(np.float32) - np.float32(offsets[i]))
                      < inlier_m)
        # (3, k) contiguous float64: numpy reduces along contiguous rows far faster.
        q = np.array(np.compress(inlier, p, axis=0).T, dtype=np.float64, order="C")
        if q.shape[1] < 3:
            continue
        centre = q.sum(1) / q.shape[1]
        q -= centre[:, None]
        refined = np.linalg.eigh(q @ q.T)[1][:, 0]   # the smallest axis (ascending order)
        if refined @ normals[i] < 0:
            refined = -refined
        normals[i], offsets[i] = refined, refined @ centre
    return (torch.from_numpy(normals).to(normal), torch.from_numpy(offsets).to(offset))


def support_plane(points: torch.Tensor, valid: torch.Tensor, version: int = FLOOR_FIT,
                  support_above_floor: tuple[float, float] | None = None,
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """The plane heights are measured from, per image: (N, 3) normals and (N,) offsets.

    The floor (``fit_floor``), or with ``support_above_floor`` the table top above it when
    that is seen (module docstring)."""
    normal, offset = fit_floor(points, valid, version)
    if support_above_floor is None:
        return normal, offset
    lo, hi = support_above_floor
    height = _distances(points, normal, offset)
    band = valid & (height > lo - SUPPORT_MARGIN_M) & (height < hi + SUPPORT_MARGIN_M)
    seen = band.sum((1, 2)) >= SUPPORT_MIN_SHARE * valid.sum((1, 2)).clamp_min(1)
    if not bool(seen.any()):
        return normal, offset
    top_normal, top_offset = fit_floor(points, band, version)
    return (torch.where(seen[:, None], top_normal, normal),
            torch.where(seen, top_offset, offset))


def _distances(points: torch.Tensor, normal: torch.Tensor, offset: torch.Tensor
               ) -> torch.Tensor:
    """(N, h, w, 3) points, planes (N, 3), (N,) -> (N, h, w) signed distances (one matrix
    product: less than half the time of a product and a sum over the last axis)."""
    n, h, w, _ = points.shape
    along = points.reshape(n, h * w, 3) @ normal[:, :, None].to(points.dtype)
    return along.reshape(n, h, w) - offset[:, None, None]


def height_above_floor(depth: torch.Tensor, valid: torch.Tensor,
                       focal_over_width: float = FOCAL_OVER_WIDTH,
                       intrinsics: torch.Tensor | None = None,
                       version: int = FLOOR_FIT,
                       support_above_floor: tuple[float, float] | None = None,
                       tracker: FloorTracker | None = None,
                       nearest: torch.Tensor | None = None,
                       ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """(N, h, w) depth (metres) and validity (bool) -> (N, h, w) height in metres; 0 where
    invalid, and everywhere in an image with fewer than three valid pixels. ``intrinsics``:
    see ``backproject``; ``version``: see ``fit_floor``; ``support_above_floor``: the (min,
    max) height of a table top above the room floor, to measure from the table when both are
    in view (module docstring). ``tracker`` (one image only): reuse the previous frame's
    plane while it still fits (``FloorTracker``). ``nearest``: a second (N, h, w) depth of
    the same pixels (``model.nearest_depth``), measured from the same plane; then the answer
    is (heights, heights of ``nearest``)."""
    points = backproject(depth.float(), focal_over_width, intrinsics)
    if tracker is None:
        normal, offset = support_plane(points, valid, version, support_above_floor)
    else:
        key = (tuple(depth.shape), focal_over_width, version,
               None if intrinsics is None else tuple(intrinsics.flatten().tolist()),
               None if support_above_floor is None else tuple(support_above_floor))
        normal, offset = tracker.plane(points, valid, key, version, support_above_floor)
    height = _distances(points, normal, offset)
    height = torch.where(valid, height, torch.zeros_like(height))
    if nearest is None:
        return height
    near = _distances(backproject(nearest.float(), focal_over_width, intrinsics), normal, offset)
    return height, torch.where(valid, near, torch.zeros_like(near))


def heights_beneath_support(height: torch.Tensor, valid: torch.Tensor,
                            support_above_floor: tuple[float, float]) -> torch.Tensor:
    """(N, h, w) heights from a table top (``height_above_floor`` with
    ``support_above_floor``) -> the same, except that what lies more than
    ``BENEATH_SUPPORT_M`` below the table top is measured from the room floor beneath it.

    Why: the local relief (``relief.local_relief``) reads an object's height above the
    morphological opening of the heights around it, and an object on the room floor seen
    beside the table top, which stands 0.7 m higher, is part of a surface the opening fits
    in (a window over the object, the table's edge and the table holds no lower point): it
    reads no relief. Tote model 0.15.0 missed 55 of the 130 small fallen objects lying on
    the room floor in its first 4,000 training images, and 62 % of those it missed read
    under 5 cm of relief (3 % of those it found). Measured from the floor beneath it, the
    same object stands above the table top beside it, and reads its height like one on the
    table. The room floor's level is each image's median height among the points lower than
    the spec's lowest table less ``SUPPORT_MARGIN_M``; with fewer than ``BENEATH_MIN_SHARE``
    of the image's pixels there (no room floor in view), the heights are returned as they
    are. What lies below the table top but more than half the lowest table height above the
    floor is the table's own side (or a pixel mixing it with the floor) and reads 0, as the
    table top does; lower down, the table's side and legs read like something standing on
    the floor, up to that half height. The floor and the table top are taken parallel, as the
    specs draw them (one tilt for the whole scene)."""
    floor_band = valid & (height < -(support_above_floor[0] - SUPPORT_MARGIN_M))
    floor_seen = floor_band.sum((1, 2)) >= BENEATH_MIN_SHARE * height.shape[1] * height.shape[2]
    levels = torch.zeros(height.shape[0], dtype=height.dtype, device=height.device)
    for i in torch.nonzero(floor_seen).flatten().tolist():
        levels[i] = height[i][floor_band[i]].median()
    beneath = valid & (height < -BENEATH_SUPPORT_M) & floor_seen[:, None, None]
    above_floor = height - levels[:, None, None]
    # Higher above the floor than half the lowest table: the table's side, or a pixel mixing
    # it with the floor, not something standing on the floor; read as the table top's own.
    on_floor = above_floor < support_above_floor[0] / 2
    return torch.where(beneath, torch.where(on_floor, above_floor, torch.zeros_like(height)),
                       height)


class FloorTracker:
    """Static cameras: keep one frame's support plane for the next frames while it still fits.

    A cell's camera rarely moves, and the RANSAC fit is about half of preprocessing. Each new
    frame checks the kept plane on ``CHECK_POINTS`` fixed pixels: it is kept while the share
    of them within the inlier band stays at least ``KEEP_SHARE`` of its share at fit time and
    almost none lie beneath it (nothing lies beneath the floor). A camera that moves or tilts
    by more than the band (8 mm) loses most inliers, so it refits; new intrinsics, another
    image size or another fit configuration refit at once. Objects arriving on the floor
    cover a few of the checked pixels, which the slack allows for. One image at a time (the
    node's frames); ``last`` says what the latest call did ("kept" or "fitted"; callers may
    clear it to None before a frame), ``reused`` and ``refits`` count what happened.
    """

    CHECK_POINTS = 400
    KEEP_SHARE = 0.8
    MAX_BENEATH_GAIN = 0.02   # beneath share may grow this much over its share at fit time

    def __init__(self) -> None:
        self._key: tuple | None = None
        self._plane: tuple[torch.Tensor, torch.Tensor] | None = None
        self._at_fit: tuple[float, float] = (0.0, 0.0)   # (inlier, beneath) shares
        self._pixels: torch.Tensor | None = None       # flat indices, drawn per size
        self.reused = 0
        self.refits = 0
        self.last: str | None = None

    def reset(self) -> None:
        """Forget the plane: the next frame is fitted afresh."""
        self._key = self._plane = None

    def plane(self, points: torch.Tensor, valid: torch.Tensor, key: tuple, version: int,
              support_above_floor: tuple[float, float] | None,
              ) -> tuple[torch.Tensor, torch.Tensor]:
        if points.shape[0] != 1:
            raise ValueError(f"FloorTracker takes one image at a time, got {points.shape[0]}")
        if self._plane is not None and key == self._key:
            inlier, beneath = self._shares(points, valid, *self._plane, version)
            fit_inlier, fit_beneath = self._at_fit
            if (inlier >= self.KEEP_SHARE * fit_inlier
                    and beneath <= fit_beneath + self.MAX_BENEATH_GAIN):
                self.reused += 1
                self.last = "kept"
                return self._plane
        normal, offset = support_plane(points, valid, version, support_above_floor)
        if key != self._key or self._pixels is None:   # fixed check pixels for this size
            gen = torch.Generator().manual_seed(_SEED + 1)
            self._pixels = torch.randint(0, valid.numel(), (self.CHECK_POINTS,),
                                         generator=gen).to(points.device)
        self._key, self._plane = key, (normal, offset)
        self._at_fit = self._shares(points, valid, normal, offset, version)
        self.refits += 1
        self.last = "fitted"
        return normal, offset

    def _shares(self, points: torch.Tensor, valid: torch.Tensor, normal: torch.Tensor,
                offset: torch.Tensor, version: int) -> tuple[float, float]:
        """(inlier, beneath) shares of the checked pixels with valid depth."""
        flat_p, flat_v = points.reshape(-1, 3), valid.reshape(-1)
        ok = flat_v[self._pixels]
        count = int(ok.sum())
        if count == 0:
            return 0.0, 0.0
        signed = flat_p[self._pixels][ok] @ normal[0] - offset[0]
        band = _INLIER_M[version]
        return (float((signed.abs() < band).sum()) / count,
                float((signed < -band).sum()) / count)
