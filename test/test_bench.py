"""The bench scripts stay runnable: smoke runs of the quick modes, written to a temporary
results file (BENCH_RESULTS), never over the measured bench/results.json.

Why this exists: a bench script named like one of the repo's packages (bench/training.py,
once) shadows it for every other script in bench/, because Python puts the script's folder
first on sys.path; bench/inference.py then failed at its first ``from training...``."""

from __future__ import annotations

import hashlib
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.pipeline

REPO = Path(__file__).resolve().parents[1]
BENCH = REPO / "bench"


def test_no_bench_script_shadows_a_package_of_the_repo():
    packages = {p.parent.name for p in REPO.glob("*/__init__.py")}
    assert {"training", "task_outcome_ros"} <= packages
    scripts = {p.stem for p in BENCH.glob("*.py")}
    assert not scripts & packages, f"rename bench/{sorted(scripts & packages)}.py"


def _run(script: str, results: Path, *args: str) -> dict:
    env = {**os.environ, "BENCH_RESULTS": str(results)}
    r = subprocess.run([sys.executable, str(BENCH / script), *args], capture_output=True,
                       text=True, timeout=300, env=env, cwd=REPO)
    assert r.returncode == 0, r.stderr[-2000:]
    return json.loads(results.read_text())


@pytest.mark.parametrize("script, args, section, timed", [
    ("inference.py", ("--quick", "--threads", "1"), "inference", 60),  # --quick: 60 frames
    ("train_step.py", ("--quick",), "training", 4),                    # --quick: 4 steps
    ("roll_step.py", ("--quick",), "roll_step", 4),                    # --quick: 4 batches
    ("train_step.py", ("--quick", "--model", "tote"), "training.tote", 4),  # its 4 channels
    ("inference.py", ("--quick", "--threads", "1", "--model", "shelf"), "inference.shelf", 60),
    ("inference.py", ("--quick", "--threads", "1", "--model", "tote", "--static-camera", "10"),
     "inference_static.tote", 60),
])
def test_quick_bench_runs_and_records_real_timings(tmp_path, script, args, section, timed):
    results = tmp_path / "results.json"
    report = _run(script, results, *args)[section]
    assert report["command"].startswith(f"python bench/{script}")
    assert report["machine"]["cores"] >= 1
    timing_key = {"inference": "segment_ms", "inference_static": "segment_ms",
                  "training": "total"}.get(section.split(".")[0])
    timings = [v[timing_key] if timing_key else v for v in report["configs"].values()]
    # Every configuration timed as many runs as the quick mode asks for, each of real work.
    assert timings and all(t["n"] == timed and t["min"] > 0.1 for t in timings)
    # Provenance instead of machine paths: the revision measured and the model's hash.
    assert report["git_revision"] and len(report["git_revision"].split("+")[0]) == 12
    task = section.partition(".")[2]  # "inference.shelf": the shelf model was measured
    shipped = REPO / "task_outcome_ros" / "models" / (
        f"outcome_fcn_{task}.pt" if task else "outcome_fcn.pt")
    assert report["shipped_model_sha256"] == hashlib.sha256(shipped.read_bytes()).hexdigest()
    text = results.read_text()
    assert str(REPO) not in text and sys.prefix not in text
    if section == "training.tote":   # the tote model's own input and augmentation were timed
        assert report["model_args"]["in_channels"] == 4
        assert report["normalisation"]["relief_window_px"] == 15
        assert report["augment"]["holes"] == 0.5
    if section == "inference.shelf":  # its own working size, not the default model's
        assert report["working_size"] == [320, 240]
        # ... and the default model timed beside it, as many frames, for the ratio of the two
        reference = report["reference"]
        assert reference["segment_ms"]["n"] == timed and reference["segment_ms"]["min"] > 0.1
        assert reference["backend"] == "onnx" and reference["threads"] == 1
        assert reference["model"].startswith("shipped") and "outcome_fcn.pt" in reference["model"]
        if "synthetic" in report["frames"] + reference["frames"]:  # no shelf run here (CI):
            assert reference["frames"] == report["frames"]  # then both on the same frames
        ratio = reference["model_over_reference"]
        assert ratio["segment_p50"] == pytest.approx(
            report["configs"]["onnx_threads1"]["segment_ms"]["p50"]
            / reference["segment_ms"]["p50"], abs=0.01)
        assert 0 < ratio["paired_ratio"] < 100
    elif section == "inference":  # nothing beside the default model unless asked
        assert report["reference"] is None
    if section.startswith("inference_static"):  # a static camera: the plane mostly kept
        assert report["static_camera_copies"] == 10
        for setup in [*report["configs"].values(), report["reference"]]:
            assert setup["planes_fitted"] >= 1 and setup["planes_kept"] > setup["planes_fitted"]


