"""Training a GEECO controller on expert demonstrations (thesis Eq. 6.3, Appendix 6.A).

A training sample is a chunk of ``train.chunk`` consecutive windows of one demonstration: the
K - 1 frames before its first window (copies of the first frame at the episode's start, as in
control) and its own frames, the target image I_T = I_H, and per window the expert's commands and
the hand's and object's positions. The network encodes each frame of the chunk once and answers
every window (``Geeco.forward``). The best checkpoint is chosen by closed-loop task progress on
validation episodes (``train.val_episodes``; the thesis chose by validation task success).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from physint_cli.errors import BadInput
from physint_cli.method import Context

from .checkpoint import episodes_of, with_optional
from .control import DEE_SCALE, scale_goal, scale_positions
from .dagger import Aggregation, parse_epochs
from .model import BUFFER

FIELDS = ["rgb", "joints", "ee", "obj", "dee", "grip", "layout", "task", "seed"]


def build_model(name: str, image_size: int, cfg, command: str = "network"):
    """A registered GEECO model (``register_models``) as the ``train`` config section ``cfg`` describes it,
    with the resolved ``command`` (``train.command=auto`` resolved by ``resolve_command``)."""
    from physint_cli.training import registered_model

    kwargs = {"image_size": int(image_size), "width": float(cfg.width), "norm": bool(cfg.norm),
              "min_side": int(cfg.min_side), "stem_stride": int(cfg.stem_stride), "dee_bins": int(cfg.dee_bins),
              "dee_modes": int(cfg.dee_modes), "readout": str(cfg.readout), "command": str(command)}
    return registered_model("geeco", name).build(**kwargs), kwargs


def load_split(root: Path, split: str) -> dict[str, np.ndarray]:
    """A whole split of demonstrations in memory (small: ~1.2 MB per demonstration at 64 px), with
    the seeds of their background videos where the dataset has them."""
    from physint_cli.datasets import ShardedDataset

    return ShardedDataset(root, split, with_optional(root, FIELDS), method="geeco", in_memory=True).arrays


class Chunks:
    """Demonstrations -> training chunks (a torch ``Dataset``); chunk ``c`` of demo ``d`` covers
    the windows ending at steps ``c * L .. c * L + L - 1``."""

    def __init__(self, demos: dict[str, np.ndarray], chunk: int, buffer: int = BUFFER):
        self.chunk, self.buffer = chunk, buffer
        self.horizon = demos["rgb"].shape[1]
        self.per_demo = self.horizon // chunk
        self.d = {k: demos[k] for k in ("rgb", "joints", "dee", "grip")}
        self.d["target"] = demos["rgb"][:, -1]  # I_T: a demonstration's last frame
        self.pos = {k: scale_positions(demos[k]) for k in ("ee", "obj")}
        if "goal" in demos:  # the target's (x, y), for command="positions"
            self.pos["goal"] = scale_goal(demos["goal"])

    @property
    def demos(self) -> int:
        return len(self.d["rgb"])

    def extend(self, more: dict[str, np.ndarray]) -> None:
        """Add episodes of the same horizon (rollouts labelled by the expert, ``dagger.py``) with
        their own ``target`` images; the next epoch's sampler sees them."""
        if more["rgb"].shape[1:] != self.d["rgb"].shape[1:]:
            raise ValueError(f"episodes of shape {more['rgb'].shape[1:]} cannot join {self.d['rgb'].shape[1:]}")
        for k in self.d:
            self.d[k] = np.concatenate([self.d[k], more[k]])
        for k in ("ee", "obj"):
            self.pos[k] = np.concatenate([self.pos[k], scale_positions(more[k])])
        if "goal" in self.pos:
            self.pos["goal"] = np.concatenate([self.pos["goal"], scale_goal(more["goal"])])

    def __len__(self) -> int:
        return self.demos * self.per_demo

    def position_windows(self):
        """Every window of every demonstration as the command head of ``command="positions"`` sees it:
        the hand's and the object's positions over the buffer (N, K, 3; padded with the first step at
        an episode's start) and the target's (N, 2), with the expert's u_dEE (N, 3); all scaled."""
        import torch

        from .model import position_windows

        steps = np.clip(np.arange(1 - self.buffer, self.horizon), 0, None)
        hand, obj = (torch.from_numpy(self.pos[k][:, steps]) for k in ("ee", "obj"))
        inputs = position_windows(hand, obj, torch.from_numpy(self.pos["goal"]), self.buffer)
        dee = torch.from_numpy((self.d["dee"] / DEE_SCALE).astype(np.float32))
        return tuple(x.flatten(0, 1) for x in inputs), dee.flatten(0, 1)

    def __getitem__(self, index: int) -> dict[str, Any]:
        import torch

        demo, c = divmod(int(index), self.per_demo)
        first = c * self.chunk
        frames = np.clip(np.arange(first - self.buffer + 1, first + self.chunk), 0, None)  # left padding
        windows = slice(first, first + self.chunk)
        return {"frames": torch.from_numpy(self.d["rgb"][demo, frames]),
                "joints": torch.from_numpy(self.d["joints"][demo, frames]),
                "target": torch.from_numpy(self.d["target"][demo]),
                "dee": torch.from_numpy(self.d["dee"][demo, windows] / DEE_SCALE),
                "grip": torch.from_numpy(self.d["grip"][demo, windows].astype(np.int64)),
                "ee": torch.from_numpy(self.pos["ee"][demo, windows]),
                "obj": torch.from_numpy(self.pos["obj"][demo, windows]),
                **({"hand_steps": torch.from_numpy(self.pos["ee"][demo, frames]),  # every frame's, for the
                    "obj_steps": torch.from_numpy(self.pos["obj"][demo, frames]),  # command head
                    "goal": torch.from_numpy(self.pos["goal"][demo])} if "goal" in self.pos else {})}


