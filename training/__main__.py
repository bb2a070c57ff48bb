"""``python -m training <stage>``: the offline pipeline, one sub-command per stage.

simulate -> discover -> render (+ manifest, previews) -> train -> evaluate; ``dataset`` runs
the first three, ``run`` runs everything. Each stage reads the previous stage's files in the
run folder (``--out``) and writes its own; re-running a stage resumes it. ``export-bag`` writes
a run's images as a rosbag2 bag for the ROS side (outcome_bag, outcome_replay); ``demo``
plays a small fresh bag through the live node and scores it (``make demo``).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

from task_outcome_ros.cli_args import non_negative_int, positive_int
from task_outcome_ros.fragments import FRAGMENT_MAX_PIXELS
from training.config import (
    ROBUSTNESS_IMAGES,
    ConfigError,
    DatasetConfig,
    dataset_config_from_dict,
    load_json,
    save_json,
)
from training.scene import DEFAULT_SCENE, bundled_scenes, load_scene

DEFAULT_OUT = Path("runs/default")


def add_dataset_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=DEFAULT_OUT,
                   help="run folder (default: %(default)s)")
    p.add_argument("--scene", default=None, metavar="NAME|FILE",
                   help="scene spec: a bundled name (" + ", ".join(bundled_scenes())
                        + ") or a YAML file (default: the run's own, else 'default')")
    p.add_argument("--episodes", type=positive_int, default=None,
                   help="episodes to simulate (default 10000, or the run's own)")
    p.add_argument("--seed", type=non_negative_int, default=None,
                   help="run seed (default 0, or the run's own)")
    p.add_argument("--workers", type=positive_int, default=None,
                   help="worker processes (default 2); results do not depend on it")
    p.add_argument("--chunk-size", type=positive_int, default=None,
                   help="episodes per resumable unit (default 50)")


def resolve_dataset_config(args: argparse.Namespace) -> DatasetConfig:
    """The scene spec given (else the run folder's saved config, else the default spec), with
    the options given on top. A spec other than the run's own is refused when saved."""
    saved = Path(args.out) / "config.json"
    scene = getattr(args, "scene", None)
    if scene is not None and saved.exists():  # the run's size and seed, unless given anew
        run = dataset_config_from_dict(load_json(saved))
        cfg = load_scene(scene, episodes=run.episodes, seed=run.seed,
                         chunk_size=run.chunk_size, val_fraction=run.val_fraction)
        if dataclasses.replace(cfg, workers=run.workers) != run:
            raise ConfigError(f"{saved} was made with scene {run.task!r}, not with the spec "
                              f"{scene!r} as given; use another --out, or leave --scene out "
                              "to continue the run")
    elif scene is not None:
        cfg = load_scene(scene)
    elif saved.exists():
        cfg = dataset_config_from_dict(load_json(saved))
    else:
        cfg = load_scene(DEFAULT_SCENE)
    overrides = {name: getattr(args, attr) for name, attr in
                 (("episodes", "episodes"), ("seed", "seed"), ("workers", "workers"),
                  ("chunk_size", "chunk_size")) if getattr(args, attr, None) is not None}
    return dataclasses.replace(cfg, **overrides).validate()


def cmd_simulate(args) -> None:
    from training.dataset import save_run_config
    from training.simulate import run_simulate

    cfg = resolve_dataset_config(args)
    save_run_config(args.out, cfg)
    run_simulate(args.out, cfg)


def _episodes(args, cfg):
    from training.chunks import load_chunks

    return load_chunks(Path(args.out) / "simulate", cfg.episodes, cfg.chunk_size)


def cmd_discover(args) -> None:
    from training.discover import run_discover

    cfg = resolve_dataset_config(args)
    run_discover(args.out, cfg, _episodes(args, cfg))
    report = load_json(Path(args.out) / "discovery.json")
    print(f"discover: {report['n_clusters']} clusters {report['cluster_names']}, "
          f"ARI vs geometry {report['ari_vs_geometry']}, noise points {report['noise_points']}")


def cmd_render(args) -> None:
    from training.dataset import write_manifest
    from training.discover import load_outcomes
    from training.preview import save_examples
    from training.render import run_render

    cfg = resolve_dataset_config(args)
    outcomes, table = load_outcomes(args.out)
    records = run_render(args.out, cfg, _episodes(args, cfg), outcomes, table)
    manifest = write_manifest(args.out, cfg, records, table)
    save_examples(Path(args.out) / "examples.png", Path(args.out), manifest)
    _save_noise_figure(args.out, cfg, _episodes(args, cfg), outcomes, table)


def _save_noise_figure(out: Path, cfg: DatasetConfig, episodes, outcomes, table) -> None:
    from training.noise import save_clean_vs_noisy_figure
    from training.render import render_episode

    shot = render_episode(episodes[0], outcomes[0], cfg, cfg.seed, table)
    save_clean_vs_noisy_figure(Path(out) / "noise.png", shot["clean"], shot["depth"],
                               shot["labels"], table)


def cmd_dataset(args) -> None:
    timings = {}
    for name, fn in (("simulate", cmd_simulate), ("discover", cmd_discover),
                     ("render", cmd_render)):
        start = time.perf_counter()
        fn(args)
        timings[name] = round(time.perf_counter() - start, 2)
    cfg = resolve_dataset_config(args)
    save_json(Path(args.out) / "timings.json",
              {"episodes": cfg.episodes, "workers": cfg.workers, "seconds": timings})
    print(f"dataset: {cfg.episodes} episodes in {Path(args.out)} ({timings} s)")


def add_train_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--epochs", type=positive_int, default=None, help="training epochs")
    p.add_argument("--batch-size", type=positive_int, default=None)
    p.add_argument("--lr", type=float, default=None)
    p.add_argument("--base-width", type=positive_int, default=None,
                   help="FCN width of the first level (default 8)")
    p.add_argument("--levels", type=positive_int, default=None,
                   help="FCN stride-2 stages (default 5)")
    p.add_argument("--head-width", type=int, default=None, metavar="CHANNELS",
                   help="channels of the last decoder block, which the 1x1 head reads (default "
                        "0: --base-width); for a --base-width under the task's class count")
    p.add_argument("--space-to-depth", type=positive_int, default=None,
                   help="2: fold 2 x 2 input pixels into channels, run the convs at half "
                        "the working size and upsample the logits back: a twice-finer "
                        "--input-size for about the same cost, or the same one for about "
                        "half (default 1)")
    p.add_argument("--full-size-head", type=int, default=None, metavar="CHANNELS",
                   help="with --space-to-depth 2: a thin head of this many channels at the "
                        "working size, fed the unfolded input, draws the outcome boundaries "
                        "(0 = none, the logits are upsampled; default 0)")
    p.add_argument("--input-size", type=int, nargs=2, metavar=("W", "H"), default=None,
                   help="working resolution (default 160 120)")
    p.add_argument("--max-minutes", type=float, default=None, help="training time budget")
    p.add_argument("--ema-decay", type=float, default=None,
                   help="per-step decay of the weight average that is validated (0 = off)")
    p.add_argument("--near-boundary-weight", "--near-rim-weight", type=float, default=None,
                   dest="near_boundary_weight",
                   help="sampling weight of training images with an object within 2 cm of "
                        "the task's inside/partly-inside boundary, e.g. a box top near the "
                        "rim (default 2.5; 1 = uniform)")
    p.add_argument("--small-outcome-weight", type=float, default=None,
                   help="sampling weight of training images with an outcome present under "
                        "800 px at 640 x 480, times the near-boundary weight (default 1 = off)")
    p.add_argument("--touching-outcomes-weight", type=float, default=None,
                   help="sampling weight of training images where two different outcomes "
                        "touch in the labels, e.g. a box stacked on another, times the other "
                        "weights (default 1 = off)")
    p.add_argument("--touching-objects-weight", type=float, default=None,
                   help="sampling weight of training images where two objects touch in the "
                        "frame, whatever their outcomes, times the other weights (default 1 = "
                        "off)")
    p.add_argument("--object-distance-weight", type=float, default=None,
                   help="weight of a training-only target: each object pixel's distance to "
                        "the nearest pixel of anything else, read from the class head's "
                        "features, so they tell touching objects apart (default 0 = off)")
    p.add_argument("--aug-noise", type=float, default=None,
                   help="re-drawn training noise per image: up to this many times the "
                        "sensor's own (default 1; 0 = off)")
    p.add_argument("--aug-holes", type=float, default=None,
                   help="share of training images that lose their depth over large smooth "
                        "regions (up to 35 %% of the image), as real frames lose whole "
                        "surfaces (default 0 = off)")
    p.add_argument("--aug-roll", type=float, default=None, dest="aug_roll_deg",
                   help="camera roll added per training image, up to this many degrees either "
                        "way on top of the spec's, by turning the image about its principal "
                        "point (default 0 = off)")
    p.add_argument("--aug-islands", type=float, default=None,
                   help="outlier islands per training image: up to this rate per 640 x 480 "
                        "pixel of small patches of wrong depth, as disparity sensors' wrong "
                        "matches (e.g. 3e-4; default 0 = off)")
    p.add_argument("--aug-islands-discs", action=argparse.BooleanOptionalAction, default=None,
                   help="draw each outlier island as a disc of its own size in working pixels "
                        "(several at 320 x 240) instead of in one (default off)")
    p.add_argument("--aug-range-limit", type=float, default=None,
                   help="share of training images cut at a range limit drawn in their far "
                        "depths, with the nearer-reading band their noise gives there, as a "
                        "sensor leaves along its maximum range (e.g. 0.5; default 0 = off)")
    p.add_argument("--train-crop", type=int, nargs=2, metavar=("W", "H"), default=None,
                   help="train on one W x H crop per image of the --input-size cache, its "
                        "heights above the support plane fitted on the whole image: a finer "
                        "working size at the cost per step of the crop's (default: whole "
                        "images)")
    p.add_argument("--lovasz-weight", type=float, default=None,
                   help="weight of the per-image outcome IoU (Lovász) loss added to "
                        "cross-entropy (default 0.5; 0 = off)")
    p.add_argument("--object-balance-pixels", type=non_negative_int, default=None,
                   help="cross-entropy weighs each outcome object smaller than this many "
                        "working-size pixels like one of this size, so small objects count "
                        "like large ones (default 0 = off)")
    p.add_argument("--relief-window-px", type=non_negative_int, default=None,
                   help="add the heights' local relief over a square of this many (odd) "
                        "working pixels as a fourth input channel, so a small object stands "
                        "out the same on any surface (default 0 = off)")
    p.add_argument("--relief-smoothing-px", type=non_negative_int, default=None,
                   help="compute that relief on the heights' mean over a square of this many "
                        "(odd) working pixels, so sensor noise does not read as relief "
                        "(default 0 = off)")
    p.add_argument("--relief-base-px", type=non_negative_int, default=None,
                   help="find that relief's surface on the heights' mean over a square of this "
                        "many (odd) working pixels, so noise on a flat surface reads less "
                        "relief (default 0 = the same heights as each pixel's own)")
    p.add_argument("--relief-noise-sds", type=float, default=None,
                   help="lower that relief by this many deviations of the smoothed heights' "
                        "noise, measured around each pixel, so a noisy far floor reads as "
                        "flat as a quiet one (needs --relief-smoothing-px; default 0 = off)")
    p.add_argument("--relief-beneath-support", action=argparse.BooleanOptionalAction,
                   default=None,
                   help="measure that relief, below a table top, from the room floor beneath "
                        "it, so an object on the room floor beside the table reads its height "
                        "(a task on a table; default off)")
    p.add_argument("--nearest-height", action=argparse.BooleanOptionalAction, default=None,
                   help="add each working pixel's near-side height as an input channel, "
                        "so a thin rim and an object's top edge keep their true height "
                        "(default off)")
    p.add_argument("--camera-intrinsics", action=argparse.BooleanOptionalAction, default=None,
                   help="height channel from each image's own intrinsics (camera_info on the "
                        "robot) instead of the nominal camera's")
    p.add_argument("--device", choices=("cpu", "cuda", "auto"), default=None)
    p.add_argument("--amp", choices=("auto", "bf16", "off"), default=None,
                   help="autocast: auto = fp16 on CUDA, bf16 on CPUs with native bf16, else "
                        "fp32 (default auto)")
    p.add_argument("--channels-last", action=argparse.BooleanOptionalAction, default=None,
                   help="NHWC activations on or off (default: the faster layout on this "
                        "machine, timed before the first epoch; see bench/train_step.py)")
    p.add_argument("--train-seed", type=non_negative_int, default=None)
    p.add_argument("--no-resume", action="store_true", help="start training from scratch")
    p.add_argument("--ship", action="store_true",
                   help="copy the best checkpoint (+ ONNX) into task_outcome_ros/models/")


def resolve_train_config(args: argparse.Namespace):
    from training.config import TrainConfig

    fields = {"epochs": "epochs", "batch_size": "batch_size", "lr": "lr",
              "base_width": "base_width", "levels": "levels", "max_minutes": "max_minutes",
              "device": "device",
              "amp": "amp", "seed": "train_seed", "ema_decay": "ema_decay",
              "channels_last": "channels_last", "near_boundary_weight": "near_boundary_weight",
              "small_outcome_weight": "small_outcome_weight",
              "touching_outcomes_weight": "touching_outcomes_weight",
              "touching_objects_weight": "touching_objects_weight",
              "object_distance_weight": "object_distance_weight",
              "aug_noise": "aug_noise", "aug_holes": "aug_holes", "aug_islands": "aug_islands",
              "aug_islands_discs": "aug_islands_discs",
              "aug_range_limit": "aug_range_limit",
              "aug_roll_deg": "aug_roll_deg",
              "lovasz_weight": "lovasz_weight",
              "object_balance_pixels": "object_balance_pixels",
              "relief_window_px": "relief_window_px",
              "relief_smoothing_px": "relief_smoothing_px",
              "relief_base_px": "relief_base_px", "relief_noise_sds": "relief_noise_sds",
              "nearest_height": "nearest_height",
              "relief_beneath_support": "relief_beneath_support",
              "camera_intrinsics": "camera_intrinsics", "space_to_depth": "space_to_depth",
              "full_size_head": "full_size_head", "head_width": "head_width"}
    overrides = {k: getattr(args, a) for k, a in fields.items() if getattr(args, a) is not None}
    if args.input_size is not None:
        overrides["input_size"] = tuple(args.input_size)
    if args.train_crop is not None:
        overrides["train_crop"] = tuple(args.train_crop)
    return dataclasses.replace(TrainConfig(), **overrides).validate()


def cmd_train(args) -> None:
    cfg = resolve_train_config(args)   # a bad option is refused before anything is linked
    if args.dataset_from is not None:
        from training.dataset import link_dataset

        linked = link_dataset(args.dataset_from, Path(args.out))
        print(f"train: on the dataset of {args.dataset_from} ({', '.join(linked)} linked "
              f"into {args.out})")
    train_and_ship(args, cfg)


def train_and_ship(args, cfg) -> None:
    """Train on the dataset in --out (and ship with --ship): what `train` and `run` share."""
    from training.train import train

    best = train(args.out, cfg, resume=not args.no_resume)
    print(f"train: best checkpoint {best}")
    if args.ship:
        ship(best)


def ship(best: Path) -> Path:
    """Install a checkpoint as the package's model for its task (``model_path:=<task>``),
    with its ONNX export beside it."""
    import shutil

    from task_outcome_ros.checkpoint import load
    from task_outcome_ros.inference import models_dir, shipped_model_file
    from task_outcome_ros.onnx_export import export_onnx

    task = (load(best).train_config.get("dataset") or {}).get("task", "default")
    target = models_dir() / shipped_model_file(task)
    target.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(best, target)
    export_onnx(target)
    print(f"shipped: {target} (+ ONNX)")
    return target


def cmd_evaluate(args) -> None:
    from training.evaluate import evaluate
    from training.size_recall import SMALL_OUTCOME_PIXELS, found_in

    model = args.checkpoint or Path(args.out) / "train" / "best.pt"
    data = args.data or Path(args.out)
    out = args.eval_out or (Path(args.out) / ("eval" if data == Path(args.out)
                                              else f"eval_{Path(data).name}"))
    report = evaluate(model, data, args.split, out, backend=args.backend,
                      fragment_max_pixels=args.fragment_max_pixels,
                      camera_info=args.camera_info)
    print(f"evaluate: {report['n_images']} images of {data} ({args.split}, heights from the "
          f"{report['heights_from']}): image all-correct "
          f"{report['image_all_correct']:.4f} (95 % interval "
          f"{report['image_all_correct_ci95'][0]:.3f}-{report['image_all_correct_ci95'][1]:.3f}), "
          f"pixel mIoU {report['pixel_miou']:.4f}, "
          f"presence recall {report['presence_recall']} -> {out}/eval.json")
    hard = report.get("hard_cases")
    if hard:
        untagged = hard["untagged_image_all_correct"]
        print(f"  mistakes per hard case {hard['mistakes']}; all-correct on the "
              f"{hard['untagged_images']} images without one: "
              + ("-" if untagged is None else f"{untagged:.4f}"))
        print("  right per boundary gap: " + ", ".join(
            f"{e['bin']} {e['images'] - e['mistakes']}/{e['images']}"
            for e in hard["by_boundary_gap"]))
    for outcome, bins in report["recall_by_size"]["by_outcome"].items():
        print(f"  {outcome} found by size (px at 640 x 480): " + ", ".join(
            f"{e['bin']} {e['found']}/{e['images']}" for e in bins if e["images"]))
    for outcome, places in report.get("recall_by_place", {}).get("by_outcome", {}).items():
        if sum(any(e["images"] for e in bins) for bins in places.values()) > 1:
            print(f"  {outcome} found by where it rests (under {SMALL_OUTCOME_PIXELS} px): "
                  + "; ".join("{} {}/{} ({}/{})".format(
                      place, *found_in(bins), *found_in(bins, SMALL_OUTCOME_PIXELS))
                      for place, bins in places.items()))


def add_robustness_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=DEFAULT_OUT,
                   help="run folder (default: %(default)s)")
    p.add_argument("--checkpoint", default=None,
                   help="a shipped model's name or a checkpoint (default: the run's "
                        "train/best.pt, else the shipped model of the data's task)")
    p.add_argument("--data", type=Path, default=None,
                   help="dataset run whose validation episodes are re-rendered (default: --out)")
    p.add_argument("--images", type=positive_int, default=ROBUSTNESS_IMAGES,
                   help=f"validation episodes per stress point (default {ROBUSTNESS_IMAGES})")
    p.add_argument("--eval-out", type=Path, default=None,
                   help="where robustness.json goes (default: <data>/robustness)")
    p.add_argument("--factors", nargs="+", default=None, metavar="FACTOR",
                   help="sweep only these factors, e.g. lost_depth_share (default: all)")


