"""The one episode loop: everything that steps a GEECO scene, with the expert or a controller
(thesis Sections 6.3 and 6.4): the expert's demonstrations (``dataset.record``) and target images
(``control.expert_target``), closed-loop control alone and side by side (``control.run_episode``,
``control.run_episodes``) and DAgger's rollouts (``dagger.rollouts``).

:func:`run` steps episodes side by side in lockstep, one :class:`Rollout` (a live simulation
from an episode's start state) each. At each step t, for the episodes still running:

1. observe: the robot's state, the camera frame (its background replaced by the episode's video)
   and, with ``true_positions``, the object's and the target's true positions; an episode that
   does not ``see`` (the expert driving alone: it reads the simulator) renders nothing;
2. label: the expert's command u_dEE, u_GRP in the state reached (an episode with an ``expert``);
3. record: the frame I_t, the joint angles x_t, q_EE, q_OBJ and that command (an episode that
   ``record``\\ s: the arrays of a demonstration);
4. act: ``act(rollouts, observations)`` decides who acts: :func:`expert_drives` (with the
   demonstrations' DART noise), the episodes' controllers (``control.controllers``, their frames
   through the network as one batch) or the two mixed (``dagger.mixed``, DAgger's beta);
5. ``on_step(t, rollout, observation, action)`` sees the step (deploy's video and recording);
6. execute the action (:meth:`Rollout.apply`). An episode stops where its action is not finite
   (a diverging controller: ``diverged``), the others go on; all stop after ``steps`` steps.

:class:`ClosedLoop` is a rollout driven by a controller and scored as it runs: REACH, PICK and at
the end PUSH / PLACE (``control.py`` says how).
"""

from __future__ import annotations

import time
from typing import Any, Callable

import numpy as np

from . import scenes as S
from .expert import Expert, on_target

GRIP_CLASS = {-1: 0, 0: 1, 1: 2}  # gripper command -> class id (open, no-op, close)
LIFTED = 0.02  # PICK: the object's bottom at least this far off the table


def observe(sim, step: int, video=None) -> np.ndarray:
    """The camera frame at ``step``, its background replaced by ``video`` if one is given
    (``S.background_video``: BG:PRISMA's rainbow, or a demonstration's random background)."""
    if video is None:
        return sim.render("front").rgb
    frame = sim.render("front", segmentation=True)
    return S.replace_background(frame.rgb, frame.segmentation, step, video)


def empty_episode(horizon: int, resolution: int) -> dict[str, np.ndarray]:
    """The per-step arrays of one recorded episode, zeroed."""
    return {"rgb": np.zeros((horizon, resolution, resolution, 3), np.uint8),
            "joints": np.zeros((horizon, 7), np.float32), "ee": np.zeros((horizon, 3), np.float32),
            "obj": np.zeros((horizon, 3), np.float32), "dee": np.zeros((horizon, 3), np.float32),
            "grip": np.zeros(horizon, np.int8)}


def record_step(out: dict[str, np.ndarray], t: int, sim, ep: S.Episode, state, rgb: np.ndarray,
                command: np.ndarray) -> None:
    """Step ``t``: the frame, the robot's state and object position, and the expert's ``command``."""
    out["rgb"][t], out["joints"][t], out["ee"][t] = rgb, state.joints, state.ee_pos
    out["obj"][t] = sim.get_pose(ep.object)[0]
    out["dee"][t], out["grip"][t] = command[:3], GRIP_CLASS[int(command[3])]


