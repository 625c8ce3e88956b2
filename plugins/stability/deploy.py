"""Deploying the stability predictor: stackability, stacking, counterbalancing (thesis Section 3.5).

``physint deploy stability --task T`` with T one of

``stackability`` (Section 3.5.1, Figs. 3.5 and 3.6)
    Every object of a seeded pool (cuboids of varied aspect ratios, cubes, cylinders, spheres) is
    put on the ground as the base of a stack in each of its discrete orientations (a cuboid has
    three, one per pair of faces; a cylinder two, upright and lying; a sphere one). Every other
    object, in each of its orientations, is placed on top at the position simulated annealing finds
    most stable. The base's *stackability* is the mean, over the others, of their best score. The
    base position and yaw are perturbed at random for every other object (robustness). The
    predictor scores a combination from ``STACKABILITY_VIEWS`` (2) opposite cameras (the thesis
    assesses "an image" of it), which keeps this O(n^2 x orientations^2 x steps) task affordable.

``stack`` (Section 3.5.2, Figs. 3.7 and 3.8)
    Scenarios ``cubes``, ``cuboids`` and ``ccs`` (a CCS pool holds exactly two spheres). Each
    episode randomises texture, colours, lights and cameras, draws a pool of ``deploy.pool`` (12)
    objects, orders them and picks their orientation by stackability (a quick estimate: each base
    tried with ``QUICK_OTHERS`` random (object, orientation) pairs, ``anneal_steps / 6`` annealing
    steps, ``STACKABILITY_VIEWS`` cameras), puts the first one at the
    scene centre, and spawns each next one ``SPAWN_GAP`` above the trunk at the (x, y) where
    simulated annealing finds the highest predicted stability within ``deploy.anneal_radius`` of
    the trunk's top centre. An object whose best score is below 0.5 is put aside for good. After
    each release the physics runs ``SETTLE_SECONDS``; the episode ends when the tower collapses
    (an object moved more than 1 cm or tipped more than 10 degrees) or the pool is empty. The
    height is the number of objects standing when it ends. The cameras move up with the tower.

``balance`` (Section 3.5.3, Fig. 3.9)
    An unstable "T" (a base block and a long plank whose centre of mass overhangs the base: a
    VCOM) is frozen; one counterweight (cube, cuboid, cylinder or sphere) is placed on the plank
    where simulated annealing finds the highest predicted stability; everything is unfrozen and
    simulated for ``BALANCE_SECONDS``: success when nothing falls.

Agents, compared on the same pools, Ts, appearances and seeds:

``predictor``  the trained network (``ctx.source_run``): stability = 1 - mean P(unstable) over
               the ``deploy.cameras`` views (Eq. 3.2's logistic output), :class:`PredictorScorer`.
``oracle``     Lemma 1 (:func:`physics.analyse`): the smallest signed margin of Eq. 3.1 over all
               interfaces, squashed to (0, 1) by a logistic of width ``ORACLE_SCALE`` (0.5 at margin
               0), :class:`OracleScorer`. Same search as the predictor.
``random``     placements uniform in the search region, never put aside (stack: in the oracle's
               stackability order and orientations, so only placement differs).
``none``       (balance only) the T without a counterweight: the control, should always fall.

``deploy.agents`` (comma-separated) picks the agents; by default: ``predictor`` when there is a trained run, then ``oracle`` and ``random``.

Episodes are work units run through ``ctx.map`` (``--workers`` / ``--ray`` parallelise them).
Artifacts: ``stackability_area.png`` (Fig. 3.6), ``stackability_strip.png`` (Fig. 3.5),
``stack_heights.png`` (Fig. 3.7), ``stack_<scenario>_<agent>.mp4`` and ``.rrd`` (one episode),
``balance_success.png`` (Fig. 3.9), ``balance_<weight>_<agent>.mp4`` and ``.rrd``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from physint_backends import SimulationError
from physint_backends.randomize import PALETTE, orbit_cameras
from physint_backends.spec import Camera, Scene, Texture
from physint_cli.errors import BadInput, unknown
from physint_cli.method import Context, Unit, unit_seed
from physint_cli.training import torch_threads

from .physics import SHAPES, StackObject, analyse, stack_up
from .scenes import (CUBOID_EDGE, CUBOID_MAX_ASPECT, Scenario, default_textures, lighting_conditions, sample_cube,
                     sample_cuboid, sample_cylinder, sample_sphere, tilt_degrees, to_scene)

__all__ = [
    "TASKS", "AGENTS", "STACK_SCENARIOS", "COUNTERWEIGHTS", "Appearance", "Disc", "Rect", "AnnealResult", "anneal",
    "Scorer", "OracleScorer", "PredictorScorer", "lemma1_margin", "oracle_score", "orientations", "projected_area",
    "object_class", "stackability_pool", "base_stackability", "stackability_ranking", "stack_pool", "stack_episode",
    "unstable_t", "counterweight", "balance_episode", "stackability_unit", "make_scorer", "run_stackability",
    "run_stacking", "run_balance", "deploy",
]

TASKS = ("stackability", "stack", "balance")
AGENTS = ("predictor", "oracle", "random", "none")
STACK_SCENARIOS = ("cubes", "cuboids", "ccs")
COUNTERWEIGHTS = ("cube", "cuboid", "cylinder", "sphere")

ACCEPT = 0.5  # put an object aside when its best predicted stability is below this (Section 3.5.2)
ORACLE_SCALE = 0.01  # m: the oracle's stability is a logistic of the Lemma-1 margin with this width
SPAWN_GAP = 0.003  # m: h_r, objects are released this far above the trunk
SETTLE_SECONDS = 1.5  # s of physics after each release while stacking
BALANCE_SECONDS = 2.0  # s of physics after unfreezing the T
HOLD_SECONDS = 0.2  # s the counterweight settles on the frozen T before it is unfrozen
MOVE_THRESHOLD = 0.01  # m: an object moved further than this has fallen
TILT_THRESHOLD = 10.0  # degrees: an object tipped further than this has fallen
CHECK_EVERY = 0.01  # s between fall checks
BASE_JITTER = 0.01  # m: random perturbation of the base position in the stackability score
STACKABILITY_VIEWS = 2  # cameras whose images score a stackability combination (the thesis: one image)
QUICK_OTHERS = 3  # stacking orders its pool with this many (other object, orientation) pairs per base ...
QUICK_STEPS_DIVISOR = 6  # ... and anneal_steps / this annealing steps per placement (min. 4)
PARK = 100.0  # m: pool objects wait on the ground this far away (beyond every backend's far plane: <= 50 m)
VIDEO_SIZE = 160  # px
VIDEO_FPS = 25.0
_STRIP_SIZE = 96  # px per object in the Fig. 3.5 strip


# ==============================================================================================
# appearance: one random draw per episode; only geometry changes within it
# ==============================================================================================

def _object_key(obj: StackObject) -> list[int]:
    return [SHAPES.index(obj.shape)] + [int(round(s * 1e6)) for s in obj.size]


@dataclass
class Appearance:
    """An episode's randomised look: ground texture, lights, object colours, a camera ring.

    Drawn once (:meth:`draw`) and reused for every scene of the episode, so that the predictor
    only ever sees the geometry change. Colours are a function of the object (its shape and size)
    and the episode seed; an object never shares the colour of the one below it (as in training).
    """

    seed: int
    texture: Texture | None
    lights: list
    elevation: float = 20.0  # degrees
    azimuth: float = 0.0  # radians, first camera of the ring
    distance: float = 1.1  # times the distance at which the stack just fits the view
    cameras: int = 6
    resolution: int = 64
    fovy: float = 45.0
    timestep: float = 0.002

    @classmethod
    def draw(cls, rng: np.random.Generator, cameras: int = 6, resolution: int = 64, textures: int = 25,
             randomise: bool = True, timestep: float = 0.002) -> Appearance:
        bank = default_textures()[:max(1, textures)]
        seed = int(rng.integers(2**31 - 1))
        if not randomise:
            return cls(seed, bank[0], list(lighting_conditions()[0]), cameras=cameras, resolution=resolution,
                       timestep=timestep)
        return cls(seed, bank[int(rng.integers(len(bank)))], list(lighting_conditions()[int(rng.integers(5))]),
                   elevation=float(rng.uniform(5, 35)), azimuth=float(rng.uniform(0, 2 * math.pi)),
                   distance=float(rng.uniform(1.0, 1.3)), cameras=cameras, resolution=resolution, timestep=timestep)

    def colour(self, obj: StackObject, avoid: tuple | None = None) -> tuple:
        order = np.random.default_rng([self.seed] + _object_key(obj)).permutation(len(PALETTE))
        for k in order:
            if PALETTE[k] != avoid:
                return PALETTE[k]
        return PALETTE[order[0]]

    def colours(self, objects: list[StackObject]) -> list[tuple]:
        out: list[tuple] = []
        for obj in objects:
            out.append(self.colour(obj, out[-1] if out else None))
        return out

    def ring(self, objects: list[StackObject], n: int | None = None, size: int | None = None, factor: float = 1.0,
             prefix: str = "cam", azimuth: float = 0.0) -> list[Camera]:
        """``n`` cameras orbiting the stack's middle at the distance where it fits the view (as :func:`to_scene`)."""
        lo = np.min([o.xy - o.radius_xy() for o in objects], axis=0)
        hi = np.max([o.xy + o.radius_xy() for o in objects], axis=0)
        top = max(o.z + o.height / 2 for o in objects)
        centre = (lo + hi) / 2
        lookat = (float(centre[0]), float(centre[1]), top / 2)
        bound = math.sqrt((top / 2) ** 2 + float(np.max(hi - lo) / 2) ** 2)
        dist = bound / math.sin(math.radians(self.fovy) / 2) * self.distance * factor
        el = math.radians(self.elevation)
        return orbit_cameras(self.cameras if n is None else n, radius=dist * math.cos(el),
                             height=lookat[2] + dist * math.sin(el), lookat=lookat, fovy=self.fovy,
                             width=size or self.resolution, height_px=size or self.resolution,
                             start=self.azimuth + azimuth, prefix=prefix)

    def scene(self, objects: list[StackObject], cameras: list[Camera] | None = None,
              colours: list[tuple] | None = None) -> Scene:
        """The scene of ``objects`` (heights set; bodies ``obj0``..) in this appearance, with the
        camera ring fitted to them unless ``cameras`` are given."""
        scenario = Scenario("ccs", "stable", list(objects), None, self.seed)  # type: ignore[arg-type]
        scene = to_scene(scenario, np.random.default_rng(self.seed), cameras=0, resolution=self.resolution,
                         textures=[self.texture] if self.texture is not None else [], randomise=False,
                         timestep=self.timestep)
        colours = colours or self.colours(objects)
        bodies = [dataclasses.replace(b, geoms=[dataclasses.replace(g, rgba=colours[i]) for g in b.geoms])
                  for i, b in enumerate(scene.bodies)]
        cams = self.ring(objects) if cameras is None else list(cameras)
        return dataclasses.replace(scene, bodies=bodies, lights=list(self.lights), cameras=cams)


