"""Search regions (a disc, a rotated rectangle) and the simulated annealing that places an
object in them (Section 3.5.2: "we use simulated annealing to find the placement")."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np


# ==============================================================================================
# search regions and simulated annealing
# ==============================================================================================

@dataclass
class Disc:
    """Positions within ``radius`` of ``centre`` (the stacking search region)."""

    centre: np.ndarray
    radius: float

    def __post_init__(self) -> None:
        self.centre = np.asarray(self.centre, dtype=float)

    @property
    def scale(self) -> float:
        return self.radius

    def sample(self, rng: np.random.Generator) -> np.ndarray:
        r = self.radius * math.sqrt(rng.random())
        t = rng.uniform(0, 2 * math.pi)
        return self.centre + r * np.array([math.cos(t), math.sin(t)])

    def project(self, p) -> np.ndarray:
        d = np.asarray(p, dtype=float) - self.centre
        n = float(np.linalg.norm(d))
        return self.centre + (d * (self.radius / n) if n > self.radius else d)


@dataclass
class Rect:
    """Positions on a rectangle of full ``extents`` rotated by ``yaw`` (a plank's top face)."""

    centre: np.ndarray
    extents: tuple[float, float]
    yaw: float = 0.0

    def __post_init__(self) -> None:
        self.centre = np.asarray(self.centre, dtype=float)

    @property
    def scale(self) -> float:
        return 0.5 * max(self.extents)

    def _axes(self) -> np.ndarray:
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return np.array([[c, s], [-s, c]])  # rows: the rectangle's x and y axes

    def sample(self, rng: np.random.Generator) -> np.ndarray:
        local = (rng.random(2) - 0.5) * np.asarray(self.extents)
        return self.centre + local @ self._axes()

    def project(self, p) -> np.ndarray:
        axes = self._axes()
        local = axes @ (np.asarray(p, dtype=float) - self.centre)
        half = 0.5 * np.asarray(self.extents)
        return self.centre + np.clip(local, -half, half) @ axes


@dataclass
class AnnealResult:
    xy: np.ndarray  # the best position found
    score: float  # its score
    start_score: float  # the score where the search started
    evaluations: int
    accepted: int
    trace: list[float] = field(default_factory=list)  # best score so far, per evaluation


def _log_odds(p: float, eps: float = 1e-15) -> float:
    p = min(max(float(p), eps), 1.0 - eps)
    return math.log(p / (1.0 - p))


def anneal(score: Callable[[np.ndarray], float], domain, steps: int, rng: np.random.Generator, start=None,
           t_start: float = 1.0, t_end: float = 0.05, step_start: float = 0.5, step_end: float = 0.1) -> AnnealResult:
    """Simulated annealing of ``score(xy)`` over ``domain`` (a :class:`Disc` or :class:`Rect`), keeping the best.

    ``steps`` evaluations in all, the first at ``start`` (default: the domain's centre). Each step
    proposes a Gaussian move of ``domain.scale`` times a step size shrinking linearly from
    ``step_start`` to ``step_end`` (clipped into the domain) and accepts it with the Metropolis
    rule ``min(1, exp((E' - E) / T))`` on the log-odds ``E = log(s / (1 - s))`` of the stability
    ``s`` in [0, 1], the temperature falling geometrically from ``t_start`` to ``t_end``. (On the
    stability itself a logistic output is flat far from the decision boundary, where a fixed
    temperature turns the search into a random walk; the log-odds keep its slope: for the
    Lemma-1 oracle they are the margin over ``ORACLE_SCALE``.)
    """
    steps = max(1, int(steps))
    x = domain.project(domain.centre if start is None else start)
    s = float(score(x))
    best_x, best_s, start_s = x.copy(), s, s
    trace, accepted, e = [s], 0, _log_odds(s)
    for k in range(1, steps):
        frac = (k - 1) / max(1, steps - 2)
        temp = t_start * (t_end / t_start) ** frac
        sigma = domain.scale * (step_start + (step_end - step_start) * frac)
        y = domain.project(x + rng.normal(0.0, sigma, 2))
        sy = float(score(y))
        ey = _log_odds(sy)
        if ey >= e or rng.random() < math.exp((ey - e) / temp):  # Metropolis acceptance
            x, s, e = y, sy, ey
            accepted += 1
        if sy > best_s:
            best_x, best_s = y.copy(), sy
        trace.append(best_s)
    return AnnealResult(best_x, best_s, start_s, steps, accepted, trace)
