"""``python -m training robustness``: how a model holds up when the world departs from its
training draws, one factor at a time.

Each stress point re-renders the same validation episodes of a dataset run (their simulated
final states and discovered outcomes, their own camera draws) with one factor changed, and
scores the model through the node's code path (``OutcomeSegmenter.segment``) with the paper's
image-level metric. Factors, each swept beyond what training drew:

- ``support_tilt_deg``: the support seen tilted (towards a direction drawn per image); the
  physics stays that of the level support, so only what the camera sees changes;
- ``camera_roll_deg``: the camera turned about its optical axis;
- ``noise_scale``: the sensor's disparity noise, edge jitter and speckle (ToF: axial noise and
  dropouts; stereo: disparity noise, mismatches and holes) times this factor;
- ``sensor_model``: every frame from one sensor model (``kinect_v1`` structured light,
  ``tof``, or ``active_stereo``: the stereo model, which no bundled spec trains on, with its
  spec's parameters or the defaults of ``config.StereoConfig``), instead of the spec's mix;
- ``focal_error``: camera_info's focal length off by this fraction (the true camera is not);
- ``camera_info``: with and without camera_info;
- ``resolution``: other image sizes, with the focal length scaled to keep the field of view;
  the sensor keeps its errors in pixels (a sensor made at that size), so its depth errors in
  metres scale with one over the focal length: twice the 640 x 480 sensor's at 320 x 240;
- ``resolution_same_depth_error``: the same sizes with the sensor's pixel-unit errors
  (disparity noise, quantisation, offset and low-frequency error, edge jitter) scaled with
  the focal length, so that its depth errors in metres are the 640 x 480 sensor's: the image
  size alone (the time-of-flight model's errors are in metres already);
- ``lost_depth_share``: this share of each frame loses its depth in smooth blobs
  (``holes.lose_depth``), as real frames lose whole surfaces; their labels are ignored, so
  an object wholly inside them is not in the image's truth;
- ``outlier_islands``: islands of wrong depth seeded at this rate per pixel
  (``islands.add_islands``: up to 3 px in radius, each off by up to 4 px of disparity at a
  0.075 m baseline, nearer or farther), as disparity sensors' wrong matches; labels kept;
- ``scene_emptied``: the same cameras and sensors with the fixture and the objects left out
  (``render.render_episode``'s ``emptied``), a cell with nothing to judge. Right means what
  the node owes its user there: no outcome reported, and the frame flagged outside the
  envelope because the fixture is not seen (``envelope.FIXTURE_NOT_SEEN``). Added after a
  candidate default model labelled a quarter of an empty floor as container, which no other
  point could show. Every other point renders each scene whole, also from a run whose spec
  empties some of its frames (``scene.empty_cell_share``).

Calibration error the spec draws for camera_info is left out of every point, so that
``focal_error`` is the only one. Writes ``robustness.json`` (per factor its values and, at
each, the all-correct with its 95 % interval and the episodes got wrong; the image count)
and ``robustness.png`` beside it. At 100 scenes a point, 97 right has the interval 0.92-0.99;
at 300 (the default, ``config.ROBUSTNESS_IMAGES``), 0.94-0.98.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from task_outcome_ros.camera import Intrinsics
from task_outcome_ros.envelope import FIXTURE_NOT_SEEN
from task_outcome_ros.inference import OutcomeSegmenter
from task_outcome_ros.labels import IGNORE, LabelTable, outcomes_present
from training.chunks import load_chunks
from training.config import (
    ROBUSTNESS_IMAGES,
    DatasetConfig,
    NoiseConfig,
    StereoConfig,
    dataset_config_from_dict,
    save_json,
)
from training.dataset import load_manifest
from training.discover import load_outcomes
from training.evaluate import same_task
from training.fixture import episode_fixture
from training.holes import lose_depth
from training.islands import add_islands
from training.render import render_episode
from training.seeding import episode_rng
from training.stats import wilson_interval
from training.stereo import STEREO_MODEL

# What robustness.json keeps per factor, one list entry per value; the mistakes (episode
# ids) let `python -m training compare` pair two models on each stress point.
POINT_FIELDS = ("values", "image_all_correct", "ci95", "outside_envelope", "mistakes")
# The sweeps: factor -> values; the first value of each is the training condition.
SWEEPS: dict[str, tuple] = {
    "support_tilt_deg": (0.0, 1.5, 3.0, 4.5, 6.0),
    "camera_roll_deg": (0.0, 5.0, 10.0, 20.0),
    "noise_scale": (1.0, 0.5, 2.0, 3.0),
    "sensor_model": ("", "kinect_v1", "tof", STEREO_MODEL),
    "focal_error": (0.0, -0.08, -0.04, 0.04, 0.08),
    "camera_info": (True, False),
    "resolution": ("640x480", "320x240", "1280x720"),
    "resolution_same_depth_error": ("640x480", "320x240", "1280x720"),
    "lost_depth_share": (0.0, 0.15, 0.3),
    "outlier_islands": (0.0, 5e-5, 1e-4, 3e-4),
    "scene_emptied": (False, True),
}
# Factors plotted on their own y range (plot_robustness): they may take a model to chance.
OWN_RANGE_FACTORS = frozenset({"lost_depth_share", "outlier_islands", "scene_emptied"})


@dataclass(frozen=True)
class Stress:
    """One departure from the training draws (the defaults: none)."""

    support_tilt_deg: float = 0.0
    camera_roll_deg: float = 0.0
    noise_scale: float = 1.0
    sensor_model: str = ""  # "" = the spec's mix
    focal_error: float = 0.0
    camera_info: bool = True
    resolution: str = ""   # "WxH"; "" = the envelope's own
    resolution_same_depth_error: str = ""   # "WxH", the sensor's errors in metres kept
    lost_depth_share: float = 0.0
    outlier_islands: float = 0.0   # islands of wrong depth per pixel (training/islands.py)
    scene_emptied: bool = False    # the fixture and the objects left out


def stressed_frame(episode: dict, outcomes: list[str], cfg: DatasetConfig, seed: int,
                   stress: Stress, table: LabelTable
                   ) -> tuple[np.ndarray, np.ndarray, Intrinsics | None]:
    """(noisy depth, noisy labels, the camera_info the model is given) of one episode: the
    dataset's own ``render_episode`` on the episode and config with the stress applied."""
    fixture = episode_fixture(episode, cfg.scene)
    if stress.support_tilt_deg:
        azimuth = float(episode_rng(seed, episode["episode"], "robustness").uniform(0.0, 360.0))
        fixture = dataclasses.replace(fixture, tilt_deg=stress.support_tilt_deg,
                                      tilt_azimuth_deg=azimuth)
    out = render_episode({**episode, "fixture": fixture.to_record()}, outcomes,
                         _stressed_config(cfg, stress), seed, table,
                         emptied=stress.scene_emptied)
    depth, labels = out["depth"], out["labels"]
    if stress.outlier_islands:
        fx = out["record"]["camera"]["fx"]
        depth = add_islands(depth, fx, stress.outlier_islands,
                            episode_rng(seed, episode["episode"], "islands"))
        labels = np.where(np.isfinite(depth), labels, IGNORE).astype(np.uint8)
    if stress.lost_depth_share:
        blobs = int(episode_rng(seed, episode["episode"], "lost_depth").integers(2**31))
        depth, labels = lose_depth(depth, labels, stress.lost_depth_share, blobs)
    intrinsics = None
    if stress.camera_info:
        camera = Intrinsics.from_record(out["record"]["camera"])
        f = camera.fx * (1.0 + stress.focal_error)
        intrinsics = dataclasses.replace(camera, fx=f, fy=f)
    return depth, labels, intrinsics


