"""Benchmark the network alone, untrained, for a few architectures: ONNX Runtime, 1 thread.

    python bench/networks.py            # 8 interleaved rounds of 15 runs per network (~1 min)
    python bench/networks.py --quick    # a smoke run (2 rounds of 3)

Why: choosing an architecture for a finer working size needs its cost before an hour of
training. The network's time does not follow its multiply-adds at a few channels (ONNX
Runtime blocks channels, so a 4-channel conv costs about what a 16-channel one does), so it
is measured, not computed. The networks run interleaved in short rounds, so a change in
machine load hits them all alike; compare them as ratios to the first (the default model's
network), within one run.

Writes the ``networks`` section of bench/results.json.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import (  # noqa: E402
    exported_checkpoint,
    percentiles,
    record,
    rotated,
    untrained_network,
)

# name -> (model_args on top of the default model's, input size (W, H)). The first is the
# reference the ratios are taken to.
NETWORKS: dict[str, tuple[dict, tuple[int, int]]] = {
    "default (160 x 120)": ({}, (160, 120)),
    "plain at 320 x 240 (shelf 0.16.0)": ({}, (320, 240)),
    "thin 320 x 240 level (--base-width 4 --levels 6)": (
        {"base_width": 4, "levels": 6}, (320, 240)),
    "thin 320 x 240 level, 8-channel head (--head-width 8)": (
        {"base_width": 4, "levels": 6, "head_width": 8}, (320, 240)),
}


def exported_network(model_args: dict, size: tuple[int, int], tmp: Path):
    """An untrained network of ``model_args`` for a working ``size`` (W, H), saved as a
    checkpoint in ``tmp`` and exported as the package exports a shipped model; its ONNX
    Runtime session as the node opens it (1 thread), an input, and its parameter count."""
    from task_outcome_ros.inference import onnx_session
    from task_outcome_ros.model import count_parameters
    from task_outcome_ros.onnx_export import onnx_path_for

    net = untrained_network(model_args)
    path = exported_checkpoint(tmp / "network.pt", net, model_args, input_size=size)
    session = onnx_session(onnx_path_for(path), num_threads=1)
    w, h = size
    x = np.random.default_rng(0).standard_normal(
        (1, model_args["in_channels"], h, w)).astype(np.float32)
    return session, x, count_parameters(net)


def main() -> None:
    from task_outcome_ros.model import DEFAULT_MODEL_ARGS

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=8, help="interleaved rounds")
    parser.add_argument("--runs", type=int, default=15, help="timed runs per network a round")
    parser.add_argument("--quick", action="store_true", help="smoke run: 2 rounds of 3")
    args = parser.parse_args()
    if args.quick:
        args.rounds, args.runs = 2, 3
    networks = {}
    with tempfile.TemporaryDirectory(prefix="bench_networks_") as tmp:
        for k, (name, (extra, size)) in enumerate(NETWORKS.items()):
            model_args = {**DEFAULT_MODEL_ARGS, **extra}
            folder = Path(tmp) / str(k)
            folder.mkdir()
            networks[name] = (*exported_network(model_args, size, folder), model_args, size)
    times: dict[str, list[float]] = {name: [] for name in networks}
    for name in networks:  # warm-up
        session, x = networks[name][:2]
        session.run(None, {"input": x})
    for r in range(args.rounds):
        for name in rotated(list(networks), r):
            session, x = networks[name][:2]
            for _ in range(args.runs):
                t0 = time.perf_counter()
                session.run(None, {"input": x})
                times[name].append((time.perf_counter() - t0) * 1e3)
    reference = float(np.median(times[next(iter(times))]))
    configs = {}
    for name, (_, _, parameters, model_args, size) in networks.items():
        configs[name] = {"model_args": model_args, "input_size": list(size),
                         "parameters": parameters, "network_ms": percentiles(times[name]),
                         "ratio_to_first": round(float(np.median(times[name])) / reference, 2)}
        print(f"{name}: p50 {configs[name]['network_ms']['p50']} ms, "
              f"{configs[name]['ratio_to_first']}x")
    record("networks", {"backend": "onnx", "threads": 1, "rounds": args.rounds,
                        "runs_per_round": args.runs, "configs": configs},
           "python bench/networks.py" + (" --quick" if args.quick else ""))


if __name__ == "__main__":
    main()
