"""Shared by the bench scripts: machine description and merging into bench/results.json."""

from __future__ import annotations

import json
import os
import platform
import time
from pathlib import Path

import numpy as np

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


def record(section: str, data: dict, command: str) -> None:
    """Merge one benchmark's figures into bench/results.json under ``section``."""
    results = json.loads(RESULTS.read_text()) if RESULTS.exists() else {}
    results[section] = {"command": command, "machine": machine(),
                        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), **data}
    RESULTS.write_text(json.dumps(results, indent=1, sort_keys=True) + "\n")
    print(json.dumps(results[section], indent=1))
