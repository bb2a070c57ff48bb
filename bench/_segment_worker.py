"""One (code, model) pair of bench/revision.py: ``segment()`` timed in blocks on request.

    python bench/_segment_worker.py --model tote --frames frames.npz

Run with PYTHONPATH set to the code under test (a revision unpacked by bench/revision.py, or
this checkout), so that ``task_outcome_ros`` is that code's. It loads the model (ONNX Runtime,
one thread, as the node runs it on one core), warms up, prints one JSON line saying which
code and model it runs, then waits: each line ``N`` on stdin times the next N frames (in
order, cycling) and answers with a JSON line of their times in ms; ``quit`` ends it. Waiting
on stdin costs no CPU, so only the worker asked works at any moment.

Only the API every revision has is used: ``OutcomeSegmenter(model, backend=, num_threads=)``,
``segment(depth, intrinsics)`` and ``camera.Intrinsics``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--model", required=True, help="a shipped model's name")
    parser.add_argument("--frames", required=True, help=".npz of depth (N, H, W) and cameras")
    parser.add_argument("--warmup", type=int, default=20)
    args = parser.parse_args()

    import cv2
    import torch

    import task_outcome_ros
    from task_outcome_ros.camera import Intrinsics
    from task_outcome_ros.inference import OutcomeSegmenter

    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    with np.load(args.frames) as data:
        depths = list(data["depth"])
        # (width, height, fx, fy, cx, cy) per frame; width 0: no camera_info
        cameras = [None if c[0] == 0 else Intrinsics(int(c[0]), int(c[1]), *map(float, c[2:]))
                   for c in data["cameras"]]
    seg = OutcomeSegmenter(None if args.model == "default" else args.model,
                           backend="onnx", num_threads=1)
    for i in range(args.warmup):
        seg.segment(depths[i % len(depths)], cameras[i % len(depths)])
    print(json.dumps({"code": task_outcome_ros.__file__, "model": str(seg.model_path),
                      "backend": seg.backend}), flush=True)
    k = 0
    for line in sys.stdin:
        if line.strip() == "quit":
            break
        times = []
        for _ in range(int(line)):
            depth, camera = depths[k % len(depths)], cameras[k % len(depths)]
            k += 1
            t0 = time.perf_counter()
            seg.segment(depth, camera)
            times.append((time.perf_counter() - t0) * 1e3)
        print(json.dumps(times), flush=True)


if __name__ == "__main__":
    main()
