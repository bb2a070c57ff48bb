"""How often the node's envelope check flags frames the model was trained for, and which
frames of another envelope it lets through.

Not a timing: each validation image of a run goes through ``OutcomeSegmenter.segment`` (the
node's code path, with the image's camera as camera_info) and is counted as flagged when
``outside_envelope`` is non-empty. Run on a run of the model's own spec (in-envelope: should
be flagged rarely) and on a run of another spec (should be flagged always).

    python bench/envelope.py --data runs/bench_dataset                   # default spec run
    python bench/envelope.py --data runs/tote --model default --label tote_frames

Writes the ``envelope.<label>`` section of bench/results.json.
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import record  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True, help="a dataset run folder")
    parser.add_argument("--split", default="val", choices=("val", "train", "all"))
    parser.add_argument("--limit", type=int, default=500, help="at most this many images")
    parser.add_argument("--model", default=None, help="shipped model name or checkpoint")
    parser.add_argument("--label", default=None, help="section name (default: the run's task)")
    args = parser.parse_args()

    from tqdm import tqdm

    from task_outcome_ros.camera import Intrinsics
    from task_outcome_ros.inference import OutcomeSegmenter
    from training.dataset import load_manifest
    from training.render import read_pair, reported_camera

    manifest = load_manifest(args.data)
    images = [im for im in manifest["images"]
              if args.split == "all" or im["split"] == args.split][:args.limit]
    seg = OutcomeSegmenter(args.model, backend="auto", num_threads=1)
    reasons: Counter = Counter()
    flagged = []
    for im in tqdm(images, desc="envelope", unit="img"):
        depth, _ = read_pair(args.data, im["episode"])
        result = seg.segment(depth, Intrinsics.from_record(reported_camera(im)))
        if result.outside_envelope:
            flagged.append(im["episode"])
            reasons.update(why.split(" ")[0] + " " + why.split(" ")[1]
                           for why in result.outside_envelope)
    task = manifest["config"].get("task", "default")
    record(f"envelope.{args.label or task}", {
        "data": f"{len(images)} {args.split} images of {args.data} (task {task})",
        "model": str(seg.model_path), "model_task": seg.envelope.task if seg.envelope else None,
        "images": len(images), "flagged": len(flagged),
        "flagged_fraction": round(len(flagged) / max(1, len(images)), 4),
        "reasons": dict(reasons), "flagged_episodes": flagged[:50],
    }, command="python bench/envelope.py " + " ".join(sys.argv[1:]), model=seg.model_path)


if __name__ == "__main__":
    main()
