"""The three scene families RELATE is trained on, as backend-neutral scenes (thesis Section 5.4, Appendix 5.C).

* ``balls-in-bowl``: two (up to four) balls of fixed, distinct colours roll in an elliptical bowl of random
  orientation and eccentricity, seen from straight above (a replica of Ehrhardt et al.'s
  BallsInBowl). The bowl is the elliptical paraboloid z = depth * ((x'/a)^2 + (y'/b)^2) in its own
  frame turned by ``angle``; it is built from convex slabs (one per patch of a polar grid), since
  every backend collides convex meshes only.
* ``clevr-table``: 2-5 primitives (cube, cylinder, sphere; CLEVR's eight colours, two sizes) at
  random, non-penetrating places on a grey table, seen in perspective from the front and above.
* ``shapestacks``: the stability plugin's ShapeStacks towers, reached through the registry
  (``plugins.scene("stability", "ccs").build``), seen from the front: the ordered variant's data.

Each scene comes with its ground truth (object positions, bowl parameters) for evaluation only: the
models never see it.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np

from physint_backends.spec import Body, Camera, Geom, Ground, Light, Scene

# balls-in-bowl (metres)
BALL_RADIUS = 0.025
# fixed per ball (data.balls <= 4): red, blue, green, yellow; each is high in some channels and low in the others
BALL_COLOURS = ((0.9, 0.15, 0.1, 1.0), (0.1, 0.35, 0.95, 1.0), (0.1, 0.75, 0.15, 1.0), (0.95, 0.85, 0.1, 1.0))
BOWL_MAJOR = 0.16  # semi-axis a
BOWL_MINOR = (0.55, 1.0)  # b / a: the eccentricity's range
BOWL_DEPTH = 0.03  # shallow enough that balls at 0.8 m/s range over the whole bowl (median 0.38 a)
BOWL_RGBA = (0.85, 0.85, 0.8, 1.0)
BOWL_RINGS, BOWL_SECTORS, BOWL_THICKNESS = 8, 24, 0.01
BOWL_FRICTION = BALL_FRICTION = 0.6
BOWL_CAMERA_HEIGHT = 1.5
BOWL_EXTENT = 0.2  # the top-down camera sees +-0.2 m
TABLE_RGBA = (0.35, 0.35, 0.38, 1.0)

# clevr-table
CLEVR_COLOURS = {"gray": (0.34, 0.34, 0.34), "red": (0.68, 0.13, 0.13), "blue": (0.16, 0.29, 0.84),
                 "green": (0.11, 0.41, 0.08), "brown": (0.51, 0.29, 0.1), "purple": (0.51, 0.15, 0.75),
                 "cyan": (0.16, 0.82, 0.82), "yellow": (1.0, 0.93, 0.2)}
CLEVR_SHAPES = ("cube", "cylinder", "sphere")
CLEVR_SIZES = (0.035, 0.05)  # half extents (m): small, large
CLEVR_AREA = 0.16  # objects within +-0.16 m of the table's centre
CLEVR_GAP = 0.01  # least gap between two objects' bounding circles
CLEVR_TABLE = (0.62, 0.62, 0.6, 1.0)


@dataclass
class Truth:
    """What the simulator knows of a scene and a model never sees: per object its name, position
    (metres, world frame) and attributes; the bowl's parameters for balls-in-bowl."""

    names: list[str]
    shapes: list[int] = field(default_factory=list)  # index into the scene family's shape names
    colours: list[int] = field(default_factory=list)
    sizes: list[float] = field(default_factory=list)
    bowl: tuple[float, float, float, float] | None = None  # (angle rad, a, b, depth)


def top_camera(size: int) -> Camera:
    fovy = math.degrees(2 * math.atan(BOWL_EXTENT / BOWL_CAMERA_HEIGHT))
    return Camera("top", pos=(0.0, 0.0, BOWL_CAMERA_HEIGHT), lookat=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0),
                  fovy=fovy, width=size, height=size)


def front_camera(size: int, lookat=(0.0, 0.0, 0.0), distance: float = 0.75, elevation: float = 35.0,
                 fovy: float = 32.0) -> Camera:
    el = math.radians(elevation)
    pos = (lookat[0] - distance * math.cos(el), lookat[1], lookat[2] + distance * math.sin(el))
    return Camera("front", pos=pos, lookat=lookat, up=(0.0, 0.0, 1.0), fovy=fovy, width=size, height=size)


# -- balls in a bowl -------------------------------------------------------------------------------------------

def bowl_height(x, y, angle: float, a: float, b: float, depth: float):
    """The bowl's surface: z = depth * ((x'/a)^2 + (y'/b)^2), (x', y') the point in the bowl's frame."""
    c, s = math.cos(angle), math.sin(angle)
    xl, yl = c * np.asarray(x) + s * np.asarray(y), -s * np.asarray(x) + c * np.asarray(y)
    return depth * ((xl / a) ** 2 + (yl / b) ** 2)


