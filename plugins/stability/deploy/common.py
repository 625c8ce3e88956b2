"""What the three deployment tasks share: their constants, the appearance of an episode (one
random draw; only geometry changes within it), watching live objects fall, the episode recorder
(MP4 or GIF, and .rrd) and the work units of the episodes."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from physint_backends.randomize import PALETTE, orbit_cameras
from physint_backends.spec import Camera, Scene, Texture
from physint_cli.method import Context, Unit, unit_seed

from ..physics import SHAPES, StackObject
from ..scenes import default_textures, lighting_conditions, Scenario, tilt_degrees, to_scene


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


# ==============================================================================================
# figures
# ==============================================================================================

_AGENT_COLOURS = {"predictor": "tab:orange", "oracle": "tab:blue", "random": "tab:gray", "none": "black"}
_CLASS_COLOURS = {"cuboid largest face": "tab:blue", "cuboid middle face": "tab:cyan",
                  "cuboid smallest face": "tab:purple", "cube": "tab:green", "cylinder upright": "tab:orange",
                  "cylinder lying": "tab:red", "sphere": "tab:gray"}
