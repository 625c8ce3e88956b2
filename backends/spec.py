"""Backend-neutral scene specs.

A :class:`Scene` describes a world once; every backend builds the same world from it. Units
are SI (metres, kilograms, seconds); quaternions are ``(w, x, y, z)``; positions are in the
world frame with z up and the ground plane at z = 0.

Sizes are given the way a person measures an object, not as MuJoCo half-sizes:

* ``box``: ``(x, y, z)`` full edge lengths;
* ``cylinder``: ``(radius, height)``, axis along the body's local z;
* ``sphere``: ``(radius,)``;
* ``mesh``: ``()``; the geometry is a convex ``trimesh.Trimesh`` in the body frame.

Every spec validates itself on construction and raises :class:`SpecError` (a ``BadInput``,
exit code 2) naming the field and the allowed values, so a bad spec never reaches a simulator.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from physint_cli.errors import BadInput

SHAPES = ("box", "cylinder", "sphere", "mesh")
SIZE_ARITY = {"box": 3, "cylinder": 2, "sphere": 1, "mesh": 0}
GRIPPER_OPEN, GRIPPER_NOOP, GRIPPER_CLOSE = -1, 0, 1
ROBOT_PARTS = ("fingers", "palm", "any")
GOAL_MODES = ("achieved", "desired")
GOAL_LEAD_STEPS = 2  # in "desired" mode the goal leads the hand by at most this many max_delta per axis


class SpecError(BadInput):
    """A scene spec or an action is invalid; the message names the field and what is allowed."""


def quat_matrix(quat) -> np.ndarray:
    """Rotation matrix of a unit quaternion (w, x, y, z)."""
    w, x, y, z = quat
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _finite_vector(value: Any, n: int, where: str) -> tuple[float, ...]:
    try:
        arr = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise SpecError(f"{where} must be {n} numbers, got {value!r}") from None
    if arr.shape != (n,):
        raise SpecError(f"{where} must be {n} numbers, got {arr.size}")
    if not np.all(np.isfinite(arr)):
        raise SpecError(f"{where} must be finite, got {arr.tolist()}")
    return tuple(float(v) for v in arr)


def _unit_quat(value: Any, where: str) -> tuple[float, float, float, float]:
    q = np.asarray(_finite_vector(value, 4, where))
    norm = float(np.linalg.norm(q))
    if norm < 1e-9:
        raise SpecError(f"{where} must be a non-zero quaternion (w, x, y, z)")
    return tuple(float(v) for v in q / norm)  # type: ignore[return-value]


def _positive(value: Any, where: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise SpecError(f"{where} must be a positive number, got {value!r}") from None
    if not math.isfinite(v) or v <= 0:
        raise SpecError(f"{where} must be a positive number, got {value!r}")
    return v


def _rgba(value: Any, where: str) -> tuple[float, float, float, float]:
    try:
        arr = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise SpecError(f"{where} must be 3 or 4 numbers in [0, 1], got {value!r}") from None
    if arr.size == 3:
        arr = np.append(arr, 1.0)
    rgba = _finite_vector(arr, 4, where)
    if min(rgba) < 0 or max(rgba) > 1:
        raise SpecError(f"{where} must have components in [0, 1], got {list(rgba)}")
    return rgba  # type: ignore[return-value]


@dataclass
class Texture:
    """An RGB image (uint8, HxWx3) wrapped around a geom or tiled over the ground."""

    image: np.ndarray
    name: str = "texture"
    repeat: tuple[float, float] = (1.0, 1.0)

    def __post_init__(self) -> None:
        img = np.asarray(self.image)
        if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8 or min(img.shape[:2]) < 1:
            raise SpecError(f"texture {self.name!r}: image must be uint8 HxWx3, got {img.dtype} {img.shape}")
        self.image = np.ascontiguousarray(img)


@dataclass
class Geom:
    """One collision + visual shape of a body, posed in the body frame."""

    shape: str
    size: tuple[float, ...] = ()
    pos: tuple[float, float, float] = (0.0, 0.0, 0.0)
    quat: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    rgba: tuple[float, float, float, float] = (0.7, 0.7, 0.7, 1.0)
    texture: Texture | None = None
    mesh: Any = None  # trimesh.Trimesh, convex, for shape == "mesh"

    def __post_init__(self) -> None:
        if self.shape not in SHAPES:
            raise SpecError(f"geom shape {self.shape!r} is not supported; allowed: {', '.join(SHAPES)}")
        n = SIZE_ARITY[self.shape]
        if self.shape == "mesh":
            if self.mesh is None or not hasattr(self.mesh, "vertices") or len(self.mesh.vertices) < 4:
                raise SpecError("geom of shape 'mesh' needs mesh=<trimesh.Trimesh with >= 4 vertices>")
            self.size = ()
        else:
            size = np.atleast_1d(np.asarray(self.size, dtype=float)) if np.size(self.size) else np.zeros(0)
            if size.size != n:
                raise SpecError(f"{self.shape} size must have {n} value(s) {_SIZE_NAMES[self.shape]}, got {list(size)}")
            self.size = tuple(_positive(v, f"{self.shape} size") for v in size)
        self.pos = _finite_vector(self.pos, 3, "geom pos")  # type: ignore[assignment]
        self.quat = _unit_quat(self.quat, "geom quat")
        self.rgba = _rgba(self.rgba, "geom rgba")

    def volume(self) -> float:
        if self.shape == "box":
            return float(np.prod(self.size))
        if self.shape == "cylinder":
            return math.pi * self.size[0] ** 2 * self.size[1]
        if self.shape == "sphere":
            return 4.0 / 3.0 * math.pi * self.size[0] ** 3
        return float(abs(self.mesh.convex_hull.volume))

    def half_height(self) -> float:
        """Half the geom's extent along its own z axis (for placing it on a surface)."""
        if self.shape == "box":
            return self.size[2] / 2
        if self.shape == "cylinder":
            return self.size[1] / 2
        if self.shape == "sphere":
            return self.size[0]
        z = np.asarray(self.mesh.vertices)[:, 2]
        return float(z.max() - z.min()) / 2

    def outline(self, segments: int = 16) -> np.ndarray:
        """(N, 3) points in the body frame whose convex hull is the geom (a sphere's and a cylinder's curved
        surfaces to within one part in ``segments``): the box's corners, the cylinder's two rims, points spread
        over the sphere (golden-angle spiral), the mesh's vertices. Projected, they bound the geom in an image."""
        if self.shape == "box":
            local = np.array([[i, j, k] for i in (-0.5, 0.5) for j in (-0.5, 0.5) for k in (-0.5, 0.5)]) * self.size
        elif self.shape == "cylinder":
            phi = np.linspace(0.0, 2 * math.pi, segments, endpoint=False)
            rim = np.stack([self.size[0] * np.cos(phi), self.size[0] * np.sin(phi)], axis=1)
            local = np.concatenate([np.c_[rim, np.full(segments, z)] for z in (-self.size[1] / 2, self.size[1] / 2)])
        elif self.shape == "sphere":
            n = segments ** 2 // 2
            z = np.linspace(-1.0, 1.0, n)
            phi = np.arange(n) * math.pi * (3.0 - math.sqrt(5.0))
            r = np.sqrt(1.0 - z ** 2)
            local = self.size[0] * np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
        else:
            local = np.asarray(self.mesh.vertices, dtype=float)
        return np.asarray(self.pos) + local @ quat_matrix(self.quat).T