def _stressed_config(cfg: DatasetConfig, stress: Stress) -> DatasetConfig:
    """The camera and sensor of ``cfg`` with the stress's roll, size, sensor and noise scale,
    and camera_info exact (the stress's focal error is applied by ``stressed_frame``)."""
    camera = dataclasses.replace(cfg.camera, info_focal_error=0.0, info_principal_error_px=0.0)
    noise, tof, stereo = cfg.noise, cfg.tof, cfg.stereo
    if stress.camera_roll_deg:
        camera = dataclasses.replace(camera, roll_deg=(stress.camera_roll_deg,) * 2)
    size = stress.resolution or stress.resolution_same_depth_error
    if size:  # the same view at another size: focal length and offsets scaled
        width, height = (int(v) for v in size.split("x"))
        scale = width / camera.width
        camera = dataclasses.replace(
            camera, width=width, height=height,
            focal_px=tuple(f * scale for f in camera.focal_px),
            principal_offset_px=camera.principal_offset_px * scale)
        if stress.resolution_same_depth_error:
            noise, stereo = same_depth_error(noise, scale), same_depth_error(stereo, scale)
    if stress.noise_scale != 1.0:
        noise, tof, stereo = (
            dataclasses.replace(sensor, **{name: _scaled(getattr(sensor, name),
                                                         stress.noise_scale) for name in names})
            for sensor, names in ((noise, NOISE_SCALED), (tof, TOF_SCALED),
                                  (stereo, STEREO_SCALED)))
    if stress.sensor_model:  # every frame from that one model
        tof = dataclasses.replace(tof, share=float(stress.sensor_model == "tof"))
        stereo = dataclasses.replace(stereo, share=float(stress.sensor_model == STEREO_MODEL))
    return dataclasses.replace(cfg, camera=camera, noise=noise, tof=tof, stereo=stereo)


