"""The Franka Panda of the MuJoCo backend: robosuite's packaged model driven like robosuite's OSC.

The arm (``robots/panda/robot.xml``) and the gripper (``grippers/panda_gripper.xml``) are read
from the installed robosuite package's assets (robosuite itself is never imported). The gripper
is mounted in the arm's ``right_hand`` body exactly as robosuite merges it (its root body keeps
its own quaternion), and the arm stands on a pedestal at ``robot.base_pos`` facing +x, next to a
table whose top is at ``robot.table_height``. Joint armature and friction loss are set the way
robosuite's ``RobotModel`` sets them.

Control (one action every ``1 / control_hz`` s) reproduces robosuite's ``OSC_POSITION``
controller: the end-effector goal moves by the clipped displacement and the gripper orientation
is held pointing down; every physics step the joint torques are (Khatib 1987)

    a   = [Kp (x_goal - x) - Kd ẋ ;  Kp e_ori(R_goal, R) - Kd ω]   (task-space acceleration)
    τ   = Jᵀ Λ a + qfrc_bias                                       (OSC + gravity/Coriolis)
    τ  += Nᵀ M (kp_null (q_home - q) - kd_null q̇)                  (posture in the nullspace)

with ``Λ = (J M⁻¹ Jᵀ)⁻¹`` and ``N = I - M⁻¹ Jᵀ Λ J``, Kp = ``robot.osc_kp`` (robosuite's default
150) and critical damping. Position and orientation share the full 6x6 Λ (robosuite's
``uncouple_pos_ori=False``): with robosuite's default separate 3x3 blocks the hand sways by a few
millimetres off the commanded line and overshoots; with the full Λ it follows the ideal
critically damped response. The fingers are robosuite's position actuators: -1 opens, +1 closes,
0 keeps the last command.
"""

from __future__ import annotations

import importlib.util
import os

import mujoco
from typing import Any

import numpy as np

from .base import Robot, RobotState, check_part
from .spec import GOAL_LEAD_STEPS, GRIPPER_CLOSE, GRIPPER_NOOP, GRIPPER_OPEN, SpecError, unknown_name, validate_action
from .spec import Robot as RobotSpec

PREFIX = "panda/"
GRIPPER_PREFIX = "gripper/"
ARM_JOINTS = [f"{PREFIX}joint{i}" for i in range(1, 8)]
FINGER_JOINTS = [f"{PREFIX}{GRIPPER_PREFIX}finger_joint1", f"{PREFIX}{GRIPPER_PREFIX}finger_joint2"]
EE_SITE = f"{PREFIX}{GRIPPER_PREFIX}grip_site"  # robosuite's end-effector point, between the fingertips
PALM_BODIES = [f"{PREFIX}{GRIPPER_PREFIX}right_gripper"]
FINGER_BODIES = [f"{PREFIX}{GRIPPER_PREFIX}{b}" for b in ("leftfinger", "rightfinger", "finger_joint1_tip",
                                                            "finger_joint2_tip")]
ROOT_BODY = f"{PREFIX}base"

HOME_QPOS = np.array([0.0, np.pi / 16.0, 0.0, -np.pi / 2.0 - np.pi / 3.0, 0.0, np.pi - 0.2, np.pi / 4])  # robosuite
# grip-site axes in the world when pointing down: x along +y, y along +x, z down (fingers close along y)
EE_DOWN = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
FINGER_OPEN = np.array([0.04, -0.04])  # finger joint targets (m); closed is (0, 0)
FINGER_CLOSED = np.array([0.0, 0.0])

PEDESTAL = (0.24, 0.24)  # robot pedestal footprint (m)
PEDESTAL_RGBA = (0.25, 0.25, 0.27, 1.0)
LINK_RGBA = (0.93, 0.93, 0.93, 1.0)  # collision meshes drawn as the Panda's white links
DARK_RGBA = (0.25, 0.25, 0.27, 1.0)  # fingers


def robosuite_assets() -> str:
    """Folder of robosuite's packaged model assets, found without importing robosuite."""
    spec = importlib.util.find_spec("robosuite")
    if spec is None or spec.origin is None:
        raise SpecError("the MuJoCo Panda needs robosuite's model files: pip install robosuite==1.5.1")
    return os.path.join(os.path.dirname(spec.origin), "models", "assets")


