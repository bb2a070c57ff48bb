"""Stage 3: render one depth image per episode from a random camera in the envelope, with exact
per-pixel labels, then apply the sensor noise model.

The scene is nothing but boxes and cylinders on a plane, so instead of a general rasteriser
the renderer ray-casts analytically: a slab test per box, a quadric and two caps per cylinder,
each evaluated only inside the shape's projected bounding rectangle. Measured on a 2-core
machine this is ~10x faster than pybullet's TinyRenderer at 640 x 480 (~65 ms), and it gives
exact depth, labels and surface normals (the noise model needs the incidence angle) from one
pass, so labels cannot drift from depth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from task_outcome_ros.camera import Intrinsics
from task_outcome_ros.labels import (
    BACKGROUND,
    LabelTable,
    outcome_pixel_counts,
    outcomes_present,
)
from training.chunks import load_chunks, run_chunks
from training.config import (
    NOISE_PARAMETERS,
    STEREO_PARAMETERS,
    TOF_PARAMETERS,
    CameraConfig,
    DatasetConfig,
    SceneConfig,
)
from training.fixture import PlacedFixture, _uniform, episode_fixture, euler_rotation
from training.geometry import quat_to_matrix
from training.noise import apply_kinect_noise
from training.scenery import draw_neighbours
from training.seeding import drawn_in_share, episode_rng, episode_seed
from training.stereo import STEREO_MODEL, apply_stereo_noise
from training.tof import apply_tof_noise

NEAR = 0.05  # m: hits closer than this to the camera are ignored


@dataclass(frozen=True)
class Camera(Intrinsics):
    """A pinhole camera: the intrinsics camera_info would carry (``camera.Intrinsics``) and
    the pose of its optical frame (x right, y down, z fwd)."""

    position: np.ndarray      # (3,) world
    rotation: np.ndarray      # (3, 3) columns = optical x, y, z axes in world

    def to_dict(self) -> dict:
        return {"width": self.width, "height": self.height, "fx": self.fx, "fy": self.fy,
                "cx": self.cx, "cy": self.cy, "position": self.position.tolist(),
                "rotation": self.rotation.tolist()}


def look_at(position: np.ndarray, target: np.ndarray, azimuth_deg: float = 0.0,
            roll_deg: float = 0.0) -> np.ndarray:
    """Rotation whose columns are the optical frame axes for a camera at ``position`` looking at
    ``target``, image x horizontal, then turned by ``roll_deg`` about the optical axis. Looking
    straight down, "horizontal" is the limit from below: perpendicular to the azimuth."""
    forward = target - position
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    length = np.linalg.norm(right)
    if length < 1e-9:
        az = math.radians(azimuth_deg)
        right = np.array([-math.sin(az), math.cos(az), 0.0])
    else:
        right /= length
    down = np.cross(forward, right)
    if roll_deg:
        c, s = math.cos(math.radians(roll_deg)), math.sin(math.radians(roll_deg))
        right, down = c * right + s * down, -s * right + c * down
    return np.stack([right, down, forward], axis=1)


def draw_camera(cam: CameraConfig, fixture: PlacedFixture,
                rng: np.random.Generator) -> tuple[Camera, dict]:
    """A camera from the envelope (docs/interface.md §4); returns it and its draws (manifest)."""
    f = float(rng.uniform(*cam.focal_px))
    cx = (cam.width - 1) / 2 + float(rng.uniform(-cam.principal_offset_px,
                                                 cam.principal_offset_px))
    cy = (cam.height - 1) / 2 + float(rng.uniform(-cam.principal_offset_px,
                                                  cam.principal_offset_px))
    distance = float(rng.uniform(*cam.distance))
    elevation = float(rng.uniform(*cam.elevation_deg))
    azimuth = float(rng.uniform(*cam.azimuth_deg))
    if cam.azimuth_frame == "fixture":
        azimuth += math.degrees(fixture.yaw)
    # Look-at point uniform in a ball of radius target_offset around the fixture's aim point.
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    radius = cam.target_offset * float(rng.uniform()) ** (1 / 3)
    target = fixture.centre() + radius * direction
    # Drawn last, and only when it varies, so envelopes without roll draw what they always did.
    roll = _uniform(rng, cam.roll_deg)
    el, az = math.radians(elevation), math.radians(azimuth)
    position = target + distance * np.array([math.cos(el) * math.cos(az),
                                             math.cos(el) * math.sin(az), math.sin(el)])
    rotation = look_at(position, target, azimuth, roll)
    if fixture.tilt_deg:  # into the support's frame, where the scene is: it looks tilted
        tilt = fixture.tilt_rotation()
        pivot = fixture.centre()
        position = pivot + tilt.T @ (position - pivot)
        target = pivot + tilt.T @ (target - pivot)
        rotation = tilt.T @ rotation
    camera = Camera(cam.width, cam.height, f, f, cx, cy, position, rotation)
    draws = {"distance": distance, "elevation_deg": elevation, "azimuth_deg": azimuth,
             "roll_deg": roll, "look_at": target.tolist()}
    return camera, draws


@dataclass
class SceneBox:
    """A solid in the scene: a box, or a cylinder along its local z (``cylinder`` True, radius
    ``half_extents[0]``, half height ``half_extents[2]``)."""

    half_extents: np.ndarray  # (3,)
    centre: np.ndarray        # (3,) world
    rotation: np.ndarray      # (3, 3) shape axes in world
    label: int
    cylinder: bool = False


def scene_boxes(episode: dict, outcomes: list[str], scene: SceneConfig,
                table: LabelTable) -> list[SceneBox]:
    """The fixture's solids, the room's (a wall), the table, and the objects, each with its
    pixel label (``table`` gives the outcomes' ids)."""
    fixture = episode_fixture(episode, scene)
    rot = fixture.rotation
    base = np.array([fixture.x, fixture.y, fixture.base_z])
    boxes = [SceneBox(np.array(h), rot @ np.array(p) + base, rot @ euler_rotation(turn), label)
             for label, (h, p, turn) in fixture.labelled_boxes()]
    ids = table.outcome_ids
    if fixture.table is not None:  # the support: background, like the room floor
        half, centre = fixture.table.box()
        boxes.append(SceneBox(np.array(half), np.array(centre), rot, BACKGROUND))
    for obj, outcome in zip(episode["objects"], outcomes):
        boxes.append(SceneBox(np.array(obj["size"]) / 2, np.array(obj["position"]),
                              quat_to_matrix(obj["orientation"]), ids[outcome],
                              cylinder=obj.get("shape", "box") == "cylinder"))
    return boxes


def _pixel_rays(camera: Camera) -> np.ndarray:
    """World direction of every pixel's ray as (3, H, W), scaled so its optical-axis component
    is 1 (so the ray parameter t is the depth along the optical axis). Channel-first keeps each
    component contiguous for the per-axis slab arithmetic below."""
    u = (np.arange(camera.width, dtype=np.float32) - camera.cx) / camera.fx
    v = (np.arange(camera.height, dtype=np.float32) - camera.cy) / camera.fy
    r = camera.rotation.astype(np.float32)
    return np.stack([r[k, 0] * u[None, :] + r[k, 1] * v[:, None] + r[k, 2] for k in range(3)])


def _box_rectangle(box: SceneBox, camera: Camera) -> tuple[int, int, int, int] | None:
    """Pixel rectangle (v0, v1, u0, u1) covering the box's projection; None if off-screen."""
    signs = np.array([[a, b, c] for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)], float)
    corners = (signs * box.half_extents) @ box.rotation.T + box.centre
    local = (corners - camera.position) @ camera.rotation
    if np.any(local[:, 2] <= NEAR):  # straddles the camera plane: test the whole image
        return 0, camera.height, 0, camera.width
    u = camera.fx * local[:, 0] / local[:, 2] + camera.cx
    v = camera.fy * local[:, 1] / local[:, 2] + camera.cy
    u0, u1 = max(0, int(math.floor(u.min()))), min(camera.width, int(math.ceil(u.max())) + 1)
    v0, v1 = max(0, int(math.floor(v.min()))), min(camera.height, int(math.ceil(v.max())) + 1)
    if u0 >= u1 or v0 >= v1:
        return None
    return v0, v1, u0, u1


