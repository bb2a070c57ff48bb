"""``make demo`` end to end on a few episodes: dataset -> bag -> the live node over DDS ->
scored answers, contact sheet, and the example client's outcome/check after each place."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

pytest.importorskip("rclpy", reason="ROS 2 rclpy is not installed")

import node_helpers as nh  # noqa: E402

pytestmark = pytest.mark.pipeline


def test_the_demo_runs_and_the_example_checks_each_place(tmp_path):
    out = tmp_path / "demo"
    result = subprocess.run([sys.executable, "-m", "training", "demo", "--out", str(out),
                             "--episodes", "20", "--seed", "5"], cwd=nh.REPO, env=nh.ros_env(),
                            capture_output=True, text=True, timeout=400)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames_sent"] == summary["frames_answered"] == 20
    assert summary["scores"]["n_images"] == 20 and summary["scores"]["n_missing"] == 0
    assert (out / "contact_sheet.png").stat().st_size > 10_000
    places = [line for line in result.stdout.splitlines() if line.startswith("place ")]
    assert len(places) == 5, result.stdout[-2000:]
    for line in places:  # the reaction follows what the node said; the truth is printed
        said = line.split(": ", 1)[1].split(" -> ")[0]
        only_success = set(said.split(",")) <= {"success", "nothing"}
        assert ("-> ok, next place" in line) == (only_success and "outside" not in line), line
        assert ("-> retry" in line) != ("-> ok, next place" in line)
        assert "[truth: " in line
