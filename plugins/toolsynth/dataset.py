"""The dataset of controlled reaching scenarios (thesis Appendix 4.A, Table 4.A.1).

Each record is one task and one tool: the top-down task image I_G, the tool's RGB image I_T and
silhouette I_S in two of the ``data.views`` ring views (i, j), and the label rho: whether the tool
can reach the target (``feasibility.check``). Record ``n`` of a split has scenario type
``types[n mod len(types)]`` and is feasible on every other round of types, so each split is
balanced 50/50 per type; a record draws tasks of its type and tools (even odds stick or hook) until
the check gives the label it needs. The training split holds ``data.train_types`` (A-D: E is held
out), validation and test ``data.eval_types``. The task, the tool's dimensions and colour are kept
with the images, so evaluation can judge imagined tools against the same task and deployment
can rebuild it. A share ``data.sim_check`` of the records is confirmed in the simulator by contacts
(``scenes.sim_verdict``); the manifest reports the agreement rate.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from physint_cli.errors import BadInput
from physint_cli.method import Context, Unit, split_units

from . import feasibility
from . import scenes as S
from .tasks import TYPES, Task, parse_types, sample_task
from .tools import Tool, sample_tool

TOOLS_PER_TASK = 100


def split_types(cfg, split: str) -> tuple[str, ...]:
    return parse_types(cfg.train_types if split == "train" else cfg.eval_types)


def plan_units(ctx: Context) -> list[Unit]:
    cfg = ctx.config.data
    return split_units({"train": cfg.train, "val": cfg.val, "test": cfg.test}, cfg.per_shard, ctx.seed)


def draw_record(kind: str, feasible: bool, rng: np.random.Generator, max_attempts: int
                ) -> tuple[Task, Tool, feasibility.Verdict, int]:
    """A task of type ``kind`` and a tool whose verdict on it is ``feasible``, and the tools tried."""
    tried = 0
    for _ in range(max_attempts):
        task = sample_task(kind, rng)
        for _ in range(TOOLS_PER_TASK):
            tool = sample_tool(rng)
            tried += 1
            verdict = feasibility.check(tool.footprint(), task)
            if verdict.feasible == feasible:
                return task, tool, verdict, tried
    raise RuntimeError(f"no {'feasible' if feasible else 'infeasible'} tool found for {max_attempts} type-{kind} "
                       f"tasks of {TOOLS_PER_TASK} tools each; raise data.max_attempts")


def generate(ctx: Context, unit: Unit) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    cfg = ctx.config.data
    types = split_types(cfg, unit.split)
    fields: dict[str, list] = {}
    stats = {"records": 0, "tools_tried": 0, "sim_checked": 0, "sim_agreed": 0}
    sim = check_sim = None
    try:
        for k in range(unit.count):
            index = unit.params["start"] + k
            kind, feasible = types[index % len(types)], (index // len(types)) % 2 == 1
            rng = np.random.default_rng([unit.seed, k])
            task, tool, verdict, tried = draw_record(kind, feasible, rng, cfg.max_attempts)
            rgba = (*rng.uniform(0.15, 0.85, 3), 1.0)
            views = rng.choice(cfg.views, size=2, replace=False)
            scene = S.record_scene(task, tool.convex_parts(), rgba, cfg.task_size, cfg.views, cfg.tool_size,
                                   cfg.elevation)
            if sim is None:
                sim = ctx.make_sim(scene)
            else:
                sim.reset(scene)
            record = S.render_record(sim, views, tool_index=len(scene.bodies) - 1)
            checked = rng.random() < cfg.sim_check
            agrees = True
            if checked:
                check_scene = S.check_scene(task, tool.convex_parts())
                if check_sim is None:
                    check_sim = ctx.make_sim(check_scene)
                else:
                    check_sim.reset(check_scene)
                agrees = S.sim_verdict(check_sim, task, tool.footprint(), verdict) == verdict.feasible
            record.update(task.to_arrays(), label=np.uint8(verdict.feasible), tool=tool.to_array(),
                          rgba=np.asarray(rgba, np.float32), views=views.astype(np.int16),
                          sim_checked=np.uint8(checked), sim_agrees=np.uint8(agrees))
            for key, value in record.items():
                fields.setdefault(key, []).append(value)
            stats["records"] += 1
            stats["tools_tried"] += tried
            stats["sim_checked"] += int(checked)
            stats["sim_agreed"] += int(checked and agrees)
            stats[f"type_{kind}"] = stats.get(f"type_{kind}", 0) + 1
    finally:
        for s in (sim, check_sim):
            if s is not None:
                s.close()
    return {k: np.stack(v) for k, v in fields.items()}, stats


def summarize(stats: list[dict[str, Any]]) -> dict[str, Any]:
    from physint_cli.datasets import add_up

    total = add_up(stats)
    checked = total.get("sim_checked", 0)
    total["sim_agreement"] = total.get("sim_agreed", 0) / checked if checked else None
    total["records_per_cpu_second"] = total.get("records", 0) / max(total.get("seconds", 0.0), 1e-9)
    return total


def check_dataset(root, split: str) -> None:
    """Exit 2 unless ``root`` is a toolsynth dataset with ``split``."""
    from physint_cli.datasets import read_manifest

    manifest = read_manifest(root, "toolsynth")
    if not manifest.get("splits", {}).get(split):
        raise BadInput(f"dataset {root} has no {split!r} records")


__all__ = ["TYPES", "plan_units", "generate", "summarize"]
