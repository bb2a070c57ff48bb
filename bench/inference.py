"""Benchmark ``OutcomeSegmenter.segment`` on 640 x 480 depth: torch vs ONNX, 1 vs 2 threads,
and a task's model against the default model.

    python bench/inference.py                 # 300 timed frames per configuration (~1-3 min)
    python bench/inference.py --frames 500
    python bench/inference.py --quick         # a smoke run (~20 s)
    python bench/inference.py --model shelf   # another shipped model, on its own run's frames
    python bench/inference.py --model tote --static-camera 30   # the node's case: see below

The configurations (backend torch/onnx x threads 1/2, and the reference model's) run
interleaved in short blocks, in a rotating order, so a change in machine load hits them all
alike; ``paired_ratio`` compares neighbouring blocks only. Each timed frame is one
``segment()`` call (the node's code path); the same frame run through its stages one by one
(the segmenter's own preprocessing, network and ``postprocess``) gives the breakdown
(preprocess / network / post).
A random-init model labels everything background, so its post stage (fragments, resize back,
presence, connected components: ``OutcomeSegmenter.postprocess``) is also timed on the
dataset's ground-truth labels at the working size, which is what a trained model would produce.

With ``--model <name>`` the default task's model is timed beside it (``--reference``), ONNX
Runtime on the first thread count, on its own frames, its blocks next to the measured model's
ONNX blocks on that thread count: whether a task's model costs more than the default's
``segment()`` is the question, and on a shared machine whose speed drifted 1.7x within a day
only a ratio within one run answers it. When either model's run folder is missing, both
models get the same synthetic frames, so that the ratio compares models, not frames.

``--static-camera COPIES``: each frame comes COPIES times in a row with fresh 2 mm noise and
the segmenters keep their support plane while it still fits (``reuse_floor_fit``, as the node
does for a camera that does not move), so the plane is fitted once per COPIES frames. Without
it every frame has its own camera and is fitted afresh: the worst case.

Writes the ``inference`` section of bench/results.json (``inference.<name>`` for
``--model <name>``; ``inference_static`` and ``inference_static.<name>`` with
``--static-camera``).
"""

from __future__ import annotations

import argparse
import os
import shutil
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
    sha256,
    static_camera_copy,
    static_camera_description,
    untrained_network,
)

REPO = Path(__file__).resolve().parents[1]
RUN_DIR = REPO / "runs" / "default"
SIZE = (640, 480)  # (W, H)
MODEL, REFERENCE = "model", "reference"  # the model measured; the one it is compared with


# ---- shared with bench/node.py -------------------------------------------------------------

def prepare_model(tmp: Path, shipped: Path | None = None) -> tuple[Path, str]:
    """(checkpoint path with a matching .onnx beside it, description of where it came from).

    The shipped checkpoint ``shipped`` (default: the default task's) when there is one (copied
    to ``tmp`` and exported there if its ONNX file is missing or stale; the package folder is
    never written), else a random-init checkpoint of the default architecture: same compute
    cost, meaningless labels.
    """
    from task_outcome_ros.checkpoint import file_sha256
    from task_outcome_ros.inference import default_model_path
    from task_outcome_ros.onnx_export import (
        META_SOURCE_SHA256,
        export_onnx,
        onnx_path_for,
        read_metadata,
    )

    shipped = default_model_path() if shipped is None else shipped
    if shipped.is_file():
        onnx = onnx_path_for(shipped)
        try:
            fresh = read_metadata(onnx).get(META_SOURCE_SHA256) == file_sha256(shipped)
        except Exception:  # missing or unreadable ONNX file
            fresh = False
        if fresh:
            return shipped, f"shipped {shipped} (+ its ONNX export)"
        path = tmp / shipped.name
        shutil.copyfile(shipped, path)
        export_onnx(path)
        return path, f"shipped {shipped} (ONNX exported to a temp dir)"

    from task_outcome_ros.model import DEFAULT_MODEL_ARGS

    args = dict(DEFAULT_MODEL_ARGS)
    path = exported_checkpoint(tmp / "outcome_fcn.pt", untrained_network(args), args)
    return path, ("random-init checkpoint, default architecture (no shipped model at "
                  f"{shipped}); same compute cost, labels meaningless")


