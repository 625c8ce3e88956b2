"""Stackability (Section 3.5.1, Figs. 3.5 and 3.6): how well each object serves as a base,
scored by a predictor or the oracle over the others placed on it, ranked and plotted."""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any

import numpy as np

from physint_cli.errors import BadInput
from physint_cli.method import Context, Unit, unit_seed

from ..physics import stack_up, StackObject
from ..scenes import sample_cube, sample_cuboid, sample_cylinder, sample_sphere
from .common import _artifact, _CLASS_COLOURS, _STRIP_SIZE, Appearance, BASE_JITTER, STACKABILITY_VIEWS
from .scorers import _Stage, make_scorer, PredictorScorer, Scorer
from .search import anneal, Disc


# ==============================================================================================
# stackability (Section 3.5.1)
# ==============================================================================================

def orientations(obj: StackObject) -> list[StackObject]:
    """The object in each of its distinct discrete orientations (a cube has one, like a sphere)."""
    from ..physics import ORIENTATIONS

    out, seen = [], set()
    for o in ORIENTATIONS[obj.shape]:
        cand = obj.moved(orientation=o)
        key = (cand.curved_top, round(cand.height, 6), tuple(sorted(round(e, 6) for e in cand.extents)))
        if key not in seen:
            seen.add(key)
            out.append(cand)
    return out


def projected_area(obj: StackObject) -> float:
    """Area (m^2) of the object's projection onto the x-y plane in its orientation."""
    if obj.shape == "sphere" or (obj.shape == "cylinder" and obj.orientation == "upright"):
        return math.pi * obj.size[0] ** 2
    ex, ey = obj.extents
    return ex * ey


def object_class(obj: StackObject) -> str:
    """Fig. 3.6's classes: cube, cuboid largest / middle / smallest face (up), cylinder upright / lying, sphere."""
    if obj.shape == "sphere":
        return "sphere"
    if obj.shape == "cylinder":
        return f"cylinder {obj.orientation}"
    if max(obj.size) - min(obj.size) < 1e-9:
        return "cube"
    faces = sorted({round(projected_area(o), 12) for o in orientations(obj)}, reverse=True)
    rank = faces.index(round(projected_area(obj), 12))
    if len(faces) == 2:  # two equal edges: a largest and a smallest face only
        return "cuboid largest face" if rank == 0 else "cuboid smallest face"
    return ("cuboid largest face", "cuboid middle face", "cuboid smallest face")[rank]


CLASS_ORDER = ("cuboid largest face", "cuboid middle face", "cuboid smallest face", "cube", "cylinder upright",
               "cylinder lying", "sphere")
_EXPECTED = ("cuboid largest face", "cylinder upright", "cylinder lying", "sphere")  # the thesis's finding

_POOL_CYCLE = ("cuboid", "cylinder", "sphere", "cube", "cuboid", "cylinder", "cuboid", "cube", "cylinder", "cuboid",
               "sphere", "cuboid")


def stackability_pool(n: int, rng: np.random.Generator) -> list[StackObject]:
    """``n`` objects of every class (cuboids of varied aspect ratios, cubes, cylinders, spheres), random yaw."""
    make = {"cuboid": sample_cuboid, "cube": sample_cube, "cylinder": sample_cylinder, "sphere": sample_sphere}
    out = []
    for i in range(n):
        obj = make[_POOL_CYCLE[i % len(_POOL_CYCLE)]](rng)
        if obj.shape == "cylinder" and rng.random() < 0.5:
            obj = obj.moved(orientation="lying")
        out.append(obj.moved(yaw=float(rng.uniform(0, math.pi))))
    return out


def base_stackability(base: StackObject, others: list[StackObject], scorer: Scorer, rng: np.random.Generator,
                      steps: int, radius: float, jitter: float = BASE_JITTER,
                      every_orientation: bool = True) -> tuple[float, list[float]]:
    """Section 3.5.1: the mean over ``others`` of the best score of each on top of ``base``.

    For each other object the base is perturbed at random (position within ``jitter``, yaw), the
    object is tried in each of its orientations (or only as given, ``every_orientation=False``),
    each placed by :func:`anneal` within ``radius`` of the base's top centre; its best score over
    orientations and positions is recorded.
    """
    per_other = []
    for other in others:
        b = stack_up([base.moved(x=float(rng.uniform(-jitter, jitter)), y=float(rng.uniform(-jitter, jitter)),
                                 yaw=float(rng.uniform(0, math.pi)))])
        best = 0.0
        for o in (orientations(other) if every_orientation else [other]):
            res = anneal(scorer.placement(b, o), Disc(b[0].xy, radius), steps, rng)
            best = max(best, res.score)
        per_other.append(best)
    return (float(np.mean(per_other)) if per_other else 0.0), per_other