@pytest.mark.parametrize("static", [0, 5])
def test_revision_bench_times_each_model_on_both_codes_in_its_own_process(tmp_path, static):
    """bench/revision.py against HEAD: four (code, model) workers, each importing its own copy
    of the package, as many frames each, and the ratios made from their timings; with a
    static camera every worker keeps its plane (HEAD has the option) between refits."""
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True,
                          text=True, check=True).stdout.strip()
    section = "revision_static.tote" if static else "revision.tote"
    report = _run("revision.py", tmp_path / "results.json", "--against", "HEAD", "--quick",
                  "--model", "tote", "--static-camera", str(static))[section]
    assert report["absent"] == {}
    assert report["static_camera_copies"] == static
    for pair in report["pairs"].values():
        assert pair["reuse_floor_fit"] == bool(static)
        if static:   # 40 frames: 8 images, 5 copies each: fitted once per image at most
            assert pair["planes"]["kept"] + pair["planes"]["fitted"] == 40
            assert pair["planes"]["kept"] >= 4 * pair["planes"]["fitted"] > 0
        else:
            assert pair["planes"] is None
    assert report["against"] == head and report["models"] == ["tote", "default"]
    assert set(report["pairs"]) == {f"{code}/{m}" for code in ("here", head[:12])
                                    for m in ("tote", "default")}
    for pair in report["pairs"].values():
        assert pair["segment_ms"]["n"] == 40 and pair["segment_ms"]["min"] > 0.1
    shipped = REPO / "task_outcome_ros" / "models" / "outcome_fcn_tote.pt"
    assert report["pairs"]["here/tote"]["model_sha256"] == hashlib.sha256(
        shipped.read_bytes()).hexdigest()
    tote = report["ratios"]["tote_here_over_default_at_revision"]
    here, old = report["pairs"]["here/tote"], report["pairs"][f"{head[:12]}/default"]
    assert tote["p50"] == pytest.approx(here["segment_ms"]["p50"] / old["segment_ms"]["p50"],
                                        rel=0.02)
    assert set(report["ratios"]) == {"tote_here_over_tote_at_revision",
                                     "default_here_over_default_at_revision",
                                     "tote_here_over_default_at_revision",
                                     "tote_here_over_default_here"}
    assert all(0 < r["paired"] < 100 for r in report["ratios"].values())


def test_revision_bench_against_code_that_shipped_no_tote_and_refit_every_frame(tmp_path):
    """467bcef (package 0.2.0, 2026-12-01, the inference budget's reference) shipped the default
    model only and had no reuse_floor_fit: its tote pair is left out, saying why, and its
    default pair refits every frame while this checkout's keep their plane."""
    report = _run("revision.py", tmp_path / "results.json", "--against", "467bcef", "--quick",
                  "--model", "tote", "--static-camera", "5")["revision_static.tote"]
    old = report["against"][:12]
    assert set(report["pairs"]) == {"here/tote", "here/default", f"{old}/default"}
    assert "no shipped model named 'tote'" in report["absent"][f"{old}/tote"]
    assert report["pairs"][f"{old}/default"]["reuse_floor_fit"] is False
    assert report["pairs"][f"{old}/default"]["planes"] is None
    assert report["pairs"]["here/tote"]["planes"]["kept"] > 0
    assert set(report["ratios"]) == {"default_here_over_default_at_revision",
                                     "tote_here_over_default_at_revision",
                                     "tote_here_over_default_here"}


def test_revision_bench_names_a_revision_git_does_not_know(tmp_path):
    r = subprocess.run([sys.executable, str(BENCH / "revision.py"), "--against", "no-such-rev"],
                       capture_output=True, text=True, timeout=60, cwd=REPO,
                       env={**os.environ, "BENCH_RESULTS": str(tmp_path / "r.json")})
    assert r.returncode == 2 and "no-such-rev" in r.stderr
    assert not (tmp_path / "r.json").exists()


def test_quick_network_bench_times_every_architecture_it_names(tmp_path):
    report = _run("networks.py", tmp_path / "results.json", "--quick")["networks"]
    assert report["command"] == "python bench/networks.py --quick"
    networks = _bench_module("networks").NETWORKS
    assert list(report["configs"]) == list(networks)
    for name, config in report["configs"].items():
        assert config["network_ms"]["n"] == 2 * 3 and config["network_ms"]["min"] > 0.1
        assert config["input_size"] == list(networks[name][1])
        assert config["parameters"] > 100_000
    first = report["configs"][next(iter(networks))]
    assert first["ratio_to_first"] == 1.0 and first["input_size"] == [160, 120]