def _move_cameras(sim, cameras: list[Camera]) -> None:
    """The cameras follow the stack up (Section 3.5.2): move the live ones to a new ring."""
    for cam in cameras:
        sim.set_camera(cam.name, pos=cam.pos, lookat=cam.lookat)


# ==============================================================================================
# search regions and simulated annealing
# ==============================================================================================

@dataclass
class Disc:
    """Positions within ``radius`` of ``centre`` (the stacking search region)."""

    centre: np.ndarray
    radius: float

    def __post_init__(self) -> None:
        self.centre = np.asarray(self.centre, dtype=float)

    @property
    def scale(self) -> float:
        return self.radius

    def sample(self, rng: np.random.Generator) -> np.ndarray:
        r = self.radius * math.sqrt(rng.random())
        t = rng.uniform(0, 2 * math.pi)
        return self.centre + r * np.array([math.cos(t), math.sin(t)])

    def project(self, p) -> np.ndarray:
        d = np.asarray(p, dtype=float) - self.centre
        n = float(np.linalg.norm(d))
        return self.centre + (d * (self.radius / n) if n > self.radius else d)


@dataclass
class Rect:
    """Positions on a rectangle of full ``extents`` rotated by ``yaw`` (a plank's top face)."""

    centre: np.ndarray
    extents: tuple[float, float]
    yaw: float = 0.0

    def __post_init__(self) -> None:
        self.centre = np.asarray(self.centre, dtype=float)

    @property
    def scale(self) -> float:
        return 0.5 * max(self.extents)

    def _axes(self) -> np.ndarray:
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return np.array([[c, s], [-s, c]])  # rows: the rectangle's x and y axes

    def sample(self, rng: np.random.Generator) -> np.ndarray:
        local = (rng.random(2) - 0.5) * np.asarray(self.extents)
        return self.centre + local @ self._axes()

    def project(self, p) -> np.ndarray:
        axes = self._axes()
        local = axes @ (np.asarray(p, dtype=float) - self.centre)
        half = 0.5 * np.asarray(self.extents)
        return self.centre + np.clip(local, -half, half) @ axes


@dataclass
class AnnealResult:
    xy: np.ndarray  # the best position found
    score: float  # its score
    start_score: float  # the score where the search started
    evaluations: int
    accepted: int
    trace: list[float] = field(default_factory=list)  # best score so far, per evaluation


def _log_odds(p: float, eps: float = 1e-15) -> float:
    p = min(max(float(p), eps), 1.0 - eps)
    return math.log(p / (1.0 - p))


def anneal(score: Callable[[np.ndarray], float], domain, steps: int, rng: np.random.Generator, start=None,
           t_start: float = 1.0, t_end: float = 0.05, step_start: float = 0.5, step_end: float = 0.1) -> AnnealResult:
    """Simulated annealing of ``score(xy)`` over ``domain`` (a :class:`Disc` or :class:`Rect`), keeping the best.

    ``steps`` evaluations in all, the first at ``start`` (default: the domain's centre). Each step
    proposes a Gaussian move of ``domain.scale`` times a step size shrinking linearly from
    ``step_start`` to ``step_end`` (clipped into the domain) and accepts it with the Metropolis
    rule ``min(1, exp((E' - E) / T))`` on the log-odds ``E = log(s / (1 - s))`` of the stability
    ``s`` in [0, 1], the temperature falling geometrically from ``t_start`` to ``t_end``. (On the
    stability itself a logistic output is flat far from the decision boundary, where a fixed
    temperature turns the search into a random walk; the log-odds keep its slope: for the
    Lemma-1 oracle they are the margin over ``ORACLE_SCALE``.)
    """
    steps = max(1, int(steps))
    x = domain.project(domain.centre if start is None else start)
    s = float(score(x))
    best_x, best_s, start_s = x.copy(), s, s
    trace, accepted, e = [s], 0, _log_odds(s)
    for k in range(1, steps):
        frac = (k - 1) / max(1, steps - 2)
        temp = t_start * (t_end / t_start) ** frac
        sigma = domain.scale * (step_start + (step_end - step_start) * frac)
        y = domain.project(x + rng.normal(0.0, sigma, 2))
        sy = float(score(y))
        ey = _log_odds(sy)
        if ey >= e or rng.random() < math.exp((ey - e) / temp):  # Metropolis acceptance
            x, s, e = y, sy, ey
            accepted += 1
        if sy > best_s:
            best_x, best_s = y.copy(), sy
        trace.append(best_s)
    return AnnealResult(best_x, best_s, start_s, steps, accepted, trace)


# ==============================================================================================
# scorers: how stable would the stack be with this object placed here?
# ==============================================================================================

def _top(trunk: list[StackObject]) -> float:
    return max(o.z + o.height / 2 for o in trunk) if trunk else 0.0


