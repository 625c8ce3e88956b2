"""The scripted expert that records GEECO's demonstrations (thesis Section 6.4, "pre-computed plan").

It sees the simulator's true state (privileged) and follows the object as it moves:

* pick-and-place: approach above the object, descend, grasp, lift, carry above the target,
  lower, release, retreat;
* pushing: close the fingers, go behind the cube on the line through cube and target, push
  along that line in a straight stroke; a cube left more than ``PUSH_TOLERANCE`` from the
  target's centre (it turned or slid sideways) gets another stroke from behind, three at most.

Plans run on the commanded hand position (the robot's goal in ``goal_mode="desired"``); where
contact matters (grasping, placing, starting a stroke, rising before moving over) a phase also
waits for the hand to catch up. Every plan ends with the hand parked at ``REST_EE``, out of the
way, so the demonstration's last frame is a clean target image. Commands are end-effector
displacements of at most ``SPEED`` per step and a gripper command in {-1 open, 0 no-op, +1 close}.
"""

from __future__ import annotations

import numpy as np

from .scenes import (CUBE, CUP_HEIGHT, CONE_HEIGHT, NUT_RADIUS, NUT_WALL, REST_EE, TABLE_Z, Episode,
                     object_half_height, push_start, target_top)

SPEED = 0.03  # m per control step in free space (0.75 m/s at 25 Hz)
SLOW = 0.015  # near objects
PUSH_SPEED = 0.015
PUSH_HOVER = 0.075  # the hand moves between strokes at this height
PUSH_TOLERANCE = 0.03  # a stroke leaving the cube's centre further from the target's is followed by another
PUSH_HEIGHT = 0.017  # the hand (between the fingertips) while pushing: low on the cube, so it slides, not tips
HOVER = 0.13  # carrying height above the table
HAND_TOLERANCE = 0.012  # a phase ends when the hand is this close to where it was sent
OPEN, NOOP, CLOSE = -1, 0, 1


def _toward(ee: np.ndarray, goal: np.ndarray, speed: float) -> np.ndarray:
    d = np.asarray(goal, dtype=float) - ee
    n = float(np.linalg.norm(d))
    return d if n <= speed else d / n * speed


def grasp_offset(name: str) -> np.ndarray:
    """Where the fingers close, relative to the object's centre (the nut is held by a wall)."""
    if name == "nut":
        return np.array([0.0, NUT_RADIUS * np.cos(np.pi / 6) - NUT_WALL / 2, 0.0])
    return np.zeros(3)


def on_target(ep: Episode, sim) -> bool:
    """Whether the episode's object rests on (in) its target: the PUSH / PLACE criterion."""
    obj, tgt = ep.object, ep.target
    p = sim.get_pose(obj)[0]
    t = ep.xy(tgt)
    rel = p[:2] - t
    z = p[2] - TABLE_Z
    if tgt.endswith("_pad"):
        from .scenes import PAD

        inside = bool(np.all(np.abs(rel) <= PAD / 2))  # the pad's axes are the world's
        surface = target_top(tgt, ep.skill) if ep.skill == "pickplace" else 0.0  # pushing pads are markings
        resting = abs(z - (surface + object_half_height(obj))) < 0.012
        return inside and resting
    if tgt == "cone":  # the nut is threaded over the cone, down near its base
        return bool(np.linalg.norm(rel) < 0.012 and z < CONE_HEIGHT * 0.6)
    if tgt == "cup":  # the ball is inside the cup
        from .scenes import CUP_RADIUS

        return bool(np.linalg.norm(rel) < CUP_RADIUS and z < CUP_HEIGHT)
    raise ValueError(tgt)


