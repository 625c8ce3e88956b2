"""Speed of the simulator backends, each figure beside raw MuJoCo (or raw robosuite) in the same run.

    python benchmarks/backends.py [--quick] [--json FILE] [--backends mujoco,pybullet,robosuite]

Measured on one core (one process; OpenMP/BLAS at one thread; Mesa's llvmpipe rasterising in the
calling thread, ``LP_NUM_THREADS=0``; each can be overridden from the environment), per backend
of ``physint_backends``:

1. physics steps/s of a stable single-stranded stack of 6 cubes, one ``step(1)`` per call and
   ``step(100)`` per call;
2. renders/s (RGB) of that scene from one camera at 64x64 and at 128x128;
3. small scenes per minute: build the stack scene (``make``), 10 physics steps, ``close``; and
   the same with ``sim.reset(new_scene)`` on a live simulation instead of ``make``/``close``;
4. control steps/s of a Panda scene (``scene.robot = RobotSpec()``, one 4 cm cube on the table,
   one 64x64 camera): ``sim.robot.act([dx, dy, dz, g])`` plus one 64x64 render; and without the
   render;
5. renders/s of that Panda scene with the robot's detailed visual meshes (``robot_visual``
   ``"full"``) beside the default low-poly drawing.

The raw references are measured in the same run, interleaved with each backend figure (rounds of
backend / reference; each figure is the best round, which discards slow-downs caused by other
processes on a shared machine):

* raw MuJoCo: the same stack hand-written as an MJCF string (same timestep, integrator, friction
  cones and contact stiffness as the MuJoCo backend, the same flat sky colour as a flat skybox
  texture; one extra row shows raw MuJoCo with a black background instead), stepped with ``mujoco.mj_step`` and
  rendered with ``mujoco.Renderer`` with ``shadowsize=0 offsamples=0`` and no reflections, the
  fastest reasonable direct use of MuJoCo; its scene "build" is ``MjModel.from_xml_string`` +
  ``MjData`` + 10 ``mj_step``;
* raw robosuite for the Panda rows: robosuite's own ``Lift`` environment (Panda, default
  ``OSC_POSE`` controller, ``control_freq`` set to the spec's 25 Hz so that a control step covers
  the same simulated time, ``hard_reset=False``, see :class:`RawLift`), ``env.step`` with a zero
  action, with its own 64x64 camera observation (``use_camera_obs=True``) or without any camera.

stdout carries the results (a Markdown table and notes); stderr carries progress.
Exit code 0 when every measurement ran (goals met or not), 1 when a backend failed.
"""

from __future__ import annotations

import os

# -- one core: set before numpy, torch, mujoco or Mesa start their thread pools ----------------
for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
# Mesa llvmpipe's rasteriser threads: 0 rasterises in the calling thread (one core, and the
# fastest and steadiest here: 1 adds a hand-off to a worker thread, ~45% slower at 64x64)
os.environ.setdefault("LP_NUM_THREADS", "0")
if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY"):
    os.environ["MUJOCO_GL"] = "egl"  # headless, as physint_backends does
if os.environ.get("MUJOCO_GL") == "egl":
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import argparse  # noqa: E402
import contextlib  # noqa: E402
import datetime  # noqa: E402
import gc  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import traceback  # noqa: E402
from dataclasses import asdict, dataclass  # noqa: E402
from importlib.metadata import PackageNotFoundError, version  # noqa: E402
from typing import Callable  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from commands import cpu_model  # noqa: E402

BACKENDS = ("mujoco", "pybullet", "robosuite")
CUBE = 0.06  # edge of the stacked cubes (m)
N_CUBES = 6
TIMESTEP = 0.002  # the spec's default physics step (s)
BUILD_STEPS = 10  # physics steps per small-scene build cycle
RENDER_GOAL_RATIO = 0.5  # stack-scene rendering within 2x of raw MuJoCo
CONTROL_GOAL = 100.0  # control steps/s with a 64x64 camera, on the MuJoCo and robosuite backends
SCENES_GOAL = 2000.0  # "thousands of small scenes per minute"
CONTROL_GOAL_BACKENDS = ("mujoco", "robosuite")
DETAILED_ROBOT = {"mujoco": "full", "pybullet": "full", "robosuite": "full"}  # robot_visual option values


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