def _strip(spec: mujoco.MjSpec, visual: str) -> None:
    """Keep either the collision meshes (drawn as visuals) or robosuite's detailed visual meshes."""
    for geom in list(spec.geoms):
        is_visual = geom.contype == 0 and geom.conaffinity == 0 and geom.group == 1
        if visual == "collision":
            if is_visual:
                spec.delete(geom)
            else:
                geom.rgba = list(DARK_RGBA if "finger" in geom.name else LINK_RGBA)
                geom.material = ""
        elif not is_visual:
            geom.group = 3  # collision geoms stay, hidden from the default render groups
    if visual == "collision":
        used = {g.meshname for g in spec.geoms if g.type == mujoco.mjtGeom.mjGEOM_MESH}
        for mesh in list(spec.meshes):
            if mesh.name not in used:
                spec.delete(mesh)
        for mat in list(spec.materials):
            spec.delete(mat)
    for mat in spec.materials:  # no reflections (slow on Mesa)
        mat.reflectance = 0.0
    for site in spec.sites:  # robosuite's marker sites (grip point, axes) are not drawn
        site.group = 4


def add_panda(spec: mujoco.MjSpec, robot: RobotSpec, *, visual: str = "collision", friction: float = 0.8,
              solref: list[float] | None = None) -> tuple[list[str], str]:
    """Add the table, the pedestal and the Panda with its gripper to ``spec``.

    Returns the table's geom names and the robot's root body name.
    """
    assets = robosuite_assets()
    arm = mujoco.MjSpec.from_file(os.path.join(assets, "robots", "panda", "robot.xml"))
    gripper = mujoco.MjSpec.from_file(os.path.join(assets, "grippers", "panda_gripper.xml"))
    _strip(arm, visual)
    _strip(gripper, visual)
    for i, joint in enumerate(arm.joints):  # robosuite RobotModel defaults for the 7 arm joints
        joint.armature = 5.0 / (i + 1)  # reflected rotor inertia, stabilises torque control
        joint.frictionloss = 0.1
    for sensor in list(gripper.sensors):  # force/torque sensors are not used here
        gripper.delete(sensor)
    # mount the gripper like robosuite's merge into `right_hand`: its root keeps its own quat
    arm.body("right_hand").add_frame().attach_body(gripper.body("right_gripper"), GRIPPER_PREFIX, "")

    base_z = robot.table_height + robot.base_pos[2]
    if base_z > 1e-6:  # a pedestal from the ground up to the arm's base
        arm.body("base").add_geom(name="pedestal", type=mujoco.mjtGeom.mjGEOM_BOX, pos=[0, 0, -base_z / 2],
                                  size=[PEDESTAL[0] / 2, PEDESTAL[1] / 2, base_z / 2], rgba=list(PEDESTAL_RGBA))
    mount = spec.worldbody.add_frame(pos=[robot.base_pos[0], robot.base_pos[1], base_z])  # facing +x
    mount.attach_body(arm.body("base"), PREFIX, "")

    table_geoms = []
    if robot.table_height > 0:
        tx, ty = robot.table_size
        h = robot.table_height
        table = spec.worldbody.add_geom(name="env/table", type=mujoco.mjtGeom.mjGEOM_BOX, pos=[0, 0, h / 2],
                                        size=[tx / 2, ty / 2, h / 2], rgba=list(robot.table_rgba))
        table.friction = [friction, 0.005, 0.0001]
        if solref is not None:
            table.solref = solref
        table_geoms.append("env/table")
    return table_geoms, ROOT_BODY


def orientation_error(desired: np.ndarray, current: np.ndarray) -> np.ndarray:
    """Axis-angle-like error rotating ``current`` onto ``desired`` (robosuite's control_utils).

    robosuite sums ``0.5 * cross(c_i, d_i)`` over the columns; that sum is the axial vector of
    ``D Cᵀ - C Dᵀ``, computed here without three calls to ``np.cross``.
    """
    skew = desired @ current.T - current @ desired.T
    return 0.5 * np.array([skew[2, 1], skew[0, 2], skew[1, 0]])


