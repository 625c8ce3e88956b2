"""robosuite backend: a :class:`~physint_backends.spec.Scene` as a robosuite environment.

The world is assembled with robosuite's modelling API, the way robosuite's own tasks (``Lift``)
do it, in one small environment class, :class:`SceneEnv`: an arena (:class:`TableArena` under a
robot, :class:`EmptyArena` otherwise), every scene body as a robosuite object
(:class:`BoxObject`, :class:`CylinderObject`, :class:`BallObject`, or :class:`SceneBodyObject`
for multi-geom, offset, mesh and textured bodies) and, when the scene has a robot, robosuite's
Panda with its PandaGripper and mount, driven by robosuite's ``OSC_POSITION`` controller.

robosuite compiles that into a MuJoCo model; from there on the MuJoCo backend's layers do the
work (:class:`~physint_backends.mujoco_backend.MujocoWorld`: state, stepping, freezing,
contacts, recolouring, rendering; :class:`~physint_backends.mujoco_backend.MujocoSimulation`:
argument checking), so both backends behave alike by construction. In particular:

* one physics step is one ``mj_step`` of ``scene.timestep``; a robot control step sets a new
  OSC goal and runs robosuite's controller at every physics step (``mj_step1`` /
  ``robot.control`` / ``mj_step2``, robosuite's "lite physics" loop) for
  ``round(1 / (control_hz * timestep))`` steps. robosuite's observables, rewards and
  ``env.step`` are not used;
* rendering is ours, on our scene cameras, with shadows, multisampling and reflections off.
  The robot is drawn with its low-poly collision geoms (robosuite's Panda has 352k visual
  mesh vertices: ~87 vs ~800 renders/s here, see DESIGN.md); ``robot_visual="full"`` draws
  its visual meshes. robosuite's own cameras are off (``use_camera_obs=False``: ~20 control
  steps/s).

Physics is robosuite's (its elliptic friction cones; its robot, gripper and controller
parameters) with four exceptions that keep the backends equivalent: robosuite's air
(``density``, ``viscosity``) is off, since a scene spec has no air; its ``impratio=20`` and
Euler integrator become MuJoCo's default ``impratio=1`` and the MuJoCo backend's implicitfast
integrator (with the stiff contacts below, robosuite's settings let a 6-cube stack jump apart
within a second); and the contacts of scene bodies, ground and table are as stiff as on the MuJoCo backend
(``contact_solref``: MuJoCo's default lets stacks that should stand lean and topple).

Conventions shared with the MuJoCo backend: the arm's base (link 0) stands at
``robot.base_pos`` raised by ``robot.table_height``, facing +x (robosuite's mount stands below
it; the part of the mount under the floor is never seen); the end effector is robosuite's
``grip_site`` between the fingertips; the gripper starts open.
"""

from __future__ import annotations

import dataclasses
import logging
from collections import OrderedDict

import numpy as np

from . import ensure_headless_gl
from .base import RobotState
from .spec import (GOAL_LEAD_STEPS, GOAL_MODES, GRIPPER_NOOP, GRIPPER_OPEN, Body, Geom, Scene, SpecError, Texture,
                   validate_action)

ensure_headless_gl()  # before robosuite imports mujoco, which picks its OpenGL platform on import

ROBOSUITE_LOGGER = "robosuite_logs"