def add_eval_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--checkpoint", type=Path, default=None,
                   help="model to evaluate (default: <out>/train/best.pt)")
    p.add_argument("--data", type=Path, default=None,
                   help="dataset run folder to evaluate on (default: --out)")
    p.add_argument("--split", choices=("val", "train", "all"), default="val")
    p.add_argument("--backend", choices=("auto", "torch", "onnx"), default="auto")
    p.add_argument("--fragment-max-pixels", type=non_negative_int, default=FRAGMENT_MAX_PIXELS,
                   help="absorb outcome fragments smaller than this (at 640 x 480) into the "
                        f"object they sit on; 0 = off (default {FRAGMENT_MAX_PIXELS})")
    p.add_argument("--camera-info", action=argparse.BooleanOptionalAction, default=True,
                   help="give the model each image's intrinsics, as the node has them from "
                        "depth/camera_info (default); --no-camera-info measures a node "
                        "without it")
    p.add_argument("--eval-out", type=Path, default=None, help="where eval.json goes")


def cmd_export_bag(args) -> None:
    from training.export_bag import cmd_export_bag

    cmd_export_bag(args)


def cmd_robustness(args) -> None:
    from training.robustness import SWEEPS, check_sweeps, run_robustness

    sweeps = None
    if args.factors:  # checked before the model or the data is looked for; the suite's order
        check_sweeps(dict.fromkeys(args.factors, ()))
        sweeps = {f: SWEEPS[f] for f in SWEEPS if f in args.factors}
    data = args.data or Path(args.out)
    out = args.eval_out or Path(data) / "robustness"  # beside the data it stressed
    report = run_robustness(args.checkpoint or _robustness_model(args, Path(data)), data, out,
                            images=args.images, sweeps=sweeps)
    for factor, entry in report["factors"].items():
        pairs = ", ".join(f"{v}: {a:.3f}" for v, a in zip(entry["values"],
                                                          entry["image_all_correct"]))
        print(f"robustness {factor}: {pairs}")
    print(f"robustness: {report['images']} images per point -> {out / 'robustness.json'}")