_SIZE_NAMES = {"box": "(x, y, z) edge lengths", "cylinder": "(radius, height)", "sphere": "(radius,)", "mesh": "()"}


@dataclass
class Body:
    """A rigid body made of one or more geoms. ``static`` bodies never move (bins, pads, bowls);
    a body with ``collide=False`` is only drawn (a marking on the table): it must be static."""

    name: str
    geoms: list[Geom]
    pos: tuple[float, float, float] = (0.0, 0.0, 0.0)
    quat: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    mass: float | None = None  # kg; when None, density * volume
    density: float = 1000.0  # kg/m^3
    friction: float = 0.8  # sliding friction coefficient
    static: bool = False
    collide: bool = True

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise SpecError(f"body name must be a non-empty string, got {self.name!r}")
        if not self.geoms:
            raise SpecError(f"body {self.name!r} needs at least one geom")
        self.pos = _finite_vector(self.pos, 3, f"body {self.name!r} pos")  # type: ignore[assignment]
        self.quat = _unit_quat(self.quat, f"body {self.name!r} quat")
        if self.mass is not None:
            self.mass = _positive(self.mass, f"body {self.name!r} mass")
        self.density = _positive(self.density, f"body {self.name!r} density")
        self.friction = _positive(self.friction, f"body {self.name!r} friction")
        if not self.collide and not self.static:
            raise SpecError(f"body {self.name!r}: a body that does not collide must be static")

    @property
    def total_mass(self) -> float:
        return self.mass if self.mass is not None else self.density * sum(g.volume() for g in self.geoms)

    def outline(self, pos=None, quat=None) -> np.ndarray:
        """(N, 3) world points whose convex hull is the body (its geoms' outlines) at pose (``pos``, ``quat``),
        by default its own."""
        local = np.concatenate([g.outline() for g in self.geoms])
        pos = self.pos if pos is None else pos
        return np.asarray(pos, dtype=float) + local @ quat_matrix(self.quat if quat is None else quat).T

    # -- convenience constructors for single-geom bodies -----------------------------------
    @classmethod
    def box(cls, name: str, size, rgba=(0.7, 0.7, 0.7, 1.0), texture=None, **kw) -> Body:
        return cls(name, [Geom("box", tuple(np.atleast_1d(size)), rgba=rgba, texture=texture)], **kw)

    @classmethod
    def cylinder(cls, name: str, radius: float, height: float, rgba=(0.7, 0.7, 0.7, 1.0), texture=None, **kw) -> Body:
        return cls(name, [Geom("cylinder", (radius, height), rgba=rgba, texture=texture)], **kw)

    @classmethod
    def sphere(cls, name: str, radius: float, rgba=(0.7, 0.7, 0.7, 1.0), texture=None, **kw) -> Body:
        return cls(name, [Geom("sphere", (radius,), rgba=rgba, texture=texture)], **kw)

    @classmethod
    def from_mesh(cls, name: str, mesh, rgba=(0.7, 0.7, 0.7, 1.0), **kw) -> Body:
        return cls(name, [Geom("mesh", (), rgba=rgba, mesh=mesh)], **kw)