def _on_top(trunk: list[StackObject], obj: StackObject, xy=None, gap: float = 0.0) -> StackObject:
    """``obj`` resting on the trunk (at ``xy``, default the trunk's top centre), ``gap`` above it."""
    if xy is None:
        xy = trunk[-1].xy if trunk else (0.0, 0.0)
    return obj.moved(x=float(xy[0]), y=float(xy[1]), z=_top(trunk) + obj.height / 2 + gap)


def lemma1_margin(stack: list[StackObject]) -> float:
    """The smallest signed margin (m) of Eq. 3.1 over all interfaces (-inf for a VPSF)."""
    return float(min(analyse(stack).margins))


def oracle_score(stack: list[StackObject], scale: float = ORACLE_SCALE) -> float:
    """Lemma 1 as a stability in [0, 1]: a logistic of the smallest margin (0.5 at margin 0)."""
    m = lemma1_margin(stack)
    return 0.5 * (1.0 + math.tanh(m / (2 * scale))) if not math.isnan(m) else 0.0


class Scorer:
    """Scores placements: ``placement(trunk, obj)`` returns ``score(xy)`` = stability in [0, 1] of
    the trunk (bottom to top, heights set) with ``obj`` resting on top at ``xy``."""

    name = "?"

    def placement(self, trunk: list[StackObject], obj: StackObject) -> Callable[[np.ndarray], float]:
        raise NotImplementedError

    def stack(self, objects: list[StackObject]) -> float:
        """The stability of a whole stack (its top object where it is)."""
        objects = stack_up(list(objects))
        return self.placement(objects[:-1], objects[-1])(objects[-1].xy)

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class OracleScorer(Scorer):
    """The Lemma-1 oracle: :func:`oracle_score` of the stack with the object placed."""

    name = "oracle"

    def __init__(self, scale: float = ORACLE_SCALE):
        self.scale = scale

    def placement(self, trunk, obj):
        trunk = list(trunk)

        def score(xy) -> float:
            return oracle_score(trunk + [obj.moved(x=float(xy[0]), y=float(xy[1]))], self.scale)

        return score


class _Stage:
    """One simulation holding a body for every object an episode may show, used only to render.

    A stack is shown by moving its objects into place (any orientation: a body's pose carries it),
    recolouring them, parking every other body beyond the cameras' far plane and moving the camera
    ring to fit the stack; nothing is rebuilt and no physics runs. (A new MuJoCo simulation pays
    ~0.2 s for its GL context on the first render, 30-50x a whole 6-camera evaluation.) An object
    the stage has no body for (matched by shape and size) triggers one rebuild with it added.
    """

    def __init__(self, appearance: Appearance, make_sim: Callable[[Scene], Any], objects=(),
                 cameras: int | None = None, size: int | None = None, prefix: str = "cam"):
        self.appearance = appearance
        self.make_sim = make_sim
        self.n_cameras = appearance.cameras if cameras is None else cameras
        self.size = size or appearance.resolution
        self.prefix = prefix
        self.objects: list[StackObject] = list(objects)
        self.sim = None
        self.names: dict[tuple, list[str]] = {}
        self.camera_names: list[str] = []
        self._rgba: dict[str, tuple] = {}
        self._where: dict[str, bool | None] = {}

    def _parked(self, j: int, obj: StackObject) -> tuple[float, float, float]:
        return (PARK + 0.3 * j, PARK, obj.height / 2)

    def _build(self) -> None:
        self.close()
        parked = []
        self.names = {}
        for j, obj in enumerate(self.objects):
            x, y, z = self._parked(j, obj)
            parked.append(obj.moved(x=x, y=y, z=z))
            self.names.setdefault(tuple(_object_key(obj)), []).append(f"obj{j}")
        cams = self.appearance.ring([stack_up([self.objects[0].moved(x=0.0, y=0.0)])[0]], n=self.n_cameras,
                                    size=self.size, prefix=self.prefix)
        self.sim = self.make_sim(self.appearance.scene(parked, cameras=cams))
        self.camera_names = [c.name for c in cams]
        self._rgba = {}
        self._where = {f"obj{j}": None for j in range(len(self.objects))}

    def _bodies(self, stack: list[StackObject]) -> list[str]:
        """Body names for the stack's objects (adding missing ones, with a rebuild)."""
        counts: dict[tuple, int] = {}
        missing = []
        for obj in stack:
            key = tuple(_object_key(obj))
            counts[key] = counts.get(key, 0) + 1
            if counts[key] > len(self.names.get(key, [])):
                missing.append(obj)
        if missing or self.sim is None:
            self.objects += missing
            self._build()
        used: dict[tuple, int] = {}
        out = []
        for obj in stack:
            key = tuple(_object_key(obj))
            out.append(self.names[key][used.get(key, 0)])
            used[key] = used.get(key, 0) + 1
        return out

    def show(self, stack: list[StackObject], factor: float = 1.0) -> list[str]:
        """Put ``stack`` (heights set) in place, park the rest, fit the cameras; its body names."""
        names = self._bodies(stack)
        sim = self.sim
        shown = set(names)
        for j, obj in enumerate(self.objects):
            name = f"obj{j}"
            if name not in shown and self._where[name] is not None:
                sim.set_pose(name, self._parked(j, obj))
                self._where[name] = None
        for name, obj, rgba in zip(names, stack, self.appearance.colours(stack)):
            sim.set_pose(name, (obj.x, obj.y, obj.z), obj.quat)
            self._where[name] = True
            if self._rgba.get(name) != rgba:
                sim.set_rgba(name, rgba)
                self._rgba[name] = rgba
        _move_cameras(sim, self.appearance.ring(stack, n=self.n_cameras, size=self.size, factor=factor,
                                                prefix=self.prefix))
        return names

    def render(self, views: int | None = None) -> np.ndarray:
        """Every camera's image, or ``views`` of them evenly spaced around the ring."""
        names = self.camera_names
        if views is not None and 0 < views < len(names):
            names = [names[round(k * len(names) / views)] for k in range(views)]
        return np.stack([self.sim.render(c, rgb=True).rgb for c in names])

    def close(self) -> None:
        if self.sim is not None:
            self.sim.close()
            self.sim = None


class PredictorScorer(Scorer):
    """The learned predictor: render the candidate from the episode's cameras, stability = 1 - mean P(unstable).

    ``placement`` shows the trunk with the object resting on its top centre on a :class:`_Stage`
    (cameras fitted to that stack and kept while the object moves) and returns ``score(xy)``,
    which moves the object (``set_pose``, no physics), renders every camera and runs the network
    once on the batch. ``objects``: the episode's objects, so that the stage is built once.
    """

    name = "predictor"

    def __init__(self, model, input_size: int, appearance: Appearance, make_sim: Callable[[Scene], Any],
                 objects=(), threads: int = 1):
        self.model = model
        self.input_size = int(input_size)
        self.appearance = appearance
        self.stage = _Stage(appearance, make_sim, objects)
        self.threads = threads
        self.evaluations = 0
        self.views: int | None = None  # None: every camera; k: k of them (stackability)

    def images(self) -> np.ndarray:
        return self.stage.render(self.views)

    @contextlib.contextmanager
    def using_views(self, views: int | None):
        saved, self.views = self.views, views
        try:
            yield self
        finally:
            self.views = saved

    def stability(self, images: np.ndarray) -> float:
        from .evaluate import predict

        with torch_threads(self.threads):
            p_unstable = predict(self.model, images, self.input_size)
        self.evaluations += 1
        return float(1.0 - np.mean(p_unstable))

    def placement(self, trunk, obj):
        placed = _on_top(list(trunk), obj)
        name = self.stage.show(list(trunk) + [placed])[-1]
        sim, z, quat = self.stage.sim, placed.z, placed.quat

        def score(xy) -> float:
            sim.set_pose(name, (float(xy[0]), float(xy[1]), z), quat)
            return self.stability(self.images())

        return score

    def close(self) -> None:
        self.stage.close()


