"""The Franka Panda of the PyBullet backend, driven by end-effector displacements.

The arm is ``franka_panda/panda.urdf`` from ``pybullet_data`` with a fixed base on a pedestal
beside a table. An action ``(dx, dy, dz, gripper)`` moves a target point (the grasp point between
the fingertips, the URDF's ``panda_grasptarget`` link) by the clipped displacement, with the hand
always pointing straight down; inverse kinematics (damped least squares with a null-space pull
towards a ready pose) turns the target into joint angles that position-controlled motors track
for one control period. The fingers close with a limited force, so a grasped object is held by
friction rather than by a weld.
"""

from __future__ import annotations

import math
import os

import numpy as np
import pybullet
import pybullet_data

from .base import Robot, RobotState, check_part
from .poses import compose, invert
from .spec import GOAL_LEAD_STEPS, GRIPPER_CLOSE, GRIPPER_OPEN
from .spec import Robot as RobotSpec
from .spec import validate_action

PANDA_URDF = os.path.join(pybullet_data.getDataPath(), "franka_panda", "panda.urdf")
ARM_JOINTS = [f"panda_joint{i}" for i in range(1, 8)]
FINGER_JOINTS = ["panda_finger_joint1", "panda_finger_joint2"]
EE_LINK = "panda_grasptarget"  # 0.105 m down the hand axis: between the fingertips
PALM_LINK = "panda_hand"
FINGER_LINKS = ["panda_leftfinger", "panda_rightfinger"]

READY_POSE = [0.0, -math.pi / 4, 0.0, -3 * math.pi / 4, 0.0, math.pi / 2, math.pi / 4]  # hand down, fingers along y
DOWN_XYZW = (1.0, 0.0, 0.0, 0.0)  # hand z axis pointing at the floor, fingers closing along world y
ARM_FORCES = [87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0]  # joint torque limits from the datasheet (N m)
ARM_POSITION_GAIN = 0.05  # motor stiffness: the motors aim to close 5% of the joint error per physics step
FINGER_OPEN = 0.04  # each finger's travel (m): 8 cm between open fingers
FINGER_FORCE = 20.0  # grip force per finger (N): holds a few hundred grams by friction, never crushes
FINGER_COUPLING_FORCE = 50.0  # N: the gear keeping both fingers at the same travel
FINGER_FRICTION = 1.0  # sliding friction of the rubber finger pads
LINK_FRICTION = 0.5  # sliding friction of the rest of the arm
PEDESTAL_RGBA = (0.25, 0.25, 0.28, 1.0)
PEDESTAL_SIZE = 0.24  # edge of the square pedestal under the arm's base (m)
IK_ITERATIONS = 100
IK_TOLERANCE = 1e-6  # m
IK_DAMPING = 1e-3  # damped least squares: small, for an exact solution away from singularities