@contextlib.contextmanager
def stdout_to_stderr():
    """Send C-level writes to stdout (pybullet's import banner) to stderr: stdout carries results."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        os.dup2(2, 1)
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


# ------------------------------------------------------------------------------------------------
# timing
# ------------------------------------------------------------------------------------------------
def rate(fn: Callable[[], object], seconds: float, per_call: float = 1.0, min_calls: int = 3) -> float:
    """Calls of ``fn`` per second (times ``per_call``) over at least ``seconds`` and ``min_calls`` calls."""
    n = 0
    clock = time.perf_counter
    start = clock()
    while True:
        fn()
        n += 1
        elapsed = clock() - start
        if elapsed >= seconds and n >= min_calls:
            return n * per_call / elapsed


def warm_up(fn: Callable[[], object], seconds: float, min_calls: int = 2) -> None:
    rate(fn, seconds, min_calls=min_calls)


def interleaved(backend_fn, raw_fn, seconds: float, rounds: int, per_call=(1.0, 1.0), min_calls: int = 3):
    """Best-of-``rounds`` rates of a backend and its raw reference, measured alternately.

    Alternating rounds expose both to the same machine load; the best round of each is the
    figure least disturbed by other processes.
    """
    if raw_fn is not None:
        warm_up(raw_fn, 0.25 * seconds)
    warm_up(backend_fn, 0.25 * seconds)
    best_b = best_r = 0.0
    for _ in range(rounds):
        best_b = max(best_b, rate(backend_fn, seconds / rounds, per_call[0], min_calls))
        if raw_fn is not None:
            best_r = max(best_r, rate(raw_fn, seconds / rounds, per_call[1], min_calls))
    return best_b, (best_r if raw_fn is not None else None)


# ------------------------------------------------------------------------------------------------
# scenes: the physint spec and the hand-written MJCF of the same stack
# ------------------------------------------------------------------------------------------------
def stack_offsets(rng: np.random.Generator | None) -> np.ndarray:
    """x, y offsets of each cube: none, or up to 3 mm (a different but stable stack per build)."""
    if rng is None:
        return np.zeros((N_CUBES, 2))
    return rng.uniform(-0.003, 0.003, size=(N_CUBES, 2))


def cube_rgba(i: int) -> tuple[float, float, float, float]:
    return (0.85, 0.15 * i, 0.25 + 0.1 * i, 1.0)


def stack_scene(offsets: np.ndarray, cameras: bool = True):
    from physint_backends import Body, Camera, Scene

    bodies = [Body.box(f"cube{i}", (CUBE, CUBE, CUBE), pos=(offsets[i, 0], offsets[i, 1], CUBE * (i + 0.5)),
                       rgba=cube_rgba(i)) for i in range(N_CUBES)]
    cams = [stack_camera("cam64", 64), stack_camera("cam128", 128)] if cameras else []
    return Scene(bodies=bodies, cameras=cams)


def stack_camera(name: str, size: int):
    from physint_backends import Camera

    return Camera(name, pos=(0.8, 0.0, 0.35), lookat=(0.0, 0.0, 0.18), fovy=45.0, width=size, height=size)


def scene_background() -> tuple[float, float, float] | None:
    """The flat sky colour the backends draw behind everything (``Scene.background``), if the spec has one."""
    from physint_backends import Scene

    background = getattr(Scene(), "background", None)
    return None if background is None else tuple(float(c) for c in background)[:3]  # type: ignore[return-value]


def stack_mjcf(offsets: np.ndarray, cameras: bool = True, sky: bool = True) -> str:
    """The stack scene by hand: what someone using MuJoCo directly would write, with fast rendering.

    With ``sky``, the backends' flat background colour is a flat skybox (MuJoCo's only way to
    colour the background); without it, the background is black.
    """
    solref = f"{2.5 * TIMESTEP:g} 1"  # the MuJoCo backend's stiff contacts (stacks stand)
    bodies = "\n".join(
        f'    <body pos="{x:.6f} {y:.6f} {CUBE * (i + 0.5):.6f}"><freejoint/>'
        f'<geom type="box" size="{CUBE / 2} {CUBE / 2} {CUBE / 2}" rgba="{" ".join(f"{c:g}" for c in cube_rgba(i))}"/>'
        f'</body>' for i, (x, y) in enumerate(offsets))
    cams = ""
    if cameras:
        for name, size in (("cam64", 64), ("cam128", 128)):
            rot = stack_camera(name, size).rotation()  # columns: right, up, backwards
            xyaxes = " ".join(f"{v:.9f}" for v in (*rot[:, 0], *rot[:, 1]))
            cams += f'    <camera name="{name}" pos="0.8 0 0.35" xyaxes="{xyaxes}" fovy="45"/>\n'
    background = scene_background() if sky else None
    asset = ""
    if background is not None:
        rgb = " ".join(f"{c:g}" for c in background)
        asset = (f'  <asset><texture type="skybox" builtin="flat" rgb1="{rgb}" rgb2="{rgb}" width="8" height="8"/>'
                 f'</asset>\n')
    return f"""<mujoco model="raw_stack">
  <option timestep="{TIMESTEP}" integrator="implicitfast" cone="elliptic"/>
  <visual>
    <quality shadowsize="0" offsamples="0"/>
    <headlight active="0"/>
  </visual>
  <default><geom condim="3" friction="0.8 0.005 0.0001" solref="{solref}"/></default>
{asset}  <worldbody>
    <light directional="true" pos="0 0 3" dir="0 0 -1" diffuse="0.7 0.7 0.7" ambient="0.3 0.3 0.3"
           specular="0.1 0.1 0.1" castshadow="false"/>
    <geom name="ground" type="plane" size="5 5 0.1" rgba="0.8 0.8 0.8 1"/>
{bodies}
{cams}  </worldbody>
</mujoco>
"""


def panda_scene():
    from physint_backends import Body, Camera, RobotSpec, Scene

    robot = RobotSpec()
    table = robot.table_height
    return Scene(bodies=[Body.box("cube", (0.04, 0.04, 0.04), pos=(0.0, 0.0, table + 0.02), mass=0.05,
                                  rgba=(0.9, 0.1, 0.1, 1.0))],
                 robot=robot,
                 cameras=[Camera("front", pos=(0.9, 0.0, table + 0.5), lookat=(0.0, 0.0, table), width=64, height=64)])


class Circle:
    """Actions moving the hand around a small horizontal circle (stays in the workspace forever)."""

    def __init__(self, step: float = 0.01, period: int = 50):
        self.k, self.step, self.period = 0, step, period

    def __call__(self) -> list[float]:
        theta = 2 * math.pi * self.k / self.period
        self.k += 1
        return [self.step * math.cos(theta), self.step * math.sin(theta), 0.0, 0.0]


# ------------------------------------------------------------------------------------------------
# raw references
# ------------------------------------------------------------------------------------------------
class RawMujoco:
    """The stack scene on MuJoCo directly."""

    def __init__(self):
        import mujoco

        self.mujoco = mujoco
        self.model = mujoco.MjModel.from_xml_string(stack_mjcf(stack_offsets(None)))
        self.data = mujoco.MjData(self.model)
        mujoco.mj_forward(self.model, self.data)
        self.start = self.data.qpos.copy()
        self.renderers = {size: mujoco.Renderer(self.model, size, size) for size in (64, 128)}
        self.rng = np.random.default_rng(0)
        self.first_frame = self.render(64)()  # the stack as built, to compare each backend's image with
        self.sky = scene_background() is not None
        if self.sky:  # the same scene with a black background, to show what the flat sky costs
            self.model_nosky = mujoco.MjModel.from_xml_string(stack_mjcf(stack_offsets(None), sky=False))
            self.data_nosky = mujoco.MjData(self.model_nosky)
            mujoco.mj_forward(self.model_nosky, self.data_nosky)
            self.renderer_nosky = mujoco.Renderer(self.model_nosky, 64, 64)

    def render_nosky(self) -> np.ndarray:
        self.renderer_nosky.update_scene(self.data_nosky, camera="cam64")
        return self.renderer_nosky.render()

    def step1(self) -> None:
        self.mujoco.mj_step(self.model, self.data)

    def step100(self) -> None:
        self.mujoco.mj_step(self.model, self.data, nstep=100)

    def render(self, size: int) -> Callable[[], np.ndarray]:
        renderer, camera = self.renderers[size], f"cam{size}"

        def render() -> np.ndarray:
            renderer.update_scene(self.data, camera=camera)
            return renderer.render()

        return render

    def build_cycle(self) -> None:
        """A small scene from scratch: parse, compile, 10 steps (nothing to close)."""
        model = self.mujoco.MjModel.from_xml_string(stack_mjcf(stack_offsets(self.rng)))
        data = self.mujoco.MjData(model)
        self.mujoco.mj_step(model, data, nstep=BUILD_STEPS)

    def max_drift(self) -> float:
        """Largest cube displacement (m) from where it was built."""
        q = self.data.qpos.reshape(N_CUBES, 7)[:, :3]
        return float(np.linalg.norm(q - self.start.reshape(N_CUBES, 7)[:, :3], axis=1).max())

    def close(self) -> None:
        for r in self.renderers.values():
            r.close()
        self.renderers = {}
        if self.sky:
            self.renderer_nosky.close()
            self.sky = False


def import_robosuite():
    """robosuite, without its import-time warnings (no private macro file, optional packages)."""
    logger = logging.getLogger("robosuite_logs")
    saved = logger.level
    logger.setLevel(logging.ERROR)
    quiet = logging.Filter()
    quiet.filter = lambda record: record.levelno >= logging.ERROR  # type: ignore[method-assign]
    logger.addFilter(quiet)
    try:
        import robosuite
    finally:
        logger.removeFilter(quiet)
        logger.setLevel(max(saved, logging.WARNING))
    return robosuite


class RawLift:
    """robosuite's own Lift task, stepped with a zero action (with or without its camera observation).

    ``hard_reset=False``: robosuite's default hard reset rebuilds the MjSim and its OpenGL
    render context, and the old context is freed later by the garbage collector, whatever
    OpenGL context is current then; in a process with other contexts that deletes another
    context's framebuffer, after which robosuite "renders" garbage at ~250 steps/s ("invalid
    framebuffer operation"). Without a hard reset the environment keeps its one context.
    """

    def __init__(self, camera: bool, control_hz: float):
        robosuite = import_robosuite()
        state = np.random.get_state()
        try:
            common = dict(robots="Panda", has_renderer=False, control_freq=control_hz, ignore_done=True,
                          hard_reset=False)
            if camera:
                self.env = robosuite.make("Lift", use_camera_obs=True, camera_heights=64, camera_widths=64,
                                          has_offscreen_renderer=True, **common)
            else:
                self.env = robosuite.make("Lift", use_camera_obs=False, has_offscreen_renderer=False, **common)
            self.env.reset()
        finally:
            np.random.set_state(state)
        gc.collect()  # nothing of robosuite's left for the collector to free mid-measurement
        self.zero = np.zeros(self.env.action_dim)
        self.camera = camera
        if camera:
            self.check_rendering()

    def check_rendering(self) -> None:
        """Fail loudly if robosuite's camera renders into a broken framebuffer (see the class docstring)."""
        from OpenGL import GL

        self.env.sim._render_context_offscreen.gl_ctx.make_current()
        while GL.glGetError() != GL.GL_NO_ERROR:  # clear stale error flags
            pass
        self.step()
        error = GL.glGetError()
        if error != GL.GL_NO_ERROR:
            raise RuntimeError(f"robosuite's offscreen rendering raised OpenGL error {error:#x}")

    def step(self) -> None:
        if self.camera:
            # robosuite renders into whichever OpenGL context is current and never makes its own
            # current; in a process that also renders elsewhere (the backends), it must be made
            # current first, as it is in a process that runs robosuite alone
            self.env.sim._render_context_offscreen.gl_ctx.make_current()
        obs, *_ = self.env.step(self.zero)
        if self.camera:
            assert obs["agentview_image"].shape == (64, 64, 3)

    def close(self) -> None:
        self.env.close()


