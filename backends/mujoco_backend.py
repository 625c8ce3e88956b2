"""MuJoCo backend: a :class:`~physint_backends.spec.Scene` built with ``mujoco.MjSpec``.

The module has three layers, so that other MuJoCo-based backends (robosuite) can reuse the
lower two with a model they built themselves:

* :class:`OffscreenRenderer`: one headless OpenGL context per model, rendering RGB, metric depth
  and segmentation from a fixed camera at any size up to the model's offscreen buffer;
* :class:`MujocoWorld`: state, stepping, freezing, contacts, recolouring and rendering of a
  compiled ``(MjModel, MjData)`` given which MuJoCo bodies are the scene's bodies and what each
  geom is (a scene body, the ground, the table, the robot);
* :class:`MujocoSimulation`: the :class:`~physint_backends.base.Simulation` interface; it builds
  the model from a scene (:func:`build_spec`), validates every argument and delegates.

Physics defaults: the scene's timestep and gravity, the ``implicitfast`` integrator, elliptic
friction cones with ``condim=3`` (sliding friction; 6 for curved bodies, which also resist
rolling and spinning, and the noslip solver when the scene asks for hard friction, see
:func:`configure_contacts`) and stiff contacts (time constant 2.5 physics steps, see
:func:`contact_solref`) so that marginally stable stacks stand.
Rendering defaults follow the measurements in DESIGN.md: no shadow maps, no multisampling, no
reflections (30x faster on Mesa's software rasteriser).
"""

from __future__ import annotations

import dataclasses
import weakref
from collections.abc import Callable, Sequence

from . import ensure_headless_gl

ensure_headless_gl()  # before mujoco picks its OpenGL backend (no-op when MUJOCO_GL is set or a display exists)

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from .base import SimulationError, SEG_BACKGROUND, SEG_ROBOT, Frame, Simulation  # noqa: E402
from .spec import Body, Camera, Geom, Scene, SpecError, Texture, _rgba  # noqa: E402

GROUND = "ground"
ROBOT = "robot"
TABLE = "table"

BODY_PREFIX = "body/"  # MuJoCo names of scene bodies: "body/<name>"; geoms "body/<name>/<i>"
ENV_PREFIX = "env/"  # ground, lights, table; the robot's elements are named "panda/..."

Z_NEAR = 0.01  # camera clipping planes, metres; background depth reads Z_FAR
Z_FAR = 50.0
MIN_OFFSCREEN = 640  # offscreen framebuffer is at least this big (pixels)
CONTACT_STEPS = 2.5  # contact time constant in physics steps (see contact_solref)
FREEZE_SOLIMP = [0.99, 0.99, 0.001, 0.5, 2.0]  # stiff weld for frozen bodies (sags ~0.05 mm under gravity)
TORSION, ROLLING = 0.005, 0.0001  # MuJoCo's default torsional / rolling friction coefficients
CURVED_GEOMS = (mujoco.mjtGeom.mjGEOM_SPHERE, mujoco.mjtGeom.mjGEOM_CAPSULE, mujoco.mjtGeom.mjGEOM_ELLIPSOID,
                mujoco.mjtGeom.mjGEOM_CYLINDER, mujoco.mjtGeom.mjGEOM_MESH)
NOSLIP_ITERATIONS = 2  # noslip solver passes for Scene.hard_friction (5 measured no better)


# ------------------------------------------------------------------------------------------------
# small geometry helpers
# ------------------------------------------------------------------------------------------------
def mat_to_quat(mat: np.ndarray) -> np.ndarray:
    """(w, x, y, z) quaternion of a 3x3 rotation matrix."""
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, np.ascontiguousarray(mat, dtype=float).reshape(9))
    return quat


def quat_to_mat(quat) -> np.ndarray:
    """3x3 rotation matrix of a (w, x, y, z) quaternion."""
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, np.asarray(quat, dtype=float))
    return mat.reshape(3, 3)


def camera_quat(camera: Camera) -> np.ndarray:
    """MuJoCo camera orientation: MuJoCo cameras look along their -z with y up, like Camera.rotation()."""
    return mat_to_quat(camera.rotation())


