"""GEECO's table-top environments (thesis Section 6.4, Figs. 6.4.1 and 6.4.2) as backend-neutral scenes.

A Panda stands at the edge of a table; one camera looks at the table from the front.

* ``goal2cube2``: two small cubes (red, yellow) and two larger target pads (blue, green). Four
  tasks (either cube onto either pad), so the controller has to infer the task from the target
  image.
* ``goal1cube1``: one red cube and one blue pad (unambiguous: the E2EVMC baseline, Section 6.C).
* evaluation only (Table 6.4.2): ``clutter`` (GOAL2CUBE2 with extra distractor objects on the
  table, FG:CLUTTER), ``prisma`` (GOAL2CUBE2 with the background replaced by a looping rainbow
  video, BG:PRISMA), ``nutoncone`` (drop a hexagonal nut over a cone) and ``ballincup`` (drop a
  ball into a cup).

For pushing the pads are flat markings that nothing collides with ("reduced to flat textures");
for pick-and-place they are 2 cm platforms. An :class:`Episode` is everything needed to rebuild one start state exactly: the
scene, the skill, where each object and target stands (``layout``) and the task (which object
onto which target).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from physint_backends.shapes import bowl, pad
from physint_backends.spec import Body, Camera, Geom, Light, Robot, Scene

TRAIN_SCENES = ("goal2cube2", "goal1cube1")
EVAL_SCENES = ("clutter", "prisma", "nutoncone", "ballincup")
SCENES = TRAIN_SCENES + EVAL_SCENES
SKILLS = ("push", "pickplace")

# commands are hand displacements on every backend; a stiff OSC keeps the hand ~1.6 control steps
# behind its goal (3.6 at robosuite's default): what the camera shows is close to what was commanded
ROBOT = Robot(goal_mode="desired", osc_kp=600.0)
TABLE_Z = ROBOT.table_height  # the table top; all heights below are above it
CUBE = 0.05  # cube edge (m)
CUBE_FRICTION = 0.5  # slides when pushed low (at 1.0 pushed cubes tip and wedge the fingers more often)
PAD = 0.12  # target pad side (m)
PAD_TOP = {"push": 0.001, "pickplace": 0.02}  # pad surface above the table: a marking for pushing, a platform to place on
WORKSPACE_X = (-0.12, 0.18)  # where objects and targets start (table frame, m)
WORKSPACE_Y = (-0.22, 0.22)
REST_EE = (-0.22, 0.0, TABLE_Z + 0.32)  # where the expert parks the hand: out of the target image

RGBA = {"red": (0.9, 0.12, 0.1, 1.0), "yellow": (0.95, 0.85, 0.1, 1.0), "blue": (0.12, 0.25, 0.9, 1.0),
        "green": (0.1, 0.7, 0.2, 1.0), "grey": (0.55, 0.55, 0.6, 1.0), "white": (0.92, 0.92, 0.9, 1.0)}
CLUTTER_RGBA = ((0.6, 0.2, 0.8, 1.0), (1.0, 0.5, 0.1, 1.0), (0.1, 0.8, 0.85, 1.0), (0.95, 0.4, 0.7, 1.0),
                (0.45, 0.3, 0.15, 1.0), (0.9, 0.9, 0.9, 1.0))

# each scene's objects (things the robot moves) and targets (where they go), in layout order
OBJECTS = {"goal2cube2": ("red_cube", "yellow_cube"), "goal1cube1": ("red_cube",), "clutter": ("red_cube", "yellow_cube"),
           "prisma": ("red_cube", "yellow_cube"), "nutoncone": ("nut",), "ballincup": ("ball",)}
TARGETS = {"goal2cube2": ("blue_pad", "green_pad"), "goal1cube1": ("blue_pad",), "clutter": ("blue_pad", "green_pad"),
           "prisma": ("blue_pad", "green_pad"), "nutoncone": ("cone",), "ballincup": ("cup",)}
CLUTTER_OBJECTS = 5

# object geometry: half height, the grasp point's offset from the object's centre, and its radius
# (for spacing); nut: a hexagonal ring grasped at one of its walls
NUT_RADIUS, NUT_WALL, NUT_HEIGHT = 0.045, 0.012, 0.025
CONE_RADIUS, CONE_HEIGHT = 0.032, 0.07
BALL_RADIUS = 0.025
CUP_RADIUS, CUP_HEIGHT = 0.05, 0.06


def items(scene: str) -> tuple[str, ...]:
    return OBJECTS[scene] + TARGETS[scene]


def tasks(scene: str) -> list[tuple[int, int]]:
    """All (object index, target index) pairs of a scene: 4 in GOAL2CUBE2, 1 in the others."""
    return [(o, t) for o in range(len(OBJECTS[scene])) for t in range(len(TARGETS[scene]))]


def describe(name: str) -> str:
    return name.replace("_", " ")


@dataclass
class Episode:
    """One start state and task. ``layout[i] = (x, y, yaw)`` of ``items(scene)[i]`` on the table."""

    scene: str
    skill: str
    layout: np.ndarray  # (n_items, 3) float
    task: tuple[int, int]  # (object index, target index)
    seed: int = 0  # draws what the layout does not hold (clutter objects)
    clutter: list[tuple[str, float, float, float, int]] = field(default_factory=list)  # (shape, x, y, size, colour)
    backdrop: int = -1  # >= 0: the seed of a random background video (data.backgrounds=random); -1: the scene's own

    @property
    def object(self) -> str:
        return OBJECTS[self.scene][self.task[0]]

    @property
    def target(self) -> str:
        return TARGETS[self.scene][self.task[1]]

    def xy(self, name: str) -> np.ndarray:
        return np.asarray(self.layout[items(self.scene).index(name), :2], dtype=float)

    def goal_text(self) -> str:
        return f"{describe(self.object)} onto {describe(self.target)}"

    @classmethod
    def rebuild(cls, scene: str, skill: str, layout, task, seed: int, backdrop: int = -1) -> "Episode":
        """The episode a stored start state (a dataset record or an evaluation spec) describes;
        FG:CLUTTER's distractors come from its seed."""
        ep = cls(scene, skill, np.asarray(layout, dtype=np.float32), tuple(int(v) for v in task), int(seed),
                 backdrop=int(backdrop))
        if scene == "clutter":
            ep.clutter = sample_clutter(ep, np.random.default_rng(ep.seed))
        return ep


