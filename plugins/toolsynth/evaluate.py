"""Tool imagination against its baselines on the test tasks (thesis Section 4.4.3, Table 4.1).

The test instances are the first ``eval.instances`` infeasible records of each type in
``eval.types`` in the test split (in the dataset's order, so every method and every run meets the
same ones). Each is imagined from its tool's first stored view by:

* **task-driven**: descent of Eq. 4.5 with the model trained on L_recon + L_task (stage 2);
* **task-unaware**: the same descent with the model whose tool latent space is stage 1's;
* **random walk**: in the task-driven model's latent space, same step, cap and stop rule;
* **no-op**: the start latent decoded unchanged (a control: reconstruction error alone should
  almost never turn an infeasible tool into a feasible one).

With ``eval.latent_box`` (the default) every process, the random walk's too, is kept inside the
box round its model's training latents (``checkpoint.training_box``): beyond it the decoder
extrapolates to tools no record resembles, and the classifier was never asked about them.

A run succeeds when the decoded tool passes the geometric check on its task (``feasibility.check``
on the mesh seen from above); with ``eval.sim_check`` each success is also placed in the simulator
(its outline as convex parts) and confirmed by contacts. Reported beside the thesis: success per
type and in total with 95 % intervals, classifier accuracy and reconstruction IoU on the whole test
split, the share of runs that reached the threshold and their mean steps.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from physint_cli.errors import BadInput
from physint_cli.method import Context
from physint_cli.stats import ci95

from . import scenes as S
from .checkpoint import FIELDS, load_models, load_split, training_box, view_cameras
from .imagine import imagine, judge
from .model import task_input, tool_input
from .softras import hard_iou
from .tasks import TYPES, Task, parse_types, tasks_of
from .tools import Tool, footprint_parts

# Table 4.1: success rates (%) of task-driven / task-unaware imagination and the random walk
THESIS = {"task-driven": {"A": 96.4, "B": 78.8, "C": 76.4, "D": 81.2, "E": 86.4, "total": 83.8},
          "task-unaware": {"A": 55.6, "B": 42.0, "C": 56.8, "D": 75.2, "E": 88.4, "total": 63.6},
          "random walk": {"A": 3.6, "B": 5.6, "C": 23.6, "D": 2.4, "E": 13.6, "total": 9.8}}
RUNS = (("task-driven", "driven", "descent"), ("task-unaware", "unaware", "descent"),
        ("random walk", "driven", "random"), ("no-op", "driven", "none"))


def pick_instances(records: dict[str, np.ndarray], types: tuple[str, ...], per_type: int) -> np.ndarray:
    """The first ``per_type`` infeasible records of each type, in the split's order."""
    chosen = []
    for t in types:
        found = np.flatnonzero((records["type"] == TYPES.index(t)) & (records["label"] == 0))[:per_type]
        chosen.append(found)
    return np.concatenate(chosen) if chosen else np.zeros(0, int)


def latents(model, records: dict[str, np.ndarray], index, batch: int = 256) -> tuple[torch.Tensor, torch.Tensor]:
    """z_G of the tasks and z_T of the tools' first stored view, for records ``index``."""
    zg, zt = [], []
    with torch.no_grad():
        for s in range(0, len(index), batch):
            i = index[s:s + batch]
            zg.append(model.encode_task(task_input(records["task"][i])))
            zt.append(model.encode_tool(tool_input(records["tool_rgb"][i, 0], records["tool_sil"][i, 0])))
    return torch.cat(zg), torch.cat(zt)


