"""The per-image outcome IoU loss (training/losses.py) on hand-made logits and labels."""

from __future__ import annotations

import pytest
import torch

from task_outcome_ros.labels import DEFAULT_TABLE, IGNORE
from training.losses import outcome_lovasz_loss

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