# -- sampling start states -------------------------------------------------------------------------

def _radius(name: str, skill: str) -> float:
    """Footprint radius used to keep things apart."""
    if name.endswith("_pad"):
        return PAD / 2 * math.sqrt(2)
    return {"nut": NUT_RADIUS + 0.01, "cone": CONE_RADIUS, "ball": BALL_RADIUS, "cup": CUP_RADIUS + 0.01}.get(
        name, CUBE / 2 * math.sqrt(2))


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    ab = b - a
    t = float(np.clip(np.dot(p - a, ab) / max(np.dot(ab, ab), 1e-12), 0.0, 1.0))
    return float(np.linalg.norm(p - (a + t * ab)))


def push_start(cube: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Where the closed fingers start a push: behind the cube on the line through cube and target."""
    direction = (target - cube) / max(np.linalg.norm(target - cube), 1e-9)
    return cube - direction * (CUBE / 2 + 0.045)


def sample_episode(scene: str, skill: str, task: tuple[int, int], rng: np.random.Generator,
                   max_tries: int = 500) -> Episode:
    """A random start state of ``scene`` with nothing overlapping and the task doable by the expert."""
    names = items(scene)
    for _ in range(max_tries):
        xy = np.column_stack([rng.uniform(*WORKSPACE_X, len(names)), rng.uniform(*WORKSPACE_Y, len(names))])
        ok = all(np.linalg.norm(xy[i] - xy[j]) > _radius(names[i], skill) + _radius(names[j], skill) + 0.02
                 for i in range(len(names)) for j in range(i))
        if not ok:
            continue
        obj, tgt = OBJECTS[scene][task[0]], TARGETS[scene][task[1]]
        o, t = xy[names.index(obj)], xy[names.index(tgt)]
        if np.linalg.norm(o - t) < 0.16:  # the object starts well away from its target
            continue
        if skill == "push":
            start = push_start(o, t)
            if not (WORKSPACE_X[0] - 0.08 <= start[0] <= WORKSPACE_X[1] + 0.08 and abs(start[1]) < 0.3):
                continue
            # no other object in the way of the fingers and the pushed cube
            others = [xy[i] for i, n in enumerate(names) if n != obj and not n.endswith("_pad")]
            if any(_segment_distance(p, start, t) < CUBE * 1.2 for p in others):
                continue
        yaw = np.where([n.endswith("cube") for n in names], rng.uniform(-0.2, 0.2, len(names)), 0.0)
        ep = Episode(scene, skill, np.column_stack([xy, yaw]).astype(np.float32), task, seed=int(rng.integers(2**31)))
        if scene == "clutter":
            ep.clutter = sample_clutter(ep, rng)
        return ep
    raise RuntimeError(f"could not lay out scene {scene!r} in {max_tries} tries")


def sample_clutter(ep: Episode, rng: np.random.Generator) -> list[tuple[str, float, float, float, int]]:
    """Distractors (FG:CLUTTER): spheres, cylinders and boxes away from the task's objects and path."""
    names = items(ep.scene)
    taken = [(ep.xy(n), _radius(n, ep.skill)) for n in names]
    path = (ep.xy(ep.object), ep.xy(ep.target))
    out: list[tuple[str, float, float, float, int]] = []
    while len(out) < CLUTTER_OBJECTS:
        x, y = rng.uniform(WORKSPACE_X[0] - 0.03, WORKSPACE_X[1] + 0.05), rng.uniform(-0.28, 0.28)
        size = float(rng.uniform(0.03, 0.05))
        p = np.array([x, y])
        if any(np.linalg.norm(p - q) < r + size + 0.02 for q, r in taken):
            continue
        if _segment_distance(p, *path) < 0.09:
            continue
        taken.append((p, size))
        out.append((("sphere", "cylinder", "box")[int(rng.integers(3))], float(x), float(y), size,
                    int(rng.integers(len(CLUTTER_RGBA)))))
    return out


# -- building the scene ----------------------------------------------------------------------------

def camera(resolution: int) -> Camera:
    """The front camera: sees the table, the objects and the robot's hand."""
    return Camera("front", pos=(0.45, 0.0, TABLE_Z + 0.75), lookat=(0.02, 0.0, TABLE_Z), fovy=45.0,
                  width=resolution, height=resolution)


def _nut(name: str, pos, rgba) -> Body:
    """A hexagonal nut: six wall slabs around a hole (a concave ring made of convex boxes)."""
    geoms = []
    apothem = NUT_RADIUS * math.cos(math.pi / 6)
    side = NUT_RADIUS  # a regular hexagon's side equals its circumradius
    for k in range(6):
        az = math.pi / 6 + k * math.pi / 3  # walls facing +-y carry the grasp
        r = apothem - NUT_WALL / 2
        c, s = math.cos(az / 2), math.sin(az / 2)
        geoms.append(Geom("box", (NUT_WALL, side, NUT_HEIGHT), pos=(r * math.cos(az), r * math.sin(az), 0.0),
                          quat=(c, 0.0, 0.0, s), rgba=rgba))
    return Body(name, geoms, pos=pos, mass=0.06)


def _cone(name: str, pos, rgba) -> Body:
    import trimesh

    mesh = trimesh.creation.cone(radius=CONE_RADIUS, height=CONE_HEIGHT, sections=24)
    return Body.from_mesh(name, mesh, rgba=rgba, pos=pos, static=True)


def object_half_height(name: str) -> float:
    return {"nut": NUT_HEIGHT / 2, "ball": BALL_RADIUS}.get(name, CUBE / 2)


def target_top(name: str, skill: str) -> float:
    """Height of the surface a placed object rests on, above the table."""
    if name.endswith("_pad"):
        return PAD_TOP[skill]
    return {"cone": CONE_HEIGHT * 0.55, "cup": 0.01}[name]


def build_scene(ep: Episode, resolution: int) -> Scene:
    """The backend-neutral :class:`Scene` of an episode's start state."""
    bodies: list[Body] = []
    for i, name in enumerate(items(ep.scene)):
        x, y, yaw = (float(v) for v in ep.layout[i])
        colour = name.split("_")[0]
        if name.endswith("_cube"):
            bodies.append(Body.box(name, (CUBE, CUBE, CUBE), rgba=RGBA[colour], pos=(x, y, TABLE_Z + CUBE / 2),
                                   quat=(math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)), mass=0.1, friction=CUBE_FRICTION))
        elif name.endswith("_pad"):
            # pushing pads are markings: a cube slides over them (a 1 mm step would stop it)
            bodies.append(pad(name, size=(PAD, PAD), pos=(x, y, TABLE_Z), rgba=RGBA[colour],
                              thickness=PAD_TOP[ep.skill], collide=ep.skill != "push"))
        elif name == "nut":
            bodies.append(_nut(name, (x, y, TABLE_Z + NUT_HEIGHT / 2), RGBA["red"]))
        elif name == "cone":
            bodies.append(_cone(name, (x, y, TABLE_Z), RGBA["blue"]))
        elif name == "ball":
            bodies.append(Body.sphere(name, BALL_RADIUS, rgba=RGBA["red"], pos=(x, y, TABLE_Z + BALL_RADIUS),
                                      mass=0.05, friction=1.0))
        elif name == "cup":
            bodies.append(bowl(name, radius=CUP_RADIUS, height=CUP_HEIGHT, wall=0.006, segments=16, flare=8.0,
                               pos=(x, y, TABLE_Z), rgba=RGBA["blue"]))
    for k, (shape, x, y, size, colour) in enumerate(ep.clutter):
        rgba = CLUTTER_RGBA[colour]
        if shape == "sphere":
            bodies.append(Body.sphere(f"clutter{k}", size / 2, rgba=rgba, pos=(x, y, TABLE_Z + size / 2), mass=0.05))
        elif shape == "cylinder":
            bodies.append(Body.cylinder(f"clutter{k}", size / 2, size * 1.2, rgba=rgba, pos=(x, y, TABLE_Z + size * 0.6),
                                        mass=0.05))
        else:
            bodies.append(Body.box(f"clutter{k}", (size, size, size), rgba=rgba, pos=(x, y, TABLE_Z + size / 2), mass=0.05))
    lights = [Light(pos=(0.4, 0.3, TABLE_Z + 1.5), lookat=(0.0, 0.0, TABLE_Z), diffuse=(0.6, 0.6, 0.6),
                    ambient=(0.4, 0.4, 0.4))]
    return Scene(bodies=bodies, cameras=[camera(resolution)], lights=lights, robot=ROBOT,
                 background=(0.75, 0.78, 0.82))