# ------------------------------------------------------------------------------------------------
# results
# ------------------------------------------------------------------------------------------------
@dataclass
class Row:
    measure: str
    backend: str
    unit: str
    figure: float | None
    raw: float | None
    raw_name: str
    goal: str = "—"
    met: bool | None = None
    note: str = ""

    @property
    def ratio(self) -> float | None:
        if self.figure is None or not self.raw:
            return None
        return self.figure / self.raw

    def as_dict(self) -> dict:
        return dict(asdict(self), ratio=self.ratio)


def fmt(value: float | None) -> str:
    if value is None:
        return "—"
    if value >= 100:
        return f"{value:,.0f}"
    if value >= 10:
        return f"{value:.1f}"
    return f"{value:.2f}"


def table(rows: list[Row]) -> str:
    header = ["measure", "backend", "figure", "raw reference", "ratio", "goal", "met?"]
    body = []
    for r in rows:
        # three decimals where the goal is a ratio, so that a ratio just under it never reads as met
        ratio = "—" if r.ratio is None else f"{r.ratio:.3f}" if r.goal.startswith("ratio") else f"{r.ratio:.2f}"
        met = "—" if r.met is None else ("yes" if r.met else "**no**")
        figure = "error" if r.figure is None else f"{fmt(r.figure)} {r.unit}"
        raw = "—" if r.raw is None else f"{fmt(r.raw)} ({r.raw_name})"
        body.append([r.measure, r.backend, figure, raw, ratio, r.goal, met])
    widths = [max(len(str(line[i])) for line in [header] + body) for i in range(len(header))]
    out = ["| " + " | ".join(h.ljust(w) for h, w in zip(header, widths)) + " |",
           "|" + "|".join("-" * (w + 2) for w in widths) + "|"]
    for line in body:
        out.append("| " + " | ".join(str(c).ljust(w) for c, w in zip(line, widths)) + " |")
    return "\n".join(out)


