"""``python -m training demo`` (``make demo``): the whole story on a small simulated bag.

1. simulate a few episodes (a seed of their own) and render them with ground truth;
2. export them as a rosbag2 bag (depth/image_raw 32FC1 + depth/camera_info, 5 Hz);
3. start ``outcome_node`` as its own process (shipped model, default parameters);
4. replay the bag to it over DDS and record what it publishes (``task_outcome_ros.live_bag``);
5. score the answers with the paper's image-level metric, write a contact sheet of the
   overlays as the node published them, and ``summary.json``;
6. run ``examples/place_and_check.py`` against the same node: a manipulation stack's side,
   asking ``outcome/check`` after each of a few places.

Steps 1-2 and the contact sheet are training-side (pybullet, matplotlib); steps 3-5 use only
what a robot installs.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from task_outcome_ros.bag_io import BagToolError
from task_outcome_ros.live_bag import run_live
from task_outcome_ros.topics import STATUS_TOPIC

DEFAULT_OUT = Path("runs/demo")
EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
BAG_RATE_HZ = 5.0


def make_data(out: Path, episodes: int, seed: int, task: str = "default",
              frames: int = 40) -> Path:
    """Steps 1-2: a small dataset run of the task and a bag of its first ``frames`` images (a
    finished run resumes to nothing; one made with other options is refused, naming them).
    Discovery needs enough episodes to find every outcome of a task (a shelf: ~600), so the
    bag may hold fewer frames than the run has episodes."""
    from training.export_bag import export_bag

    data = out / "data"
    cmd = [sys.executable, "-m", "training", "dataset", "--out", str(data), "--episodes",
           str(episodes), "--seed", str(seed), "--chunk-size", "10", "--scene", task]
    subprocess.run(cmd, check=True)
    bag = out / "input_bag"
    export_bag(data, bag, split="all", limit=frames, rate_hz=BAG_RATE_HZ, encoding="32FC1",
               overwrite=True)
    return bag


def contact_sheet(path: Path, received: dict, ground_truth: dict, scores: dict,
                  n: int = 12) -> None:
    """Overlays as the node published them, titled with its answer and the truth."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    frames = ground_truth["frames"]
    wrong = {m["stamp_ns"] for m in scores["mistakes"]}
    order = [f for f in frames if f["stamp_ns"] in wrong] + \
        [f for f in frames if f["stamp_ns"] not in wrong]
    order = [f for f in order if f["stamp_ns"] in received["outcome/overlay"]][:n]
    cols = 4
    rows = max(1, (len(order) + cols - 1) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.6 * rows), dpi=80,
                             squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, frame in zip(axes.ravel(), order):
        msg = received["outcome/overlay"][frame["stamp_ns"]][1]
        rgb = np.frombuffer(bytes(msg.data), np.uint8).reshape(msg.height, msg.width, 3)
        ax.imshow(rgb)
        status = received[STATUS_TOPIC].get(frame["stamp_ns"])
        said = status[1].status[0].message if status else "(no status)"
        truth = ",".join(k for k, here in frame["present"].items() if here) or "none"
        ok = frame["stamp_ns"] not in wrong
        ax.set_title(f"ep {frame['episode']}: node says {said}\ntruth {truth}", fontsize=8,
                     color="black" if ok else "red")
    fig.suptitle(f"outcome_node on a replayed bag: {scores['image_all_correct']:.1%} of "
                 f"{scores['n_images']} images all-correct (mistakes first, in red)")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def run_demo(out: Path, episodes: int = 40, seed: int = 2026, timeout_s: float = 60.0,
             task: str = "default", frames: int = 40) -> dict:
    """The demo on a shipped task: its spec's data, its model (``model_path:=<task>``)."""
    out.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    print(f"[demo] 1-2/6 simulating {episodes} episodes of task {task!r} (seed {seed}) and "
          f"exporting a bag of {min(frames, episodes)} frames")
    bag = make_data(out, episodes, seed, task, frames)
    live = run_live(bag, out, rate_hz_note=f" at {BAG_RATE_HZ:g} Hz", timeout_s=timeout_s,
                    node_args=["-p", f"model_path:={task}"],
                    log=lambda text: print(f"[demo] 3-4/6 {text}"),
                    then=lambda env: place_and_check(bag, env))
    contact_sheet(out / "contact_sheet.png", live.received, live.ground_truth, live.scores)
    latency = live.latencies_ms()
    scores = live.scores
    summary = {
        "task": task,
        "frames_sent": live.frames_sent,
        "frames_answered": len(live.received[STATUS_TOPIC]),
        "image_all_correct": scores["image_all_correct"],
        "presence_recall": scores["presence_recall"],
        "presence_precision": scores["presence_precision"],
        "node_latency_ms_p50": float(np.median(latency)) if latency else None,
        "wall_s": round(time.monotonic() - started, 1),
        "outputs": {"contact_sheet": str(out / "contact_sheet.png"),
                    "output_bag": str(out / "output_bag"), "input_bag": str(bag)},
    }
    (out / "summary.json").write_text(json.dumps({**summary, "scores": scores}, indent=1))
    p50 = summary["node_latency_ms_p50"]
    print(f"[demo] 5/6 {summary['frames_answered']}/{live.frames_sent} frames answered, "
          f"{summary['image_all_correct']:.1%} all-correct, node latency p50 "
          f"{'n/a' if p50 is None else f'{p50:.1f}'} ms; contact sheet: "
          f"{out / 'contact_sheet.png'}")
    return summary


def place_and_check(bag: Path, env: dict[str, str], places: int = 5) -> None:
    """Step 6: the example client asks the running node about a few places."""
    print(f"[demo] 6/6 examples/place_and_check.py: {places} places, each checked with "
          "outcome/check")
    subprocess.run([sys.executable, str(EXAMPLES / "place_and_check.py"), str(bag),
                    "--places", str(places)], env=env, check=True, timeout=120)


def add_demo_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=DEFAULT_OUT,
                   help="demo folder (default: %(default)s)")
    p.add_argument("--task", default="default",
                   help="a shipped task: its spec makes the data, its model answers "
                        "(default: default; also tote, shelf)")
    p.add_argument("--episodes", type=int, default=None,
                   help="episodes to simulate (default 40; 600 for a task other than the "
                        "default one, so that discovery finds all its outcomes)")
    p.add_argument("--frames", type=int, default=40,
                   help="frames of the bag: the run's first ones (default 40)")
    p.add_argument("--seed", type=int, default=2026, help="their seed (default 2026)")


def demo_main(args: argparse.Namespace) -> int:
    try:
        episodes = args.episodes or (40 if args.task == "default" else 600)
        run_demo(args.out, episodes, args.seed, task=args.task, frames=args.frames)
    except (RuntimeError, subprocess.SubprocessError, BagToolError) as exc:
        print(f"[demo] failed: {exc}", file=sys.stderr)
        return 1
    return 0