def stackability_ranking(objects: list[StackObject], scorer: Scorer, rng: np.random.Generator, steps: int,
                         radius: float, others: int | None = None) -> list[dict[str, Any]]:
    """Every (object, orientation) as a base, scored by :func:`base_stackability`, best first.

    With ``others`` = k (stacking's quick ranking) each base is tried with k random (other object,
    orientation) pairs instead of every other object in every orientation. Ties keep the larger
    projected area first.
    """
    rows = []
    for i, obj in enumerate(objects):
        rest = [o for j, o in enumerate(objects) if j != i]
        for oriented in orientations(obj):
            if others is None:
                score, per_other = base_stackability(oriented, rest, scorer, rng, steps, radius)
            else:
                pairs = [o for r in rest for o in orientations(r)]
                pick = [pairs[k] for k in sorted(rng.choice(len(pairs), min(others, len(pairs)), replace=False))]
                score, per_other = base_stackability(oriented, pick, scorer, rng, steps, radius,
                                                     every_orientation=False)
            rows.append(_ranking_row(i, oriented, score, per_other))
    rows.sort(key=lambda r: (-r["score"], -r["projected_area"]))
    return rows


def _ranking_row(i: int, obj: StackObject, score: float, per_other: list[float]) -> dict[str, Any]:
    return {"object": i, "shape": obj.shape, "size": [round(s, 5) for s in obj.size], "orientation": obj.orientation,
            "class": object_class(obj), "score": float(score), "projected_area": projected_area(obj),
            "per_other": [round(float(s), 4) for s in per_other]}


def stackability_unit(ctx: Context, unit: Unit) -> dict[str, Any]:
    """Work unit: the stackability of one (object, orientation) base of the task's pool for one agent."""
    p = unit.params
    cfg = ctx.config.deploy
    pool_rng = np.random.default_rng(p["pool_seed"])
    pool = stackability_pool(p["pool"], pool_rng)
    appearance = Appearance.draw(pool_rng, cfg.cameras, ctx.config.data.resolution, ctx.config.data.textures)
    base = pool[p["object"]].moved(orientation=p["orientation"])
    others = [o for j, o in enumerate(pool) if j != p["object"]]
    rng = np.random.default_rng(unit.seed)  # the same perturbations and SA draws for every agent
    t0 = time.perf_counter()
    scorer = make_scorer(ctx, p["agent"], appearance, pool)
    if isinstance(scorer, PredictorScorer):
        scorer.views = STACKABILITY_VIEWS
    try:
        score, per_other = base_stackability(base, others, scorer, rng, cfg.anneal_steps, cfg.anneal_radius)
    finally:
        scorer.close()
    return {**_ranking_row(p["object"], base, score, per_other), "agent": p["agent"],
            "seconds": time.perf_counter() - t0}


def _class_means(rows: list[dict[str, Any]]) -> dict[str, float]:
    out = {}
    for cls in CLASS_ORDER:
        scores = [r["score"] for r in rows if r["class"] == cls]
        if scores:
            out[cls] = float(np.mean(scores))
    return out


def _area_correlation(rows: list[dict[str, Any]]) -> dict[str, float]:
    """Fig. 3.6: per class, Pearson's r between stackability and projected area (classes of >= 3 sizes)."""
    out = {}
    for cls in CLASS_ORDER:
        pts = np.array([(r["projected_area"], r["score"]) for r in rows if r["class"] == cls])
        if len(pts) >= 3 and pts[:, 0].std() > 0 and pts[:, 1].std() > 0:
            out[cls] = float(np.corrcoef(pts[:, 0], pts[:, 1])[0, 1])
    return out


def _expected_order(means: dict[str, float]) -> bool | None:
    present = [means[c] for c in _EXPECTED if c in means]
    if len(present) < 2:
        return None
    return all(a > b for a, b in zip(present, present[1:]))