class _OnlyErrors(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return record.levelno >= logging.ERROR


def import_robosuite():
    """Import robosuite without its import-time warnings; afterwards it logs WARNING and above.

    robosuite creates its logger (``robosuite_logs``, console handler at INFO) while importing
    and immediately warns that there is no private macro file and that optional packages
    (robosuite_models, mink) are missing. A filter on that logger drops those during the import;
    raising the level to WARNING then silences its INFO lines (controller configs loaded).
    """
    logger = logging.getLogger(ROBOSUITE_LOGGER)
    quiet = _OnlyErrors()
    logger.addFilter(quiet)
    try:
        import robosuite
    finally:
        logger.removeFilter(quiet)
    logger.setLevel(logging.WARNING)
    return robosuite


import_robosuite()

import mujoco  # noqa: E402
from robosuite.controllers import load_composite_controller_config, load_part_controller_config  # noqa: E402
from robosuite.environments.manipulation.manipulation_env import ManipulationEnv  # noqa: E402
from robosuite.models.arenas import EmptyArena, TableArena  # noqa: E402
from robosuite.models.objects import BallObject, BoxObject, CylinderObject, MujocoGeneratedObject  # noqa: E402
from robosuite.models.tasks import ManipulationTask  # noqa: E402
from robosuite.utils.mjcf_utils import new_element, new_joint  # noqa: E402

from .mujoco_backend import (  # noqa: E402
    FREEZE_SOLIMP, ROBOT, ROLLING, TORSION, Z_FAR, Z_NEAR, MujocoSimulation, MujocoWorld, cube_faces, camera_quat,
    configure_contacts, contact_solref, label_geoms,
)
from .mujoco_panda import DARK_RGBA, EE_DOWN, FINGER_OPEN, LINK_RGBA, PandaSensing, solve_ik  # noqa: E402

TABLE_THICKNESS = 0.05  # robosuite's table-top thickness, metres
ARM = "right"  # robosuite's name for the Panda's only arm
DRAWN_GROUP, HIDDEN_GROUP = 1, 3  # geom groups after compiling: MuJoCo draws groups 0-2 by default
GROUND_TEXTURE = "physint_ground_tex"


# ------------------------------------------------------------------------------------------------
# scene bodies as robosuite objects
# ------------------------------------------------------------------------------------------------
def _floats(values) -> list[float]:
    """Plain Python floats: robosuite's XML helpers reject numpy scalars."""
    return [float(v) for v in np.asarray(values, dtype=float).reshape(-1)]


def _xml(values) -> str:
    return " ".join(repr(v) for v in _floats(values))


def _half_size(geom: Geom) -> list[float]:
    """MuJoCo size parameters of a primitive spec geom (spec sizes are full lengths)."""
    if geom.shape == "box":
        return [s / 2 for s in geom.size]
    if geom.shape == "cylinder":
        return [geom.size[0], geom.size[1] / 2]
    return [geom.size[0]]  # sphere


def _friction(mu: float) -> list[float]:
    return [float(mu), TORSION, ROLLING]


def _density(body: Body) -> float:
    """The density that gives the body its spec mass (robosuite objects are specified by density)."""
    volume = sum(g.volume() for g in body.geoms)
    if not volume > 0:  # also NaN, from trimesh on a flat mesh
        raise SpecError(f"body {body.name!r} has no volume (a flat or open mesh?); bodies must be solid")
    return float(body.total_mass / volume)


def _texture_assets(name: str, texture: Texture, *, plane: bool) -> tuple[object, object]:
    """A texture of the image's size, filled in after compiling (:func:`upload_textures`), and its material.

    robosuite builds its model from an XML string, where textures can only come from files;
    builtin placeholders of the right size avoid writing any. Like the MuJoCo backend, a plane
    tiles a 2D texture and other geoms wrap a cube texture with the image on every face.
    """
    h, w = texture.image.shape[:2]
    side = cube_faces(texture.image)[0]  # a cube texture's faces are side x side
    size = dict(type="2d", width=w, height=h) if plane else dict(type="cube", width=side, height=side)
    tex = new_element("texture", name=name, builtin="flat", rgb1="1 1 1", **size)
    mat = new_element("material", name=f"{name}_mat", texture=name, texrepeat=_floats(texture.repeat),
                      texuniform="false", specular="0.2", shininess="0.3", reflectance="0")
    return tex, mat


def upload_textures(model: mujoco.MjModel, textures: dict[str, tuple[Texture, bool]]) -> None:
    """Copy texture pixels into the compiled model (name -> (texture, plane?)); before any rendering."""
    for name, (texture, plane) in textures.items():
        tid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_TEXTURE, name)
        pixels = texture.image.tobytes() if plane else cube_faces(texture.image)[1]
        adr = model.tex_adr[tid]
        model.tex_data[adr:adr + len(pixels)] = np.frombuffer(pixels, dtype=np.uint8)