def _robustness_model(args, data: Path) -> str | Path:
    """Without --checkpoint: the run's own best.pt, else the shipped model of the data's task
    (a model of another task would be refused)."""
    trained = Path(args.out) / "train" / "best.pt"
    if trained.is_file():
        return trained
    return load_json(data / "config.json").get("task", "default")


def add_independent_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", type=Path, required=True,
                   help="dataset run whose simulated episodes and outcomes are used")
    p.add_argument("--out", type=Path, required=True, help="folder for the independent set")
    p.add_argument("--images", type=positive_int, default=300,
                   help="images, one per episode from the first (default 300)")
    p.add_argument("--seed", type=non_negative_int, default=0,
                   help="seed of the cameras and the noise (default 0)")
    p.add_argument("--workers", type=positive_int, default=2, help="processes (default 2)")


def cmd_independent(args) -> None:
    from training.independent import make_independent_set

    manifest = make_independent_set(args.data, args.out, args.images, seed=args.seed,
                                    workers=args.workers)
    print(f"independent: {len(manifest['images'])} images in {args.out}; score a model with "
          f"python -m training evaluate --data {args.out} --checkpoint MODEL")


def add_compare_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("a", type=Path, help="eval.json or robustness.json (or its folder) of model A")
    p.add_argument("b", type=Path, help="the same kind of result for model B, on the same images")


