"""How right is the network's height channel? Floor fit versions 1 and 2, nominal camera and
each image's own camera.

Not a timing: the height above the floor (``floor.height_above_floor``, the network's third
input) is computed at the working size from validation images of the default run four ways:
with floor fit version 1 (models up to 0.1.7) and version 2, each with the envelope's nominal
camera and with the camera the image was rendered with (what camera_info gives the node).
Each is compared with the true height of the same depth samples, obtained from the renderer's
camera pose, above the episode's simulated floor level, on pixels more than 15 cm
above the floor (box tops, walls, the rim: where success and stuck_on_rim differ by
millimetres). Sensor noise is shared by both sides, so only the camera model and the plane fit
are measured. (An earlier version of this bench subtracted each side's median over background
pixels, which hid a fitted plane's offset.)

    python bench/heights.py [--images 200]

Writes the ``heights`` section of bench/results.json.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import record  # noqa: E402

RUN_DIR = Path(__file__).resolve().parents[1] / "runs" / "default"
WORKING_SIZE = (160, 120)
ABOVE_M = 0.15


def true_heights(depth: np.ndarray, camera: dict, k: np.ndarray) -> np.ndarray:
    """World z (m) of every working-size depth sample, through the rendering camera's pose."""
    h, w = depth.shape
    u = (np.arange(w) - (w - 1) / 2 - k[2] * w) / (k[0] * w)
    v = (np.arange(h) - (h - 1) / 2 - k[3] * h) / (k[1] * h)
    rays = np.stack(np.broadcast_arrays(u[None, :], v[:, None], np.ones((h, w))), -1)
    rotation, position = np.array(camera["rotation"]), np.array(camera["position"])
    return (rays * depth[..., None]) @ rotation.T[:, 2] + position[2]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--images", type=int, default=200, help="validation images to use")
    args = parser.parse_args()
    command = "python bench/heights.py " + " ".join(sys.argv[1:])

    import torch

    from task_outcome_ros.camera import Intrinsics
    from task_outcome_ros.depth import sanitize_depth
    from task_outcome_ros.floor import FLOOR_FIT, LEGACY_FLOOR_FIT, height_above_floor
    from task_outcome_ros.model import resize_depth
    from training.chunks import load_chunks
    from training.config import dataset_config_from_dict
    from training.dataset import load_manifest
    from training.render import read_pair

    if not (RUN_DIR / "manifest.json").is_file():
        raise SystemExit(f"no dataset at {RUN_DIR}: `make ship` (or `python -m training "
                         "dataset`) makes it")
    manifest = load_manifest(RUN_DIR)
    images = [im for im in manifest["images"] if im["split"] == "val"][:args.images]
    cfg = dataset_config_from_dict(manifest["config"])
    floor_z = {int(e["episode"]): float(e["floor_z"]) for e in
               load_chunks(RUN_DIR / "simulate", cfg.episodes, cfg.chunk_size)}
    variants = {f"fit{fit}_{cam}": (fit, cam) for fit in (LEGACY_FLOOR_FIT, FLOOR_FIT)
                for cam in ("nominal", "own")}
    errors: dict[str, list[float]] = {name: [] for name in variants}
    for im in images:
        depth, _ = read_pair(RUN_DIR, im["episode"])
        z, frac = resize_depth(sanitize_depth(depth), WORKING_SIZE)
        k = Intrinsics.from_record(im["camera"]).normalised()
        world_z = true_heights(z, im["camera"], k)
        full = frac > 0.99                           # whole working pixels only: no edges
        truth = world_z - floor_z[im["episode"]]
        up = full & (truth > ABOVE_M)
        if not up.any():
            continue
        for name, (fit, cam) in variants.items():
            intrinsics = torch.from_numpy(k)[None] if cam == "own" else None
            est = height_above_floor(torch.from_numpy(z)[None], torch.from_numpy(full)[None],
                                     intrinsics=intrinsics, version=fit)[0].numpy()
            errors[name].append(float(np.median(np.abs(est[up] - truth[up]))))
    summary = {name: {"images": len(e), "mean_mm": round(1e3 * float(np.mean(e)), 2),
                      "p95_mm": round(1e3 * float(np.percentile(e, 95)), 2),
                      "max_mm": round(1e3 * float(np.max(e)), 2),
                      "over_3mm": int(np.sum(np.array(e) > 0.003))}
               for name, e in errors.items()}
    record("heights", {
        "what": (f"per image, median |estimated - true height| over working-size pixels more "
                 f"than {ABOVE_M} m above the floor; then mean / p95 / max over images"),
        "data": f"validation images of {RUN_DIR}", "working_size": list(WORKING_SIZE),
        "floor_fit_now": FLOOR_FIT, **summary,
    }, command)


if __name__ == "__main__":
    main()
