"""Stage 2: discover the task outcomes by clustering final object states with DBSCAN.

Why these features (the paper clustered only the distance from the container centre to the
object's centre of mass): that distance, and likewise the height of the object's top, change
smoothly from "inside" to "sticking out", so DBSCAN finds no density gap between success and
stuck objects. Two measurements in the container frame do have natural gaps:

- ``com_wall``: how far the centre of mass lies beyond the walls' inner faces, in wall
  thicknesses, clipped to [-1, 2]. An object cannot balance on a 1-2 cm wall, so centres of
  mass are inside the footprint (clipped to a dense spike at -1 once more than one wall
  thickness in) or beyond the outer face by at least half the object's own thickness (a spike
  at 2): between lie only objects leaning over the wall, a wide, nearly empty gap. Measured
  in half-widths instead (the first version), that gap was wall / half-width: 0.04 for the
  paper's 1 m container, but 0.025 for a 0.8 m tote with 1 cm walls, less than DBSCAN's
  eps, and the stuck objects chained into the fallen ones on some seeds.
- ``protrusion``: the fraction of the object's volume outside the container's inner volume,
  on a log scale: log10(outside + PROTRUSION_OFFSET), mapped to [0, 1]. Objects fully inside
  sit exactly at 0 (a dense spike); any part outside costs at least one grid point of
  ``geometry.box_sample_points`` (0.1 %), and objects entirely outside sit at 1. The offset
  sits two decades below that one grid point, so a single point outside lands 0.4 from the
  spike, more than 3 x eps: a real gap between "entirely inside" and "sticks out". (Before
  model 0.2.0 the offset was 1e-3, which put one point outside only 0.10 from the spike, inside
  eps 0.12: boxes sticking out by up to 18 mm chained into the success cluster, 16 of 24,969
  objects at 10,000 episodes, and the near-rim labels the network learns from were noisy.)

Clusters are named afterwards from their members' geometry (never from the cluster index), and
DBSCAN's noise points are assigned explicitly to the cluster of their nearest core sample.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np

from task_outcome_ros.labels import OUTCOME_NAMES
from training.config import DatasetConfig, SceneConfig, load_json, save_json
from training.geometry import SAMPLE_GRID, geometric_outcome, object_measurements

COM_WALL_CLIP = (-1.0, 2.0)
# Two decades below one grid point's share of the volume (see the module docstring).
PROTRUSION_OFFSET = 0.01 / SAMPLE_GRID**3


def features(measurements: list[dict[str, float]]) -> np.ndarray:
    """(N, 2) DBSCAN features: centre of mass beyond the walls (clipped, in wall thicknesses),
    log-scaled protrusion."""
    com = np.clip([m["com_beyond_wall"] for m in measurements], *COM_WALL_CLIP)
    outside = np.array([1.0 - m["inside_fraction"] for m in measurements])
    decades = -np.log10(PROTRUSION_OFFSET)  # so that outside 0 -> 0 and outside 1 -> ~1
    protrusion = (np.log10(outside + PROTRUSION_OFFSET) + decades) / decades
    return np.stack([com, protrusion], axis=1) if len(measurements) else np.zeros((0, 2))


def name_cluster(members: list[dict[str, float]], scene: SceneConfig) -> str:
    """Name a cluster from what its typical member looks like."""
    inside = float(np.median([m["inside_fraction"] for m in members]))
    com = float(np.median([m["com_offset"] for m in members]))
    beyond = float(np.median([m["com_beyond_outer"] for m in members]))
    if inside >= 0.999 and com < 1.0:
        return "success"
    if beyond >= 0.5 and inside <= 0.001:
        return "fell_outside"
    return "stuck_on_rim"


def cluster(measurements: list[dict[str, float]], cfg: DatasetConfig) -> dict:
    """DBSCAN + explicit noise assignment + naming. Returns per-object names and statistics."""
    from sklearn.cluster import DBSCAN  # heavy import, only this stage needs it

    x = features(measurements)
    min_samples = cfg.discover.min_samples(len(x))
    db = DBSCAN(eps=cfg.discover.eps, min_samples=min_samples).fit(x)
    raw = db.labels_.copy()
    labels = raw.copy()
    noise = np.flatnonzero(raw < 0)
    core = db.core_sample_indices_
    if len(noise) and len(core):
        nearest = np.empty(len(noise), dtype=int)
        for i in range(0, len(noise), 2048):  # bounded memory for the distance matrix
            d = np.linalg.norm(x[noise[i:i + 2048], None] - x[core][None], axis=2)
            nearest[i:i + 2048] = d.argmin(axis=1)
        labels[noise] = raw[core][nearest]
    cluster_ids = sorted(set(labels[labels >= 0].tolist()))
    names = {c: name_cluster([measurements[i] for i in np.flatnonzero(labels == c)], cfg.scene)
             for c in cluster_ids}
    object_names = [names.get(int(c), "stuck_on_rim") for c in labels]
    return {"features": x, "raw_labels": raw, "labels": labels, "names": names,
            "object_names": object_names, "min_samples": min_samples,
            "noise_points": int(len(noise))}


def run_discover(run_dir: Path, cfg: DatasetConfig, episodes: list[dict]) -> list[list[str]]:
    """Cluster all objects of the run, write discovery.json/.png and outcomes.json.

    Returns the outcome name of every object, per episode.
    """
    from sklearn.metrics import adjusted_rand_score

    run_dir = Path(run_dir)
    measurements, owner = [], []
    for e in episodes:
        for k, obj in enumerate(e["objects"]):
            measurements.append(object_measurements(obj, e, cfg.scene))
            owner.append((e["episode"], k))
    result = cluster(measurements, cfg)
    geometry = [geometric_outcome(m, cfg.scene) for m in measurements]
    ari = float(adjusted_rand_score(geometry, result["labels"]))
    names = result["object_names"]
    sizes = Counter(names)
    n = max(1, len(names))
    report = {
        "n_episodes": len(episodes),
        "n_objects": len(names),
        "n_clusters": len(result["names"]),
        "cluster_names": {name: sizes.get(name, 0) for name in OUTCOME_NAMES},
        "cluster_table": {str(c): name for c, name in result["names"].items()},
        "outcome_fractions": {name: round(sizes.get(name, 0) / n, 4) for name in OUTCOME_NAMES},
        "geometry_counts": dict(Counter(geometry)),
        "ari_vs_geometry": round(ari, 5),
        "agreement_vs_geometry": round(float(np.mean([a == b for a, b in zip(names, geometry)])),
                                       5),
        "noise_points": result["noise_points"],
        "dbscan": {"eps": cfg.discover.eps, "min_samples": result["min_samples"],
                   "features": ["centre of mass beyond the walls' inner faces, in wall "
                                "thicknesses, clipped to [-1, 2]",
                                "log-scaled volume outside"]},
        "timed_out_episodes": int(sum(e["timed_out"] for e in episodes)),
    }
    save_json(run_dir / "discovery.json", report)
    per_episode: dict[int, list[str]] = {e["episode"]: [] for e in episodes}
    for (ep, _), name in zip(owner, names):
        per_episode[ep].append(name)
    outcomes = [per_episode[e["episode"]] for e in episodes]
    _invalidate_stale_renders(run_dir, outcomes)
    save_json(run_dir / "outcomes.json", {"outcomes": outcomes})
    plot_clusters(run_dir / "discovery.png", result, geometry, report)
    return outcomes


def _invalidate_stale_renders(run_dir: Path, outcomes: list[list[str]]) -> None:
    """Rendered labels come from outcomes.json: if the outcomes changed, the old render chunks
    would be resumed with stale labels, so they are removed (images are overwritten later)."""
    import shutil

    previous = run_dir / "outcomes.json"
    if previous.exists() and load_json(previous)["outcomes"] != outcomes:
        for stale in (run_dir / "render", run_dir / "cache"):
            if stale.exists():
                shutil.rmtree(stale)
        (run_dir / "manifest.json").unlink(missing_ok=True)
        print("discover: outcomes changed; removed the stale render/, cache/ and manifest")


def plot_clusters(path: Path, result: dict, geometry: list[str], report: dict) -> None:
    """Scatter of the DBSCAN features, coloured by discovered outcome; geometry disagreements
    and noise points marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from task_outcome_ros.labels import CLASS_COLOURS, OUTCOME_IDS

    x, names = result["features"], result["object_names"]
    fig, ax = plt.subplots(figsize=(7, 5), dpi=110)
    for name in OUTCOME_NAMES:
        idx = [i for i, n in enumerate(names) if n == name]
        if idx:
            colour = np.array(CLASS_COLOURS[OUTCOME_IDS[name]]) / 255.0
            ax.scatter(x[idx, 0], x[idx, 1], s=4, color=colour, alpha=0.5,
                       label=f"{name} ({len(idx)})")
    noise = np.flatnonzero(result["raw_labels"] < 0)
    if len(noise):
        ax.scatter(x[noise, 0], x[noise, 1], s=14, facecolors="none", edgecolors="k",
                   linewidths=0.5, label=f"DBSCAN noise, assigned ({len(noise)})")
    wrong = [i for i, (a, b) in enumerate(zip(names, geometry)) if a != b]
    if wrong:
        ax.scatter(x[wrong, 0], x[wrong, 1], s=30, marker="x", color="m",
                   label=f"differs from geometric rule ({len(wrong)})")
    ax.set_xlabel("centre of mass beyond the inner wall faces / wall thickness (clipped)")
    ax.set_ylabel("volume outside container (log scale, 0 = none, 1 = all)")
    ax.set_title(f"Discovered outcomes: {report['n_clusters']} clusters, "
                 f"ARI vs geometry {report['ari_vs_geometry']:.4f}")
    ax.legend(loc="center right", fontsize=8, markerscale=2)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
