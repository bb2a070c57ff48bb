"""One (code, model) pair of bench/revision.py: ``segment()`` timed in blocks on request.

    python bench/_segment_worker.py --model tote --frames frames.npz

Run with PYTHONPATH set to the code under test (a revision unpacked by bench/revision.py, or
this checkout), so that ``task_outcome_ros`` is that code's. It loads the model (ONNX Runtime,
one thread, as the node runs it on one core), warms up, prints one JSON line saying which
code and model it runs, then waits: each line ``N`` on stdin times the next N frames (in
order, cycling) and answers with a JSON line of their times in ms (and, keeping the support
plane, how often it was kept and fitted so far); ``quit`` ends it. Waiting
on stdin costs no CPU, so only the worker asked works at any moment.

Only the API every revision has is used: ``OutcomeSegmenter(model, backend=, num_threads=)``,
``segment(depth, intrinsics)`` and ``camera.Intrinsics``; ``--reuse-floor-fit`` is passed
on only to code that has the option (``reuse_floor_fit``), and the hello line says so.
"""

from __future__ import annotations

import argparse
import inspect
import json
import sys
import time

import numpy as np
from common import static_camera_copy  # bench/common.py: this script's folder is on sys.path


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--model", required=True, help="a shipped model's name")
    parser.add_argument("--frames", required=True, help=".npz of depth (N, H, W) and cameras")
    parser.add_argument("--warmup", type=int, default=20)
    parser.add_argument("--reuse-floor-fit", action="store_true",
                        help="keep the support plane while it fits, where the code can")
    parser.add_argument("--copies", type=int, default=1,
                        help="each frame this many times in a row, each time with fresh 2 mm "
                             "noise drawn from the frame's position in the sequence (so "
                             "every worker sees the same frames), when more than 1")
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
    model = None if args.model == "default" else args.model
    options = {"backend": "onnx", "num_threads": 1}
    reuse = False
    if args.reuse_floor_fit and "reuse_floor_fit" in inspect.signature(
            OutcomeSegmenter).parameters:   # code older than the option refits every frame
        options["reuse_floor_fit"] = reuse = True
    seg = OutcomeSegmenter(model, **options)
    for i in range(args.warmup):
        seg.segment(depths[i % len(depths)], cameras[i % len(depths)])
    tracker = getattr(seg, "floor_tracker", None)
    if tracker is not None:
        tracker.reset()
        tracker.reused = tracker.refits = 0   # count the timed frames only
    print(json.dumps({"code": task_outcome_ros.__file__, "model": str(seg.model_path),
                      "backend": seg.backend, "reuse_floor_fit": reuse}), flush=True)
    copies = max(args.copies, 1)

    def frame(k: int) -> tuple[np.ndarray, object]:
        """The k-th frame of the sequence (made before its timer starts)."""
        i = (k // copies) % len(depths)
        depth = depths[i]
        if copies > 1:   # a static camera: the same view, fresh noise on its valid pixels
            depth = static_camera_copy(depth, np.random.default_rng(k))
        return depth, cameras[i]

    k = 0
    for line in sys.stdin:
        if line.strip() == "quit":
            break
        times = []
        for _ in range(int(line)):
            depth, camera = frame(k)
            k += 1
            t0 = time.perf_counter()
            seg.segment(depth, camera)
            times.append((time.perf_counter() - t0) * 1e3)
        planes = None if tracker is None else {"kept": tracker.reused,
                                               "fitted": tracker.refits}
        print(json.dumps({"ms": times, "planes": planes}), flush=True)


if __name__ == "__main__":
    main()