# -- BG:PRISMA: the background as a looping rainbow video -----------------------------------------

PRISMA_PERIOD = 50  # frames per loop (2 s at 25 Hz)


@functools.lru_cache(maxsize=8)
def unit_grid(size: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (y, x) of a ``size`` x ``size`` video frame in image widths, [0, 1);
    made once per size and read-only (every frame of every background video uses them)."""
    y, x = np.mgrid[0:size, 0:size] / size
    y.flags.writeable = x.flags.writeable = False
    return y, x


def prisma_frame(step: int, size: int) -> np.ndarray:
    """Frame ``step`` of the looping rainbow video: diagonal hue bands drifting across the image."""
    y, x = unit_grid(size)
    hue = (x + 0.6 * y + step / PRISMA_PERIOD) % 1.0
    return (hsv_to_rgb(hue, 0.9, 0.95) * 255).astype(np.uint8)


def hsv_to_rgb(hue: np.ndarray, saturation: float, value: float) -> np.ndarray:
    """``colorsys.hsv_to_rgb`` over an array of hues in [0, 1) (..., 3): the same float operations,
    so the same colours, without a Python call per pixel."""
    sector = (hue * 6.0).astype(int)
    f = hue * 6.0 - sector
    v = np.full_like(hue, value)
    p = np.full_like(hue, value * (1.0 - saturation))
    q = value * (1.0 - saturation * f)
    t = value * (1.0 - saturation * (1.0 - f))
    sector %= 6
    return np.stack([np.choose(sector, channel) for channel in
                     ((v, q, p, p, t, v), (t, v, v, q, p, p), (p, p, t, v, v, q))], axis=-1)


def replace_background(rgb: np.ndarray, segmentation: np.ndarray, step: int,
                       video: Callable[[int, int], np.ndarray] = prisma_frame) -> np.ndarray:
    """Every pixel showing the background (not the robot, the table or an object) becomes frame
    ``step`` of ``video`` (BG:PRISMA: the rainbow)."""
    out = rgb.copy()
    mask = segmentation == -1
    out[mask] = video(step, rgb.shape[0])[mask]
    return out


# -- random background videos (data.backgrounds=random; domain randomisation, not in the thesis) ---

def random_backdrop(seed: int) -> Callable[[int, int], np.ndarray]:
    """A random moving background, the same for the same ``seed``: ``video(step, size)`` is its
    frame at ``step``. Two families, drawn evenly: a smooth field of random colours (a 2..6-cell
    periodic grid, interpolated) and bands of 2..4 random colours at a random angle and width;
    half the videos stand still, the others drift across the image at up to half of it per second
    (25 steps)."""
    rng = np.random.default_rng(seed)
    speed = rng.uniform(0.0, 0.02) * rng.integers(0, 2)  # image widths per step
    heading = rng.uniform(0, 2 * math.pi)
    drift = speed * np.array([math.cos(heading), math.sin(heading)])
    if rng.random() < 0.5:
        cells = int(rng.integers(2, 7))
        grid = rng.uniform(0, 1, (cells, cells, 3))

        def colours(x: np.ndarray, y: np.ndarray) -> np.ndarray:
            # bilinear interpolation on the periodic grid (wraps around, so the field can drift forever)
            gx, gy = (x * cells) % cells, (y * cells) % cells
            x0, y0 = np.floor(gx).astype(int), np.floor(gy).astype(int)
            fx, fy = (gx - x0)[..., None], (gy - y0)[..., None]
            x1, y1 = (x0 + 1) % cells, (y0 + 1) % cells
            return ((1 - fy) * ((1 - fx) * grid[y0, x0] + fx * grid[y0, x1])
                    + fy * ((1 - fx) * grid[y1, x0] + fx * grid[y1, x1]))
    else:
        palette = rng.uniform(0, 1, (int(rng.integers(2, 5)), 3))
        angle, width = rng.uniform(0, math.pi), rng.uniform(0.05, 0.3)

        def colours(x: np.ndarray, y: np.ndarray) -> np.ndarray:
            along = x * math.cos(angle) + y * math.sin(angle)
            return palette[np.floor(along / width).astype(int) % len(palette)]

    still: dict[int, np.ndarray] = {}  # a still video's one frame per size, made once (read-only)

    def video(step: int, size: int) -> np.ndarray:
        if size in still:
            return still[size]
        y, x = unit_grid(size)
        frame = (colours(x - drift[0] * step, y - drift[1] * step) * 255).astype(np.uint8)
        if not speed:
            frame.flags.writeable = False
            still[size] = frame
        return frame

    return video


def background_video(ep: Episode) -> Callable[[int, int], np.ndarray] | None:
    """What replaces ``ep``'s background: the rainbow in BG:PRISMA, the episode's own random video
    (``ep.backdrop``), or nothing (the scene's plain background)."""
    if ep.scene == "prisma":
        return prisma_frame
    if ep.backdrop >= 0:
        return random_backdrop(ep.backdrop)
    return None


# -- goals in words ------------------------------------------------------------------------------

def parse_goal(text: str, scene: str) -> tuple[int, int]:
    """'red cube onto green pad' -> (object index, target index) in ``scene``; ValueError names the choices."""
    words = text.lower().replace("_", " ").replace(",", " ").split()
    joined = " ".join(words)
    for sep in (" onto ", " into ", " on ", " in ", " to "):
        if sep in f" {joined} ":
            left, right = f" {joined} ".split(sep, 1)
            break
    else:
        left, right = joined, ""

    def find(part: str, names: tuple[str, ...], kind: str) -> int:
        hits = [i for i, n in enumerate(names) if all(w in part.split() for w in n.split("_"))]
        if len(hits) != 1:
            raise ValueError(f"goal {text!r}: no single {kind} of scene {scene} in {part.strip()!r}; "
                             f"{kind}s: {', '.join(describe(n) for n in names)}")
        return hits[0]

    return find(left, OBJECTS[scene], "object"), find(right, TARGETS[scene], "target")