class SceneBodyObject(MujocoGeneratedObject):
    """Any spec body as a robosuite object (used for multi-geom, offset, mesh or textured bodies).

    Like robosuite's primitive objects, every spec geom becomes a collision geom (group 0) and a
    visual twin (group 1, no contacts) in one MuJoCo body, which has a free joint unless the body
    is static. Meshes are written inline (vertices and faces): no mesh files.
    """

    def __init__(self, name: str, body: Body, solref: list[float]):
        super().__init__(obj_type="all", duplicate_collision_geoms=True)
        self._name = name
        self.body = body
        self.solref = solref
        self.textures: dict[str, tuple[Texture, bool]] = {}  # for upload_textures()
        self._obj = self._get_object_subtree()
        self._get_object_properties()

    def _get_object_subtree(self):
        body, prefix = self.body, self.naming_prefix  # assets are named with the prefix already
        obj = new_element("body", name="main")
        for i, geom in enumerate(body.geoms):
            shape = dict(type=geom.shape, pos=_floats(geom.pos), quat=_floats(geom.quat))
            if geom.shape == "mesh":
                shape["mesh"] = f"{prefix}mesh{i}"
                self.asset.append(new_element("mesh", name=shape["mesh"], vertex=_floats(geom.mesh.vertices),
                                              face=[int(f) for f in np.asarray(geom.mesh.faces).reshape(-1)]))
            else:
                shape["size"] = _half_size(geom)
            visual = dict(shape, **self.get_visual_attrib_template(), rgba=_floats(geom.rgba))
            if geom.texture is not None:
                tex, mat = _texture_assets(f"{prefix}tex{i}", geom.texture, plane=False)
                self.asset.extend([tex, mat])
                self.textures[tex.get("name")] = (geom.texture, False)
                visual["material"] = mat.get("name")
            if body.collide:
                obj.append(new_element("geom", name=f"g{i}", **shape, **self.get_collision_attrib_template(),
                                       density=_density(body), friction=_friction(body.friction), solref=self.solref))
            obj.append(new_element("geom", name=f"g{i}_vis", **visual))
        if not body.static:
            obj.append(new_joint(name="joint0", type="free"))
        obj.append(new_element("site", **dict(self.get_site_attrib_template(), name="default_site", rgba="1 0 0 0")))
        return obj

    @property
    def horizontal_radius(self):  # bounding-sphere radius: robosuite's placement helpers use these
        return max(float(np.linalg.norm(g.pos)) + (max(_half_size(g)) if g.shape != "mesh" else
                                                    float(np.linalg.norm(g.mesh.vertices, axis=1).max()))
                   for g in self.body.geoms)

    @property
    def bottom_offset(self):
        return np.array([0.0, 0.0, -self.horizontal_radius])

    @property
    def top_offset(self):
        return np.array([0.0, 0.0, self.horizontal_radius])


def scene_object(name: str, body: Body, solref: list[float]):
    """The robosuite object of a spec body: a primitive object when one fits, else a SceneBodyObject.

    ``solref`` is the contact stiffness of its geoms (the MuJoCo backend's, see ``contact_solref``).
    """
    geom = body.geoms[0]
    primitive = {"box": BoxObject, "cylinder": CylinderObject, "sphere": BallObject}.get(geom.shape)
    if (len(body.geoms) > 1 or primitive is None or geom.texture is not None or any(geom.pos) or not body.collide
            or geom.quat != (1.0, 0.0, 0.0, 0.0)):
        return SceneBodyObject(name, body, solref)
    return primitive(name=name, size=_half_size(geom), rgba=_floats(geom.rgba), density=_density(body),
                     friction=_friction(body.friction), solref=solref, joints=None if body.static else "default")