def _inverse(matrix: np.ndarray) -> np.ndarray:
    """Inverse, or the pseudo-inverse where the matrix is singular (arm at a singularity)."""
    try:
        return np.linalg.inv(matrix)
    except np.linalg.LinAlgError:
        return np.linalg.pinv(matrix)


class PandaModel:
    """Indices of the Panda's joints, actuators, end-effector site and geoms in a compiled model."""

    def __init__(self, model: mujoco.MjModel):
        self.arm_joints = np.array([model.joint(n).id for n in ARM_JOINTS])
        self.qadr = model.jnt_qposadr[self.arm_joints]
        self.dofs = model.jnt_dofadr[self.arm_joints]
        self.finger_joints = np.array([model.joint(n).id for n in FINGER_JOINTS])
        self.finger_qadr = model.jnt_qposadr[self.finger_joints]
        self.finger_dofs = model.jnt_dofadr[self.finger_joints]
        joint_of_actuator = model.actuator_trnid[:, 0]
        self.arm_act = np.array([int(np.flatnonzero(joint_of_actuator == j)[0]) for j in self.arm_joints])
        self.finger_act = np.array([int(np.flatnonzero(joint_of_actuator == j)[0]) for j in self.finger_joints])
        self.torque_limit = model.actuator_ctrlrange[self.arm_act]
        self.limits = model.jnt_range[self.arm_joints]
        self.site = model.site(EE_SITE).id
        body_of = model.geom_bodyid
        self.palm_geoms = np.flatnonzero(np.isin(body_of, [model.body(b).id for b in PALM_BODIES]))
        self.finger_geoms = np.flatnonzero(np.isin(body_of, [model.body(b).id for b in FINGER_BODIES]))


