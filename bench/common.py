"""Shared by the bench scripts: machine description and merging into bench/results.json."""

from __future__ import annotations

import hashlib
import json
import os
import platform
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SHIPPED_MODEL = REPO / "task_outcome_ros" / "models" / "outcome_fcn.pt"

# BENCH_RESULTS redirects the figures (the smoke tests write to a temporary file, so they
# never overwrite the measured ones).
RESULTS = Path(os.environ.get("BENCH_RESULTS")
               or Path(__file__).resolve().parent / "results.json")


def machine() -> dict:
    cpu = platform.processor() or ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(),
            "platform": platform.platform()}


def percentiles(values: list[float]) -> dict:
    """n, p50, p95, mean and min of timings (ms), rounded for results.json."""
    a = np.asarray(values, float)
    return {"n": int(a.size), "p50": round(float(np.percentile(a, 50)), 2),
            "p95": round(float(np.percentile(a, 95)), 2), "mean": round(float(a.mean()), 2),
            "min": round(float(a.min()), 2)}


# A static camera's frames in the benches: the same view again with fresh noise of this sd.
STATIC_NOISE_M = 0.002


def static_camera_copy(depth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``depth`` seen again by a camera that did not move: fresh Gaussian noise of
    ``STATIC_NOISE_M`` on its valid pixels, float32."""
    return np.where(np.isfinite(depth), depth + rng.normal(0.0, STATIC_NOISE_M, depth.shape),
                    depth).astype(np.float32)


def static_camera_description(copies: int) -> str:
    """What a frame description gains when each frame comes ``copies`` times."""
    return f", each {copies} times in a row with fresh {STATIC_NOISE_M * 1e3:g} mm noise"


def rotated(items: Sequence, r: int) -> Sequence:
    """``items`` in round ``r``'s order: rotated by ``r``, so that over the rounds each comes
    first as often, and a change in machine load hits every configuration alike."""
    k = r % len(items)
    return items[k:] + items[:k]


def git_revision() -> str | None:
    """The checked-out commit, with ``+dirty`` when tracked files differ from it."""
    try:
        rev = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=REPO,
                             capture_output=True, text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               cwd=REPO, capture_output=True, text=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None  # not a git checkout (an installed copy)
    return rev + ("+dirty" if dirty else "")


def sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def relative_paths(value: Any) -> Any:
    """Every string with this checkout's (or the interpreter's) absolute prefix made relative,
    so results.json says ``runs/default``, not where one machine keeps it."""
    if isinstance(value, dict):
        return {k: relative_paths(v) for k, v in value.items()}
    if isinstance(value, list):
        return [relative_paths(v) for v in value]
    if isinstance(value, str):
        for prefix, short in ((str(REPO) + os.sep, ""), (sys.prefix + os.sep, "<venv>/")):
            value = value.replace(prefix, short)
        return value
    return value


def cached_training_images(run: Path, size: tuple[int, int], count: int
                           ) -> tuple[dict, str] | None:
    """The first ``count`` images (depth, valid, labels) of ``run``'s working-size training
    cache and a line saying where they came from; None when the run has no such cache."""
    from training.dataset import cache_path

    path = cache_path(Path(run).resolve(), "train", size)
    if not path.exists():
        return None
    with np.load(path) as data:
        arrays = {k: data[k][:count] for k in ("depth", "valid", "labels")}
    shown = path.relative_to(REPO) if path.is_relative_to(REPO) else path
    return arrays, f"first {count} images of {shown}"


def untrained_network(model_args: dict):
    """A network of ``model_args`` with torch's seed 0 weights: the same for every bench."""
    import torch

    from task_outcome_ros import model

    torch.manual_seed(0)
    return model.build_model(model_args)


def exported_checkpoint(path: Path, net, model_args: dict, **fields) -> Path:
    """``net`` saved as a checkpoint at ``path`` and exported to ONNX beside it, as the package
    ships a model. ``fields``: ``checkpoint.save``'s other arguments; left out, the default
    task's working size and normalisation, no training config and no metrics."""
    from task_outcome_ros import checkpoint, model
    from task_outcome_ros.onnx_export import export_onnx

    fields = {"input_size": model.DEFAULT_INPUT_SIZE,
              "normalisation": dict(model.DEFAULT_NORMALISATION), "train_config": {},
              "metrics": {}, **fields}
    checkpoint.save(path, net, model_args=model_args, **fields)
    export_onnx(path)
    return path


def record(section: str, data: dict, command: str, model: Path | None = None) -> None:
    """Merge one benchmark's figures into bench/results.json under ``section``, with the git
    revision measured and the sha256 of the model measured (``model``: a shipped model other
    than the default task's; None: the default task's)."""
    results = json.loads(RESULTS.read_text()) if RESULTS.exists() else {}
    model = SHIPPED_MODEL if model is None else Path(model)
    provenance = {"git_revision": git_revision(),
                  "shipped_model_sha256": sha256(model) if model.exists() else None}
    results[section] = relative_paths(
        {"command": command, "machine": machine(),
         "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), **provenance, **data})
    RESULTS.write_text(json.dumps(results, indent=1, sort_keys=True) + "\n")
    print(json.dumps(results[section], indent=1))
