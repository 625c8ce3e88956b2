"""Training the tool imagination networks with the thesis's curriculum (Section 4.4.2, Eq. 4.2-4.4).

Every record holds the tool in two of the ring views: one, i, is encoded (z_T = psi(I_T^i, I_S^i),
Eq. 4.1) and the decoded mesh is rendered by the soft rasteriser in the other, j, against that
view's silhouette (L_recon, Eq. 4.2); which of the two is i is drawn per record and batch.

1. **Reconstruction** (``train.recon_epochs``): psi and psi' on L_recon alone.
2. **Task-driven** (``train.joint_epochs``, from stage 1): L_recon + L_task (Eq. 4.4) train all four
   networks, so the task loss also shapes the tool latent space.
3. **Task-unaware** (``train.joint_epochs``, from the same stage-1 checkpoint, seed and initial
   phi / ff): psi and psi' stay frozen at stage 1, so L_task trains phi and ff only; z_T of both
   views of every record is computed once and the stage trains on those latents.

Each stage is a ``training.fit`` in its own directory under the run's ``stages/`` (checkpoints every
epoch, ``--resume`` continues the stage that was interrupted). The best epoch of stage 1 has the
highest validation IoU, of stages 2 and 3 the highest validation accuracy on the training types
(the held-out type E takes no part in choosing). ``best.pt`` holds both stage-2 models: the
task-driven one as the run's model, the task-unaware one beside it.
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np
import torch
from torch import nn

from physint_cli.errors import BadInput
from physint_cli.method import Context

from . import scenes as S
from .checkpoint import MODEL, data_config, load_split, view_cameras
from .softras import hard_iou
from .tasks import TYPES, parse_types

FIELDS = ["task", "tool_rgb", "tool_sil", "views", "label", "type"]
TASK_FIELDS = ["target", "obstacles", "n_obstacles"]  # the geometric check of hard examples


def build_model(name: str, data_cfg: dict[str, Any], cfg):
    """A registered ToolSynth model for a dataset's image sizes, as ``train`` config ``cfg`` sizes it."""
    from physint_cli.training import registered_model

    kwargs = {"image_size": int(data_cfg["tool_size"]), "task_size": int(data_cfg["task_size"]),
              "z_tool": int(cfg.z_tool), "z_task": int(cfg.z_task), "width": float(cfg.width),
              "task_width": float(cfg.task_width), "subdivisions": int(cfg.subdivisions),
              "deform": str(cfg.deform), "norm": str(cfg.norm), "latent": str(cfg.latent)}
    return registered_model("toolsynth", name).build(**kwargs), kwargs


class Records:
    """Dataset records in memory as a torch ``Dataset`` of dicts of arrays; ``latents`` (N, 2, Z)
    adds the frozen encoder's z_T of each record's two views."""

    def __init__(self, arrays: dict[str, np.ndarray], latents: np.ndarray | None = None):
        self.arrays = arrays
        self.latents = latents

    def __len__(self) -> int:
        return len(self.arrays["label"])

    def __getitem__(self, index: int) -> dict[str, Any]:
        item = {k: v[index] for k, v in self.arrays.items()}
        if self.latents is not None:
            item["latents"] = self.latents[index]
        return item


def views_of(batch: dict[str, Any], first: Any) -> dict[str, Any]:
    """A collated batch -> network inputs: view ``first`` (per record: 0 or 1) is the encoded view
    i, the other the rendered view j; images in [0, 1], channels first."""
    from .model import task_input, tool_input

    b = torch.arange(len(batch["label"]))
    i = torch.as_tensor(first).long()
    out = {"task": task_input(batch["task"]), "label": batch["label"].long(), "type": batch["type"].long(),
           "view_j": batch["views"][b, 1 - i].long(), "target_sil": (batch["tool_sil"][b, 1 - i] > 0).float(),
           **{k: batch[k] for k in TASK_FIELDS if k in batch}}
    if "latents" in batch:
        out["z_tool"] = batch["latents"][b, i].float()
    else:
        out["tool"] = tool_input(batch["tool_rgb"][b, i], batch["tool_sil"][b, i])
    return out


def random_views(batch: dict[str, Any]) -> dict[str, Any]:
    """Training batches: i drawn per record (torch's generator: seeded and resumed by ``fit``)."""

    return views_of(batch, torch.randint(0, 2, (len(batch["label"]),)))


def fixed_views(batch: dict[str, Any]) -> dict[str, Any]:
    """Validation batches: always the first stored view encoded, the second rendered."""

    return views_of(batch, torch.zeros(len(batch["label"]), dtype=torch.long))