def inside_bowl(x, y, angle: float, a: float, b: float, margin: float = 0.0):
    """Whether (x, y) lies within the bowl's rim, shrunk by ``margin`` metres along both axes."""
    c, s = math.cos(angle), math.sin(angle)
    xl, yl = c * np.asarray(x) + s * np.asarray(y), -s * np.asarray(x) + c * np.asarray(y)
    return (xl / (a - margin)) ** 2 + (yl / (b - margin)) ** 2 <= 1.0


@functools.lru_cache(maxsize=1)
def unit_bowl_slabs() -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    """The slabs of the bowl with a = b = 1, unturned, as (vertices, faces) per sector and patch (the
    rim's wall last in each sector): computed once, since any bowl is a linear map of it."""
    import trimesh

    def point(rho: float, phi: float) -> np.ndarray:
        return np.array([rho * math.cos(phi), rho * math.sin(phi), rho ** 2])

    rhos = np.linspace(0.0, 1.0, BOWL_RINGS + 1)
    phis = np.linspace(0.0, 2 * math.pi, BOWL_SECTORS + 1)
    out = []
    for j in range(BOWL_SECTORS):
        parts = []
        for i in range(BOWL_RINGS):
            top = np.array([point(r, p) for r in rhos[i:i + 2] for p in phis[j:j + 2]])
            parts.append(np.concatenate([top, top - [0, 0, 1.0]]))  # z in units of depth; bottom fixed below
        foot = np.array([point(1.0, p) for p in phis[j:j + 2]])
        wall = np.concatenate([foot, foot + [0, 0, 1.0]])
        parts.append(np.concatenate([wall, wall * [1.04, 1.04, 1.0]]))
        for points in parts:
            hull = trimesh.convex.convex_hull(points)
            out.append((np.asarray(hull.vertices), np.asarray(hull.faces)))
    return tuple(out)


def bowl_bodies(angle: float, a: float, b: float, depth: float) -> list[Body]:
    """The bowl as convex slabs, one static body per sector of a polar grid over the ellipse (PyBullet
    lets balls through a body of more than about 16 convex parts): each patch is the convex hull of the
    surface's points at its corners and the same points ``BOWL_THICKNESS`` lower, and a wall
    3 ball radii high stands at the rim. A bowl is the unit bowl's slabs under (x, y) -> R(angle) diag(a, b),
    which keeps them convex."""
    import trimesh

    c, s = math.cos(angle), math.sin(angle)
    linear = np.array([[c, -s], [s, c]]) @ np.diag([a, b])
    slabs = unit_bowl_slabs()
    per_sector = BOWL_RINGS + 1
    bodies = []
    for j in range(BOWL_SECTORS):
        geoms = []
        for i, (vertices, faces) in enumerate(slabs[j * per_sector:(j + 1) * per_sector]):
            v = vertices.copy()
            v[:, :2] = v[:, :2] @ linear.T
            rim = i == per_sector - 1
            lower = v[:, 2] < (1.5 if rim else vertices[:, 0] ** 2 + vertices[:, 1] ** 2 - 0.5)
            if rim:  # the wall: from the rim's height up 3 ball radii
                v[:, 2] = depth + np.where(lower, 0.0, 3 * BALL_RADIUS)
            else:  # a slab: the surface's depth * rho^2, the bottom BOWL_THICKNESS below it
                v[:, 2] = np.where(lower, depth * (v[:, 2] + 1.0) - BOWL_THICKNESS, depth * v[:, 2])
            geoms.append(Geom("mesh", mesh=trimesh.Trimesh(vertices=v, faces=faces, process=False), rgba=BOWL_RGBA))
        bodies.append(Body(f"bowl{j}", geoms, static=True, friction=BOWL_FRICTION))
    return bodies


def sample_bowl(rng: np.random.Generator) -> tuple[float, float, float, float]:
    """A bowl of random orientation and eccentricity: (angle, a, b, depth)."""
    return float(rng.uniform(0.0, math.pi)), BOWL_MAJOR, float(BOWL_MAJOR * rng.uniform(*BOWL_MINOR)), BOWL_DEPTH