_PREDICTORS: dict[tuple[str, str], tuple[Any, int]] = {}


def _load_predictor(ctx: Context) -> tuple[Any, int]:
    """The trained network of ``ctx.source_run``, loaded once per process."""
    from .checkpoint import load_predictor

    if ctx.source_run is None:
        raise BadInput("the predictor agent needs a trained stability run (--run)")
    key = (str(ctx.source_run), ctx.device)
    if key not in _PREDICTORS:
        _PREDICTORS[key] = load_predictor(Path(ctx.source_run), ctx.device)
    return _PREDICTORS[key]


def make_scorer(ctx: Context, agent: str, appearance: Appearance, objects=()) -> Scorer | None:
    """The scorer an agent searches with (None for ``random`` / ``none``, which do not search);
    ``objects``: what the episode will show (the predictor's stage is built with them)."""
    if agent == "predictor":
        model, size = _load_predictor(ctx)
        return PredictorScorer(model, size, appearance, ctx.make_sim, objects)
    if agent == "oracle":
        return OracleScorer()
    return None


def _choose(agent: str, scorer: Scorer | None, trunk: list[StackObject], obj: StackObject, domain, steps: int,
            rng: np.random.Generator) -> tuple[np.ndarray, float | None]:
    """Where the agent puts ``obj``: SA on its scorer, or uniform in the domain (``random``)."""
    if scorer is None:
        return domain.sample(rng), None
    res = anneal(scorer.placement(trunk, obj), domain, steps, rng)
    return res.xy, res.score


# ==============================================================================================
# stackability (Section 3.5.1)
# ==============================================================================================

def orientations(obj: StackObject) -> list[StackObject]:
    """The object in each of its distinct discrete orientations (a cube has one, like a sphere)."""
    from .physics import ORIENTATIONS

    out, seen = [], set()
    for o in ORIENTATIONS[obj.shape]:
        cand = obj.moved(orientation=o)
        key = (cand.curved_top, round(cand.height, 6), tuple(sorted(round(e, 6) for e in cand.extents)))
        if key not in seen:
            seen.add(key)
            out.append(cand)
    return out


def projected_area(obj: StackObject) -> float:
    """Area (m^2) of the object's projection onto the x-y plane in its orientation."""
    if obj.shape == "sphere" or (obj.shape == "cylinder" and obj.orientation == "upright"):
        return math.pi * obj.size[0] ** 2
    ex, ey = obj.extents
    return ex * ey


def object_class(obj: StackObject) -> str:
    """Fig. 3.6's classes: cube, cuboid largest / middle / smallest face (up), cylinder upright / lying, sphere."""
    if obj.shape == "sphere":
        return "sphere"
    if obj.shape == "cylinder":
        return f"cylinder {obj.orientation}"
    if max(obj.size) - min(obj.size) < 1e-9:
        return "cube"
    faces = sorted({round(projected_area(o), 12) for o in orientations(obj)}, reverse=True)
    rank = faces.index(round(projected_area(obj), 12))
    if len(faces) == 2:  # two equal edges: a largest and a smallest face only
        return "cuboid largest face" if rank == 0 else "cuboid smallest face"
    return ("cuboid largest face", "cuboid middle face", "cuboid smallest face")[rank]


CLASS_ORDER = ("cuboid largest face", "cuboid middle face", "cuboid smallest face", "cube", "cylinder upright",
               "cylinder lying", "sphere")
_EXPECTED = ("cuboid largest face", "cylinder upright", "cylinder lying", "sphere")  # the thesis's finding

_POOL_CYCLE = ("cuboid", "cylinder", "sphere", "cube", "cuboid", "cylinder", "cuboid", "cube", "cylinder", "cuboid",
               "sphere", "cuboid")


def stackability_pool(n: int, rng: np.random.Generator) -> list[StackObject]:
    """``n`` objects of every class (cuboids of varied aspect ratios, cubes, cylinders, spheres), random yaw."""
    make = {"cuboid": sample_cuboid, "cube": sample_cube, "cylinder": sample_cylinder, "sphere": sample_sphere}
    out = []
    for i in range(n):
        obj = make[_POOL_CYCLE[i % len(_POOL_CYCLE)]](rng)
        if obj.shape == "cylinder" and rng.random() < 0.5:
            obj = obj.moved(orientation="lying")
        out.append(obj.moved(yaw=float(rng.uniform(0, math.pi))))
    return out


def base_stackability(base: StackObject, others: list[StackObject], scorer: Scorer, rng: np.random.Generator,
                      steps: int, radius: float, jitter: float = BASE_JITTER,
                      every_orientation: bool = True) -> tuple[float, list[float]]:
    """Section 3.5.1: the mean over ``others`` of the best score of each on top of ``base``.

    For each other object the base is perturbed at random (position within ``jitter``, yaw), the
    object is tried in each of its orientations (or only as given, ``every_orientation=False``),
    each placed by :func:`anneal` within ``radius`` of the base's top centre; its best score over
    orientations and positions is recorded.
    """
    per_other = []
    for other in others:
        b = stack_up([base.moved(x=float(rng.uniform(-jitter, jitter)), y=float(rng.uniform(-jitter, jitter)),
                                 yaw=float(rng.uniform(0, math.pi)))])
        best = 0.0
        for o in (orientations(other) if every_orientation else [other]):
            res = anneal(scorer.placement(b, o), Disc(b[0].xy, radius), steps, rng)
            best = max(best, res.score)
        per_other.append(best)
    return (float(np.mean(per_other)) if per_other else 0.0), per_other


def stackability_ranking(objects: list[StackObject], scorer: Scorer, rng: np.random.Generator, steps: int,
                         radius: float, others: int | None = None) -> list[dict[str, Any]]:
    """Every (object, orientation) as a base, scored by :func:`base_stackability`, best first.

    With ``others`` = k (stacking's quick ranking) each base is tried with k random (other object,
    orientation) pairs instead of every other object in every orientation. Ties keep the larger
    projected area first.
    """
    rows = []
    for i, obj in enumerate(objects):
        rest = [o for j, o in enumerate(objects) if j != i]
        for oriented in orientations(obj):
            if others is None:
                score, per_other = base_stackability(oriented, rest, scorer, rng, steps, radius)
            else:
                pairs = [o for r in rest for o in orientations(r)]
                pick = [pairs[k] for k in sorted(rng.choice(len(pairs), min(others, len(pairs)), replace=False))]
                score, per_other = base_stackability(oriented, pick, scorer, rng, steps, radius,
                                                     every_orientation=False)
            rows.append(_ranking_row(i, oriented, score, per_other))
    rows.sort(key=lambda r: (-r["score"], -r["projected_area"]))
    return rows


def _ranking_row(i: int, obj: StackObject, score: float, per_other: list[float]) -> dict[str, Any]:
    return {"object": i, "shape": obj.shape, "size": [round(s, 5) for s in obj.size], "orientation": obj.orientation,
            "class": object_class(obj), "score": float(score), "projected_area": projected_area(obj),
            "per_other": [round(float(s), 4) for s in per_other]}


def stackability_unit(ctx: Context, unit: Unit) -> dict[str, Any]:
    """Work unit: the stackability of one (object, orientation) base of the task's pool for one agent."""
    p = unit.params
    cfg = ctx.config.deploy
    pool_rng = np.random.default_rng(p["pool_seed"])
    pool = stackability_pool(p["pool"], pool_rng)
    appearance = Appearance.draw(pool_rng, cfg.cameras, ctx.config.data.resolution, ctx.config.data.textures)
    base = pool[p["object"]].moved(orientation=p["orientation"])
    others = [o for j, o in enumerate(pool) if j != p["object"]]
    rng = np.random.default_rng(unit.seed)  # the same perturbations and SA draws for every agent
    t0 = time.perf_counter()
    scorer = make_scorer(ctx, p["agent"], appearance, pool)
    if isinstance(scorer, PredictorScorer):
        scorer.views = STACKABILITY_VIEWS
    try:
        score, per_other = base_stackability(base, others, scorer, rng, cfg.anneal_steps, cfg.anneal_radius)
    finally:
        scorer.close()
    return {**_ranking_row(p["object"], base, score, per_other), "agent": p["agent"],
            "seconds": time.perf_counter() - t0}


