"""Soak the real outcome_node: 10 minutes at 30 Hz over DDS, then is it still the same node?

    python bench/soak.py                 # 600 s at 30 Hz (~11 min)
    python bench/soak.py --seconds 120   # a shorter look

One scenario of bench/node.py (best-effort input, the Fast DDS SHM profile, one static
camera's frames with fresh noise each, the node's default parameters), with the 30 Hz phase
stretched to ``--seconds``. It reports:

* answered: the share of published frames whose labels came back (target >= 0.99; a frame
  the node overwrote while busy counts as unanswered, as a robot would see it);
* RSS: the node's resident memory sampled every 2 s, and its slope (least squares, MB per
  minute, after the first minute, which holds allocator warm-up); flat means |slope| small
  against the RSS itself;
* lag p95 per minute, and the ratio of the worst minute to the best (stable: near 1).

Writes the ``soak`` section of bench/results.json.
"""

from __future__ import annotations

import argparse
import signal
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import record  # noqa: E402
from inference import load_average, prepare_model  # noqa: E402
from node import run_scenario  # noqa: E402

WARMUP_S = 60.0
ANSWERED_TARGET = 0.99


def rss_slope_mb_per_min(samples: list[tuple[float, int]], skip_s: float) -> float | None:
    """Least-squares slope of RSS (kB samples at t seconds) after ``skip_s``, in MB/min."""
    kept = [(t, kb) for t, kb in samples if t >= skip_s]
    if len(kept) < 3:
        return None
    t, kb = np.array(kept, dtype=float).T
    return round(float(np.polyfit(t / 60.0, kb / 1024.0, 1)[0]), 4)


def verdict(throughput: dict, seconds: float) -> dict:
    """The soak's figures from the client's throughput result."""
    windows = [w for w in throughput["windows"] if w["lag_p95_ms"] is not None]
    p95 = [w["lag_p95_ms"] for w in windows]
    rss = throughput["node_rss_kb"]
    slope = rss_slope_mb_per_min(rss["samples_t_s_kb"], min(WARMUP_S, seconds / 4))
    return {
        "seconds": seconds, "published": throughput["published"],
        "fraction_answered": throughput["fraction_answered"],
        "answered_target": ANSWERED_TARGET,
        "answered_ok": throughput["fraction_answered"] >= ANSWERED_TARGET,
        "dropped_frames_node": throughput["dropped_frames_node"],
        "lost_before_node": throughput["lost_before_node"],
        "rss_mb_start_end_max": [round(rss[k] / 1024, 1) for k in ("start", "end", "max")],
        "rss_slope_mb_per_min_after_warmup": slope,
        "lag_p95_ms_per_window": p95,
        "lag_p95_worst_over_best": round(max(p95) / min(p95), 2) if p95 else None,
        "lag_ms": throughput["lag_ms"],
        "node_cpu_percent": throughput["node_cpu_percent"],
        "node_cpu_ms_per_answered_frame": throughput.get("node_cpu_ms_per_answered_frame"),
        "support_plane_kept_share": throughput.get("support_plane_kept_share"),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=600.0,
                        help="length of the 30 Hz run (default 600)")
    parser.add_argument("--images", type=int, default=30, help="distinct frames to cycle")
    args = parser.parse_args()
    if args.seconds < 10:
        parser.error("--seconds must be at least 10")

    def on_term(signum, frame):  # turn SIGTERM into run_scenario's cleanup
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, on_term)
    load_start, t0 = load_average(), time.monotonic()
    with tempfile.TemporaryDirectory(prefix="bench_soak_") as tmp:
        model, model_desc = prepare_model(Path(tmp))
        print(f"[bench/soak] {args.seconds:g} s at 30 Hz ...", flush=True)
        result = run_scenario(model, "sensor_data", True, 0, args.seconds, args.images,
                              Path(tmp), timeout=240 + args.seconds * 1.5, static=True)
    if not result.get("ok") or "throughput" not in result:
        sys.exit(f"bench/soak.py: the run failed: {result.get('error')}\n"
                 f"{result.get('node_log_tail', '')}")
    figures = verdict(result["throughput"], args.seconds)
    print(f"[bench/soak] {figures}", flush=True)
    record("soak", {
        "model": model_desc, "scenario": result["scenario"],
        "frames": result.get("frames"), "wall_s": round(time.monotonic() - t0, 1),
        "load_average_1_5_15": {"start": load_start, "end": load_average()},
        "node_alive_at_end": result["node_alive_at_end"],
        "summary": figures, "throughput": result["throughput"],
    }, f"python bench/soak.py {' '.join(sys.argv[1:])}".strip())


if __name__ == "__main__":
    main()
