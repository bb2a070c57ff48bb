"""Stage 4: the dataset on disk (manifest + split) and its torch view for training.

On disk (``<run>/``): ``images/NNNNNN_depth.png`` (16-bit, millimetres, 0 = invalid, like a
Kinect's 16UC1) and ``images/NNNNNN_labels.png`` (ids of the task's label table, 255 = no
depth), plus ``manifest.json``: the label table, and per image its seeds, camera, per-object
outcomes, the outcomes present by the presence rule and the split (95/5 by episode).

Training never decodes PNGs in its loop: ``build_cache`` shrinks every image once to the
network's working size with the inference code's own ``resize_depth`` (so training sees exactly
what the node will feed the network) and stores the result as one compressed array file.
"""

from __future__ import annotations

import json
import multiprocessing as mp
from pathlib import Path

import numpy as np
from tqdm import tqdm

from task_outcome_ros.labels import IGNORE, LabelTable
from training.config import DatasetConfig, dataset_config_from_dict, load_json, save_json, to_dict
from training.seeding import STAGE_STREAMS

SPLITS = ("train", "val")


def split_episodes(n_episodes: int, val_fraction: float, seed: int) -> dict[str, list[int]]:
    """A seeded permutation: the first round(val_fraction * n) episodes are validation."""
    order = np.random.default_rng([seed, STAGE_STREAMS["split"]]).permutation(n_episodes)
    n_val = int(round(val_fraction * n_episodes))
    if n_episodes >= 2 and val_fraction > 0:
        n_val = min(max(n_val, 1), n_episodes - 1)  # tiny runs still get both splits
    return {"train": sorted(order[n_val:].tolist()), "val": sorted(order[:n_val].tolist())}


def write_manifest(run_dir: Path, cfg: DatasetConfig, records: list[dict],
                   table: LabelTable) -> dict:
    """manifest.json: the images with their split, the config and the label table."""
    split = split_episodes(len(records), cfg.val_fraction, cfg.seed)
    which = {i: name for name, ids in split.items() for i in ids}
    images = []
    for rec in records:
        i = rec["episode"]
        images.append({**rec, "split": which[i], "depth": f"images/{i:06d}_depth.png",
                       "labels": f"images/{i:06d}_labels.png"})
    # The worker count is how the data was made, not what it is: leaving it out keeps the
    # manifest byte-identical for any --workers (and across resumes with another count).
    config = {k: v for k, v in to_dict(cfg).items() if k != "workers"}
    manifest = {"seed": cfg.seed, "n_images": len(images), "config": config,
                "label_table": table.to_dict(),
                "split_sizes": {k: len(v) for k, v in split.items()}, "images": images}
    save_json(Path(run_dir) / "manifest.json", manifest)
    return manifest


def load_manifest(run_dir: Path) -> dict:
    return load_json(Path(run_dir) / "manifest.json")


def manifest_table(manifest: dict) -> LabelTable:
    """The label table a manifest carries (manifests written before: the default task's)."""
    from training.discover import table_of

    return table_of(manifest)


