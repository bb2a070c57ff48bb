"""``python -m training real-frames``: what a model says on real depth frames.

Everything else the pipeline scores is rendered. A *frame set* is a folder of real depth
images with a ``frames.yaml`` (see ``training/real_frames/arc2017/frames.yaml``): the task whose
outcome names the truth uses, the depth files' scale to metres, and per frame its intrinsics
and the outcomes truly present, written by hand at the image level (no pixel labels).

For each frame the report records what the model calls present, whether its envelope check
calls the frame outside what it was trained on, and, when the model's task is the frame
set's, whether the image is right: the outcomes it calls present are exactly the truth's (the
image-level metric of Bowkett et al., as ``evaluate`` scores rendered images). A model
of another task is not scored; the only right answer it can give is "outside my envelope".
It writes ``real_frames.json`` and a contact sheet, ``real_frames.png`` (depth | overlay).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from task_outcome_ros.camera import Intrinsics
from task_outcome_ros.depth import sanitize_depth
from training.config import ConfigError

FRAMES_FILE = "frames.yaml"
BUNDLED = Path(__file__).resolve().parent / "real_frames"
INTRINSIC_KEYS = ("fx", "fy", "cx", "cy")


@dataclass(frozen=True)
class RealFrame:
    name: str
    depth_path: Path
    intrinsics: tuple[float, float, float, float]   # fx, fy, cx, cy at the file's size
    present: tuple[str, ...]                        # outcomes truly present
    note: str = ""


@dataclass(frozen=True)
class FrameSet:
    name: str
    task: str
    depth_scale: float                              # metres per unit of integer images
    frames: tuple[RealFrame, ...]


def frame_set_path(name_or_path: str | Path) -> Path:
    """A bundled set's name (``arc2017``) or a folder holding ``frames.yaml``."""
    text = str(name_or_path)
    folder = BUNDLED / text if (BUNDLED / text / FRAMES_FILE).is_file() else Path(text)
    if not (folder / FRAMES_FILE).is_file():
        bundled = sorted(p.parent.name for p in BUNDLED.glob(f"*/{FRAMES_FILE}"))
        raise ConfigError(f"frame set {text!r}: no {FRAMES_FILE} there, and not a bundled set "
                          f"(bundled: {', '.join(bundled)})")
    return folder


def load_frame_set(name_or_path: str | Path) -> FrameSet:
    """The validated frame set; every error names the file and the frame."""
    import yaml

    folder = frame_set_path(name_or_path)
    path = folder / FRAMES_FILE
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from None
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list) \
            or not data["frames"]:
        raise ConfigError(f"{path}: needs a non-empty 'frames' list")
    task = data.get("task")
    scale = data.get("depth_scale", 0.001)
    if not isinstance(task, str) or not task:
        raise ConfigError(f"{path}: 'task' names the task whose outcomes 'present' lists")
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not 0 < scale <= 1:
        raise ConfigError(f"{path}: depth_scale is metres per unit, in (0, 1], got {scale!r}")
    frames = tuple(_frame(path, i, entry) for i, entry in enumerate(data["frames"]))
    names = [f.name for f in frames]
    if len(set(names)) != len(names):
        raise ConfigError(f"{path}: frame names repeat: {names}")
    return FrameSet(str(data.get("name", folder.name)), task, float(scale), frames)


def _frame(path: Path, index: int, entry: Any) -> RealFrame:
    where = f"{path}: frame {index}"
    if not isinstance(entry, dict):
        raise ConfigError(f"{where}: a mapping with name, depth, intrinsics and present")
    missing = [k for k in ("name", "depth", "intrinsics", "present") if k not in entry]
    if missing:
        raise ConfigError(f"{where}: missing {missing}")
    where = f"{path}: frame {entry['name']!r}"
    depth = path.parent / str(entry["depth"])
    if not depth.is_file():
        raise ConfigError(f"{where}: no depth file {depth}")
    k = entry["intrinsics"]
    if not isinstance(k, dict) or sorted(k) != sorted(INTRINSIC_KEYS) or not all(
            isinstance(k[key], (int, float)) and not isinstance(k[key], bool)
            and k[key] > 0 for key in INTRINSIC_KEYS):
        raise ConfigError(f"{where}: intrinsics must be positive {', '.join(INTRINSIC_KEYS)} "
                          f"in pixels, got {k!r}")
    present = entry["present"]
    if not isinstance(present, list) or not all(isinstance(p, str) for p in present):
        raise ConfigError(f"{where}: present is a list of outcome names (may be empty)")
    return RealFrame(str(entry["name"]), depth, tuple(float(k[key]) for key in INTRINSIC_KEYS),
                     tuple(present), str(entry.get("note", "")))


def read_depth(frame: RealFrame, scale: float) -> np.ndarray:
    """Metres, NaN where the sensor gave nothing (0): 16-bit PNG x ``scale``, or .npy metres."""
    import cv2

    if frame.depth_path.suffix == ".npy":
        depth = np.load(frame.depth_path).astype(np.float32)
        depth = depth[..., 0] if depth.ndim == 3 and depth.shape[-1] == 1 else depth
    else:
        raw = cv2.imread(str(frame.depth_path), cv2.IMREAD_UNCHANGED)
        if raw is None or raw.dtype != np.uint16:
            raise ConfigError(f"{frame.depth_path}: not a 16-bit depth image")
        depth = raw.astype(np.float32) * np.float32(scale)
    if depth.ndim != 2:
        raise ConfigError(f"{frame.depth_path}: depth must be one channel, got {depth.shape}")
    return sanitize_depth(depth, copy=False)   # the node's own rule for "no depth"