# What the noise_scale points multiply, per sensor model.
NOISE_SCALED = ("sigma_disparity_px", "lateral_sigma_px", "speckle_rate")
TOF_SCALED = ("sigma_1m", "dropout_rate")
STEREO_SCALED = ("sigma_disparity_px", "mismatch_rate", "speckle_rate")
# The disparity models' errors given in image pixels (training/noise.py, training/stereo.py):
# at a focal length k times as long, k times as many pixels make the same depth error. (The
# stereo model's block and fattening sizes stay in pixels, as a camera's matcher does.)
PIXEL_UNIT_ERRORS = {
    NoiseConfig: ("sigma_disparity_px", "bias_disparity_px", "lowfreq_disparity_px",
                  "lateral_sigma_px"),
    StereoConfig: ("sigma_disparity_px", "bias_disparity_px", "lowfreq_disparity_px",
                   "mismatch_disparity_px"),
}


def same_depth_error(sensor: NoiseConfig | StereoConfig, scale: float
                     ) -> NoiseConfig | StereoConfig:
    """A disparity sensor for an image whose focal length is ``scale`` times as long, with
    the same depth errors in metres: its pixel-unit errors times ``scale`` and its disparity
    steps (1 / ``disparity_subpixel`` px) too."""
    scaled = {name: _scaled(getattr(sensor, name), scale)
              for name in PIXEL_UNIT_ERRORS[type(sensor)]}
    steps = sensor.disparity_subpixel
    scaled["disparity_subpixel"] = (tuple(max(1, round(v / scale)) for v in steps)
                                    if isinstance(steps, tuple) else max(1, round(steps / scale)))
    return dataclasses.replace(sensor, **scaled)


def _scaled(value: float | tuple[float, float], scale: float) -> float | tuple[float, float]:
    """A sensor parameter (a value, or a range drawn per frame) times ``scale``."""
    return tuple(v * scale for v in value) if isinstance(value, tuple) else value * scale


def score_stress(seg: OutcomeSegmenter, items: list[tuple[dict, list[str]]],
                 cfg: DatasetConfig, stress: Stress) -> dict:
    mistakes, flagged = [], 0
    for episode, outcomes in items:
        depth, labels, intrinsics = stressed_frame(episode, outcomes, cfg, cfg.seed, stress,
                                                   seg.table)
        result = seg.segment(depth, intrinsics)
        truth = outcomes_present(labels, seg.presence_min_pixels, seg.table)
        if not answered_right(result.present, truth, result.outside_envelope,
                              stress.scene_emptied):
            mistakes.append(int(episode["episode"]))
        flagged += int(bool(result.outside_envelope))
    n = len(items)
    right = n - len(mistakes)
    return {"image_all_correct": round(right / n, 4), "images": n,
            "ci95": [round(v, 4) for v in wilson_interval(right, n)],
            "outside_envelope": flagged, "mistakes": mistakes}


def answered_right(present: dict[str, bool], truth: dict[str, bool],
                   outside_envelope: list[str], emptied: bool) -> bool:
    """The paper's image-level metric (the outcomes present are the truth's); on an emptied
    scene also the envelope's flag that the fixture is not seen, without which the node
    would report an empty cell as a scene with no outcome in it."""
    if present != truth:
        return False
    return not emptied or any(FIXTURE_NOT_SEEN in why for why in outside_envelope)