def cmd_compare(args) -> None:
    from training.compare import run_compare

    run_compare(args.a, args.b)


def add_real_frames_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", default=None,
                   help="checkpoint path or shipped task name (default: the default model)")
    p.add_argument("--frames", default="arc2017",
                   help="a bundled frame set (training/real_frames/NAME) or a folder with "
                        "frames.yaml (default arc2017: real totes)")
    p.add_argument("--out", type=Path, required=True,
                   help="folder for real_frames.json and real_frames.png")


def cmd_real_frames(args) -> None:
    from training.real import run_real_frames, wrong_outcomes

    report = run_real_frames(args.model, args.frames, args.out)
    for row in report["rows"]:
        verdict = ("outside the envelope: " + "; ".join(row["outside_envelope"])
                   if row["outside_envelope"] else "inside the envelope")
        if "correct" in row:
            invented, missed = wrong_outcomes(row)
            verdict += (", right" if row["correct"] else
                        f", wrong (invented {invented or '-'}, missed {missed or '-'})")
        print(f"real-frames {row['frame']}: {', '.join(row['predicted']) or 'nothing'} "
              f"({verdict})")
    score = (f"image all-correct {report['image_all_correct']:.3f}, "
             f"{report['invented_pixels']} px of outcomes the frames do not hold, "
             if report["scored"]
             else f"not scored (a {report['model_task']} model on {report['frame_set_task']} "
                  f"frames), ")
    print(f"real-frames: {report['frames']} frames of {report['frame_set']}, {score}"
          f"{report['inside_envelope']} inside the envelope -> {args.out / 'real_frames.json'}")


