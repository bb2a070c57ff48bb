"""Benchmark this checkout's ``segment()`` against another revision's, in one run.

    python bench/revision.py --against 983a4b8 --model tote      # ~3 min
    python bench/revision.py --against 983a4b8 --quick           # a smoke run

Why: an issue asks that a model's ``segment()`` "cost no more than today", and this machine's
speed drifts 1.7x within a day, so only a ratio within one run answers it; when the code that
runs the models changes, "today" is another revision's code, which one process cannot import
beside this one. So each (code, model) pair runs in a worker process of its own
(bench/_segment_worker.py): this checkout's code as it is, the revision's unpacked from
``git archive`` (its package folder, shipped models included) into a temporary folder. Every
worker times ONNX Runtime on one thread, as the node runs on one core, on the same frames
(its model's task's run folder, as bench/inference.py loads them, with their camera_info). The
workers wait on stdin and are asked for a block of frames one at a time, in a rotating order,
so only one works at any moment and a change in machine load hits them all alike.

``--static-camera COPIES``: each frame comes COPIES times in a row with fresh 2 mm noise, and
each worker keeps the support plane while it fits where its code has that option
(``reuse_floor_fit``, the node's default), as each revision's node runs on a camera that
does not move; older code refits every frame, as its node did. Written to
``revision_static[.<model>]``.

The pairs: ``--model`` and ``--reference`` (default: the default task's model), each on this
checkout's code and on the revision's; a model the revision did not ship is left out there
(``absent`` says why). Writes ``revision.<model>`` in bench/results.json: each
pair's timings, and ``ratios``: each model here over the same model on the revision (what the
change of code did) and ``--model`` here over ``--reference`` on the revision (whether the
model costs no more than the reference did), each as the ratio of p50s and as the median
ratio of the two pairs' blocks within a round (``paired``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import (  # noqa: E402
    percentiles,
    record,
    rotated,
    sha256,
    static_camera_description,
)
from inference import load_frames_for  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
WORKER = Path(__file__).resolve().parent / "_segment_worker.py"
HERE = "here"
NOT_SHIPPED = "no shipped model named"   # what OutcomeSegmenter says of a model not shipped


def resolve(revision: str) -> str:
    """The full commit hash of ``revision``; ValueError naming it when git does not know it."""
    done = subprocess.run(["git", "rev-parse", "--verify", "--quiet", revision + "^{commit}"],
                          cwd=REPO, capture_output=True, text=True)
    if done.returncode != 0:
        raise ValueError(f"git does not know the revision {revision!r} in {REPO}")
    return done.stdout.strip()


def unpack(commit: str, into: Path) -> Path:
    """The revision's ``task_outcome_ros`` package (models included) unpacked under ``into``;
    returns the folder to put on PYTHONPATH."""
    archive = into / "code.tar"
    with archive.open("wb") as out:
        subprocess.run(["git", "archive", "--format=tar", commit, "task_outcome_ros"],
                       cwd=REPO, stdout=out, check=True)
    with tarfile.open(archive) as tar:
        tar.extractall(into / "code", filter="data")
    archive.unlink()
    return into / "code"


def save_frames(path: Path, depths: list[np.ndarray], cameras: list) -> None:
    """Frames and their cameras for the workers (camera rows: w, h, fx, fy, cx, cy; 0s: none)."""
    rows = [[0.0] * 6 if c is None else [c.width, c.height, c.fx, c.fy, c.cx, c.cy]
            for c in cameras]
    np.savez(path, depth=np.stack(depths), cameras=np.asarray(rows, np.float64))


class WorkerFailed(RuntimeError):
    """A worker ended before it was ready; the text ends with its stderr's last line."""


class Worker:
    """A bench/_segment_worker.py process running ``model`` on the code under ``code``; its
    stderr goes to ``log``."""

    def __init__(self, code: Path, model: str, frames: Path, warmup: int, log: Path,
                 copies: int = 0) -> None:
        env = {**os.environ, "PYTHONPATH": str(code), "OMP_NUM_THREADS": "1"}
        command = [sys.executable, str(WORKER), "--model", model, "--frames", str(frames),
                   "--warmup", str(warmup)]
        if copies:
            command += ["--reuse-floor-fit", "--copies", str(copies)]
        self.log, self.what = log, f"the worker for {model} on {code}"
        with log.open("w") as err:
            self.proc = subprocess.Popen(command, stdin=subprocess.PIPE,
                                         stdout=subprocess.PIPE, stderr=err, text=True,
                                         env=env, cwd=code)
        try:
            hello = self.proc.stdout.readline()
            if not hello:
                raise WorkerFailed(f"{self.what} ended before it was ready "
                                   f"(exit {self.proc.wait()}): {self.last_error()}")
            self.info = json.loads(hello)
            if not Path(self.info["code"]).resolve().is_relative_to(code.resolve()):
                raise RuntimeError(f"{self.what} imported task_outcome_ros from "
                                   f"{self.info['code']}: PYTHONPATH did not take")
        except BaseException:
            self.close()
            raise

    def last_error(self) -> str:
        lines = self.log.read_text().strip().splitlines() if self.log.exists() else []
        return lines[-1] if lines else "(no stderr)"

    def block(self, n: int) -> list[float]:
        """The times (ms) of the next ``n`` frames; ``planes`` says how the plane was kept."""
        self.proc.stdin.write(f"{n}\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"{self.what} ended mid-run (exit {self.proc.wait()}): "
                               f"{self.last_error()}")
        answer = json.loads(line)
        self.planes = answer["planes"]
        return answer["ms"]

    def close(self) -> None:
        """Ask the worker to quit; kill it if it does not within 30 s (or cannot be asked)."""
        try:
            if self.proc.poll() is None:
                self.proc.stdin.write("quit\n")
                self.proc.stdin.flush()
            self.proc.wait(timeout=30)
        except (OSError, subprocess.TimeoutExpired):
            self.proc.kill()
            self.proc.wait()


