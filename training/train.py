"""Stage 5: train the outcome FCN on the cached working-size dataset.

Class-weighted cross-entropy ignoring 255 (no depth), AdamW with warm-up + cosine decay, an
exponential moving average (EMA) of the weights that is validated and shipped, label-honest
augmentation (``training.augment``: mirror, small shifts, depth scale, re-drawn noise and
the sensor's other errors leave labels where the objects are; ``training.crops`` the same
on crops, without the shift and scale), images with an object near the task's inside /
partly-inside boundary drawn more often (``near_boundary_weight``: where most mistakes are),
mixed precision where the hardware does it natively (fp16 on CUDA, bf16 on CPUs with
AVX512-BF16/AMX), the memory layout (channels-last or contiguous) that steps faster on this
machine, resumable self-describing checkpoints after every epoch, a training-curve plot.

Efficiency on 2 CPU cores (measured, see README): images are decoded and shrunk once into the
cache (training.dataset.build_cache), so an epoch is pure tensor work; augmentation runs on the
whole batch at once. The validation metric during training is the paper's image-level one at
the working size, with pixel counts scaled to 640 x 480 (exact for the 4x nearest-neighbour
upsampling the node does).
"""

from __future__ import annotations

import json
import math
import time
from contextlib import nullcontext
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from task_outcome_ros import checkpoint
from task_outcome_ros.camera import Intrinsics
from task_outcome_ros.checkpoint import resolve_device
from task_outcome_ros.fragments import absorb_fragments, fragment_threshold
from task_outcome_ros.labels import (
    BACKGROUND,
    FIRST_OUTCOME_ID,
    IGNORE,
    PRESENCE_MIN_PIXELS,
    REFERENCE_PIXELS,
    LabelTable,
    scale_pixel_count,
)
from task_outcome_ros.model import (
    DEFAULT_NORMALISATION,
    INTRINSICS_FROM_CAMERA_INFO,
    NEAREST_HEIGHT,
    RELIEF_BENEATH_SUPPORT,
    build_model,
    check_normalisation,
    input_channels,
    network_input,
)
from training.augment import (
    OBJECT_DISTANCE,
    Augmentations,
    gather_batch,
    measure_for_roll,
)
from training.config import (
    LATER_NETWORK_OPTIONS,
    CameraConfig,
    DatasetConfig,
    NoiseConfig,
    TrainConfig,
    dataset_config_from_dict,
    save_json,
    to_dict,
)
from training.crops import crop_batch, measure_planes
from training.dataset import load_cache, load_manifest, manifest_table
from training.hard_cases import episode_hard_cases
from training.losses import (
    OBJECT_BALANCE_MAX_WEIGHT,
    ObjectDistanceHead,
    object_balance_weights,
    object_distance_loss,
    outcome_lovasz_loss,
)
from training.overlaps import (
    OBJECT_DISTANCE_CLIP_PX,
    frames_with_touching_objects,
    object_distance_cache,
)
from training.size_recall import SMALL_OUTCOME_PIXELS

WARMUP_FRACTION = 0.03


# The default task's sensor (training/config.NoiseConfig defaults), which the figure above
# measured: other sensors scale it by their axial noise, sigma_d / (f b).
_DEFAULT_AXIAL = NoiseConfig().sigma_disparity_px / (CameraConfig().nominal_focal_px
                                                     * NoiseConfig().baseline)


def task_normalisation(dataset: DatasetConfig) -> dict:
    """The network input's normalisation for a task: depth centred on the envelope's middle
    distance, heights in units of the spec's ``height_scale`` (the tallest fixture top: an
    open box's rim sits at 1 or below), and the
    envelope's middle focal length as the nominal camera. The default task's is exactly
    ``model.DEFAULT_NORMALISATION``. A task on a table measures heights from its top."""
    norm = dict(DEFAULT_NORMALISATION)
    norm["offset_m"] = (dataset.camera.distance[0] + dataset.camera.distance[1]) / 2
    norm["height_scale_m"] = dataset.scene.height_scale
    norm["focal_over_width"] = dataset.camera.nominal_focal_px / dataset.camera.width
    if dataset.scene.table_size is not None:  # heights from the table top, not the room floor
        norm["support_above_floor"] = list(dataset.scene.table_height)
    return norm


def sensor_noise_ratio(dataset: DatasetConfig) -> float:
    """The task's sensor noise over the default sensor's, for the augmentation noise."""
    noise, camera = dataset.noise, dataset.camera  # parameters drawn per frame: their midpoints
    axial = noise.midpoint("sigma_disparity_px") / (camera.nominal_focal_px
                                                    * noise.midpoint("baseline"))
    return axial / _DEFAULT_AXIAL


