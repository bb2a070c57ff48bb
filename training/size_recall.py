"""Presence recall by how many pixels an outcome covers in the true label image.

Why: the working size (160 x 120) gives an outcome of 100 pixels at 640 x 480 about six
working pixels. The tote model 0.9.0 finds fallen objects covering 1,600 pixels or more in
473 of 474 validation images, but those under 200 pixels in 4 of 23, although 36 of the 37
it misses have 50 or more pixels standing out from what lies behind them by two or more
depth steps of the frame's sensor (docs/evaluation.md, "Small outcomes"). One recall per
outcome hides that; this report shows where it falls.

Sizes are given at 640 x 480 (like the presence rule's 50 pixels) and scaled with the image
area, so runs at other resolutions share the bins.
"""

from __future__ import annotations

from pathlib import Path

from task_outcome_ros.labels import scale_pixel_count

# An outcome showing fewer pixels than this at 640 x 480 is small: the tote model finds half
# the fallen objects under it and 0.98 of those above (docs/evaluation.md). Training can draw
# images with one more often (train.small_outcome_sample_weights); the evaluation's command
# line reports them apart. It is one of the bins' edges below.
SMALL_OUTCOME_PIXELS = 800
# Lower edges of the bins, in pixels at 640 x 480; the last bin is open above.
SIZE_BINS_PX = (50, 100, 200, 400, SMALL_OUTCOME_PIXELS, 1600)


def size_bin_names() -> list[str]:
    edges = list(SIZE_BINS_PX)
    return [f"{lo}-{hi}" for lo, hi in zip(edges, edges[1:])] + [f">= {edges[-1]}"]


def size_bin(pixels: int, height: int, width: int) -> int | None:
    """Index of the bin of an outcome covering ``pixels`` in an image of this size; None
    below the first bin (not present by the default presence rule)."""
    edges = [scale_pixel_count(p, height, width) for p in SIZE_BINS_PX]
    found = [i for i, lo in enumerate(edges) if pixels >= lo]
    return found[-1] if found else None


def found_in(bins: list[dict], below_px: int | None = None) -> tuple[int, int]:
    """(found, images) summed over a ``recall_by_size`` outcome's bins, or over those of
    outcomes under ``below_px`` pixels at 640 x 480 (an edge of the bins)."""
    kept = [e for lo, e in zip(SIZE_BINS_PX, bins) if below_px is None or lo < below_px]
    return sum(e["found"] for e in kept), sum(e["images"] for e in kept)


def recall_by_size(rows: list[dict], outcome_names: list[str], height: int, width: int
                   ) -> dict:
    """Per outcome and size bin: images where the outcome is truly present, and how many of
    them the prediction calls present. ``rows`` carry ``truth`` and ``pred`` (outcome ->
    present) and ``truth_pixels`` (outcome -> pixel count)."""
    names = size_bin_names()
    table = {}
    for outcome in outcome_names:
        bins = [{"bin": name, "images": 0, "found": 0} for name in names]
        for r in rows:
            if not r["truth"][outcome]:
                continue
            k = size_bin(r["truth_pixels"][outcome], height, width)
            if k is None:  # present by a presence rule below the first bin
                continue
            bins[k]["images"] += 1
            bins[k]["found"] += bool(r["pred"][outcome])
        for entry in bins:
            entry["recall"] = entry["found"] / entry["images"] if entry["images"] else None
        table[outcome] = bins
    return {"size_bins_px": list(SIZE_BINS_PX), "by_outcome": table}


def plot_recall_by_size(path: Path, report: dict) -> None:
    """Presence recall against the outcome's size in the truth, one line per outcome."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = size_bin_names()
    fig, ax = plt.subplots(figsize=(7, 4), dpi=100)
    for j, (outcome, bins) in enumerate(report["by_outcome"].items()):
        xs = [i for i, e in enumerate(bins) if e["images"]]
        line, = ax.plot(xs, [bins[i]["recall"] for i in xs], marker="o", label=outcome)
        for i in xs:  # counts stacked per outcome, so that equal recalls stay readable
            ax.annotate(f"{bins[i]['found']}/{bins[i]['images']}", (i, bins[i]["recall"]),
                        textcoords="offset points", xytext=(0, 5 + 9 * j), ha="center",
                        fontsize=7, color=line.get_color())
    ax.set_xticks(range(len(names)), names)
    ax.set_ylim(0, 1.2)
    ax.set_xlabel("pixels the outcome covers in the true labels (at 640 x 480)")
    ax.set_ylabel("presence recall")
    ax.set_title("Which outcomes are found, by how much of the image they cover")
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