def _class_means(rows: list[dict[str, Any]]) -> dict[str, float]:
    out = {}
    for cls in CLASS_ORDER:
        scores = [r["score"] for r in rows if r["class"] == cls]
        if scores:
            out[cls] = float(np.mean(scores))
    return out


def _area_correlation(rows: list[dict[str, Any]]) -> dict[str, float]:
    """Fig. 3.6: per class, Pearson's r between stackability and projected area (classes of >= 3 sizes)."""
    out = {}
    for cls in CLASS_ORDER:
        pts = np.array([(r["projected_area"], r["score"]) for r in rows if r["class"] == cls])
        if len(pts) >= 3 and pts[:, 0].std() > 0 and pts[:, 1].std() > 0:
            out[cls] = float(np.corrcoef(pts[:, 0], pts[:, 1])[0, 1])
    return out


def _expected_order(means: dict[str, float]) -> bool | None:
    present = [means[c] for c in _EXPECTED if c in means]
    if len(present) < 2:
        return None
    return all(a > b for a, b in zip(present, present[1:]))


def run_stackability(ctx: Context, agents: list[str]) -> dict[str, Any]:
    cfg = ctx.config.deploy
    agents = [a for a in agents if a in ("predictor", "oracle")]
    if not agents:
        raise BadInput("stackability needs a scoring agent: predictor or oracle")
    pool_seed = unit_seed(ctx.seed, "stackability-pool")
    pool = stackability_pool(cfg.stackability_pool, np.random.default_rng(pool_seed))
    units = []
    for agent in agents:
        for i, obj in enumerate(pool):
            for oriented in orientations(obj):
                units.append(Unit(f"stackability-{agent}", len(units), 1,
                                  unit_seed(ctx.seed, "stackability", i, oriented.orientation),
                                  {"agent": agent, "object": i, "orientation": oriented.orientation,
                                   "pool": cfg.stackability_pool, "pool_seed": pool_seed}))
    t0 = time.perf_counter()
    rows = ctx.map(stackability_unit, units, description="stackability")
    result: dict[str, Any] = {"task": "stackability", "objects": len(pool), "bases": len(units) // len(agents),
                              "anneal_steps": cfg.anneal_steps, "agents": {}}
    for agent in agents:
        mine = sorted(({k: v for k, v in r.items() if k != "agent"} for r in rows if r["agent"] == agent),
                      key=lambda r: (-r["score"], -r["projected_area"]))
        means = _class_means(mine)
        best = {}
        for r in mine:
            best.setdefault(r["object"], r)
        result["agents"][agent] = {
            "ranking": mine, "class_means": means, "expected_order_holds": _expected_order(means),
            "area_correlation": _area_correlation(mine),
            "object_order": [{"object": o, "orientation": r["orientation"], "score": r["score"]} for o, r in best.items()],
            "seconds": float(sum(r.pop("seconds") for r in mine)),
        }
    result["seconds"] = time.perf_counter() - t0
    if ctx.run is not None:
        main = agents[0]
        result["artifacts"] = _stackability_figures(ctx, pool, result["agents"], main, pool_seed)
    return result


# ==============================================================================================
# stacking (Section 3.5.2)
# ==============================================================================================

def stack_pool(scenario: str, n: int, rng: np.random.Generator) -> list[StackObject]:
    """A pool of ``n`` objects: cubes, cuboids, or CCS (cuboids and cylinders, exactly two spheres)."""
    if scenario == "cubes":
        objs = [sample_cube(rng) for _ in range(n)]
    elif scenario == "cuboids":
        objs = [sample_cuboid(rng) for _ in range(n)]
    elif scenario == "ccs":
        spheres = min(2, n)
        objs = [sample_sphere(rng) for _ in range(spheres)]
        objs += [sample_cuboid(rng) if rng.random() < 0.5 else sample_cylinder(rng) for _ in range(n - spheres)]
        objs = [objs[i] for i in rng.permutation(n)]
    else:
        raise unknown("stacking scenario", scenario, STACK_SCENARIOS)
    # all aligned (yaw 0): two rotated rectangles can meet in an octagon, on which MuJoCo 3.9's
    # box-box collider overflows ("returned 9 contacts ... expected at most 8")
    return [o.moved(yaw=0.0) for o in objs]


def _stack_order(pool: list[StackObject], scorer: Scorer, rng: np.random.Generator, steps: int,
                 radius: float) -> list[StackObject]:
    """Stack order and orientation by (quick) stackability: each object in its best orientation,
    most stackable first."""
    rows = stackability_ranking(pool, scorer, rng, steps, radius, others=QUICK_OTHERS)
    queue, done = [], set()
    for r in rows:
        if r["object"] not in done:
            done.add(r["object"])
            queue.append(pool[r["object"]].moved(orientation=r["orientation"]))
    return queue


def _live_objects(sim, names: list[str], objects: list[StackObject]) -> list[StackObject]:
    """The objects where the simulation has them now (position; orientation as placed)."""
    out = []
    for name, obj in zip(names, objects):
        pos, _ = sim.get_pose(name)
        out.append(obj.moved(x=float(pos[0]), y=float(pos[1]), z=float(pos[2])))
    return out


def _watch(sim, names: list[str], objects: list[StackObject], start: list, seconds: float, stop_early: bool = True,
           frame: Callable[[float], None] | None = None, frame_every: float = 1 / VIDEO_FPS) -> bool:
    """Run the physics for ``seconds``; True when one of the named objects fell (moved more than
    MOVE_THRESHOLD from its ``start`` pose or tipped more than TILT_THRESHOLD)."""
    dt = sim.scene.timestep
    chunk = max(1, int(round(CHECK_EVERY / dt)))
    every = max(1, int(round(frame_every / dt)))
    total = max(1, int(round(seconds / dt)))
    fell, done = False, 0
    while done < total:
        n = min(chunk, total - done)
        if frame is not None:
            n = min(n, every - done % every)
        sim.step(n)
        done += n
        if frame is not None and done % every == 0:
            frame(done * dt)
        if not fell:
            for name, obj, (p0, q0) in zip(names, objects, start):
                pos, quat = sim.get_pose(name)
                if np.linalg.norm(pos - p0) > MOVE_THRESHOLD or tilt_degrees(obj, q0, quat) > TILT_THRESHOLD:
                    fell = True
                    break
            if fell and stop_early:
                return True
    return fell


class _Recorder:
    """Video frames and a rerun recording of one episode (inactive when ``path`` is None)."""

    def __init__(self, stem: Path | None, name: str, camera: str = "video0", fps: float = VIDEO_FPS):
        self.stem, self.camera, self.fps = stem, camera, fps
        self.frames: list[np.ndarray] = []
        self.rec = None
        self.files: list[str] = []
        if stem is not None:
            from physint_cli.artifacts import Recording

            self.rec = Recording(stem.with_suffix(".rrd"), name)

    @property
    def active(self) -> bool:
        return self.stem is not None

    def frame(self, sim, t: float) -> None:
        img = sim.render(self.camera, rgb=True).rgb
        self.frames.append(img)
        if self.rec is not None and len(self.frames) % 5 == 1:  # 5 fps in the recording
            self.rec.time(seconds=t)
            self.rec.image("video", img)

    def step(self, sim, step: int, t: float, cameras: list[str], **scalars: float | None) -> None:
        """Images per step: every stacking camera after a placement, and the step's numbers."""
        if self.rec is None:
            return
        self.rec.time(step=step, seconds=t)
        for cam in cameras:
            self.rec.image(f"cameras/{cam}", sim.render(cam, rgb=True).rgb)
        for key, value in scalars.items():
            if value is not None:
                self.rec.scalar(key, value)

    def text(self, entity: str, text: str) -> None:
        if self.rec is not None:
            self.rec.text(entity, text)

    def close(self) -> list[str]:
        if self.stem is None:
            return []
        from physint_cli.artifacts import save_movie

        self.rec.close()
        self.files.append(self.stem.with_suffix(".rrd").name)
        if self.frames:
            self.files.append(save_movie(self.stem, self.frames, fps=self.fps).name)
        return self.files


