"""Deploying the stability predictor: stackability, stacking, counterbalancing (thesis Section 3.5).

``physint deploy stability --task T`` with T one of

``stackability`` (Section 3.5.1, Figs. 3.5 and 3.6)
    Every object of a seeded pool (cuboids of varied aspect ratios, cubes, cylinders, spheres) is
    put on the ground as the base of a stack in each of its discrete orientations (a cuboid has
    three, one per pair of faces; a cylinder two, upright and lying; a sphere one). Every other
    object, in each of its orientations, is placed on top at the position simulated annealing finds
    most stable. The base's *stackability* is the mean, over the others, of their best score. The
    base position and yaw are perturbed at random for every other object (robustness). The
    predictor scores a combination from ``STACKABILITY_VIEWS`` (2) opposite cameras (the thesis
    assesses "an image" of it), which keeps this O(n^2 x orientations^2 x steps) task affordable.

``stack`` (Section 3.5.2, Figs. 3.7 and 3.8)
    Scenarios ``cubes``, ``cuboids`` and ``ccs`` (a CCS pool holds exactly two spheres). Each
    episode randomises texture, colours, lights and cameras, draws a pool of ``deploy.pool`` (12)
    objects, orders them and picks their orientation by stackability (a quick estimate: each base
    tried with ``QUICK_OTHERS`` random (object, orientation) pairs, ``anneal_steps / 6`` annealing
    steps, ``STACKABILITY_VIEWS`` cameras), puts the first one at the
    scene centre, and spawns each next one ``SPAWN_GAP`` above the trunk at the (x, y) where
    simulated annealing finds the highest predicted stability within ``deploy.anneal_radius`` of
    the trunk's top centre. An object whose best score is below 0.5 is put aside for good. After
    each release the physics runs ``SETTLE_SECONDS``; the episode ends when the tower collapses
    (an object moved more than 1 cm or tipped more than 10 degrees) or the pool is empty. The
    height is the number of objects standing when it ends. The cameras move up with the tower.

``balance`` (Section 3.5.3, Fig. 3.9)
    An unstable "T" (a base block and a long plank whose centre of mass overhangs the base: a
    VCOM) is frozen; one counterweight (cube, cuboid, cylinder or sphere) is placed on the plank
    where simulated annealing finds the highest predicted stability; everything is unfrozen and
    simulated for ``BALANCE_SECONDS``: success when nothing falls.

Agents, compared on the same pools, Ts, appearances and seeds:

``predictor``  the trained network (``ctx.source_run``): stability = 1 - mean P(unstable) over
               the ``deploy.cameras`` views (Eq. 3.2's logistic output), :class:`PredictorScorer`.
``oracle``     Lemma 1 (:func:`physics.analyse`): the smallest signed margin of Eq. 3.1 over all
               interfaces, squashed to (0, 1) by a logistic of width ``ORACLE_SCALE`` (0.5 at margin
               0), :class:`OracleScorer`. Same search as the predictor.
``random``     placements uniform in the search region, never put aside (stack: in the oracle's
               stackability order and orientations, so only placement differs).
``none``       (balance only) the T without a counterweight: the control, should always fall.

``deploy.agents`` (comma-separated) picks the agents; by default: ``predictor`` when there is a
trained run, then ``oracle`` and ``random``.

Episodes are work units run through ``ctx.map`` (``--workers`` / ``--ray`` parallelise them).
Artifacts: ``stackability_area.png`` (Fig. 3.6), ``stackability_strip.png`` (Fig. 3.5),
``stack_heights.png`` (Fig. 3.7), ``stack_<scenario>_<agent>.mp4`` and ``.rrd`` (one episode),
``balance_success.png`` (Fig. 3.9), ``balance_<weight>_<agent>.mp4`` and ``.rrd``.

The package, one module per task (each reads like its section):

    common.py        constants, an episode's appearance, fall checks, the recorder, work units
    search.py        search regions and simulated annealing
    scorers.py       the predictor, the Lemma-1 oracle and their search (make_scorer)
    stackability.py  Section 3.5.1, Figs. 3.5 and 3.6
    stacking.py      Section 3.5.2, Fig. 3.7
    balance.py       Section 3.5.3, Fig. 3.9
"""

from __future__ import annotations

from typing import Any

from physint_cli.errors import unknown
from physint_cli.method import Context

from .balance import balance_episode, counterweight, run_balance, unstable_t
from .common import AGENTS, Appearance, COUNTERWEIGHTS, STACK_SCENARIOS, TASKS
from .stackability import (base_stackability, object_class, orientations, projected_area, run_stackability,
                           stackability_pool, stackability_ranking, stackability_unit)
from .scorers import lemma1_margin, make_scorer, oracle_score, OracleScorer, PredictorScorer, Scorer
from .search import AnnealResult, anneal, Disc, Rect
from .stacking import run_stacking, stack_episode, stack_pool

__all__ = [
    "TASKS", "AGENTS", "STACK_SCENARIOS", "COUNTERWEIGHTS", "Appearance", "Disc", "Rect", "AnnealResult", "anneal",
    "Scorer", "OracleScorer", "PredictorScorer", "lemma1_margin", "oracle_score", "orientations", "projected_area",
    "object_class", "stackability_pool", "base_stackability", "stackability_ranking", "stack_pool", "stack_episode",
    "unstable_t", "counterweight", "balance_episode", "stackability_unit", "make_scorer", "run_stackability",
    "run_stacking", "run_balance", "deploy",
]


def _agents(ctx: Context) -> list[str]:
    chosen = ctx.config.deploy.agents
    if not chosen:
        return (["predictor"] if ctx.source_run is not None else []) + ["oracle", "random"]
    if isinstance(chosen, str):
        chosen = [a.strip() for a in chosen.split(",") if a.strip()]
    for a in chosen:
        if a not in AGENTS:
            raise unknown("deploy agent", a, AGENTS)
    return list(dict.fromkeys(chosen))


def deploy(ctx: Context) -> dict[str, Any]:
    """Run the deployment task ``ctx.task`` (--task; default ``stackability``); JSON-ready metrics."""
    task = ctx.task or "stackability"
    if task not in TASKS:
        raise unknown("deploy task for stability", task, TASKS)
    episodes = ctx.config.deploy.episodes  # --episodes N arrives as deploy.episodes=N; >= 1 by the config
    agents = _agents(ctx)
    ctx.log(f"stability deploy: task {task}, agents {', '.join(agents)}")
    if task == "stackability":
        return run_stackability(ctx, agents)
    if task == "stack":
        return run_stacking(ctx, agents, episodes)
    return run_balance(ctx, agents, episodes)