def check_model(model: str | Path | None, frame_set: FrameSet) -> tuple[dict, list, Any]:
    """(report, [(depth, labels)] per frame, the model's label table) of one model on every
    frame of the set."""
    from task_outcome_ros.inference import OutcomeSegmenter

    seg = OutcomeSegmenter(model, backend="auto", num_threads=1)
    task = seg.envelope.task if seg.envelope else None
    scored = task == frame_set.task
    if scored:
        known = seg.table.outcome_names
        unknown = {p for f in frame_set.frames for p in f.present} - set(known)
        if unknown:
            raise ConfigError(f"frame set {frame_set.name}: outcomes {sorted(unknown)} are not "
                              f"the {task} model's ({', '.join(known)})")
    rows, images = [], []
    for frame in frame_set.frames:
        depth = read_depth(frame, frame_set.depth_scale)
        fx, fy, cx, cy = frame.intrinsics
        intrinsics = Intrinsics(depth.shape[1], depth.shape[0], fx, fy, cx, cy)
        result = seg.segment(depth, intrinsics)
        predicted = sorted(k for k, v in result.present.items() if v)
        row = {"frame": frame.name, "size": [depth.shape[1], depth.shape[0]],
               "valid_fraction": round(float(np.isfinite(depth).mean()), 3),
               "truth": sorted(frame.present), "predicted": predicted,
               "outside_envelope": result.outside_envelope,
               "pixel_counts": result.pixel_counts}
        if scored:
            row["correct"] = predicted == sorted(frame.present)
            row["invented_pixels"] = invented_pixels(row)
        rows.append(row)
        images.append((depth, result.labels))
    inside = [r for r in rows if not r["outside_envelope"]]
    report = {"model": str(seg.model_path.name), "model_task": task,
              "frame_set": frame_set.name, "frame_set_task": frame_set.task,
              "scored": scored, "frames": len(rows), "inside_envelope": len(inside),
              "rows": rows}
    if scored:
        report["image_all_correct"] = round(sum(r["correct"] for r in rows) / len(rows), 3)
        report["wrong_outcomes"] = wrong_outcome_counts(rows)
        report["invented_pixels"] = sum(r["invented_pixels"] for r in rows)
    return report, images, seg.table


def wrong_outcomes(row: dict) -> tuple[list[str], list[str]]:
    """(outcomes invented, outcomes missed) of one scored frame."""
    truth, pred = set(row["truth"]), set(row["predicted"])
    return sorted(pred - truth), sorted(truth - pred)


def invented_pixels(row: dict) -> int:
    """Pixels of a scored frame labelled with an outcome its truth does not hold, whether or
    not there are enough of them to call it present: a model's specks, which decide a real
    frame on one bad day, counted before the presence rule hides them."""
    return int(sum(n for name, n in row["pixel_counts"].items() if name not in row["truth"]))


def wrong_outcome_counts(rows: list[dict]) -> dict[str, dict[str, int]]:
    """Per outcome, in how many frames it was invented and in how many missed."""
    counts: dict[str, dict[str, int]] = {}
    for row in rows:
        invented, missed = wrong_outcomes(row)
        for kind, names in (("invented", invented), ("missed", missed)):
            for name in names:
                counts.setdefault(name, {"invented": 0, "missed": 0})[kind] += 1
    return counts


def plot_frames(path: Path, report: dict, images: list, table) -> None:
    """depth | overlay per frame, titled with truth, prediction and the envelope's verdict."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from task_outcome_ros.outcome_report import colourise_depth, overlay_rgb

    fig, axes = plt.subplots(len(images), 2, figsize=(8, 3.1 * len(images)), dpi=80,
                             squeeze=False)
    for (ax_depth, ax_over), row, (depth, labels) in zip(axes, report["rows"], images):
        ax_depth.imshow(colourise_depth(depth))
        ax_depth.set_title(row["frame"], fontsize=9)
        ax_over.imshow(overlay_rgb(depth, labels, 0.6, table))
        verdict = ("outside the envelope" if row["outside_envelope"]
                   else "right" if row.get("correct") else "wrong" if "correct" in row
                   else "inside the envelope")
        ax_over.set_title(f"truth: {', '.join(row['truth']) or 'nothing'} | predicted: "
                          f"{', '.join(row['predicted']) or 'nothing'}\n{verdict}", fontsize=8,
                          color="black" if verdict in ("right", "outside the envelope")
                          else "red")
        for ax in (ax_depth, ax_over):
            ax.axis("off")
    fig.suptitle(f"{report['model']} ({report['model_task']}) on {report['frame_set']}",
                 fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.35 / fig.get_figheight()))  # 0.35 in for the title
    fig.savefig(path)
    plt.close(fig)


def run_real_frames(model: str | None, frames: str | Path, out: Path) -> dict:
    """Check ``model`` on a frame set; writes real_frames.json and real_frames.png in ``out``."""
    frame_set = load_frame_set(frames)
    report, images, table = check_model(model, frame_set)
    out.mkdir(parents=True, exist_ok=True)
    (out / "real_frames.json").write_text(json.dumps(report, indent=1) + "\n")
    plot_frames(out / "real_frames.png", report, images, table)
    return report
