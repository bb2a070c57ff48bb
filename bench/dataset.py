"""Benchmark the dataset run: wall time per stage (episodes/s), discovery figures, memory.

    python bench/dataset.py                      # the default 10,000-episode run (~5 min)
    python bench/dataset.py --episodes 2000 --seeds 5   # discovery stability over seeds
    python bench/dataset.py --scene tote --seeds 5 --seed-episodes 1500 --seeds-only
    python bench/dataset.py --scene shelf --seeds 5 --seed-episodes 1500 --seeds-only

Writes the ``dataset`` (and ``discovery_seeds``) sections of bench/results.json; with
``--scene`` other than default, ``dataset.<scene>`` and ``discovery_seeds.<scene>``.
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import record  # noqa: E402


def run_dataset(out: Path, episodes: int, seed: int, workers: int, scene: str) -> dict:
    cmd = [sys.executable, "-m", "training", "dataset", "--out", str(out), "--episodes",
           str(episodes), "--seed", str(seed), "--workers", str(workers), "--scene", scene]
    start = time.perf_counter()
    subprocess.run(cmd, check=True)
    wall = time.perf_counter() - start
    timings = json.loads((out / "timings.json").read_text())["seconds"]
    discovery = json.loads((out / "discovery.json").read_text())
    return {"wall_s": round(wall, 1), "stage_s": timings,
            "episodes_per_s": {k: round(episodes / v, 1) for k, v in timings.items() if v > 0},
            "discovery": {k: discovery[k] for k in ("n_clusters", "cluster_names",
                                                    "outcome_fractions", "ari_vs_geometry",
                                                    "noise_points")}}


def memory_slope(episodes: int = 3000) -> dict:
    """RSS of one simulation world over many episodes: it must not grow per episode."""
    from training.config import SceneConfig
    from training.simulate import World, simulate_episode

    world = World(SceneConfig())
    samples = []
    for i in range(episodes):
        simulate_episode(world, 0, i)
        if i % 500 == 499:
            samples.append((i + 1, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss))
    first, last = samples[0], samples[-1]
    return {"episodes": episodes, "max_rss_kb": [s[1] for s in samples],
            "growth_kb_per_1000_episodes": round(1000 * (last[1] - first[1])
                                                 / (last[0] - first[0]), 1)}


def dataset_disk_mb(out: Path) -> float:
    return round(sum(p.stat().st_size for p in (out / "images").glob("*.png")) / 1e6, 1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--episodes", type=int, default=10_000)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seeds", type=int, default=0,
                        help="also check discovery on this many seeds (at --seed-episodes)")
    parser.add_argument("--seed-episodes", type=int, default=2000)
    parser.add_argument("--seeds-only", action="store_true",
                        help="skip the 10,000-episode run; only the discovery seed check")
    parser.add_argument("--out", type=Path, default=None,
                        help="run folder, wiped first (default: runs/bench_dataset)")
    parser.add_argument("--scene", default="default", help="scene spec (default: default)")
    args = parser.parse_args()
    suffix = "" if args.scene == "default" else f".{Path(args.scene).stem}"
    command = "python bench/dataset.py " + " ".join(sys.argv[1:])
    out = args.out or Path("runs/bench_dataset")  # never runs/default: it is wiped first
    if not args.seeds_only:
        if out.exists():
            shutil.rmtree(out)  # resuming an earlier run would make the timing meaningless
        data = run_dataset(out, args.episodes, 0, args.workers, args.scene)
        data.update(episodes=args.episodes, workers=args.workers, out=str(out),
                    images_mb=dataset_disk_mb(out), memory=memory_slope())
        record("dataset" + suffix, data, command)
    if args.seeds:
        per_seed = []
        for seed in range(1, args.seeds + 1):
            with tempfile.TemporaryDirectory() as tmp:
                cmd = [sys.executable, "-m", "training", "simulate", "--out", tmp,
                       "--episodes", str(args.seed_episodes), "--seed", str(seed),
                       "--scene", args.scene]
                subprocess.run(cmd, check=True, stderr=subprocess.DEVNULL)
                subprocess.run([*cmd[:3], "discover", "--out", tmp, "--scene", args.scene],
                               check=True)
                d = json.loads((Path(tmp) / "discovery.json").read_text())
            per_seed.append({"seed": seed, "n_clusters": d["n_clusters"],
                             "ari_vs_geometry": d["ari_vs_geometry"],
                             "cluster_names": d["cluster_names"],
                             "outcome_fractions": d["outcome_fractions"]})
        record("discovery_seeds" + suffix, {
            "episodes": args.seed_episodes, "runs": per_seed,
            "all_three_clusters": all(r["n_clusters"] == 3 for r in per_seed),
            "min_ari_vs_geometry": min(r["ari_vs_geometry"] for r in per_seed)}, command)


if __name__ == "__main__":
    main()