def cmd_demo(args) -> int:
    from training.demo import demo_main

    return demo_main(args)


def cmd_run(args) -> None:
    """Everything: dataset, train (and ship), evaluate on the validation split."""
    cfg = resolve_train_config(args)   # refused before minutes of dataset, not after
    cmd_dataset(args)
    train_and_ship(args, cfg)          # on the dataset it has just made: no --dataset-from
    cmd_evaluate(args)


COMMANDS = {
    "simulate": (cmd_simulate, "simulate the episodes (pybullet)"),
    "discover": (cmd_discover, "cluster final object states into outcomes (DBSCAN)"),
    "render": (cmd_render, "render noisy depth + labels, write the manifest and previews"),
    "dataset": (cmd_dataset, "simulate + discover + render"),
    "train": (cmd_train, "train the FCN on the run's dataset"),
    "evaluate": (cmd_evaluate, "evaluate a checkpoint with the paper's image-level metric"),
    "run": (cmd_run, "dataset + train + evaluate"),
    "export-bag": (cmd_export_bag, "write a run's images as a rosbag2 bag (+ ground truth)"),
    "robustness": (cmd_robustness, "score a model on stress sets, one factor at a time"),
    "independent": (cmd_independent, "an evaluation set made by pybullet ray tests and a "
                                     "separately written noise model"),
    "compare": (cmd_compare, "two models' results on the same images, paired (McNemar)"),
    "real-frames": (cmd_real_frames, "what a model says on real depth frames (hand-labelled "
                                     "outcomes, envelope verdicts, contact sheet)"),
    "demo": (cmd_demo, "a small simulated bag through the live outcome_node, scored"),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m training", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="stage", required=True, metavar="stage")
    for name, (_, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text)
        if name == "export-bag":
            from training.export_bag import add_args

            add_args(p)
            continue
        if name == "demo":
            from training.demo import add_demo_args

            add_demo_args(p)
            continue
        if name == "robustness":
            add_robustness_args(p)
            continue
        if name == "independent":
            add_independent_args(p)
            continue
        if name == "compare":
            add_compare_args(p)
            continue
        if name == "real-frames":
            add_real_frames_args(p)
            continue
        add_dataset_args(p)
        if name in ("train", "run"):
            add_train_args(p)
        if name == "train":
            p.add_argument("--dataset-from", type=Path, default=None, metavar="RUN",
                           help="train in --out on RUN's dataset, linked rather than copied "
                                "(a second recipe on the same images; `compare` pairs them)")
        if name in ("evaluate", "run"):
            add_eval_args(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        code = COMMANDS[args.stage][0](args)
    except (ConfigError, FileNotFoundError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted: run the same command again to resume", file=sys.stderr)
        return 130
    return int(code or 0)


if __name__ == "__main__":
    sys.exit(main())
