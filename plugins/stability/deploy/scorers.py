"""Scorers: how stable would the stack be with this object placed here? The stability
predictor on rendered images (Section 3.5), the Lemma-1 oracle (Eq. 3.1) and their search."""

from __future__ import annotations

import contextlib
import math
from pathlib import Path
from typing import Any, Callable

import numpy as np

from physint_backends.spec import Scene
from physint_cli.errors import BadInput
from physint_cli.method import Context
from physint_cli.training import torch_threads

from ..physics import analyse, stack_up, StackObject
from .common import _move_cameras, _object_key, Appearance, ORACLE_SCALE, PARK
from .search import anneal


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
        from ..evaluate import predict

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
    from ..checkpoint import load_predictor

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