class Scores:
    """Validation of a stage: mean reconstruction IoU in view j, and the classifier's accuracy on
    all records and on the training types; ``key`` names the one that chooses the best epoch."""

    def __init__(self, cams, train_types: tuple[str, ...], key: str, sigma: float):
        self.cams, self.key, self.sigma = cams, key, sigma
        self.train_types = [TYPES.index(t) for t in train_types]
        self.last: dict[str, float] = {}

    def __call__(self, model, loader) -> float:

        device = next(model.parameters()).device
        iou, right, right_train, n, n_train = [], 0, 0, 0, 0
        for batch in loader:
            batch = {k: v.to(device) for k, v in fixed_views(batch).items()}
            z = batch["z_tool"] if "z_tool" in batch else model.encode_tool(batch["tool"])
            if self.key == "iou":
                sil = model.silhouettes(model.decode(z), self.cams.to(device), batch["view_j"], self.sigma)
                iou.append(hard_iou(sil, batch["target_sil"]).cpu())
                continue
            pred = model.classify(model.encode_task(batch["task"]), z).argmax(1)
            hit = pred == batch["label"]
            seen = torch.isin(batch["type"], torch.tensor(self.train_types, device=device))
            right, n = right + int(hit.sum()), n + len(hit)
            right_train, n_train = right_train + int(hit[seen].sum()), n_train + int(seen.sum())
        if self.key == "iou":
            self.last = {"iou": float(torch.cat(iou).mean())}
        else:
            self.last = {"accuracy": right / max(n, 1), "accuracy_train_types": right_train / max(n_train, 1)}
        return self.last["iou" if self.key == "iou" else "accuracy_train_types"]


class TaskHead(nn.Module):
    """phi and ff of a model whose psi / psi' are frozen, trained on cached latents (stage 3)."""

    def __init__(self, model):
        super().__init__()
        self.task_encoder = copy.deepcopy(model.task_encoder)
        self.classifier = copy.deepcopy(model.classifier)

    def encode_task(self, task):
        return self.task_encoder(task)

    def classify(self, z_task, z_tool):
        return self.classifier(z_task, z_tool)


