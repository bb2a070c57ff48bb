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

pytestmark = pytest.mark.install

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


def test_node_runs_from_the_install_tree_like_ros2_run(install):
    """What `ros2 run task_outcome_ros outcome_node` does after `colcon build`: the ament index
    gives the package prefix, the executable is <prefix>/lib/<package>/outcome_node, and the
    shipped model is found inside the installed package (no model_path)."""
    import random
    import signal
    import subprocess
    import time

    from ament_index_python.packages import get_package_prefix

    site = next((install / "lib").glob("python3*/site-packages"))
    if not (site / PACKAGE / "models" / "outcome_fcn.pt").is_file():
        pytest.skip("no shipped model in the package to start the node with")
    env = dict(os.environ, AMENT_PREFIX_PATH=str(install),
               PYTHONPATH=os.pathsep.join([str(site), os.environ.get("PYTHONPATH", "")]),
               ROS_DOMAIN_ID=str(random.randint(1, 200)),
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    os.environ["AMENT_PREFIX_PATH"], saved = str(install), os.environ.get("AMENT_PREFIX_PATH")
    try:
        prefix = Path(get_package_prefix(PACKAGE))
    finally:
        if saved is None:
            del os.environ["AMENT_PREFIX_PATH"]
        else:
            os.environ["AMENT_PREFIX_PATH"] = saved
    assert prefix == install
    exe = prefix / "lib" / PACKAGE / "outcome_node"
    proc = subprocess.Popen([str(exe)], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, cwd=install.parent)
    try:
        lines, deadline = [], time.monotonic() + 60
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            if "ready:" in line:
                break
        log = "".join(lines)
        assert "ready:" in log, log
        assert str(site / PACKAGE / "models" / "outcome_fcn.pt") in log, log
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=20) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