class PybulletPanda(Robot):
    """A Panda arm in a :class:`~physint_backends.pybullet_backend.PybulletSimulation`."""

    def __init__(self, sim, spec: RobotSpec):
        self.spec = spec
        self._sim = sim
        self._p = sim._p
        self._cid = sim._cid
        self.table_uid, self.mount_uid = self._add_fixtures()
        self.arm = self._load_arm()
        self.uids = [u for u in (self.arm, self.table_uid, self.mount_uid) if u is not None]  # all drawn as robot
        self._substeps = max(1, int(round(self.control_dt / sim.scene.timestep)))
        self._gripper_target = FINGER_OPEN
        self._init_pose()

    # -- building ------------------------------------------------------------------------------
    def _add_fixtures(self) -> tuple[int | None, int | None]:
        """A static table (top at ``table_height``) and, when the base is off the table, a pedestal."""
        spec, p = self.spec, self._p
        h = spec.table_height
        if h <= 0:
            return None, None
        friction = math.sqrt(self._sim.scene.ground.friction if self._sim.scene.ground else 0.8)

        def box(size, centre, rgba):
            half = [s / 2 for s in size]
            col = p.createCollisionShape(pybullet.GEOM_BOX, halfExtents=half)
            vis = p.createVisualShape(pybullet.GEOM_BOX, halfExtents=half, rgbaColor=list(rgba))
            uid = p.createMultiBody(0.0, col, vis, list(centre))
            p.changeDynamics(uid, -1, lateralFriction=friction, frictionAnchor=1)
            return uid

        tx, ty = spec.table_size
        table = box((tx, ty, h), (0.0, 0.0, h / 2), spec.table_rgba)
        bx, by, _ = spec.base_pos
        mount = None
        if abs(bx) > tx / 2 or abs(by) > ty / 2:  # base beside the table: stand it on a pedestal
            mount = box((PEDESTAL_SIZE, PEDESTAL_SIZE, h), (bx, by, h / 2), PEDESTAL_RGBA)
        return table, mount

    def _load_arm(self) -> int:
        """Load the URDF on the table top (z of ``base_pos`` is above it), facing +x."""
        p, spec = self._p, self.spec
        base = [spec.base_pos[0], spec.base_pos[1], spec.table_height + spec.base_pos[2]]
        arm = p.loadURDF(self._urdf(), base, [0, 0, 0, 1], useFixedBase=True,
                         flags=pybullet.URDF_ENABLE_CACHED_GRAPHICS_SHAPES)
        joints = {}
        for j in range(p.getNumJoints(arm)):
            info = p.getJointInfo(arm, j)
            joints[info[1].decode()] = j  # joint name -> index; link j is the joint's child
            joints["link:" + info[12].decode()] = j
        self._arm_joints = [joints[n] for n in ARM_JOINTS]
        self._finger_joints = [joints[n] for n in FINGER_JOINTS]
        self._ee_link = joints["link:" + EE_LINK]
        self._palm_link = joints["link:" + PALM_LINK]
        self._finger_links = [joints["link:" + n] for n in FINGER_LINKS]
        # links with collision shapes, apart from the base; the grasp-target link has none
        self._contact_links = [j for j in range(p.getNumJoints(arm)) if p.getCollisionShapeData(arm, j)]
        base = p.getBasePositionAndOrientation(arm)
        self._base_inv = invert(base[0], base[1])  # world -> the base frame Bullet's IK uses
        self._movable = [j for j in range(p.getNumJoints(arm)) if p.getJointInfo(arm, j)[2] != pybullet.JOINT_FIXED]
        info = [p.getJointInfo(arm, j) for j in self._movable]
        self._lower = [i[8] for i in info]
        self._upper = [i[9] for i in info]
        self._ranges = [u - lo for lo, u in zip(self._lower, self._upper)]
        self._rest = [*READY_POSE, FINGER_OPEN, FINGER_OPEN]
        for j in range(-1, p.getNumJoints(arm)):
            fingers = j in self._finger_links
            p.changeDynamics(arm, j, lateralFriction=math.sqrt(FINGER_FRICTION if fingers else LINK_FRICTION),
                             linearDamping=0.0, angularDamping=0.0)
        # the fingers are coupled like the real gripper's (the URDF's <mimic>, which Bullet
        # ignores): they move symmetrically, so a grasped object stays centred between them
        gear = p.createConstraint(arm, self._finger_joints[0], arm, self._finger_joints[1], pybullet.JOINT_GEAR,
                                  [1, 0, 0], [0, 0, 0], [0, 0, 0])
        p.changeConstraint(gear, gearRatio=-1, erp=0.1, maxForce=FINGER_COUPLING_FORCE)
        if self._sim.robot_visual == "collision":
            for j in self._finger_links:  # dark fingers, so the gripper reads in small images
                p.changeVisualShape(arm, j, rgbaColor=[0.2, 0.2, 0.2, 1.0])
        return arm

    def _urdf(self) -> str:
        """The Panda URDF; with ``robot_visual="collision"`` a copy drawing the low-poly collision meshes."""
        if self._sim.robot_visual == "full":
            return PANDA_URDF
        meshes = os.path.join(os.path.dirname(PANDA_URDF), "meshes") + os.sep

        def write(path: str) -> None:
            with open(PANDA_URDF) as fh:
                text = fh.read()
            text = text.replace("package://meshes/visual/", "package://meshes/collision/")
            text = text.replace("package://meshes/", meshes)  # absolute paths: the copy lives elsewhere
            with open(path, "w") as fh:
                fh.write(text)

        return self._sim._file(b"panda-collision-visuals:" + PANDA_URDF.encode(), ".urdf", write)

    def _init_pose(self) -> None:
        """Put the arm, hand down, with its grasp point at ``init_ee_pos``; fingers open."""
        p, arm = self._p, self.arm
        for j, q in zip(self._movable, self._rest):
            p.resetJointState(arm, j, q)
        target = np.asarray(self.spec.init_ee_pos, dtype=float)
        for _ in range(20):  # IK starts from the current joints: iterate to convergence
            q = self._ik(target)
            for j, qj in zip(self._arm_joints, q):
                p.resetJointState(arm, j, qj)
            if np.linalg.norm(self._ee_pos() - target) < 1e-4:
                break
        self._target = target
        self._q_target = np.array([p.getJointState(arm, j)[0] for j in self._arm_joints])
        self._drive()

    # -- control -------------------------------------------------------------------------------
    def _ik(self, target: np.ndarray) -> np.ndarray:
        """Arm joint angles putting the grasp point at ``target`` with the hand pointing down.

        Bullet's null-space IK keeps the elbow near the ready pose but stops ~2 mm short of the
        target; a second, plain damped-least-squares solve started from that posture lands on
        the target exactly and stays next to it.
        """
        p = self._p
        posture = p.calculateInverseKinematics(
            self.arm, self._ee_link, list(target), DOWN_XYZW,
            lowerLimits=self._lower, upperLimits=self._upper, jointRanges=self._ranges, restPoses=self._rest,
            maxNumIterations=IK_ITERATIONS, residualThreshold=IK_TOLERANCE)
        # with currentPositions Bullet wants the target in the base frame
        local_pos, local_orn = compose(self._base_inv[0], self._base_inv[1], tuple(target), DOWN_XYZW)
        solution = p.calculateInverseKinematics(
            self.arm, self._ee_link, local_pos, local_orn, currentPositions=list(posture),
            jointDamping=[IK_DAMPING] * len(self._movable),
            maxNumIterations=IK_ITERATIONS, residualThreshold=IK_TOLERANCE)
        return np.asarray(solution[:7], dtype=float)  # the first 7 movable joints are the arm's

    def _drive(self) -> None:
        """Send the joint targets to the arm motors and the gripper target to the finger motors."""
        p, arm = self._p, self.arm
        p.setJointMotorControlArray(arm, self._arm_joints, pybullet.POSITION_CONTROL,
                                    targetPositions=list(self._q_target), forces=ARM_FORCES,
                                    positionGains=[ARM_POSITION_GAIN] * 7, velocityGains=[1.0] * 7)
        p.setJointMotorControlArray(arm, self._finger_joints, pybullet.POSITION_CONTROL,
                                    targetPositions=[self._gripper_target] * 2, forces=[FINGER_FORCE] * 2)

    def act(self, action) -> RobotState:
        a = validate_action(action)  # raises SpecError before anything moves
        delta = np.clip(a[:3], -self.spec.max_delta, self.spec.max_delta)
        ee = self._ee_pos()
        if self.spec.goal_mode == "achieved":  # from where the hand is
            self._target = ee + delta
        else:  # "desired": the target accumulates clipped displacements, but never runs more than
            # GOAL_LEAD_STEPS control steps ahead of the hand (e.g. while pressing on the table)
            lead = GOAL_LEAD_STEPS * self.spec.max_delta
            self._target = ee + np.clip(self._target + delta - ee, -lead, lead)
        if a[3] == GRIPPER_OPEN:
            self._gripper_target = FINGER_OPEN
        elif a[3] == GRIPPER_CLOSE:
            self._gripper_target = 0.0
        # GRIPPER_NOOP keeps the last gripper command
        self._q_target = self._ik(self._target)
        self._drive()
        self._sim.step(self._substeps)  # one control period of physics
        return self.state()

    # -- sensing -------------------------------------------------------------------------------
    def _ee_pos(self) -> np.ndarray:
        state = pybullet.getLinkState(self.arm, self._ee_link, computeForwardKinematics=1, physicsClientId=self._cid)
        return np.array(state[4], dtype=float)  # world position of the link frame

    def state(self) -> RobotState:
        p, arm = self._p, self.arm
        joints = p.getJointStates(arm, self._arm_joints)
        fingers = p.getJointStates(arm, self._finger_joints)
        return RobotState(joints=np.array([s[0] for s in joints], dtype=float),
                          ee_pos=self._ee_pos(),
                          gripper_opening=float(fingers[0][0] + fingers[1][0]),  # each finger's travel from the centre
                          contacts=self._contacts())

    def _contacts(self) -> dict[str, list[str]]:
        """Robot part -> names of the bodies it touches ("fingers", "palm", "any": any arm link)."""
        sim, names = self._sim, self._sim._names
        parts: dict[str, set[str]] = {"fingers": set(), "palm": set(), "any": set()}
        for link in self._contact_links:  # the base link stands on its pedestal: not a contact
            touched = {names.get(uid, "?") for uid in sim.touching_uids(self.arm, link)}
            parts["any"] |= touched
            if link in self._finger_links:
                parts["fingers"] |= touched
            elif link == self._palm_link:
                parts["palm"] |= touched
        return {k: sorted(v) for k, v in parts.items()}

    def touching(self, body: str, part: str = "any") -> bool:
        index = self._sim._check_body(body)
        check_part(part)
        return self._sim.body_names[index] in self._contacts()[part]

