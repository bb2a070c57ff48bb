"""Pictures of a dataset run, for people: example images with their labels, clean vs noisy."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from task_outcome_ros.labels import IGNORE, colourise
from task_outcome_ros.outcome_report import overlay_rgb


def depth_to_grey(depth_m: np.ndarray, near: float = 1.0, far: float = 4.0) -> np.ndarray:
    """Depth -> uint8 grey (near = bright); invalid pixels black."""
    with np.errstate(invalid="ignore"):
        g = np.clip((far - depth_m) / (far - near), 0.0, 1.0)
    return np.where(np.isfinite(depth_m), g * 255, 0).astype(np.uint8)


def save_examples(path: Path, run_dir: Path, manifest: dict, n: int = 6) -> None:
    """A grid of depth | labels | overlay for the first ``n`` images of a run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    from training.dataset import manifest_table
    from training.render import read_pair

    table = manifest_table(manifest)
    colours = table.colour_map()
    images = manifest["images"][:n]
    fig, axes = plt.subplots(len(images), 3, figsize=(11, 2.9 * len(images)), dpi=80,
                             squeeze=False)
    for row, im in zip(axes, images):
        depth, labels = read_pair(run_dir, im["episode"])
        present = [k for k, v in im["present"].items() if v] or ["nothing"]
        row[0].imshow(depth_to_grey(depth), cmap="gray")
        row[0].set_title(f"episode {im['episode']} depth", fontsize=9)
        row[1].imshow(colourise(labels, table))
        row[1].set_title("labels: " + ", ".join(present), fontsize=9)
        row[2].imshow(overlay_rgb(depth, labels, table=table))
        row[2].set_title("objects: " + ", ".join(im["objects"]), fontsize=8)
        for ax in row:
            ax.axis("off")
    handles = [Patch(color=np.array(colours[i]) / 255, label=name)
               for i, name in enumerate(table.classes)]
    handles.append(Patch(color=np.array(colours[IGNORE]) / 255, label=f"no depth ({IGNORE})"))
    fig.legend(handles=handles, loc="lower center", ncol=6, fontsize=9)
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    fig.savefig(path)
    plt.close(fig)