# ------------------------------------------------------------------------------------------------
# the robosuite environment
# ------------------------------------------------------------------------------------------------
def osc_position_config(max_delta: float, kp: float = 150.0) -> dict:
    """robosuite's Panda composite controller with an ``OSC_POSITION`` arm taking metres.

    OSC_POSITION maps an input in [input_min, input_max] linearly onto a displacement in
    [output_min, output_max]; with both ranges ±max_delta the input is the displacement in metres.
    (The robot passes ``GOAL_LEAD_STEPS * max_delta``: a "desired"-mode goal may be that far ahead.)
    Position and orientation share the full 6x6 task-space inertia (``uncouple_pos_ori=False``, as
    on the MuJoCo backend): with robosuite's default separate blocks the hand lagged 4 cm behind a
    descending goal, stopped 1.2 cm above it, and strayed up to 11 cm sideways with its fingers on
    the table; coupled, it tracks exactly like the MuJoCo backend's Panda.
    """
    config = load_composite_controller_config(robot="Panda")
    arm = load_part_controller_config(default_controller="OSC_POSITION")
    arm.update(input_max=max_delta, input_min=-max_delta, output_max=[max_delta] * 3, output_min=[-max_delta] * 3,
               uncouple_pos_ori=False, kp=kp,
               gripper=config["body_parts"][ARM]["gripper"])
    config["body_parts"][ARM] = arm
    return config


class SceneEnv(ManipulationEnv):
    """A robosuite environment that holds one physint scene, with robosuite's Panda or no robot.

    It only builds the world (:meth:`_load_model`); :class:`RobosuiteSimulation` steps and
    renders it. Scene body ``i`` is the robosuite object ``physint{i}`` and scene camera ``i``
    the model camera ``physint_cam{i}``.
    """

    def __init__(self, scene: Scene):
        self.scene = scene
        self.scene_objects: list = []
        self.table_body = None  # name of the table body, if any
        robot = scene.robot
        state = np.random.get_state()  # robosuite draws (zero) joint noise from numpy's global RNG
        try:
            super().__init__(
                robots=["Panda"] if robot else [],
                controller_configs=osc_position_config(robot.max_delta * GOAL_LEAD_STEPS, robot.osc_kp) if robot else None,
                initialization_noise=None,
                use_camera_obs=False, has_renderer=False, has_offscreen_renderer=False,
                control_freq=robot.control_hz if robot else 20, horizon=2 ** 62, ignore_done=True,
                hard_reset=False, renderer="mujoco",
            )
        finally:
            np.random.set_state(state)

    @staticmethod
    def camera_name(i: int) -> str:
        """Model name of scene camera ``i`` (robosuite's arenas have cameras of their own)."""
        return f"physint_cam{i}"

    @property
    def textures(self) -> dict[str, tuple[Texture, bool]]:
        """Texture pixels to upload after compiling (see :func:`upload_textures`)."""
        out = {}
        ground = self.scene.ground
        if ground is not None and ground.texture is not None:
            out[GROUND_TEXTURE] = (ground.texture, True)
        for obj in self.scene_objects:
            out.update(getattr(obj, "textures", {}))
        return out

    def _load_model(self):
        super()._load_model()  # the robot models
        scene, robot = self.scene, self.scene.robot
        if robot is not None and robot.table_height > 0:
            arena = TableArena(table_full_size=(*robot.table_size, min(TABLE_THICKNESS, robot.table_height)),
                               table_offset=(0, 0, robot.table_height))
            arena.table_collision.set("solref", _xml(self.solref))
            self.table_body = "table"
        else:
            arena = EmptyArena()
        self._restyle_arena(arena)
        for i, camera in enumerate(scene.cameras):
            arena.set_camera(camera_name=self.camera_name(i), pos=_floats(camera.pos),
                             quat=_floats(camera_quat(camera)), camera_attribs={"fovy": repr(float(camera.fovy))})
        if self.robots:  # the arm's base at base_pos on the table top; robosuite's mount below it
            model = self.robots[0].robot_model
            model.set_base_xpos(np.add(robot.base_pos, (0.0, 0.0, robot.table_height)) + model.bottom_offset)
        self.scene_objects = []
        for i, body in enumerate(scene.bodies):
            obj = scene_object(f"physint{i}", body, self.solref)
            obj.get_obj().set("pos", _xml(body.pos))  # free joints start at their body's pose
            obj.get_obj().set("quat", _xml(body.quat))
            self.scene_objects.append(obj)
        self.model = ManipulationTask(mujoco_arena=arena, mujoco_robots=[r.robot_model for r in self.robots],
                                      mujoco_objects=self.scene_objects)
        for obj, body in zip(self.scene_objects, scene.bodies):
            if not body.static:  # a weld to the world, off until MujocoWorld.freeze() switches it on
                self.model.equality.append(new_element(
                    "weld", name=f"{obj.naming_prefix}freeze", body1="world", body2=obj.root_body, active="false",
                    solimp=FREEZE_SOLIMP))

    @property
    def solref(self) -> list[float]:
        """Contact stiffness of the scene's bodies, ground and table (the MuJoCo backend's: stacks stand)."""
        return contact_solref(self.scene.timestep)

    def _restyle_arena(self, arena) -> None:
        """The scene's ground (or none) and lights instead of robosuite's; no decorative walls."""
        worldbody = arena.worldbody
        for element in list(worldbody):
            if element.tag == "light" or (element.tag == "geom" and (element.get("name") or "").startswith("wall_")):
                worldbody.remove(element)
        ground = self.scene.ground
        if ground is None:
            worldbody.remove(arena.floor)
        else:
            floor = arena.floor
            floor.attrib.pop("material", None)
            floor.set("rgba", _xml(ground.rgba))
            floor.set("friction", _xml(_friction(ground.friction)))
            floor.set("size", _xml((ground.size, ground.size, 0.125)))
            floor.set("solref", _xml(self.solref))
            if ground.texture is not None:
                tex, mat = _texture_assets(GROUND_TEXTURE, ground.texture, plane=True)
                arena.asset.extend([tex, mat])
                floor.set("material", mat.get("name"))
        for light in self.scene.lights:
            direction = np.subtract(light.lookat, light.pos)
            worldbody.append(new_element(
                "light", name=None, pos=_floats(light.pos), dir=_floats(direction if np.any(direction) else (0, 0, -1)),
                directional="true" if light.directional else "false", diffuse=_floats(light.diffuse),
                ambient=_floats(light.ambient), specular=[0.1, 0.1, 0.1], castshadow="false"))

    # robosuite hooks we do not use: no observables (we read the state), no reward, no success
    def _setup_observables(self):
        return OrderedDict()

    def reward(self, action=None):
        return 0.0

    def _check_success(self):
        return False