def test_scores(model, records: dict[str, np.ndarray], cams, sigma: float, batch: int = 128) -> dict[str, Any]:
    """On the whole test split: the classifier's accuracy (all and per type), the mean
    reconstruction IoU in the second stored view and from above (the decoded tool's outline
    against the true tool's, what the geometric check sees), and how often the geometric check gives the tool
    decoded from the first view the record's own label (per type): the share of tools whose
    reconstruction keeps what they can reach, which bounds what imagination can decode."""
    pred, iou, z_all = [], [], []
    with torch.no_grad():
        for s in range(0, len(records["label"]), batch):
            sl = slice(s, s + batch)
            z = model.encode_tool(tool_input(records["tool_rgb"][sl, 0], records["tool_sil"][sl, 0]))
            z_all.append(z)
            pred.append(model.classify(model.encode_task(task_input(records["task"][sl])), z).argmax(1).numpy())
            sil = model.silhouettes(model.decode(z), cams, torch.as_tensor(records["views"][sl, 1]).long(), sigma)
            iou.append(hard_iou(sil, torch.as_tensor(records["tool_sil"][sl, 1] > 0).float()).numpy())
    right = np.concatenate(pred) == records["label"]
    verdicts, shapes = judge(model, torch.cat(z_all), tasks_of(records, range(len(right))))
    kept = np.array([v.feasible for v in verdicts]) == records["label"].astype(bool)
    footprint_iou = np.array([footprint_overlap(shape, Tool.from_array(a).footprint())
                              for shape, a in zip(shapes, records["tool"])])

    def per_type(hit: np.ndarray) -> dict[str, float]:
        return {t: float(hit[records["type"] == TYPES.index(t)].mean())
                for t in TYPES if (records["type"] == TYPES.index(t)).any()}

    feasible = records["label"] == 1
    return {"accuracy": float(right.mean()), "accuracy_per_type": per_type(right),
            "iou": float(np.concatenate(iou).mean()), "footprint_iou": float(footprint_iou.mean()),
            "reconstruction_keeps_label": float(kept.mean()), "reconstruction_keeps_label_per_type": per_type(kept),
            "reconstruction_keeps_feasible": float(kept[feasible].mean()) if feasible.any() else float("nan")}


def footprint_overlap(decoded, true) -> float:
    """IoU from above of a decoded tool's outline (None: no area) and the true tool's, both in the tool frame."""
    if decoded is None:
        return 0.0
    union = decoded.union(true).area
    return float(decoded.intersection(true).area / union) if union > 0 else 0.0


def between_tools(z: torch.Tensor) -> float:
    """The mean distance between two of the latents ``z`` (two different tools): the unit of ``latent_moved``."""
    return float(torch.pdist(z).mean()) if len(z) > 1 else float("nan")


def moved(z_start: torch.Tensor, z_end: torch.Tensor, unit: float) -> float:
    """How far imagination took the latents: the mean of |z_end - z_start| in units of ``unit``
    (:func:`between_tools` of the start latents). Far below 1, the classifier was talked into
    success by a move that hardly changes the tool."""
    return float((z_end - z_start).norm(dim=1).mean()) / unit


def confirm_in_sim(ctx: Context, tasks: list[Task], verdicts, shapes) -> tuple[int, int]:
    """How many of the geometric successes the simulator confirms by contacts (of how many)."""
    confirmed = checked = 0
    sim = None
    try:
        for task, verdict, shape in zip(tasks, verdicts, shapes):
            if not verdict.feasible:
                continue
            scene = S.check_scene(task, footprint_parts(shape))
            if sim is None:
                sim = ctx.make_sim(scene)
            else:
                sim.reset(scene)
            checked += 1
            confirmed += int(S.sim_verdict(sim, task, shape, verdict))
    finally:
        if sim is not None:
            sim.close()
    return confirmed, checked


def rates(success: np.ndarray, types: np.ndarray, letters: tuple[str, ...]) -> dict[str, Any]:
    out = {}
    for t in letters:
        s = success[types == TYPES.index(t)]
        out[t] = {"rate": float(s.mean()) if len(s) else float("nan"), "ci95": ci95(int(s.sum()), len(s)),
                  "n": int(len(s))}
    out["total"] = {"rate": float(success.mean()) if len(success) else float("nan"),
                    "ci95": ci95(int(success.sum()), len(success)), "n": int(len(success))}
    return out


