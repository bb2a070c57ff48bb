"""The per-image outcome IoU loss (training/losses.py) on hand-made logits and labels."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from task_outcome_ros.labels import DEFAULT_TABLE, IGNORE
from training.losses import object_balance_weights, outcome_lovasz_loss
from training.train import weighted_cross_entropy

pytestmark = pytest.mark.unit

SUCCESS, STUCK = DEFAULT_TABLE.outcome_ids["success"], DEFAULT_TABLE.outcome_ids["stuck_on_rim"]


def _confident(labels: torch.Tensor) -> torch.Tensor:
    """Logits that put (almost) all probability on ``labels`` (IGNORE -> class 0)."""
    safe = torch.where(labels == IGNORE, 0, labels)
    one_hot = torch.nn.functional.one_hot(safe, DEFAULT_TABLE.num_classes)
    return 30.0 * one_hot.permute(0, 3, 1, 2).float()


def test_a_right_answer_costs_nothing_and_a_spurious_fragment_costs_a_whole_class():
    labels = torch.zeros((1, 30, 40), dtype=torch.long)
    labels[0, 5:15, 5:15] = SUCCESS
    logits = _confident(labels)
    assert float(outcome_lovasz_loss(logits, labels)) < 1e-6
    # Four stuck_on_rim pixels on the success box: tiny for cross-entropy, but stuck_on_rim is
    # absent from the image, so its IoU is 0: a loss of 1 for that class, 1/3 over outcomes.
    fringe = labels.clone()
    fringe[0, 5:7, 5:7] = STUCK
    loss = float(outcome_lovasz_loss(_confident(fringe), labels))
    assert abs(loss - (1 + 4 / 100) / 3) < 1e-3        # + success lost 4 of its 100 pixels


def test_small_and_large_objects_count_alike():
    """Missing half of an object costs the same whatever its size (cross-entropy would charge
    the large one 25x more)."""
    def half_missed(side: int) -> float:
        labels = torch.zeros((1, 60, 80), dtype=torch.long)
        labels[0, :side, :side] = SUCCESS
        predicted = labels.clone()
        predicted[0, :side // 2, :side] = 0
        return float(outcome_lovasz_loss(_confident(predicted), labels))

    assert abs(half_missed(10) - half_missed(50)) < 1e-3


def test_ignored_pixels_take_no_part_and_truncation_keeps_the_largest_errors():
    torch.manual_seed(0)
    labels = torch.randint(0, DEFAULT_TABLE.num_classes, (2, 24, 32))
    labels[:, :4] = IGNORE
    logits = torch.randn(2, DEFAULT_TABLE.num_classes, 24, 32, requires_grad=True)
    loss = outcome_lovasz_loss(logits, labels, top_k=10_000)
    loss.backward()
    loss = loss.detach()
    assert logits.grad[:, :, :4].abs().max() == 0          # no gradient where there is no depth
    other = logits.detach().clone()
    other[:, :, :4] = torch.randn(2, DEFAULT_TABLE.num_classes, 4, 32)
    assert torch.allclose(outcome_lovasz_loss(other, labels, top_k=10_000), loss)
    # Keeping only the largest errors changes the value a little, not the nature.
    truncated = float(outcome_lovasz_loss(logits.detach(), labels, top_k=300))
    assert 0 < truncated <= float(loss) + 1e-6 and truncated > 0.9 * float(loss)


def _two_objects() -> torch.Tensor:
    """One image: a 20 x 20 fell_outside object, a 2 x 2 fell_outside sliver, a 10 x 10
    stuck_on_rim object, and a row of pixels without depth."""
    labels = torch.zeros(1, 40, 60, dtype=torch.long)
    fell = DEFAULT_TABLE.outcome_ids["fell_outside"]
    stuck = DEFAULT_TABLE.outcome_ids["stuck_on_rim"]
    labels[0, 5:25, 5:25] = fell
    labels[0, 30:32, 50:52] = fell
    labels[0, 5:15, 40:50] = stuck
    labels[0, 39] = IGNORE
    return labels


def test_object_balance_weighs_small_objects_up_to_the_reference_and_the_cap():
    labels = _two_objects()
    ids = sorted(DEFAULT_TABLE.outcome_ids.values())
    w = object_balance_weights(labels, ids, reference_pixels=200, max_weight=16.0)
    assert w.shape == labels.shape and w.dtype == torch.float32
    assert torch.all(w[0, 5:25, 5:25] == 1.0)             # 400 px: larger than the reference
    assert torch.all(w[0, 5:15, 40:50] == 2.0)            # 100 px: 200 / 100
    assert torch.all(w[0, 30:32, 50:52] == 16.0)          # 4 px: 50, capped at 16
    assert torch.all(w[0, 39] == 1.0) and w[0, 0, 0] == 1.0  # ignored and background
    # Each outcome's components are counted apart: the sliver does not share the box's area.
    w_big = object_balance_weights(labels, ids, reference_pixels=4, max_weight=16.0)
    assert torch.all(w_big == 1.0)


def test_pixel_weighted_cross_entropy_is_the_class_weighted_mean_when_weights_are_one():
    gen = torch.Generator().manual_seed(3)
    labels = _two_objects()
    logits = torch.randn(1, DEFAULT_TABLE.num_classes, 40, 60, generator=gen)
    class_w = torch.tensor([0.5, 0.8, 1.2, 1.5, 1.0])
    plain = F.cross_entropy(logits, labels, weight=class_w, ignore_index=IGNORE)
    ones = weighted_cross_entropy(logits, labels, class_w, torch.ones(labels.shape))
    assert torch.allclose(plain, ones, atol=1e-6)
    # Weighing the sliver up moves the loss towards the sliver's own loss.
    boosted = torch.ones(labels.shape)
    boosted[0, 30:32, 50:52] = 50.0
    sliver = F.cross_entropy(logits[..., 30:32, 50:52], labels[:, 30:32, 50:52])
    assert abs(weighted_cross_entropy(logits, labels, class_w, boosted) - sliver) < \
        abs(plain - sliver)