# ------------------------------------------------------------------------------------------------
# the robot
# ------------------------------------------------------------------------------------------------
def hold_gripper_down(controller) -> None:
    """Give robosuite's OSC_POSITION controller a fixed goal orientation: the gripper pointing down.

    Up to robosuite 1.4, OSC_POSITION held this orientation (``set_ori = [[0, 1, 0], [1, 0, 0],
    [0, 0, -1]]``, which is :data:`EE_DOWN`); robosuite 1.5 holds whatever orientation the hand
    has when an action arrives, so only damping resists tilting: the gripper drifted 3-5 degrees
    over moves across the table and 25-87 degrees towards the edge of the workspace, where a
    grasp from above fails. Held down, tracking overshoots a little more (+10 cm in x: 8.5 mm
    after 1 s, 1 mm after 2 s; 3.9 mm and 0.1 mm without). The goal is in the controller's
    frame, the robot base, which faces +x unrotated.
    """
    controller.compute_goal_ori = lambda delta, goal_update_mode=None: EE_DOWN.copy()


def _geom_ids(model: mujoco.MjModel, names: list[str]) -> np.ndarray:
    return np.array([mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, n) for n in names])


@dataclasses.dataclass
class PandaIndices:
    """Where robosuite's Panda lives in the compiled model (the fields mujoco_panda.solve_ik reads)."""

    qadr: np.ndarray  # arm joint qpos addresses
    dofs: np.ndarray  # arm joint dof addresses
    limits: np.ndarray  # (7, 2) arm joint ranges
    finger_qadr: np.ndarray  # finger joint qpos addresses
    site: int  # robosuite's grip_site, between the fingertips