@dataclass
class Camera:
    """A pinhole camera looking from ``pos`` at ``lookat``; ``fovy`` is the vertical field of view in degrees."""

    name: str
    pos: tuple[float, float, float] = (1.0, 0.0, 0.5)
    lookat: tuple[float, float, float] = (0.0, 0.0, 0.0)
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    fovy: float = 45.0
    width: int = 64
    height: int = 64

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise SpecError(f"camera name must be a non-empty string, got {self.name!r}")
        self.pos = _finite_vector(self.pos, 3, f"camera {self.name!r} pos")  # type: ignore[assignment]
        self.lookat = _finite_vector(self.lookat, 3, f"camera {self.name!r} lookat")  # type: ignore[assignment]
        self.up = _finite_vector(self.up, 3, f"camera {self.name!r} up")  # type: ignore[assignment]
        fovy = _positive(self.fovy, f"camera {self.name!r} fovy")
        if fovy >= 180:
            raise SpecError(f"camera {self.name!r} fovy must be in (0, 180) degrees, got {fovy}")
        self.fovy = fovy
        for attr in ("width", "height"):
            v = getattr(self, attr)
            if not isinstance(v, (int, np.integer)) or v < 1 or v > 4096:
                raise SpecError(f"camera {self.name!r} {attr} must be an integer in [1, 4096], got {v!r}")
        if np.linalg.norm(np.subtract(self.lookat, self.pos)) < 1e-9:
            raise SpecError(f"camera {self.name!r}: pos and lookat must differ")

    @classmethod
    def from_pose(cls, name: str, pos, quat, **kw) -> Camera:
        """A camera at ``pos`` with orientation ``quat`` (w, x, y, z), looking along its local -z, y up."""
        rot = quat_matrix(_unit_quat(quat, f"camera {name!r} quat"))
        p = np.asarray(_finite_vector(pos, 3, f"camera {name!r} pos"))
        return cls(name, pos=tuple(p), lookat=tuple(p - rot[:, 2]), up=tuple(rot[:, 1]), **kw)

    def rotation(self) -> np.ndarray:
        """World-from-camera rotation (columns: camera x right, y up, z backwards, OpenGL convention)."""
        forward = np.subtract(self.lookat, self.pos)
        forward = forward / np.linalg.norm(forward)
        right = np.cross(forward, self.up)
        if np.linalg.norm(right) < 1e-9:  # looking straight along `up`
            right = np.cross(forward, (0.0, 1.0, 0.0) if abs(forward[1]) < 0.9 else (1.0, 0.0, 0.0))
        right = right / np.linalg.norm(right)
        up = np.cross(right, forward)
        return np.stack([right, up, -forward], axis=1)

    def project(self, points: np.ndarray) -> np.ndarray:
        """Pixel coordinates (u right, v down) of world points, for checks across backends."""
        pts = np.atleast_2d(points) - np.asarray(self.pos)
        cam = pts @ self.rotation()
        f = 0.5 * self.height / math.tan(math.radians(self.fovy) / 2)
        u = self.width / 2 + f * cam[:, 0] / -cam[:, 2]
        v = self.height / 2 - f * cam[:, 1] / -cam[:, 2]
        return np.stack([u, v], axis=1)


