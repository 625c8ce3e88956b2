"""Closed-loop control with a trained GEECO controller (thesis Sections 6.3 and 6.4).

:class:`Policy` keeps the observation buffer of the last K (frame, joint angles) pairs, padded
on the left with copies of the oldest at the start of an episode (Appendix 6.A), and turns the
network's outputs back into robot commands; :func:`act_together` steps several policies of one
model with one forward pass. :func:`run_episode` runs one episode (:func:`run_episodes` several
side by side, in lockstep) through the one episode loop (``episode.run``, the policies acting:
:func:`controllers`) and scores it the thesis's way (``episode.ClosedLoop``):

* REACH: the robot touched the object to move at least once;
* PICK: the object was held: the fingers touch it with the gripper closed and it is lifted at
  least 2 cm off the table (the thesis's Fetch counted palm contact with closed fingers; the
  Panda holds a cube between its fingers, not against its palm);
* PUSH / PLACE: the object rests on its target at the end (200 steps).

A non-finite command (a diverging model) ends the episode as a failure (``diverged``), so an
evaluation always finishes.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np

from . import scenes as S
from .episode import ClosedLoop, Rollout, expert_drives, observe, run
from .expert import on_target

DEE_SCALE = 0.03  # network u_dEE is in units of the expert's free-space step (m)
POS_SCALE = 0.1  # network positions are in decimetres from the table centre
GRIP_COMMAND = (-1, 0, 1)  # class id -> gripper command (open, no-op, close)
LOCKSTEP = 16  # training's closed-loop episodes (validation, DAgger) stepped side by side, at most


def scale_positions(q: np.ndarray) -> np.ndarray:
    return (np.asarray(q, dtype=np.float32) - np.array([0.0, 0.0, S.TABLE_Z], np.float32)) / POS_SCALE


def scale_goal(xy: np.ndarray) -> np.ndarray:
    """The target's (x, y) on the table (m) in the network's units (the table centre is the origin)."""
    return (np.asarray(xy, dtype=np.float32) / POS_SCALE).astype(np.float32)


def unscale_positions(q: np.ndarray) -> np.ndarray:
    return np.asarray(q, dtype=float) * POS_SCALE + np.array([0.0, 0.0, S.TABLE_Z])


def to_tensor_frames(frames: np.ndarray):
    """uint8 (..., S, S, 3) -> float (..., 3, S, S) in [0, 1]."""
    import torch

    t = torch.from_numpy(np.ascontiguousarray(frames)).float().div_(255.0)
    return t.movedim(-1, -3)


class Policy:
    """A trained controller with its observation buffer."""

    def __init__(self, model, device: str | None = None):
        """``device``: where to run the model (default: where its weights are, so a model in
        training stays on its device)."""
        device = device or str(next(model.parameters()).device)
        self.model = model.eval().to(device)
        self.device = device
        self.buffer: deque = deque(maxlen=model.buffer)
        self.positions: deque = deque(maxlen=model.buffer)  # command="positions": (hand, object) per step
        self.target = None
        self.target_code = None  # GEECO-R: psi_OBS(I_T), encoded at the episode's first step (set targets by reset)
        self.last: dict[str, Any] = {}

    def reset(self, target_rgb: np.ndarray | None) -> None:
        self.buffer.clear()
        self.positions.clear()
        self.target = None if target_rgb is None else to_tensor_frames(target_rgb)[None].to(self.device)
        self.target_code = None

    def act(self, rgb: np.ndarray, joints: np.ndarray, hand: np.ndarray | None = None,
            truth: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """The next robot action ``(dx, dy, dz, gripper)``; NaN where the network diverged.

        ``hand``: the hand's measured position (proprioception, m), which a ``command="positions"``
        controller takes with its estimates of the object's and the target's (without it, its own
        estimate of the hand's); ``truth``: the object's true position (3) and the target's (2), m,
        to use instead of those estimates (``eval.positions=true``)."""
        return act_together([self], [(rgb, joints, hand, truth)])[0]

    def _push(self, frame, joints, item) -> None:
        """Add this step's frame (1, 1, 3, S, S), joint angles (1, 1, 7) and what the network keeps
        of it to the buffer; at an episode's start, pad with copies of it (the robot is at rest)."""
        if not self.buffer:
            self.buffer.extend([(frame, joints, item)] * (self.buffer.maxlen - 1))
        self.buffer.append((frame, joints, item))

    def _action(self, out: dict[str, Any], frames, hand: np.ndarray | None,
                truth: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray:
        """This policy's heads (batch of one) -> its robot action; ``last`` keeps its estimates."""
        import torch

        if getattr(self.model, "command", "network") == "positions":
            if truth is not None:
                out["obj"] = torch.from_numpy(scale_positions(truth[0]))[None].to(out["obj"].device)
                out["goal"] = torch.from_numpy(scale_goal(truth[1]))[None].to(out["obj"].device)
            out["dee"] = self._command_from_positions(out, hand)
        dee = out["dee"][0].float().cpu().numpy() * DEE_SCALE
        grip = GRIP_COMMAND[int(out["grip"][0].argmax())]
        self.last = {"ee": unscale_positions(out["ee"][0].float().cpu().numpy()),
                     "obj": unscale_positions(out["obj"][0].float().cpu().numpy()), "frames": frames}
        if "goal" in out:
            self.last["goal"] = out["goal"][0].float().cpu().numpy() * POS_SCALE
        return np.array([*dee, grip], dtype=float)

    def _command_from_positions(self, out: dict[str, Any], hand: np.ndarray | None):
        """u_dEE from the command head: the hand's and the object's positions over the last K steps
        (padded with the first at an episode's start, as the frames are) and the target's."""
        import torch

        obj = out["obj"][0].float()
        ee = out["ee"][0].float() if hand is None else torch.from_numpy(scale_positions(hand)).to(obj.device)
        step = (ee, obj)
        if not self.positions:
            self.positions.extend([step] * (self.positions.maxlen - 1))
        self.positions.append(step)
        history = [torch.stack([p[i] for p in self.positions])[None] for i in (0, 1)]
        with torch.no_grad():
            return self.model.command_from_positions(*history, out["goal"].float())


def act_together(policies: list[Policy], observations: list[tuple]) -> list[np.ndarray]:
    """The next action of each of ``policies`` (all of one model, each in its own episode) for its
    ``(rgb, joints, hand, truth)`` as :meth:`Policy.act` takes them: their frames go through the
    network as one batch, which on a CPU costs a fraction of one forward pass per episode. Any
    other object with an ``act`` (a scripted stand-in) acts on its own."""
    import torch

    if not policies or not all(isinstance(p, Policy) for p in policies):
        return [p.act(*obs) for p, obs in zip(policies, observations, strict=True)]
    model, device = policies[0].model, policies[0].device
    if any(p.model is not model for p in policies):
        raise ValueError("policies acting together must share one model")
    if model.conditioned and any(p.target is None for p in policies):
        raise ValueError(f"{model.variant} needs a target image")
    frames = [to_tensor_frames(rgb)[None, None].to(device) for rgb, *_ in observations]  # (1, 1, 3, S, S)
    joints = [torch.as_tensor(obs[1], dtype=torch.float32)[None, None].to(device) for obs in observations]
    with torch.no_grad():
        if model.variant == "geeco-f":  # encodes the whole buffer's dynamic image at every step
            items = frames
        else:  # per-frame variants keep each frame's state: one new frame is encoded per step
            targets = codes = None
            if model.variant == "geeco-r":  # the target's encoding is the same all episode: encode it once
                fresh = [p for p in policies if p.target_code is None]
                if fresh:
                    for p, code in zip(fresh, model.target_code(torch.cat([p.target for p in fresh])).split(1)):
                        p.target_code = code
                codes = torch.cat([p.target_code for p in policies])
            elif model.conditioned:
                targets = torch.cat([p.target for p in policies])
            items = model.frame_states(torch.cat(frames), torch.cat(joints), targets, codes).split(1)
        for policy, frame, x, item in zip(policies, frames, joints, items):
            policy._push(frame, x, item)
        buffers = [torch.cat([f for f, _, _ in p.buffer], dim=1) for p in policies]  # (1, K, 3, S, S) each
        if model.variant == "geeco-f":
            out = {k: v[:, -1] for k, v in model(torch.cat(buffers), torch.cat(
                [torch.cat([j for _, j, _ in p.buffer], dim=1) for p in policies]),
                torch.cat([p.target for p in policies])).items()}
        else:
            out = model.decide(torch.cat([torch.cat([s for _, _, s in p.buffer], dim=1) for p in policies]))
    return [policy._action({k: v[i:i + 1] for k, v in out.items()}, buffer, *obs[2:])
            for i, (policy, buffer, obs) in enumerate(zip(policies, buffers, observations, strict=True))]


def controllers(rollouts: list[ClosedLoop], observations: list[tuple]) -> list[np.ndarray]:
    """``act`` for :func:`episode.run`: each closed loop's policy acts, one batch (:func:`act_together`)."""
    return act_together([r.policy for r in rollouts], observations)


def expert_target(sim, ep: S.Episode, resolution: int, horizon: int = 100) -> np.ndarray | None:
    """The target image of ``ep`` on this backend: the expert's last frame (None if it failed)."""
    rollout = Rollout(sim, ep, resolution, expert=True, see=False)  # the expert reads the simulator
    run([rollout], horizon, expert_drives())
    if not (on_target(ep, sim) and rollout.expert.done):
        return None
    return observe(sim, horizon, rollout.video)


def run_episode(sim, ep: S.Episode, policy: Policy, target_rgb: np.ndarray | None, steps: int, resolution: int,
                on_step=None, true_positions: bool = False) -> dict[str, Any]:
    """One closed-loop episode (:class:`ClosedLoop`); ``on_step(t, rgb, action, policy)`` sees each step.
    ``policy`` has :class:`Policy`'s ``reset(target_rgb)`` and ``act(rgb, joints, hand, truth)``."""
    hook = None if on_step is None else lambda t, _, observation, action: on_step(t, observation[0], action, policy)
    return run_episodes([sim], [ep], [policy], [target_rgb], steps, resolution, true_positions, hook)[0]


def sims_for(sims: list, make_sim, episodes: list[S.Episode], resolution: int) -> list:
    """The first ``len(episodes)`` of ``sims``, made with ``make_sim(scene)`` where there are fewer."""
    while len(sims) < len(episodes):
        sims.append(make_sim(S.build_scene(episodes[len(sims)], resolution)))
    return sims[:len(episodes)]


def run_episodes(sims: list, episodes: list[S.Episode], policies: list[Policy], targets: list, steps: int,
                 resolution: int, true_positions: bool = False, on_step=None) -> list[dict[str, Any]]:
    """Episodes side by side, one simulation and one policy (of one model) each, stepped in lockstep
    so that their frames go through the network as one batch (:func:`act_together`); the results of
    :func:`run_episode`, each episode's ``seconds`` its share of the wall time. ``on_step``: as
    :func:`episode.run` takes it."""
    loops = [ClosedLoop(sim, ep, resolution, policy, target, true_positions=true_positions)
             for sim, ep, policy, target in zip(sims, episodes, policies, targets, strict=True)]
    seconds = run(loops, steps, controllers, on_step) / max(1, len(loops))
    return [loop.result(seconds) for loop in loops]
