"""Stacking (Section 3.5.2, Fig. 3.7): build the tallest stack of a pool of objects, placing
each where the scorer predicts it stable and putting aside those it does not."""

from __future__ import annotations

import contextlib
import math
import time
from typing import Any

import numpy as np

from physint_backends import SimulationError
from physint_cli.errors import BadInput, unknown
from physint_cli.method import Context, Unit

from ..physics import StackObject
from ..scenes import sample_cube, sample_cuboid, sample_cylinder, sample_sphere
from .common import (_AGENT_COLOURS, _artifact, _histogram, _live_objects, _move_cameras, _Recorder, _watch, ACCEPT,
                     AGENTS, Appearance, episode_units, PARK, QUICK_OTHERS, QUICK_STEPS_DIVISOR, SETTLE_SECONDS,
                     SPAWN_GAP, STACK_SCENARIOS, STACKABILITY_VIEWS, VIDEO_SIZE)
from .scorers import _choose, _on_top, make_scorer, OracleScorer, PredictorScorer, Scorer
from .search import Disc
from .stackability import stackability_ranking


# ==============================================================================================
# stacking (Section 3.5.2)
# ==============================================================================================

def stack_pool(scenario: str, n: int, rng: np.random.Generator) -> list[StackObject]:
    """A pool of ``n`` objects: cubes, cuboids, or CCS (cuboids and cylinders, exactly two spheres)."""
    if scenario == "cubes":
        objs = [sample_cube(rng) for _ in range(n)]
    elif scenario == "cuboids":
        objs = [sample_cuboid(rng) for _ in range(n)]
    elif scenario == "ccs":
        spheres = min(2, n)
        objs = [sample_sphere(rng) for _ in range(spheres)]
        objs += [sample_cuboid(rng) if rng.random() < 0.5 else sample_cylinder(rng) for _ in range(n - spheres)]
        objs = [objs[i] for i in rng.permutation(n)]
    else:
        raise unknown("stacking scenario", scenario, STACK_SCENARIOS)
    # all aligned (yaw 0): two rotated rectangles can meet in an octagon, on which MuJoCo 3.9's
    # box-box collider overflows ("returned 9 contacts ... expected at most 8")
    return [o.moved(yaw=0.0) for o in objs]


def _stack_order(pool: list[StackObject], scorer: Scorer, rng: np.random.Generator, steps: int,
                 radius: float) -> list[StackObject]:
    """Stack order and orientation by (quick) stackability: each object in its best orientation,
    most stackable first."""
    rows = stackability_ranking(pool, scorer, rng, steps, radius, others=QUICK_OTHERS)
    queue, done = [], set()
    for r in rows:
        if r["object"] not in done:
            done.add(r["object"])
            queue.append(pool[r["object"]].moved(orientation=r["orientation"]))
    return queue