@dataclass
class Light:
    """A directional light (``directional=True``) or a spot light at ``pos`` aimed at ``lookat``."""

    pos: tuple[float, float, float] = (0.0, 0.0, 3.0)
    lookat: tuple[float, float, float] = (0.0, 0.0, 0.0)
    diffuse: tuple[float, float, float] = (0.7, 0.7, 0.7)
    ambient: tuple[float, float, float] = (0.3, 0.3, 0.3)
    directional: bool = True

    def __post_init__(self) -> None:
        self.pos = _finite_vector(self.pos, 3, "light pos")  # type: ignore[assignment]
        self.lookat = _finite_vector(self.lookat, 3, "light lookat")  # type: ignore[assignment]
        self.diffuse = _finite_vector(self.diffuse, 3, "light diffuse")  # type: ignore[assignment]
        self.ambient = _finite_vector(self.ambient, 3, "light ambient")  # type: ignore[assignment]


@dataclass
class Ground:
    """The ground plane at z = 0."""

    rgba: tuple[float, float, float, float] = (0.8, 0.8, 0.8, 1.0)
    texture: Texture | None = None
    friction: float = 0.8
    size: float = 5.0  # half extent in metres (visual only; collision is infinite)

    def __post_init__(self) -> None:
        self.rgba = _rgba(self.rgba, "ground rgba")
        self.friction = _positive(self.friction, "ground friction")
        self.size = _positive(self.size, "ground size")


@dataclass
class Robot:
    """A Franka Panda with a parallel gripper, its base on the table edge.

    Action (one control step of ``1 / control_hz`` s): ``(dx, dy, dz, gripper)`` with the end-
    effector displacement in metres, each component clipped to ``±max_delta``, and ``gripper``
    in {-1 open, 0 no-op, +1 close}.

    ``goal_mode`` says what the displacement moves (robosuite's ``goal_update_mode``):
    ``"achieved"`` puts the hand's goal at where the hand is plus the displacement (a proportional
    step: with the OSC of MuJoCo and robosuite the hand covers about a fifth of it per step);
    ``"desired"`` adds it to the previous goal, which never leads the hand by more than
    ``GOAL_LEAD_STEPS`` displacements, so on every backend the hand follows a sequence of
    displacements at their speed (what a learned end-effector velocity controller needs).

    ``osc_kp`` is the stiffness of the operational-space controller on MuJoCo and robosuite
    (robosuite's default 150, critically damped): the hand follows a moving goal about 3.6 control
    steps behind; at 600 about 1.6 steps behind, settling within 3 steps of a stop. PyBullet drives
    the joints by inverse kinematics and position control (0.6 steps behind) and ignores it.
    """

    name: str = "panda"
    base_pos: tuple[float, float, float] = (-0.56, 0.0, 0.0)  # on the table top, facing +x
    table_height: float = 0.8  # table top height (m); 0 puts the robot on the ground
    table_size: tuple[float, float] = (0.8, 0.8)  # table top (x, y) in metres, centred at the origin
    table_rgba: tuple[float, float, float, float] = (0.72, 0.58, 0.42, 1.0)
    control_hz: float = 25.0
    max_delta: float = 0.05  # m per control step, per axis
    init_ee_pos: tuple[float, float, float] | None = None  # world; default: 0.2 m above the table centre
    goal_mode: str = "achieved"  # "achieved" or "desired" (see above)
    osc_kp: float = 150.0  # stiffness Kp of the operational-space controller (see above)

    def __post_init__(self) -> None:
        if self.name != "panda":
            raise SpecError(f"robot {self.name!r} is not supported; allowed: panda")
        self.base_pos = _finite_vector(self.base_pos, 3, "robot base_pos")  # type: ignore[assignment]
        if not math.isfinite(self.table_height) or self.table_height < 0:
            raise SpecError(f"robot table_height must be >= 0, got {self.table_height}")
        self.table_rgba = _rgba(self.table_rgba, "robot table_rgba")
        self.control_hz = _positive(self.control_hz, "robot control_hz")
        self.max_delta = _positive(self.max_delta, "robot max_delta")
        self.osc_kp = _positive(self.osc_kp, "robot osc_kp")
        if self.goal_mode not in GOAL_MODES:
            raise SpecError(f"robot goal_mode {self.goal_mode!r} is not known; allowed: {', '.join(GOAL_MODES)}")
        if self.init_ee_pos is None:
            self.init_ee_pos = (0.0, 0.0, self.table_height + 0.2)
        self.init_ee_pos = _finite_vector(self.init_ee_pos, 3, "robot init_ee_pos")  # type: ignore[assignment]


