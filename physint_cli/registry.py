"""What plugins register: methods, backends, scenes, models, metrics.

The core knows these records and nothing about any simulator or method behind them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable


@dataclass
class Backend:
    """A simulator backend. ``make(scene)`` returns a live simulation of a backend-neutral scene."""

    name: str
    description: str
    make: Callable[..., Any]
    version: Callable[[], str] = lambda: "unknown"
    probe: Callable[[], dict] | None = None  # -> {"can_render": bool, "detail": str}
    robot: bool = True  # offers the Panda arm
    plugin: str = ""  # filled in by the plugin manager


@dataclass
class MethodPart:
    """Something a plugin provides for a method, built on demand by ``build``."""

    name: str
    method: str
    description: str = ""
    build: Callable[..., Any] | None = None
    plugin: str = ""


class SceneInfo(MethodPart):
    """A named scene (scenario family) a method can generate data from."""


class ModelInfo(MethodPart):
    """A network a method can train: ``build(**kwargs) -> torch.nn.Module``."""


@dataclass
class MetricInfo:
    """A metric: ``fn(*args) -> float`` (or a dict of floats)."""

    name: str
    description: str = ""
    fn: Callable[..., Any] | None = None
    method: str | None = None
    plugin: str = ""


@dataclass
class Registry:
    methods: dict[str, Any] = field(default_factory=dict)
    backends: dict[str, Backend] = field(default_factory=dict)
    scenes: dict[str, SceneInfo] = field(default_factory=dict)
    models: dict[str, ModelInfo] = field(default_factory=dict)
    metrics: dict[str, MetricInfo] = field(default_factory=dict)