class OperationalSpaceController:
    """robosuite's OSC_POSITION controller (fixed impedance, orientation held)."""

    def __init__(self, model: mujoco.MjModel, panda: PandaModel, kp: float = 150.0, damping_ratio: float = 1.0,
                 kp_null: float = 10.0):
        self.panda = panda
        self.kp, self.kd = kp, 2.0 * np.sqrt(kp) * damping_ratio  # critical damping
        self.kp_null, self.kd_null = kp_null, 2.0 * np.sqrt(kp_null)
        self.goal_pos = np.zeros(3)
        self.goal_rot = EE_DOWN.copy()
        self.posture = HOME_QPOS.copy()
        self._jac = np.zeros((6, model.nv))  # rows: translational, rotational Jacobian of the site
        self._mass = np.zeros((model.nv, model.nv))
        self._q = _as_slice(panda.qadr)
        self._dof = _as_slice(panda.dofs)
        self._block = np.ix_(panda.dofs, panda.dofs) if isinstance(self._dof, np.ndarray) else (self._dof,) * 2
        self._lo, self._hi = panda.torque_limit[:, 0].copy(), panda.torque_limit[:, 1].copy()

    def __call__(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        """Write the arm torques for the current state into ``data.ctrl`` (called after mj_step1)."""
        p = self.panda
        mujoco.mj_jacSite(model, data, self._jac[:3], self._jac[3:], p.site)
        jac = self._jac[:, self._dof]
        mujoco.mj_fullM(model, self._mass, data.qM)
        mass = self._mass[self._block]  # joint-space inertia M of the arm (armature included)
        jm = jac @ np.linalg.inv(mass)  # J M⁻¹
        lam = _inverse(jm @ jac.T)  # operational-space inertia Λ = (J M⁻¹ Jᵀ)⁻¹
        q, qd = data.qpos[self._q], data.qvel[self._dof]
        # desired end-effector acceleration: a spring-damper towards the goal pose
        err = np.empty(6)
        err[:3] = self.goal_pos - data.site_xpos[p.site]
        err[3:] = orientation_error(self.goal_rot, data.site_xmat[p.site].reshape(3, 3))
        accel = self.kp * err - self.kd * (jac @ qd)
        # posture torques M (kp_null (q_home - q) - kd_null q̇), to be projected into the nullspace
        posture = mass @ (self.kp_null * (self.posture - q) - self.kd_null * qd)
        # τ = Jᵀ Λ a + Nᵀ posture + bias, with Nᵀ = I - Jᵀ Λ J M⁻¹ (dynamically consistent nullspace)
        tau = jac.T @ (lam @ (accel - jm @ posture)) + posture + data.qfrc_bias[self._dof]
        data.ctrl[p.arm_act] = np.minimum(np.maximum(tau, self._lo), self._hi)  # actuator torque limits


def _as_slice(index: np.ndarray):
    """A slice for consecutive indices (fast numpy views), else the index array itself."""
    index = np.asarray(index)
    if np.array_equal(index, np.arange(index[0], index[0] + len(index))):
        return slice(int(index[0]), int(index[-1]) + 1)
    return index


_IK_CACHE: dict[tuple, np.ndarray] = {}  # (base_pos, table_height, init_ee_pos) -> arm joint angles


def solve_ik(model: mujoco.MjModel, data: mujoco.MjData, panda: PandaModel, target: np.ndarray,
             rot: np.ndarray = EE_DOWN, q0: np.ndarray = HOME_QPOS, iters: int = 300) -> tuple[np.ndarray, float]:
    """Arm joint angles putting the end effector at ``target`` with orientation ``rot``.

    Damped least squares on the site Jacobian from ``q0``, clamped to the joint limits. Writes
    the arm qpos of ``data`` (call before setting the final state). Returns ``(q, residual m)``.
    """
    jacp, jacr = np.zeros((3, model.nv)), np.zeros((3, model.nv))
    q = q0.copy()
    damping = 1e-2
    err_norm = np.inf
    for _ in range(iters):
        data.qpos[panda.qadr] = q
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        x = data.site_xpos[panda.site]
        r = data.site_xmat[panda.site].reshape(3, 3)
        err = np.concatenate([target - x, orientation_error(rot, r)])
        err_norm = float(np.linalg.norm(err))
        if err_norm < 1e-7:
            break
        mujoco.mj_jacSite(model, data, jacp, jacr, panda.site)
        jac = np.vstack([jacp[:, panda.dofs], jacr[:, panda.dofs]])
        # Δq = Jᵀ (J Jᵀ + λ² I)⁻¹ e, plus a small pull towards the home posture in the nullspace
        jjt = jac @ jac.T + damping ** 2 * np.eye(6)
        dq = jac.T @ np.linalg.solve(jjt, err)
        null = np.eye(7) - jac.T @ np.linalg.solve(jjt, jac)
        dq += 0.1 * null @ (q0 - q)
        q = np.clip(q + dq, panda.limits[:, 0], panda.limits[:, 1])
    data.qpos[panda.qadr] = q
    mujoco.mj_kinematics(model, data)
    return q, float(np.linalg.norm(target - data.site_xpos[panda.site]))


class PandaSensing(Robot):
    """What a Panda in a MuJoCo model senses, for any controller driving it.

    Subclasses set ``world`` (a MujocoWorld), ``panda`` (joint, finger and site indices),
    ``parts`` (robot part -> geom ids) and ``body_names`` (the scene's bodies).
    """

    world: Any
    panda: Any
    parts: dict[str, np.ndarray]
    body_names: list[str]

    def state(self) -> RobotState:
        self.world.forward()
        d, p = self.world.data, self.panda
        fingers = d.qpos[p.finger_qadr]
        return RobotState(
            joints=d.qpos[p.qadr].copy(),
            ee_pos=d.site_xpos[p.site].copy(),
            gripper_opening=float(fingers[0] - fingers[1]),  # pad gap: finger 1 opens +, finger 2 opens -
            contacts={part: self._touched(part) for part in self.parts},
        )

    def touching(self, body: str, part: str = "any") -> bool:
        check_part(part)
        if body not in ("table", "ground") and body not in self.body_names:
            raise unknown_name("body", body, self.body_names)
        return body in self._touched(part)

    def _touched(self, part: str) -> list[str]:
        return self.world.touching(self.parts[part], exclude=("robot",))


class MujocoPanda(PandaSensing):
    """The Panda of a :class:`~physint_backends.mujoco_backend.MujocoSimulation`.

    ``goal_update_mode`` follows robosuite's OSC: ``"achieved"`` (default) adds each
    displacement to where the hand is now, so closed-loop commands like ``clip(target - ee)``
    converge without overshoot; ``"desired"`` adds it to the previous goal, for open-loop
    sequences of displacements (a closed loop then integrates the tracking lag and overshoots).
    """

    def __init__(self, world, spec: RobotSpec, body_names: list[str], goal_update_mode: str = "achieved"):
        """Drive the Panda of ``world`` (a MujocoWorld); ``body_names`` are the scene's bodies."""
        if goal_update_mode not in ("achieved", "desired"):
            raise SpecError(f"goal_update_mode {goal_update_mode!r} is not supported; allowed: achieved, desired")
        self.goal_update_mode = goal_update_mode
        self.spec = spec
        self.world = world
        self.body_names = list(body_names)
        model = world.model
        self.panda = PandaModel(model)
        self.controller = OperationalSpaceController(model, self.panda, kp=spec.osc_kp)
        self.substeps = max(1, int(round(self.control_dt / model.opt.timestep)))  # physics steps per action
        world.controllers.append(self.controller)
        robot_geoms = np.flatnonzero(np.asarray(world.geom_owner) == "robot")
        self.parts = {"fingers": self.panda.finger_geoms, "palm": self.panda.palm_geoms, "any": robot_geoms}
        self.grip_command = GRIPPER_OPEN
        self._home: np.ndarray | None = None
        self.reset()

    def reset(self) -> None:
        """Arm at the IK solution for ``init_ee_pos`` pointing down, fingers open, at rest."""
        m, d, p = self.world.model, self.world.data, self.panda
        key = (tuple(self.spec.base_pos), self.spec.table_height, tuple(self.spec.init_ee_pos))
        if key not in _IK_CACHE:
            q, residual = solve_ik(m, d, p, np.asarray(self.spec.init_ee_pos))
            if residual > 0.005:
                raise SpecError(f"robot init_ee_pos {list(self.spec.init_ee_pos)} is out of the Panda's reach "
                                f"from base_pos {list(self.spec.base_pos)} (closest: {residual:.3f} m away)")
            if len(_IK_CACHE) > 256:
                _IK_CACHE.clear()
            _IK_CACHE[key] = q
        self._home = _IK_CACHE[key].copy()
        d.qpos[p.qadr] = self._home
        d.qvel[p.dofs] = 0.0
        d.qpos[p.finger_qadr] = FINGER_OPEN
        d.qvel[p.finger_dofs] = 0.0
        self.grip_command = GRIPPER_OPEN
        d.ctrl[p.finger_act] = FINGER_OPEN
        d.ctrl[p.arm_act] = 0.0
        self.world.invalidate()
        self.world.forward()
        self.controller.posture = self._home.copy()
        self.controller.goal_pos = d.site_xpos[p.site].copy()
        self.controller.goal_rot = EE_DOWN.copy()

    # -- Robot interface ------------------------------------------------------------------------
    def act(self, action) -> RobotState:
        a = validate_action(action)  # raises SpecError before anything moves
        delta = np.clip(a[:3], -self.spec.max_delta, self.spec.max_delta)
        if self.goal_update_mode == "achieved":  # robosuite's default: from where the hand is now
            self.world.forward()
            self.controller.goal_pos = self.world.data.site_xpos[self.panda.site] + delta
        else:  # "desired": from the previous goal, so a sequence of deltas is followed without drift,
            # but never more than GOAL_LEAD_STEPS displacements ahead of the hand (pressing on the table)
            self.world.forward()
            hand = self.world.data.site_xpos[self.panda.site]
            lead = GOAL_LEAD_STEPS * self.spec.max_delta
            self.controller.goal_pos = hand + np.clip(self.controller.goal_pos + delta - hand, -lead, lead)
        if a[3] != GRIPPER_NOOP:
            self.grip_command = int(a[3])
            self.world.data.ctrl[self.panda.finger_act] = FINGER_CLOSED if a[3] == GRIPPER_CLOSE else FINGER_OPEN
        self.world.step(self.substeps)
        return self.state()
