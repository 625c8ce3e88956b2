"""Counterbalancing (Section 3.5.3, Fig. 3.9): place a counterweight on an unstable T-shaped
stack so that it stands."""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from physint_backends import SimulationError
from physint_backends.spec import Camera
from physint_cli.errors import unknown
from physint_cli.method import Context, Unit

from ..physics import analyse, stack_up, StackObject
from ..scenes import CUBOID_EDGE, CUBOID_MAX_ASPECT
from .common import (_AGENT_COLOURS, _artifact, _Recorder, _watch, AGENTS, Appearance, BALANCE_SECONDS,
                     COUNTERWEIGHTS, episode_units, HOLD_SECONDS, SPAWN_GAP, VIDEO_SIZE)
from .scorers import _choose, _on_top, lemma1_margin, make_scorer
from .search import Rect


# ==============================================================================================
# counterbalancing (Section 3.5.3)
# ==============================================================================================

def counterweight(kind: str, rng: np.random.Generator) -> StackObject:
    """A counterweight of ~0.1-0.2 kg: cube, cuboid (largest face down), upright cylinder, or sphere."""
    if kind == "cube":
        a = rng.uniform(0.045, 0.06)
        obj = StackObject("box", (a, a, a))
    elif kind == "cuboid":
        obj = StackObject("box", (rng.uniform(0.06, 0.075), rng.uniform(0.045, 0.055), rng.uniform(0.035, 0.045)))
    elif kind == "cylinder":
        obj = StackObject("cylinder", (rng.uniform(0.026, 0.032), rng.uniform(0.045, 0.06)))
    elif kind == "sphere":
        obj = StackObject("sphere", (rng.uniform(0.029, 0.034),))
    else:
        raise unknown("counterweight", kind, COUNTERWEIGHTS)
    return obj


def unstable_t(rng: np.random.Generator, weight: StackObject, min_band: float = 0.015, safe: float = 0.005,
               max_tries: int = 200) -> list[StackObject]:
    """An unstable "T": a base block and a plank whose centre of mass overhangs the base's edge by
    0.5-2 cm along the plank (a VCOM), such that ``weight`` placed on the plank's axis can balance it
    with a Lemma-1 margin of at least ``safe`` along at least ``min_band`` metres of the plank.

    Both are shapes of the training distribution (CCS cuboids: edges up to 11 cm, aspect ratio at
    most 3.5), so the predictor is asked about objects it has seen: a first version with a
    20-26 cm plank, longer than anything in the dataset, left the predictor below random placement.
    """
    longest = CUBOID_EDGE[1]
    for _ in range(max_tries):
        a = rng.uniform(0.04, 0.06)
        yaw = rng.uniform(0, 2 * math.pi)
        base = StackObject("box", (a, a, rng.uniform(0.05, 0.09)), yaw=yaw)
        length = rng.uniform(0.10, longest)
        thickness = rng.uniform(length / CUBOID_MAX_ASPECT, 0.035)
        plank_size = (length, rng.uniform(max(thickness, 0.035), 0.05), thickness)
        u = np.array([math.cos(yaw), math.sin(yaw)])
        c = (a / 2 + rng.uniform(0.005, 0.02)) * u
        plank = StackObject("box", plank_size, x=float(c[0]), y=float(c[1]), yaw=yaw)
        t = stack_up([base, plank])
        weight = weight.moved(yaw=yaw)  # aligned with the plank (see stack_pool)
        if analyse(t).violation != "VCOM":
            continue
        s = np.linspace(-plank_size[0] / 2, plank_size[0] / 2, 41)
        ok = [lemma1_margin(t + [weight.moved(x=float(c[0] + k * u[0]), y=float(c[1] + k * u[1]))]) >= safe for k in s]
        if np.sum(ok) * (s[1] - s[0]) >= min_band:
            return t
    raise RuntimeError("no balanceable T found")


