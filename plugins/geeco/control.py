"""Closed-loop control with a trained GEECO controller (thesis Sections 6.3 and 6.4).

:class:`Policy` keeps the observation buffer of the last K (frame, joint angles) pairs, padded
on the left with copies of the oldest at the start of an episode (Appendix 6.A), and turns the
network's outputs back into robot commands; :func:`act_together` steps several policies of one
model with one forward pass. :func:`run_episode` runs one episode (:func:`run_episodes` several
side by side, in lockstep) and scores it the thesis's way (:class:`ClosedLoop`):

* REACH: the robot touched the object to move at least once;
* PICK: the object was held: the fingers touch it with the gripper closed and it is lifted at
  least 2 cm off the table (the thesis's Fetch counted palm contact with closed fingers; the
  Panda holds a cube between its fingers, not against its palm);
* PUSH / PLACE: the object rests on its target at the end (200 steps).

A non-finite command (a diverging model) ends the episode as a failure (``diverged``), so an
evaluation always finishes.
"""

from __future__ import annotations

import time
from collections import deque
from typing import Any

import numpy as np

from . import scenes as S
from .expert import Expert, on_target

DEE_SCALE = 0.03  # network u_dEE is in units of the expert's free-space step (m)
POS_SCALE = 0.1  # network positions are in decimetres from the table centre
GRIP_COMMAND = (-1, 0, 1)  # class id -> gripper command (open, no-op, close)
LIFTED = 0.02  # PICK: the object's bottom at least this far off the table
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


def observe(sim, step: int, video=None) -> np.ndarray:
    """The camera frame at ``step``, its background replaced by ``video`` if one is given
    (``S.background_video``: BG:PRISMA's rainbow, or a demonstration's random background)."""
    if video is None:
        return sim.render("front").rgb
    frame = sim.render("front", segmentation=True)
    return S.replace_background(frame.rgb, frame.segmentation, step, video)


def expert_target(sim, ep: S.Episode, resolution: int, horizon: int = 100) -> np.ndarray | None:
    """The target image of ``ep`` on this backend: the expert's last frame (None if it failed)."""
    sim.reset(S.build_scene(ep, resolution))
    expert = Expert(ep)
    for _ in range(horizon):
        sim.robot.act(expert.act(sim))
    if not (on_target(ep, sim) and expert.done):
        return None
    return observe(sim, horizon, S.background_video(ep))


class ClosedLoop:
    """One closed-loop episode from ``ep``'s start state on ``sim``, scored as it runs: REACH, PICK,
    a diverged command, and at the end PUSH / PLACE (:meth:`result`). ``true_positions``: a
    ``command="positions"`` controller gets the simulator's object and target positions instead of
    its network's estimates."""

    def __init__(self, sim, ep: S.Episode, policy, target_rgb: np.ndarray | None, resolution: int,
                 true_positions: bool = False):
        self.sim, self.ep, self.true_positions = sim, ep, true_positions
        sim.reset(S.build_scene(ep, resolution))
        policy.reset(target_rgb)
        self.video = S.background_video(ep)
        self.reach = self.pick = self.diverged = self.gripper_closed = False
        self.steps = 0
        self.state = None  # the robot's state at the last observation

    def observe(self, step: int) -> tuple:
        """What the policy gets at ``step``: (rgb, joints, hand, truth), as :meth:`Policy.act` takes them."""
        sim, ep = self.sim, self.ep
        self.state = state = sim.robot.state()
        truth = (sim.get_pose(ep.object)[0], ep.xy(ep.target)) if self.true_positions else None
        return (observe(sim, step, self.video), np.asarray(state.joints, dtype=np.float32),
                np.asarray(state.ee_pos), truth)

    def apply(self, action: np.ndarray) -> bool:
        """Execute ``action``; False (and the episode is over, a failure) if it is not finite."""
        sim, ep = self.sim, self.ep
        self.steps += 1
        if not np.all(np.isfinite(action)):
            self.diverged = True
            return False
        sim.robot.act(action)
        if action[3] != 0:
            self.gripper_closed = action[3] > 0
        self.reach = self.reach or sim.robot.touching(ep.object)
        if not self.pick and self.gripper_closed and sim.robot.touching(ep.object, "fingers"):
            bottom = sim.get_pose(ep.object)[0][2] - S.object_half_height(ep.object) - S.TABLE_Z
            self.pick = bottom > LIFTED
        return True

    def result(self, seconds: float) -> dict[str, Any]:
        sim, ep = self.sim, self.ep
        final_xy = sim.get_pose(ep.object)[0][:2]
        return {"reach": bool(self.reach), "pick": bool(self.pick),
                "success": bool((not self.diverged) and on_target(ep, sim)), "diverged": self.diverged,
                "steps": self.steps, "seconds": seconds,
                # how far the object is from its target's centre (m), at the start and at the end
                "start_distance": float(np.linalg.norm(ep.xy(ep.object) - ep.xy(ep.target))),
                "final_distance": float(np.linalg.norm(final_xy - ep.xy(ep.target))),
                "final_xy": [round(float(v), 4) for v in final_xy]}  # where the object ended (m)


def run_episode(sim, ep: S.Episode, policy: Policy, target_rgb: np.ndarray | None, steps: int, resolution: int,
                on_step=None, true_positions: bool = False) -> dict[str, Any]:
    """One closed-loop episode (:class:`ClosedLoop`); ``on_step(t, rgb, action, policy)`` sees each step.
    ``policy`` has :class:`Policy`'s ``reset(target_rgb)`` and ``act(rgb, joints, hand, truth)``."""
    loop = ClosedLoop(sim, ep, policy, target_rgb, resolution, true_positions)
    t0 = time.perf_counter()
    for step in range(steps):
        observation = loop.observe(step)
        action = policy.act(*observation)
        if on_step is not None:
            on_step(step, observation[0], action, policy)
        if not loop.apply(action):
            break
    return loop.result(time.perf_counter() - t0)


def sims_for(sims: list, make_sim, episodes: list[S.Episode], resolution: int) -> list:
    """The first ``len(episodes)`` of ``sims``, made with ``make_sim(scene)`` where there are fewer."""
    while len(sims) < len(episodes):
        sims.append(make_sim(S.build_scene(episodes[len(sims)], resolution)))
    return sims[:len(episodes)]


def run_episodes(sims: list, episodes: list[S.Episode], policies: list[Policy], targets: list, steps: int,
                 resolution: int, true_positions: bool = False) -> list[dict[str, Any]]:
    """Episodes side by side, one simulation and one policy (of one model) each, stepped in lockstep
    so that their frames go through the network as one batch (:func:`act_together`); the results of
    :func:`run_episode`, each episode's ``seconds`` its share of the wall time."""
    loops = [ClosedLoop(*args, resolution, true_positions)
             for args in zip(sims, episodes, policies, targets, strict=True)]
    live = list(range(len(loops)))
    t0 = time.perf_counter()
    for step in range(steps):
        if not live:
            break
        actions = act_together([policies[i] for i in live], [loops[i].observe(step) for i in live])
        live = [i for i, action in zip(live, actions) if loops[i].apply(action)]
    seconds = (time.perf_counter() - t0) / max(1, len(loops))
    return [loop.result(seconds) for loop in loops]
