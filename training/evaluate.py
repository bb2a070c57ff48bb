"""Stage 6: evaluate a checkpoint with the paper's image-level metric, exactly as the node runs.

Every image goes through ``OutcomeSegmenter.segment`` at full resolution (the node's code
path), and the presence rule of labels.py decides which outcomes are present in the predicted
and in the true label image. Writes ``eval.json`` (docs/interface.md §6), a confusion matrix, a
picture of examples, mistakes first, the recall by outcome size (size_recall.py) and, for a
task on a table, by where the outcome's objects rest (rest_place.py).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from tqdm import tqdm

from task_outcome_ros.camera import Intrinsics
from task_outcome_ros.fragments import FRAGMENT_MAX_PIXELS
from task_outcome_ros.inference import OutcomeSegmenter
from task_outcome_ros.labels import (
    IGNORE,
    PRESENCE_MIN_PIXELS,
    LabelTable,
    outcome_pixel_counts,
    presence_from_counts,
    presence_scores,
    presence_threshold,
)
from training.config import save_json
from training.dataset import load_manifest, manifest_table
from training.hard_cases import (
    GAP_BINS_MM,
    NEAR_BOUNDARY_M,
    TAGS,
    HardCase,
    gap_bin,
    gap_bin_names,
    hard_cases_of,
    run_episodes,
)
from training.render import read_pair, reported_camera
from training.rest_place import places_of, recall_by_place
from training.size_recall import plot_recall_by_size, recall_by_size
from training.stats import wilson_interval


def confusion(truth: np.ndarray, pred: np.ndarray, num_classes: int) -> np.ndarray:
    keep = truth != IGNORE
    return np.bincount(truth[keep].astype(np.int64) * num_classes + pred[keep],
                       minlength=num_classes ** 2).reshape(num_classes, num_classes)


def same_task(model: LabelTable, data: LabelTable, model_path, data_dir) -> np.ndarray:
    """A model can only be scored on data of its own task: the same fixture, and outcomes it
    knows (a small run may not have found them all). Returns the lookup table that maps the
    data's label ids to the model's, by name (255 stays 255)."""
    unknown = [name for name in data.outcome_names if name not in model.outcome_names]
    if data.fixture_name != model.fixture_name or unknown:
        raise ValueError(f"model {model_path} knows the classes {list(model.classes)}, but "
                         f"{data_dir} is labelled with {list(data.classes)}: evaluate a model "
                         "of this task")
    lut = np.full(256, IGNORE, np.uint8)
    for data_id, name in enumerate(data.classes):
        lut[data_id] = model.classes.index(name)
    return lut


def hard_case_report(rows: list[dict], cases: dict[int, HardCase] | None) -> dict:
    """Mistakes per hard-case tag (hard_cases.py), the all-correct rate of untagged images and
    the all-correct rate per boundary-gap bin."""
    if cases is None:
        return {}
    tagged = {r["episode"]: cases[r["episode"]].tags for r in rows}
    untagged = [r for r in rows if not tagged[r["episode"]]]
    mistakes = [r for r in rows if not r["correct"]]
    by_gap = [{"bin": name, "images": 0, "mistakes": 0} for name in gap_bin_names()]
    for r in rows:
        entry = by_gap[gap_bin(cases[r["episode"]].gap_m)]
        entry["images"] += 1
        entry["mistakes"] += not r["correct"]
    for entry in by_gap:
        entry["image_all_correct"] = (1.0 - entry["mistakes"] / entry["images"]
                                      if entry["images"] else None)
    return {"hard_cases": {
        "near_boundary_m": NEAR_BOUNDARY_M,
        "images": {t: sum(t in tagged[r["episode"]] for r in rows) for t in TAGS},
        "mistakes": {**{t: sum(t in tagged[r["episode"]] for r in mistakes) for t in TAGS},
                     "untagged": sum(not tagged[r["episode"]] for r in mistakes)},
        "untagged_images": len(untagged),
        "untagged_image_all_correct": (sum(r["correct"] for r in untagged) / len(untagged)
                                       if untagged else None),
        "gap_bins_mm": list(GAP_BINS_MM),
        "by_boundary_gap": by_gap,
    }}


def evaluate(model_path: Path | None, data_dir: Path, split: str, out_dir: Path,
             backend: str = "auto", presence_min_pixels: int = PRESENCE_MIN_PIXELS,
             fragment_max_pixels: int = FRAGMENT_MAX_PIXELS,
             limit: int | None = None, progress: bool = True, camera_info: bool = True) -> dict:
    """Evaluate on ``split`` ('val', 'train' or 'all') of the dataset in ``data_dir``.

    ``camera_info``: give ``segment`` each image's intrinsics, as the node has them when
    depth/camera_info is published; False measures a node without camera_info (it matters
    only for a network trained with them, ``OutcomeSegmenter.uses_intrinsics``)."""
    manifest = load_manifest(data_dir)
    images = [im for im in manifest["images"] if split == "all" or im["split"] == split]
    if limit:
        images = images[:limit]
    if not images:
        raise ValueError(f"{data_dir}: no images in split {split!r}")
    seg = OutcomeSegmenter(model_path, presence_min_pixels=presence_min_pixels, backend=backend,
                           fragment_max_pixels=fragment_max_pixels)
    table = seg.table
    to_model_ids = same_task(table, manifest_table(manifest), seg.model_path, data_dir)
    k = table.num_classes
    conf = np.zeros((k, k), np.int64)
    truth_p, pred_p, rows, times = [], [], [], []
    # What camera_info would carry for each image (None: evaluated without it).
    cameras = {im["episode"]: Intrinsics.from_record(reported_camera(im)) if camera_info else None
               for im in images}
    for im in tqdm(images, desc=f"evaluate {split}", disable=not progress, unit="img"):
        depth, labels = read_pair(data_dir, im["episode"])
        labels = to_model_ids[labels]
        result = seg.segment(depth, cameras[im["episode"]])
        times.append(result.inference_ms)
        counts = outcome_pixel_counts(labels, table)  # once: presence and size bins
        t = presence_from_counts(counts, presence_threshold(*labels.shape, presence_min_pixels))
        truth_p.append([t[n] for n in table.outcome_names])
        pred_p.append([result.present[n] for n in table.outcome_names])
        conf += confusion(labels, result.labels, k)
        rows.append({"episode": im["episode"], "truth": t, "pred": result.present,
                     "correct": t == result.present,
                     "truth_pixels": counts})
    truth_arr, pred_arr = np.array(truth_p, bool), np.array(pred_p, bool)
    iou = np.diag(conf) / np.maximum(1, conf.sum(0) + conf.sum(1) - np.diag(conf))
    h, w = depth.shape
    episodes = run_episodes(data_dir, {r["episode"] for r in rows})  # for both breakdowns
    report = {
        "n_images": len(images),
        "split": split,
        "data": str(data_dir),
        "model": str(seg.model_path),
        "backend": seg.backend,
        **presence_scores(truth_arr, pred_arr, table.outcome_names),
        "image_all_correct_ci95": [round(v, 4) for v in wilson_interval(
            sum(r["correct"] for r in rows), len(rows))],
        "label_table": table.to_dict(),
        "pixel_miou": float(iou.mean()),
        "iou": {name: round(float(iou[c]), 5) for c, name in enumerate(table.classes)},
        "presence_min_pixels": presence_min_pixels,
        "presence_threshold_pixels": presence_threshold(h, w, presence_min_pixels),
        "fragment_max_pixels": fragment_max_pixels,
        "camera_info": camera_info,
        "heights_from": ("camera_info" if camera_info and seg.uses_intrinsics
                         else "nominal camera"),
        "image_size": [w, h],
        "inference_ms_p50": float(np.percentile(times, 50)),
        "confusion": conf.tolist(),
        "mistakes": [r["episode"] for r in rows if not r["correct"]],
        "recall_by_size": recall_by_size(rows, table.outcome_names, h, w),
        **hard_case_report(rows, hard_cases_of(episodes)),
        **recall_by_place(rows, places_of(episodes, data_dir), table.outcome_names, h, w),
    }
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    save_json(out_dir / "eval.json", report)
    plot_confusion(out_dir / "confusion.png", conf, table)
    plot_examples(out_dir / "eval_examples.png", data_dir, rows, seg, cameras, to_model_ids)
    plot_recall_by_size(out_dir / "recall_by_size.png", report["recall_by_size"])
    if "hard_cases" in report:
        plot_boundary_gap(out_dir / "boundary_gap.png",
                          report["hard_cases"]["by_boundary_gap"], report["image_all_correct"])
    return report


def plot_confusion(path: Path, conf: np.ndarray, table: LabelTable) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    norm = conf / np.maximum(1, conf.sum(1, keepdims=True))
    fig, ax = plt.subplots(figsize=(6, 5), dpi=100)
    im = ax.imshow(norm, cmap="Blues", vmin=0, vmax=1)
    for i in range(table.num_classes):
        for j in range(table.num_classes):
            ax.text(j, i, f"{norm[i, j]:.3f}", ha="center", va="center", fontsize=8,
                    color="white" if norm[i, j] > 0.5 else "black")
    ax.set_xticks(range(table.num_classes), table.classes, rotation=30, ha="right")
    ax.set_yticks(range(table.num_classes), table.classes)
    ax.set_xlabel("predicted")
    ax.set_ylabel("true (pixels with depth)")
    ax.set_title("pixel confusion, row-normalised")
    fig.colorbar(im)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_boundary_gap(path: Path, by_gap: list[dict], overall: float) -> None:
    """All-correct per boundary-gap bin (hard_cases.py), with image counts: where the errors
    are."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [e["bin"] for e in by_gap]
    rates = [e["image_all_correct"] if e["images"] else 0.0 for e in by_gap]
    fig, ax = plt.subplots(figsize=(7, 4), dpi=100)
    bars = ax.bar(names, rates, color="tab:blue")
    for bar, e in zip(bars, by_gap):
        ax.text(bar.get_x() + bar.get_width() / 2, bar.get_height() + 0.01,
                f"{e['images'] - e['mistakes']}/{e['images']}", ha="center", fontsize=8)
    ax.axhline(overall, color="k", linestyle="--", linewidth=1,
               label=f"all images: {overall:.3f}")
    ax.set_ylim(0, 1.08)
    ax.set_xlabel("boundary gap: the smallest distance of an object over the fixture from the "
                  "inside / partly-inside boundary")
    ax.set_ylabel("image all-correct")
    ax.set_title("Where the mistakes are: images by how close an object is to the boundary")
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_examples(path: Path, data_dir: Path, rows: list[dict], seg: OutcomeSegmenter,
                  cameras: dict[int, Intrinsics | None], to_model_ids: np.ndarray,
                  n: int = 6) -> None:
    """depth | truth | prediction | disagreement for mistakes first, then correct images;
    ``cameras``: each episode's intrinsics as ``evaluate`` gave them to ``segment``;
    ``to_model_ids``: the data's label ids -> the model's (``same_task``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from task_outcome_ros.labels import colourise
    from training.preview import depth_to_grey

    chosen = ([r for r in rows if not r["correct"]] + [r for r in rows if r["correct"]])[:n]
    fig, axes = plt.subplots(len(chosen), 4, figsize=(13, 2.6 * len(chosen)), dpi=75,
                             squeeze=False)
    for row, r in zip(axes, chosen):
        depth, labels = read_pair(data_dir, r["episode"])
        labels = to_model_ids[labels]
        pred = seg.segment(depth, cameras[r["episode"]]).labels
        wrong = (pred != labels) & (labels != IGNORE)
        names = lambda p: ", ".join(k for k, v in p.items() if v) or "nothing"  # noqa: E731
        row[0].imshow(depth_to_grey(depth), cmap="gray")
        row[0].set_title(f"episode {r['episode']} " + ("OK" if r["correct"] else "MISTAKE"),
                         fontsize=9, color="black" if r["correct"] else "red")
        row[1].imshow(colourise(labels, seg.table))
        row[1].set_title("truth: " + names(r["truth"]), fontsize=8)
        row[2].imshow(colourise(pred, seg.table))
        row[2].set_title("predicted: " + names(r["pred"]), fontsize=8)
        row[3].imshow(wrong, cmap="Reds")
        row[3].set_title(f"wrong pixels: {int(wrong.sum())}", fontsize=8)
        for ax in row:
            ax.axis("off")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
