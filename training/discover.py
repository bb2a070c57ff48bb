"""Stage 2: discover the task outcomes by clustering final object states with DBSCAN.

Everything is measured against the spec's *target region* (training/fixture.py ``Region``):
an open box's inner volume, the volume above a shelf board. Why these features (the paper
clustered only the distance from the container centre to the object's centre of mass): that
distance, and likewise the height of the object's top, change smoothly from "inside" to
"sticking out", so DBSCAN finds no density gap between them. Two measurements do have
natural gaps:

- ``com_edge``: how far the centre of mass lies beyond the region (beyond its footprint, or,
  once below the region, below its bottom), in edge thicknesses (an open box's wall, a board's
  own thickness), clipped to [-1, 2]. An object cannot balance on a 1-2 cm edge, so centres of
  mass are inside the footprint (clipped to a dense spike at -1 once more than one thickness
  in) or beyond the outer face by at least half the object's own thickness, or fallen far
  below a board (a spike at 2): between lie only objects leaning over the edge, a wide, nearly
  empty gap. Measured in half-widths instead (the first version), that gap was wall / half-
  width: 0.04 for the paper's 1 m container, but 0.025 for a 0.8 m tote with 1 cm walls, less
  than DBSCAN's eps, and the stuck objects chained into the fallen ones on some seeds.
- ``protrusion``: the fraction of the object's volume outside the region, on a log scale:
  log10(outside + PROTRUSION_OFFSET), mapped to [0, 1]. Objects fully inside sit exactly at 0
  (a dense spike); any part outside costs at least one grid point of
  ``geometry.object_sample_points`` (0.1 %), and objects entirely outside sit at 1. The offset
  sits two decades below that one grid point, so a single point outside lands 0.4 from the
  spike, more than 3 x eps: a real gap between "entirely inside" and "sticks out". (Before
  model 0.2.0 the offset was 1e-3, which put one point outside only 0.10 from the spike, inside
  eps 0.12: boxes sticking out by up to 18 mm chained into the success cluster, 16 of 24,969
  objects at 10,000 episodes, and the near-top labels the network learns from were noisy.)

How many outcomes there are is what DBSCAN finds. Each cluster is then described from its
typical member's geometry in the region's terms (``DESCRIPTORS``: inside, outside, partly
inside; never from the cluster index), and the spec maps descriptors to the task's words
(``discover.outcome_names``). Two clusters with the same description are an error, not a
merge. DBSCAN's noise points are assigned explicitly to the cluster of their nearest core
sample. The label table (task_outcome_ros/labels.py) follows: the fixture, then the outcomes
in ``DESCRIPTORS`` order, the inside one (success-like) first.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np

from task_outcome_ros.labels import LabelTable
from training.config import DESCRIPTORS, ConfigError, DatasetConfig, load_json, save_json
from training.geometry import SAMPLE_GRID, geometric_outcome, object_measurements

COM_EDGE_CLIP = (-1.0, 2.0)
# Two decades below one grid point's share of the volume (see the module docstring).
PROTRUSION_OFFSET = 0.01 / SAMPLE_GRID**3
SUCCESS_DESCRIPTOR = "inside"


class DiscoveryError(ConfigError):
    """Clusters that cannot become a label table (the message says which and what to try)."""


def features(measurements: list[dict[str, float]]) -> np.ndarray:
    """(N, 2) DBSCAN features: centre of mass beyond the region (clipped, in edge
    thicknesses), log-scaled protrusion."""
    com = np.clip([m["com_beyond_edge"] for m in measurements], *COM_EDGE_CLIP)
    outside = np.array([1.0 - m["inside_fraction"] for m in measurements])
    decades = -np.log10(PROTRUSION_OFFSET)  # so that outside 0 -> 0 and outside 1 -> ~1
    protrusion = (np.log10(outside + PROTRUSION_OFFSET) + decades) / decades
    return np.stack([com, protrusion], axis=1) if len(measurements) else np.zeros((0, 2))


def describe_cluster(members: list[dict[str, float]]) -> str:
    """A cluster's descriptor (``DESCRIPTORS``) from what its typical member looks like."""
    inside = float(np.median([m["inside_fraction"] for m in members]))
    com = float(np.median([m["com_offset"] for m in members]))
    beyond = float(np.median([m["com_beyond_outer"] for m in members]))
    if inside >= 0.999 and com < 1.0:
        return "inside"
    if beyond >= 0.5 and inside <= 0.001:
        return "outside"
    return "partly_inside"


def label_table(descriptors: set[str], cfg: DatasetConfig) -> LabelTable:
    """The task's label table: its fixture, then the found outcomes in DESCRIPTORS order."""
    return LabelTable.build(cfg.discover.fixture_name,
                            [(cfg.discover.outcome_name(d), d != SUCCESS_DESCRIPTOR)
                             for d in DESCRIPTORS if d in descriptors])