def downsample_labels(labels: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Shrink a label image to (W, H) by an area-weighted majority vote, ignoring 255.

    Nearest-neighbour would keep whichever pixel the grid hits, often a noise hole (255) or a
    one-pixel edge; a vote keeps what most of the block shows. Integer factors vote over exact
    blocks; other factors (e.g. 640 x 480 -> 192 x 144) weigh each source pixel by the share
    of it that falls in the output pixel (OpenCV's area resize of each class's mask). An
    output pixel that covers only ignored pixels is ignored.
    """
    import cv2

    w, h = size
    H, W = labels.shape
    measured = labels[labels != IGNORE]
    n_classes = int(measured.max()) + 1 if measured.size else 1  # any task's table
    if H % h or W % w:
        shares = np.stack([cv2.resize((labels == c).astype(np.float32), (w, h),
                                      interpolation=cv2.INTER_AREA)
                           for c in range(n_classes)])
    else:
        fy, fx = H // h, W // w
        blocks = labels.reshape(h, fy, w, fx)
        shares = np.stack([(blocks == c).sum(axis=(1, 3)) for c in range(n_classes)])
    out = shares.argmax(axis=0).astype(np.uint8)
    out[shares.max(axis=0) <= 0] = IGNORE
    return out


def _cache_one(args: tuple[str, int, tuple[int, int]]) -> tuple[np.ndarray, np.ndarray,
                                                                 np.ndarray]:
    from task_outcome_ros.model import resize_depth
    from training.render import read_pair

    run_dir, index, size = args
    depth, labels = read_pair(Path(run_dir), index)
    small_depth, valid_fraction = resize_depth(depth, size)
    return (small_depth.astype(np.float16), valid_fraction.astype(np.float16),
            downsample_labels(labels, size))


def cache_path(run_dir: Path, split: str, size: tuple[int, int]) -> Path:
    return Path(run_dir) / "cache" / f"{split}_{size[0]}x{size[1]}.npz"


def _build_split_file(run_dir: Path, split: str, size: tuple[int, int], path: Path,
                      one, names: tuple[str, ...], workers: int, desc: str) -> Path:
    """``one((run_dir, episode, size))`` for every image of ``split``, its tuple's items
    stacked into the arrays ``names`` of ``path`` beside the episode ``indices`` (written
    once, atomically; an existing file is kept)."""
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    if path.exists():
        return path
    manifest = load_manifest(run_dir)
    indices = [im["episode"] for im in manifest["images"] if im["split"] == split]
    jobs = [(str(run_dir), i, tuple(size)) for i in indices]
    if workers > 1 and len(jobs) > 64:
        with mp.get_context("spawn").Pool(workers) as pool:
            results = list(tqdm(pool.imap(one, jobs, chunksize=32), total=len(jobs),
                                desc=f"{desc} {split}", unit="img"))
    else:
        results = [one(j) for j in tqdm(jobs, desc=f"{desc} {split}", unit="img")]
    empty = np.zeros((0, *size[::-1]))
    arrays = {name: np.stack([r[k] for r in results]) if results else empty
              for k, name in enumerate(names)}
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.stem + ".tmp.npz")
    np.savez(tmp, indices=np.array(indices, np.int64), **arrays)
    tmp.replace(path)
    return path


def build_cache(run_dir: Path, split: str, size: tuple[int, int], workers: int = 2) -> Path:
    """Working-size arrays of one split (built once, reused by every training run)."""
    return _build_split_file(run_dir, split, size, cache_path(run_dir, split, size),
                             _cache_one, ("depth", "valid", "labels"), workers, "cache")


def _nearest_one(args: tuple[str, int, tuple[int, int]]) -> tuple[np.ndarray]:
    from task_outcome_ros.depth import sanitize_depth
    from task_outcome_ros.model import nearest_depth
    from training.render import read_pair

    run_dir, index, size = args
    depth = sanitize_depth(read_pair(Path(run_dir), index)[0])
    return (nearest_depth(depth, size).astype(np.float16),)


def nearest_cache_path(run_dir: Path, split: str, size: tuple[int, int]) -> Path:
    return Path(run_dir) / "cache" / f"{split}_{size[0]}x{size[1]}_nearest.npz"


def build_nearest_cache(run_dir: Path, split: str, size: tuple[int, int],
                        workers: int = 2) -> Path:
    """The near-side depths (``model.nearest_depth``) of one split at working size, in a
    file of their own beside the main cache: only networks with that input channel need
    them, and the main cache of an existing run stays as it is."""
    return _build_split_file(run_dir, split, size, nearest_cache_path(run_dir, split, size),
                             _nearest_one, ("nearest",), workers, "nearest")


def load_cache(run_dir: Path, split: str, size: tuple[int, int], workers: int = 2,
               nearest: bool = False) -> dict:
    """{'indices', 'depth' (N,h,w) m, 'valid' (N,h,w) fraction, 'labels' (N,h,w) uint8},
    plus 'nearest' (N,h,w) m when ``nearest`` (``build_nearest_cache``)."""
    with np.load(build_cache(run_dir, split, size, workers)) as data:
        arrays = {k: data[k] for k in data.files}
    if nearest:
        with np.load(build_nearest_cache(run_dir, split, size, workers)) as data:
            if not np.array_equal(data["indices"], arrays["indices"]):
                raise ValueError(f"{nearest_cache_path(run_dir, split, size)} holds other "
                                 "images than the main cache; delete it to rebuild it")
            arrays["nearest"] = data["nearest"]
    return arrays


class OutcomeDataset:
    """A torch ``Dataset`` over one split at working size: (depth, valid, labels) tensors.

    Subclassing torch's Dataset is not needed (duck typing); importing torch lazily keeps the
    data-generation stages light.
    """

    def __init__(self, run_dir: Path, split: str, size: tuple[int, int], workers: int = 2):
        self.arrays = load_cache(run_dir, split, size, workers)

    def __len__(self) -> int:
        return len(self.arrays["indices"])

    def __getitem__(self, i: int):
        import torch

        return (torch.from_numpy(self.arrays["depth"][i].astype(np.float32)),
                torch.from_numpy(self.arrays["valid"][i].astype(np.float32)),
                torch.from_numpy(self.arrays["labels"][i].astype(np.int64)))


def save_run_config(run_dir: Path, cfg: DatasetConfig) -> None:
    """Save the resolved config; refuse to mix a run folder with a different config."""
    path = Path(run_dir) / "config.json"
    data = json.loads(json.dumps(to_dict(cfg)))  # tuples -> lists, as they come back from disk
    comparable = {k: v for k, v in data.items() if k != "workers"}
    if path.exists():
        # Through the config classes, so a folder saved before a field existed compares by
        # what it means (its defaults), not by its spelling.
        saved = json.loads(json.dumps(to_dict(dataset_config_from_dict(load_json(path)))))
        old = {k: v for k, v in saved.items() if k != "workers"}
        if old != comparable:
            raise ValueError(
                f"{path} holds a different config than requested; use another --out folder "
                "or the same options to resume")
    save_json(path, data)


# What the dataset stages write into a run folder (simulate, discover, render, the training
# cache), everything a training run and its evaluation read; not train/ or eval*/ results.
DATASET_ENTRIES = ("config.json", "simulate", "discovery.json", "outcomes.json", "render",
                   "images", "manifest.json", "cache", "timings.json")


def link_dataset(source: Path, run_dir: Path) -> list[str]:
    """Make ``run_dir`` train on ``source``'s dataset: symlink each of its
    ``DATASET_ENTRIES`` into ``run_dir`` (nothing is copied; when the source has a cache, one
    built later for another working size lands in that shared folder). Running it again is a
    no-op; an entry ``run_dir`` already holds that is not the same link is refused, so two
    datasets never mix. Returns the names linked."""
    source, run_dir = Path(source).resolve(), Path(run_dir)
    if not (source / "manifest.json").is_file():
        raise FileNotFoundError(f"{source}: no manifest.json; make its dataset first "
                                f"(python -m training dataset --out {source})")
    present = [name for name in DATASET_ENTRIES if (source / name).exists()]
    for name in present:
        link = run_dir / name
        if (link.exists() or link.is_symlink()) and not (
                link.is_symlink() and link.resolve() == (source / name).resolve()):
            raise ValueError(f"{link} exists and is not a link to {source / name}: use a new "
                             f"--out to train on {source}'s dataset")
    run_dir.mkdir(parents=True, exist_ok=True)
    for name in present:
        target = source / name
        if not (run_dir / name).is_symlink():
            (run_dir / name).symlink_to(target, target_is_directory=target.is_dir())
    return present