class RobosuiteRobot(PandaSensing):
    """robosuite's Panda under its OSC_POSITION controller, behind the backend-neutral Robot interface.

    What the robot senses (:meth:`state`, :meth:`touching`) is the MuJoCo backend's
    (:class:`PandaSensing`): the same quantities (:class:`PandaIndices`, ``parts``) of the same
    kind of model. Building, resetting and acting are robosuite's.

    The controller runs inside :class:`~physint_backends.mujoco_backend.MujocoWorld`'s step loop
    (it is one of the world's ``controllers``): between ``mj_step1`` and ``mj_step2`` of every
    physics step it calls robosuite's ``robot.control``, with a new goal on the first step of a
    control step. Between actions (``sim.step``) it keeps the last goal and gripper command.
    ``goal_update_mode`` is robosuite's: a displacement moves the goal from where the hand is
    (``"achieved"``) or from the previous goal (``"desired"``).
    """

    def __init__(self, world: MujocoWorld, robot, spec, body_names: list[str],
                 goal_update_mode: str = "achieved"):
        self.spec = spec
        self.world = world
        self.body_names = list(body_names)
        if goal_update_mode not in GOAL_MODES:
            raise SpecError(f"goal_update_mode {goal_update_mode!r} is not supported; allowed: {', '.join(GOAL_MODES)}")
        self.goal_update_mode = goal_update_mode
        self._goal: np.ndarray | None = None  # "desired" mode: the hand's goal in the world frame
        self._robot = robot  # robosuite's Robot (FixedBaseRobot) of the environment
        gripper = self._robot.gripper[ARM]
        model = self.world.model
        self.panda = PandaIndices(
            qadr=np.asarray(self._robot._ref_joint_pos_indexes), dofs=np.asarray(self._robot._ref_joint_vel_indexes),
            limits=model.jnt_range[self._robot._ref_joint_indexes],
            finger_qadr=np.asarray(self._robot._ref_gripper_joint_pos_indexes[ARM]),
            site=mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, gripper.important_sites["grip_site"]))
        fingers = _geom_ids(model, gripper.important_geoms["left_finger"] + gripper.important_geoms["right_finger"])
        self.parts = {"fingers": fingers, "palm": np.setdiff1d(_geom_ids(model, gripper.contact_geoms), fingers),
                      "any": np.flatnonzero(np.asarray(self.world.geom_owner, dtype=object) == ROBOT)}
        self.substeps = max(1, round(self.control_dt / model.opt.timestep))
        self._action = np.zeros(4)  # robosuite action: (dx, dy, dz) metres, gripper (+1 closes, -1 opens)
        self._new_goal = True
        self.world.controllers.append(self._control)
        # arm angles with the gripper at init_ee_pos pointing down become robosuite's initial joint angles
        q, residual = solve_ik(model, mujoco.MjData(model), self.panda, np.asarray(spec.init_ee_pos),
                               q0=np.asarray(self._robot.init_qpos, dtype=float))
        if residual > 0.005:
            raise SpecError(f"robot init_ee_pos {list(spec.init_ee_pos)} is out of the Panda's reach from base_pos "
                            f"{list(spec.base_pos)} (closest: {residual:.3f} m away)")
        self._robot.init_qpos = q
        self.reset()

    def _control(self, model, data) -> None:
        """One physics step of robosuite control (the world calls it between mj_step1 and mj_step2)."""
        self._robot.control(self._action, policy_step=self._new_goal)
        self._new_goal = False

    def reset(self) -> None:
        """Arm at its initial angles, gripper open, at rest; the next step sets the goal to here."""
        data = self.world.data
        self._robot.reset(deterministic=True)  # arm qpos, fresh controllers
        arm = self._robot.part_controllers[ARM]
        hold_gripper_down(arm)
        # robosuite always moves the goal from the hand; "desired" mode is kept here (see act)
        arm.set_goal_update_mode("achieved")
        self._goal = None
        # robosuite's fresh goal is the hand's pose in the world frame, but goals live in the base
        # frame: without a goal, the first set_goal starts from the hand's pose in the right frame
        arm.goal_pos = arm.goal_ori = None
        data.qpos[self.panda.finger_qadr] = FINGER_OPEN
        self._robot.gripper[ARM].current_action = np.array([1.0, -1.0])  # robosuite's "fully open" command
        self._action = np.array([0.0, 0.0, 0.0, GRIPPER_OPEN])
        self._new_goal = True
        self.world.invalidate()

    # -- Robot interface ------------------------------------------------------------------------
    def act(self, action) -> RobotState:
        a = validate_action(action)  # SpecError before anything moves
        gripper = self._action[3] if a[3] == GRIPPER_NOOP else a[3]  # no-op repeats the last command
        delta = np.clip(a[:3], -self.spec.max_delta, self.spec.max_delta)
        if self.goal_update_mode == "desired":  # from the previous goal, at most GOAL_LEAD_STEPS ahead
            self.world.forward()
            hand = self.world.data.site_xpos[self.panda.site].copy()
            goal = hand if self._goal is None else self._goal
            lead = GOAL_LEAD_STEPS * self.spec.max_delta
            self._goal = hand + np.clip(goal + delta - hand, -lead, lead)
            delta = self._goal - hand
        self._action = np.array([*delta, gripper])
        self._new_goal = True
        self.world.step(self.substeps)
        return self.state()