# ------------------------------------------------------------------------------------------------
# the machine
# ------------------------------------------------------------------------------------------------
def gl_renderer() -> str:
    """The OpenGL renderer MuJoCo gets here (e.g. Mesa llvmpipe: software rasterisation)."""
    try:
        import mujoco
        from OpenGL import GL

        ctx = mujoco.GLContext(16, 16)
        ctx.make_current()
        try:
            return f"{GL.glGetString(GL.GL_RENDERER).decode()}; {GL.glGetString(GL.GL_VERSION).decode()}"
        finally:
            ctx.free()
    except Exception as exc:  # diagnostic only
        return f"unknown ({type(exc).__name__})"


def pkg(dist: str) -> str:
    try:
        return version(dist)
    except PackageNotFoundError:
        return "not installed"


def machine() -> dict:
    try:
        affinity = len(os.sched_getaffinity(0))
    except AttributeError:
        affinity = os.cpu_count()
    return {
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "cores_usable": affinity,
        "load_average": [round(x, 2) for x in os.getloadavg()],
        "python": platform.python_version(),
        "platform": platform.platform(),
        "gl": gl_renderer(),
        "MUJOCO_GL": os.environ.get("MUJOCO_GL", ""),
        "threads": {v: os.environ.get(v) for v in ("OMP_NUM_THREADS", "LP_NUM_THREADS")},
        "versions": {d: pkg(d) for d in ("physint", "mujoco", "robosuite", "pybullet", "numpy")},
    }