def cluster(measurements: list[dict[str, float]], cfg: DatasetConfig) -> dict:
    """DBSCAN + explicit noise assignment + naming. Returns per-object names and statistics;
    raises DiscoveryError when DBSCAN finds no cluster or two clusters look alike."""
    x = features(measurements)
    if not len(x):   # every episode empty (scene.empty_share): nothing to cluster
        raise DiscoveryError("no objects to cluster: every episode placed nothing; "
                             "simulate more episodes or lower scene.empty_share")
    min_samples = cfg.discover.min_samples(len(x))
    raw, core = dbscan_collapsed(x, cfg.discover.eps, min_samples)
    labels = raw.copy()
    noise = np.flatnonzero(raw < 0)
    if not core.any():
        raise DiscoveryError(f"DBSCAN found no cluster among {len(x)} objects (eps "
                             f"{cfg.discover.eps}, min_samples {min_samples}): simulate more "
                             "episodes or lower discover.min_samples_floor")
    if len(noise):
        # Each noise point joins its nearest core sample's cluster. Identical core samples
        # have one label, so the distinct ones suffice (the spikes are thousands of copies).
        core_points, first = np.unique(x[core], axis=0, return_index=True)
        core_labels = raw[core][first]
        nearest = np.empty(len(noise), dtype=int)
        for i in range(0, len(noise), 2048):  # bounded memory for the distance matrix
            d = np.linalg.norm(x[noise[i:i + 2048], None] - core_points[None], axis=2)
            nearest[i:i + 2048] = d.argmin(axis=1)
        labels[noise] = core_labels[nearest]
    cluster_ids = sorted(set(labels.tolist()))
    descriptors = {c: describe_cluster([measurements[i] for i in np.flatnonzero(labels == c)])
                   for c in cluster_ids}
    _refuse_lookalikes(descriptors, labels, cfg)
    names = {c: cfg.discover.outcome_name(d) for c, d in descriptors.items()}
    return {"features": x, "raw_labels": raw, "labels": labels, "names": names,
            "descriptors": descriptors, "object_names": [names[int(c)] for c in labels],
            "min_samples": min_samples, "noise_points": int(len(noise)),
            "label_table": label_table(set(descriptors.values()), cfg)}