def cube_faces(image: np.ndarray, max_side: int = 512) -> tuple[int, bytes]:
    """A cube texture's data: the image resampled to a square (nearest pixel) and repeated on 6 faces."""
    h, w = image.shape[:2]
    side = int(min(max(h, w), max_side))
    rows = (np.arange(side) * h // side).clip(0, h - 1)
    cols = (np.arange(side) * w // side).clip(0, w - 1)
    square = np.ascontiguousarray(image[rows][:, cols])
    return side, np.concatenate([square] * 6, axis=0).tobytes()


# ------------------------------------------------------------------------------------------------
# building an MjSpec from a Scene
# ------------------------------------------------------------------------------------------------
@dataclasses.dataclass
class BuiltScene:
    """An MjSpec built from a Scene, and which spec elements stand for what."""

    spec: mujoco.MjSpec
    body_names: list[str]  # MuJoCo body name of each scene body, in scene order
    camera_names: list[str]  # MuJoCo camera name of each scene camera, in scene order
    ground_geom: str | None  # MuJoCo geom name of the ground plane
    table_geoms: list[str]  # MuJoCo geom names of the robot's table
    robot_root: str | None  # MuJoCo name of the robot's root body


def _texture_material(spec: mujoco.MjSpec, name: str, texture: Texture, rgba, *, plane: bool) -> str:
    """Add a texture and a material using it; a plane tiles a 2D texture, other geoms wrap a cube texture."""
    img = texture.image
    tex = spec.add_texture(name=name, nchannel=3)
    if plane:
        tex.type = mujoco.mjtTexture.mjTEXTURE_2D
        tex.height, tex.width = img.shape[:2]
        tex.data = img.tobytes()
    else:
        side, data = cube_faces(img)
        tex.type = mujoco.mjtTexture.mjTEXTURE_CUBE
        tex.width, tex.height = side, 6 * side
        tex.data = data
    mat = spec.add_material(name=name, rgba=list(rgba), reflectance=0.0, specular=0.2, shininess=0.3)
    textures = list(mat.textures)
    textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = name
    mat.textures = textures
    mat.texuniform = False  # the image is repeated `repeat` times over the whole geom / ground
    mat.texrepeat = list(texture.repeat)
    return name


def configure_contacts(world: "MujocoWorld", scene: Scene) -> None:
    """Rolling and torsional friction for the scene's curved bodies, and hard friction on request.

    A curved scene geom (sphere, cylinder, mesh) gets ``condim`` 6, so that its contacts resist
    rolling and spinning with the coefficients ROLLING and TORSION, as its body does on PyBullet;
    flat-faced bodies keep ``condim`` 3 (several contact points already resist turning). With
    ``scene.hard_friction`` the noslip solver removes the creep that soft contacts allow: without it
    a sphere rolls off a balanced plank that the contacts have tilted by 0.05 degrees.
    """
    model = world.model
    for geoms in world.body_geoms:
        for g in geoms:
            if model.geom_type[g] in CURVED_GEOMS:
                model.geom_condim[g] = 6
    model.opt.noslip_iterations = NOSLIP_ITERATIONS if scene.hard_friction else 0


def contact_solref(timestep: float) -> list[float]:
    """Contact stiffness: time constant 2.5 physics steps (MuJoCo's stable minimum is 2), critically damped.

    MuJoCo's default time constant (0.02 s) lets stacks sink and lean enough that stacks whose
    centre of mass is a few millimetres inside the support topple; at 2.5 steps they stand.
    """
    return [CONTACT_STEPS * timestep, 1.0]


def _add_geom(spec: mujoco.MjSpec, body: mujoco.MjsBody, name: str, geom: Geom, *, mass: float | None,
              density: float, friction: float, solref: list[float], collide: bool = True) -> None:
    """One scene geom: spec sizes (full lengths) become MuJoCo half sizes."""
    g = body.add_geom(name=name, pos=list(geom.pos), quat=list(geom.quat), rgba=list(geom.rgba))
    if geom.shape == "box":
        g.type = mujoco.mjtGeom.mjGEOM_BOX
        g.size = [s / 2 for s in geom.size]
    elif geom.shape == "cylinder":
        g.type = mujoco.mjtGeom.mjGEOM_CYLINDER
        g.size = [geom.size[0], geom.size[1] / 2, 0.0]
    elif geom.shape == "sphere":
        g.type = mujoco.mjtGeom.mjGEOM_SPHERE
        g.size = [geom.size[0], 0.0, 0.0]
    else:  # convex trimesh in the geom frame
        spec.add_mesh(name=name, uservert=np.asarray(geom.mesh.vertices, dtype=float).reshape(-1).tolist(),
                      userface=np.asarray(geom.mesh.faces, dtype=np.int64).reshape(-1).tolist())
        g.type = mujoco.mjtGeom.mjGEOM_MESH
        g.meshname = name
    if mass is not None:
        g.mass = mass
    else:
        g.density = density
    g.friction = [friction, TORSION, ROLLING]
    g.condim = 3  # sliding friction (elliptic cones, see build_spec)
    g.solref = solref
    if not collide:  # drawn only
        g.contype = g.conaffinity = 0
    if geom.texture is not None:
        g.material = _texture_material(spec, name, geom.texture, geom.rgba, plane=False)


def _add_body(spec: mujoco.MjSpec, body: Body, solref: list[float]) -> str:
    """A scene body: free joint when dynamic, none when static; mass spread over geoms by volume."""
    name = BODY_PREFIX + body.name
    b = spec.worldbody.add_body(name=name, pos=list(body.pos), quat=list(body.quat))
    if not body.static:
        b.add_freejoint(name=name)
        # a weld to the world, off until the body is frozen
        weld = spec.add_equality(name=name, type=mujoco.mjtEq.mjEQ_WELD, objtype=mujoco.mjtObj.mjOBJ_BODY,
                                 name1="world", name2=name, active=False)
        weld.solimp = FREEZE_SOLIMP
    volumes = np.array([g.volume() for g in body.geoms]) if body.mass is not None else None
    for i, geom in enumerate(body.geoms):
        if body.mass is not None:  # the body's mass, shared by volume
            share = volumes[i] / volumes.sum() if volumes.sum() > 0 else 1.0 / len(volumes)
            mass = body.mass * share
        else:
            mass = None
        _add_geom(spec, b, f"{name}/{i}", geom, mass=mass, density=body.density, friction=body.friction,
                  solref=solref, collide=body.collide)
    return name


def build_spec(scene: Scene, *, robot_visual: str = "collision") -> BuiltScene:
    """Translate a backend-neutral Scene into an ``mujoco.MjSpec`` (not yet compiled)."""
    spec = mujoco.MjSpec()
    spec.modelname = "physint"
    # -- physics options -----------------------------------------------------------------------
    spec.option.timestep = scene.timestep
    spec.option.gravity = list(scene.gravity)
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC  # exact Coulomb friction cones
    # -- rendering: fast on Mesa (no shadow maps, no multisampling), clipping planes in metres --
    spec.visual.quality.shadowsize = 0
    spec.visual.quality.offsamples = 0
    spec.stat.extent = 1.0  # so that znear / zfar below are in metres
    spec.visual.map.znear = Z_NEAR
    spec.visual.map.zfar = Z_FAR
    spec.visual.global_.offwidth = max([MIN_OFFSCREEN] + [c.width for c in scene.cameras])
    spec.visual.global_.offheight = max([MIN_OFFSCREEN] + [c.height for c in scene.cameras])
    spec.visual.headlight.active = 0 if scene.lights else 1
    spec.add_texture(name=ENV_PREFIX + "sky", type=mujoco.mjtTexture.mjTEXTURE_SKYBOX,
                     builtin=mujoco.mjtBuiltin.mjBUILTIN_FLAT, rgb1=list(scene.background),
                     rgb2=list(scene.background), width=8, height=8)
    solref = contact_solref(scene.timestep)

    ground_geom = None
    if scene.ground is not None:
        ground = scene.ground
        ground_geom = ENV_PREFIX + "ground"
        g = spec.worldbody.add_geom(name=ground_geom, type=mujoco.mjtGeom.mjGEOM_PLANE,
                                    size=[ground.size, ground.size, 0.1], rgba=list(ground.rgba))
        g.friction = [ground.friction, TORSION, ROLLING]
        g.solref = solref
        if ground.texture is not None:
            g.material = _texture_material(spec, ground_geom, ground.texture, ground.rgba, plane=True)

    for i, light in enumerate(scene.lights):
        direction = np.subtract(light.lookat, light.pos)
        norm = np.linalg.norm(direction)
        direction = direction / norm if norm > 1e-9 else np.array([0.0, 0.0, -1.0])
        spec.worldbody.add_light(
            name=f"{ENV_PREFIX}light{i}", pos=list(light.pos), dir=direction.tolist(),
            type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL if light.directional else mujoco.mjtLightType.mjLIGHT_SPOT,
            diffuse=list(light.diffuse), ambient=list(light.ambient), specular=[0.1, 0.1, 0.1], castshadow=False)

    body_names = [_add_body(spec, body, solref) for body in scene.bodies]

    camera_names = []
    for cam in scene.cameras:
        name = "camera/" + cam.name
        spec.worldbody.add_camera(name=name, pos=list(cam.pos), quat=camera_quat(cam).tolist(), fovy=cam.fovy)
        camera_names.append(name)

    table_geoms, robot_root = [], None
    if scene.robot is not None:
        from .mujoco_panda import add_panda

        table_geoms, robot_root = add_panda(spec, scene.robot, visual=robot_visual, solref=solref,
                                            friction=scene.ground.friction if scene.ground else 0.8)
    return BuiltScene(spec, body_names, camera_names, ground_geom, table_geoms, robot_root)


# ------------------------------------------------------------------------------------------------
# rendering
# ------------------------------------------------------------------------------------------------
_SHARED_GL: list = []  # [(GLContext, width, height)]: one OpenGL context per process, reused by every model


def _shared_gl(width: int, height: int):
    """The process's OpenGL context, (re)made when a model needs a bigger offscreen buffer.

    A new context costs Mesa's software rasteriser ~60-120 ms on its first frame (it compiles its
    pipeline per context); sharing one across simulations makes building and rendering many
    small scenes cheap. Older contexts are kept alive for the render contexts still using them.
    """
    if not _SHARED_GL or _SHARED_GL[-1][1] < width or _SHARED_GL[-1][2] < height:
        w = max(width, _SHARED_GL[-1][1] if _SHARED_GL else 0)
        h = max(height, _SHARED_GL[-1][2] if _SHARED_GL else 0)
        _SHARED_GL.append((mujoco.GLContext(w, h), w, h))
    return _SHARED_GL[-1][0]


class _GLResources:
    """The MuJoCo render context of one model on the shared OpenGL context; freed once, even at exit."""

    def __init__(self, model: mujoco.MjModel):
        self.gl = _shared_gl(model.vis.global_.offwidth, model.vis.global_.offheight)
        self.gl.make_current()
        self.con = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_50.value)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN.value, self.con)
        self.con.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR

    def free(self) -> None:
        try:
            if self.con is not None:
                self.gl.make_current()
                self.con.free()
        except Exception:  # at interpreter exit EGL may already be torn down: nothing left to free
            pass
        self.con = None
        self.gl = None


