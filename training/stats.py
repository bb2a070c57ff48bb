"""How sure a figure is: intervals for an all-correct rate, and paired tests between models.

Why: the decisions in docs/experiments.md turn on a few images (a model 3 images worse on
the 300-image independent set, one point of the robustness suite 0.01 apart on 100 scenes).
At 0.97 on 300 images the 95 % interval is about ±0.02, so such gaps are often noise. Two
tools make that visible where the figures are made:

- ``wilson_interval``: the Wilson score interval of a rate (k right of n), which stays inside
  [0, 1] and behaves near 1.0, where our rates live (the normal approximation does not);
- ``paired_comparison``: two models on the *same* images. Only the images on which they
  disagree carry information (McNemar); under "equally good" each of those is a fair coin,
  so the two-sided exact binomial p-value says how surprising the split is;
- ``holm_adjusted``: the same p-values made fit for a rule over many of them at once. A
  robustness comparison tests 20-odd points; between two equally good models, were the 22
  tests independent and exactly at their level, at least one would come out worse at
  p < 0.05 about 4 times in 10 (1 - 0.975^22), so a rule that asks "no point worse beyond
  chance" should name the adjusted values.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

Z_95 = 1.959963984540054  # two-sided 95 % normal quantile


def wilson_interval(right: int, n: int, z: float = Z_95) -> tuple[float, float]:
    """(low, high) Wilson score interval of the rate right / n (95 % by default)."""
    if n <= 0 or not 0 <= right <= n:
        raise ValueError(f"need 0 <= right <= n and n > 0, got right={right} n={n}")
    p = right / n
    z2 = z * z
    centre = (p + z2 / (2 * n)) / (1 + z2 / n)
    half = z * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n)) / (1 + z2 / n)
    # At 0 or n right the bound is exactly 0 or 1; say so rather than 0.9999999999999998.
    low = 0.0 if right == 0 else max(0.0, centre - half)
    high = 1.0 if right == n else min(1.0, centre + half)
    return low, high


def exact_mcnemar_p(only_a_wrong: int, only_b_wrong: int) -> float:
    """Two-sided exact McNemar p-value: the chance of a split at least this uneven among the
    discordant images if each went either way with probability 1/2."""
    if only_a_wrong < 0 or only_b_wrong < 0:
        raise ValueError("counts must be >= 0")
    n = only_a_wrong + only_b_wrong
    if n == 0:
        return 1.0
    k = min(only_a_wrong, only_b_wrong)
    tail = sum(math.comb(n, i) for i in range(k + 1)) / 2.0 ** n
    return min(1.0, 2.0 * tail)


def holm_adjusted(p_values: Iterable[float]) -> list[float]:
    """Holm's step-down adjustment, in the input's order: the k-th smallest of m p-values is
    multiplied by m - k + 1 (k from 1), each kept at least as large as the one before it and
    at most 1. Rejecting where the adjusted value is under alpha keeps the chance of any false
    "beyond chance" in the family under alpha, without assuming the tests independent."""
    p = list(p_values)
    if any(not 0.0 <= v <= 1.0 for v in p):
        raise ValueError(f"p-values must lie in [0, 1], got {p}")
    m, adjusted, running = len(p), [0.0] * len(p), 0.0
    for rank, index in enumerate(sorted(range(m), key=p.__getitem__)):
        running = max(running, min(1.0, (m - rank) * p[index]))
        adjusted[index] = running
    return adjusted


def rate_with_interval(right: int, n: int) -> dict:
    """{"all_correct": right / n, "ci95": its Wilson interval}: how every rate is reported."""
    return {"all_correct": right / n, "ci95": wilson_interval(right, n)}


def paired_comparison(mistakes_a: Iterable[int], mistakes_b: Iterable[int], n: int) -> dict:
    """Two models' mistakes (image ids) on the same ``n`` images -> who got which wrong, each
    rate with its interval, and the exact McNemar p-value of the difference."""
    a, b = set(mistakes_a), set(mistakes_b)
    if n <= 0 or len(a) > n or len(b) > n:
        raise ValueError(f"{len(a)} and {len(b)} mistakes cannot come from {n} images")
    only_a, only_b = sorted(a - b), sorted(b - a)
    return {
        "images": n,
        "a": {**rate_with_interval(n - len(a), n), "mistakes": len(a)},
        "b": {**rate_with_interval(n - len(b), n), "mistakes": len(b)},
        "both_wrong": len(a & b),
        "only_a_wrong": only_a,
        "only_b_wrong": only_b,
        "p_value": exact_mcnemar_p(len(only_a), len(only_b)),
    }