@dataclass
class Scene:
    """Everything a backend needs to build a world."""

    bodies: list[Body] = field(default_factory=list)
    cameras: list[Camera] = field(default_factory=list)
    lights: list[Light] = field(default_factory=lambda: [Light()])
    ground: Ground | None = field(default_factory=Ground)
    robot: Robot | None = None
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)
    timestep: float = 0.002  # physics step in seconds
    background: tuple[float, float, float] = (0.72, 0.78, 0.86)  # colour of the sky behind everything
    # Friction holds resting bodies exactly. MuJoCo's contacts are soft: without this a body under a
    # small tangential load creeps (a sphere rolls off a plank that the contacts tilt by 0.05 deg)
    # and the backend runs its noslip solver to stop it; Bullet's friction is already hard.
    hard_friction: bool = False

    def __post_init__(self) -> None:
        self.gravity = _finite_vector(self.gravity, 3, "scene gravity")  # type: ignore[assignment]
        self.background = _rgba(self.background, "scene background")[:3]  # type: ignore[assignment]
        self.timestep = _positive(self.timestep, "scene timestep")
        for kind, items in (("body", self.bodies), ("camera", self.cameras)):
            names = [x.name for x in items]
            dup = sorted({n for n in names if names.count(n) > 1})
            if dup:
                raise SpecError(f"{kind} names must be unique; repeated: {', '.join(dup)}")

    def body(self, name: str) -> Body:
        for b in self.bodies:
            if b.name == name:
                return b
        raise unknown_name("body", name, [b.name for b in self.bodies])

    def camera(self, name: str) -> Camera:
        for c in self.cameras:
            if c.name == name:
                return c
        raise unknown_name("camera", name, [c.name for c in self.cameras])


def unknown_name(kind: str, name: str, choices: list[str]) -> SpecError:
    from physint_cli.errors import suggest

    valid = ", ".join(choices) if choices else "none in this scene"
    plural = {"body": "bodies"}.get(kind, kind + "s")
    return SpecError(f"no {kind} named {name!r}{suggest(name, choices)}; {plural}: {valid}")


def validate_action(action: Any) -> np.ndarray:
    """Check a robot action ``(dx, dy, dz, gripper)`` and return it as a float array."""
    try:
        a = np.asarray(action, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise SpecError(f"action must be 4 numbers (dx, dy, dz, gripper), got {action!r}") from None
    if a.shape != (4,):
        raise SpecError(f"action must be 4 numbers (dx, dy, dz, gripper), got shape {np.shape(action)}")
    if not np.all(np.isfinite(a)):
        raise SpecError(f"action must be finite, got {a.tolist()}")
    if a[3] not in (GRIPPER_OPEN, GRIPPER_NOOP, GRIPPER_CLOSE):
        raise SpecError(f"action gripper must be one of -1 (open), 0 (no-op), 1 (close), got {a[3]}")
    return a