class Expert:
    """A closed-loop state machine: ``act(sim)`` returns the next ``(dx, dy, dz, gripper)``."""

    def __init__(self, ep: Episode):
        self.ep = ep
        self.phase = "close" if ep.skill == "push" else "above"
        self.steps_in_phase = 0
        self.done = False
        self.goal: np.ndarray | None = None  # where the commands so far put the hand (robot goal_mode "desired")
        self.stroke: tuple[np.ndarray, np.ndarray] | None = None  # pushing: (start, end) of the current stroke
        self.strokes = 0
        self._arrived = 0

    def _next(self, phase: str) -> None:
        self.phase, self.steps_in_phase = phase, 0

    def act(self, sim) -> np.ndarray:
        self.hand = np.asarray(sim.robot.state().ee_pos, dtype=float)
        if self.goal is None:
            self.goal = self.hand.copy()
        # plans run on the commanded position: the hand follows it a step or two behind
        move, grip = (self._push if self.ep.skill == "push" else self._pick_place)(sim, self.goal)
        self.goal = self.goal + move
        self.steps_in_phase += 1
        return np.array([*move, grip], dtype=float)

    def _rest(self, ee: np.ndarray) -> tuple[np.ndarray, int]:
        move = _toward(ee, REST_EE, SPEED)
        if np.linalg.norm(np.asarray(REST_EE) - ee) < 1e-6:
            self.done = True
        return move, NOOP

    def _go(self, at: np.ndarray, goal, speed: float, then: str, wait: int = -1) -> np.ndarray:
        """A step from ``at`` towards ``goal``; once there the phase becomes ``then`` (with ``wait`` >= 0:
        after ``wait`` more steps and the hand caught up with the goal)."""
        move = _toward(at, goal, speed)
        if np.linalg.norm(np.asarray(goal, dtype=float) - at - move) < 1e-6:
            self._arrived += 1
            # the hand lags its goal by a step or two (more on some backends): wait for it, within reason
            caught_up = wait < 0 or np.linalg.norm(self.hand - np.asarray(goal, dtype=float)) < HAND_TOLERANCE
            if (self._arrived > wait and caught_up) or self._arrived > wait + 6:
                self._arrived = 0
                self._next(then)
        return move

    # -- pick and place ---------------------------------------------------------------------------
    def _pick_place(self, sim, at: np.ndarray) -> tuple[np.ndarray, int]:
        ep = self.ep
        obj = sim.get_pose(ep.object)[0] + grasp_offset(ep.object)
        tgt = np.array([*ep.xy(ep.target), TABLE_Z]) + grasp_offset(ep.object)
        hover = TABLE_Z + HOVER
        if self.phase == "above":
            return self._go(at, [obj[0], obj[1], hover], SPEED, "descend"), OPEN
        if self.phase == "descend":  # wait two steps at the bottom for the hand to catch up
            return self._go(at, [obj[0], obj[1], obj[2] + 0.003], SLOW, "grasp", wait=1), OPEN
        if self.phase == "grasp":
            if self.steps_in_phase >= 5:
                self._next("lift")
            return np.zeros(3), CLOSE
        if self.phase == "lift":
            return self._go(at, [at[0], at[1], hover], SPEED, "carry"), NOOP
        if self.phase == "carry":
            return self._go(at, [tgt[0], tgt[1], hover], SPEED, "lower"), NOOP
        if self.phase == "lower":
            if ep.target == "cone":
                release = TABLE_Z + CONE_HEIGHT + 0.025
            elif ep.target == "cup":
                release = TABLE_Z + CUP_HEIGHT + 0.04
            else:
                release = TABLE_Z + target_top(ep.target, ep.skill) + object_half_height(ep.object) + 0.008
            return self._go(at, [tgt[0], tgt[1], release], SLOW, "release", wait=1), NOOP
        if self.phase == "release":
            if self.steps_in_phase >= 4:
                self._next("retreat")
            return np.zeros(3), OPEN
        if self.phase == "retreat":
            return self._go(at, [at[0], at[1], hover + 0.04], SPEED, "rest"), NOOP
        return self._rest(at)

    # -- pushing ----------------------------------------------------------------------------------
    def _plan_stroke(self, cube: np.ndarray, tgt: np.ndarray) -> None:
        """From behind the cube to where its centre reaches the target's."""
        direction = (tgt - cube) / max(np.linalg.norm(tgt - cube), 1e-9)
        # the stroke ends a little past where the fingers would leave the cube's centre on the target's:
        # the hand lags its goal and the fingertips' faces lie up to 1 cm ahead of the hand's point
        self.stroke = (push_start(cube, tgt), tgt - direction * (CUBE / 2 + 0.004))
        self.strokes += 1

    def _push(self, sim, at: np.ndarray) -> tuple[np.ndarray, int]:
        """Straight strokes through the cube's centre towards the target's; a stroke that leaves the
        cube short (it turned or slid sideways) is followed by another from behind it (at most three)."""
        ep = self.ep
        cube = sim.get_pose(ep.object)[0][:2]
        tgt = ep.xy(ep.target)
        height = TABLE_Z + PUSH_HEIGHT
        if self.stroke is None:
            self._plan_stroke(cube, tgt)
        start, end = self.stroke
        if self.phase == "close":  # close the fingers on the way: they push as one flat tip
            if self.steps_in_phase >= 3:
                self._next("above_start")
            return _toward(at, [start[0], start[1], TABLE_Z + PUSH_HOVER], SPEED), CLOSE
        if self.phase == "behind":
            return self._go(at, [at[0], at[1], TABLE_Z + PUSH_HOVER], SPEED, "above_start", wait=0), NOOP
        if self.phase == "above_start":
            return self._go(at, [start[0], start[1], TABLE_Z + PUSH_HOVER], SPEED, "down", wait=0), NOOP
        if self.phase == "down":
            return self._go(at, [start[0], start[1], height], SPEED, "push"), NOOP
        if self.phase == "push":
            return self._go(at, [end[0], end[1], height], PUSH_SPEED, "check", wait=0), NOOP
        if self.phase == "check":
            if np.linalg.norm(tgt - cube) > PUSH_TOLERANCE and self.strokes < 3:
                self._plan_stroke(cube, tgt)
                self._next("behind")
            else:
                self._next("retreat")
            return np.zeros(3), NOOP
        if self.phase == "retreat":
            return self._go(at, [at[0], at[1], TABLE_Z + 0.12], SPEED, "rest"), NOOP
        return self._rest(at)