# ------------------------------------------------------------------------------------------------
# the Simulation interface
# ------------------------------------------------------------------------------------------------
class RobosuiteSimulation(MujocoSimulation):
    """A Scene as a robosuite environment (see the module docstring).

    Everything but building the world is the MuJoCo backend's, and so are the options
    (``physint_backends.make("robosuite", scene, **options)``):
        robot_visual: ``"collision"`` (default) draws the Panda with its low-poly collision
            geoms; ``"full"`` draws robosuite's visual meshes (~10x slower to render).
        goal_update_mode: overrides the scene robot's ``goal_mode`` (see ``spec.Robot``):
            ``"achieved"`` (a displacement moves the goal from where the hand is) or ``"desired"``
            (from the previous goal, leading the hand by at most ``GOAL_LEAD_STEPS`` displacements).
    """

    backend = "robosuite"

    def __init__(self, scene: Scene, robot_visual: str = "collision", goal_update_mode: str | None = None):
        self.env: SceneEnv | None = None
        super().__init__(scene, robot_visual=robot_visual, goal_update_mode=goal_update_mode)

    def _build(self, scene: Scene) -> None:
        """Build ``scene`` as a robosuite environment, world and robot; only then replace the old ones."""
        if not isinstance(scene, Scene):
            raise SpecError(f"scene must be a physint_backends.Scene, got {type(scene).__name__}")
        try:
            env = SceneEnv(scene)
        except SpecError:
            raise
        except ValueError as exc:  # MuJoCo's compiler
            raise SpecError(f"robosuite cannot build this scene: {exc}") from None
        try:
            model, data = env.sim.model._model, env.sim.data._data
            configure_model(model, scene, env.textures)
            names = [b.name for b in scene.bodies]
            body_ids = [model.body(obj.root_body).id for obj in env.scene_objects]
            table = [] if env.table_body is None else np.flatnonzero(model.geom_bodyid == model.body(env.table_body).id)
            floor = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "floor")
            geom_label, geom_owner = label_geoms(
                model, body_ids, names, table_geoms=table, ground_geoms=[floor] if floor >= 0 else [],
                robot_root=model.body(env.robots[0].robot_model.root_body).id if env.robots else None)
            draw_robot(model, np.asarray(geom_owner, dtype=object) == ROBOT, self.robot_visual)
            if scene.robot is not None:
                paint_table(model, table, scene.robot.table_rgba)
            world = MujocoWorld(model, data, body_ids, geom_label, geom_owner)
            configure_contacts(world, scene)
            robot = None
            if scene.robot is not None:
                robot = RobosuiteRobot(world, env.robots[0], scene.robot, names,
                                       self.goal_update_mode or scene.robot.goal_mode)
        except BaseException:
            env.close()
            raise
        self.close()  # the previous world and environment
        self._install(scene, world, robot, [model.camera(SceneEnv.camera_name(i)).id for i in range(len(scene.cameras))])
        self.env = env

    def close(self) -> None:
        super().close()
        if self.env is not None:
            # drop robosuite's MjSim (and with it the model and data) by reference counting:
            # env.close() would also run a full gc.collect(), 60 % of a small scene's life here
            self.env.sim = None
            self.env = None