class OffscreenRenderer:
    """Headless renderer of one model: RGB, metric depth and geom-id segmentation from fixed cameras.

    One OpenGL context serves every image size up to the model's offscreen buffer
    (``visual/global offwidth, offheight``); it is created on the first render and freed by
    :meth:`close` (or when the renderer is garbage collected, or at interpreter exit).
    """

    def __init__(self, model: mujoco.MjModel, max_geom: int | None = None):
        self.model = model
        self.scene = mujoco.MjvScene(model, maxgeom=max_geom or max(1000, 2 * model.ngeom + 100))
        self.option = mujoco.MjvOption()
        self.camera = mujoco.MjvCamera()
        self.camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self._gl: _GLResources | None = None
        self._finalizer = None

    def _context(self) -> _GLResources:
        if self._gl is None:
            self._gl = _GLResources(self.model)
            self._finalizer = weakref.finalize(self, self._gl.free)
        self._gl.gl.make_current()
        # several models share the OpenGL context: bind this one's offscreen framebuffer, which
        # the render context made last (by another simulation in this process) left bound
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN.value, self._gl.con)
        return self._gl

    def render(self, data: mujoco.MjData, camera_id: int, width: int, height: int, *, rgb: bool = True,
               depth: bool = False, segmentation: bool = False) -> tuple:
        """Render ``(rgb uint8 HxWx3, depth float32 HxW metres, geom ids int32 HxW (-1: none))``.

        Colour and depth come from one pass; the id pass (also used for depth-only requests,
        because it skips lighting) is a second one. Arrays not asked for are None.
        """
        m = self.model
        if width > m.vis.global_.offwidth or height > m.vis.global_.offheight:
            raise SpecError(f"image {width}x{height} is larger than the offscreen buffer "
                            f"{m.vis.global_.offwidth}x{m.vis.global_.offheight}")
        gl = self._context()
        rect = mujoco.MjrRect(0, 0, width, height)
        self.camera.fixedcamid = camera_id
        mujoco.mjv_updateScene(m, data, self.option, None, self.camera, mujoco.mjtCatBit.mjCAT_ALL.value, self.scene)
        rgb_out = depth_out = seg_out = None
        depth_raw = np.empty((height, width), np.float32) if depth else None
        if rgb:
            rgb_out = np.empty((height, width, 3), np.uint8)
            mujoco.mjr_render(rect, self.scene, gl.con)
            read_depth = depth_raw if (depth and not segmentation) else None
            mujoco.mjr_readPixels(rgb_out, read_depth, rect, gl.con)
            rgb_out = np.ascontiguousarray(rgb_out[::-1])  # OpenGL rows run bottom-up
        if segmentation or (depth and not rgb):
            flags = self.scene.flags
            flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = True
            flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = True
            try:
                mujoco.mjr_render(rect, self.scene, gl.con)
                ids = np.empty((height, width, 3), np.uint8) if segmentation else None
                mujoco.mjr_readPixels(ids, depth_raw if depth else None, rect, gl.con)
            finally:
                flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = False
                flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = False
            if segmentation:
                seg_out = np.ascontiguousarray(self._geom_ids(ids)[::-1])
        if depth:
            depth_out = np.ascontiguousarray(self._linear_depth(depth_raw)[::-1])
        return rgb_out, depth_out, seg_out

    def _geom_ids(self, ids: np.ndarray) -> np.ndarray:
        """Per pixel MuJoCo geom id from the id-colour pass (-1 for background and non-geom objects)."""
        segid = ids[..., 0].astype(np.int32) | (ids[..., 1].astype(np.int32) << 8) | (ids[..., 2].astype(np.int32) << 16)
        n = self.scene.ngeom
        lut = np.full(n + 1, -1, np.int32)  # segid + 1 -> geom id; segid 0 (+1) is the background
        geom_type = int(mujoco.mjtObj.mjOBJ_GEOM)
        for g in self.scene.geoms[:n]:
            if g.segid >= 0 and g.objtype == geom_type:
                lut[g.segid + 1] = g.objid
        return lut[np.clip(segid, 0, n)]

    def _linear_depth(self, raw: np.ndarray) -> np.ndarray:
        """OpenGL depth buffer (reversed-z, mjDEPTH_ZEROFAR) to metric distance along the camera axis."""
        extent = self.model.stat.extent
        near = np.float32(self.model.vis.map.znear * extent)
        far = np.float32(self.model.vis.map.zfar * extent)
        c = np.float32(-0.5) * (-(far + near) / (far - near)) - np.float32(0.5)
        d = np.float32(-0.5) * (-(np.float32(2) * far * near) / (far - near))
        return (d / (raw.astype(np.float64) + c)).astype(np.float32)

    def close(self) -> None:
        if self._finalizer is not None:
            self._finalizer()  # frees the GL resources once
            self._finalizer = None
        self._gl = None


