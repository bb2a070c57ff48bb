"""Benchmark the training loop's data step with the camera-roll augmentation: what the turn
costs a batch, and what measuring each cached image's noise and depth edges once
(``augment.measure_for_roll``) saves against measuring them in every batch.

    python bench/roll_step.py                       # 3 configurations x 60 batches (seconds)
    python bench/roll_step.py --run runs/tote --batches 120
    python bench/roll_step.py --quick               # a smoke run

A data step is ``augment.gather_batch`` on a batch of 32 at 160 x 120 (the ``TrainConfig``
defaults) at the training loop's thread count: gather, then augment (roll 15 degrees as
``--aug-roll 15`` does, mirror, shift, distance change, re-drawn noise). The configurations
(no roll; roll measuring in the batch; roll with the images measured once) run interleaved
batch by batch, so load changes on the shared machine hit them alike; compare them as ratios.
Batches come from ``--run``'s working-size training cache when it exists, else synthetic
tilted planes with a box.

Writes the ``roll_step`` section of bench/results.json.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import cached_training_images, percentiles, record  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
ROLL_DEG = 15.0  # shelf model 0.14.0's --aug-roll


def load_arrays(run: Path, size: tuple[int, int], count: int) -> tuple[dict, str]:
    cached = cached_training_images(run, size, count)
    if cached is not None:
        return cached
    rng = np.random.default_rng(0)
    w, h = size
    depth = np.broadcast_to(2.0 + np.linspace(-0.3, 0.3, h)[:, None], (count, h, w)).copy()
    depth[:, h // 3:h // 2, w // 3:w // 2] -= 0.2                     # a box: depth edges
    depth *= 1 + rng.normal(0, 0.002, depth.shape)
    return ({"depth": depth.astype(np.float16),
             "valid": np.ones(depth.shape, np.float16),
             "labels": rng.integers(0, 5, depth.shape).astype(np.uint8)},
            "synthetic tilted planes with a box (no cache in --run)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run", type=Path, default=REPO / "runs" / "default",
                    help="run whose training cache gives the images (default runs/default)")
    ap.add_argument("--batches", type=int, default=60, help="timed batches per configuration")
    ap.add_argument("--quick", action="store_true", help="4 batches each, a smoke run")
    args = ap.parse_args()
    batches = 4 if args.quick else args.batches

    import torch

    from training.augment import Augmentations, gather_batch, measure_for_roll
    from training.config import TrainConfig

    cfg = TrainConfig()
    torch.set_num_threads(cfg.threads)
    plain, source = load_arrays(args.run, cfg.input_size, 512)
    measured = dict(plain)
    started = time.perf_counter()
    measure_for_roll(measured)
    measure_once_ms = (time.perf_counter() - started) * 1e3
    configs = {"no_roll": (plain, 0.0), "roll_measured_per_batch": (plain, ROLL_DEG),
               "roll_measured_once": (measured, ROLL_DEG)}
    timings = {name: [] for name in configs}
    gen = torch.Generator().manual_seed(0)
    n = len(plain["depth"])
    for b in range(batches + 2):                     # the first two warm the allocator up
        idx = np.sort(torch.randint(0, n, (cfg.batch_size,), generator=gen).numpy())
        for name, (arrays, roll_deg) in configs.items():
            t0 = time.perf_counter()
            gather_batch(arrays, idx, torch.Generator().manual_seed(b),
                         Augmentations(roll_deg=roll_deg))
            if b >= 2:
                timings[name].append((time.perf_counter() - t0) * 1e3)
    medians = {name: float(np.median(t)) for name, t in timings.items()}
    record("roll_step", {
        "images": source, "batch_size": cfg.batch_size, "input_size": list(cfg.input_size),
        "threads": cfg.threads, "roll_deg": ROLL_DEG,
        "configs": {name: percentiles(t) for name, t in timings.items()},
        "measure_once_ms_per_image": round(measure_once_ms / n, 3),
        "roll_cost_ratio_measured_once_vs_per_batch": round(
            (medians["roll_measured_once"] - medians["no_roll"])
            / (medians["roll_measured_per_batch"] - medians["no_roll"]), 3)},
        "python bench/roll_step.py" + "".join(f" {a}" for a in sys.argv[1:]))


if __name__ == "__main__":
    main()