def fit_command_head(model, train_set: Chunks, val_set: Chunks, epochs: int, seed: int, log,
                     batch_size: int = 256, lr: float = 1e-3) -> dict[str, float]:
    """The first stage of ``train.command=positions``: the command head alone learns the expert's u_dEE
    from the demonstrations' true positions, every window (MSE; Adam, the rate cosine-decayed to 0),
    keeping the epoch with the lowest validation MSE; then it is frozen. The network trains after it,
    so the closed-loop validation that picks the network's checkpoint drives the robot with the
    command head the controller keeps (learned jointly, the head is only as far as the chosen epoch)."""
    import copy

    import torch
    from torch.nn import functional as F

    (hand, obj, goal), dee = train_set.position_windows()
    val_inputs, val_dee = val_set.position_windows()
    head = model.command_head
    head.requires_grad_(True)
    optimizer = torch.optim.Adam(head.parameters(), lr=lr)
    per_epoch = max(1, len(dee) // batch_size)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, epochs * per_epoch)
    generator = torch.Generator().manual_seed(seed)

    def val_mse() -> float:
        with torch.no_grad():
            return float(F.mse_loss(model.command_from_positions(*val_inputs), val_dee))

    best = (val_mse(), copy.deepcopy(head.state_dict()))
    for epoch in range(1, epochs + 1):
        order = torch.randperm(len(dee), generator=generator)
        total = 0.0
        for b in range(per_epoch):
            i = order[b * batch_size:(b + 1) * batch_size]
            loss = F.mse_loss(model.command_from_positions(hand[i], obj[i], goal[i]), dee[i])
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            schedule.step()
            total += float(loss.detach())
        mse = val_mse()
        log(f"command head epoch {epoch}/{epochs}: train MSE {total / per_epoch:.4f}, val MSE {mse:.4f}")
        if mse < best[0]:
            best = (mse, copy.deepcopy(head.state_dict()))
    head.load_state_dict(best[1])
    head.requires_grad_(False)
    mean_mse = float(F.mse_loss(dee.mean(0).expand_as(val_dee), val_dee))
    return {"val_mse": best[0], "val_mse_of_the_mean_command": mean_mse, "train_windows": len(dee)}


def true_positions(batch: dict[str, Any]):
    """The demonstrations' hand and object positions at every frame of a chunk and the target's, from
    which a ``command="positions"`` controller's command head learns (None for the others)."""
    return (batch["hand_steps"], batch["obj_steps"], batch["goal"]) if "goal" in batch else None


def to_float_frames(batch: dict[str, Any]) -> dict[str, Any]:
    """uint8 (B, T, S, S, 3) frames and (B, S, S, 3) targets -> float (.., 3, S, S) in [0, 1]."""
    out = dict(batch)
    out["frames"] = batch["frames"].float().div_(255.0).movedim(-1, -3)
    out["target"] = batch["target"].float().div_(255.0).movedim(-1, -3)
    return out


def add_goals(demos: dict[str, np.ndarray], scene: str, skill: str) -> dict[str, np.ndarray]:
    """Give ``demos`` each one's target position ``goal`` (x, y, m), which ``command="positions"`` learns."""
    demos["goal"] = np.array([ep.xy(ep.target) for ep in episodes_of(demos, scene, skill)], np.float32)
    return demos


class ClosedLoopProgress:
    """Validation metric: mean task progress over validation episodes run with the network
    (push: (REACH + PUSH) / 2; pick-and-place: (REACH + PICK + PLACE) / 3)."""

    def __init__(self, ctx: Context, demos: dict[str, np.ndarray], skill: str, episodes: int, steps: int):
        self.ctx, self.skill, self.steps = ctx, skill, steps
        self.episodes = episodes_of(demos, ctx.scene, skill)[:episodes]
        self.targets = demos["rgb"][:episodes, -1]
        self.resolution = demos["rgb"].shape[2]
        self.sims: list = []  # made at the first validation, kept for the next

    def __call__(self, model, loader) -> float:
        from .control import LOCKSTEP, Policy, run_episodes, sims_for

        scores = []
        for start in range(0, len(self.episodes), LOCKSTEP):
            episodes = self.episodes[start:start + LOCKSTEP]
            targets = [t if model.conditioned else None for t in self.targets[start:start + LOCKSTEP]]
            sims = sims_for(self.sims, self.ctx.make_sim, episodes, self.resolution)
            for r in run_episodes(sims, episodes, [Policy(model) for _ in episodes], targets, self.steps,
                                  self.resolution):
                parts = [r["reach"], r["success"]] if self.skill == "push" else [r["reach"], r["pick"], r["success"]]
                scores.append(float(np.mean(parts)))
        model.train()
        return float(np.mean(scores))

    def close(self) -> None:
        for sim in self.sims:
            sim.close()
        self.sims.clear()


class ValidationLoss:
    """Validation metric when ``train.val_episodes`` is 0: minus the loss of Eq. 6.3 (with the command
    head's if it learns with the network, ``joint_command``)."""

    def __init__(self, aux_weight: float, joint_command: bool = False):
        self.aux_weight, self.joint_command = aux_weight, joint_command

    def __call__(self, model, loader) -> float:
        import torch

        from .model import geeco_loss

        total, n = 0.0, 0
        with torch.no_grad():
            for batch in loader:
                batch = to_float_frames(batch)
                out = model(batch["frames"], batch["joints"], batch["target"],
                            true_positions(batch) if self.joint_command else None)
                loss, _ = geeco_loss(out, batch, self.aux_weight, getattr(model, "dee_centres", None))
                total += float(loss) * len(batch["frames"])
                n += len(batch["frames"])
        return -total / max(n, 1)


def resolve_command(command: str, skill: str, classified: bool = False, aux_weight: float = 1.0) -> str:
    """``train.command``: ``auto`` is positions for pushing (its end-to-end u_dEE pushed 14.5 % at the
    small preset's scale, docs/geeco.md) and network for pick-and-place (the thesis), or whenever
    u_dEE is ``classified`` (``train.dee_bins`` or ``train.dee_modes`` read the network's u_dEE) or the
    positions it would read are not learned (λ = ``aux_weight`` = 0 in Eq. 6.3, the thesis's ablation)."""
    if command == "auto":
        return "positions" if skill == "push" and not classified and aux_weight > 0 else "network"
    return command


def train(ctx: Context) -> dict[str, Any]:
    from physint_cli.artifacts import save_training_curves
    from physint_cli.datasets import read_manifest
    from physint_cli.training import adamw_cosine, fit

    from .model import geeco_loss

    cfg = ctx.config.train
    manifest = read_manifest(ctx.data, "geeco")
    data_cfg = manifest["config"].get("data", manifest["config"])
    skill, scene = data_cfg["skill"], manifest["scene"]
    name = ctx.model or cfg.model
    if cfg.chunk < 1 or cfg.chunk > data_cfg["horizon"]:
        raise BadInput(f"train.chunk must be in [1, {data_cfg['horizon']}], got {cfg.chunk}")
    command = resolve_command(cfg.command, skill, bool(cfg.dee_bins or cfg.dee_modes), cfg.aux_weight)
    # the ranges, choices and rules between fields are the config's (config.TrainConfig.validate);
    # what is checked here needs the dataset: its horizon, its skill and the command resolved for it
    if command == "positions" and cfg.aux_weight == 0:
        raise BadInput("train.command=positions commands from the network's position estimates, which "
                       "train.aux_weight=0 leaves unlearned (lambda of Eq. 6.3): use train.command=network or auto")
    if command == "positions" and (cfg.dee_bins or cfg.dee_modes):
        raise BadInput("train.command=positions regresses u_dEE from positions: not with train.dee_bins or train.dee_modes")
    rounds = parse_epochs(cfg.dagger_epochs, cfg.epochs, skill, command)
    model, kwargs = build_model(name, data_cfg["resolution"], cfg, command)
    train_demos, val_demos = load_split(ctx.data, "train"), load_split(ctx.data, "val")
    if command == "positions":
        for demos in (train_demos, val_demos):
            add_goals(demos, scene, skill)
    if cfg.dee_modes:
        model.set_modes(train_demos["dee"] / DEE_SCALE, seed=ctx.seed)
    train_set, val_set = Chunks(train_demos, cfg.chunk), Chunks(val_demos, cfg.chunk)
    run = ctx.output()
    aggregation = Aggregation(ctx, run.path, train_set, train_demos, rounds, cfg.dagger_episodes,
                              data_cfg["horizon"], cfg.dagger_beta, ctx.log) if rounds else None
    ctx.log(f"training {name} on {len(train_demos['rgb'])} {skill} demonstrations of {scene} "
            f"({len(train_set)} chunks of {cfg.chunk} windows), validating on {len(val_demos['rgb'])}")
    command_head = None
    if command == "positions" and cfg.command_epochs:  # first the command head, from true positions
        command_head = fit_command_head(model, train_set, val_set, cfg.command_epochs, ctx.seed, ctx.log)
    joint_command = command == "positions" and not cfg.command_epochs  # or with the network

    def loss_fn(net, batch):
        out = net(batch["frames"], batch["joints"], batch["target"], true_positions(batch) if joint_command else None)
        loss, _ = geeco_loss(out, batch, cfg.aux_weight, getattr(model, "dee_centres", None))  # Eq. 6.3
        return loss

    if cfg.val_episodes > 0:
        metric = ClosedLoopProgress(ctx, val_demos, skill, cfg.val_episodes, ctx.config.eval.steps)
    else:
        metric = ValidationLoss(cfg.aux_weight, joint_command)
    make_optimizer = None
    if cfg.schedule == "cosine":
        def make_optimizer(net):
            return adamw_cosine(net, lr=cfg.lr, weight_decay=0.0, epochs=cfg.epochs)  # Adam, decaying rate

    try:
        result = fit(model, train_set, val_set, run=run, epochs=cfg.epochs, batch_size=cfg.batch_size,
                     lr=cfg.lr, loss_fn=loss_fn, metric_fn=metric, make_optimizer=make_optimizer, device=ctx.device,
                     seed=ctx.seed, resume=ctx.resume, log=ctx.log, higher_is_better=True,
                     precision=cfg.precision, batch_transform=to_float_frames, before_epoch=aggregation,
                     progress=not ctx.quiet, meta={"method": "geeco", "model": name, "kwargs": kwargs, "scene": scene,
                                                   "skill": skill, "backend": manifest["backend"],
                                                   "horizon": data_cfg["horizon"]})
    finally:
        if isinstance(metric, ClosedLoopProgress):
            metric.close()  # its simulators and their render contexts
    save_training_curves(run.artifact("training_curves.png"), result.history, loss="train loss (Eq. 6.3)",
                         metric="val task progress (closed loop)" if cfg.val_episodes > 0 else "val: minus loss")
    return {"model": name, "skill": skill, "scene": scene, "epochs": result.epochs,
            "val_metric": result.best_metric, "val_metric_is": "closed-loop task progress" if cfg.val_episodes
            else "minus validation loss (Eq. 6.3)", "train_demos": len(train_demos["rgb"]),
            "val_demos": len(val_demos["rgb"]), "command": command, "dagger_epochs": rounds,
            "dagger": aggregation.stats if aggregation else [],
            **({"command_head": command_head} if command_head else {})}
