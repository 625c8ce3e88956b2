"""Closed-loop control with a trained GEECO controller (thesis Sections 6.3 and 6.4).

:class:`Policy` keeps the observation buffer of the last K (frame, joint angles) pairs, padded
on the left with copies of the oldest at the start of an episode (Appendix 6.A), and turns the
network's outputs back into robot commands. :func:`run_episode` runs one episode and scores it
the thesis's way:

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

    def __init__(self, model, device: str = "cpu"):
        self.model = model.eval().to(device)
        self.device = device
        self.buffer: deque = deque(maxlen=model.buffer)
        self.positions: deque = deque(maxlen=model.buffer)  # command="positions": (hand, object) per step
        self.target = None
        self.last: dict[str, Any] = {}

    def reset(self, target_rgb: np.ndarray | None) -> None:
        self.buffer.clear()
        self.positions.clear()
        self.target = None if target_rgb is None else to_tensor_frames(target_rgb)[None].to(self.device)

    def act(self, rgb: np.ndarray, joints: np.ndarray, hand: np.ndarray | None = None,
            truth: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """The next robot action ``(dx, dy, dz, gripper)``; NaN where the network diverged.

        ``hand``: the hand's measured position (proprioception, m), which a ``command="positions"``
        controller takes with its estimates of the object's and the target's (without it, its own
        estimate of the hand's); ``truth``: the object's true position (3) and the target's (2), m,
        to use instead of those estimates (``eval.positions=true``)."""
        import torch

        frame = to_tensor_frames(rgb)[None, None].to(self.device)  # (1, 1, 3, S, S)
        x = torch.as_tensor(joints, dtype=torch.float32)[None, None].to(self.device)
        with torch.no_grad():
            # per-frame variants keep each frame's state: one new frame is encoded per step
            item = frame if self.model.variant == "geeco-f" else self.model.frame_states(frame, x, self.target)
            if not self.buffer:  # episode start: pad with copies of the oldest frame (the robot is at rest)
                self.buffer.extend([(frame, x, item)] * (self.buffer.maxlen - 1))
            self.buffer.append((frame, x, item))
            frames = torch.cat([f for f, _, _ in self.buffer], dim=1)
            if self.model.variant == "geeco-f":
                out = {k: v[:, -1] for k, v in self.model(frames, torch.cat([j for _, j, _ in self.buffer], dim=1),
                                                          self.target).items()}
            else:
                out = self.model.decide(torch.cat([s for _, _, s in self.buffer], dim=1))
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


def run_episode(sim, ep: S.Episode, policy: Policy, target_rgb: np.ndarray | None, steps: int, resolution: int,
                on_step=None, true_positions: bool = False) -> dict[str, Any]:
    """One closed-loop episode from ``ep``'s start state; ``on_step(t, rgb, action, policy)`` sees each step.
    ``policy`` has :class:`Policy`'s ``reset(target_rgb)`` and ``act(rgb, joints, hand, truth)``.
    ``true_positions``: a ``command="positions"`` controller gets the simulator's object and target
    positions instead of its network's estimates."""
    sim.reset(S.build_scene(ep, resolution))
    policy.reset(target_rgb)
    reach = pick = diverged = False
    gripper_closed = False
    t0 = time.perf_counter()
    step = 0
    video = S.background_video(ep)
    for step in range(steps):
        rgb = observe(sim, step, video)
        state = sim.robot.state()
        truth = (sim.get_pose(ep.object)[0], ep.xy(ep.target)) if true_positions else None
        action = policy.act(rgb, np.asarray(state.joints, dtype=np.float32), np.asarray(state.ee_pos), truth)
        if on_step is not None:
            on_step(step, rgb, action, policy)
        if not np.all(np.isfinite(action)):
            diverged = True
            break
        state = sim.robot.act(action)
        if action[3] != 0:
            gripper_closed = action[3] > 0
        reach = reach or sim.robot.touching(ep.object)
        if not pick and gripper_closed and sim.robot.touching(ep.object, "fingers"):
            bottom = sim.get_pose(ep.object)[0][2] - S.object_half_height(ep.object) - S.TABLE_Z
            pick = bottom > LIFTED
    seconds = time.perf_counter() - t0
    success = (not diverged) and on_target(ep, sim)
    final_xy = sim.get_pose(ep.object)[0][:2]
    return {"reach": bool(reach), "pick": bool(pick), "success": bool(success), "diverged": diverged,
            "steps": step + 1, "seconds": seconds,
            # how far the object is from its target's centre (m), at the start and at the end
            "start_distance": float(np.linalg.norm(ep.xy(ep.object) - ep.xy(ep.target))),
            "final_distance": float(np.linalg.norm(final_xy - ep.xy(ep.target))),
            "final_xy": [round(float(v), 4) for v in final_xy]}  # where the object ended (m)
