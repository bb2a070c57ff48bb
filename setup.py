"""ament_python package: installs with pip into a venv and builds with colcon."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "task_outcome_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=[PACKAGE, f"{PACKAGE}.*", "training", "training.*"]),
    package_data={PACKAGE: ["models/*.pt", "models/*.onnx", "models/*.json"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml") + glob("config/*.xml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
    ],
    # Runtime deps come from requirements.txt (venv) or rosdep keys in package.xml (ROS);
    # listing them here would make colcon's setuptools try to fetch them.
    install_requires=["setuptools"],
    extras_require={"test": ["pytest"]},
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
            f"outcome_replay = {PACKAGE}.bag_tools:replay_main",
        ],
    },
)