def table(results: dict[str, Any], letters: tuple[str, ...]) -> str:
    """Table 4.1 as markdown: ours (95 % interval) | thesis, per type and in total."""
    cols = [*letters, "total"]
    lines = ["| method | " + " | ".join(cols) + " |", "|---|" + "---|" * len(cols)]
    for name, r in results.items():
        cells = []
        for c in cols:
            ours = r["success"][c]
            thesis = THESIS.get(name, {}).get(c)
            cells.append(f"{100 * ours['rate']:.1f} ± {100 * ours['ci95']:.1f}"
                         + (f" ({thesis:.1f})" if thesis is not None else ""))
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n\nours: success % ± 95 % interval (thesis Table 4.1 in brackets)\n"


def evaluate(ctx: Context) -> dict[str, Any]:
    import json

    cfg = ctx.config.eval
    letters = parse_types(cfg.types, "eval.types")
    driven, unaware, meta = load_models(ctx.trained().path, ctx.device)
    models = {"driven": driven, "unaware": unaware}
    root = Path(ctx.data or meta["dataset"])
    records = load_split(root, "test", FIELDS)
    index = pick_instances(records, letters, cfg.instances)
    if not len(index):
        raise BadInput(f"dataset {root} has no infeasible test records of types {''.join(letters)} to imagine from")
    tasks, types = tasks_of(records, index), records["type"][index]
    ctx.log(f"imagining tools for {len(index)} infeasible test tasks ({', '.join(f'{t}: {int((types == TYPES.index(t)).sum())}' for t in letters)}), "
            f"step {cfg.step}, at most {cfg.max_steps} steps, threshold {cfg.threshold}")
    results: dict[str, Any] = {}
    rows = []
    start = {which: latents(model, records, index) for which, model in models.items()}  # each model's, once
    box = {which: training_box(meta, which, model, root) if cfg.latent_box else None for which, model in models.items()}
    unit = {which: between_tools(z_start) for which, (_, z_start) in start.items()}
    for name, which, method in RUNS:
        model = models[which]
        z_task, z_start = start[which]
        run = imagine(model, z_task, z_start, method, cfg.step, cfg.max_steps, cfg.threshold, seed=ctx.seed,
                      optimizer=cfg.optimizer, box=box[which])
        verdicts, shapes = judge(model, run.z, tasks)
        success = np.array([v.feasible for v in verdicts])
        r = {"success": rates(success, types, letters), "reached_threshold": float(run.reached.mean()),
             "latent_moved": moved(z_start, run.z, unit[which]),
             "mean_steps": float(run.steps[run.reached].mean()) if run.reached.any() else None,  # of runs that reached
             "p_start": float(run.p_start.mean()), "p_end": float(run.p_end.mean())}
        if cfg.sim_check:
            confirmed, checked = confirm_in_sim(ctx, tasks, verdicts, shapes)
            r["sim_confirmed"] = {"confirmed": confirmed, "of": checked,
                                  "rate": confirmed / checked if checked else None}
        results[name] = r
        ctx.log(f"{name}: {100 * r['success']['total']['rate']:.1f} % success, "
                f"{100 * r['reached_threshold']:.0f} % reached p >= {cfg.threshold}")
        rows += [{"method": name, "record": int(i), "type": TYPES[int(t)], "steps": int(s), "p_start": float(p0),
                  "p_end": float(p1), "feasible": bool(v.feasible)}
                 for i, t, s, p0, p1, v in zip(index, types, run.steps, run.p_start, run.p_end, verdicts)]
    cams = view_cameras(int(meta["views"]), int(meta["kwargs"]["image_size"]), float(meta.get("elevation", S.ELEVATION)))
    scores = {title: test_scores(models[which], records, cams, float(meta.get("sigma", 1.0)))
              for title, which in (("task-driven", "driven"), ("task-unaware", "unaware"))}
    out = ctx.output()
    out.artifact("table_4_1.md").write_text(table(results, letters))
    out.artifact("instances.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    return {"instances": int(len(index)), "types": "".join(letters), "step": cfg.step, "max_steps": cfg.max_steps,
            "threshold": cfg.threshold, "latent_box": cfg.latent_box, "imagination": results, "test": scores, "thesis": THESIS,
            "dataset": str(root), "trained_on": meta["backend"]}
