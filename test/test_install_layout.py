"""The colcon install layout `ros2 run` / `ros2 launch` rely on.

The repository is copied to a temporary folder (without .venv, runs, build products) and built
there with build, install and log bases in the same folder, so the test never writes into the
working tree. An ament_python package is found by ros2 through the ament index marker, its
executables through lib/<package>/ (setup.cfg's install_scripts), its data through share/.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("colcon_core", reason="colcon (colcon-core) is not installed")

REPO = Path(__file__).resolve().parents[1]
PACKAGE = "task_outcome_ros"
EXECUTABLES = ("outcome_node", "outcome_bag", "outcome_replay")
NOT_SOURCES = (".git", ".venv", "runs", "demo_out", "build", "install", "log", "*.egg-info",
               "__pycache__", ".pytest_cache", ".ruff_cache")


def _colcon() -> str:
    beside = Path(sys.executable).with_name("colcon")
    found = str(beside) if beside.exists() else shutil.which("colcon")
    if not found:
        pytest.skip("colcon_core is importable but the `colcon` executable is not on PATH")
    return found


@pytest.fixture(scope="module")
def install(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("colcon")
    src = tmp / "src" / PACKAGE
    shutil.copytree(REPO, src, ignore=shutil.ignore_patterns(*NOT_SOURCES))
    env = dict(os.environ, COLCON_LOG_PATH=str(tmp / "log"))
    result = subprocess.run(
        [_colcon(), "--log-base", str(tmp / "log"), "build", "--base-paths", str(tmp / "src"),
         "--build-base", str(tmp / "build"), "--install-base", str(tmp / "install"),
         "--event-handlers", "console_direct+"],
        cwd=tmp, env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, f"colcon build failed:\n{result.stdout}\n{result.stderr}"
    assert f"Finished <<< {PACKAGE}" in result.stdout, result.stdout
    return tmp / "install" / PACKAGE


def test_package_is_in_the_ament_index(install):
    marker = install / "share" / "ament_index" / "resource_index" / "packages" / PACKAGE
    assert marker.is_file()


def test_package_xml_and_data_are_in_share(install):
    share = install / "share" / PACKAGE
    assert (share / "package.xml").read_bytes() == (REPO / "package.xml").read_bytes()
    for config in (REPO / "config").iterdir():   # parameter YAML and the DDS profile
        assert (share / "config" / config.name).is_file(), config.name
    for launch in (REPO / "launch").glob("*.launch.py"):
        assert (share / "launch" / launch.name).is_file(), launch.name


@pytest.mark.parametrize("name", EXECUTABLES)
def test_executables_are_in_lib_package(install, name):
    """`ros2 run task_outcome_ros <name>` looks in lib/<package>/, not in bin/."""
    exe = install / "lib" / PACKAGE / name
    assert exe.is_file(), sorted(p.name for p in (install / "lib" / PACKAGE).iterdir())
    assert os.access(exe, os.X_OK)
    text = exe.read_text()
    assert text.startswith("#!") and name in text
    assert not (install / "bin" / name).exists()


def test_python_packages_are_installed(install):
    site = next((install / "lib").glob("python3*/site-packages"))
    assert (site / PACKAGE / "node.py").is_file()
    assert (site / PACKAGE / "labels.py").is_file()
    assert (site / "training" / "__main__.py").is_file()