# One level, 2 channels then 4 (455 parameters with 3 inputs and 5 classes); capping the level
# at 2 channels too would save 170 more, nothing next to the frame's other work.
TINY_NETWORK_ARGS = {"base_width": 2, "levels": 1, "decoder_convs": 1, "max_width": None}


def tiny_network_model(source: Path, tmp: Path) -> tuple[Path, str]:
    """``source``'s checkpoint with its network swapped for a one-level ``OutcomeFCN`` of the
    same inputs and classes (seed 0), exported to ONNX in ``tmp``.

    Everything else the node does with ``source`` stays: the working size, the height channel
    and its floor fit, the label table, the envelope. So a node running it costs what the
    real one costs but for the network: a bound on how far a cheaper network could take the
    node. Its head answers background everywhere (weights 0, background's bias 1): a random
    head scatters every class over the frame and makes postprocessing (components, fragments)
    cost far more than a trained network's; an empty answer makes it cost least, so the bound
    is a lower one."""
    import torch

    from task_outcome_ros import checkpoint, model

    real = checkpoint.load(source)
    args = {**real.model_args, **TINY_NETWORK_ARGS}
    net = untrained_network(args)
    with torch.no_grad():
        net.head.weight.zero_()
        net.head.bias.zero_()
        net.head.bias[0] = 1.0           # id 0: background, in every label table
    path = exported_checkpoint(tmp / "tiny_network.pt", net, args, input_size=real.input_size,
                               normalisation=real.normalisation,
                               train_config=real.train_config, label_table=real.label_table)
    return path, (f"{source.name} with its network swapped for {args} "
                  f"({model.count_parameters(net)} parameters, random init, the head "
                  "answering background everywhere): the node's cost but the network's, "
                  "with nothing to report")


def synth_frame(rng: np.random.Generator) -> np.ndarray:
    """A tilted floor plane at ~2 m with a few boxes and invalid (NaN) speckle, 640 x 480."""
    w, h = SIZE
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    depth = 2.0 + 0.3 * (v / h - 0.5) + 0.05 * (u / w - 0.5)
    for _ in range(rng.integers(2, 6)):
        bw, bh = rng.integers(30, 160, 2)
        x, y = rng.integers(0, w - bw), rng.integers(0, h - bh)
        depth[y:y + bh, x:x + bw] -= rng.uniform(0.05, 0.4)
    depth += rng.normal(0, 0.003, depth.shape).astype(np.float32)
    depth[rng.random(depth.shape) < 0.02] = np.nan
    return depth.astype(np.float32)