def ratios(times: dict, blocks: dict, a: tuple, b: tuple) -> dict:
    """``a`` over ``b``: p50 over p50, and the median over rounds of their block means."""
    return {"p50": round(float(np.median(times[a]) / np.median(times[b])), 3),
            "paired": round(float(np.median(np.divide(blocks[a], blocks[b]))), 3)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--against", required=True, help="a git revision (hash, tag, branch)")
    parser.add_argument("--model", default="default", help="a shipped model's name")
    parser.add_argument("--reference", default="default",
                        help="the model --model is compared with (default: %(default)s)")
    parser.add_argument("--frames", type=int, default=300, help="timed frames per pair")
    parser.add_argument("--block", type=int, default=10, help="frames per block")
    parser.add_argument("--images", type=int, default=50, help="distinct frames per model")
    parser.add_argument("--warmup", type=int, default=20, help="untimed frames per pair")
    parser.add_argument("--quick", action="store_true", help="smoke run: 40 frames, 10 images")
    parser.add_argument("--static-camera", type=int, default=0, metavar="COPIES",
                        help="each frame COPIES times in a row with fresh 2 mm noise, and the "
                             "support plane kept while it fits where the code can, as the "
                             "node runs (default 0: every frame refitted)")
    args = parser.parse_args()
    for name in ("frames", "block", "images"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be >= 1, got {getattr(args, name)}")
    if args.static_camera < 0:
        parser.error(f"--static-camera must be >= 0, got {args.static_camera}")
    if args.quick:
        args.frames, args.images, args.warmup = min(args.frames, 40), min(args.images, 10), 3
    try:
        commit = resolve(args.against)
    except ValueError as exc:
        parser.error(str(exc))
    command = "python bench/revision.py " + " ".join(sys.argv[1:])
    models = list(dict.fromkeys([args.model, args.reference]))

    def run_dir(name: str) -> Path:
        return REPO / "runs" / name

    loaded = load_frames_for(args.images, {m: run_dir(m) for m in models})
    described = {m: loaded[m][3] + (static_camera_description(args.static_camera)
                                    if args.static_camera else "") for m in models}
    with tempfile.TemporaryDirectory(prefix="bench_revision_") as tmp:
        codes = {HERE: REPO, commit[:12]: unpack(commit, Path(tmp))}
        workers, absent = {}, {}
        try:
            for m in models:
                frames_file = Path(tmp) / f"frames_{m}.npz"
                save_frames(frames_file, loaded[m][0], loaded[m][2])
                for code_name, code in codes.items():
                    log = Path(tmp) / f"worker_{code_name}_{m}.log"
                    try:
                        workers[code_name, m] = Worker(code, m, frames_file, args.warmup, log,
                                                       args.static_camera)
                    except WorkerFailed as exc:
                        # Only a model the revision did not ship is left out; any other
                        # failure is the bench's to report, not a figure to drop.
                        if code_name == HERE or NOT_SHIPPED not in str(exc):
                            raise
                        absent[f"{code_name}/{m}"] = str(exc).replace(tmp, "<tmp>")
            pairs = list(workers)
            times = {p: [] for p in pairs}
            blocks = {p: [] for p in pairs}
            start = time.perf_counter()
            for r in range(-(-args.frames // args.block)):
                for pair in rotated(pairs, r):
                    block = workers[pair].block(min(args.block, args.frames - len(times[pair])))
                    times[pair] += block
                    blocks[pair].append(float(np.mean(block)))
            wall = time.perf_counter() - start
            model_sha = {p: sha256(Path(workers[p].info["model"])) for p in pairs}
            here_model = Path(workers[HERE, args.model].info["model"])   # in this checkout
        finally:
            for worker in workers.values():
                worker.close()

    old = commit[:12]
    wanted = {f"{m}_here_over_{m}_at_revision": ((HERE, m), (old, m)) for m in models}
    if args.model != args.reference:
        wanted[f"{args.model}_here_over_{args.reference}_at_revision"] = (
            (HERE, args.model), (old, args.reference))
        wanted[f"{args.model}_here_over_{args.reference}_here"] = (
            (HERE, args.model), (HERE, args.reference))
    # A model the revision did not ship has no pair there, and no ratio to it.
    result_ratios = {name: ratios(times, blocks, a, b) for name, (a, b) in wanted.items()
                     if a in times and b in times}
    base = "revision_static" if args.static_camera else "revision"
    section = base if args.model == "default" else f"{base}.{args.model}"
    record(section, {
        "against": commit, "models": models, "quick": args.quick, "wall_s": round(wall, 1),
        "frames": described, "block": args.block,
        "warmup_per_pair": args.warmup,
        "static_camera_copies": args.static_camera,
        "pairs": {f"{code}/{m}": {"segment_ms": percentiles(times[code, m]),
                                  "model_sha256": model_sha[code, m],
                                  "reuse_floor_fit": workers[code, m].info["reuse_floor_fit"],
                                  "planes": workers[code, m].planes}
                  for code, m in pairs},
        "ratios": result_ratios,
        "absent": absent,
        "note": ("segment_ms = one OutcomeSegmenter.segment() call on a 640x480 frame with its "
                 "camera_info, ONNX Runtime on one thread, each (code, model) pair in its own "
                 "process; pairs interleaved in rotating blocks; here = this checkout's code"),
    }, command, model=here_model)


if __name__ == "__main__":
    main()
