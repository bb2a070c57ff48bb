"""`make ship SCENE=<task>` retrains each shipped model with the recipe it was trained with.

The Makefile keeps each task's extra training options in ``SHIP_OPTIONS_<task>``; the shipped
checkpoint records the ``TrainConfig`` it was trained with. If one moves without the other, a
user who runs ``make ship`` gets a different model from the one the README's figures describe.
``make -n`` prints the command without running it; the command's options go through the
training CLI's own parser, so the comparison is what ``run`` would really train with.
"""

from __future__ import annotations

import dataclasses
import shlex
import shutil
import subprocess
from pathlib import Path

import pytest

pytestmark = pytest.mark.unit

REPO = Path(__file__).resolve().parents[1]
# Where the shipped checkpoint legitimately differs from what `make ship` would ask for: the
# machine it ran on (device, precision), and the run's own bookkeeping.
MACHINE_FIELDS = {"device", "amp"}


def ship_command(task: str) -> list[str]:
    """The `python -m training run ...` arguments `make ship SCENE=task` would run."""
    make = shutil.which("make")
    if make is None:
        pytest.skip("make is not installed")
    printed = subprocess.run([make, "-n", "ship", f"SCENE={task}"], cwd=REPO, check=True,
                             capture_output=True, text=True).stdout
    joined = printed.replace("\\\n", " ")          # the recipe's continued lines
    lines = [line for line in joined.splitlines() if "-m training run" in line]
    assert len(lines) == 1, f"expected one `training run` line in:\n{printed}"
    words = shlex.split(lines[0])
    return words[words.index("training") + 1:]


def shipped_tasks() -> list[str]:
    from task_outcome_ros.inference import shipped_models

    return shipped_models()


@pytest.mark.parametrize("task", shipped_tasks())
def test_make_ship_trains_the_shipped_models_recipe(task):
    from task_outcome_ros import checkpoint
    from task_outcome_ros.inference import resolve_model_path
    from training.__main__ import build_parser, resolve_train_config
    from training.config import TrainConfig

    args = build_parser().parse_args(ship_command(task))
    assert args.stage == "run" and args.ship
    assert Path(args.scene).stem == task
    wanted = dataclasses.asdict(resolve_train_config(args))
    trained = checkpoint.load(resolve_model_path(task)).train_config["train"]
    defaults = dataclasses.asdict(TrainConfig())
    differ = {}
    for name, value in wanted.items():
        if name in MACHINE_FIELDS:
            continue
        # Options added after a model was trained are absent from its record: it ran with
        # what is now their default.
        had = trained.get(name, defaults[name])
        if isinstance(value, tuple):
            had = tuple(had)
        if had != value:
            differ[name] = {"make ship": value, "shipped": had}
    assert not differ, (f"SHIP_OPTIONS_{task} in the Makefile and the shipped {task} model's "
                        f"training config disagree: {differ}")