def balance_episode(ctx: Context, unit: Unit) -> dict[str, Any]:
    """Work unit: one counterbalancing episode (``params['weight']``, ``params['agent']``).

    The T and the counterweight come from ``unit.seed`` (the same for every agent). The T is frozen,
    the counterweight released ``SPAWN_GAP`` above the plank where the agent chooses, allowed to
    settle for ``HOLD_SECONDS``, then the T is unfrozen: success when no object moves more than 1 cm
    (the counterweight: from where it was put) or tips more than 10 degrees in ``BALANCE_SECONDS``.
    Agent ``none`` is the control: the T alone, unfrozen.
    """
    p = unit.params
    cfg = ctx.config.deploy
    agent, kind = p["agent"], p["weight"]
    t0 = time.perf_counter()
    rng = np.random.default_rng(unit.seed)
    weight = counterweight(kind, rng)
    t = unstable_t(rng, weight)
    weight = weight.moved(yaw=t[1].yaw)
    appearance = Appearance.draw(rng, cfg.cameras, ctx.config.data.resolution, ctx.config.data.textures,
                                 timestep=ctx.config.data.timestep)
    arng = np.random.default_rng([unit.seed, AGENTS.index(agent)])
    plank = t[1]
    score = None
    scorer = make_scorer(ctx, agent, appearance, t + [weight])
    try:
        if agent == "none":
            objects = list(t)
        else:
            xy, score = _choose(agent, scorer, t, weight, Rect(plank.xy, plank.extents, plank.yaw), cfg.anneal_steps,
                                arng)
            objects = t + [_on_top(t, weight, xy, gap=SPAWN_GAP)]
    finally:
        if scorer is not None:
            scorer.close()
    rec = _Recorder(_artifact(ctx, f"balance_{kind}_{agent}") if p.get("record") else None, f"balance-{kind}-{agent}")
    cams = appearance.ring(objects)
    video = appearance.ring(objects, n=1, size=VIDEO_SIZE, factor=1.3, prefix="video", azimuth=math.pi / 6)
    names = [f"obj{i}" for i in range(len(objects))]
    error = None
    with ctx.make_sim(appearance.scene(objects, cameras=cams + video)) as sim:
        try:
            fell = _balance_live(sim, agent, names, objects, cams, rec, score)
        except SimulationError as exc:  # the simulator broke down: a failed episode
            fell, error = True, str(exc)
    margin = lemma1_margin(objects)
    return {"weight": kind, "agent": agent, "episode": unit.index, "success": not fell, "sim_error": error,
            "score": None if score is None else float(score),
            "lemma1_margin": margin if math.isfinite(margin) else None,
            "seconds": time.perf_counter() - t0, "artifacts": rec.close()}


def _balance_live(sim, agent: str, names: list[str], objects: list[StackObject], cams: list[Camera], rec: _Recorder,
                  score: float | None) -> bool:
    """Freeze the T, let the counterweight settle on it, unfreeze, watch: True when something fell."""
    frame = (lambda tt: rec.frame(sim, tt)) if rec.active else None
    if agent != "none":
        sim.freeze("obj0")
        sim.freeze("obj1")
        spawn = sim.get_pose("obj2")
        rec.step(sim, 0, 0.0, [c.name for c in cams], score=score)
        _watch(sim, [], [], [], HOLD_SECONDS, stop_early=False, frame=frame)
        sim.unfreeze("obj0")
        sim.unfreeze("obj1")
        start = [sim.get_pose("obj0"), sim.get_pose("obj1"), spawn]
    else:
        start = [sim.get_pose(nm) for nm in names]
    fell = _watch(sim, names, objects, start, BALANCE_SECONDS, stop_early=not rec.active, frame=frame)
    rec.step(sim, 1, sim.time, [c.name for c in cams], success=float(not fell))
    return fell


def run_balance(ctx: Context, agents: list[str], episodes: int) -> dict[str, Any]:
    cfg = ctx.config.deploy
    agents = [a for a in agents if a in AGENTS]
    if "none" not in agents:
        agents = agents + ["none"]
    units = episode_units(ctx, "balance", "weight", COUNTERWEIGHTS, agents, episodes)
    t0 = time.perf_counter()
    results = ctx.map(balance_episode, units, description="counterbalancing")
    out: dict[str, Any] = {"task": "balance", "episodes": episodes, "anneal_steps": cfg.anneal_steps,
                           "counterweights": {}}
    artifacts: list[str] = []
    for kind in COUNTERWEIGHTS:
        per = {}
        for agent in agents:
            mine = [r for r in results if r["weight"] == kind and r["agent"] == agent]
            per[agent] = {"success_rate": float(np.mean([r["success"] for r in mine])),
                          "successes": int(sum(r["success"] for r in mine)), "episodes": len(mine),
                          "sim_errors": sum(r["sim_error"] is not None for r in mine),
                          "seconds_per_episode": float(np.mean([r["seconds"] for r in mine]))}
            for r in mine:
                artifacts += r["artifacts"]
        out["counterweights"][kind] = per
    out["success_rate"] = {a: float(np.mean([out["counterweights"][k][a]["success_rate"] for k in COUNTERWEIGHTS]))
                           for a in agents}
    out["seconds"] = time.perf_counter() - t0
    if ctx.run is not None:
        artifacts.append(_balance_figure(ctx, out, agents))
        out["artifacts"] = artifacts
    return out


def _balance_figure(ctx: Context, out: dict[str, Any], agents: list[str]) -> str:
    """Fig. 3.9 (right): success rate per counterweight type and agent."""
    from physint_cli.artifacts import save_plot

    def draw(ax):
        width = 0.8 / len(agents)
        for k, agent in enumerate(agents):
            rates = [out["counterweights"][w][agent]["success_rate"] for w in COUNTERWEIGHTS]
            x = np.arange(len(COUNTERWEIGHTS)) + (k - (len(agents) - 1) / 2) * width
            ax.bar(x, rates, width, color=_AGENT_COLOURS[agent], label=agent)
        ax.set_xticks(range(len(COUNTERWEIGHTS)), COUNTERWEIGHTS)
        ax.set_ylim(0, 1.05)
        ax.set_ylabel(f"success rate ({out['episodes']} episodes)")
        ax.set_title("counterbalancing an unstable T")
        ax.legend(fontsize=8)

    path = _artifact(ctx, "balance_success.png")
    save_plot(path, draw, figsize=(6, 3.5))
    return path.name