def _quick_steps(cfg) -> int:
    return max(4, cfg.anneal_steps // QUICK_STEPS_DIVISOR)


def stack_episode(ctx: Context, unit: Unit) -> dict[str, Any]:
    """Work unit: one stacking episode of ``unit.params['scenario']`` by ``unit.params['agent']``.

    ``unit.seed`` fixes the pool and the appearance (the same for every agent); the agent's own
    draws (annealing, random placements) come from a generator seeded by the unit seed and the agent.
    """
    p = unit.params
    cfg = ctx.config.deploy
    agent, scenario, n = p["agent"], p["scenario"], int(p["pool"])
    t0 = time.perf_counter()
    rng = np.random.default_rng(unit.seed)
    pool = stack_pool(scenario, n, rng)
    appearance = Appearance.draw(rng, cfg.cameras, ctx.config.data.resolution, ctx.config.data.textures,
                                 timestep=ctx.config.data.timestep)
    arng = np.random.default_rng([unit.seed, AGENTS.index(agent)])
    scorer = make_scorer(ctx, agent, appearance, pool)
    try:  # random placement: in the oracle's order
        with (scorer.using_views(STACKABILITY_VIEWS) if isinstance(scorer, PredictorScorer)
              else contextlib.nullcontext()):
            queue = _stack_order(pool, scorer or OracleScorer(), arng, _quick_steps(cfg), cfg.anneal_radius)
        rec = _Recorder(_artifact(ctx, f"stack_{scenario}_{agent}") if p.get("record") else None,
                        f"stack-{scenario}-{agent}")
        out = _stack_live(ctx, queue, appearance, agent, scorer, arng, rec)
    finally:
        if scorer is not None:
            scorer.close()
    out.update(scenario=scenario, agent=agent, episode=unit.index, pool=n, seconds=time.perf_counter() - t0,
               artifacts=rec.close())
    return out


def _stack_live(ctx: Context, queue: list[StackObject], appearance: Appearance, agent: str, scorer: Scorer | None,
                rng: np.random.Generator, rec: _Recorder) -> dict[str, Any]:
    """Build the tower in one live simulation: pool objects wait far away, each is moved to its
    spawn pose, released and watched; the cameras follow the tower up."""
    cfg = ctx.config.deploy
    names = [f"obj{i}" for i in range(len(queue))]
    parked = [o.moved(x=PARK + 0.5 * i, y=PARK, z=o.height / 2) for i, o in enumerate(queue)]
    first = _on_top([], queue[0], (0.0, 0.0))
    cams = appearance.ring([first])
    video = appearance.ring([first], n=1, size=VIDEO_SIZE, factor=1.4, prefix="video", azimuth=math.pi / 6)
    sim = ctx.make_sim(appearance.scene(parked, cameras=cams + video))
    placed: list[int] = []
    trunk: list[StackObject] = []
    scores: list[float | None] = []
    put_aside, collapsed, step, error = 0, False, 0, None
    try:
        if rec.active:
            rec.text("episode", f"agent {agent}; queue: " + ", ".join(f"{o.shape} {o.orientation}" for o in queue))
            rec.frame(sim, 0.0)
        for i, obj in enumerate(queue):
            if not trunk:
                xy, score = np.zeros(2), None  # the first object goes to the scene centre
            else:
                xy, score = _choose(agent, scorer, trunk, obj, Disc(trunk[-1].xy, cfg.anneal_radius),
                                    cfg.anneal_steps, rng)
                if score is not None and score < ACCEPT:
                    put_aside += 1  # no stable position: disregarded for the rest of the episode
                    continue
            spawn = _on_top(trunk, obj, xy, gap=SPAWN_GAP)
            sim.set_pose(names[i], (spawn.x, spawn.y, spawn.z), spawn.quat)
            sim.set_velocity(names[i], (0.0, 0.0, 0.0))
            watched = [names[k] for k in placed] + [names[i]]
            objs = [queue[k] for k in placed] + [obj]
            start = [sim.get_pose(nm) for nm in watched]
            try:
                fell = _watch(sim, watched, objs, start, SETTLE_SECONDS, stop_early=not rec.active,
                              frame=(lambda t: rec.frame(sim, t)) if rec.active else None)
            except SimulationError as exc:  # the simulator broke down: the episode ends here
                error = str(exc)
                break
            scores.append(score)
            step += 1
            if fell:
                collapsed = True
                rec.step(sim, step, sim.time, [c.name for c in cams], score=score, height=len(placed))
                break
            placed.append(i)
            trunk = _live_objects(sim, [names[k] for k in placed], [queue[k] for k in placed])
            cams = appearance.ring(trunk)
            _move_cameras(sim, cams + appearance.ring(trunk, n=1, size=VIDEO_SIZE, factor=1.4, prefix="video",
                                                      azimuth=math.pi / 6))
            rec.step(sim, step, sim.time, [c.name for c in cams], score=score, height=len(placed))
    finally:
        sim.close()
    return {"height": len(placed), "collapsed": collapsed, "put_aside": put_aside, "sim_error": error,
            "order": [f"{o.shape}/{o.orientation}" for o in queue],
            "scores": [None if s is None else round(float(s), 4) for s in scores]}


def run_stacking(ctx: Context, agents: list[str], episodes: int) -> dict[str, Any]:
    cfg = ctx.config.deploy
    agents = [a for a in agents if a in ("predictor", "oracle", "random")]
    if not agents:
        raise BadInput("stacking needs an agent: predictor, oracle or random")
    units = episode_units(ctx, "stack", "scenario", STACK_SCENARIOS, agents, episodes, pool=cfg.pool)
    t0 = time.perf_counter()
    results = ctx.map(stack_episode, units, description="stacking")
    out: dict[str, Any] = {"task": "stack", "episodes": episodes, "pool": cfg.pool, "anneal_steps": cfg.anneal_steps,
                           "anneal_radius": cfg.anneal_radius, "scenarios": {}}
    artifacts: list[str] = []
    for scenario in STACK_SCENARIOS:
        top = cfg.pool - (min(2, cfg.pool) - 1 if scenario == "ccs" else 0)  # CCS: at most one sphere, on top
        per: dict[str, Any] = {"max_height": top}
        for agent in agents:
            mine = [r for r in results if r["scenario"] == scenario and r["agent"] == agent]
            heights = [r["height"] for r in mine]
            per[agent] = {"heights": heights, "histogram": _histogram(heights, cfg.pool),
                          "mean_height": float(np.mean(heights)), "collapses": sum(r["collapsed"] for r in mine),
                          "put_aside_mean": float(np.mean([r["put_aside"] for r in mine])),
                          "sim_errors": sum(r["sim_error"] is not None for r in mine),
                          "seconds_per_episode": float(np.mean([r["seconds"] for r in mine]))}
            for r in mine:
                artifacts += r["artifacts"]
        out["scenarios"][scenario] = per
    out["seconds"] = time.perf_counter() - t0
    if ctx.run is not None:
        artifacts.append(_stack_figure(ctx, out, agents))
        out["artifacts"] = artifacts
    return out


def _stack_figure(ctx: Context, out: dict[str, Any], agents: list[str]) -> str:
    """Fig. 3.7: per scenario, how often each agent built a tower of each height; dashed: the mean."""
    from physint_cli.artifacts import save_plot

    def draw(ax):
        fig = ax.figure
        ax.remove()
        axes = fig.subplots(1, len(STACK_SCENARIOS), sharey=True)
        width = 0.8 / len(agents)
        for axis, scenario in zip(axes, STACK_SCENARIOS):
            per = out["scenarios"][scenario]
            for k, agent in enumerate(agents):
                hist = per[agent]["histogram"]
                x = np.arange(len(hist)) + (k - (len(agents) - 1) / 2) * width
                axis.bar(x, hist, width, color=_AGENT_COLOURS[agent], label=agent)
                axis.axvline(per[agent]["mean_height"], color=_AGENT_COLOURS[agent], ls="--", lw=1)
            axis.set_title(scenario)
            axis.set_xlabel("tower height (objects)")
            axis.set_xticks(range(0, out["pool"] + 1, 2))
        axes[0].set_ylabel("episodes")
        axes[-1].legend(fontsize=8)

    path = _artifact(ctx, "stack_heights.png")
    save_plot(path, draw, figsize=(11, 3.2))
    return path.name