def test_measured_results_hold_no_machine_paths():
    """bench/results.json is tracked: it says runs/default, not where one machine keeps it."""
    text = (BENCH / "results.json").read_text()
    assert not re.search(r'"/(work|root|home|tmp|usr|opt)/', text)
    assert not re.search(r' /(work|root|home|tmp)/', text)
    results = json.loads(text)
    assert all("shipped_model_sha256" in section for section in results.values())


def _bench_module(name: str):
    sys.path.insert(0, str(BENCH))
    try:
        return __import__(name)
    finally:
        sys.path.remove(str(BENCH))


@pytest.mark.unit
def test_soak_figures_measure_slope_and_windows():
    soak, client = _bench_module("soak"), _bench_module("_node_client")
    # 10 MB/min growth after a flat first minute; the slope ignores the warm-up.
    samples = [(t, 300_000 if t < 60 else 300_000 + int((t - 60) / 60 * 10 * 1024))
               for t in range(0, 600, 2)]
    assert soak.rss_slope_mb_per_min(samples, 60.0) == pytest.approx(10.0, abs=0.05)
    assert soak.rss_slope_mb_per_min(samples[:2], 0.0) is None
    # Windows: frames published at 0..119 s (1 Hz), every other one answered, lag = index.
    published = np.arange(120.0)
    answered = np.arange(0, 120, 2)
    lag = answered.astype(float)
    wins = client.windows(published, answered, lag, 60.0)
    assert [w["published"] for w in wins] == [60, 60]
    assert [w["fraction_answered"] for w in wins] == [0.5, 0.5]
    assert wins[1]["lag_p95_ms"] > wins[0]["lag_p95_ms"]
    throughput = {"windows": wins, "published": 120, "fraction_answered": 0.5,
                  "dropped_frames_node": 60, "lost_before_node": 0, "lag_ms": {},
                  "node_cpu_percent": 50.0,
                  "node_rss_kb": {"start": 300_000, "end": 400_000, "max": 400_000,
                                  "samples_t_s_kb": samples}}
    figures = soak.verdict(throughput, 120.0)
    assert not figures["answered_ok"]
    assert figures["lag_p95_worst_over_best"] == pytest.approx(
        wins[1]["lag_p95_ms"] / wins[0]["lag_p95_ms"], abs=0.01)


@pytest.mark.unit
def test_a_reference_run_reports_ratios_to_the_past_node_not_to_a_floor():
    node = _bench_module("node")
    scenario = {"ok": True, "node_ready_line": "model m", "reference_ready_line": "model r",
                "latency": {"end_to_end_ms": {"p50": 10.0, "p95": 12.0},
                            "cpu_ms_per_frame": 11.0, "unanswered": 0,
                            "floor": {"end_to_end_ms": {"p50": 20.0, "p95": 30.0},
                                      "cpu_ms_per_frame": 22.0, "unanswered": 1},
                            "ratio_to_floor": {"p50": 0.5, "p95": 0.4}}}
    out = node.against_reference(scenario)
    assert out["ok"]
    assert out["summary"]["ratios"] == {"latency_p50": 0.5, "latency_p95": 0.4,
                                        "cpu_per_frame": 0.5}
    assert "floor" not in out["latency"] and "ratio_to_floor" not in out["latency"]
    assert out["reference_latency"]["unanswered"] == 1
    # A reference that never answered gives no ratio, and the run is not recorded as ok.
    scenario["latency"]["floor"]["end_to_end_ms"] = None
    assert not node.against_reference(scenario)["ok"]


@pytest.mark.unit
def test_the_tiny_network_keeps_everything_but_the_network(tmp_path):
    from task_outcome_ros import checkpoint
    from task_outcome_ros.inference import OutcomeSegmenter, default_model_path

    inference = _bench_module("inference")
    path, desc = inference.tiny_network_model(default_model_path(), tmp_path)
    real, tiny = checkpoint.load(default_model_path()), checkpoint.load(path)
    for field in ("input_size", "normalisation", "train_config"):
        assert getattr(tiny, field) == getattr(real, field), field
    assert tiny.label_table.to_dict() == real.label_table.to_dict()
    assert tiny.model_args["in_channels"] == real.model_args["in_channels"]
    small = sum(p.numel() for p in tiny.model.parameters())
    assert small * 1000 < sum(p.numel() for p in real.model.parameters())
    assert f"({small} parameters," in desc
    seg = OutcomeSegmenter(path, backend="auto", num_threads=1)
    assert seg.backend == "onnx"          # the node would run the tiny ONNX export
    depth = np.full((480, 640), 2.0, np.float32)
    labels = seg.segment(depth).labels
    assert labels.shape == depth.shape and not labels.any()   # background everywhere
