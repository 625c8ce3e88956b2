"""Statistics the methods report beside the thesis's tables."""

from __future__ import annotations

import math


def ci95(successes: int, n: int) -> float:
    """Half-width of the 95 % normal-approximation binomial confidence interval."""
    if n == 0:
        return float("nan")
    p = successes / n
    return 1.96 * math.sqrt(p * (1 - p) / n)
