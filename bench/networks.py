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
import io
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import percentiles, record  # noqa: E402

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


def onnx_session(model_args: dict, size: tuple[int, int]):
    """An ONNX Runtime session (1 thread, all graph optimisations, as the node's) of an
    untrained network built from ``model_args``, and an input of ``size`` (W, H)."""
    import onnxruntime as ort
    import torch

    from task_outcome_ros.model import build_model
    from task_outcome_ros.onnx_export import DEFAULT_OPSET

    model = build_model(model_args).eval()
    w, h = size
    x = torch.zeros(1, model_args["in_channels"], h, w)
    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # tracer warnings about the padding arithmetic
        torch.onnx.export(model, (x,), buf, input_names=["input"], output_names=["logits"],
                          opset_version=DEFAULT_OPSET, dynamo=False)
    opts = ort.SessionOptions()
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.intra_op_num_threads = opts.inter_op_num_threads = 1
    session = ort.InferenceSession(buf.getvalue(), opts, providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(0)
    return session, rng.standard_normal((1, *x.shape[1:])).astype(np.float32)


def main() -> None:
    from task_outcome_ros.model import DEFAULT_MODEL_ARGS, build_model, count_parameters

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=8, help="interleaved rounds")
    parser.add_argument("--runs", type=int, default=15, help="timed runs per network a round")
    parser.add_argument("--quick", action="store_true", help="smoke run: 2 rounds of 3")
    args = parser.parse_args()
    if args.quick:
        args.rounds, args.runs = 2, 3
    sessions = {}
    for name, (extra, size) in NETWORKS.items():
        model_args = {**DEFAULT_MODEL_ARGS, **extra}
        session, x = onnx_session(model_args, size)
        session.run(None, {"input": x})  # warm-up
        sessions[name] = (session, x, model_args, size)
    times: dict[str, list[float]] = {name: [] for name in sessions}
    for r in range(args.rounds):
        order = list(sessions)[r % len(sessions):] + list(sessions)[:r % len(sessions)]
        for name in order:
            session, x = sessions[name][:2]
            for _ in range(args.runs):
                t0 = time.perf_counter()
                session.run(None, {"input": x})
                times[name].append((time.perf_counter() - t0) * 1e3)
    reference = float(np.median(times[next(iter(times))]))
    configs = {}
    for name, (_, _, model_args, size) in sessions.items():
        configs[name] = {"model_args": model_args, "input_size": list(size),
                         "parameters": count_parameters(build_model(model_args)),
                         "network_ms": percentiles(times[name]),
                         "ratio_to_first": round(float(np.median(times[name])) / reference, 2)}
        print(f"{name}: p50 {configs[name]['network_ms']['p50']} ms, "
              f"{configs[name]['ratio_to_first']}x")
    record("networks", {"backend": "onnx", "threads": 1, "rounds": args.rounds,
                        "runs_per_round": args.runs, "configs": configs},
           "python bench/networks.py" + (" --quick" if args.quick else ""))


if __name__ == "__main__":
    main()