def render(boxes: list[SceneBox], floor_z: float, camera: Camera
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Clean depth (float32 m along the optical axis, NaN = no hit), labels (uint8) and the
    |cosine| of the incidence angle of every pixel."""
    rays = _pixel_rays(camera)
    norm = np.sqrt(rays[0] ** 2 + rays[1] ** 2 + rays[2] ** 2)
    depth = np.full((camera.height, camera.width), np.inf, np.float32)
    labels = np.full((camera.height, camera.width), BACKGROUND, np.uint8)
    cosine = np.zeros((camera.height, camera.width), np.float32)
    # The floor plane z = floor_z.
    dz = rays[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_floor = np.float32(floor_z - camera.position[2]) / dz
    hit = (dz < 0) & (t_floor > NEAR)
    depth[hit] = t_floor[hit]
    cosine[hit] = np.abs(dz[hit]) / norm[hit]
    for box in boxes:
        rect = _box_rectangle(box, camera)
        if rect is not None:
            cast = _cast_cylinder if box.cylinder else _cast_box
            cast(box, camera, rays, norm, rect, depth, labels, cosine)
    depth[~np.isfinite(depth)] = np.nan
    return depth, labels, cosine


def _local_rays(solid: SceneBox, camera: Camera, rays: np.ndarray,
                rect: tuple[int, int, int, int]) -> tuple[np.ndarray, list[np.ndarray]]:
    """The camera's position and the rays inside ``rect``, both in the solid's own frame."""
    v0, v1, u0, u1 = rect
    block = rays[:, v0:v1, u0:u1]
    rot = solid.rotation.astype(np.float32)
    origin = (camera.position - solid.centre) @ solid.rotation
    return origin, [block[0] * rot[0, k] + block[1] * rot[1, k] + block[2] * rot[2, k]
                    for k in range(3)]


def _write_hits(solid: SceneBox, rect: tuple[int, int, int, int], hit: np.ndarray,
                t_hit: np.ndarray, n_dot: np.ndarray, norm: np.ndarray, depth: np.ndarray,
                labels: np.ndarray, cosine: np.ndarray) -> None:
    """Z-buffered write of a solid's hits: depth, label and |cos| of the incidence angle."""
    v0, v1, u0, u1 = rect
    zbuf = depth[v0:v1, u0:u1]
    closer = hit & (t_hit < zbuf)
    zbuf[closer] = t_hit[closer]
    labels[v0:v1, u0:u1][closer] = solid.label
    cosine[v0:v1, u0:u1][closer] = (np.abs(n_dot) / norm[v0:v1, u0:u1])[closer]


def _cast_box(box: SceneBox, camera: Camera, rays: np.ndarray, norm: np.ndarray,
              rect: tuple[int, int, int, int], depth: np.ndarray, labels: np.ndarray,
              cosine: np.ndarray) -> None:
    """Slab test of one box against the rays inside ``rect``."""
    origin, dirs = _local_rays(box, camera, rays, rect)
    shape = dirs[0].shape
    t_near = np.full(shape, -np.inf, np.float32)
    t_far = np.full(shape, np.inf, np.float32)
    entry_axis_d = np.zeros(shape, np.float32)        # ray component along the entry axis
    with np.errstate(divide="ignore", invalid="ignore"):
        for k, d in enumerate(dirs):
            inv = 1.0 / d
            t1 = (-box.half_extents[k] - origin[k]) * inv
            t2 = (box.half_extents[k] - origin[k]) * inv
            lo, hi = np.fmin(t1, t2), np.fmax(t1, t2)
            enters_here = lo > t_near
            t_near = np.where(enters_here, lo, t_near)
            entry_axis_d = np.where(enters_here, d, entry_axis_d)
            t_far = np.fmin(t_far, hi)
    _write_hits(box, rect, (t_far >= t_near) & (t_near > NEAR), t_near, entry_axis_d, norm,
                depth, labels, cosine)


def _cast_cylinder(cyl: SceneBox, camera: Camera, rays: np.ndarray, norm: np.ndarray,
                   rect: tuple[int, int, int, int], depth: np.ndarray, labels: np.ndarray,
                   cosine: np.ndarray) -> None:
    """Ray-cylinder entry (side quadric or either cap) inside ``rect``."""
    o, d = _local_rays(cyl, camera, rays, rect)
    r, h = float(cyl.half_extents[0]), float(cyl.half_extents[2])
    t_hit = np.full(d[0].shape, np.inf, np.float32)
    n_dot = np.zeros(d[0].shape, np.float32)       # ray . surface normal at the hit
    with np.errstate(divide="ignore", invalid="ignore"):
        a = d[0] ** 2 + d[1] ** 2
        b = 2.0 * (o[0] * d[0] + o[1] * d[1])
        c = o[0] ** 2 + o[1] ** 2 - r * r
        t_side = (-b - np.sqrt(b * b - 4.0 * a * c)) / (2.0 * a)
        z_side = o[2] + t_side * d[2]
        side = np.isfinite(t_side) & (np.abs(z_side) <= h) & (t_side > NEAR)
        t_hit = np.where(side, t_side, t_hit)
        n_dot = np.where(side, ((o[0] + t_side * d[0]) * d[0]
                                + (o[1] + t_side * d[1]) * d[1]) / r, n_dot)
        for cap in (h, -h):
            t_cap = (cap - o[2]) / d[2]
            x, y = o[0] + t_cap * d[0], o[1] + t_cap * d[1]
            hit = (np.isfinite(t_cap) & (x * x + y * y <= r * r) & (t_cap > NEAR)
                   & (t_cap < t_hit))
            t_hit = np.where(hit, t_cap, t_hit)
            n_dot = np.where(hit, d[2], n_dot)
    _write_hits(cyl, rect, np.isfinite(t_hit), t_hit, n_dot, norm, depth, labels, cosine)


def episode_scene(episode: dict, outcomes: list[str], cfg: DatasetConfig, seed: int,
                  table: LabelTable) -> tuple[list[SceneBox], dict | None]:
    """Every solid of one frame: the episode's (``scene_boxes``) and the scenery drawn for it
    (background), with the record of what scenery was drawn (None: none)."""
    boxes = scene_boxes(episode, outcomes, cfg.scene, table)
    scenery, drawn = draw_neighbours(episode_fixture(episode, cfg.scene), cfg.scene,
                                     episode["objects"],
                                     episode_rng(seed, episode["episode"], "scenery"))
    return boxes + [SceneBox(s.half, s.centre, s.rotation, BACKGROUND) for s in scenery], drawn


def drawn_empty(scene: SceneConfig, seed: int, index: int) -> bool:
    """Whether frame ``index`` is rendered as an empty cell: ``scene.empty_cell_share`` of
    them, from a stream of their own, drawn only when the share is above 0 (a spec without
    it draws and renders what it did before)."""
    return drawn_in_share(scene.empty_cell_share, seed, index, "empty_cell")


def render_episode(episode: dict, outcomes: list[str], cfg: DatasetConfig, seed: int,
                   table: LabelTable, emptied: bool | None = None) -> dict:
    """Camera draw, clean render and noise for one episode; returns arrays and the record.
    ``emptied``: the same camera and sensor draws with the fixture and the objects left out
    (the floor, a table, the room and the scenery stay), a cell with nothing to judge; None
    draws it (``drawn_empty``: the spec's ``empty_cell_share`` of the frames)."""
    index = episode["episode"]
    if emptied is None:
        emptied = drawn_empty(cfg.scene, seed, index)
    fixture = episode_fixture(episode, cfg.scene)
    camera, draws = draw_camera(cfg.camera, fixture, episode_rng(seed, index, "render"))
    boxes, drawn = episode_scene(episode, outcomes, cfg, seed, table)
    if emptied:
        boxes = [box for box in boxes if box.label == BACKGROUND]
    clean, labels, cosine = render(boxes, fixture.room_floor_z, camera)
    noisy, noisy_labels, sensor = apply_sensor(clean, labels, cosine, camera, cfg, seed, index)
    record = {
        "episode": index,
        "seed": {"render": episode_seed(seed, index, "render"),
                 "noise": episode_seed(seed, index, "noise"),
                 "simulate": episode_seed(seed, index, "simulate")},
        "camera": {**camera.to_dict(), **draws},
        "objects": outcomes,
        "present": outcomes_present(noisy_labels, table=table),
        "pixel_counts": outcome_pixel_counts(noisy_labels, table),
    }
    if sensor is not None:
        record["sensor"] = sensor
    if drawn is not None:
        record["scenery"] = drawn
    if emptied:
        record["emptied"] = True
    if cfg.camera.info_differs:
        record["camera_info"] = draw_camera_info(camera, cfg.camera,
                                                 episode_rng(seed, index, "camera_info"))
    return {"clean": clean, "depth": noisy, "labels": noisy_labels, "record": record}


def apply_sensor(clean: np.ndarray, labels: np.ndarray, cosine: np.ndarray, camera: Camera,
                 cfg: DatasetConfig, seed: int, index: int
                 ) -> tuple[np.ndarray, np.ndarray, dict | None]:
    """This frame's sensor model and parameters, drawn, then applied. Returns (depth, labels,
    the sensor's record or None when nothing was drawn). Each draw has a stream of its own, so
    a spec with one sensor and fixed values draws (and makes) exactly what it always did."""
    mixed = cfg.tof.share > 0 or cfg.stereo.share > 0
    # One draw picks the model: ToF below tof.share, stereo in the next stereo.share, else
    # the noise section's; a spec without stereo picks exactly as it always did.
    pick = (episode_rng(seed, index, "sensor_model").random()
            if mixed and cfg.noise.enabled else 1.0)
    if pick < cfg.tof.share:
        tof = cfg.tof.draw(episode_rng(seed, index, "sensor"))
        depth, noisy_labels = apply_tof_noise(clean, labels, cosine, tof,
                                              episode_rng(seed, index, "noise"))
        return depth, noisy_labels, {"model": "tof",
                                     **{n: getattr(tof, n) for n in TOF_PARAMETERS}}
    if pick < cfg.tof.share + cfg.stereo.share:
        stereo = cfg.stereo.draw(episode_rng(seed, index, "sensor"))
        depth, noisy_labels = apply_stereo_noise(clean, labels, cosine, camera.fx, stereo,
                                                 episode_rng(seed, index, "noise"))
        return depth, noisy_labels, {"model": STEREO_MODEL,
                                     **{n: getattr(stereo, n) for n in STEREO_PARAMETERS}}
    sensor = cfg.noise.draw(episode_rng(seed, index, "sensor"))
    depth, noisy_labels = apply_kinect_noise(clean, labels, cosine, camera.fx, sensor,
                                             episode_rng(seed, index, "noise"))
    if not (cfg.noise.drawn_per_frame() or mixed):
        return depth, noisy_labels, None
    return depth, noisy_labels, {"model": sensor.model,
                                 **{n: getattr(sensor, n) for n in NOISE_PARAMETERS}}


def draw_camera_info(camera: Camera, envelope: CameraConfig, rng: np.random.Generator
                     ) -> dict:
    """The intrinsics camera_info reports for ``camera``: off by the envelope's calibration
    error (fx = fy scaled by 1 + U(-e, e), cx and cy shifted by U(-p, p) px)."""
    f = camera.fx * (1.0 + float(rng.uniform(-envelope.info_focal_error,
                                             envelope.info_focal_error)))
    dc = rng.uniform(-envelope.info_principal_error_px, envelope.info_principal_error_px, 2)
    return {"width": camera.width, "height": camera.height, "fx": f, "fy": f,
            "cx": camera.cx + float(dc[0]), "cy": camera.cy + float(dc[1])}


def reported_camera(record: dict) -> dict:
    """The camera an image's camera_info gives the node: its calibration-error draw when the
    spec has one, else the true camera."""
    return record.get("camera_info", record["camera"])


# ---- on-disk format: 16-bit PNG depth in mm (0 = invalid, as a Kinect's 16UC1) + PNG labels --

def image_paths(run_dir: Path, index: int) -> tuple[Path, Path]:
    folder = Path(run_dir) / "images"
    return folder / f"{index:06d}_depth.png", folder / f"{index:06d}_labels.png"


def write_pair(run_dir: Path, index: int, depth_m: np.ndarray, labels: np.ndarray) -> None:
    from task_outcome_ros.depth import encode_depth

    depth_path, label_path = image_paths(run_dir, index)
    depth_path.parent.mkdir(parents=True, exist_ok=True)
    data, _ = encode_depth(depth_m, "16UC1")
    mm = np.frombuffer(data, "<u2").reshape(depth_m.shape)
    for path, array in ((depth_path, mm), (label_path, labels)):
        tmp = path.with_name(path.stem + ".tmp.png")
        if not cv2.imwrite(str(tmp), array):
            raise OSError(f"could not write {tmp}")
        tmp.replace(path)


def read_pair(run_dir: Path, index: int) -> tuple[np.ndarray, np.ndarray]:
    """(depth float32 metres with NaN invalid, labels uint8) of one stored image."""
    from task_outcome_ros.depth import sanitize_depth

    depth_path, label_path = image_paths(run_dir, index)
    mm = cv2.imread(str(depth_path), cv2.IMREAD_UNCHANGED)
    labels = cv2.imread(str(label_path), cv2.IMREAD_UNCHANGED)
    if mm is None or labels is None or mm.dtype != np.uint16 or labels.dtype != np.uint8:
        raise ValueError(f"{depth_path} / {label_path}: missing or not a 16-bit depth PNG and "
                         "an 8-bit label PNG; re-run `python -m training render` to rebuild")
    return sanitize_depth(mm.astype(np.float32) * 1e-3), labels


# ---- stage entry point ------------------------------------------------------------------------

_STATE: dict = {}


def _init_worker(run_dir: str, cfg: DatasetConfig, episodes: list[dict],
                 outcomes: list[list[str]], table: LabelTable) -> None:
    cv2.setNumThreads(1)  # one process per core already; OpenCV threads would oversubscribe
    _STATE.update(run_dir=run_dir, cfg=cfg, episodes=episodes, outcomes=outcomes, table=table)


def _render_chunk(episodes: tuple[int, int]) -> dict:
    run_dir, cfg = _STATE["run_dir"], _STATE["cfg"]
    records = []
    for i in range(*episodes):
        out = render_episode(_STATE["episodes"][i], _STATE["outcomes"][i], cfg, cfg.seed,
                             _STATE["table"])
        write_pair(Path(run_dir), i, out["depth"], out["labels"])
        records.append(out["record"])
    return {"episodes": records}


def run_render(run_dir: Path, cfg: DatasetConfig, episodes: list[dict],
               outcomes: list[list[str]], table: LabelTable) -> list[dict]:
    """Render every episode into <run>/images/ (resumable); returns the per-image records."""
    stage_dir = Path(run_dir) / "render"
    run_chunks(stage_dir, cfg.episodes, cfg.chunk_size, cfg.workers, _render_chunk, "render",
               initializer=_init_worker, initargs=(str(run_dir), cfg, episodes, outcomes,
                                                   table))
    return load_chunks(stage_dir, cfg.episodes, cfg.chunk_size)
