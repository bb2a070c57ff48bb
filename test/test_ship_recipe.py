"""`make ship SCENE=<task>` retrains each shipped model with the recipe it was trained with.

The Makefile keeps each task's extra training options in ``SHIP_OPTIONS_<task>``; the shipped
checkpoint records the ``TrainConfig`` it was trained with. If one moves without the other, a
user who runs ``make ship`` gets a different model from the one the README's figures describe.
``make -n`` prints the command without running it; the command's options go through the
training CLI's own parser, so the comparison is what ``run`` would really train with; the
episodes and seed of its data, and the bundled spec it is made from, are checked too.
"""

from __future__ import annotations

import shlex
import shutil
import subprocess
from pathlib import Path

import pytest

pytestmark = pytest.mark.unit

REPO = Path(__file__).resolve().parents[1]


def ship_command(task: str) -> list[str]:
    """The `python -m training run ...` arguments `make ship SCENE=task` would run."""
    make = shutil.which("make")
    if make is None:
        pytest.skip("make is not installed")
    done = subprocess.run([make, "-n", "ship", f"SCENE={task}"], cwd=REPO,
                          capture_output=True, text=True)
    assert done.returncode == 0, f"make -n ship SCENE={task} failed:\n{done.stderr}"
    printed = done.stdout
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
    from training.config import dataset_config_from_dict
    from training.scene import load_scene
    from training.train import resume_differences

    args = build_parser().parse_args(ship_command(task))
    assert args.stage == "run" and args.ship
    assert Path(args.scene).stem == task
    recorded = checkpoint.load(resolve_model_path(task)).train_config
    # The same comparison that decides whether a run may be resumed with these options:
    # renamed fields and fields added since (at the value runs had before them) are mapped,
    # a field the checkpoint did not record is a difference, and only how a run is executed
    # (device, precision, time budget) may differ.
    differ = resume_differences(recorded["train"], resolve_train_config(args), "same", "same")
    assert not differ, (f"SHIP_OPTIONS_{task} in the Makefile and the shipped {task} model's "
                        f"training config disagree: {differ}")
    spec = load_scene(args.scene)
    episodes = args.episodes or spec.episodes
    seed = spec.seed if args.seed is None else args.seed
    assert (episodes, seed) == (recorded["dataset"]["episodes"], recorded["dataset"]["seed"]), (
        f"make ship SCENE={task} simulates {episodes} episodes of seed {seed}; the shipped "
        f"model was trained on {recorded['dataset']['episodes']} of seed "
        f"{recorded['dataset']['seed']}")
    # ... and the bundled spec it simulates and renders is the one the model was trained on
    # (default model 0.19.0's empty cells, for one, live in the spec, not in the options).
    trained_on = dataset_config_from_dict(recorded["dataset"])
    for section in ("scene", "camera", "noise", "tof", "discover"):
        assert getattr(trained_on, section) == getattr(spec, section), (
            f"training/scenes/{task}.yaml's {section} differs from what the shipped {task} "
            "model was trained on")
