"""Dataset aggregation for the push controller (DAgger, Ross et al. 2011): not in the thesis.

The thesis trained GEECO on 2,000 noise-free demonstrations per skill. With the small preset's
400, the push controller stalls in states no demonstration shows (docs/geeco.md). Here, at the
start of the epochs listed in ``train.dagger_epochs``, the controller being trained drives the
robot from ``train.dagger_episodes`` training start states for H steps (at each step, with
probability ``train.dagger_beta``, the expert's command is executed instead: beta_i of Ross et
al.), and the push expert,
a feedback law on the current state (:meth:`Expert._push`), labels every state the controller
reached with the command it would give there (and the simulator with the hand's, the object's
and the target's true positions, which ``train.command=positions`` controllers learn to see).
These labelled rollouts (with the target image of their start state) join the training
demonstrations for the remaining epochs, so the controller learns what to do, and where things
are, in the states its own errors lead to.

Only pushing: the pick-and-place expert is a plan with phases (grasp, lift, carry), whose
command in a state the controller reached need not be the right one.
Each round is saved in the run (``dagger/epoch-NNN.npz``); a resumed training reloads the
rounds made before it stopped.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import numpy as np

from physint_cli.errors import BadInput

from . import scenes as S
from .checkpoint import episodes_of
from .config import dagger_rounds
from .control import LOCKSTEP, Policy, controllers, sims_for
from .episode import Act, ClosedLoop, run
from .expert import on_target

ROLLOUT_FIELDS = ("rgb", "joints", "ee", "obj", "dee", "grip", "target", "goal")


AUTO_ROUNDS = (3, 4, 5)  # train.dagger_epochs=auto: rounds before the epochs at 3/6, 4/6, 5/6 of the training


def parse_epochs(text: str, epochs: int, skill: str, command: str = "network") -> list[int]:
    """``train.dagger_epochs`` ("5,7,9") as sorted epoch numbers; bad values exit 2. ``auto``: for a
    positions controller of pushing (``command``), rounds before the epochs at 1/2, 2/3 and 5/6 of
    the training (5, 7, 9 of 10; none before epoch 2), else none: for network commands the rounds
    did not help (docs/geeco.md, session 12)."""
    if str(text).strip() == "auto":
        if skill != "push" or command != "positions":
            return []
        return sorted({-(-epochs * k // 6) for k in AUTO_ROUNDS} & set(range(2, epochs + 1)))  # ceil(epochs k / 6)
    rounds = dagger_rounds(text, epochs)  # the config's check: numbers in [2, epochs]
    if rounds and skill != "push":
        raise BadInput("train.dagger_epochs needs push demonstrations: the pick-and-place expert is a plan, "
                       "not a feedback law, so it cannot label the states a controller reaches")
    return rounds


def rollouts(sims: list, episodes: list[S.Episode], policies: list[Policy], targets: list[np.ndarray], horizon: int,
             beta: float = 0.0, rngs: list[np.random.Generator] | None = None) -> list[dict[str, np.ndarray] | None]:
    """The controller drives for ``horizon`` steps from each episode's start state, the episodes side
    by side (one simulation and policy each, their frames through the network as one batch); with
    probability ``beta`` a step executes the expert's command instead (drawn from the episode's own
    generator in ``rngs``). Every step is recorded with the expert's command for that state, and
    ``on_target`` says whether the object ended on its target. None for an episode where the
    controller diverged."""
    resolution = targets[0].shape[0]
    loops = [ClosedLoop(sim, ep, resolution, policy, target, expert=True, record=horizon)
             for sim, ep, policy, target in zip(sims, episodes, policies, targets, strict=True)]
    run(loops, horizon, mixed(beta, dict(zip(loops, rngs or ()))))
    outs: list[dict[str, np.ndarray] | None] = []
    for loop, target in zip(loops, targets):
        if loop.diverged:  # no rollout
            outs.append(None)
            continue
        ep = loop.ep
        outs.append(dict(loop.arrays, target=target,
                         goal=np.asarray(ep.xy(ep.target), np.float32),  # where the object belongs (x, y), m
                         on_target=np.bool_(on_target(ep, loop.sim))))
    return outs


def mixed(beta: float, coins: dict) -> Act:
    """``act`` of a DAgger rollout: the controller's command, or with probability ``beta`` (a draw
    from the rollout's generator in ``coins``) the expert's; the expert's plan follows the hand that
    was actually sent (``Expert.follow``)."""

    def act(loops: list[ClosedLoop], observations: list[tuple]) -> list[np.ndarray]:
        actions = controllers(loops, observations)
        for k, (loop, action) in enumerate(zip(loops, actions)):
            if np.all(np.isfinite(action)):
                if beta > 0 and coins[loop].random() < beta:
                    actions[k] = action = loop.command
                loop.expert.follow(loop.command, action)
        return actions

    return act


def aggregation_round(make_sim, model, demos: dict[str, np.ndarray], scene: str, episodes: int, horizon: int,
                      rng: np.random.Generator, beta: float = 0.0) -> dict[str, np.ndarray]:
    """Rollouts of ``model`` from ``episodes`` training start states drawn by ``rng``, stacked."""
    starts = episodes_of(demos, scene, "push")
    chosen = rng.choice(len(starts), size=min(episodes, len(starts)), replace=False)
    coins = rng.spawn(len(chosen))  # each rollout its own draws, whichever episodes share its group
    sims, made = [], []
    try:
        for at in range(0, len(chosen), LOCKSTEP):
            group = chosen[at:at + LOCKSTEP]
            eps = [starts[i] for i in group]
            made += rollouts(sims_for(sims, make_sim, eps, demos["rgb"].shape[2]), eps, [Policy(model) for _ in eps],
                             [demos["rgb"][i, -1] for i in group], horizon, beta, coins[at:at + LOCKSTEP])
    finally:
        for sim in sims:
            sim.close()
        model.train()
    made = [r for r in made if r is not None]
    if not made:
        return {}
    return {k: np.stack([r[k] for r in made]) for k in (*ROLLOUT_FIELDS, "on_target")}


class Aggregation:
    """``fit``'s ``before_epoch`` hook: at each epoch of ``rounds`` (1-based), roll out the
    controller, label with the expert and add the rollouts to ``train_set`` (a ``Chunks``)."""

    def __init__(self, ctx, run_dir: Path, train_set, demos: dict[str, np.ndarray], rounds: list[int],
                 episodes: int, horizon: int, beta: float = 0.0, log=print):
        self.ctx, self.dir, self.train_set, self.demos = ctx, Path(run_dir) / "dagger", train_set, demos
        self.rounds, self.episodes, self.horizon, self.beta, self.log = rounds, episodes, horizon, beta, log
        self.added: set[int] = set()
        self.stats: list[dict[str, Any]] = []

    def __call__(self, epoch: int, model) -> None:
        """Called before training epoch ``epoch`` (0-based) starts; also when resuming there."""
        from physint_cli.datasets import atomic_write_bytes

        for at in self.rounds:
            if at > epoch + 1 or at in self.added:
                continue
            path = self.dir / f"epoch-{at:03d}.npz"
            if path.exists():  # made before a resume
                with np.load(path) as saved:
                    arrays = {k: saved[k] for k in saved.files}
            else:
                self.log(f"DAgger round before epoch {at}: the controller drives {self.episodes} training start "
                         f"states, the expert labels what it sees")
                rng = np.random.default_rng([self.ctx.seed, at])
                arrays = aggregation_round(self.ctx.make_sim, model, self.demos, self.ctx.scene, self.episodes,
                                           self.horizon, rng, self.beta)
                buffer = io.BytesIO()
                np.savez(buffer, **arrays)
                self.dir.mkdir(parents=True, exist_ok=True)
                atomic_write_bytes(path, buffer.getvalue())
            if arrays:
                self.train_set.extend(arrays)
            self.added.add(at)
            done = arrays.get("on_target", np.zeros(0, bool))
            self.stats.append({"epoch": at, "rollouts": len(done), "train_demos": self.train_set.demos,
                               "on_target": float(done.mean()) if len(done) else None})
            self.log(f"training now on {self.train_set.demos} demonstrations and rollouts")