def _artifact(ctx: Context, name: str) -> Path | None:
    if ctx.run is None:
        return None
    from physint_cli.runs import Run

    path = Run(Path(ctx.run)).artifact(name)
    path.parent.mkdir(parents=True, exist_ok=True)
    return path


def _quick_steps(cfg) -> int:
    return max(4, cfg.anneal_steps // QUICK_STEPS_DIVISOR)


def stack_episode(ctx: Context, unit: Unit) -> dict[str, Any]:
    """Work unit: one stacking episode of ``unit.params['scenario']`` by ``unit.params['agent']``.

    ``unit.seed`` fixes the pool and the appearance (the same for every agent); the agent's own
    draws (annealing, random placements) come from a generator seeded by the unit seed and the agent.
    """
    p = unit.params
    cfg = ctx.config.deploy
    agent, scenario, n = p["agent"], p["scenario"], int(p["pool"])
    t0 = time.perf_counter()
    rng = np.random.default_rng(unit.seed)
    pool = stack_pool(scenario, n, rng)
    appearance = Appearance.draw(rng, cfg.cameras, ctx.config.data.resolution, ctx.config.data.textures,
                                 timestep=ctx.config.data.timestep)
    arng = np.random.default_rng([unit.seed, AGENTS.index(agent)])
    scorer = make_scorer(ctx, agent, appearance, pool)
    try:  # random placement: in the oracle's order
        with (scorer.using_views(STACKABILITY_VIEWS) if isinstance(scorer, PredictorScorer)
              else contextlib.nullcontext()):
            queue = _stack_order(pool, scorer or OracleScorer(), arng, _quick_steps(cfg), cfg.anneal_radius)
        rec = _Recorder(_artifact(ctx, f"stack_{scenario}_{agent}") if p.get("record") else None,
                        f"stack-{scenario}-{agent}")
        out = _stack_live(ctx, queue, appearance, agent, scorer, arng, rec)
    finally:
        if scorer is not None:
            scorer.close()
    out.update(scenario=scenario, agent=agent, episode=unit.index, pool=n, seconds=time.perf_counter() - t0,
               artifacts=rec.close())
    return out


def _stack_live(ctx: Context, queue: list[StackObject], appearance: Appearance, agent: str, scorer: Scorer | None,
                rng: np.random.Generator, rec: _Recorder) -> dict[str, Any]:
    """Build the tower in one live simulation: pool objects wait far away, each is moved to its
    spawn pose, released and watched; the cameras follow the tower up."""
    cfg = ctx.config.deploy
    names = [f"obj{i}" for i in range(len(queue))]
    parked = [o.moved(x=PARK + 0.5 * i, y=PARK, z=o.height / 2) for i, o in enumerate(queue)]
    first = _on_top([], queue[0], (0.0, 0.0))
    cams = appearance.ring([first])
    video = appearance.ring([first], n=1, size=VIDEO_SIZE, factor=1.4, prefix="video", azimuth=math.pi / 6)
    sim = ctx.make_sim(appearance.scene(parked, cameras=cams + video))
    placed: list[int] = []
    trunk: list[StackObject] = []
    scores: list[float | None] = []
    put_aside, collapsed, step, error = 0, False, 0, None
    try:
        if rec.active:
            rec.text("episode", f"agent {agent}; queue: " + ", ".join(f"{o.shape} {o.orientation}" for o in queue))
            rec.frame(sim, 0.0)
        for i, obj in enumerate(queue):
            if not trunk:
                xy, score = np.zeros(2), None  # the first object goes to the scene centre
            else:
                xy, score = _choose(agent, scorer, trunk, obj, Disc(trunk[-1].xy, cfg.anneal_radius),
                                    cfg.anneal_steps, rng)
                if score is not None and score < ACCEPT:
                    put_aside += 1  # no stable position: disregarded for the rest of the episode
                    continue
            spawn = _on_top(trunk, obj, xy, gap=SPAWN_GAP)
            sim.set_pose(names[i], (spawn.x, spawn.y, spawn.z), spawn.quat)
            sim.set_velocity(names[i], (0.0, 0.0, 0.0))
            watched = [names[k] for k in placed] + [names[i]]
            objs = [queue[k] for k in placed] + [obj]
            start = [sim.get_pose(nm) for nm in watched]
            try:
                fell = _watch(sim, watched, objs, start, SETTLE_SECONDS, stop_early=not rec.active,
                              frame=(lambda t: rec.frame(sim, t)) if rec.active else None)
            except SimulationError as exc:  # the simulator broke down: the episode ends here
                error = str(exc)
                break
            scores.append(score)
            step += 1
            if fell:
                collapsed = True
                rec.step(sim, step, sim.time, [c.name for c in cams], score=score, height=len(placed))
                break
            placed.append(i)
            trunk = _live_objects(sim, [names[k] for k in placed], [queue[k] for k in placed])
            cams = appearance.ring(trunk)
            _move_cameras(sim, cams + appearance.ring(trunk, n=1, size=VIDEO_SIZE, factor=1.4, prefix="video",
                                                      azimuth=math.pi / 6))
            rec.step(sim, step, sim.time, [c.name for c in cams], score=score, height=len(placed))
    finally:
        sim.close()
    return {"height": len(placed), "collapsed": collapsed, "put_aside": put_aside, "sim_error": error,
            "order": [f"{o.shape}/{o.orientation}" for o in queue],
            "scores": [None if s is None else round(float(s), 4) for s in scores]}


def _histogram(heights: list[int], top: int) -> list[int]:
    counts = [0] * (top + 1)
    for h in heights:
        counts[min(h, top)] += 1
    return counts


def episode_units(ctx: Context, task: str, key: str, variants, agents: list[str], episodes: int,
                  **params: Any) -> list[Unit]:
    """One work unit per (variant, agent, episode). Every agent meets the same episode seeds, so the
    agents are compared on the same pools and appearances; the first agent's first episode of the
    first variant is recorded."""
    return [Unit(f"{task}-{variant}-{agent}", e, 1, unit_seed(ctx.seed, task, variant, e),
                 {key: variant, "agent": agent, **params,
                  "record": agent == agents[0] and e == 0 and variant == variants[0]})
            for variant in variants for agent in agents for e in range(episodes)]


def run_stacking(ctx: Context, agents: list[str], episodes: int) -> dict[str, Any]:
    cfg = ctx.config.deploy
    agents = [a for a in agents if a in ("predictor", "oracle", "random")]
    if not agents:
        raise BadInput("stacking needs an agent: predictor, oracle or random")
    units = episode_units(ctx, "stack", "scenario", STACK_SCENARIOS, agents, episodes, pool=cfg.pool)
    t0 = time.perf_counter()
    results = ctx.map(stack_episode, units, description="stacking")
    out: dict[str, Any] = {"task": "stack", "episodes": episodes, "pool": cfg.pool, "anneal_steps": cfg.anneal_steps,
                           "anneal_radius": cfg.anneal_radius, "scenarios": {}}
    artifacts: list[str] = []
    for scenario in STACK_SCENARIOS:
        top = cfg.pool - (min(2, cfg.pool) - 1 if scenario == "ccs" else 0)  # CCS: at most one sphere, on top
        per: dict[str, Any] = {"max_height": top}
        for agent in agents:
            mine = [r for r in results if r["scenario"] == scenario and r["agent"] == agent]
            heights = [r["height"] for r in mine]
            per[agent] = {"heights": heights, "histogram": _histogram(heights, cfg.pool),
                          "mean_height": float(np.mean(heights)), "collapses": sum(r["collapsed"] for r in mine),
                          "put_aside_mean": float(np.mean([r["put_aside"] for r in mine])),
                          "sim_errors": sum(r["sim_error"] is not None for r in mine),
                          "seconds_per_episode": float(np.mean([r["seconds"] for r in mine]))}
            for r in mine:
                artifacts += r["artifacts"]
        out["scenarios"][scenario] = per
    out["seconds"] = time.perf_counter() - t0
    if ctx.run is not None:
        artifacts.append(_stack_figure(ctx, out, agents))
        out["artifacts"] = artifacts
    return out


# ==============================================================================================
# counterbalancing (Section 3.5.3)
# ==============================================================================================

def counterweight(kind: str, rng: np.random.Generator) -> StackObject:
    """A counterweight of ~0.1-0.2 kg: cube, cuboid (largest face down), upright cylinder, or sphere."""
    if kind == "cube":
        a = rng.uniform(0.045, 0.06)
        obj = StackObject("box", (a, a, a))
    elif kind == "cuboid":
        obj = StackObject("box", (rng.uniform(0.06, 0.075), rng.uniform(0.045, 0.055), rng.uniform(0.035, 0.045)))
    elif kind == "cylinder":
        obj = StackObject("cylinder", (rng.uniform(0.026, 0.032), rng.uniform(0.045, 0.06)))
    elif kind == "sphere":
        obj = StackObject("sphere", (rng.uniform(0.029, 0.034),))
    else:
        raise unknown("counterweight", kind, COUNTERWEIGHTS)
    return obj


def unstable_t(rng: np.random.Generator, weight: StackObject, min_band: float = 0.015, safe: float = 0.005,
               max_tries: int = 200) -> list[StackObject]:
    """An unstable "T": a base block and a plank whose centre of mass overhangs the base's edge by
    0.5-2 cm along the plank (a VCOM), such that ``weight`` placed on the plank's axis can balance it
    with a Lemma-1 margin of at least ``safe`` along at least ``min_band`` metres of the plank.

    Both are shapes of the training distribution (CCS cuboids: edges up to 11 cm, aspect ratio at
    most 3.5), so the predictor is asked about objects it has seen: a first version with a
    20-26 cm plank, longer than anything in the dataset, left the predictor below random placement.
    """
    longest = CUBOID_EDGE[1]
    for _ in range(max_tries):
        a = rng.uniform(0.04, 0.06)
        yaw = rng.uniform(0, 2 * math.pi)
        base = StackObject("box", (a, a, rng.uniform(0.05, 0.09)), yaw=yaw)
        length = rng.uniform(0.10, longest)
        thickness = rng.uniform(length / CUBOID_MAX_ASPECT, 0.035)
        plank_size = (length, rng.uniform(max(thickness, 0.035), 0.05), thickness)
        u = np.array([math.cos(yaw), math.sin(yaw)])
        c = (a / 2 + rng.uniform(0.005, 0.02)) * u
        plank = StackObject("box", plank_size, x=float(c[0]), y=float(c[1]), yaw=yaw)
        t = stack_up([base, plank])
        weight = weight.moved(yaw=yaw)  # aligned with the plank (see stack_pool)
        if analyse(t).violation != "VCOM":
            continue
        s = np.linspace(-plank_size[0] / 2, plank_size[0] / 2, 41)
        ok = [lemma1_margin(t + [weight.moved(x=float(c[0] + k * u[0]), y=float(c[1] + k * u[1]))]) >= safe for k in s]
        if np.sum(ok) * (s[1] - s[0]) >= min_band:
            return t
    raise RuntimeError("no balanceable T found")


def balance_episode(ctx: Context, unit: Unit) -> dict[str, Any]:
    """Work unit: one counterbalancing episode (``params['weight']``, ``params['agent']``).

    The T and the counterweight come from ``unit.seed`` (the same for every agent). The T is frozen,
    the counterweight released ``SPAWN_GAP`` above the plank where the agent chooses, allowed to
    settle for ``HOLD_SECONDS``, then the T is unfrozen: success when no object moves more than 1 cm
    (the counterweight: from where it was put) or tips more than 10 degrees in ``BALANCE_SECONDS``.
    Agent ``none`` is the control: the T alone, unfrozen.
    """
    p = unit.params
    cfg = ctx.config.deploy
    agent, kind = p["agent"], p["weight"]
    t0 = time.perf_counter()
    rng = np.random.default_rng(unit.seed)
    weight = counterweight(kind, rng)
    t = unstable_t(rng, weight)
    weight = weight.moved(yaw=t[1].yaw)
    appearance = Appearance.draw(rng, cfg.cameras, ctx.config.data.resolution, ctx.config.data.textures,
                                 timestep=ctx.config.data.timestep)
    arng = np.random.default_rng([unit.seed, AGENTS.index(agent)])
    plank = t[1]
    score = None
    scorer = make_scorer(ctx, agent, appearance, t + [weight])
    try:
        if agent == "none":
            objects = list(t)
        else:
            xy, score = _choose(agent, scorer, t, weight, Rect(plank.xy, plank.extents, plank.yaw), cfg.anneal_steps,
                                arng)
            objects = t + [_on_top(t, weight, xy, gap=SPAWN_GAP)]
    finally:
        if scorer is not None:
            scorer.close()
    rec = _Recorder(_artifact(ctx, f"balance_{kind}_{agent}") if p.get("record") else None, f"balance-{kind}-{agent}")
    cams = appearance.ring(objects)
    video = appearance.ring(objects, n=1, size=VIDEO_SIZE, factor=1.3, prefix="video", azimuth=math.pi / 6)
    names = [f"obj{i}" for i in range(len(objects))]
    error = None
    with ctx.make_sim(appearance.scene(objects, cameras=cams + video)) as sim:
        try:
            fell = _balance_live(sim, agent, names, objects, cams, rec, score)
        except SimulationError as exc:  # the simulator broke down: a failed episode
            fell, error = True, str(exc)
    margin = lemma1_margin(objects)
    return {"weight": kind, "agent": agent, "episode": unit.index, "success": not fell, "sim_error": error,
            "score": None if score is None else float(score),
            "lemma1_margin": margin if math.isfinite(margin) else None,
            "seconds": time.perf_counter() - t0, "artifacts": rec.close()}


def _balance_live(sim, agent: str, names: list[str], objects: list[StackObject], cams: list[Camera], rec: _Recorder,
                  score: float | None) -> bool:
    """Freeze the T, let the counterweight settle on it, unfreeze, watch: True when something fell."""
    frame = (lambda tt: rec.frame(sim, tt)) if rec.active else None
    if agent != "none":
        sim.freeze("obj0")
        sim.freeze("obj1")
        spawn = sim.get_pose("obj2")
        rec.step(sim, 0, 0.0, [c.name for c in cams], score=score)
        _watch(sim, [], [], [], HOLD_SECONDS, stop_early=False, frame=frame)
        sim.unfreeze("obj0")
        sim.unfreeze("obj1")
        start = [sim.get_pose("obj0"), sim.get_pose("obj1"), spawn]
    else:
        start = [sim.get_pose(nm) for nm in names]
    fell = _watch(sim, names, objects, start, BALANCE_SECONDS, stop_early=not rec.active, frame=frame)
    rec.step(sim, 1, sim.time, [c.name for c in cams], success=float(not fell))
    return fell


def run_balance(ctx: Context, agents: list[str], episodes: int) -> dict[str, Any]:
    cfg = ctx.config.deploy
    agents = [a for a in agents if a in AGENTS]
    if "none" not in agents:
        agents = agents + ["none"]
    units = episode_units(ctx, "balance", "weight", COUNTERWEIGHTS, agents, episodes)
    t0 = time.perf_counter()
    results = ctx.map(balance_episode, units, description="counterbalancing")
    out: dict[str, Any] = {"task": "balance", "episodes": episodes, "anneal_steps": cfg.anneal_steps,
                           "counterweights": {}}
    artifacts: list[str] = []
    for kind in COUNTERWEIGHTS:
        per = {}
        for agent in agents:
            mine = [r for r in results if r["weight"] == kind and r["agent"] == agent]
            per[agent] = {"success_rate": float(np.mean([r["success"] for r in mine])),
                          "successes": int(sum(r["success"] for r in mine)), "episodes": len(mine),
                          "sim_errors": sum(r["sim_error"] is not None for r in mine),
                          "seconds_per_episode": float(np.mean([r["seconds"] for r in mine]))}
            for r in mine:
                artifacts += r["artifacts"]
        out["counterweights"][kind] = per
    out["success_rate"] = {a: float(np.mean([out["counterweights"][k][a]["success_rate"] for k in COUNTERWEIGHTS]))
                           for a in agents}
    out["seconds"] = time.perf_counter() - t0
    if ctx.run is not None:
        artifacts.append(_balance_figure(ctx, out, agents))
        out["artifacts"] = artifacts
    return out


# ==============================================================================================
# figures
# ==============================================================================================

_AGENT_COLOURS = {"predictor": "tab:orange", "oracle": "tab:blue", "random": "tab:gray", "none": "black"}
_CLASS_COLOURS = {"cuboid largest face": "tab:blue", "cuboid middle face": "tab:cyan",
                  "cuboid smallest face": "tab:purple", "cube": "tab:green", "cylinder upright": "tab:orange",
                  "cylinder lying": "tab:red", "sphere": "tab:gray"}


def _stack_figure(ctx: Context, out: dict[str, Any], agents: list[str]) -> str:
    """Fig. 3.7: per scenario, how often each agent built a tower of each height; dashed: the mean."""
    from physint_cli.artifacts import save_plot

    def draw(ax):
        fig = ax.figure
        ax.remove()
        axes = fig.subplots(1, len(STACK_SCENARIOS), sharey=True)
        width = 0.8 / len(agents)
        for axis, scenario in zip(axes, STACK_SCENARIOS):
            per = out["scenarios"][scenario]
            for k, agent in enumerate(agents):
                hist = per[agent]["histogram"]
                x = np.arange(len(hist)) + (k - (len(agents) - 1) / 2) * width
                axis.bar(x, hist, width, color=_AGENT_COLOURS[agent], label=agent)
                axis.axvline(per[agent]["mean_height"], color=_AGENT_COLOURS[agent], ls="--", lw=1)
            axis.set_title(scenario)
            axis.set_xlabel("tower height (objects)")
            axis.set_xticks(range(0, out["pool"] + 1, 2))
        axes[0].set_ylabel("episodes")
        axes[-1].legend(fontsize=8)

    path = _artifact(ctx, "stack_heights.png")
    save_plot(path, draw, figsize=(11, 3.2))
    return path.name


def _balance_figure(ctx: Context, out: dict[str, Any], agents: list[str]) -> str:
    """Fig. 3.9 (right): success rate per counterweight type and agent."""
    from physint_cli.artifacts import save_plot

    def draw(ax):
        width = 0.8 / len(agents)
        for k, agent in enumerate(agents):
            rates = [out["counterweights"][w][agent]["success_rate"] for w in COUNTERWEIGHTS]
            x = np.arange(len(COUNTERWEIGHTS)) + (k - (len(agents) - 1) / 2) * width
            ax.bar(x, rates, width, color=_AGENT_COLOURS[agent], label=agent)
        ax.set_xticks(range(len(COUNTERWEIGHTS)), COUNTERWEIGHTS)
        ax.set_ylim(0, 1.05)
        ax.set_ylabel(f"success rate ({out['episodes']} episodes)")
        ax.set_title("counterbalancing an unstable T")
        ax.legend(fontsize=8)

    path = _artifact(ctx, "balance_success.png")
    save_plot(path, draw, figsize=(6, 3.5))
    return path.name


def _portrait(stage: _Stage, obj: StackObject) -> np.ndarray:
    """One object alone on the ground, seen from the front."""
    stage.show(stack_up([obj.moved(x=0.0, y=0.0)]), factor=1.25)
    return stage.render()[0]


def _stackability_figures(ctx: Context, pool: list[StackObject], agents_out: dict[str, Any], main: str,
                          pool_seed: int) -> list[str]:
    from physint_cli.artifacts import save_plot

    rows = agents_out[main]["ranking"]

    def scatter(ax):  # Fig. 3.6
        for cls in CLASS_ORDER:
            pts = [(r["projected_area"] * 1e4, r["score"]) for r in rows if r["class"] == cls]
            if pts:
                x, y = zip(*pts)
                ax.scatter(x, y, s=22, color=_CLASS_COLOURS[cls], label=cls)
        ax.set_xlabel("projected surface area (cm$^2$)")
        ax.set_ylabel(f"stackability ({main})")
        ax.set_ylim(-0.03, 1.03)
        ax.legend(fontsize=7, loc="lower right")

    files = []
    path = _artifact(ctx, "stackability_area.png")
    save_plot(path, scatter, figsize=(6, 4))
    files.append(path.name)

    appearance = Appearance.draw(np.random.default_rng(pool_seed), randomise=False,
                                 textures=ctx.config.data.textures)
    appearance = dataclasses.replace(appearance, elevation=25.0, azimuth=-math.pi / 2 + 0.4)
    order = agents_out[main]["object_order"]
    stage = _Stage(appearance, ctx.make_sim, pool, cameras=1, size=_STRIP_SIZE, prefix="portrait")
    try:
        top = [_portrait(stage, o) for o in pool]
        bottom = [_portrait(stage, pool[r["object"]].moved(orientation=r["orientation"])) for r in order]
    finally:
        stage.close()
    strip = np.concatenate([np.concatenate(top, axis=1), np.concatenate(bottom, axis=1)], axis=0)

    def draw_strip(ax):  # Fig. 3.5
        ax.imshow(strip)
        for k, r in enumerate(order):
            ax.text((k + 0.5) * _STRIP_SIZE, 2 * _STRIP_SIZE + 12, f"{r['score']:.2f}", ha="center", va="top",
                    fontsize=7)
        ax.set_xticks([])
        ax.set_yticks([_STRIP_SIZE / 2, 1.5 * _STRIP_SIZE], ["pool", "by stackability"], fontsize=8)
        ax.set_title(f"objects sorted by stackability ({main}), best orientation", fontsize=9)

    path = _artifact(ctx, "stackability_strip.png")
    save_plot(path, draw_strip, figsize=(max(6, 0.9 * len(pool)), 2.6))
    files.append(path.name)
    return files


# ==============================================================================================
# the verb
# ==============================================================================================

def _agents(ctx: Context) -> list[str]:
    chosen = ctx.config.deploy.agents
    if not chosen:
        return (["predictor"] if ctx.source_run is not None else []) + ["oracle", "random"]
    if isinstance(chosen, str):
        chosen = [a.strip() for a in chosen.split(",") if a.strip()]
    for a in chosen:
        if a not in AGENTS:
            raise unknown("deploy agent", a, AGENTS)
    return list(dict.fromkeys(chosen))


def deploy(ctx: Context) -> dict[str, Any]:
    """Run the deployment task ``ctx.task`` (--task; default ``stackability``); JSON-ready metrics."""
    task = ctx.task or "stackability"
    if task not in TASKS:
        raise unknown("deploy task for stability", task, TASKS)
    episodes = ctx.config.deploy.episodes  # --episodes N arrives as deploy.episodes=N; >= 1 by the config
    agents = _agents(ctx)
    ctx.log(f"stability deploy: task {task}, agents {', '.join(agents)}")
    if task == "stackability":
        return run_stackability(ctx, agents)
    if task == "stack":
        return run_stacking(ctx, agents, episodes)
    return run_balance(ctx, agents, episodes)