# ------------------------------------------------------------------------------------------------
# the benchmark
# ------------------------------------------------------------------------------------------------
class Bench:
    def __init__(self, seconds: float, rounds: int):
        self.seconds, self.rounds = seconds, rounds
        self.raw = RawMujoco()
        self._lift: dict[bool, RawLift | None] = {}
        self.notes: list[str] = []

    def lift(self, camera: bool) -> RawLift | None:
        """The raw robosuite reference, built once and kept for every backend's Panda rows."""
        if camera not in self._lift:
            try:
                log(f"  building robosuite Lift ({'with' if camera else 'without'} camera observations)")
                self._lift[camera] = RawLift(camera, control_hz=panda_scene().robot.control_hz)
            except Exception as exc:
                self._lift[camera] = None
                self.notes.append(f"raw robosuite Lift ({'camera' if camera else 'no camera'}) failed: "
                                  f"{type(exc).__name__}: {exc}".splitlines()[0])
        return self._lift[camera]

    def pair(self, backend_fn, raw_fn, per_call=(1.0, 1.0), seconds=None, min_calls=3):
        return interleaved(backend_fn, raw_fn, seconds or self.seconds, self.rounds, per_call, min_calls)

    # -- one backend ------------------------------------------------------------------------------
    def backend(self, name: str) -> list[Row]:
        import physint_backends as pb

        rows: list[Row] = []
        raw = self.raw
        # 1-2: the stack scene, stepping and rendering
        specs = [("physics steps/s, 6-cube stack, step(1) per call", "steps/s", "raw MuJoCo"),
                 ("physics steps/s, 6-cube stack, step(100) per call", "steps/s", "raw MuJoCo"),
                 ("renders/s, stack, RGB 64×64", "renders/s", "raw MuJoCo"),
                 ("renders/s, stack, RGB 128×128", "renders/s", "raw MuJoCo")]
        try:
            log(f"[{name}] stack scene")
            sim = pb.make(name, stack_scene(stack_offsets(None)))
            try:
                start = {n: sim.get_pose(n)[0] for n in sim.body_names}
                first = sim.render("cam64").rgb  # the stack as built: the same picture as raw MuJoCo's?
                image_diff = float(np.abs(first.astype(np.int16) - raw.first_frame).mean())
                b1, r1 = self.pair(lambda: sim.step(1), raw.step1)
                b100, r100 = self.pair(lambda: sim.step(100), raw.step100, per_call=(100, 100))
                drift = max(float(np.linalg.norm(sim.get_pose(n)[0] - start[n])) for n in sim.body_names)
                simulated = sim.time
                frame = sim.render("cam64")
                assert frame.rgb is not None and frame.rgb.shape == (64, 64, 3), "64x64 render has the wrong shape"
                render64, raw64 = self.pair(lambda: sim.render("cam64"), raw.render(64))
                render128, raw128 = self.pair(lambda: sim.render("cam128"), raw.render(128))
                # the state did not change while rendering: the image must not have either
                # (catches a renderer drawing into a broken framebuffer, which is fast and wrong)
                again = sim.render("cam64").rgb
                assert np.array_equal(again, frame.rgb), "64x64 renders of an unchanged state differ"
                assert frame.rgb.std() > 1.0, "the 64x64 render is blank"
            finally:
                sim.close()
            stable = drift < 0.01
            note = (f"stack stood through {simulated:,.0f} s simulated (max cube drift {drift * 1000:.1f} mm)"
                    if stable else f"STACK FELL during stepping: max cube displacement {drift:.3f} m after "
                                   f"{simulated:,.0f} s simulated")
            render_note = f"64×64 image of the stack as built differs from raw MuJoCo's by {image_diff:.2f}/255 per channel"
            rows += [Row(specs[0][0], name, "steps/s", b1, r1, "raw MuJoCo", note=note),
                     Row(specs[1][0], name, "steps/s", b100, r100, "raw MuJoCo", note=note)]
            ratio = render64 / raw64
            rows.append(Row(specs[2][0], name, "renders/s", render64, raw64, "raw MuJoCo",
                            goal=f"ratio ≥ {RENDER_GOAL_RATIO}", met=ratio >= RENDER_GOAL_RATIO, note=render_note))
            rows.append(Row(specs[3][0], name, "renders/s", render128, raw128, "raw MuJoCo"))
        except Exception as exc:
            rows += self.failed(name, specs, exc)

        # 3: small scenes per minute
        specs = [("small scenes/min: make + 10 steps + close", "scenes/min", "raw MuJoCo"),
                 ("small scenes/min: reset(new scene) + 10 steps", "scenes/min", "raw MuJoCo")]
        try:
            log(f"[{name}] small scenes")
            rng = np.random.default_rng(1)

            def build_cycle():
                sim = pb.make(name, stack_scene(stack_offsets(rng)))
                sim.step(BUILD_STEPS)
                sim.close()

            built, raw_built = self.pair(build_cycle, raw.build_cycle, per_call=(60, 60))
            rows.append(Row(specs[0][0], name, "/min", built, raw_built, "raw MuJoCo",
                            goal=f"≥ {SCENES_GOAL:,.0f}/min", met=built >= SCENES_GOAL))
            sim = pb.make(name, stack_scene(stack_offsets(rng)))
            try:
                def reset_cycle():
                    sim.reset(stack_scene(stack_offsets(rng)))
                    sim.step(BUILD_STEPS)

                reset, raw_built = self.pair(reset_cycle, raw.build_cycle, per_call=(60, 60))
            finally:
                sim.close()
            rows.append(Row(specs[1][0], name, "/min", reset, raw_built, "raw MuJoCo",
                            goal=f"≥ {SCENES_GOAL:,.0f}/min", met=reset >= SCENES_GOAL))
        except Exception as exc:
            rows += self.failed(name, specs, exc, goal=f"≥ {SCENES_GOAL:,.0f}/min")

        # 4: the Panda
        specs = [("control steps/s, Panda + 64×64 camera (act + render)", "steps/s", "robosuite Lift, camera obs"),
                 ("control steps/s, Panda, no camera (act)", "steps/s", "robosuite Lift, no camera")]
        goal = f"≥ {CONTROL_GOAL:.0f}/s" if name in CONTROL_GOAL_BACKENDS else "—"
        try:
            log(f"[{name}] Panda scene")
            lift_cam, lift_nocam = self.lift(True), self.lift(False)
            t0 = time.perf_counter()
            sim = pb.make(name, panda_scene())
            build_s = time.perf_counter() - t0
            try:
                circle = Circle()

                def control_with_camera():
                    sim.robot.act(circle())
                    return sim.render("front")

                frame = control_with_camera()
                assert frame.rgb is not None and frame.rgb.shape == (64, 64, 3), "64x64 render has the wrong shape"
                cam, raw_cam = self.pair(control_with_camera, lift_cam.step if lift_cam else None)
                nocam, raw_nocam = self.pair(lambda: sim.robot.act(circle()), lift_nocam.step if lift_nocam else None)
                ee = sim.robot.state().ee_pos
            finally:
                sim.close()
            note = f"Panda scene built in {build_s:.2f} s; hand at {np.round(ee, 3).tolist()} after the run"
            rows.append(Row(specs[0][0], name, "steps/s", cam, raw_cam, specs[0][2], goal=goal,
                            met=(cam >= CONTROL_GOAL) if goal != "—" else None, note=note))
            rows.append(Row(specs[1][0], name, "steps/s", nocam, raw_nocam, specs[1][2], note=note))
        except Exception as exc:
            rows += self.failed(name, specs, exc, goal=goal, first_goal_only=True)

        # what the default low-poly robot drawing saves: the Panda scene drawn with detailed meshes
        detailed = DETAILED_ROBOT[name]
        specs = [(f"renders/s, Panda scene RGB 64×64, robot_visual={detailed!r}", "renders/s",
                  "same backend, low-poly robot (default)")]
        try:
            log(f"[{name}] Panda scene with detailed robot meshes")
            sim = pb.make(name, panda_scene())
            t0 = time.perf_counter()
            sim_detailed = pb.make(name, panda_scene(), robot_visual=detailed)
            build_s = time.perf_counter() - t0
            try:
                full, low = self.pair(lambda: sim_detailed.render("front"), lambda: sim.render("front"))
            finally:
                sim_detailed.close()
                sim.close()
            rows.append(Row(specs[0][0], name, "renders/s", full, low, specs[0][2],
                            note=f"Panda scene with robot_visual={detailed!r} built in {build_s:.2f} s"))
        except Exception as exc:
            rows += self.failed(name, specs, exc)
        return rows

    def sky_cost(self) -> list[Row]:
        """Raw MuJoCo with a black background beside raw MuJoCo with the backends' flat sky."""
        if not self.raw.sky:
            return []
        log("[raw MuJoCo] the flat sky's cost")
        nosky, sky = self.pair(self.raw.render_nosky, self.raw.render(64))
        return [Row("renders/s, stack, RGB 64×64, black background (no sky)", "raw MuJoCo", "renders/s", nosky, sky,
                    "raw MuJoCo with the flat sky")]

    def failed(self, name, specs, exc, goal="—", first_goal_only=False) -> list[Row]:
        message = f"{type(exc).__name__}: {exc}".splitlines()[0]
        log(f"[{name}] FAILED: {message}")
        log("".join(traceback.format_exception(exc)))
        self.notes.append(f"{name}: {specs[0][0]} ... failed: {message}")
        rows = []
        for i, (measure, unit, raw_name) in enumerate(specs):
            g = goal if (i == 0 or not first_goal_only) else "—"
            rows.append(Row(measure, name, unit, None, None, raw_name, goal=g, met=False if g != "—" else None,
                            note=f"failed: {message}"))
        return rows

    def close(self) -> None:
        self.raw.close()
        for lift in self._lift.values():
            if lift is not None:
                lift.close()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="~0.3 s per measurement instead of ~2 s")
    parser.add_argument("--json", metavar="FILE", help="also write the machine and the rows as JSON")
    parser.add_argument("--backends", default=",".join(BACKENDS),
                        help=f"comma-separated subset of {', '.join(BACKENDS)} (default: all)")
    args = parser.parse_args(argv)
    names = [n.strip() for n in args.backends.split(",") if n.strip()]
    bad = [n for n in names if n not in BACKENDS]
    if bad or not names:
        print(f"error: unknown backend(s) {', '.join(bad) or '(none)'}; allowed: {', '.join(BACKENDS)}",
              file=sys.stderr)
        return 2
    seconds, rounds = (0.3, 1) if args.quick else (2.0, 3)

    with stdout_to_stderr():  # pybullet greets on stdout when imported; stdout carries results
        import physint_backends  # noqa: F401
        if "pybullet" in names:
            import pybullet  # noqa: F401
        try:  # the Panda rows' reference (robosuite's Lift) is measured for every backend
            import_robosuite()
        except Exception:
            pass  # reported as a note when the reference is built
    info = machine()
    t_start = time.perf_counter()
    bench = Bench(seconds, rounds)
    rows: list[Row] = []
    try:
        for name in names:
            with stdout_to_stderr():
                rows += bench.backend(name)
        with stdout_to_stderr():
            rows += bench.sky_cost()
    finally:
        with stdout_to_stderr():
            bench.close()
    info["load_average_end"] = [round(x, 2) for x in os.getloadavg()]
    info["wall_s"] = round(time.perf_counter() - t_start, 1)

    cmd = "python benchmarks/backends.py" + "".join(f" {a}" for a in (argv if argv is not None else sys.argv[1:]))
    print(f"# physint backends benchmark ({'quick' if args.quick else 'full'})")
    print(f"command: {cmd}")
    print(f"date: {info['date']}; wall time {info['wall_s']} s")
    print(f"machine: {info['cpu']}, {info['cores']} cores ({info['cores_usable']} usable); "
          f"load average {info['load_average'][0]} at start, {info['load_average_end'][0]} at end")
    print(f"one core: OMP_NUM_THREADS={info['threads']['OMP_NUM_THREADS']}, "
          f"LP_NUM_THREADS={info['threads']['LP_NUM_THREADS']} (Mesa llvmpipe; 0: in the calling thread), "
          "one process")
    print(f"OpenGL (MUJOCO_GL={info['MUJOCO_GL']}): {info['gl']}")
    print(f"python {info['python']}; " + ", ".join(f"{k} {v}" for k, v in info["versions"].items()))
    print(f"each figure: best of {rounds} round(s) of {seconds / rounds:.2f} s, alternating with its reference")
    print()
    print(table(rows))
    print()
    notes = []
    seen = set()
    for r in rows:
        if r.note and (r.backend, r.note) not in seen and not r.note.startswith("failed"):
            seen.add((r.backend, r.note))
            notes.append(f"{r.backend}: {r.note}")
    notes.append(f"raw MuJoCo stack: max cube drift {bench.raw.max_drift() * 1000:.1f} mm over "
                 f"{bench.raw.data.time:,.0f} s simulated")
    notes += bench.notes
    print("notes:")
    for n in notes:
        print(f"- {n}")

    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"machine": info, "quick": args.quick, "seconds_per_measure": seconds, "rounds": rounds,
                       "rows": [r.as_dict() for r in rows], "notes": notes}, fh, indent=2)
        log(f"wrote {args.json}")
    return 1 if any(r.figure is None for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