def run_stackability(ctx: Context, agents: list[str]) -> dict[str, Any]:
    cfg = ctx.config.deploy
    agents = [a for a in agents if a in ("predictor", "oracle")]
    if not agents:
        raise BadInput("stackability needs a scoring agent: predictor or oracle")
    pool_seed = unit_seed(ctx.seed, "stackability-pool")
    pool = stackability_pool(cfg.stackability_pool, np.random.default_rng(pool_seed))
    units = []
    for agent in agents:
        for i, obj in enumerate(pool):
            for oriented in orientations(obj):
                units.append(Unit(f"stackability-{agent}", len(units), 1,
                                  unit_seed(ctx.seed, "stackability", i, oriented.orientation),
                                  {"agent": agent, "object": i, "orientation": oriented.orientation,
                                   "pool": cfg.stackability_pool, "pool_seed": pool_seed}))
    t0 = time.perf_counter()
    rows = ctx.map(stackability_unit, units, description="stackability")
    result: dict[str, Any] = {"task": "stackability", "objects": len(pool), "bases": len(units) // len(agents),
                              "anneal_steps": cfg.anneal_steps, "agents": {}}
    for agent in agents:
        mine = sorted(({k: v for k, v in r.items() if k != "agent"} for r in rows if r["agent"] == agent),
                      key=lambda r: (-r["score"], -r["projected_area"]))
        means = _class_means(mine)
        best = {}
        for r in mine:
            best.setdefault(r["object"], r)
        result["agents"][agent] = {
            "ranking": mine, "class_means": means, "expected_order_holds": _expected_order(means),
            "area_correlation": _area_correlation(mine),
            "object_order": [{"object": o, "orientation": r["orientation"], "score": r["score"]} for o, r in best.items()],
            "seconds": float(sum(r.pop("seconds") for r in mine)),
        }
    result["seconds"] = time.perf_counter() - t0
    if ctx.run is not None:
        main = agents[0]
        result["artifacts"] = _stackability_figures(ctx, pool, result["agents"], main, pool_seed)
    return result


def _portrait(stage: _Stage, obj: StackObject) -> np.ndarray:
    """One object alone on the ground, seen from the front."""
    stage.show(stack_up([obj.moved(x=0.0, y=0.0)]), factor=1.25)
    return stage.render()[0]


def _stackability_figures(ctx: Context, pool: list[StackObject], agents_out: dict[str, Any], main: str,
                          pool_seed: int) -> list[str]:
    from physint_cli.artifacts import save_plot

    rows = agents_out[main]["ranking"]

    def scatter(ax):  # Fig. 3.6
        for cls in CLASS_ORDER:
            pts = [(r["projected_area"] * 1e4, r["score"]) for r in rows if r["class"] == cls]
            if pts:
                x, y = zip(*pts)
                ax.scatter(x, y, s=22, color=_CLASS_COLOURS[cls], label=cls)
        ax.set_xlabel("projected surface area (cm$^2$)")
        ax.set_ylabel(f"stackability ({main})")
        ax.set_ylim(-0.03, 1.03)
        ax.legend(fontsize=7, loc="lower right")

    files = []
    path = _artifact(ctx, "stackability_area.png")
    save_plot(path, scatter, figsize=(6, 4))
    files.append(path.name)

    appearance = Appearance.draw(np.random.default_rng(pool_seed), randomise=False,
                                 textures=ctx.config.data.textures)
    appearance = dataclasses.replace(appearance, elevation=25.0, azimuth=-math.pi / 2 + 0.4)
    order = agents_out[main]["object_order"]
    stage = _Stage(appearance, ctx.make_sim, pool, cameras=1, size=_STRIP_SIZE, prefix="portrait")
    try:
        top = [_portrait(stage, o) for o in pool]
        bottom = [_portrait(stage, pool[r["object"]].moved(orientation=r["orientation"])) for r in order]
    finally:
        stage.close()
    strip = np.concatenate([np.concatenate(top, axis=1), np.concatenate(bottom, axis=1)], axis=0)

    def draw_strip(ax):  # Fig. 3.5
        ax.imshow(strip)
        for k, r in enumerate(order):
            ax.text((k + 0.5) * _STRIP_SIZE, 2 * _STRIP_SIZE + 12, f"{r['score']:.2f}", ha="center", va="top",
                    fontsize=7)
        ax.set_xticks([])
        ax.set_yticks([_STRIP_SIZE / 2, 1.5 * _STRIP_SIZE], ["pool", "by stackability"], fontsize=8)
        ax.set_title(f"objects sorted by stackability ({main}), best orientation", fontsize=9)

    path = _artifact(ctx, "stackability_strip.png")
    save_plot(path, draw_strip, figsize=(max(6, 0.9 * len(pool)), 2.6))
    files.append(path.name)
    return files
