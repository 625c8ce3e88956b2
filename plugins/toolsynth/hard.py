"""Hard examples for the classifier: imagined tools labelled by the geometric check (a deviation,
``train.hard_examples``; off in the thesis's setup).

Trained on the dataset's tools alone, the classifier ff is asked in imagination about latents no
record has: those that Eq. 4.5's descent reaches. There it may say "success" for a tool the
decoder draws as a longer stick through a wall, and imagination stops at a tool that cannot
reach. With ``train.hard_examples`` = n > 0, stages 2 and 3 run, in every batch, imagination
itself (``imagine.imagine``, the eval's step, optimiser and threshold, at most
``train.hard_steps`` steps) from the latents of up to n of the batch's infeasible records, with
the classifier as it stands; decode the latents where it stopped, ask ``feasibility.check``
whether those tools reach their tasks, and add L_task (Eq. 4.3) of the classifier on those
latents with the check's verdict as label: the hard examples join the batch's records in
one mean, so that each weighs as much as a record. The task-driven and the task-unaware model get the
same treatment (each with its own decoder), so the two stay comparable.
"""

from __future__ import annotations

from typing import Any

import torch

from .imagine import imagine, judge
from .model import task_loss
from .tasks import tasks_of


class HardExamples:
    """L_task of stage 2 or 3 with the batch's hard examples, and how many it made and found feasible."""

    def __init__(self, count: int, steps: int, step: float, threshold: float, optimizer: str):
        self.count, self.steps, self.step, self.threshold, self.optimizer = count, steps, step, threshold, optimizer
        self.seen = 0
        self.feasible = 0

    def loss(self, net, decoder, z_task: torch.Tensor, z_tool: torch.Tensor, batch: dict[str, Any],
             z_input: torch.Tensor | None = None) -> torch.Tensor:
        """L_task (Eq. 4.3) of ``net``'s classifier on the batch's records (tool latents
        ``z_input``, default ``z_tool``) and on where imagination from its infeasible tools ends,
        labelled by the geometric check of ``decoder``'s meshes there, as one mean."""
        z_task_all, z_tool_all = z_task, z_tool if z_input is None else z_input
        labels = batch["label"]
        pick = torch.nonzero(labels == 0).flatten()[:self.count]
        if self.count and len(pick):
            tasks = tasks_of({k: batch[k].cpu() for k in ("type", "target", "obstacles", "n_obstacles")}, pick.tolist())
            ended = imagine(net, z_task[pick].detach(), z_tool[pick].detach(), "descent", self.step, self.steps,
                            self.threshold, optimizer=self.optimizer)
            verdicts, _ = judge(decoder, ended.z, tasks)
            verdict = torch.tensor([int(v.feasible) for v in verdicts], device=labels.device)
            self.seen += len(verdict)
            self.feasible += int(verdict.sum())
            z_task_all, z_tool_all = torch.cat([z_task, z_task[pick]]), torch.cat([z_tool_all, ended.z])
            labels = torch.cat([labels, verdict])
        return task_loss(net.classify(z_task_all, z_tool_all), labels)  # records and hard examples: one batch

    def summary(self) -> dict[str, float]:
        return {"hard_examples": self.seen, "hard_feasible": self.feasible / max(self.seen, 1)}
