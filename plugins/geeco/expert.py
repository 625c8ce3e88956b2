"""The scripted expert that records GEECO's demonstrations (thesis Section 6.4, "pre-computed plan").

It sees the simulator's true state (privileged) and follows the object as it moves:

* pick-and-place: approach above the object, descend, grasp, lift, carry above the target,
  lower, release, retreat;
* pushing: close the fingers, go behind the cube on the line through cube and target, push
  along that line, steering onto the line through the cube's current centre; a cube that slid
  out of reach gets another push from behind it. Pushing is a feedback law on the current
  state (:meth:`Expert._push`), so the demonstrations show one consistent response per state.

Plans run on the commanded hand position (the robot's goal in ``goal_mode="desired"``); where
contact matters (grasping, placing, starting a push) a phase also waits for the hand to catch up.
Every plan ends with the hand parked at ``REST_EE``, out of the way, so the demonstration's last
frame is a clean target image. Commands are end-effector displacements of at most ``SPEED`` per
step and a gripper command in {-1 open, 0 no-op, +1 close}.
"""

from __future__ import annotations

import numpy as np

from .scenes import (CUBE, CUP_HEIGHT, CONE_HEIGHT, NUT_RADIUS, NUT_WALL, REST_EE, TABLE_Z, Episode,
                     object_half_height, push_start, target_top)

SPEED = 0.03  # m per control step in free space (0.75 m/s at 25 Hz)
SLOW = 0.015  # near objects
PUSH_SPEED = 0.015
PUSH_HOVER = 0.075  # the hand flies to the start of a push at this height
PUSH_CLEAR = 0.1  # after pushing, the hand rises this high before it leaves
PUSH_DONE = 0.03  # the push ends with the cube's centre this close to the target's
PUSH_CORRIDOR = 0.03  # a hand this far beside the line through the cube's centre keeps pushing
PUSH_STEER = 0.2  # lateral gain: m of sideways hand motion per m the hand is beside that line, a step
PUSH_STEER_MAX = 0.006  # m: at most this much sideways a step
PUSH_HEIGHT = 0.017  # the hand (between the fingertips) while pushing: low on the cube, so it slides, not tips
HOVER = 0.13  # carrying height above the table
HAND_TOLERANCE = 0.012  # a phase ends when the hand is this close to where it was sent
HAND_REACH = 0.03  # pushing: the hand is over the start when this close (some backends hold it ~1.5 cm short at the far edge)
GRIP_SETTLED = 0.001  # m per step: the fingers have closed on the object when their opening changes less
GRASP_STEPS = 20  # at most this many steps closing the fingers
OPEN, NOOP, CLOSE = -1, 0, 1
SETTLING = ("grasp", "release", "retreat", "rest")  # phases the demonstration noise leaves alone


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
        self.phase = "push" if ep.skill == "push" else "above"
        self.steps_in_phase = 0
        self.done = False
        self.goal: np.ndarray | None = None  # where the commands so far put the hand (robot goal_mode "desired")
        self._arrived = 0
        self._opening: float | None = None  # the fingers' opening at the last grasp step

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

    def perturb(self, action: np.ndarray, noise: np.ndarray) -> np.ndarray:
        """``action`` with ``noise`` (m) added to its displacement, the plan following the perturbed
        hand; unchanged while the hand holds still (grasping, releasing) or leaves for its rest, so
        the target image stays clean. Recording the unperturbed commands in states the noise led to
        shows a learner how to recover from its own errors (DART, Laskey et al. 2017)."""
        if self.done or self.phase in SETTLING or not np.any(action[:3]):
            return action
        executed = np.array([*(action[:3] + noise), action[3]], dtype=float)
        self.follow(action, executed)
        return executed

    def follow(self, commanded: np.ndarray, executed: np.ndarray) -> None:
        """The robot executed ``executed`` instead of this expert's last command ``commanded``
        (a controller drove it, DAgger): the plan follows the hand that was actually sent."""
        self.goal = self.goal + (np.asarray(executed[:3], dtype=float) - np.asarray(commanded[:3], dtype=float))

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
        if self.phase == "grasp":  # close until the fingers stop on the object (robosuite's close slower)
            opening = sim.robot.state().gripper_opening
            closed = self._opening is not None and abs(opening - self._opening) < GRIP_SETTLED
            self._opening = opening
            if (self.steps_in_phase >= 5 and closed) or self.steps_in_phase >= GRASP_STEPS:
                self._opening = None
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
    def _push(self, sim, at: np.ndarray) -> tuple[np.ndarray, int]:
        """Pushing as a feedback law on what the camera shows (the hand, the cube, the target): the
        command depends on the current state alone, not on a plan made earlier, so a controller
        imitating it can recover from where it went astray. With d the unit vector from the cube's
        centre to the target's:

        * cube within ``PUSH_DONE`` of the target: rise, then park the hand;
        * hand low behind the cube, near the line through its centre along d: push along d,
          steering back onto that line and slowing down as the cube nears the target;
        * hand above the start point behind the cube: descend to pushing height;
        * hand low anywhere else: rise; high: fly over to above the start point.
        """
        ep = self.ep
        cube = sim.get_pose(ep.object)[0][:2]
        tgt = ep.xy(ep.target)
        grip = CLOSE if self.steps_in_phase < 3 else NOOP  # close the fingers on the way: they push as one flat tip
        remaining = float(np.linalg.norm(tgt - cube))
        if remaining < PUSH_DONE or self.phase == "rest":
            self.phase = "rest"  # the cube stays put once the hand has left it
            if at[2] < TABLE_Z + PUSH_CLEAR:
                return _toward(at, [at[0], at[1], TABLE_Z + PUSH_CLEAR + 0.02], SPEED), grip
            return self._rest(at)[0], grip
        d = (tgt - cube) / remaining
        normal = np.array([-d[1], d[0]])
        start = push_start(cube, tgt)
        height = TABLE_Z + PUSH_HEIGHT
        along, across = float((self.hand[:2] - cube) @ d), float((self.hand[:2] - cube) @ normal)
        low = self.hand[2] < height + 0.015
        if low and -(CUBE / 2 + 0.065) < along < -CUBE / 2 + 0.012 and abs(across) < PUSH_CORRIDOR:
            speed = min(PUSH_SPEED, max(0.004, 0.5 * remaining))
            lateral = -np.clip(PUSH_STEER * across, -PUSH_STEER_MAX, PUSH_STEER_MAX)  # steer the hand back onto the line
            xy = speed * d + lateral * normal
            return np.array([xy[0], xy[1], np.clip(height - at[2], -SLOW, SLOW)]), grip
        above_start = np.linalg.norm(at[:2] - start) < 0.01 and np.linalg.norm(self.hand[:2] - start) < HAND_REACH
        if above_start:
            return _toward(at, [start[0], start[1], height], SLOW), grip
        if self.hand[2] < TABLE_Z + PUSH_HOVER - 0.015:
            return _toward(at, [at[0], at[1], TABLE_Z + PUSH_HOVER], SPEED), grip
        return _toward(at, [start[0], start[1], TABLE_Z + PUSH_HOVER], SPEED), grip
