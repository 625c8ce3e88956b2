"""Tool imagination (thesis Section 4.3.3, Eq. 4.5) and its baselines, batched over tasks.

From the latent z_T of a tool that cannot reach a task's target, imagination descends the task
loss towards "success" in z_T alone, the networks fixed:

    z_T <- z_T - eta * d L_task(ff([z_G, z_T]), rho = 1) / d z_T

(Eq. 4.5 prints a plus: ascending that loss would move away from success). Each instance stops at
its own first step where p(success) >= gamma (``threshold``), or at the step cap.

The thesis "modifies the latent vector via backpropagation using a learning rate of 0.01". With
``optimizer="sgd"`` that is Eq. 4.5 literally, a step of eta times the gradient, whose length
depends on how steep the classifier happens to be in z_T; with ``optimizer="adam"`` (the default)
Adam at learning rate eta moves each coordinate by about eta per step, the same scale as the
random walk's steps, so the two searches cover comparable distances. Adam's moments are
elementwise, so one optimiser over the batch is one per instance. The random walk
(Section 4.4.3's baseline) steps z_T <- z_T + eta * eps, eps ~ N(0, I), with the same stop rule;
the no-op control decodes the start latent unchanged. With a ``box`` (:func:`latent_box` of the
training records' latents, not in the thesis) each step is clipped to it, coordinate by coordinate.
:func:`judge` decodes final latents to meshes
and asks the geometric check (``feasibility.check`` on the mesh seen from above) whether they reach.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from . import feasibility
from .model import p_success, task_loss
from .tasks import Task

METHODS = ("descent", "random", "none")
OPTIMIZERS = ("adam", "sgd")


@dataclass
class Imagination:
    """Where a batch of imagination processes ended: final latents (B, Z), the steps each took,
    p(success) at the start and at the end, whether it reached the threshold, and the latents
    every ``keep_every`` steps (for the deploy strip)."""

    z: torch.Tensor
    steps: np.ndarray
    p_start: np.ndarray
    p_end: np.ndarray
    reached: np.ndarray
    trace: list[tuple[int, torch.Tensor, np.ndarray]] = field(default_factory=list)


def imagine(model, z_task: torch.Tensor, z_start: torch.Tensor, method: str = "descent", step: float = 0.01,
            max_steps: int = 2000, threshold: float = 0.997, seed: int = 0, keep_every: int = 0,
            optimizer: str = "adam", box: tuple[torch.Tensor, torch.Tensor] | None = None) -> Imagination:
    """Run ``method`` (``descent``: Eq. 4.5 with ``optimizer``; ``random``: the random walk;
    ``none``: no-op) from ``z_start`` (B, Z) for tasks ``z_task`` (B, Z_G) with the classifier of
    ``model``. With ``box`` (low, high), each of shape (Z,), every step is clipped to that box
    (:func:`latent_box`)."""
    if method not in METHODS:
        raise ValueError(f"imagination method must be one of {', '.join(METHODS)}, got {method!r}")
    if optimizer not in OPTIMIZERS:
        raise ValueError(f"imagination optimizer must be one of {', '.join(OPTIMIZERS)}, got {optimizer!r}")
    gen = torch.Generator(device=z_start.device).manual_seed(seed)
    z_task = z_task.detach()
    z = z_start.detach().clone()
    success = torch.ones(len(z), dtype=torch.long, device=z.device)
    with torch.no_grad():
        p0 = p_success(model.classify(z_task, z))
    p = p0.clone()
    active = (p < threshold) if method != "none" else torch.zeros(len(z), dtype=torch.bool, device=z.device)
    steps = torch.zeros(len(z), dtype=torch.long, device=z.device)
    trace = [(0, z.clone(), p.cpu().numpy())] if keep_every else []
    zk = z.clone().requires_grad_(True)
    adam = torch.optim.Adam([zk], lr=step) if optimizer == "adam" else None
    for k in range(1, max_steps + 1):
        if not bool(active.any()):
            break
        if method == "descent":
            zk.data.copy_(z)
            # sum of per-instance losses: each instance's gradient is its own (Eq. 4.5 per task)
            loss = task_loss(model.classify(z_task, zk), success) * len(z)
            (grad,) = torch.autograd.grad(loss, zk)
            if adam is None:
                move = -step * grad  # Eq. 4.5, descending
            else:  # Adam's step on the same gradient; finished instances get none and stay put (below)
                zk.grad = grad * active[:, None]
                adam.step()
                move = zk.detach() - z
        else:
            move = step * torch.randn(z.shape, generator=gen, device=z.device)
        z = torch.where(active[:, None], z + move, z)
        if box is not None:
            z = z.clamp(box[0], box[1])
        steps += active.long()
        with torch.no_grad():
            p = torch.where(active, p_success(model.classify(z_task, z)), p)
        active &= p < threshold
        if keep_every and (k % keep_every == 0):
            trace.append((k, z.clone(), p.cpu().numpy()))
    if keep_every and trace[-1][0] != int(steps.max()):
        trace.append((int(steps.max()), z.clone(), p.cpu().numpy()))
    return Imagination(z.detach(), steps.cpu().numpy(), p0.cpu().numpy(), p.cpu().numpy(),
                       (p >= threshold).cpu().numpy(), trace)


def latent_box(z: torch.Tensor, margin: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """The box round latents ``z`` (N, Z): per coordinate their least and greatest value, widened
    by ``margin`` times the range on each side."""
    low, high = z.min(0).values, z.max(0).values
    pad = margin * (high - low)
    return (low - pad).detach(), (high + pad).detach()


def encode_views(model, arrays: dict[str, np.ndarray], batch: int = 256) -> np.ndarray:
    """z_T (N, 2, Z) of both stored views of every record (``tool_rgb`` (N, 2, S, S, 3) and
    ``tool_sil`` (N, 2, S, S)), by the model's encoder in eval mode."""
    from .model import tool_input

    model.eval()
    out = []
    with torch.no_grad():
        for s in range(0, len(arrays["tool_rgb"]), batch):
            rgb = torch.as_tensor(arrays["tool_rgb"][s:s + batch])
            sil = torch.as_tensor(arrays["tool_sil"][s:s + batch])
            out.append(torch.stack([model.encode_tool(tool_input(rgb[:, v], sil[:, v])) for v in range(2)], 1).numpy())
    return np.concatenate(out)


def footprints(model, z: torch.Tensor, batch: int = 256) -> list:
    """The top-down outlines (shapely polygons, or None) of the meshes decoded from latents ``z``."""
    faces = model.faces.cpu().numpy()
    out = []
    with torch.no_grad():
        for s in range(0, len(z), batch):
            vertices = model.decode(z[s:s + batch]).cpu().numpy()
            out += [feasibility.mesh_footprint(v, faces) for v in vertices]
    return out


def judge(model, z: torch.Tensor, tasks: list[Task]) -> tuple[list[feasibility.Verdict], list]:
    """The geometric check's verdict on each decoded tool for its task, and the tools' outlines."""
    shapes = footprints(model, z)
    return [feasibility.check(shape, task) for shape, task in zip(shapes, tasks)], shapes
