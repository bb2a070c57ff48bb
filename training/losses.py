"""Per-image outcome IoU loss (Lovász-softmax), added to the pixel cross-entropy.

Why: the metric that matters is image-level (is each outcome present?), but cross-entropy
weighs pixels. A 300-pixel fringe of a failure outcome painted on a success object costs
cross-entropy little, because it is a few hundred of the batch's 600,000 pixels, yet it makes
the presence rule report an outcome that is not there. The Lovász-softmax loss (Berman,
Rannen Triki &
Blaschko, CVPR 2018) is a convex surrogate of 1 - IoU; taken per image and per outcome class,
every image's outcome maps count alike, whatever their size:

- for an outcome present in the image, it is the surrogate of 1 - IoU of that outcome;
- for an absent outcome, IoU is 0 as soon as one pixel carries it, and the loss reduces to the
  largest probability of that outcome anywhere in the image.

Only the outcome classes are scored (background and the fixture are large and easy:
cross-entropy handles them), and only each row's ``top_k`` largest errors are sorted. The
Lovász gradient at a sorted position depends only on the positions before it, so truncation
drops just the smallest errors' terms. On the 2-core EPYC (batch 32) a full sort of all 19,200
working pixels made a training step about 23 % slower; the top 2,048 cost 6 %
(bench/train_step.py).
"""

from __future__ import annotations

import cv2
import numpy as np
import torch

from task_outcome_ros.labels import FIRST_OUTCOME_ID, IGNORE


def outcome_lovasz_loss(logits: torch.Tensor, labels: torch.Tensor, top_k: int = 2048
                        ) -> torch.Tensor:
    """Mean over images and outcome classes of the Lovász-softmax surrogate of 1 - IoU.

    logits (N, C, H, W), labels (N, H, W) long with ``IGNORE`` for pixels without depth (they
    take no part); the outcome classes are ids FIRST_OUTCOME_ID .. C - 1 (any task's table).
    Returns a scalar.
    """
    classes = list(range(FIRST_OUTCOME_ID, logits.shape[1]))
    prob = logits.float().softmax(1)[:, classes].flatten(2)              # N, K, P
    flat = labels.flatten(1)
    keep = (flat != IGNORE)[:, None]
    truth = torch.stack([flat == c for c in classes], 1).float()        # N, K, P
    # Ignored pixels get error -1, so they sort last and carry no gradient.
    errors = torch.where(keep, (truth - prob).abs(), torch.full_like(prob, -1.0))
    errors, order = errors.topk(min(top_k, errors.shape[-1]), dim=-1)
    truth_sorted = truth.gather(-1, order)
    area = truth.sum(-1, keepdim=True)
    # Jaccard loss after including the first i sorted pixels in the prediction; its
    # increments are the Lovász extension's weights.
    jaccard = 1.0 - (area - truth_sorted.cumsum(-1)) / (area + (1.0 - truth_sorted).cumsum(-1))
    weights = torch.cat([jaccard[..., :1], jaccard[..., 1:] - jaccard[..., :-1]], dim=-1)
    return (errors.clamp_min(0.0) * weights).sum(-1).mean()


# The largest weight a small object's pixels get: a component of a working pixels counts like
# at most 16 a pixels, so a stray pixel or two of label noise cannot count like a whole object.
OBJECT_BALANCE_MAX_WEIGHT = 16.0


def object_balance_weights(labels: torch.Tensor, outcome_ids: list[int], reference_pixels: int,
                           max_weight: float) -> torch.Tensor:
    """Per-pixel cross-entropy weights that make every object count, not every pixel.

    Why: the image metric asks whether each outcome is present, so a fallen object with 80
    pixels in view matters as much as one with 8,000; pixel cross-entropy charges missing it
    1 %. Tote model 0.9.0 predicted *no* pixel on 36 of its 37 missed fallen objects (68-1,044
    px at 640 x 480), and missed them as often on training images (recall 0.931) as on
    validation: the loss never asked for them. Here each 8-connected component of an outcome
    class smaller than ``reference_pixels`` (working-size pixels) weighs as much as one of
    ``reference_pixels``: its pixels get ``reference_pixels / area``, at most ``max_weight``.
    Touching objects of one outcome form one component; that is the unit the presence rule
    sees too. labels (N, H, W) long; returns (N, H, W) float32, 1 elsewhere."""
    weights = np.ones(labels.shape, np.float32)
    lab = labels.cpu().numpy()
    for i in range(lab.shape[0]):
        for outcome in outcome_ids:
            mask = lab[i] == outcome
            if not mask.any():
                continue
            _, components, stats, _ = cv2.connectedComponentsWithStats(
                mask.astype(np.uint8), connectivity=8)
            area = stats[:, cv2.CC_STAT_AREA].astype(np.float32)
            boost = np.clip(reference_pixels / np.maximum(area, 1.0), 1.0, max_weight)
            weights[i][mask] = boost[components[mask]]
    return torch.from_numpy(weights).to(labels.device)


class ObjectDistanceHead(torch.nn.Module):
    """A training-only readout of each pixel's distance inside its own object
    (``overlaps.object_distance``, ``TrainConfig.object_distance_weight``), from the very
    features the network's class head reads: a 1x1 convolution, so the features themselves
    must carry where one object ends and the next begins.

    It listens to ``network.head``'s input through a forward pre-hook, so the network and
    its checkpoint stay as they are (the runtime never sees this head). Build it after any
    copy of the network (the weight average), or the copy carries the hook too."""

    def __init__(self, network: torch.nn.Module) -> None:
        super().__init__()
        self.readout = torch.nn.Conv2d(network.head.in_channels, 1, 1)
        # A folded network without a full-size head reads its features on the half-size grid
        # and upsamples its logits; so does this readout.
        self.upsample = 1 if network.full_size_head else network.space_to_depth
        self._features: torch.Tensor | None = None
        self._hook = network.head.register_forward_pre_hook(self._keep)

    def _keep(self, _module, args) -> None:
        self._features = args[0]

    def remove(self) -> None:
        """Detach from the network: its forwards no longer keep their features here."""
        self._hook.remove()
        self._features = None

    def forward(self, size: tuple[int, int]) -> torch.Tensor:
        """(N, h, w) logits of the last network forward's features, at ``size`` (h, w)."""
        if self._features is None:
            raise RuntimeError("ObjectDistanceHead: run the network forward first")
        h, w = size
        out = self.readout(self._features)
        self._features = None  # one readout per forward: a stale tensor is never reused
        if self.upsample > 1:
            out = torch.nn.functional.interpolate(out, scale_factor=float(self.upsample),
                                                  mode="bilinear", align_corners=False)
        return out[:, 0, :h, :w]


def object_distance_loss(logits: torch.Tensor, target_px: torch.Tensor, labels: torch.Tensor,
                         clip_px: int) -> torch.Tensor:
    """Mean absolute error of sigmoid(logits) against ``target_px / clip_px`` over the pixels
    labelled with an outcome (what the target describes; elsewhere the head may say anything).
    logits (N, h, w), target_px (N, h, w) distances in pixels, labels (N, h, w) long."""
    on_objects = (labels >= FIRST_OUTCOME_ID) & (labels != IGNORE)
    error = (logits.float().sigmoid() - target_px / clip_px).abs()
    return (error * on_objects).sum() / on_objects.sum().clamp_min(1)
