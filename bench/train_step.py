"""Benchmark one training step of the outcome FCN on this CPU: where the time goes, whether
bf16 autocast or channels-last memory format would help, and what the IoU loss costs.

    python bench/train_step.py              # 5 configurations x 24 timed steps (~4 min on 2 cores)
    python bench/train_step.py --steps 48
    python bench/train_step.py --quick      # a smoke run (native precisions only)
    python bench/train_step.py --model tote --run runs/tote   # another shipped model's recipe

A step is what ``training.train`` does per batch of 32 at 160 x 120 (the ``TrainConfig``
defaults), through the training loop's own functions: ``gather_batch`` (gather + augment),
``network_input`` (incl. the floor fit for the height channel), ``optimise_step`` (forward +
class-weighted loss + backward + AdamW) and the weight-average update. The network
configurations (fp32 / bf16 autocast, each contiguous / channels-last, with cross-entropy
alone; and the training default, bf16 + channels-last with the per-image outcome IoU loss of
training/losses.py added) run interleaved in rotating blocks so load changes on the shared
machine hit them alike. Batches come from the default run's working-size cache when it
exists, else synthetic depth.

``--model`` (a shipped task's name or a checkpoint) times that model's recipe instead: its
input channels (normalisation: heights from the support plane of a task on a table, local
relief), its network's classes and the augmentations it was trained with (holes, roll,
noise level; the noise level unscaled by the task's sensor), on the images of ``--run``.

Writes the ``training`` section of bench/results.json, ``training.<task>`` with ``--model``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import cached_training_images, percentiles, record, rotated  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
# (autocast dtype, channels-last, IoU loss on); the last one is the TrainConfig default.
CONFIGS = (("fp32", False, False), ("fp32", True, False), ("bf16", False, False),
           ("bf16", True, False), ("bf16", True, True))


def load_arrays(size: tuple[int, int], run: Path = REPO / "runs" / "default"
                ) -> tuple[dict, str]:
    from task_outcome_ros.labels import DEFAULT_TABLE

    cached = cached_training_images(run, size, 512)
    if cached is not None:
        return cached
    rng = np.random.default_rng(0)
    w, h = size
    v = np.linspace(-0.3, 0.3, h, dtype=np.float32)[:, None]
    depth = (2.0 + v + rng.normal(0, 0.004, (512, h, w))).astype(np.float32)
    return ({"depth": depth, "valid": np.ones_like(depth),
             "labels": rng.integers(0, DEFAULT_TABLE.num_classes, depth.shape).astype(np.uint8)},
            "synthetic tilted planes (no cache in --run)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=24, help="timed steps per configuration")
    ap.add_argument("--quick", action="store_true",
                    help="4 timed steps per configuration, bf16 only where it is native")
    ap.add_argument("--model", help="a shipped task's name or a checkpoint whose recipe to "
                    "time (default: the TrainConfig defaults, the default task's input)")
    ap.add_argument("--run", type=Path, default=REPO / "runs" / "default",
                    help="run whose training cache gives the images (default runs/default)")
    args = ap.parse_args()
    steps = 4 if args.quick else args.steps
    block = 2 if args.quick else 4

    import torch

    from training.train import cpu_has_native_bf16

    # Emulated bf16 runs ~10x slower than fp32: a smoke run on such a CPU skips it (the full
    # run still times it, to show why training falls back to fp32 there).
    native_bf16 = cpu_has_native_bf16()
    configs = CONFIGS if native_bf16 or not args.quick else \
        tuple(c for c in CONFIGS if c[0] != "bf16")

    from task_outcome_ros.inference import resolve_model_path
    from task_outcome_ros.model import DEFAULT_NORMALISATION, build_model, network_input
    from training.augment import Augmentations, gather_batch, measure_for_roll
    from training.config import TrainConfig
    from training.train import (
        WeightAverage,
        autocast_factory,
        class_weights,
        optimise_step,
    )

    cfg, norm, model_args, task = TrainConfig(), DEFAULT_NORMALISATION, None, None
    model_path = resolve_model_path(args.model) if args.model else None
    if model_path:
        cfg, norm, model_args, task = model_recipe(model_path)
    model_args = model_args or cfg.model_args
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(0)
    arrays, source = load_arrays(cfg.input_size, args.run)
    if cfg.aug_roll_deg > 0:       # as the training loop does: each image measured once
        measure_for_roll(arrays)
    n = len(arrays["depth"])
    # The model's classes, as the nets below have (the timing does not depend on them).
    weights = class_weights(arrays["labels"], cfg.class_weight_power,
                            model_args["num_classes"])
    nets = {}
    for dtype, channels_last, iou_loss in configs:
        net = build_model(model_args)
        if channels_last:
            net = net.to(memory_format=torch.channels_last)
        optim = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
        nets[dtype, channels_last, iou_loss] = (net.train(), optim,
                                                WeightAverage(net, cfg.ema_decay))
    timings = {c: {"data": [], "network_input": [], "step": [], "average": [], "total": []}
               for c in configs}
    # The noise, holes and roll the section's "augment" records (the islands and the range
    # limit's band are not timed here).
    timed_augmentations = Augmentations(noise_level=cfg.aug_noise, holes=cfg.aug_holes,
                                        roll_deg=cfg.aug_roll_deg)
    gen = torch.Generator().manual_seed(0)

    def one_step(config) -> None:
        net, optim, average = nets[config]
        t0 = time.perf_counter()
        idx = np.sort(torch.randint(0, n, (cfg.batch_size,), generator=gen).numpy())
        depth, valid, labels = gather_batch(arrays, idx, gen, timed_augmentations)[:3]
        t1 = time.perf_counter()
        x = network_input(depth, valid, norm)
        if config[1]:
            x = x.contiguous(memory_format=torch.channels_last)
        t2 = time.perf_counter()
        optimise_step(net, optim, x, labels, weights, autocast_factory(config[0], "cpu"), None,
                      cfg.lovasz_weight if config[2] else 0.0)
        t3 = time.perf_counter()
        average.update(net)
        t4 = time.perf_counter()
        for key, value in (("data", t1 - t0), ("network_input", t2 - t1), ("step", t3 - t2),
                           ("average", t4 - t3), ("total", t4 - t0)):
            timings[config][key].append(value * 1e3)

    for config in configs:  # warm-up: allocator, oneDNN kernels
        for _ in range(2):
            one_step(config)
        for values in timings[config].values():
            values.clear()
    started = time.perf_counter()
    for r in range(0, steps, block):
        for config in rotated(configs, r // block):
            for _ in range(min(block, steps - r)):
                one_step(config)
    wall = time.perf_counter() - started

    def name(config) -> str:
        return (f"{config[0]}_{'channels_last' if config[1] else 'contiguous'}"
                + ("_iou_loss" if config[2] else ""))

    results = {name(c): {k: percentiles(v) for k, v in timings[c].items()} for c in configs}
    base = results["fp32_contiguous"]["total"]["p50"]
    record("training" if task is None else f"training.{task}", {
        "model": args.model, "normalisation": norm,
        "augment": {"noise": cfg.aug_noise, "holes": cfg.aug_holes, "roll_deg": cfg.aug_roll_deg},
        "batch": cfg.batch_size, "input_size": list(cfg.input_size), "threads": cfg.threads,
        "model_args": model_args, "data": source, "timed_steps_per_config": steps,
        "iou_loss_weight": cfg.lovasz_weight, "cpu_native_bf16": native_bf16,
        "wall_s": round(wall, 1), "configs": results,
        "total_p50_over_fp32_contiguous": {k: round(v["total"]["p50"] / base, 2)
                                           for k, v in results.items()},
        "epoch_s_estimate_fp32": round(base / 1e3 * 9500 / cfg.batch_size, 1),
        "versions": {"torch": torch.__version__},
        "note": "ms per training step of one batch; step = training.train.optimise_step "
                "(forward + class-weighted loss + backward + AdamW); *_iou_loss adds the "
                "per-image outcome IoU loss (training/losses.py) as training does by default; "
                "configurations interleaved in rotating blocks; shared, noisy machine",
    }, command="python bench/train_step.py " + " ".join(sys.argv[1:]),
        model=model_path)


def model_recipe(model_path: Path):
    """(TrainConfig, normalisation, model_args, task) of a checkpoint: what its training loop
    ran, so that its step can be timed."""
    from task_outcome_ros.checkpoint import load
    from training.config import TrainConfig, _from_dict
    from training.train import RENAMED_TRAIN_FIELDS

    loaded = load(model_path)
    # Rebuilt as a saved dataset config is (lists to tuples, unknown fields refused), older
    # field names under today's.
    trained = {RENAMED_TRAIN_FIELDS.get(k, k): v
               for k, v in loaded.train_config.get("train", {}).items()}
    task = (loaded.train_config.get("dataset") or {}).get("task", "default")
    return _from_dict(TrainConfig, trained), loaded.normalisation, loaded.model_args, task


if __name__ == "__main__":
    main()