def class_weights(labels: np.ndarray, power: float, num_classes: int) -> torch.Tensor:
    """(1 / frequency) ** power, normalised to mean 1; unseen classes get the largest weight."""
    # In chunks of images: bincount casts to int64, 8 bytes per pixel, and a whole 20,000-image
    # cache at 320 x 240 would take 12 GB at once (the run was killed for memory).
    counts = np.zeros(256, np.float64)
    for start in range(0, len(labels), 256):
        counts += np.bincount(labels[start:start + 256].ravel(), minlength=256)
    counts = counts[:num_classes]
    freq = counts / max(1.0, counts.sum())
    w = np.where(freq > 0, (1.0 / np.maximum(freq, 1e-12)) ** power, 0.0)
    w[freq == 0] = w.max() if w.max() > 0 else 1.0
    return torch.tensor(w / w.mean(), dtype=torch.float32)


def fitted_epochs(epochs: int, epoch_s: float, max_minutes: float) -> int:
    """The epochs the learning-rate schedule spans: ``epochs``, or fewer when ``epochs`` of
    ``epoch_s`` seconds (the first epoch's time, validation included) would overrun the
    budget. A CPU without native bf16 takes about twice as long a step as one with it, and
    a schedule cut off by the budget would stop with its learning rate still high; fitted,
    the cosine decays to zero within the budget on any machine."""
    if epoch_s <= 0:
        return epochs
    return max(1, min(epochs, int(max_minutes * 60 // epoch_s)))


def lr_at(step: int, total: int, base: float) -> float:
    warm = max(1, int(WARMUP_FRACTION * total))
    if step < warm:
        return base * (step + 1) / warm
    progress = (step - warm) / max(1, total - warm)
    return base * 0.5 * (1.0 + math.cos(math.pi * min(1.0, progress)))


class WeightAverage:
    """EMA of the weights and BatchNorm buffers: ``avg = d * avg + (1 - d) * current``.

    The decay ramps up as min(decay, (1 + n) / (10 + n)) over the first updates so the average
    does not drag the random initial weights along; ``decay = 0`` keeps a plain copy.
    """

    def __init__(self, model: torch.nn.Module, decay: float) -> None:
        import copy

        self.decay, self.updates = decay, 0
        self.module = copy.deepcopy(model).eval()
        for p in self.module.parameters():
            p.requires_grad_(False)

    @torch.no_grad()
    def update(self, model: torch.nn.Module) -> None:
        self.updates += 1
        d = min(self.decay, (1 + self.updates) / (10 + self.updates))
        current = model.state_dict()
        for name, avg in self.module.state_dict().items():
            if avg.dtype.is_floating_point:
                avg.mul_(d).add_(current[name].detach(), alpha=1 - d)
            else:  # BatchNorm's num_batches_tracked
                avg.copy_(current[name])


def cpu_has_native_bf16() -> bool:
    """Whether this CPU computes bf16 natively (Linux /proc/cpuinfo flags; False elsewhere)."""
    try:
        flags = Path("/proc/cpuinfo").read_text().split()
    except OSError:
        return False
    return "avx512_bf16" in flags or "amx_bf16" in flags


def resolve_precision(amp: str, device_type: str) -> str:
    """``TrainConfig.amp`` -> the autocast dtype used: "fp16" (with a grad scaler), "bf16" or
    "fp32". ``auto`` picks mixed precision only where the hardware does it natively: fp16 on
    CUDA, bf16 on a CPU with AVX512-BF16/AMX (0.56x the fp32 step time on the 2-core EPYC,
    bench/train_step.py), fp32 elsewhere (emulated bf16 can be slower than fp32)."""
    if amp == "off":
        return "fp32"
    if amp == "bf16":
        return "bf16"
    if device_type == "cuda":
        return "fp16"
    return "bf16" if device_type == "cpu" and cpu_has_native_bf16() else "fp32"


def autocast_factory(precision: str, device_type: str):
    """A zero-argument callable giving the autocast context of ``resolve_precision``'s answer
    (a no-op context for fp32)."""
    if precision == "fp32":
        return nullcontext
    dtype = torch.float16 if precision == "fp16" else torch.bfloat16
    return lambda: torch.autocast(device_type, dtype=dtype)


def weighted_cross_entropy(logits: torch.Tensor, labels: torch.Tensor,
                           class_weights: torch.Tensor | None,
                           pixel_weights: torch.Tensor | None = None) -> torch.Tensor:
    """Cross-entropy ignoring 255, weighted by class and, when given, by pixel: the weighted
    mean sum(p w[y] l) / sum(p w[y]), which is ``F.cross_entropy``'s own mean when every
    pixel weight is 1."""
    if pixel_weights is None:
        return F.cross_entropy(logits, labels, weight=class_weights, ignore_index=IGNORE)
    per_pixel = F.cross_entropy(logits, labels, weight=class_weights, ignore_index=IGNORE,
                                reduction="none")            # w[y] l, 0 where ignored
    keep = labels != IGNORE
    w_y = (class_weights[labels.clamp_max(len(class_weights) - 1)]
           if class_weights is not None else torch.ones_like(per_pixel))
    total = (pixel_weights * w_y * keep).sum()
    return (pixel_weights * per_pixel).sum() / total.clamp_min(1e-12)


def layout_step_seconds(model_args: dict, x: torch.Tensor, labels: torch.Tensor,
                        weights: torch.Tensor | None, autocast, scaler, cfg: TrainConfig,
                        rounds: int = 2) -> dict[bool, float]:
    """{channels_last: seconds} of a training step on this machine, each layout's fastest
    of ``rounds`` interleaved steps after one to warm up, on throwaway copies of the network.
    Which layout is faster depends on the CPU (bench/train_step.py: channels-last 0.87x
    contiguous on a 2-core EPYC, 1.48x on an AMX Xeon), so ``TrainConfig.channels_last``
    "auto" measures it. The random state is put back, so the run's own draws do not move."""
    nets = {}
    with torch.random.fork_rng(devices=[]):
        for layout in (True, False):
            fmt = torch.channels_last if layout else torch.contiguous_format
            net = build_model(model_args).to(x.device, memory_format=fmt).train()
            optim = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
            nets[layout] = (net, optim, x.contiguous(memory_format=fmt))
        best = {True: math.inf, False: math.inf}
        for r in range(rounds + 1):
            for layout, (net, optim, xl) in nets.items():
                started = time.perf_counter()
                optimise_step(net, optim, xl, labels, weights, autocast, scaler,
                              cfg.lovasz_weight).item()
                if r:                                             # round 0 warms up
                    best[layout] = min(best[layout], time.perf_counter() - started)
    return best


def faster_layout(cfg: TrainConfig, arrays: dict, norm: dict, model_args: dict,
                  weights: torch.Tensor | None, autocast, scaler, device: torch.device
                  ) -> tuple[bool, str]:
    """Whether channels-last steps faster than contiguous here, on the first batch of
    ``arrays`` (unaugmented), and a note with both times for the log."""
    sample = gather_batch(arrays, np.arange(min(cfg.batch_size, len(arrays["indices"]))), None)
    x = network_input(sample.depth, sample.valid, norm, sample.intrinsics,
                      nearest=sample.nearest).to(device)
    labels = sample.labels.to(device)
    if cfg.train_crop is not None:  # timed at the size the network trains on
        cw, ch = cfg.train_crop
        x, labels = x[..., :ch, :cw], labels[..., :ch, :cw]
    step_s = layout_step_seconds(model_args, x, labels, weights, autocast, scaler, cfg)
    return step_s[True] < step_s[False], (f"chosen: {step_s[True]:.3f} s a step "
                                          f"channels-last, {step_s[False]:.3f} s contiguous")


def optimise_step(model, optim, x: torch.Tensor, labels: torch.Tensor,
                  weights: torch.Tensor | None, autocast, scaler, lovasz_weight: float = 0.0,
                  pixel_weights: torch.Tensor | None = None,
                  object_distance: tuple[ObjectDistanceHead, torch.Tensor, float] | None = None
                  ) -> torch.Tensor:
    """Forward (under ``autocast``), class-weighted cross-entropy ignoring 255 (per pixel
    weighted by ``pixel_weights`` too when given, ``losses.object_balance_weights``; plus
    ``lovasz_weight`` x the per-image outcome IoU loss, ``losses.py``; plus, with
    ``object_distance`` = (head, target in pixels, weight), that weight x the head's
    ``losses.object_distance_loss``), backward and one optimiser step (through the grad
    scaler when there is one; the optimiser holds the head's weights too). Returns the loss."""
    with autocast():
        logits = model(x)
        if object_distance is not None:
            head, target_px, distance_weight = object_distance
            distance_logits = head(labels.shape[-2:])
    logits = logits.float()          # both losses in fp32; one cast, not one per loss
    loss = weighted_cross_entropy(logits, labels, weights, pixel_weights)
    if lovasz_weight > 0:
        loss = loss + lovasz_weight * outcome_lovasz_loss(logits, labels)
    if object_distance is not None:
        loss = loss + distance_weight * object_distance_loss(
            distance_logits, target_px, labels, OBJECT_DISTANCE_CLIP_PX)
    optim.zero_grad(set_to_none=True)
    if scaler is not None:
        scaler.scale(loss).backward()
        scaler.step(optim)
        scaler.update()
    else:
        loss.backward()
        optim.step()
    return loss


def working_size_presence(counts: np.ndarray, small_pixels: int) -> np.ndarray:
    """(N, classes) working-size class counts -> (N, outcomes) presence at the reference
    resolution, outcomes in id order."""
    scaled = counts * (REFERENCE_PIXELS / small_pixels)
    return scaled[:, FIRST_OUTCOME_ID:] >= PRESENCE_MIN_PIXELS


@torch.inference_mode()
def validate(model, arrays: dict, truth_present: np.ndarray, device, norm, batch_size: int,
             table: LabelTable) -> dict:
    """Image-level all-correct rate and pixel IoU at the working size, after the same
    fragment absorption as inference."""
    model.eval()
    n = len(arrays["indices"])
    k = table.num_classes
    conf = np.zeros((k, k), np.int64)
    counts = np.zeros((n, k), np.int64)
    for s in range(0, n, batch_size):
        batch = gather_batch(arrays, np.arange(s, min(s + batch_size, n)), None)
        pred = model(network_input(batch.depth, batch.valid, norm, batch.intrinsics,
                                   nearest=batch.nearest).to(device)).argmax(1).cpu().numpy()
        # As inference does: fragments absorbed first, then no depth -> background.
        fragments = fragment_threshold(*pred.shape[1:])
        pred = np.stack([absorb_fragments(p.astype(np.uint8), fragments, table=table)
                         for p in pred])
        pred[batch.valid.numpy() == 0] = BACKGROUND
        truth = arrays["labels"][s:s + batch_size]
        for c in range(k):
            counts[s:s + len(pred), c] = (pred == c).reshape(len(pred), -1).sum(1)
        keep = truth != IGNORE
        conf += np.bincount(truth[keep].astype(np.int64) * k + pred[keep],
                            minlength=k ** 2).reshape(k, k)
    small = arrays["labels"].shape[1] * arrays["labels"].shape[2]
    pred_present = working_size_presence(counts, small)
    iou = np.diag(conf) / np.maximum(1, conf.sum(0) + conf.sum(1) - np.diag(conf))
    return {"image_all_correct": float(np.mean(np.all(pred_present == truth_present, axis=1))),
            "pixel_miou": float(iou.mean()), "iou": iou.round(4).tolist()}


def epoch_order(n: int, sample_weights: np.ndarray | None, gen: torch.Generator) -> np.ndarray:
    """The n training-image indices of one epoch: a permutation, or, with sampling weights, n
    draws with replacement in proportion to them."""
    if sample_weights is None:
        return torch.randperm(n, generator=gen).numpy()
    return torch.multinomial(torch.as_tensor(sample_weights, dtype=torch.float64), n,
                             replacement=True, generator=gen).numpy()


def flagged_sample_weights(flagged: np.ndarray, weight: float, what: str) -> np.ndarray:
    """``weight`` for the flagged training images, 1 for the others, saying how many are
    flagged (``what`` they are) -- the tail every per-image sampling weight below shares."""
    print(f"train: {flagged.sum()} of {len(flagged)} training images {what}; "
          f"sampled with weight {weight:g}")
    return np.where(flagged, weight, 1.0)


def near_boundary_sample_weights(run_dir: Path, indices: np.ndarray, weight: float
                                 ) -> np.ndarray | None:
    """Per-image sampling weights: ``weight`` for images tagged near_boundary, 1 for others;
    None (uniform epochs) when ``weight`` is 1."""
    if weight == 1.0:
        return None
    cases = episode_hard_cases(run_dir, {int(i) for i in indices})
    if cases is None:
        raise ValueError(f"{run_dir}: near_boundary_weight needs the run's simulate/ results "
                         "to find the near-boundary images; --near-boundary-weight 1 samples "
                         "uniformly")
    near = np.array(["near_boundary" in cases[int(i)].tags for i in indices])
    return flagged_sample_weights(near, weight, "are near the boundary")


def small_outcome_sample_weights(manifest: dict, indices: np.ndarray, weight: float
                                 ) -> np.ndarray | None:
    """Per-image sampling weights: ``weight`` for images with an outcome present that shows
    fewer than ``SMALL_OUTCOME_PIXELS`` (scaled from 640 x 480 to the image's size), 1 for
    others; None when ``weight`` is 1."""
    if weight == 1.0:
        return None
    by_index = {im["episode"]: im for im in manifest["images"]}
    small = np.zeros(len(indices), bool)
    for k, i in enumerate(indices):
        im = by_index[int(i)]
        size = im["camera"]   # the rendered size (camera_info: only with a calibration error)
        limit = scale_pixel_count(SMALL_OUTCOME_PIXELS, size["height"], size["width"])
        small[k] = any(present and im["pixel_counts"][name] < limit
                       for name, present in im["present"].items())
    return flagged_sample_weights(small, weight,
                                  f"show an outcome under {SMALL_OUTCOME_PIXELS} px")


def touching_outcome_pixels(labels: np.ndarray) -> np.ndarray:
    """(N, H, W) label images -> (N,) count of 4-neighbour pixel pairs whose two labels are
    different outcomes (ids from ``FIRST_OUTCOME_ID``; 255, no depth, is no outcome)."""
    def outcome(x: np.ndarray) -> np.ndarray:
        return (x >= FIRST_OUTCOME_ID) & (x != IGNORE)

    counts = np.zeros(len(labels), np.int64)
    for a, b in ((labels[:, 1:, :], labels[:, :-1, :]), (labels[:, :, 1:], labels[:, :, :-1])):
        touching = outcome(a) & outcome(b) & (a != b)
        counts += touching.reshape(len(labels), -1).sum(axis=1)
    return counts


def touching_outcomes_sample_weights(labels: np.ndarray, weight: float,
                                     chunk: int = 2000) -> np.ndarray | None:
    """Per-image sampling weights: ``weight`` for training images where two different
    outcomes touch (``touching_outcome_pixels`` > 0 in the working-size labels), 1 for
    others; None when ``weight`` is 1. Chunked: the labels may be memory-mapped."""
    if weight == 1.0:
        return None
    touching = np.concatenate([touching_outcome_pixels(np.asarray(labels[i:i + chunk])) > 0
                               for i in range(0, len(labels), chunk)])
    return flagged_sample_weights(touching, weight, "show two outcomes touching")


def touching_objects_sample_weights(run_dir: Path, manifest: dict, indices: np.ndarray,
                                    size: tuple[int, int], weight: float) -> np.ndarray | None:
    """Per-image sampling weights: ``weight`` for training images where two objects touch in
    the frame cast at the working ``size`` (``overlaps.frames_with_touching_objects``), 1 for
    others; None when ``weight`` is 1."""
    if weight == 1.0:
        return None
    touching = frames_with_touching_objects(run_dir, manifest, indices, tuple(size))
    return flagged_sample_weights(touching, weight, "show two objects touching")


def training_batch(arrays: dict, idx: np.ndarray, gen: torch.Generator, cfg: TrainConfig,
                   aug_noise: float, norm: dict
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """The network input, labels and object distances (None unless ``arrays`` holds them) of
    the training images ``idx``: whole images (``gather_batch``, augmented when
    ``cfg.augment``) or one crop of each (``crops.crop_batch``, with ``cfg.train_crop``)."""
    aug = Augmentations.of_config(cfg, aug_noise)
    if cfg.train_crop is not None:
        return (*crop_batch(arrays, idx, cfg.train_crop, gen, norm, aug), None)
    batch = gather_batch(arrays, idx, gen if cfg.augment else None, aug)
    return (network_input(batch.depth, batch.valid, norm, batch.intrinsics,
                          nearest=batch.nearest), batch.labels, batch.object_distance)


def combined_sample_weights(*weights: np.ndarray | None) -> np.ndarray | None:
    """The product of per-image sampling weights (None: uniform, left out)."""
    given = [w for w in weights if w is not None]
    return np.prod(given, axis=0) if given else None


# Fields that say how a run is executed, not what it learns: a resume may change them (the
# activations' memory layout among them). amp is compared by the precision it resolves to
# ("auto" and "bf16" are the same run on a CPU with native bf16), device through that
# precision too.
RESUME_FREE_FIELDS = frozenset({"max_minutes", "device", "threads", "amp",
                                "channels_last"})
# Training fields saved under an older name: the same setting (a resume is not refused).
RENAMED_TRAIN_FIELDS = {"near_rim_weight": "near_boundary_weight"}
# Training fields added later, with the value every run before them had (not a difference).
ADDED_TRAIN_FIELDS = {**LATER_NETWORK_OPTIONS, "object_balance_pixels": 0,
                      "small_outcome_weight": 1.0, "touching_outcomes_weight": 1.0,
                      "touching_objects_weight": 1.0, "object_distance_weight": 0.0,
                      "relief_window_px": 0, "relief_smoothing_px": 0, "relief_base_px": 0,
                      "relief_noise_sds": 0.0, "nearest_height": False,
                      "relief_beneath_support": False, "aug_holes": 0.0, "aug_islands": 0.0,
                      "aug_islands_discs": False, "aug_range_limit": 0.0, "aug_roll_deg": 0.0,
                      "train_crop": None}


def _field_differences(old: dict, new: dict, prefix: str = "",
                       ignore: frozenset[str] = frozenset()) -> list[str]:
    """"<prefix>field: old -> new" for every field that differs; a field only one side has
    differs from "<not recorded>" (its value on the other side is unknown)."""
    missing = "<not recorded>"
    return [f"{prefix}{k}: {old.get(k, missing)!r} -> {new.get(k, missing)!r}"
            for k in sorted((set(old) | set(new)) - ignore)
            if old.get(k, missing) != new.get(k, missing)]


def resume_differences(saved: dict, cfg: TrainConfig, saved_precision: str | None,
                       precision: str, saved_normalisation: dict | None = None,
                       normalisation: dict | None = None) -> list[str]:
    """What differs between a saved run's training config and ``cfg``, as "field: old -> new"
    lines; empty when the run may be resumed. A field the saved run did not record (it
    predates the field) counts as a difference: its value then is unknown. The input
    normalisations (both through ``check_normalisation``) are compared too: code changes
    such as the floor fit version change the inputs without changing the config."""
    now = json.loads(json.dumps(to_dict(cfg)))
    saved = {**ADDED_TRAIN_FIELDS,
             **{RENAMED_TRAIN_FIELDS.get(k, k): v for k, v in saved.items()}}
    differences = _field_differences(saved, now, ignore=RESUME_FREE_FIELDS)
    if saved_precision != precision:
        differences.append(f"precision: {saved_precision} -> {precision}")
    return differences + _field_differences(saved_normalisation or {}, normalisation or {},
                                            prefix="normalisation ")


def manifest_intrinsics(manifest: dict, indices: np.ndarray) -> np.ndarray:
    """(N, 4) float32 ``camera.Intrinsics.normalised`` of the images ``indices``, from the
    camera_info each was rendered with (what the node is given on the robot)."""
    from training.render import reported_camera

    cameras = {im["episode"]: reported_camera(im) for im in manifest["images"]}
    return np.stack([Intrinsics.from_record(cameras[int(i)]).normalised() for i in indices]
                    ) if len(indices) else np.zeros((0, 4), np.float32)


def _truth_present(manifest: dict, indices: np.ndarray, table: LabelTable) -> np.ndarray:
    by_index = {im["episode"]: im["present"] for im in manifest["images"]}
    return np.array([[by_index[int(i)][name] for name in table.outcome_names]
                     for i in indices]).reshape(len(indices), len(table.outcome_names))


def train(run_dir: Path, cfg: TrainConfig, out: Path | None = None, resume: bool = True,
          progress: bool = True) -> Path:
    """Train on <run>/cache, write <run>/train/{last,best}.pt, history and curves.

    Returns the path of the best checkpoint (by validation image_all_correct, then mIoU).
    """
    cfg = cfg.validate()
    run_dir = Path(run_dir)
    out = Path(out) if out else run_dir / "train"
    out.mkdir(parents=True, exist_ok=True)
    device = resolve_device(cfg.device)
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    manifest = load_manifest(run_dir)
    dataset = dataset_config_from_dict(manifest["config"])
    norm = task_normalisation(dataset)
    if cfg.relief_beneath_support and "support_above_floor" not in norm:  # before the caches load
        raise ValueError(f"{run_dir}: relief_beneath_support needs a task on a table (its "
                         "spec's table_size), which this run's spec has not")
    aug_noise = cfg.aug_noise * sensor_noise_ratio(dataset)
    train_arrays = load_cache(run_dir, "train", cfg.input_size, nearest=cfg.nearest_height)
    val_arrays = load_cache(run_dir, "val", cfg.input_size, nearest=cfg.nearest_height)
    if cfg.camera_intrinsics:
        norm["intrinsics"] = INTRINSICS_FROM_CAMERA_INFO
        for arrays in (train_arrays, val_arrays):
            arrays["intrinsics"] = manifest_intrinsics(manifest, arrays["indices"])
    for key in ("relief_window_px", "relief_smoothing_px", "relief_base_px",
                "relief_noise_sds"):
        if getattr(cfg, key):  # 0: off, left out of the normalisation
            norm[key] = getattr(cfg, key)
    if cfg.nearest_height:
        norm[NEAREST_HEIGHT] = True
    if cfg.relief_beneath_support:
        norm[RELIEF_BENEATH_SUPPORT] = True
    if len(train_arrays["indices"]) == 0:
        raise ValueError(f"{run_dir}: the train split is empty; generate more episodes")
    if cfg.train_crop is not None:
        print(f"train: fitting the support planes of {len(train_arrays['indices'])} training "
              f"images at {cfg.input_size[0]} x {cfg.input_size[1]} for {cfg.train_crop[0]} x "
              f"{cfg.train_crop[1]} crops")
        measure_planes(train_arrays, check_normalisation(norm))
    elif cfg.augment and cfg.aug_roll_deg > 0:  # crops are turned in windows, measured there
        measure_for_roll(train_arrays)
    if cfg.object_distance_weight:
        train_arrays[OBJECT_DISTANCE] = object_distance_cache(
            run_dir, manifest, train_arrays["indices"], "train", cfg.input_size)
    table = manifest_table(manifest)
    val_truth = _truth_present(manifest, val_arrays["indices"], table)
    weights = class_weights(train_arrays["labels"], cfg.class_weight_power,
                            table.num_classes).to(device)
    sample_weights = combined_sample_weights(
        near_boundary_sample_weights(run_dir, train_arrays["indices"], cfg.near_boundary_weight),
        small_outcome_sample_weights(manifest, train_arrays["indices"], cfg.small_outcome_weight),
        touching_outcomes_sample_weights(train_arrays["labels"], cfg.touching_outcomes_weight),
        touching_objects_sample_weights(run_dir, manifest, train_arrays["indices"],
                                        cfg.input_size, cfg.touching_objects_weight))

    model_args = {**cfg.model_args, "in_channels": input_channels(norm),
                  "num_classes": table.num_classes}
    outcome_ids = sorted(table.outcome_ids.values())
    model = build_model(model_args).to(device)
    if device.type == "cpu" and cfg.amp == "bf16" and not cpu_has_native_bf16():
        print("warning: --amp bf16 on a CPU without AVX512-BF16/AMX is emulated and may be "
              "slower than fp32 (--amp off)")
    precision = resolve_precision(cfg.amp, device.type)
    scaler = torch.amp.GradScaler("cuda") if precision == "fp16" else None
    autocast = autocast_factory(precision, device.type)
    channels_last, layout_note = cfg.channels_last, "set"
    if channels_last == "auto":
        channels_last, layout_note = faster_layout(cfg, train_arrays, norm, model_args,
                                                   weights, autocast, scaler, device)
    memory_format = torch.channels_last if channels_last else torch.contiguous_format
    model = model.to(memory_format=memory_format)
    average = WeightAverage(model, cfg.ema_decay)
    # After the average's copy, which must not carry the head's hook.
    distance_head = (ObjectDistanceHead(model).to(device, memory_format=memory_format)
                     if cfg.object_distance_weight else None)
    trained = [*model.parameters(), *(distance_head.parameters() if distance_head else ())]
    optim = torch.optim.AdamW(trained, lr=cfg.lr, weight_decay=cfg.weight_decay)
    print(f"train: {device.type}, {'fp32' if precision == 'fp32' else precision + ' autocast'}, "
          f"{'channels-last' if channels_last else 'contiguous'} activations ({layout_note})")

    n = len(train_arrays["indices"])
    steps_per_epoch = math.ceil(n / cfg.batch_size)
    schedule_epochs = cfg.epochs  # fitted to the budget after the first epoch
    history: list[dict] = []
    start_epoch, best_key = 0, (-1.0, -1.0)
    last_path, best_path = out / "last.pt", out / "best.pt"
    if resume and last_path.exists():
        state = checkpoint.load(last_path, device=str(device))
        differences = resume_differences(state.train_config.get("train") or {}, cfg,
                                         state.extra.get("precision"), precision,
                                         state.normalisation, check_normalisation(norm))
        if differences:
            raise ValueError(f"{last_path} was trained with another config "
                             f"({'; '.join(differences)}); use a new --out or delete it to "
                             "start over")
        # last.pt's model is the average (what validation saw); the raw weights, the optimizer
        # and the average's update count live in its training state.
        average.module.load_state_dict(state.model.state_dict())
        model.load_state_dict(state.optimizer_state["raw_weights"])
        optim.load_state_dict(state.optimizer_state["optimizer"])
        average.updates = int(state.optimizer_state["average_updates"])
        if distance_head is not None:
            distance_head.load_state_dict(state.optimizer_state["object_distance_head"])
        history = state.extra["history"]
        start_epoch = len(history)
        schedule_epochs = int(state.extra.get("schedule_epochs", cfg.epochs))
        best_key = tuple(state.extra["best_key"])
        print(f"resuming from {last_path} after epoch {start_epoch}")

    started = time.perf_counter()
    for epoch in range(start_epoch, schedule_epochs):
        total_steps = schedule_epochs * steps_per_epoch
        model.train()
        gen = torch.Generator().manual_seed(cfg.seed * 100_003 + epoch)
        order = epoch_order(n, sample_weights, gen)
        losses = []
        bar = tqdm(range(steps_per_epoch), desc=f"epoch {epoch + 1}/{schedule_epochs}",
                   disable=not progress, dynamic_ncols=True, mininterval=2.0)
        t_epoch = time.perf_counter()
        for b in bar:
            idx = np.sort(order[b * cfg.batch_size:(b + 1) * cfg.batch_size])
            x, labels, distance = training_batch(train_arrays, idx, gen, cfg, aug_noise, norm)
            x, labels = x.to(device, memory_format=memory_format), labels.to(device)
            aux = ((distance_head, distance.to(device), cfg.object_distance_weight)
                   if distance_head is not None else None)
            for group in optim.param_groups:
                group["lr"] = lr_at(epoch * steps_per_epoch + b, total_steps, cfg.lr)
            balance = (object_balance_weights(labels, outcome_ids, cfg.object_balance_pixels,
                                              OBJECT_BALANCE_MAX_WEIGHT)
                       if cfg.object_balance_pixels else None)
            loss = optimise_step(model, optim, x, labels, weights, autocast, scaler,
                                 cfg.lovasz_weight, balance, aux)
            average.update(model)
            losses.append(loss.item())
            bar.set_postfix(loss=f"{np.mean(losses[-20:]):.4f}")
        metrics = validate(average.module, val_arrays, val_truth, device, norm, 64, table)
        entry = {"epoch": epoch + 1, "train_loss": float(np.mean(losses)),
                 "epoch_s": round(time.perf_counter() - t_epoch, 1), **metrics}
        history.append(entry)
        if epoch == 0:
            schedule_epochs = fitted_epochs(cfg.epochs, entry["epoch_s"], cfg.max_minutes)
            if schedule_epochs < cfg.epochs:
                print(f"train: {cfg.epochs} epochs of {entry['epoch_s']:.0f} s would overrun "
                      f"the {cfg.max_minutes:g} min budget; the schedule now spans "
                      f"{schedule_epochs} epochs")
        print(f"epoch {epoch + 1}: loss {entry['train_loss']:.4f} val all-correct "
              f"{metrics['image_all_correct']:.4f} mIoU {metrics['pixel_miou']:.4f} "
              f"({entry['epoch_s']} s)")
        key = (metrics["image_all_correct"], metrics["pixel_miou"])
        extra = {"history": history, "best_key": list(max(key, best_key)),
                 "dataset": str(run_dir), "n_train": n, "precision": precision,
                 "channels_last": channels_last,
                 "schedule_epochs": schedule_epochs}
        common = dict(model_args=model_args, label_table=table, input_size=cfg.input_size,
                      normalisation=norm,
                      train_config={"train": to_dict(cfg), "dataset": manifest["config"]},
                      metrics=metrics)
        if key > best_key:
            best_key = key
            checkpoint.save(best_path, average.module, **common, extra=extra)
        training_state = {"optimizer": optim.state_dict(), "raw_weights": model.state_dict(),
                          "average_updates": average.updates}
        if distance_head is not None:
            training_state["object_distance_head"] = distance_head.state_dict()
        checkpoint.save(last_path, average.module, **common, optimizer_state=training_state,
                        extra=extra)
        save_json(out / "history.json", history)
        plot_curves(out / "training_curves.png", history, cfg.lovasz_weight,
                    cfg.object_distance_weight)
        if epoch + 1 >= schedule_epochs:  # the range above may be longer than the fit
            break
        if (time.perf_counter() - started) / 60 > cfg.max_minutes:  # slower than epoch 1
            print(f"stopping: the {cfg.max_minutes} min budget is spent; best kept")
            break
    if distance_head is not None:
        distance_head.remove()
    return best_path


def plot_curves(path: Path, history: list[dict], lovasz_weight: float = 0.0,
                object_distance_weight: float = 0.0) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    epochs = [h["epoch"] for h in history]
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.8), dpi=100)
    a.plot(epochs, [h["train_loss"] for h in history], "o-")
    a.set_xlabel("epoch")
    a.set_ylabel("train loss (weighted CE"
                 + (f" + {lovasz_weight:g} x IoU" if lovasz_weight else "")
                 + (f" + {object_distance_weight:g} x distance" if object_distance_weight
                    else "") + ")")
    a.set_yscale("log")
    b.plot(epochs, [h["image_all_correct"] for h in history], "o-", label="image all-correct")
    b.plot(epochs, [h["pixel_miou"] for h in history], "s-", label="pixel mIoU")
    b.axhline(0.868, color="grey", ls="--", lw=1, label="paper: 0.868 all-correct")
    b.set_xlabel("epoch")
    lowest = min(min(h["pixel_miou"], h["image_all_correct"]) for h in history)
    b.set_ylim(min(0.5, lowest - 0.02), 1.0)
    b.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