def dbscan_collapsed(x: np.ndarray, eps: float, min_samples: int
                     ) -> tuple[np.ndarray, np.ndarray]:
    """scikit-learn's DBSCAN on ``x`` with identical rows collapsed into one weighted sample:
    (labels, is-core mask), the same as ``DBSCAN(eps, min_samples).fit(x)`` gives.

    Why: the features have exact spikes (every object well inside at (-1, 0), every object
    far outside at (2, 1)), and DBSCAN stores every point's neighbourhood. A spike of k
    copies costs k^2 indices: 20,000 tote episodes (~30,000 objects at one spike) asked for
    more than 24 GB and were killed. A weighted sample has the same neighbourhood weight as
    its copies had neighbours, so core points, clusters and noise are unchanged, and clusters
    are numbered as DBSCAN numbers them, in order of their first core point. (A border point
    within reach of two clusters goes to the one expanded first, in either form; the order of
    expansion differs, so such a point, which is not a core point of either, may differ.)"""
    from sklearn.cluster import DBSCAN  # heavy import, only this stage needs it

    unique, inverse, counts = np.unique(x, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    db = DBSCAN(eps=eps, min_samples=min_samples).fit(unique, sample_weight=counts)
    core_unique = np.zeros(len(unique), bool)
    core_unique[db.core_sample_indices_] = True
    labels, core = db.labels_[inverse], core_unique[inverse]
    # DBSCAN numbers clusters as it meets their first core point in input order.
    found, first_core = np.unique(labels[core], return_index=True)
    renumber = np.full(len(found) + 1, -1)       # index 0: noise (-1) stays -1
    renumber[found[np.argsort(first_core)] + 1] = np.arange(len(found))
    return renumber[labels + 1], core


def _refuse_lookalikes(descriptors: dict[int, str], labels: np.ndarray,
                       cfg: DatasetConfig) -> None:
    """Two clusters with one description would share a label: say which, and what to try."""
    by_descriptor: dict[str, list[int]] = {}
    for c, d in descriptors.items():
        by_descriptor.setdefault(d, []).append(c)
    twins = {d: cs for d, cs in by_descriptor.items() if len(cs) > 1}
    if twins:
        sizes = {d: [int(np.sum(labels == c)) for c in cs] for d, cs in twins.items()}
        raise DiscoveryError(
            f"DBSCAN found {len(descriptors)} clusters, and several look alike: "
            + "; ".join(f"{len(cs)} clusters are '{d}' (sizes {sizes[d]})"
                        for d, cs in twins.items())
            + f". Raise discover.eps (now {cfg.discover.eps}) or "
            f"discover.min_samples_fraction (now {cfg.discover.min_samples_fraction}) so that "
            "they join, or change the spec so that they differ")


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
    geometry = [cfg.discover.outcome_name(geometric_outcome(m, cfg.discover.yardstick_inside))
                for m in measurements]
    ari = float(adjusted_rand_score(geometry, result["labels"]))
    names = result["object_names"]
    table = result["label_table"]
    sizes = Counter(names)
    n = max(1, len(names))
    report = {
        "n_episodes": len(episodes),
        "n_objects": len(names),
        "n_clusters": len(result["names"]),
        "cluster_names": {name: sizes.get(name, 0) for name in table.outcome_names},
        "cluster_table": {str(c): name for c, name in result["names"].items()},
        "descriptors": {result["names"][c]: d for c, d in result["descriptors"].items()},
        "label_table": table.to_dict(),
        "outcome_fractions": {name: round(sizes.get(name, 0) / n, 4)
                              for name in table.outcome_names},
        "geometry_counts": dict(Counter(geometry)),
        "ari_vs_geometry": round(ari, 5),
        "agreement_vs_geometry": round(float(np.mean([a == b for a, b in zip(names, geometry)])),
                                       5),
        "noise_points": result["noise_points"],
        "dbscan": {"eps": cfg.discover.eps, "min_samples": result["min_samples"],
                   "features": ["centre of mass beyond the target region, in edge "
                                "thicknesses, clipped to [-1, 2]",
                                "log-scaled volume outside the region"]},
        "yardstick_inside": cfg.discover.yardstick_inside,
        "timed_out_episodes": int(sum(e["timed_out"] for e in episodes)),
    }
    save_json(run_dir / "discovery.json", report)
    per_episode: dict[int, list[str]] = {e["episode"]: [] for e in episodes}
    for (ep, _), name in zip(owner, names):
        per_episode[ep].append(name)
    outcomes = [per_episode[e["episode"]] for e in episodes]
    _invalidate_stale_renders(run_dir, outcomes, table)
    save_json(run_dir / "outcomes.json", {"outcomes": outcomes, "label_table": table.to_dict()})
    plot_clusters(run_dir / "discovery.png", result, geometry, report, table)
    return outcomes


def load_outcomes(run_dir: Path) -> tuple[list[list[str]], LabelTable]:
    """Every object's outcome name per episode, and the label table (outcomes.json); files
    written before tables travelled as data are the default task's."""
    data = load_json(Path(run_dir) / "outcomes.json")
    return data["outcomes"], table_of(data)


def table_of(record: dict) -> LabelTable:
    """The label table a discovery file, outcomes file or manifest carries (legacy: the
    default task's)."""
    from task_outcome_ros.labels import DEFAULT_TABLE

    return LabelTable.from_dict(record["label_table"]) if "label_table" in record \
        else DEFAULT_TABLE


def _invalidate_stale_renders(run_dir: Path, outcomes: list[list[str]],
                              table: LabelTable) -> None:
    """Rendered labels come from outcomes.json: if the outcomes or their ids changed, the old
    render chunks would be resumed with stale labels, so they are removed (images are
    overwritten later)."""
    import shutil

    previous = run_dir / "outcomes.json"
    if previous.exists() and load_outcomes(run_dir) != (outcomes, table):
        for stale in (run_dir / "render", run_dir / "cache"):
            if stale.exists():
                shutil.rmtree(stale)
        (run_dir / "manifest.json").unlink(missing_ok=True)
        print("discover: outcomes changed; removed the stale render/, cache/ and manifest")


def plot_clusters(path: Path, result: dict, geometry: list[str], report: dict,
                  table: LabelTable) -> None:
    """Scatter of the DBSCAN features, coloured by discovered outcome; geometry disagreements
    and noise points marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x, names = result["features"], result["object_names"]
    fig, ax = plt.subplots(figsize=(7, 5), dpi=110)
    for name, class_id in table.outcome_ids.items():
        idx = [i for i, n in enumerate(names) if n == name]
        if idx:
            colour = np.array(table.colours[class_id]) / 255.0
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
    ax.set_xlabel("centre of mass beyond the target region / edge thickness (clipped)")
    ax.set_ylabel("volume outside the target region (log scale, 0 = none, 1 = all)")
    ax.set_title(f"Discovered outcomes: {report['n_clusters']} clusters, "
                 f"ARI vs geometry {report['ari_vs_geometry']:.4f}")
    ax.legend(loc="center right", fontsize=8, markerscale=2)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