def check_sweeps(sweeps: dict[str, tuple]) -> None:
    """Refuse an empty sweep or a factor the suite does not know, before anything renders."""
    if not sweeps:
        raise ValueError("robustness: no factor to sweep")
    unknown = sorted(set(sweeps) - set(SWEEPS))
    if unknown:
        raise ValueError(f"robustness: unknown factor(s) {', '.join(unknown)}; "
                         f"expected some of {', '.join(SWEEPS)}")


def run_robustness(checkpoint: Path | None, data_dir: Path, out_dir: Path,
                   images: int = ROBUSTNESS_IMAGES, sweeps: dict[str, tuple] | None = None,
                   progress: bool = True) -> dict:
    """Every sweep on the first ``images`` validation episodes of ``data_dir``."""
    data_dir, out_dir = Path(data_dir), Path(out_dir)
    if sweeps is None:
        sweeps = SWEEPS
    check_sweeps(sweeps)
    manifest = load_manifest(data_dir)
    cfg = dataset_config_from_dict(manifest["config"])
    episodes = load_chunks(data_dir / "simulate", cfg.episodes, cfg.chunk_size)
    outcomes, table = load_outcomes(data_dir)
    val = [im["episode"] for im in manifest["images"] if im["split"] == "val"][:images]
    if not val:
        raise ValueError(f"{data_dir}: no validation images to re-render")
    items = [(episodes[i], outcomes[i]) for i in val]
    seg = OutcomeSegmenter(checkpoint, backend="auto", num_threads=1)
    same_task(seg.table, table, seg.model_path, data_dir)  # renders then use the model's ids
    report: dict = {"model": str(seg.model_path), "data": str(data_dir), "task": cfg.task,
                    "images": len(items), "factors": {}}
    points = [(f, v) for f, values in sweeps.items() for v in values]
    # Most sweeps start at the training condition, the same Stress(): render and score it once.
    scored: dict[Stress, dict] = {}
    for factor, value in tqdm(points, desc="robustness", unit="point", disable=not progress):
        stress = Stress(**{factor: value})
        if stress not in scored:
            scored[stress] = score_stress(seg, items, cfg, stress)
        result = scored[stress]
        entry = report["factors"].setdefault(factor, {key: [] for key in POINT_FIELDS})
        entry["values"].append(value)
        for key in POINT_FIELDS[1:]:
            entry[key].append(result[key])
    out_dir.mkdir(parents=True, exist_ok=True)
    save_json(out_dir / "robustness.json", report)
    plot_robustness(out_dir / "robustness.png", report)
    return report


def plot_robustness(path: Path, report: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    factors = report["factors"]
    cols = 3
    rows = math.ceil(len(factors) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.2 * rows), dpi=90,
                             squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    # One y range for the panels, from just under the lowest rate (or interval) to 1: the
    # rates live near the top, and 0-1 would flatten the intervals into the markers. A factor
    # that can break a model outright (OWN_RANGE_FACTORS) gets its own, so that it does not
    # flatten the others.
    def bottom_of(entries) -> float:
        lows = [v for e in entries for v in
                (np.array(e["ci95"])[:, 0] if "ci95" in e else e["image_all_correct"])]
        return max(0.0, math.floor(min(lows) * 20) / 20 - 0.05) if lows else 0.0

    shared = bottom_of([e for f, e in factors.items() if f not in OWN_RANGE_FACTORS])
    for ax, (factor, entry) in zip(axes.ravel(), factors.items()):
        ax.axis("on")
        bottom = bottom_of([entry]) if factor in OWN_RANGE_FACTORS else shared
        labels = [str(v) if v != "" else "as trained" for v in entry["values"]]
        rates = np.array(entry["image_all_correct"])
        if "ci95" in entry:  # older results have no intervals
            lo, hi = np.array(entry["ci95"]).T
            ax.errorbar(range(len(labels)), rates, yerr=[rates - lo, hi - rates], fmt="o-",
                        capsize=3)
        else:
            ax.plot(range(len(labels)), rates, "o-")
        ax.set_xticks(range(len(labels)), labels)
        ax.set_ylim(bottom, 1.005)
        ax.axhline(entry["image_all_correct"][0], color="grey", lw=0.8, ls="--")
        ax.set_title(factor + (" (own y range)" if factor in OWN_RANGE_FACTORS else ""),
                     fontsize=9)
        ax.set_ylabel("image all-correct")
    fig.suptitle(f"robustness of {Path(report['model']).name} on {report['images']} "
                 f"{report['task']} validation scenes (first value of each: as trained; "
                 "bars: 95 % interval)")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