def sample_balls(rng: np.random.Generator, bowl, count: int = 2, speed: float = 0.8) -> tuple[np.ndarray, np.ndarray]:
    """Start positions (on the surface, apart) and horizontal velocities of ``count`` balls."""
    angle, a, b, depth = bowl
    pos: list[np.ndarray] = []
    while len(pos) < count:
        xy = rng.uniform(-a, a, 2)
        if not inside_bowl(*xy, angle, a, b, margin=1.5 * BALL_RADIUS):
            continue
        if any(np.linalg.norm(xy - p[:2]) < 2.5 * BALL_RADIUS for p in pos):
            continue
        pos.append(np.array([*xy, float(bowl_height(*xy, angle, a, b, depth)) + BALL_RADIUS + 0.002]))
    vel = rng.uniform(-speed, speed, (count, 2))
    return np.stack(pos), np.concatenate([vel, np.zeros((count, 1))], axis=1)


def balls_scene(bowl, starts: np.ndarray, size: int, colours=BALL_COLOURS) -> tuple[Scene, Truth]:
    balls = [Body(f"ball{k}", [Geom("sphere", (BALL_RADIUS,), rgba=colours[k % len(colours)])], pos=tuple(p),
                  mass=0.05, friction=BALL_FRICTION) for k, p in enumerate(starts)]
    scene = Scene(bodies=bowl_bodies(*bowl) + balls, cameras=[top_camera(size)],
                  lights=[Light(pos=(0.1, -0.2, 3.0), lookat=(0, 0, 0), diffuse=(0.6, 0.6, 0.6),
                                ambient=(0.4, 0.4, 0.4))],
                  ground=Ground(rgba=TABLE_RGBA), timestep=0.002)
    return scene, Truth(names=[b.name for b in balls], bowl=tuple(bowl))


# -- CLEVR-like table --------------------------------------------------------------------------------------------

def clevr_geom(shape: str, half: float, rgba) -> Geom:
    if shape == "cube":
        return Geom("box", (2 * half,) * 3, rgba=rgba)
    if shape == "cylinder":
        return Geom("cylinder", (half, 2 * half), rgba=rgba)
    return Geom("sphere", (half,), rgba=rgba)


def clevr_scene(rng: np.random.Generator, count: int, size: int) -> tuple[Scene, Truth]:
    """``count`` primitives of random shape, colour and size at random places that do not overlap
    (their bounding circles keep ``CLEVR_GAP`` apart), resting on the table."""
    names = list(CLEVR_COLOURS)
    bodies, truth = [], Truth(names=[])
    placed: list[tuple[np.ndarray, float]] = []
    while len(bodies) < count:
        shape, colour = int(rng.integers(len(CLEVR_SHAPES))), int(rng.integers(len(names)))
        half = float(CLEVR_SIZES[int(rng.integers(len(CLEVR_SIZES)))])
        reach = half * (math.sqrt(2) if CLEVR_SHAPES[shape] == "cube" else 1.0)
        xy = rng.uniform(-CLEVR_AREA, CLEVR_AREA, 2)
        if any(np.linalg.norm(xy - p) < reach + r + CLEVR_GAP for p, r in placed):
            continue
        yaw = float(rng.uniform(0, math.pi / 2))
        quat = (math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2))
        name = f"object{len(bodies)}"
        bodies.append(Body(name, [clevr_geom(CLEVR_SHAPES[shape], half, (*CLEVR_COLOURS[names[colour]], 1.0))],
                           pos=(float(xy[0]), float(xy[1]), half), quat=quat, friction=0.8))
        placed.append((xy, reach))
        truth.names.append(name)
        truth.shapes.append(shape)
        truth.colours.append(colour)
        truth.sizes.append(half)
    scene = Scene(bodies=bodies, cameras=[front_camera(size)],
                  lights=[Light(pos=(-0.5, -0.6, 2.0), lookat=(0, 0, 0)), Light(pos=(0.4, 0.6, 1.5), lookat=(0, 0, 0),
                                                                               diffuse=(0.3, 0.3, 0.3),
                                                                               ambient=(0.0, 0.0, 0.0))],
                  ground=Ground(rgba=CLEVR_TABLE), background=(0.55, 0.55, 0.55))
    return scene, truth


# -- ShapeStacks, through the stability plugin's registered scene -----------------------------------------------

def stack_scene(build, seed: int, height: int, size: int, randomise: bool, kind: str = "stable") -> tuple[Scene, Truth]:
    """A ShapeStacks tower of ``height`` objects, of Lemma 1's ``kind`` (stable, or VCOM for the evaluation's
    tower reader), (``build`` is the stability plugin's registered scene builder; ``randomise``: its random
    textures and colours) seen by its first camera, ``front``."""
    import dataclasses

    scene, scenario = build(seed=seed, height=height, kind=kind, cameras=1, resolution=size, randomise=randomise)
    scene.cameras = [dataclasses.replace(scene.cameras[0], name="front")]
    names = [b.name for b in scene.bodies if not b.static][:height]
    return scene, Truth(names=names, sizes=[float(max(o.size)) for o in scenario.objects])
