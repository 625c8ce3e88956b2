"""PyBullet backend: a backend-neutral :class:`~physint_backends.spec.Scene` on PyBullet.

Each :class:`PybulletSimulation` owns one headless physics server
(``BulletClient(pybullet.DIRECT)``), so any number of simulations can live in one process, and
renders on the CPU with Bullet's TinyRenderer; no window is ever opened. ``reset()`` reuses the
server (``resetSimulation`` + rebuild), so building and tearing down small scenes is cheap.

How the spec maps onto Bullet:

* a body is one rigid Bullet body (maximal coordinates) whose collision and visual shapes are
  its geoms; several geoms become a compound shape. Its centre of mass and inertia
  are computed from the geoms (uniform density) and given to Bullet explicitly, because Bullet
  reports and sets the pose of the *centre-of-mass* frame: this module converts to and from the
  body frame of the spec, so ``get_pose`` returns exactly what the scene put in;
* Bullet multiplies the friction coefficients of two touching bodies; every shape is given the
  square root of its spec coefficient, so two bodies touch with the geometric mean of their
  coefficients (the coefficient itself when both are equal, as in MuJoCo). Friction anchors
  keep resting contacts from creeping (without them a 6-cube stack slides ~1 mm/s);
* ``freeze`` makes a body static (mass 0: it still collides, nothing moves it) and
  ``unfreeze`` gives its mass and inertia back;
* the ground is an infinite collision plane with a thin visual slab of ``Ground.size``;
* the first ``Light`` becomes TinyRenderer's directional light (it has only one);
* ``scene.robot`` adds a table, a pedestal and the Franka Panda (see ``pybullet_panda``).
"""

from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import hashlib
import math
import os
import shutil
import sys
import tempfile

import numpy as np
import pybullet
from pybullet_utils.bullet_client import BulletClient

from .base import SEG_BACKGROUND, SEG_ROBOT, Frame, Simulation
from .poses import compose, invert
from .spec import Body, Geom, Light, Scene, SpecError, Texture, _rgba, quat_matrix

GROUND_NAME = "ground"
ROBOT_NAME = "robot"
TABLE_NAME = "table"

# Rolling and spinning friction (m) of bodies with curved geoms, MuJoCo's defaults; Bullet scales
# them by the other body's sliding friction. Flat-faced bodies get none: their several contact
# points already resist spinning, and the extra solver rows would halve the step rate.
ROLLING_FRICTION = 1e-4
SPINNING_FRICTION = 5e-3
CURVED = ("sphere", "cylinder", "mesh")
CYLINDER_SLICES = 28  # sides of a drawn cylinder: MuJoCo's default visual quality.numslices
MESH_MARGIN = 1e-3  # m: Bullet's collision margin around convex hulls (boxes and spheres keep theirs inside)
# Two bodies touch when their surfaces are at most this far apart (m). contacts() measures the
# distance itself rather than reading Bullet's contact manifolds, which miss resting contacts at
# exactly zero distance and lag behind poses set by hand.
TOUCH_DISTANCE = 1e-3


# -- small pose helpers (spec quaternions are w, x, y, z; Bullet's are x, y, z, w) -------------

def to_xyzw(q) -> tuple[float, float, float, float]:
    """Spec quaternion (w, x, y, z) -> Bullet quaternion (x, y, z, w)."""
    return (float(q[1]), float(q[2]), float(q[3]), float(q[0]))


def to_wxyz(q) -> np.ndarray:
    """Bullet quaternion (x, y, z, w) -> spec quaternion (w, x, y, z) as an array."""
    return np.array((q[3], q[0], q[1], q[2]), dtype=float)


