"""ament_python package: installs with pip into a venv and builds with colcon."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "task_outcome_ros"

setup(
    name=PACKAGE,
    version="0.21.0",
    packages=find_packages(include=[PACKAGE, f"{PACKAGE}.*", "training", "training.*"]),
    package_data={PACKAGE: ["models/*.pt", "models/*.onnx", "models/*.json"],
                  "training": ["scenes/*.yaml"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml") + glob("config/*.xml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
    ],
    # Runtime deps come from requirements-runtime.txt (venv) or rosdep keys in package.xml
    # (ROS); listing them here would make colcon's setuptools try to fetch them. The extras
    # name what the offline side adds: `pip install -e .[training]`.
    install_requires=["setuptools"],
    extras_require={
        "training": ["pybullet>=3.2.6", "scikit-learn>=1.4", "matplotlib>=3.8", "onnx>=1.16",
                     "pyyaml>=6.0"],
        "test": ["pytest>=8"],
    },
    zip_safe=False,
    python_requires=">=3.10",
    maintainer="task_outcome_ros maintainers",
    maintainer_email="maintainers@task-outcome-ros.invalid",
    description="Task-outcome segmentation from depth images, learned in simulation.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            f"outcome_node = {PACKAGE}.node:main",
            f"outcome_bag = {PACKAGE}.bag_tools:offline_main",
            f"outcome_replay = {PACKAGE}.replay:main",
        ],
    },
)