class Rollout:
    """One episode on the live ``sim`` from ``ep``'s start state: with ``resolution``, ``sim`` is
    reset to it first (without, the caller has). ``expert``: an :class:`Expert` labels every state
    reached (``command``; ``done_at``: the first step at which its plan was done); ``record`` (with an
    expert): the per-step arrays of that many steps are kept (``arrays``, labelled by it); ``see``: the
    camera renders each step; ``true_positions``: observations carry the object's and the target's
    true positions."""

    def __init__(self, sim, ep: S.Episode, resolution: int | None = None, *, expert: bool = False,
                 record: int = 0, see: bool = True, true_positions: bool = False):
        if resolution is not None:
            sim.reset(S.build_scene(ep, resolution))
        self.sim, self.ep, self.see, self.true_positions = sim, ep, see, true_positions
        self.video = S.background_video(ep)
        self.expert = Expert(ep) if expert else None
        self.arrays = empty_episode(record, sim.scene.camera("front").width) if record else None
        self.state = self.command = self.done_at = None
        self.steps = 0
        self.diverged = False

    def observe(self, step: int) -> tuple:
        """What a controller gets at ``step``: (rgb, joints, hand, truth), as ``Policy.act`` takes them."""
        sim, ep = self.sim, self.ep
        self.state = state = sim.robot.state()
        truth = (sim.get_pose(ep.object)[0], ep.xy(ep.target)) if self.true_positions else None
        return (observe(sim, step, self.video), np.asarray(state.joints, dtype=np.float32),
                np.asarray(state.ee_pos), truth)

    def label(self, step: int, rgb: np.ndarray | None) -> None:
        """The expert's command in the state reached (``command``), recorded with ``rgb`` and the state."""
        self.command = self.expert.act(self.sim)
        if self.expert.done and self.done_at is None:
            self.done_at = step
        if self.arrays is not None:
            record_step(self.arrays, step, self.sim, self.ep, self.state, rgb, self.command)

    def apply(self, action: np.ndarray) -> bool:
        """Execute ``action``; False (and the episode is over, a failure) if it is not finite."""
        self.steps += 1
        if not np.all(np.isfinite(action)):
            self.diverged = True
            return False
        self.sim.robot.act(action)
        return True


class ClosedLoop(Rollout):
    """A rollout driven by ``policy`` (reset to ``target_rgb``), scored as it runs: REACH, PICK, a
    diverged command, and at the end PUSH / PLACE (:meth:`result`). The options are a
    :class:`Rollout`'s."""

    def __init__(self, sim, ep: S.Episode, resolution: int | None, policy, target_rgb: np.ndarray | None,
                 **options: Any):
        super().__init__(sim, ep, resolution, **options)
        self.policy = policy
        policy.reset(target_rgb)
        self.reach = self.pick = self.gripper_closed = False

    def apply(self, action: np.ndarray) -> bool:
        if not super().apply(action):
            return False
        sim, ep = self.sim, self.ep
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


Act = Callable[[list, list], list]  # (the running rollouts, their observations) -> their actions


def run(rollouts: list[Rollout], steps: int, act: Act, on_step=None) -> float:
    """Step ``rollouts`` in lockstep for at most ``steps`` steps (the module's docstring says how);
    the wall time it took, in seconds."""
    live = list(rollouts)
    t0 = time.perf_counter()
    for step in range(steps):
        if not live:
            break
        observations = [r.observe(step) if r.see else None for r in live]
        for r, observation in zip(live, observations):
            if r.expert is not None:
                r.label(step, None if observation is None else observation[0])
        actions = act(live, observations)
        if on_step is not None:
            for r, observation, action in zip(live, observations, actions):
                on_step(step, r, observation, action)
        live = [r for r, action in zip(live, actions, strict=True) if r.apply(action)]
    return time.perf_counter() - t0


def expert_drives(noise: float = 0.0, rng: np.random.Generator | None = None) -> Act:
    """``act``: the expert's own commands; with ``noise`` > 0 the executed displacements are
    perturbed by N(0, noise^2) draws from ``rng`` (``Expert.perturb``, DART), the labels stay."""

    def act(rollouts: list[Rollout], observations: list) -> list[np.ndarray]:
        if noise <= 0:
            return [r.command for r in rollouts]
        return [r.expert.perturb(r.command, rng.normal(0.0, noise, 3)) for r in rollouts]

    return act