def load_frames(n: int, run_dir: Path = RUN_DIR
                ) -> tuple[list[np.ndarray], list[np.ndarray | None], list, str]:
    """``n`` 640 x 480 float32 depth frames, their true labels and cameras (``Intrinsics``, what
    camera_info carries) when they come from the dataset run ``run_dir``, else None each, and
    what they are."""
    if (run_dir / "manifest.json").is_file():
        import json

        from task_outcome_ros.camera import Intrinsics
        from training.render import read_pair

        images = json.loads((run_dir / "manifest.json").read_text())["images"]
        depths, labels, cameras = [], [], []
        for index in np.linspace(0, len(images) - 1, n).astype(int):
            try:
                d, lab = read_pair(run_dir, int(images[index]["episode"]))
            except (ValueError, OSError):
                continue
            if d.shape == (SIZE[1], SIZE[0]):
                depths.append(d.astype(np.float32))
                labels.append(lab)
                cameras.append(Intrinsics.from_record(images[index]["camera"]))
        if len(depths) >= max(1, n // 2):
            return (depths, labels, cameras,
                    f"{len(depths)} images of {run_dir} (training.render.read_pair), with "
                    "their camera_info")
    rng = np.random.default_rng(0)
    return ([synth_frame(rng) for _ in range(n)], [None] * n, [None] * n,
            f"{n} synthetic frames (plane + boxes + 2 % NaN)")


def load_frames_for(n: int, run_dirs: dict[str, Path]) -> dict[str, tuple]:
    """``load_frames(n, run_dir)`` for each model's run folder; when any model gets synthetic
    frames, every model gets those same ones: frames of two kinds would time the frames as
    well as the models."""
    loaded = {who: load_frames(n, run_dir) for who, run_dir in run_dirs.items()}
    synthetic = [who for who, rows in loaded.items() if rows[1][0] is None]
    return {who: loaded[synthetic[0]] for who in loaded} if synthetic else loaded


def repeat_as_static_camera(copies: int, *tables: dict) -> None:
    """Each model's frames (``tables``: frames, true labels, cameras, descriptions, keyed by
    model) as a static camera sees them: every frame ``copies`` times in a row, the copies with
    fresh 2 mm Gaussian noise on their valid pixels (seed 0), the others as they were."""
    frames, true_labels, cameras, frames_desc = tables
    rng = np.random.default_rng(0)
    for who in list(frames):
        frames[who] = [static_camera_copy(f, rng) for f in frames[who] for _ in range(copies)]
        true_labels[who] = [lab for lab in true_labels[who] for _ in range(copies)]
        cameras[who] = [cam for cam in cameras[who] for _ in range(copies)]
        frames_desc[who] += static_camera_description(copies)


def load_average() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


# ---- the benchmark ---------------------------------------------------------------------------

def staged(seg, frame: np.ndarray, camera=None) -> tuple[float, float, float]:
    """segment() split in three timed stages (ms): preprocess, network (+argmax), post.

    The stages are the segmenter's own methods; only the split into timers is added here."""
    from task_outcome_ros.depth import sanitize_depth

    t0 = time.perf_counter()
    depth = sanitize_depth(frame)
    x = seg.prepare(depth, camera)
    t1 = time.perf_counter()
    small = seg._predict_small(x)
    t2 = time.perf_counter()
    seg.postprocess(small, depth)
    t3 = time.perf_counter()
    return (t1 - t0) * 1e3, (t2 - t1) * 1e3, (t3 - t2) * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=300,
                        help="timed segment() frames per configuration (default 300)")
    parser.add_argument("--block", type=int, default=10, help="frames per interleaved block")
    parser.add_argument("--warmup", type=int, default=20, help="untimed frames per configuration")
    parser.add_argument("--images", type=int, default=50, help="distinct frames to cycle through")
    parser.add_argument("--threads", default="1,2", help="comma-separated thread counts")
    parser.add_argument("--quick", action="store_true", help="smoke run: 60 frames, 20 images")
    parser.add_argument("--model", default="default",
                        help="a shipped model's name (default: %(default)s); its frames come "
                             "from runs/<name>, else synthetic ones")
    parser.add_argument("--reference", default=None,
                        help="a shipped model timed beside --model (ONNX, the first thread "
                             "count, its own frames) for the ratio of the two; default: the "
                             "default task's model when --model is another, 'none' for none")
    parser.add_argument("--static-camera", type=int, default=0, metavar="COPIES",
                        help="each frame COPIES times in a row with fresh 2 mm noise, the "
                             "plane kept while it fits (default 0: every frame refitted)")
    args = parser.parse_args()
    if args.static_camera < 0:
        parser.error(f"--static-camera must be >= 0, got {args.static_camera}")
    if args.reference is None:
        args.reference = "none" if args.model == "default" else "default"
    if args.quick:
        args.frames, args.images, args.warmup = min(args.frames, 60), min(args.images, 20), 5
    command = "python bench/inference.py " + " ".join(sys.argv[1:])

    import cv2
    import onnxruntime
    import torch

    from task_outcome_ros.inference import OutcomeSegmenter, resolve_model_path

    def run_dir(name: str) -> Path:
        return RUN_DIR if name == "default" else REPO / "runs" / name

    default = args.model == "default"
    shipped = resolve_model_path(None if default else args.model)
    threads = [int(t) for t in args.threads.split(",")]
    load_start = load_average()
    reference = None if args.reference == "none" else args.reference
    run_dirs = {MODEL: run_dir(args.model)}
    if reference is not None:
        run_dirs[REFERENCE] = run_dir(reference)
    loaded = load_frames_for(args.images, run_dirs)
    frames, true_labels, cameras, frames_desc = (
        {who: rows[k] for who, rows in loaded.items()} for k in range(4))
    if args.static_camera:
        repeat_as_static_camera(args.static_camera, frames, true_labels, cameras, frames_desc)
    with tempfile.TemporaryDirectory(prefix="bench_inference_") as tmp:
        model_path, model_desc = prepare_model(Path(tmp), shipped)
        paths = {MODEL: model_path}
        # (which model, backend, threads); the reference on ONNX Runtime, one thread count,
        # right after the measured model's blocks of the same setup.
        configs = [(MODEL, b, t) for t in threads for b in ("torch", "onnx")]
        if reference is not None:
            reference_dir = Path(tmp) / "reference"
            reference_dir.mkdir()
            reference_shipped = resolve_model_path(None if reference == "default" else reference)
            paths[REFERENCE], reference_desc = prepare_model(reference_dir, reference_shipped)
            configs.insert(configs.index((MODEL, "onnx", threads[0])) + 1,
                           (REFERENCE, "onnx", threads[0]))
        segs = {}
        for cfg in configs:
            segs[cfg] = OutcomeSegmenter(paths[cfg[0]], backend=cfg[1], num_threads=cfg[2],
                                         reuse_floor_fit=args.static_camera > 0)
            assert segs[cfg].backend == cfg[1], segs[cfg].backend_reason

        def use(cfg: tuple[str, str, int]):
            torch.set_num_threads(cfg[2])  # torch's pool is global; set before every block
            cv2.setNumThreads(cfg[2])
            return segs[cfg]

        for cfg in configs:
            seg, fr, cams = use(cfg), frames[cfg[0]], cameras[cfg[0]]
            for i in range(args.warmup):
                seg.segment(fr[i % len(fr)], cams[i % len(fr)])
                staged(seg, fr[i % len(fr)], cams[i % len(fr)])

        total = {c: [] for c in configs}
        stages = {c: ([], [], []) for c in configs}
        block_means = {c: [] for c in configs}
        cpu = {c: [] for c in configs}  # process CPU time (all threads) per segment()
        rounds = -(-args.frames // args.block)
        start = time.perf_counter()
        k = {c: 0 for c in configs}  # each setup walks its frames in order (a static camera's)
        for r in range(rounds):
            for cfg in rotated(configs, r):
                seg, fr, cams = use(cfg), frames[cfg[0]], cameras[cfg[0]]
                block = []
                for _ in range(args.block):
                    frame, camera = fr[k[cfg] % len(fr)], cams[k[cfg] % len(fr)]
                    k[cfg] += 1
                    c0, t0 = time.process_time(), time.perf_counter()
                    seg.segment(frame, camera)
                    block.append((time.perf_counter() - t0) * 1e3)
                    cpu[cfg].append((time.process_time() - c0) * 1e3)
                    for dst, v in zip(stages[cfg], staged(seg, frame, camera), strict=True):
                        dst.append(v)
                total[cfg] += block
                block_means[cfg].append(float(np.mean(block)))
        wall = time.perf_counter() - start

        # Post stage on the true labels (what a trained model's output costs to summarise).
        post_true = None
        if all(lab is not None for lab in true_labels[MODEL]):
            import cv2

            from task_outcome_ros.depth import sanitize_depth
            from task_outcome_ros.labels import BACKGROUND, IGNORE

            seg = use((MODEL, "onnx", threads[0]))
            times = []
            fr, truth = frames[MODEL], true_labels[MODEL]
            for i in range(min(len(fr), 50) * 2):
                depth = sanitize_depth(fr[i % len(fr)])
                # The truth at the working size, as the network would answer (255 -> 0).
                lab = cv2.resize(truth[i % len(fr)], seg.input_size,
                                 interpolation=cv2.INTER_NEAREST)
                lab[lab == IGNORE] = BACKGROUND
                t0 = time.perf_counter()
                seg.postprocess(lab, depth)
                times.append((time.perf_counter() - t0) * 1e3)
            post_true = percentiles(times)

    def summary(cfg: tuple[str, str, int]) -> dict:
        pre, net, post = stages[cfg]
        tracker = segs[cfg].floor_tracker
        planes = {} if tracker is None else {"planes_kept": tracker.reused,
                                             "planes_fitted": tracker.refits}
        return {"backend": cfg[1], "threads": cfg[2], **planes,
                "segment_ms": percentiles(total[cfg]), "segment_cpu_ms": percentiles(cpu[cfg]),
                "breakdown_ms": {"preprocess": percentiles(pre), "network": percentiles(net),
                                 "post": percentiles(post)}}

    results = {f"{backend}_threads{n}": summary((who, backend, n))
               for who, backend, n in configs if who == MODEL}
    against = None
    if reference is not None:
        ref_cfg = (REFERENCE, "onnx", threads[0])
        ref, own = summary(ref_cfg), results[f"onnx_threads{threads[0]}"]
        against = {
            "model": reference_desc, "frames": frames_desc[REFERENCE],
            "sha256": sha256(reference_shipped) if reference_shipped.exists() else None, **ref,
            # this run's model over the reference, ONNX on threads[0]: whole segment() and
            # its stages (p50s), and the median of the ratios of their blocks within a round
            "model_over_reference": {
                "segment_p50": round(own["segment_ms"]["p50"] / ref["segment_ms"]["p50"], 2),
                **{f"{stage}_p50": round(own["breakdown_ms"][stage]["p50"]
                                         / ref["breakdown_ms"][stage]["p50"], 2)
                   for stage in ("preprocess", "network", "post")},
                "paired_ratio": round(float(np.median(np.divide(
                    block_means[MODEL, "onnx", threads[0]], block_means[ref_cfg]))), 2)}}
    ratios = {}
    for n in threads:
        t, o = results[f"torch_threads{n}"], results[f"onnx_threads{n}"]
        torch_blocks, onnx_blocks = block_means[MODEL, "torch", n], block_means[MODEL, "onnx", n]
        ratios[f"threads{n}"] = {
            "torch_over_onnx_p50": round(t["segment_ms"]["p50"] / o["segment_ms"]["p50"], 2),
            "torch_over_onnx_network_p50": round(
                t["breakdown_ms"]["network"]["p50"] / o["breakdown_ms"]["network"]["p50"], 2),
            # median over rounds of (torch block mean / onnx block mean), adjacent in time
            "paired_ratio": round(float(np.median(np.divide(torch_blocks, onnx_blocks))), 2)}
    if len(threads) > 1:
        for b in ("torch", "onnx"):
            a, z = results[f"{b}_threads{threads[0]}"], results[f"{b}_threads{threads[-1]}"]
            ratios[f"{b}_threads{threads[0]}_over_threads{threads[-1]}_p50"] = round(
                a["segment_ms"]["p50"] / z["segment_ms"]["p50"], 2)
    base = "inference_static" if args.static_camera else "inference"
    record(base if default else f"{base}.{args.model}", {
        "static_camera_copies": args.static_camera,
        "model": model_desc, "frames": frames_desc[MODEL], "frame_size": list(SIZE),
        "working_size": list(segs[configs[0]].input_size),
        "timed_frames_per_config": len(total[configs[0]]), "block": args.block,
        "warmup_per_config": args.warmup, "quick": args.quick, "wall_s": round(wall, 1),
        "load_average_1_5_15": {"start": load_start, "end": load_average()},
        "versions": {"torch": torch.__version__, "onnxruntime": onnxruntime.__version__,
                     "opencv": cv2.__version__, "numpy": np.__version__},
        "configs": results, "ratios": ratios,
        "post_on_true_labels_ms": post_true, "reference": against,
        "note": ("segment_ms = one OutcomeSegmenter.segment() call on a 640x480 float32 frame; "
                 "segment_cpu_ms = process CPU time of that call, all threads (ORT worker "
                 "threads spin-wait, so it can exceed the wall time x 1); "
                 "breakdown from the same frame run stage by stage through the segmenter's "
                 "own methods (network includes argmax); "
                 "configurations interleaved in rotating blocks; the machine is shared (see "
                 "load_average_1_5_15), so absolute figures are noisy, ratios within the run "
                 "less so"),
    }, command, model=shipped)


if __name__ == "__main__":
    main()
