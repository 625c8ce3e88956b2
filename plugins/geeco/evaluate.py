"""Closed-loop evaluation of a GEECO controller (thesis Section 6.4, Tables 6.4.1, 6.4.2, 6.C.1).

Episodes start from the test split's saved start states (the run's own scene) or from seeded
start states (the transfer scenes of Table 6.4.2: ``--scene clutter|prisma|nutoncone|ballincup``),
with their target images: the demonstrations' last frames when the backend and resolution are the
dataset's, otherwise the expert's last frame on this backend (an episode whose expert fails
there has no target and is left out, and counted). Each runs for ``eval.steps`` control steps;
REACH, PICK and PUSH / PLACE are Bernoulli outcomes reported with their 95 % binomial
(normal-approximation, as the thesis's) confidence intervals. The control rate counts the
network, the simulation and the rendering (the thesis: about 20 Hz on a GPU). With
``eval.side_by_side`` > 1 a worker steps that many episodes in lockstep (``control.run_episodes``),
faster on a CPU; the control rate is then their steps per second together.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from physint_cli.errors import BadInput
from physint_cli.method import Context, Unit, unit_seed
from physint_cli.stats import ci95

from . import scenes as S
from .checkpoint import load_controller, with_optional

NAMES = {"push": {"reach": "REACH", "success": "PUSH"},
         "pickplace": {"reach": "REACH", "pick": "PICK", "success": "PLACE"}}


def plan_episodes(ctx: Context, meta: dict[str, Any], count: int) -> list[dict[str, Any]]:
    """Episode specs: start state, task, and where the target image comes from."""
    skill = meta["skill"]
    if ctx.scene in ("nutoncone", "ballincup") and skill != "pickplace":
        raise BadInput(f"scene {ctx.scene} is a pick-and-place transfer task; this controller was trained to {skill}")
    if ctx.scene == meta["scene"]:
        from physint_cli.datasets import ShardedDataset

        if ctx.data is None:
            raise BadInput("this run's dataset is not known: pass --data DATASET (its test split holds the start states)")
        test = ShardedDataset(ctx.data, "test", with_optional(ctx.data, ["layout", "task", "seed"]), method="geeco")
        n = min(count, len(test))
        stored = ctx.backend == meta["backend"]
        records = [test[i] for i in range(n)]
        return [{"index": i, "layout": r["layout"].tolist(), "task": [int(v) for v in r["task"]], "seed": int(r["seed"]),
                 "backdrop": int(r.get("backdrop", -1)), "stored_target": stored} for i, r in enumerate(records)]
    if S.OBJECTS.get(ctx.scene) is None:
        raise BadInput(f"unknown scene {ctx.scene!r}")
    tasks = S.tasks(ctx.scene)
    specs = []
    for i in range(count):
        rng = np.random.default_rng(unit_seed(ctx.seed, "eval", ctx.scene, i))
        ep = S.sample_episode(ctx.scene, skill, tasks[i % len(tasks)], rng)
        specs.append({"index": i, "layout": ep.layout.tolist(), "task": list(ep.task), "seed": ep.seed,
                      "stored_target": False})
    return specs


def episode_of(spec: dict[str, Any], scene: str, skill: str) -> S.Episode:
    return S.Episode.rebuild(scene, skill, spec["layout"], spec["task"], spec["seed"], spec.get("backdrop", -1))


def eval_unit(ctx: Context, unit: Unit) -> list[dict[str, Any]]:
    from physint_cli.training import torch_threads

    with torch_threads(1):  # the same episodes whatever --workers is (and fastest for one frame at a time)
        return _eval_episodes(ctx, unit)


def _eval_episodes(ctx: Context, unit: Unit) -> list[dict[str, Any]]:
    from .control import Policy, expert_target, run_episodes, sims_for

    model, meta = load_controller(ctx.trained().path, ctx.device)
    cfg = ctx.config.eval
    resolution, group = model.image_size, cfg.side_by_side
    policies = [Policy(model, ctx.device) for _ in range(group)]
    test = None
    sims: list = []
    out = []
    specs = unit.params["episodes"]
    try:
        for first in range(0, len(specs), group):
            ready = []  # (spec, episode, target image) of the episodes that run together
            for spec in specs[first:first + group]:
                ep = episode_of(spec, ctx.scene, meta["skill"])
                target = None
                if model.conditioned:
                    if spec["stored_target"]:
                        if test is None:
                            from physint_cli.datasets import ShardedDataset

                            test = ShardedDataset(ctx.data, "test", ["rgb"], method="geeco")
                        target = test[spec["index"]]["rgb"][-1]
                    else:
                        sim = sims_for(sims, ctx.make_sim, [ep], resolution)[0]
                        target = expert_target(sim, ep, resolution, meta.get("horizon", 100))
                        if target is None:
                            out.append({"index": spec["index"], "no_target": True})
                            continue
                ready.append((spec, ep, target))
            if not ready:
                continue
            episodes = [ep for _, ep, _ in ready]
            running = sims_for(sims, ctx.make_sim, episodes, resolution)
            results = run_episodes(running, episodes, policies[:len(ready)], [t for _, _, t in ready], cfg.steps,
                                   resolution, cfg.positions == "true")
            out += [{"index": spec["index"], "task": ep.goal_text(), **result}
                    for (spec, ep, _), result in zip(ready, results, strict=True)]
    finally:
        for sim in sims:
            sim.close()
    return sorted(out, key=lambda r: r["index"])


def summarize(results: list[dict[str, Any]], skill: str) -> dict[str, Any]:
    ran = [r for r in results if not r.get("no_target")]
    n = len(ran)
    rates: dict[str, Any] = {}
    for key, label in NAMES[skill].items():
        k = sum(bool(r[key]) for r in ran)
        rates[label] = {"rate": k / n if n else float("nan"), "ci95": ci95(k, n), "successes": k}
    steps = sum(r["steps"] for r in ran)
    seconds = sum(r["seconds"] for r in ran)
    per_task: dict[str, dict[str, float]] = {}
    for r in ran:
        per_task.setdefault(r["task"], []).append(r["success"])  # type: ignore[arg-type]
    return {"episodes": n, "rates": rates, "diverged": sum(bool(r["diverged"]) for r in ran),
            "object_to_target_m": {when: float(np.median([r[f"{when}_distance"] for r in ran])) if n else float("nan")
                                   for when in ("start", "final")},  # medians
            "no_target": len(results) - n, "control_hz": steps / seconds if seconds else float("nan"),
            "success_by_task": {t: float(np.mean(v)) for t, v in sorted(per_task.items())}}  # type: ignore[arg-type]


def evaluate(ctx: Context) -> dict[str, Any]:
    _, meta = load_controller(ctx.trained().path)
    cfg = ctx.config.eval  # --episodes N arrives as eval.episodes=N
    if cfg.positions == "true" and meta["kwargs"].get("command", "network") != "positions":
        raise BadInput("eval.positions=true feeds true positions to a command head: this controller was not "
                       "trained with train.command=positions")
    specs = plan_episodes(ctx, meta, cfg.episodes)
    units = [Unit("test", i, len(chunk), ctx.seed, {"episodes": chunk})
             for i, chunk in enumerate(specs[j:j + cfg.per_unit] for j in range(0, len(specs), cfg.per_unit))]
    ctx.log(f"evaluating {meta['model']} ({meta['skill']}, trained on {meta['scene']} / {meta['backend']}) on "
            f"{len(specs)} {ctx.scene} episodes on {ctx.backend}, {cfg.steps} steps each"
            + (f", {cfg.side_by_side} side by side (control_hz: their steps per second together)"
               if cfg.side_by_side > 1 else ""))
    results = [r for part in ctx.map(eval_unit, units, description="episodes") for r in part]
    summary = summarize(results, meta["skill"])
    _save_table(ctx, results)
    return {"model": meta["model"], "skill": meta["skill"], "trained_on": {"scene": meta["scene"],
            "backend": meta["backend"]}, "scene": ctx.scene, "backend": ctx.backend, "steps": cfg.steps,
            "positions": cfg.positions, "side_by_side": cfg.side_by_side, **summary}


def _save_table(ctx: Context, results: list[dict[str, Any]]) -> None:
    import json

    path = ctx.output().artifact("episodes.jsonl")
    path.write_text("".join(json.dumps(r) + "\n" for r in results))
