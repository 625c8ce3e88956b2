"""physint_backends: MuJoCo, PyBullet and robosuite behind one interface.

``make(name, scene)`` builds a live :class:`~physint_backends.base.Simulation`. The built-in
backends register through the ``physint`` entry point like any third-party plugin; each
imports its simulator only when first used, so a missing simulator never breaks the others.
"""

from __future__ import annotations

import importlib
import os
import sys
from importlib.metadata import PackageNotFoundError, version

from physint_cli import hookimpl
from physint_cli.registry import Backend

from .base import Frame, Robot, RobotState, Simulation, SimulationError  # noqa: F401
from .spec import Body, Camera, Geom, Ground, Light, Scene, SpecError, Texture  # noqa: F401
from .spec import Robot as RobotSpec  # noqa: F401

# name -> (module, class, distribution, description, has robot)
BUILTIN = {
    "mujoco": ("physint_backends.mujoco_backend", "MujocoSimulation", "mujoco",
               "MuJoCo, rendered headless through EGL; Panda from robosuite's packaged model", True),
    "pybullet": ("physint_backends.pybullet_backend", "PybulletSimulation", "pybullet",
                 "PyBullet in DIRECT mode with its TinyRenderer; Panda from pybullet_data", True),
    "robosuite": ("physint_backends.robosuite_backend", "RobosuiteSimulation", "robosuite",
                  "robosuite (MuJoCo) with its Panda and operational-space position controller", True),
}


def ensure_headless_gl() -> None:
    """Render MuJoCo offscreen through EGL unless the user chose otherwise or has a display."""
    if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY"):
        os.environ["MUJOCO_GL"] = "egl"
    if os.environ.get("MUJOCO_GL") == "egl":
        os.environ.setdefault("PYOPENGL_PLATFORM", "egl")


ensure_headless_gl()  # before anything imports mujoco: it picks its GL platform at import


def simulation_class(name: str):
    if name not in BUILTIN:
        from physint_cli.errors import unknown

        raise unknown("backend", name, BUILTIN)
    module, cls, *_ = BUILTIN[name]
    ensure_headless_gl()
    return getattr(importlib.import_module(module), cls)


def make(name: str, scene: Scene, **options) -> Simulation:
    """Build a live simulation of ``scene`` on the named built-in backend."""
    return simulation_class(name)(scene, **options)


def _version(dist: str):
    def get() -> str:
        try:
            return version(dist)
        except PackageNotFoundError:
            return "not installed"

    return get


def _probe(name: str):
    def probe() -> dict:
        """Build a one-box scene and render one frame: can this machine render on this backend?"""
        try:
            scene = Scene(bodies=[Body.box("box", (0.1, 0.1, 0.1), pos=(0, 0, 0.05))],
                          cameras=[Camera("cam", pos=(0.6, 0.0, 0.4), width=32, height=32)])
            with make(name, scene) as sim:
                frame = sim.render("cam")
            ok = frame.rgb is not None and frame.rgb.shape == (32, 32, 3)
            return {"can_render": bool(ok), "detail": "ok" if ok else "render returned no image"}
        except Exception as exc:  # report, never raise: this is a diagnostic
            return {"can_render": False, "detail": f"{type(exc).__name__}: {exc}".splitlines()[0]}

    return probe


def _make_factory(name: str):
    def factory(scene: Scene, **options) -> Simulation:
        return make(name, scene, **options)

    return factory


@hookimpl
def register_backends(register):
    for name, (_, _, dist, description, robot) in BUILTIN.items():
        register(Backend(name=name, description=description, make=_make_factory(name),
                         version=_version(dist), probe=_probe(name), robot=robot))


__all__ = ["make", "simulation_class", "Scene", "Body", "Geom", "Camera", "Light", "Ground", "Texture",
           "RobotSpec", "Simulation", "SimulationError", "Frame", "Robot", "RobotState", "SpecError", "BUILTIN"]