def matrix_quat(m: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a proper rotation matrix (Shepperd's method)."""
    t = np.trace(m)
    if t > 0:
        s = 2.0 * math.sqrt(t + 1.0)
        q = (0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s)
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = ((m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s)
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = ((m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = ((m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s)
    q = np.asarray(q)
    return q / np.linalg.norm(q)


def shrunk_hull(vertices: np.ndarray, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of the convex hull of ``vertices`` with every face moved ``margin`` inwards.

    A hull thinner than twice the margin, or so thin that its shrunk copy is flat, is returned unshrunk.
    """
    from scipy.spatial import ConvexHull, HalfspaceIntersection, QhullError

    hull = ConvexHull(vertices)
    planes = hull.equations.copy()  # rows (n, d): n . x + d <= 0 inside, |n| = 1
    planes[:, 3] += margin  # each face plane moved inwards by the margin
    centre = vertices[hull.vertices].mean(axis=0)
    if np.max(planes[:, :3] @ centre + planes[:, 3]) < -1e-9:  # still strictly inside: shrinkable
        try:
            points = HalfspaceIntersection(planes, centre).intersections
            return points, ConvexHull(points).simplices
        except QhullError:  # the shrunk hull is (nearly) flat: no thicker than twice the margin after all
            pass
    return vertices, hull.simplices


# -- mass properties ---------------------------------------------------------------------------

def geom_inertia(geom: Geom, mass: float) -> tuple[np.ndarray, np.ndarray]:
    """Centre of mass and inertia tensor (about that centre) of a solid geom, in the body frame."""
    if geom.shape == "box":
        x, y, z = geom.size
        local_com = np.zeros(3)
        local = mass / 12.0 * np.diag([y * y + z * z, x * x + z * z, x * x + y * y])
    elif geom.shape == "cylinder":
        r, h = geom.size
        local_com = np.zeros(3)
        side = mass * (3 * r * r + h * h) / 12.0  # about a diameter through the centre
        local = np.diag([side, side, 0.5 * mass * r * r])  # axis along local z
    elif geom.shape == "sphere":
        local_com = np.zeros(3)
        local = np.eye(3) * 0.4 * mass * geom.size[0] ** 2
    else:  # convex mesh: its hull as a uniform solid
        hull = geom.mesh.convex_hull
        local_com = np.asarray(hull.center_mass, dtype=float)
        local = np.asarray(hull.moment_inertia, dtype=float) * (mass / float(hull.mass))
    rot = quat_matrix(geom.quat)
    return np.asarray(geom.pos) + rot @ local_com, rot @ local @ rot.T


@dataclasses.dataclass
class MassProperties:
    """What Bullet needs: total mass, and the principal inertial frame in the body frame."""

    mass: float
    com: np.ndarray  # (3,) centre of mass, body frame
    axes_xyzw: tuple[float, float, float, float]  # principal axes, body frame, Bullet order
    diagonal: np.ndarray  # (3,) principal moments of inertia, kg m^2

    @property
    def at_origin(self) -> bool:
        """Whether the inertial frame is the body frame (then no pose conversion is needed)."""
        return bool(np.allclose(self.com, 0.0, atol=1e-12) and np.allclose(self.axes_xyzw, (0, 0, 0, 1), atol=1e-12))


def mass_properties(body: Body) -> MassProperties:
    """Combine the body's geoms (mass shared by volume) into one rigid body's mass properties."""
    total = body.total_mass
    volumes = np.array([g.volume() for g in body.geoms], dtype=float)
    shares = volumes / volumes.sum() if volumes.sum() > 0 else np.full(len(volumes), 1.0 / len(volumes))
    parts = [geom_inertia(g, total * s) for g, s in zip(body.geoms, shares)]
    com = sum(total * s * c for s, (c, _) in zip(shares, parts)) / total
    inertia = np.zeros((3, 3))
    for s, (c, i_c) in zip(shares, parts):
        d = c - com  # parallel-axis theorem: move each geom's inertia to the common centre
        inertia += i_c + total * s * (d @ d * np.eye(3) - np.outer(d, d))
    moments, axes = np.linalg.eigh(inertia)
    if np.allclose(inertia, np.diag(np.diag(inertia)), atol=1e-14 * max(1.0, abs(inertia).max())):
        moments, axes = np.diag(inertia).copy(), np.eye(3)  # already principal: keep body axes
    if np.linalg.det(axes) < 0:
        axes[:, 2] = -axes[:, 2]  # a proper rotation, not a reflection
    axes_xyzw = to_xyzw(matrix_quat(axes))
    return MassProperties(total, np.asarray(com, dtype=float), axes_xyzw, np.maximum(moments, 1e-12))


# -- simulation --------------------------------------------------------------------------------

@dataclasses.dataclass
class _Live:
    """Bookkeeping for one spec body living in Bullet."""

    uid: int
    static: bool
    props: MassProperties | None  # None for static bodies
    com_pos: tuple[float, float, float]  # inertial frame in the body frame
    com_orn: tuple[float, float, float, float]
    origin_pos: tuple[float, float, float]  # body frame in the inertial frame (the inverse)
    origin_orn: tuple[float, float, float, float]
    at_origin: bool
    n_shapes: int  # visual shapes on the base
    frozen: bool = False
    link_shapes: tuple[int, ...] = ()  # visual shapes on each extra (fixed, visual-only) link


MAX_VISUAL_SHAPES = 16  # createVisualShapeArray crashes PyBullet 3.2.7 beyond 16 shapes


class PybulletSimulation(Simulation):
    """A live PyBullet world built from a :class:`Scene`.

    Options (all keyword-only):

    * ``solver_iterations``: constraint solver iterations per step (stacks need many);
    * ``robot_visual``: ``"collision"`` draws the Panda with its low-poly collision meshes
      (much faster TinyRenderer images), ``"full"`` with its detailed visual meshes (as on the other backends);
    * ``near``, ``far``: camera clipping planes in metres (background depth reads ``far``).
    """

    backend = "pybullet"

    def __init__(self, scene: Scene, *, solver_iterations: int = 50, robot_visual: str = "collision",
                 near: float = 0.01, far: float = 20.0):
        if not isinstance(scene, Scene):
            raise SpecError(f"PybulletSimulation needs a physint_backends.spec.Scene, got {type(scene).__name__}")
        if robot_visual not in ("collision", "full"):
            raise SpecError(f"robot_visual must be 'collision' or 'full', got {robot_visual!r}")
        if not (isinstance(solver_iterations, int) and solver_iterations >= 1):
            raise SpecError(f"solver_iterations must be a positive integer, got {solver_iterations!r}")
        if not (0 < near < far and math.isfinite(far)):
            raise SpecError(f"camera planes need 0 < near < far, got near={near}, far={far}")
        super().__init__(scene)
        self.solver_iterations = solver_iterations
        self.robot_visual = robot_visual
        self.near, self.far = float(near), float(far)
        with _silence_stdout():  # Bullet's C code greets with "argv[0]=" on stdout, which carries results
            self._p = BulletClient(connection_mode=pybullet.DIRECT)
        self._cid = self._p._client  # physics client id, for direct calls on hot paths
        self._tmpdir: str | None = None  # PNG textures and mesh .obj files, made on first need
        self._files: dict[str, str] = {}  # content hash -> file written to _tmpdir
        self._build()

    # -- building ------------------------------------------------------------------------------
    def _build(self) -> None:
        """Create every body, the ground, the robot, cameras and lights of ``self.scene``."""
        scene, p = self.scene, self._p
        p.resetSimulation()
        p.setGravity(*scene.gravity)
        p.setPhysicsEngineParameter(fixedTimeStep=scene.timestep, numSubSteps=0,
                                    numSolverIterations=self.solver_iterations,
                                    deterministicOverlappingPairs=1)
        self._steps = 0
        self._textures: dict[str, int] = {}  # file -> Bullet texture id (cleared by resetSimulation)
        self._live: list[_Live] = []
        self._names: dict[int, str] = {}  # Bullet uid -> name reported by contacts()
        self.body_names = [b.name for b in scene.bodies]
        self.camera_names = [c.name for c in scene.cameras]
        self._cameras = {c.name: dataclasses.replace(c) for c in scene.cameras}  # set_camera edits these
        self._matrices: dict[str, tuple[list[float], list[float]]] = {}

        self.ground_uid = self._add_ground() if scene.ground is not None else None
        for body in scene.bodies:
            self._live.append(self._add_body(body))
            self._names[self._live[-1].uid] = body.name

        self.robot = None
        self._robot_uids: set[int] = set()
        if scene.robot is not None:
            from .pybullet_panda import PybulletPanda

            self.robot = PybulletPanda(self, scene.robot)
            for uid in self.robot.uids:
                self._robot_uids.add(uid)
            self._names[self.robot.arm] = ROBOT_NAME
            if self.robot.mount_uid is not None:
                self._names[self.robot.mount_uid] = ROBOT_NAME  # the pedestal is part of the robot
            if self.robot.table_uid is not None:
                self._names[self.robot.table_uid] = TABLE_NAME

        # segmentation lookup: Bullet uid + 1 -> body index, -1 background, -2 robot
        lut = np.full(p.getNumBodies() + 1, SEG_BACKGROUND, dtype=np.int32)
        for index, live in enumerate(self._live):
            lut[live.uid + 1] = index
        for uid in self._robot_uids:
            lut[uid + 1] = SEG_ROBOT
        self._seg_lut = lut
        self._set_light(scene.lights[0] if scene.lights else Light())
        self._background = np.round(np.asarray(scene.background) * 255).astype(np.uint8)

    def _add_ground(self) -> int:
        """An infinite collision plane at z = 0, drawn as a square of the ground's size and look.

        The square is a mesh whose texture coordinates run to ``texture.repeat``, so the renderer
        tiles the texture as MuJoCo tiles its plane's (a box slab mapped a pre-tiled image about 4x
        too coarse: ``test_ground_texture_tiles_at_the_same_scale``).
        """
        ground, p = self.scene.ground, self._p
        col = p.createCollisionShape(pybullet.GEOM_PLANE)
        half = ground.size
        ru, rv = ground.texture.repeat if ground.texture is not None else (1.0, 1.0)
        vis = p.createVisualShape(pybullet.GEOM_MESH, vertices=[[-half, -half, 0], [half, -half, 0], [half, half, 0],
                                                                [-half, half, 0]],
                                  indices=[0, 1, 2, 0, 2, 3], uvs=[[0, 0], [ru, 0], [ru, rv], [0, rv]],
                                  normals=[[0, 0, 1]] * 4, rgbaColor=list(ground.rgba))
        uid = p.createMultiBody(0.0, col, vis, [0, 0, 0])
        p.changeDynamics(uid, -1, lateralFriction=math.sqrt(ground.friction), frictionAnchor=1)
        if ground.texture is not None:
            p.changeVisualShape(uid, -1, textureUniqueId=self._texture(ground.texture))
        self._names[uid] = GROUND_NAME
        return uid

    def _add_body(self, body: Body) -> _Live:
        """One spec body as one Bullet body (a compound shape when it has several geoms)."""
        p = self._p
        links: dict = {}
        chunks: list[list[Geom]] = []
        if not body.collide:  # drawn only
            col = -1
            vis = p.createVisualShapeArray(**_stack_args([self._shape_args(g, "visual") for g in body.geoms[:MAX_VISUAL_SHAPES]],
                                                         "visual"))
            if len(body.geoms) > MAX_VISUAL_SHAPES:
                raise SpecError(f"body {body.name!r}: the pybullet backend draws at most {MAX_VISUAL_SHAPES} geoms "
                                f"of a body that does not collide, got {len(body.geoms)}")
        elif len(body.geoms) == 1:
            col = p.createCollisionShape(**self._shape_args(body.geoms[0], "collision"))
            vis = p.createVisualShape(**self._shape_args(body.geoms[0], "visual"))
        else:
            col_args = [self._shape_args(g, "collision") for g in body.geoms]
            col = p.createCollisionShapeArray(**_stack_args(col_args, "collision"))
            chunks = [body.geoms[i:i + MAX_VISUAL_SHAPES] for i in range(0, len(body.geoms), MAX_VISUAL_SHAPES)]
            if len(chunks) > 1 and not body.static:
                raise SpecError(f"body {body.name!r}: the pybullet backend draws at most {MAX_VISUAL_SHAPES} geoms "
                                f"of a moving body, got {len(body.geoms)}")
            vis = p.createVisualShapeArray(**_stack_args([self._shape_args(g, "visual") for g in chunks[0]], "visual"))
            if len(chunks) > 1:  # a static body's further geoms are drawn by fixed, visual-only links
                n = len(chunks) - 1
                links = dict(
                    linkMasses=[0.0] * n, linkCollisionShapeIndices=[-1] * n,
                    linkVisualShapeIndices=[p.createVisualShapeArray(**_stack_args(
                        [self._shape_args(g, "visual") for g in chunk], "visual")) for chunk in chunks[1:]],
                    linkPositions=[[0, 0, 0]] * n, linkOrientations=[[0, 0, 0, 1]] * n,
                    linkInertialFramePositions=[[0, 0, 0]] * n, linkInertialFrameOrientations=[[0, 0, 0, 1]] * n,
                    linkParentIndices=[0] * n, linkJointTypes=[pybullet.JOINT_FIXED] * n, linkJointAxis=[[0, 0, 1]] * n)
        props = None if body.static else mass_properties(body)
        com_pos = tuple(float(v) for v in props.com) if props else (0.0, 0.0, 0.0)
        com_orn = props.axes_xyzw if props else (0.0, 0.0, 0.0, 1.0)
        uid = p.createMultiBody(baseMass=0.0 if body.static else props.mass,
                                baseCollisionShapeIndex=col, baseVisualShapeIndex=vis,
                                basePosition=list(body.pos), baseOrientation=to_xyzw(body.quat),
                                baseInertialFramePosition=list(com_pos), baseInertialFrameOrientation=list(com_orn),
                                useMaximalCoordinates=not links, **links)
        curved = any(g.shape in CURVED for g in body.geoms)
        dynamics = dict(lateralFriction=math.sqrt(body.friction), frictionAnchor=1,
                        rollingFriction=ROLLING_FRICTION if curved else 0.0,
                        spinningFriction=SPINNING_FRICTION if curved else 0.0,
                        linearDamping=0.0, angularDamping=0.0)
        if props is not None:
            # mass and inertia go together: Bullet zeroes a rigid body's mass when given inertia alone
            dynamics.update(mass=props.mass, localInertiaDiagonal=list(props.diagonal))
        p.changeDynamics(uid, -1, **dynamics)
        for i, geom in enumerate(body.geoms):
            if geom.texture is not None:
                link, shape = divmod(i, MAX_VISUAL_SHAPES)
                p.changeVisualShape(uid, link - 1, shapeIndex=shape if len(body.geoms) > 1 else -1,
                                    textureUniqueId=self._texture(geom.texture))
        origin_pos, origin_orn = invert(com_pos, com_orn)
        return _Live(uid=uid, static=body.static, props=props, com_pos=com_pos, com_orn=com_orn,
                     origin_pos=origin_pos, origin_orn=origin_orn,
                     at_origin=props is None or props.at_origin, n_shapes=len(chunks[0]) if chunks else 1,
                     link_shapes=tuple(len(c) for c in chunks[1:]))

    def _shape_args(self, geom: Geom, kind: str) -> dict:
        """Keyword arguments of create{Collision,Visual}Shape for one geom (spec sizes are full lengths)."""
        args: dict = {}
        if geom.shape == "box":
            args.update(shapeType=pybullet.GEOM_BOX, halfExtents=[s / 2 for s in geom.size])
        elif geom.shape == "cylinder" and kind == "collision":
            args.update(shapeType=pybullet.GEOM_CYLINDER, radius=geom.size[0], height=geom.size[1])
        elif geom.shape == "cylinder":  # Bullet's own cylinder mesh smooths its normals over the rims
            args.update(shapeType=pybullet.GEOM_MESH, fileName=self._cylinder_obj_file(*geom.size), meshScale=[1, 1, 1])
        elif geom.shape == "sphere":
            args.update(shapeType=pybullet.GEOM_SPHERE, radius=geom.size[0])
        else:  # convex mesh: Bullet builds the convex hull of the .obj's vertices for collision
            args.update(shapeType=pybullet.GEOM_MESH, fileName=self._obj_file(geom.mesh, kind), meshScale=[1, 1, 1])
        if kind == "collision":
            args.update(collisionFramePosition=list(geom.pos), collisionFrameOrientation=to_xyzw(geom.quat))
        else:
            args.update(visualFramePosition=list(geom.pos), visualFrameOrientation=to_xyzw(geom.quat),
                        rgbaColor=list(geom.rgba))
        return args

    # -- files for Bullet: textures and meshes -------------------------------------------------
    def _file(self, key: bytes, suffix: str, write) -> str:
        """Path of a cached file named by the hash of ``key``; ``write(path)`` makes it once."""
        digest = hashlib.sha1(key).hexdigest()[:20] + suffix
        path = self._files.get(digest)
        if path is None:
            if self._tmpdir is None:
                self._tmpdir = tempfile.mkdtemp(prefix="physint_pybullet_")
            path = os.path.join(self._tmpdir, digest)
            write(path)
            self._files[digest] = path
        return path

    def _texture(self, texture: Texture) -> int:
        """Bullet texture id of a spec texture."""
        image = texture.image

        def write(path: str) -> None:
            from PIL import Image

            Image.fromarray(np.ascontiguousarray(image)).save(path)

        path = self._file(image.tobytes() + str(image.shape).encode(), ".png", write)
        if path not in self._textures:
            self._textures[path] = self._p.loadTexture(path)
        return self._textures[path]

    def _obj_file(self, mesh, kind: str) -> str:
        """A Wavefront .obj of a convex mesh.

        ``visual``: the mesh with flat per-face normals and planar (x, y) uvs. ``collision``: its
        convex hull shrunk by Bullet's collision margin, which Bullet adds back all round, so the
        body rests on its true surface rather than a millimetre above it.
        """
        vertices = np.asarray(mesh.vertices, dtype=float)
        faces = np.asarray(mesh.faces, dtype=np.int64)

        def write_visual(path: str) -> None:
            corners = vertices[faces]  # (F, 3, 3): every face keeps its own corners, for flat shading
            normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
            normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
            lo, hi = vertices.min(0), vertices.max(0)
            uv = (corners[..., :2] - lo[:2]) / np.maximum(hi[:2] - lo[:2], 1e-9)
            _write_obj(path, corners.reshape(-1, 3), uv.reshape(-1, 2), np.repeat(normals, 3, axis=0),
                       np.arange(3 * len(faces)).reshape(-1, 3))

        def write_collision(path: str) -> None:
            points, triangles = shrunk_hull(vertices, MESH_MARGIN)
            lines = [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in points]
            lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in triangles]
            with open(path, "w") as fh:
                fh.write("\n".join(lines) + "\n")

        key = kind.encode() + vertices.tobytes() + faces.tobytes()
        return self._file(key, ".obj", write_visual if kind == "visual" else write_collision)

    def _cylinder_obj_file(self, radius: float, length: float) -> str:
        """A Wavefront .obj of a cylinder along z, centred on the origin, as MuJoCo draws one.

        The side's normals point straight out and each cap's straight up or down, with the rim
        vertices duplicated, so the rims stay sharp. Bullet's own visual cylinder shares its rim
        normals between side and cap: TinyRenderer then shades a cylinder like a rounded pebble
        and a lying one looks like a sphere. The side's uvs wrap around once (u) along the axis
        (v); the caps' are planar, as on a mesh.
        """
        def write(path: str) -> None:
            n = CYLINDER_SLICES
            angle = np.linspace(0.0, 2 * np.pi, n + 1)  # the seam's column twice, for the uvs
            ring = np.stack([np.cos(angle), np.sin(angle)], axis=1)
            half = length / 2
            # side: a bottom and a top vertex per column, normals radial
            side = np.concatenate([np.column_stack([radius * ring, np.full(n + 1, z)]) for z in (-half, half)])
            side_uv = np.concatenate([np.column_stack([angle / (2 * np.pi), np.full(n + 1, v)]) for v in (0.0, 1.0)])
            side_n = np.concatenate([np.column_stack([ring, np.zeros(n + 1)])] * 2)
            k = np.arange(n)
            bottom, top = k, n + 1 + k  # column k's two vertices; column k + 1's are bottom + 1, top + 1
            side_tri = np.concatenate([np.stack([bottom, bottom + 1, top + 1], 1), np.stack([bottom, top + 1, top], 1)])
            positions, uvs, normals, triangles = [side], [side_uv], [side_n], [side_tri]
            count = len(side)
            for z, up in ((half, 1.0), (-half, -1.0)):  # caps: a centre and a ring, normal along the axis
                cap = np.vstack([[0.0, 0.0, z], np.column_stack([radius * ring[:n], np.full(n, z)])])
                fan = np.stack([np.zeros(n, int), 1 + k, 1 + (k + 1) % n], 1)
                if up < 0:
                    fan = fan[:, [0, 2, 1]]  # counter-clockwise seen from below
                positions.append(cap)
                uvs.append(0.5 + 0.5 * np.vstack([[0.0, 0.0], ring[:n]]))
                normals.append(np.tile([0.0, 0.0, up], (n + 1, 1)))
                triangles.append(fan + count)
                count += n + 1
            _write_obj(path, np.concatenate(positions), np.concatenate(uvs), np.concatenate(normals),
                       np.concatenate(triangles))

        return self._file(f"cylinder {radius!r} {length!r} {CYLINDER_SLICES}".encode(), ".obj", write)

    # -- time ----------------------------------------------------------------------------------
    @property
    def time(self) -> float:
        return self._steps * self.scene.timestep

    def step(self, n: int = 1) -> None:
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
            raise SpecError(f"step count must be a non-negative integer, got {n!r}")
        step, cid = pybullet.stepSimulation, self._cid
        for _ in range(int(n)):
            step(physicsClientId=cid)  # one semi-implicit Euler step of scene.timestep seconds
        self._steps += int(n)

    # -- state of named bodies -----------------------------------------------------------------
    def _com_pose(self, live: _Live):
        return pybullet.getBasePositionAndOrientation(live.uid, physicsClientId=self._cid)

    def get_pose(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        live = self._live[self._check_body(name)]
        pos, orn = self._com_pose(live)
        if not live.at_origin:  # Bullet tracks the centre-of-mass frame: go back to the body frame
            pos, orn = compose(pos, orn, live.origin_pos, live.origin_orn)
        return np.array(pos, dtype=float), to_wxyz(orn)

    def set_pose(self, name: str, pos, quat=None) -> None:
        live = self._live[self._check_body(name)]
        p, q = self._check_pose(name, pos, quat)
        orn = to_xyzw(q) if q is not None else self._body_orn(live)
        com_pos, com_orn = self._to_com(live, p, orn)
        self._p.resetBasePositionAndOrientation(live.uid, com_pos, com_orn)

    def _body_orn(self, live: _Live):
        pos, orn = self._com_pose(live)
        if live.at_origin:
            return orn
        return compose(pos, orn, live.origin_pos, live.origin_orn)[1]

    def _to_com(self, live: _Live, pos, orn_xyzw):
        """Pose of the body's centre-of-mass frame given the pose of its body frame."""
        if live.at_origin:
            return list(pos), list(orn_xyzw)
        return compose(pos, orn_xyzw, live.com_pos, live.com_orn)

    def get_velocity(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        live = self._live[self._check_body(name)]
        lin, ang = pybullet.getBaseVelocity(live.uid, physicsClientId=self._cid)
        lin, ang = np.array(lin, dtype=float), np.array(ang, dtype=float)
        if not live.at_origin:  # velocity of the body origin: v_o = v_com + w x (o - com)
            com = np.asarray(self._com_pose(live)[0])
            origin, _ = self.get_pose(name)
            lin = lin + np.cross(ang, origin - com)
        return lin, ang

    def set_velocity(self, name: str, linear, angular=(0.0, 0.0, 0.0)) -> None:
        live = self._live[self._check_body(name)]
        lin, ang = self._check_velocity(name, linear, angular)
        if live.static or live.frozen:
            return  # static and frozen bodies do not move
        if not live.at_origin:  # v_com = v_o + w x (com - o)
            com = np.asarray(self._com_pose(live)[0])
            origin, _ = self.get_pose(name)
            lin = lin + np.cross(ang, com - origin)
        self._p.resetBaseVelocity(live.uid, list(lin), list(ang))

    def freeze(self, name: str) -> None:
        live = self._live[self._check_body(name)]
        if live.static or live.frozen:
            return
        self._p.resetBaseVelocity(live.uid, [0, 0, 0], [0, 0, 0])
        self._p.changeDynamics(live.uid, -1, mass=0.0)  # infinite inertia: it collides but nothing moves it
        live.frozen = True

    def unfreeze(self, name: str) -> None:
        live = self._live[self._check_body(name)]
        if not live.frozen:
            return
        # mass and inertia back, and wake it (and, through contacts, what rests on it) up
        self._p.changeDynamics(live.uid, -1, mass=live.props.mass, localInertiaDiagonal=list(live.props.diagonal),
                               activationState=pybullet.ACTIVATION_STATE_WAKE_UP)
        live.frozen = False

    def contacts(self, name: str) -> list[str]:
        live = self._live[self._check_body(name)]
        return sorted(self._names.get(uid, "?") for uid in self.touching_uids(live.uid))

    def touching_uids(self, uid: int, link: int = -1) -> set[int]:
        """Bullet bodies whose surfaces are within ``TOUCH_DISTANCE`` of body ``uid`` (its ``link``).

        Candidates come from the broadphase (bounding boxes overlapping this one, grown by the
        touch distance); each is confirmed by an exact closest-distance query. Nothing here
        changes the simulation state.
        """
        cid, d = self._cid, TOUCH_DISTANCE
        lo, hi = pybullet.getAABB(uid, link, physicsClientId=cid)
        near = pybullet.getOverlappingObjects([v - d for v in lo], [v + d for v in hi], physicsClientId=cid) or ()
        found = set()
        for other in {o for o, _ in near if o != uid}:
            if pybullet.getClosestPoints(uid, other, d, linkIndexA=link, physicsClientId=cid):
                found.add(other)
        return found

    # -- rendering -----------------------------------------------------------------------------
    def _set_light(self, light: Light) -> None:
        """TinyRenderer's single directional light from a spec light.

        TinyRenderer shades ``colour * light_colour * (ambient + min(diffuse * max(0, n.l), 1 - ambient))``;
        the light's diffuse and ambient colours become the coefficients (their means) and a
        light colour (their normalised sum).
        """
        direction = np.subtract(light.pos, light.lookat)  # from the scene towards the light
        norm = np.linalg.norm(direction)
        direction = direction / norm if norm > 1e-9 else np.array([0.0, 0.0, 1.0])
        diffuse, ambient = np.clip(light.diffuse, 0, None), np.clip(light.ambient, 0, None)
        colour = diffuse + ambient
        colour = colour / colour.max() if colour.max() > 0 else np.ones(3)
        self._light = dict(lightDirection=direction.tolist(), lightColor=colour.tolist(),
                           lightAmbientCoeff=float(ambient.mean()), lightDiffuseCoeff=float(diffuse.mean()),
                           lightSpecularCoeff=0.0, shadow=0)

    def _camera_matrices(self, name: str) -> tuple[list[float], list[float]]:
        """OpenGL view and projection matrices (column-major lists) for a named camera."""
        cached = self._matrices.get(name)
        if cached is not None:
            return cached
        cam = self._cameras[name]
        rot = cam.rotation()  # world-from-camera, the same frame Camera.project uses
        view = np.eye(4)
        view[:3, :3] = rot.T
        view[:3, 3] = -rot.T @ np.asarray(cam.pos)
        f = 1.0 / math.tan(math.radians(cam.fovy) / 2)  # vertical focal length in clip units
        n, fa = self.near, self.far
        # TinyRenderer samples pixel (column i, row j from the top) at (i, j + 1) rather than at its
        # centre (i + 0.5, j + 0.5): shift the image half a pixel left and up to match OpenGL
        proj = np.array([[f * cam.height / cam.width, 0, 1.0 / cam.width, 0],
                         [0, f, 1.0 / cam.height, 0],
                         [0, 0, (fa + n) / (n - fa), 2 * fa * n / (n - fa)],
                         [0, 0, -1, 0]])
        cached = (view.T.reshape(-1).tolist(), proj.T.reshape(-1).tolist())
        self._matrices[name] = cached
        return cached

    def render(self, camera: str, rgb: bool = True, depth: bool = False, segmentation: bool = False) -> Frame:
        self._check_camera(camera)  # raises SpecError for an unknown name
        cam = self._cameras[camera]
        frame = Frame()
        if not (rgb or depth or segmentation):
            return frame
        view, proj = self._camera_matrices(camera)
        flags = 0 if segmentation else pybullet.ER_NO_SEGMENTATION_MASK
        _, _, colour, zbuf, seg = pybullet.getCameraImage(
            cam.width, cam.height, viewMatrix=view, projectionMatrix=proj, renderer=pybullet.ER_TINY_RENDERER,
            flags=flags, physicsClientId=self._cid, **self._light)
        if rgb:
            frame.rgb = np.ascontiguousarray(np.reshape(colour, (cam.height, cam.width, 4))[..., :3], dtype=np.uint8)
            # TinyRenderer clears to white: paint the scene's background where nothing was drawn
            empty = np.reshape(np.asarray(zbuf), (cam.height, cam.width)) >= 1.0 - 1e-6
            frame.rgb[empty] = self._background
        if depth:  # invert the perspective depth buffer to metres along the camera axis
            z = np.reshape(np.asarray(zbuf, dtype=np.float64), (cam.height, cam.width))
            n, fa = self.near, self.far
            frame.depth = (fa * n / (fa - (fa - n) * z)).astype(np.float32)
        if segmentation:
            ids = np.reshape(np.asarray(seg, dtype=np.int64), (cam.height, cam.width))
            ids = np.clip(ids + 1, 0, len(self._seg_lut) - 1)  # background (-1) reads lut[0]
            frame.segmentation = self._seg_lut[ids]
        return frame

    def set_camera(self, name: str, pos=None, lookat=None, fovy=None) -> None:
        self._check_camera(name)
        cam = self._cameras[name]
        changes = {k: v for k, v in (("pos", pos), ("lookat", lookat), ("fovy", fovy)) if v is not None}
        self._cameras[name] = dataclasses.replace(cam, **changes)  # re-validates; raises SpecError
        self._matrices.pop(name, None)

    def set_rgba(self, name: str, rgba) -> None:
        live = self._live[self._check_body(name)]
        try:
            colour = list(_rgba(rgba, f"rgba of {name!r}"))
        except SpecError:
            raise
        except (TypeError, ValueError):  # spec._rgba lets numpy's conversion errors through
            raise SpecError(f"rgba of {name!r} must be 3 or 4 numbers in [0, 1], got {rgba!r}") from None
        for i in range(live.n_shapes):
            self._p.changeVisualShape(live.uid, -1, shapeIndex=i if live.n_shapes > 1 else -1, rgbaColor=colour)
        for link, n in enumerate(live.link_shapes):
            for i in range(n):
                self._p.changeVisualShape(live.uid, link, shapeIndex=i, rgbaColor=colour)

    # -- lifecycle -----------------------------------------------------------------------------
    def reset(self, scene: Scene | None = None) -> None:
        if scene is not None and not isinstance(scene, Scene):
            raise SpecError(f"reset needs a physint_backends.spec.Scene, got {type(scene).__name__}")
        if scene is not None:
            self.scene = scene
        self._build()

    def close(self) -> None:
        if getattr(self, "_p", None) is not None and self._p._client >= 0:
            self._p.disconnect()
        if getattr(self, "_tmpdir", None):
            shutil.rmtree(self._tmpdir, ignore_errors=True)
            self._tmpdir = None
            self._files = {}

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass


@contextlib.contextmanager
def _silence_stdout():
    """Drop what C code prints to stdout (file descriptor 1) for the duration (Bullet's greeting,
    once per connection: noise in every worker's log)."""
    try:
        libc = ctypes.CDLL(None)
    except OSError:  # no C library to flush through (unusual platforms): leave stdout alone
        yield
        return
    sys.stdout.flush()
    saved = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
        libc.fflush(None)  # push C's buffered output out while fd 1 still points at /dev/null
    finally:
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


def _write_obj(path: str, positions: np.ndarray, uvs: np.ndarray, normals: np.ndarray, triangles: np.ndarray) -> None:
    """A Wavefront .obj whose vertex ``i`` has position, uv and normal ``i`` (counter-clockwise triangles)."""
    lines = [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in positions]
    lines += [f"vt {u:.6g} {v:.6g}" for u, v in uvs]
    lines += [f"vn {x:.6g} {y:.6g} {z:.6g}" for x, y, z in normals]
    lines += ["f " + " ".join(f"{i + 1}/{i + 1}/{i + 1}" for i in tri) for tri in triangles]
    with open(path, "w") as fh:
        fh.write("\n".join(lines) + "\n")


def _stack_args(per_geom: list[dict], kind: str) -> dict:
    """Turn per-geom shape arguments into the parallel lists of create*ShapeArray."""
    frame = "collisionFrame" if kind == "collision" else "visualFrame"
    out: dict = {"shapeTypes": [], "halfExtents": [], "radii": [], "lengths": [], "fileNames": [],
                 "meshScales": [], f"{frame}Positions": [], f"{frame}Orientations": []}
    if kind == "visual":
        out["rgbaColors"] = []
    for args in per_geom:
        out["shapeTypes"].append(args["shapeType"])
        out["halfExtents"].append(args.get("halfExtents", [0, 0, 0]))
        out["radii"].append(args.get("radius", 0.0))
        out["lengths"].append(args.get("height", args.get("length", 0.0)))
        out["fileNames"].append(args.get("fileName", ""))
        out["meshScales"].append(args.get("meshScale", [1, 1, 1]))
        out[f"{frame}Positions"].append(args[f"{frame}Position"])
        out[f"{frame}Orientations"].append(args[f"{frame}Orientation"])
        if kind == "visual":
            out["rgbaColors"].append(args["rgbaColor"])
    return out