def train(ctx: Context) -> dict[str, Any]:

    from physint_cli.artifacts import save_training_curves
    from physint_cli.runs import Run
    from physint_cli.training import fit

    from .hard import HardExamples
    from .imagine import encode_views, latent_box
    from .model import jitter

    cfg = ctx.config.train
    manifest, data_cfg = data_config(ctx.data)
    train_types = parse_types(data_cfg["train_types"], "data.train_types")
    name = ctx.model or MODEL
    fields = FIELDS + (TASK_FIELDS if cfg.hard_examples else [])
    train_arrays, val_arrays = load_split(ctx.data, "train", fields), load_split(ctx.data, "val", FIELDS)
    labels = train_arrays["label"]
    if len(labels) < 2 or labels.min() == labels.max():
        raise BadInput(f"dataset {ctx.data} needs feasible and infeasible tools in its train split; "
                       f"make one with `physint dataset toolsynth`")
    torch.manual_seed(ctx.seed)  # stage 1's networks, and the phi / ff both stage-2 variants start from
    model, kwargs = build_model(name, data_cfg, cfg)
    elevation = float(data_cfg.get("elevation", S.ELEVATION))
    cams = view_cameras(int(data_cfg["views"]), int(data_cfg["tool_size"]), elevation)
    run = ctx.output()
    meta = {"method": "toolsynth", "model": name, "kwargs": kwargs, "backend": manifest["backend"],
            "dataset": str(ctx.data), "views": int(data_cfg["views"]), "elevation": elevation, "train_types": "".join(train_types),
            "sigma": float(cfg.sigma), "latent_noise": float(cfg.latent_noise),
            "hard_examples": int(cfg.hard_examples), "hard_steps": int(cfg.hard_steps)}
    ctx.log(f"training {name} on {len(labels)} records of types {''.join(train_types)} "
            f"({labels.mean():.0%} feasible), validating on {len(val_arrays['label'])}")

    def recon(net, batch):  # L_recon (Eq. 4.2) of the mesh decoded from view i, seen in view j
        z = net.encode_tool(batch["tool"])
        vertices = net.decode(z)
        sil = net.silhouettes(vertices, cams.to(batch["tool"].device), batch["view_j"], cfg.sigma)
        return net.recon_loss(sil, batch["target_sil"], vertices, cfg.laplacian, cfg.flatten)["total"], z

    def stage1_loss(net, batch):
        return recon(net, batch)[0]

    evaluation = ctx.config.eval  # hard examples are imagined as eval imagines
    hard = {title: HardExamples(cfg.hard_examples, cfg.hard_steps, evaluation.step, evaluation.threshold,
                                evaluation.optimizer) for title in ("task-driven", "task-unaware")}

    def joint_loss(net, batch):  # Eq. 4.4: L_recon + L_task, through psi as well
        loss, z = recon(net, batch)
        z_task = net.encode_task(batch["task"])
        return loss + cfg.task_weight * hard["task-driven"].loss(net, net, z_task, z, batch, jitter(z, cfg.latent_noise))

    def head_loss(net, batch):  # L_task on the frozen encoder's latents
        z_tool = batch["z_tool"]
        return hard["task-unaware"].loss(net, unaware, net.encode_task(batch["task"]), z_tool, batch,
                                         jitter(z_tool, cfg.latent_noise))

    def stage(title: str, net, train_set, loss_fn, key: str, epochs: int, lr: float):
        directory = run.path / "stages" / title
        (directory / "checkpoints").mkdir(parents=True, exist_ok=True)
        stage_run = Run(directory)
        scores = Scores(cams, train_types, key, cfg.sigma)
        ctx.log(f"stage {title}: {epochs} epochs")
        val_set = Records(val_arrays, val_latents if key == "head" else None)
        result = fit(net, train_set, val_set, run=stage_run, epochs=epochs,
                     batch_size=cfg.batch_size, lr=lr, loss_fn=loss_fn, metric_fn=scores, device=ctx.device,
                     seed=ctx.seed, resume=ctx.resume, log=ctx.log, higher_is_better=True, precision=cfg.precision,
                     batch_transform=random_views, progress=not ctx.quiet, meta=meta)
        best = stage_run.load_trained(ctx.device)
        net.load_state_dict(best["model"])
        net.eval()
        return result

    results = {"recon": stage("1-reconstruction", model, Records(train_arrays), stage1_loss, "iou",
                              cfg.recon_epochs, cfg.lr)}
    unaware = copy.deepcopy(model)  # stage 1's psi / psi', and phi / ff as initialised
    # task-unaware latents: psi frozen at stage 1
    train_latents, val_latents = encode_views(unaware, train_arrays), encode_views(unaware, val_arrays)
    results["task-driven"] = stage("2-task-driven", model, Records(train_arrays), joint_loss, "accuracy",
                                   cfg.joint_epochs, cfg.joint_lr)
    head = TaskHead(unaware)
    results["task-unaware"] = stage("3-task-unaware", head, Records(train_arrays, train_latents), head_loss, "head",
                                    cfg.joint_epochs, cfg.joint_lr)
    unaware.task_encoder.load_state_dict(head.task_encoder.state_dict())
    unaware.classifier.load_state_dict(head.classifier.state_dict())
    iou = Scores(cams, train_types, "iou", cfg.sigma)
    summary: dict[str, Any] = {"model": name, "train_records": int(len(labels)),
                               "val_records": int(len(val_arrays["label"])), "train_types": "".join(train_types)}
    with torch.no_grad():
        for title, net in (("task_driven", model), ("task_unaware", unaware)):
            loader = torch.utils.data.DataLoader(Records(val_arrays), batch_size=cfg.batch_size)
            scores = Scores(cams, train_types, "accuracy", cfg.sigma)
            scores(net.to(ctx.device).eval(), loader)
            iou(net, loader)
            summary[title] = {**scores.last, "val_iou": iou.last["iou"]}
    summary["stage1_val_iou"] = results["recon"].best_metric
    if cfg.hard_examples:  # in this process's epochs (a resumed stage counts from its restart)
        summary["hard_examples"] = {k.replace("-", "_"): h.summary() for k, h in hard.items()}
    summary["epochs"] = {k: r.epochs for k, r in results.items()}
    summary["seconds"] = {k: round(sum(h.get("seconds", 0) for h in r.history), 1) for k, r in results.items()}
    # where imagination may go (eval.latent_box): the box round each model's training latents
    views_latents = {"driven": encode_views(model, train_arrays), "unaware": train_latents}
    meta["latent_box"] = {which: [b.tolist() for b in latent_box(torch.as_tensor(z).flatten(0, 1))]
                          for which, z in views_latents.items()}
    run.save_trained(model=model.state_dict(), unaware=unaware.state_dict(), meta={**meta, "summary": summary})
    for title, result, loss, metric in (
            ("1-reconstruction", results["recon"], "train L_recon (Eq. 4.2)", "val IoU"),
            ("2-task-driven", results["task-driven"], "train L_recon + L_task (Eq. 4.4)", "val accuracy (train types)"),
            ("3-task-unaware", results["task-unaware"], "train L_task (Eq. 4.3)", "val accuracy (train types)")):
        save_training_curves(run.artifact(f"training_curves_{title}.png"), result.history, loss=loss, metric=metric,
                             chance=0.5 if "task" in title else None)
    return summary


__all__ = ["train", "build_model"]
