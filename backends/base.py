"""The interface every simulator backend implements.

A backend turns a :class:`~physint_backends.spec.Scene` into a live :class:`Simulation`.
Methods only ever talk to this interface, so the same scenario code runs on MuJoCo, PyBullet
and robosuite. Bodies and cameras are addressed by the names given in the spec.

Conventions shared by all backends:

* poses are ``(pos (3,), quat (4,) as w, x, y, z)`` in the world frame;
* velocities are ``(linear (3,), angular (3,))`` in the world frame;
* :meth:`Simulation.render` returns a :class:`Frame` whose ``segmentation`` holds, per pixel,
  the index of the body in ``scene.bodies`` it shows, ``-1`` for the ground / background /
  static environment that is not a scene body, and ``-2`` for the robot (arm, gripper, table);
* depth is metric distance along the camera axis, in metres (float32);
* any bad argument (unknown name, NaN pose, wrong action shape) raises ``SpecError`` *before*
  the simulator state is touched.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np

from .spec import Camera, Scene, SpecError, _finite_vector, _unit_quat, unknown_name

class SimulationError(RuntimeError):
    """The simulator failed on this world (not the user's input); rebuild it to go on."""


SEG_BACKGROUND = -1
SEG_ROBOT = -2


@dataclass
class Frame:
    """One camera image. Arrays are HxW(x3); missing modalities are ``None``."""

    rgb: np.ndarray | None = None  # uint8 HxWx3
    depth: np.ndarray | None = None  # float32 HxW, metres
    segmentation: np.ndarray | None = None  # int32 HxW, body index / -1 / -2


@dataclass
class RobotState:
    """What the robot senses after a control step."""

    joints: np.ndarray  # (7,) arm joint angles, radians
    ee_pos: np.ndarray  # (3,) end-effector (between the fingertips) position, world frame
    gripper_opening: float  # distance between the fingers, metres
    contacts: dict[str, list[str]] = field(default_factory=dict)  # robot part -> touched body names


class Robot(ABC):
    """A Panda arm driven by end-effector displacements (see ``spec.Robot``)."""

    spec: object

    @abstractmethod
    def act(self, action) -> RobotState:
        """Apply ``(dx, dy, dz, gripper)`` for one control step (``1 / control_hz`` s)."""

    @abstractmethod
    def state(self) -> RobotState:
        """The current state, without stepping."""

    @abstractmethod
    def touching(self, body: str, part: str = "any") -> bool:
        """Whether ``part`` (fingers, palm or any) of the robot touches the named body."""

    @property
    def control_dt(self) -> float:
        return 1.0 / self.spec.control_hz  # type: ignore[attr-defined]


class Simulation(ABC):
    """A live world built from a Scene."""

    backend: str = "?"

    def __init__(self, scene: Scene):
        self.scene = scene
        self.body_names = [b.name for b in scene.bodies]
        self.camera_names = [c.name for c in scene.cameras]
        self.robot: Robot | None = None

    # -- time ----------------------------------------------------------------------------------
    @property
    @abstractmethod
    def time(self) -> float:
        """Simulated seconds since the last reset."""

    @abstractmethod
    def step(self, n: int = 1) -> None:
        """Advance ``n`` physics steps of ``scene.timestep`` seconds."""

    def advance(self, seconds: float) -> None:
        """Advance by (about) ``seconds`` of simulated time."""
        self.step(max(1, int(round(seconds / self.scene.timestep))))

    # -- state of named bodies -----------------------------------------------------------------
    @abstractmethod
    def get_pose(self, name: str) -> tuple[np.ndarray, np.ndarray]: ...

    @abstractmethod
    def set_pose(self, name: str, pos, quat=None) -> None: ...

    @abstractmethod
    def get_velocity(self, name: str) -> tuple[np.ndarray, np.ndarray]: ...

    @abstractmethod
    def set_velocity(self, name: str, linear, angular=(0.0, 0.0, 0.0)) -> None: ...

    @abstractmethod
    def freeze(self, name: str) -> None:
        """Hold the body in place (it still collides) until :meth:`unfreeze`."""

    @abstractmethod
    def unfreeze(self, name: str) -> None: ...

    @abstractmethod
    def contacts(self, name: str) -> list[str]:
        """Names of bodies touching ``name`` now: scene body names, "ground" for the ground plane,
        "table" for the robot's table, "robot" for the arm, gripper and pedestal."""

    def in_contact(self, a: str, b: str) -> bool:
        return b in self.contacts(a)

    def poses(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        return {n: self.get_pose(n) for n in self.body_names}

    # -- rendering -----------------------------------------------------------------------------
    @abstractmethod
    def render(self, camera: str, rgb: bool = True, depth: bool = False, segmentation: bool = False) -> Frame: ...

    @abstractmethod
    def set_camera(self, name: str, pos=None, lookat=None, fovy=None) -> None:
        """Move a camera (for domain randomisation or cameras following a stack)."""

    @abstractmethod
    def set_rgba(self, name: str, rgba) -> None:
        """Recolour every geom of a body."""

    # -- lifecycle -----------------------------------------------------------------------------
    @abstractmethod
    def reset(self, scene: Scene | None = None) -> None:
        """Rebuild the world from ``scene`` (default: the current one); time restarts at 0."""

    @abstractmethod
    def close(self) -> None: ...

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # -- helpers for implementations: validate before touching simulator state ------------------
    def _check_body(self, name: str) -> int:
        try:
            return self.body_names.index(name)
        except ValueError:
            raise unknown_name("body", name, self.body_names) from None

    def _check_camera(self, name: str) -> Camera:
        return self.scene.camera(name)

    @staticmethod
    def _check_pose(name: str, pos, quat) -> tuple[np.ndarray, np.ndarray | None]:
        p = np.asarray(_finite_vector(pos, 3, f"pose of {name!r}: pos"))
        q = None if quat is None else np.asarray(_unit_quat(quat, f"pose of {name!r}: quat"))
        return p, q

    @staticmethod
    def _check_velocity(name: str, linear, angular) -> tuple[np.ndarray, np.ndarray]:
        return (
            np.asarray(_finite_vector(linear, 3, f"velocity of {name!r}: linear")),
            np.asarray(_finite_vector(angular, 3, f"velocity of {name!r}: angular")),
        )


def check_part(part: str) -> str:
    from .spec import ROBOT_PARTS

    if part not in ROBOT_PARTS:
        raise SpecError(f"robot part {part!r} is not known; allowed: {', '.join(ROBOT_PARTS)}")
    return part