# ------------------------------------------------------------------------------------------------
# the world: state of a compiled model
# ------------------------------------------------------------------------------------------------
class MujocoWorld:
    """A compiled ``(MjModel, MjData)`` seen through the scene's bodies.

    Args:
        model, data: the compiled model and its data.
        body_ids: MuJoCo body id of each scene body, in scene order.
        geom_label: per MuJoCo geom, its segmentation label: scene body index, ``-1``
            (background, ground, anything else) or ``-2`` (robot, table).
        geom_owner: per MuJoCo geom, the name :meth:`contacts` reports for it: a scene body's
            name, ``"ground"``, ``"table"``, ``"robot"`` or ``""`` (not reported).
            :func:`label_geoms` computes both arrays.

    Dynamic scene bodies have a free joint; :meth:`freeze` also uses a weld equality from the
    world to the body (``eq_obj1id == 0``, off by default) when the model has one. Everything
    that changes the model at run time (camera poses, colours, poses of static bodies) is
    remembered at construction and restored by :meth:`reset`.
    """

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData, body_ids: Sequence[int],
                 geom_label: np.ndarray, geom_owner: Sequence[str]):
        self.model, self.data = model, data
        self.body_ids = [int(b) for b in body_ids]
        self.geom_label = np.asarray(geom_label, dtype=np.int32)
        self.geom_owner = list(geom_owner)
        # free joint of each scene body (None for static / welded bodies)
        self.qpos_adr: list[int | None] = []
        self.dof_adr: list[int | None] = []
        for b in self.body_ids:
            j = model.body_jntadr[b]
            if model.body_jntnum[b] == 1 and model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
                self.qpos_adr.append(int(model.jnt_qposadr[j]))
                self.dof_adr.append(int(model.jnt_dofadr[j]))
            else:
                self.qpos_adr.append(None)
                self.dof_adr.append(None)
        self.body_geoms = [np.flatnonzero(model.geom_bodyid == b) for b in self.body_ids]
        # weld equality (world -> body) of each scene body, used by freeze(); None if the model has none
        welds = {int(model.eq_obj2id[e]): e for e in range(model.neq)
                 if model.eq_type[e] == mujoco.mjtEq.mjEQ_WELD and model.eq_obj1id[e] == 0
                 and model.eq_objtype[e] == mujoco.mjtObj.mjOBJ_BODY}
        self.freeze_welds: list[int | None] = [welds.get(b) if self.qpos_adr[i] is not None else None
                                               for i, b in enumerate(self.body_ids)]
        # controllers called every physics step, between mj_step1 (positions, velocities) and
        # mj_step2 (forces, integration): they read the current state and write data.ctrl
        self.controllers: list[Callable[[mujoco.MjModel, mujoco.MjData], None]] = []
        self.frozen: dict[int, np.ndarray] = {}  # scene body index -> held qpos (7,)
        self._saved = {k: getattr(model, k).copy() for k in ("body_pos", "body_quat", "cam_pos", "cam_quat",
                                                               "cam_fovy", "geom_rgba", "mat_rgba")}
        self._renderer: OffscreenRenderer | None = None
        self._fresh = False  # whether derived quantities (xpos, contacts, cameras) match the state
        self.forward()

    # -- time and stepping -----------------------------------------------------------------
    @property
    def time(self) -> float:
        return float(self.data.time)

    def step(self, n: int = 1) -> None:
        """Advance ``n`` physics steps, holding frozen bodies and running the controllers."""
        m, d = self.model, self.data
        if n <= 0:
            return
        self._fresh = False
        if not self.frozen and not self.controllers:
            mujoco.mj_step(m, d, nstep=n)
            return
        for _ in range(n):
            self._hold_frozen()
            if self.controllers:
                mujoco.mj_step1(m, d)  # kinematics, contacts, mass matrix, bias forces of this state
                for control in self.controllers:
                    control(m, d)
                mujoco.mj_step2(m, d)  # actuation, constraint forces, integration
            else:
                mujoco.mj_step(m, d)
        self._hold_frozen()

    def forward(self) -> None:
        """Recompute positions, contacts and cameras for the current state (no time passes).

        The solver's warm start is kept, so observing never changes the trajectory.
        """
        if self._fresh:
            return
        warm = self.data.qacc_warmstart.copy()
        mujoco.mj_forward(self.model, self.data)
        self.data.qacc_warmstart[:] = warm
        self._fresh = True

    def invalidate(self) -> None:
        """Mark derived quantities stale after writing to the state or model directly."""
        self._fresh = False

    # -- poses and velocities of scene bodies (index i in scene order) ------------------------
    def pose(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        adr = self.qpos_adr[i]
        if adr is not None:
            q = self.data.qpos[adr:adr + 7]
            return q[:3].copy(), q[3:7] / np.linalg.norm(q[3:7])
        b = self.body_ids[i]
        if self.model.body_parentid[b] == 0 and self.model.body_mocapid[b] < 0:
            return self.model.body_pos[b].copy(), self.model.body_quat[b].copy()  # static: exact
        self.forward()
        return self.data.xpos[b].copy(), self.data.xquat[b].copy()

    def set_pose(self, i: int, pos: np.ndarray, quat: np.ndarray | None) -> None:
        adr = self.qpos_adr[i]
        if adr is not None:
            self.data.qpos[adr:adr + 3] = pos
            if quat is not None:
                self.data.qpos[adr + 3:adr + 7] = quat
            if i in self.frozen:  # a frozen body is held where it was put
                self.frozen[i] = self.data.qpos[adr:adr + 7].copy()
                self._weld(i, self.frozen[i])
        else:  # static body: move it in the model
            b = self.body_ids[i]
            self.model.body_pos[b] = pos
            if quat is not None:
                self.model.body_quat[b] = quat
        self._fresh = False

    def velocity(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """World-frame linear velocity of the body frame's origin and world-frame angular velocity."""
        dof = self.dof_adr[i]
        if dof is None:
            return np.zeros(3), np.zeros(3)
        v = self.data.qvel[dof:dof + 6]
        rot = quat_to_mat(self.pose(i)[1])
        return v[:3].copy(), rot @ v[3:6]  # free-joint angular velocity is in the body frame

    def set_velocity(self, i: int, linear: np.ndarray, angular: np.ndarray) -> None:
        dof = self.dof_adr[i]
        rot = quat_to_mat(self.pose(i)[1])
        self.data.qvel[dof:dof + 3] = linear
        self.data.qvel[dof + 3:dof + 6] = rot.T @ np.asarray(angular)  # world -> body frame
        self._fresh = False

    def is_static(self, i: int) -> bool:
        return self.qpos_adr[i] is None

    # -- freezing ---------------------------------------------------------------------------
    def freeze(self, i: int) -> None:
        """Hold body ``i`` at its current pose with zero velocity; it still collides.

        The body's weld to the world (see :func:`build_spec`) is switched on at the current pose,
        so the constraint solver supports what rests on it like a static body; before and after
        every step the body is also put back exactly, so it never drifts.
        """
        adr = self.qpos_adr[i]
        if adr is None:
            return  # static bodies never move
        held = self.data.qpos[adr:adr + 7].copy()
        self.frozen[i] = held
        self._weld(i, held)
        self._hold_frozen()
        self._fresh = False

    def unfreeze(self, i: int) -> None:
        if self.frozen.pop(i, None) is not None:
            if self.freeze_welds[i] is not None:
                self.data.eq_active[self.freeze_welds[i]] = 0
            self._fresh = False

    def _weld(self, i: int, held: np.ndarray) -> None:
        """Switch on body ``i``'s weld to the world at pose ``held`` (pos, quat)."""
        eq = self.freeze_welds[i]
        if eq is None:
            return  # models without a weld: the body is only put back every step
        self.model.eq_data[eq, 0:3] = 0.0  # anchor at the body's origin
        self.model.eq_data[eq, 3:10] = held  # relative pose of the body in the world frame
        self.data.eq_active[eq] = 1

    def _hold_frozen(self) -> None:
        """Put frozen bodies back at their held pose, at rest."""
        for i, held in self.frozen.items():
            adr, dof = self.qpos_adr[i], self.dof_adr[i]
            self.data.qpos[adr:adr + 7] = held
            self.data.qvel[dof:dof + 6] = 0.0

    # -- contacts ---------------------------------------------------------------------------
    def contact_pairs(self) -> list[tuple[int, int]]:
        """Geom id pairs touching or penetrating in the current state (near misses within a margin excluded)."""
        self.forward()
        con = self.data.contact
        n = self.data.ncon
        touching = con.dist[:n] <= 0.0
        return list(zip(con.geom1[:n][touching].tolist(), con.geom2[:n][touching].tolist()))

    def touching(self, geoms: Sequence[int] | np.ndarray, exclude: Sequence[str] = ()) -> list[str]:
        """Names (see ``geom_owner``) of what touches any of ``geoms``, in contact order.

        Contacts among ``geoms`` themselves and names in ``exclude`` are left out.
        """
        mine = {int(g) for g in geoms}
        names: list[str] = []
        for g1, g2 in self.contact_pairs():
            if (g1 in mine) == (g2 in mine):
                continue  # not involving these geoms, or between two of them
            name = self.geom_owner[g2 if g1 in mine else g1]
            if name and name not in names and name not in exclude:
                names.append(name)
        return names

    def contacts(self, i: int) -> list[str]:
        """Names of what touches scene body ``i``."""
        return self.touching(self.body_geoms[i])

    # -- appearance and cameras -------------------------------------------------------------
    def set_rgba(self, i: int, rgba) -> None:
        for g in self.body_geoms[i]:
            self.model.geom_rgba[g] = rgba
            mat = self.model.geom_matid[g]
            if mat >= 0:  # textured geoms: the colour also tints the texture
                self.model.mat_rgba[mat] = rgba

    def set_camera(self, camera_id: int, pos, quat, fovy: float) -> None:
        self.model.cam_pos[camera_id] = pos
        self.model.cam_quat[camera_id] = quat
        self.model.cam_fovy[camera_id] = fovy
        self._fresh = False

    def render(self, camera_id: int, width: int, height: int, *, rgb: bool = True, depth: bool = False,
               segmentation: bool = False) -> Frame:
        """One camera image; segmentation holds :attr:`geom_label` per pixel (-1 where no geom)."""
        self.forward()
        if self._renderer is None:
            self._renderer = OffscreenRenderer(self.model)
        image, dist, ids = self._renderer.render(self.data, camera_id, width, height, rgb=rgb, depth=depth,
                                                 segmentation=segmentation)
        seg = None
        if ids is not None:
            lut = np.append(self.geom_label, np.int32(SEG_BACKGROUND))  # id -1 reads the last entry
            seg = lut[ids].astype(np.int32)
        return Frame(rgb=image, depth=dist, segmentation=seg)

    # -- lifecycle --------------------------------------------------------------------------
    def reset(self) -> None:
        """Back to the model's initial state: time 0, nothing frozen, run-time model edits undone."""
        for key, value in self._saved.items():
            getattr(self.model, key)[:] = value
        mujoco.mj_resetData(self.model, self.data)
        self.frozen.clear()
        self._fresh = False
        self.forward()

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


# ------------------------------------------------------------------------------------------------
# the Simulation interface
# ------------------------------------------------------------------------------------------------
class MujocoSimulation(Simulation):
    """A Scene simulated by MuJoCo and rendered headless through EGL.

    Options (``physint_backends.make("mujoco", scene, **options)``):
        robot_visual: ``"collision"`` (default) draws the Panda with its low-poly collision
            meshes (~8x faster to render, ~30x faster to build); ``"full"`` draws robosuite's
            detailed visual meshes.
        goal_update_mode: overrides the scene robot's ``goal_mode`` (see ``spec.Robot``):
            ``"achieved"`` from where the hand is now, ``"desired"`` from the previous goal.
    """

    backend = "mujoco"

    def __init__(self, scene: Scene, robot_visual: str = "collision", goal_update_mode: str | None = None):
        if robot_visual not in ("collision", "full"):
            raise SpecError(f"robot_visual {robot_visual!r} is not supported; allowed: collision, full")
        if goal_update_mode not in (None, "achieved", "desired"):
            raise SpecError(f"goal_update_mode {goal_update_mode!r} is not supported; allowed: achieved, desired")
        self.robot_visual = robot_visual
        self.goal_update_mode = goal_update_mode
        self.world: MujocoWorld | None = None
        self._build(scene)

    # -- building ----------------------------------------------------------------------------
    def _build(self, scene: Scene) -> None:
        """Compile ``scene`` into a fresh model, world and robot; only then replace the old ones."""
        if not isinstance(scene, Scene):
            raise SpecError(f"scene must be a physint_backends.Scene, got {type(scene).__name__}")
        built = build_spec(scene, robot_visual=self.robot_visual)
        try:
            model = built.spec.compile()
        except ValueError as exc:
            raise SpecError(f"MuJoCo cannot build this scene: {exc}") from None
        data = mujoco.MjData(model)
        body_ids = [model.body(n).id for n in built.body_names]
        names = [b.name for b in scene.bodies]
        geom_label, geom_owner = label_geoms(model, body_ids, names, built)
        world = MujocoWorld(model, data, body_ids, geom_label, geom_owner)
        configure_contacts(world, scene)
        robot = None
        if scene.robot is not None:
            from .mujoco_panda import MujocoPanda

            robot = MujocoPanda(world, scene.robot, names,
                                goal_update_mode=self.goal_update_mode or scene.robot.goal_mode)
        # everything built: replace the previous world
        if self.world is not None:
            self.world.close()
        self._install(scene, world, robot, [model.camera(n).id for n in built.camera_names])

    def _install(self, scene: Scene, world: MujocoWorld, robot, camera_ids: list[int]) -> None:
        """Make a freshly built world (and robot) this simulation's, after the old one is closed."""
        Simulation.__init__(self, scene)
        self.world = world
        self.robot = robot
        self._camera_ids = camera_ids
        self._cameras = {c.name: c for c in scene.cameras}  # current camera specs (set_camera edits)

    @property
    def model(self) -> mujoco.MjModel:
        return self.world.model

    @property
    def data(self) -> mujoco.MjData:
        return self.world.data

    # -- time --------------------------------------------------------------------------------
    @property
    def time(self) -> float:
        return self.world.time

    def step(self, n: int = 1) -> None:
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
            raise SpecError(f"step count must be a non-negative integer, got {n!r}")
        try:
            self.world.step(int(n))
        except mujoco.FatalError as exc:  # e.g. a collision routine's contact overflow: this world is lost
            raise SimulationError(f"MuJoCo failed at t = {self.world.time:.3f} s: {exc}") from None

    # -- bodies ------------------------------------------------------------------------------
    def get_pose(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        return self.world.pose(self._check_body(name))

    def set_pose(self, name: str, pos, quat=None) -> None:
        i = self._check_body(name)
        p, q = self._check_pose(name, pos, quat)
        self.world.set_pose(i, p, q)

    def get_velocity(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        return self.world.velocity(self._check_body(name))

    def set_velocity(self, name: str, linear, angular=(0.0, 0.0, 0.0)) -> None:
        i = self._check_body(name)
        lin, ang = self._check_velocity(name, linear, angular)
        if self.world.is_static(i):
            raise SpecError(f"body {name!r} is static; only dynamic bodies have a velocity")
        self.world.set_velocity(i, lin, ang)

    def freeze(self, name: str) -> None:
        self.world.freeze(self._check_body(name))

    def unfreeze(self, name: str) -> None:
        self.world.unfreeze(self._check_body(name))

    def contacts(self, name: str) -> list[str]:
        return self.world.contacts(self._check_body(name))

    # -- rendering ---------------------------------------------------------------------------
    def render(self, camera: str, rgb: bool = True, depth: bool = False, segmentation: bool = False) -> Frame:
        self._check_camera(camera)
        cam = self._cameras[camera]
        cid = self._camera_ids[self.camera_names.index(camera)]
        return self.world.render(cid, cam.width, cam.height, rgb=bool(rgb), depth=bool(depth),
                                 segmentation=bool(segmentation))

    def set_camera(self, name: str, pos=None, lookat=None, fovy=None) -> None:
        self._check_camera(name)
        old = self._cameras[name]
        changes = {k: v for k, v in (("pos", pos), ("lookat", lookat), ("fovy", fovy)) if v is not None}
        new = dataclasses.replace(old, **changes)  # validates (raises SpecError) before any change
        self.world.set_camera(self._camera_ids[self.camera_names.index(name)], np.asarray(new.pos),
                              camera_quat(new), new.fovy)
        self._cameras[name] = new

    def set_rgba(self, name: str, rgba) -> None:
        i = self._check_body(name)
        self.world.set_rgba(i, _rgba(rgba, f"rgba of {name!r}"))

    # -- lifecycle ---------------------------------------------------------------------------
    def reset(self, scene: Scene | None = None) -> None:
        if scene is not None:
            self._build(scene)
            return
        self.world.reset()
        self._cameras = {c.name: c for c in self.scene.cameras}
        if self.robot is not None:
            self.robot.reset()

    def close(self) -> None:
        if self.world is not None:
            self.world.close()


def label_geoms(model: mujoco.MjModel, body_ids: Sequence[int], body_names: Sequence[str],
                built: BuiltScene | None = None, robot_root: int | None = None,
                table_geoms: Sequence[int] = (), ground_geoms: Sequence[int] = ()) -> tuple[np.ndarray, list[str]]:
    """Segmentation label and contact name of every geom of ``model``.

    Scene bodies (``body_ids``, scene order) get their index and name; geoms in the robot's
    subtree (``robot_root``) get ``-2`` / ``"robot"``; ``table_geoms`` get ``-2`` / ``"table"``;
    ``ground_geoms`` get ``-1`` / ``"ground"``; everything else ``-1`` / ``""``. With ``built``,
    the robot root, table and ground are read from it.
    """
    if built is not None:
        if built.robot_root is not None:
            robot_root = model.body(built.robot_root).id
        table_geoms = [model.geom(n).id for n in built.table_geoms]
        ground_geoms = [model.geom(built.ground_geom).id] if built.ground_geom else []
    label = np.full(model.ngeom, SEG_BACKGROUND, np.int32)
    owner = [""] * model.ngeom
    body_index = {b: i for i, b in enumerate(body_ids)}
    robot_bodies = set()
    if robot_root is not None:
        for b in range(model.nbody):  # the robot's subtree: walk parents up to the root
            a = b
            while a > 0 and a != robot_root:
                a = model.body_parentid[a]
            if a == robot_root:
                robot_bodies.add(b)
    for g in range(model.ngeom):
        b = int(model.geom_bodyid[g])
        if b in body_index:
            label[g], owner[g] = body_index[b], body_names[body_index[b]]
        elif b in robot_bodies:
            label[g], owner[g] = SEG_ROBOT, ROBOT
    for g in table_geoms:
        label[g], owner[g] = SEG_ROBOT, TABLE
    for g in ground_geoms:
        label[g], owner[g] = SEG_BACKGROUND, GROUND
    return label, owner