def configure_model(model: mujoco.MjModel, scene: Scene, textures: dict[str, tuple[Texture, bool]]) -> None:
    """Physics and rendering settings of robosuite's compiled model, as the MuJoCo backend's."""
    model.opt.timestep = scene.timestep
    model.opt.gravity[:] = scene.gravity
    model.opt.density = 0.0  # no air
    model.opt.impratio = 1.0  # robosuite's 20 with stiff contacts makes tall stacks explode
    model.opt.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST  # as on the MuJoCo backend
    model.opt.viscosity = 0.0
    model.vis.quality.shadowsize = 0  # shadow maps and multisampling cost 30x on Mesa
    model.vis.quality.offsamples = 0
    model.mat_reflectance[:] = 0.0
    model.vis.map.znear = Z_NEAR / model.stat.extent  # clipping planes in metres, as on the MuJoCo backend
    model.vis.map.zfar = Z_FAR / model.stat.extent
    model.vis.headlight.active = 0 if scene.lights else 1
    model.vis.global_.offwidth = max([model.vis.global_.offwidth] + [c.width for c in scene.cameras])
    model.vis.global_.offheight = max([model.vis.global_.offheight] + [c.height for c in scene.cameras])
    model.site_group[:] = HIDDEN_GROUP  # robosuite's sites are markers, not part of the scene
    upload_textures(model, textures)
    paint_sky(model, scene.background)


def paint_sky(model: mujoco.MjModel, rgb) -> None:
    """Fill robosuite's skybox textures with the scene's flat background colour, as on the other backends."""
    colour = np.round(np.asarray(rgb) * 255).astype(np.uint8)
    for t in np.flatnonzero(model.tex_type == mujoco.mjtTexture.mjTEXTURE_SKYBOX):
        adr, n = model.tex_adr[t], model.tex_width[t] * model.tex_height[t]
        pixels = model.tex_data[adr:adr + n * model.tex_nchannel[t]].reshape(n, model.tex_nchannel[t])
        pixels[:, :3] = colour


def paint_table(model: mujoco.MjModel, table_geoms, rgba) -> None:
    """The table in the spec's plain colour instead of robosuite's ceramic texture."""
    for g in table_geoms:
        model.geom_matid[g] = -1
        model.geom_rgba[g] = rgba


def draw_robot(model: mujoco.MjModel, robot: np.ndarray, robot_visual: str) -> None:
    """Choose the drawn geoms: visual geoms (group 1), but the robot's collision geoms unless ``full``.

    Drawn geoms go to group 1 and the rest to group 3, which MuJoCo does not draw by default.
    robosuite's collision geoms are coloured by kind (green arm, blue gripper); drawn, they take
    the MuJoCo backend's Panda colours.
    """
    visual = model.geom_group == 1
    if robot_visual == "full":
        drawn = visual
    else:
        drawn = np.where(robot, model.geom_group == 0, visual)
        names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or "" for g in range(model.ngeom)]
        dark = np.array(["finger" in n or "mount" in n for n in names])
        model.geom_rgba[robot & drawn] = LINK_RGBA
        model.geom_rgba[robot & drawn & dark] = DARK_RGBA
    model.geom_group[:] = np.where(drawn, DRAWN_GROUP, HIDDEN_GROUP)
