"""What plugins register: methods, backends, scenes, models, metrics.

The core knows these records and nothing about any simulator or method behind them. Methods and
backends are known by name; scenes, models and metrics by (method, name), so two methods may
each have a scene called ``default``. A second registration of a key that is taken is refused
(the first stays) and reported by ``physint plugins``.
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
    """A named scene (scenario family) a method can generate data from. Its ``--scene`` name is
    ``name``; ``build(seed, **settings)``, where given, returns a backend-neutral
    ``physint_backends.Scene`` (and whatever the method documents beside it), so another plugin
    can reuse the scenario generator through the registry without importing the plugin."""


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


def key_of(kind: str, item: Any) -> str | tuple[str | None, str]:
    """The registry key of an item: its name (methods, backends) or (method, name)."""
    return item.name if kind in ("methods", "backends") else (getattr(item, "method", None), item.name)


@dataclass
class Registry:
    methods: dict[str, Any] = field(default_factory=dict)
    backends: dict[str, Backend] = field(default_factory=dict)
    scenes: dict[tuple[str | None, str], SceneInfo] = field(default_factory=dict)
    models: dict[tuple[str | None, str], ModelInfo] = field(default_factory=dict)
    metrics: dict[tuple[str | None, str], MetricInfo] = field(default_factory=dict)
