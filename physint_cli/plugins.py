"""Discovering plugins through the ``physint`` entry-point group, with pluggy.

A plugin that fails to import, or whose hook raises, is recorded as broken with its error and
skipped; it never breaks other plugins or commands. A name that a second plugin registers again
(a method, a backend, or a scene, model or metric of the same method) is refused, the first
registration stays, and the clash is listed in ``conflicts`` (``physint plugins`` shows them).
"""

from __future__ import annotations

import os
import traceback
from dataclasses import dataclass, field
from importlib.metadata import entry_points
from typing import Any

import pluggy

from . import hookspecs
from .errors import BadInput, unknown
from .registry import Backend, MetricInfo, ModelInfo, Registry, SceneInfo, key_of

GROUP = "physint"
REGISTER_HOOKS = {
    "register_methods": "methods",
    "register_backends": "backends",
    "register_scenes": "scenes",
    "register_models": "models",
    "register_metrics": "metrics",
}


@dataclass
class PluginInfo:
    name: str
    module: str
    distribution: str = ""
    version: str = ""
    provides: dict[str, list[str]] = field(default_factory=dict)
    error: str | None = None

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.name, "module": self.module, "distribution": self.distribution,
                "version": self.version, "provides": self.provides, "error": self.error}


class Plugins:
    """The loaded plugins and everything they registered."""

    def __init__(self, load_entry_points: bool = True):
        self.pm = pluggy.PluginManager(GROUP)
        self.pm.add_hookspecs(hookspecs)
        self.info: dict[str, PluginInfo] = {}
        self.registry = Registry()
        self.broken: list[PluginInfo] = []
        self.conflicts: list[str] = []
        if load_entry_points:
            self._load_entry_points()
        self._collect()

    # -- discovery ---------------------------------------------------------------------------
    def _load_entry_points(self) -> None:
        blocked = {n.strip() for n in os.environ.get("PHYSINT_DISABLE_PLUGINS", "").split(",") if n.strip()}
        seen: set[str] = set()
        for ep in entry_points(group=GROUP):
            if ep.name in seen or ep.name in blocked:
                continue
            seen.add(ep.name)
            dist = getattr(ep, "dist", None)
            info = PluginInfo(name=ep.name, module=ep.value,
                              distribution=dist.metadata["Name"] if dist else "",
                              version=dist.version if dist else "")
            try:
                module = ep.load()
                self.pm.register(module, name=ep.name)
            except Exception as exc:  # a broken plugin is reported, never fatal
                info.error = _one_line(exc)
                self.broken.append(info)
            self.info[ep.name] = info

    def add(self, module: Any, name: str, distribution: str = "", version: str = "") -> None:
        """Register a plugin object directly (tests, notebooks)."""
        self.pm.register(module, name=name)
        self.info[name] = PluginInfo(name=name, module=getattr(module, "__name__", repr(module)),
                                     distribution=distribution, version=version)
        self.registry = Registry()
        self.conflicts = []
        self._collect()

    def _collect(self) -> None:
        for hook_name, kind in REGISTER_HOOKS.items():
            hook = getattr(self.pm.hook, hook_name)
            for impl in hook.get_hookimpls():
                plugin = impl.plugin_name
                info = self.info.setdefault(plugin, PluginInfo(name=plugin, module=str(impl.plugin)))
                if info.error:
                    continue

                def register(item, _kind=kind, _plugin=plugin):
                    target, key = getattr(self.registry, _kind), key_of(_kind, item)
                    if key in target:  # refused: the first registration stays
                        owner = f" of method {key[0]!r}" if isinstance(key, tuple) and key[0] else ""
                        self.conflicts.append(f"{_kind[:-1]} {item.name!r}{owner} registered by plugin {_plugin!r} is "
                                              f"refused: plugin {target[key].plugin!r} registered it first")
                        return
                    item.plugin = _plugin
                    target[key] = item
                    self.info[_plugin].provides.setdefault(_kind, []).append(item.name)

                try:
                    impl.function(register=register)
                except Exception as exc:
                    info.error = f"{hook_name} failed: {_one_line(exc)}"
                    self.broken.append(info)
        self._bind_scenes()

    def _bind_scenes(self) -> None:
        """Each method's ``--scene`` choices are the scenes registered for it (its ``default_scene``
        first, else the first registered); a method that registers none keeps its own ``scenes``."""
        for method in self.registry.methods.values():
            names = [name for (owner, name) in self.registry.scenes if owner == method.name]
            if not names:
                continue
            first = getattr(method, "default_scene", None)
            if first in names:
                names.remove(first)
                names.insert(0, first)
            method.scenes = tuple(names)

    # -- lookups with helpful errors -----------------------------------------------------------
    def method(self, name: str):
        if name not in self.registry.methods:
            broken = [b for b in self.broken if name in b.name]
            hint = f"; plugin {broken[0].name!r} is broken: {broken[0].error}" if broken else ""
            raise BadInput(str(unknown("method", name, self.registry.methods)) + hint)
        return self.registry.methods[name]

    def backend(self, name: str) -> Backend:
        if name not in self.registry.backends:
            raise unknown("backend", name, self.registry.backends)
        return self.registry.backends[name]

    def models_for(self, method: str) -> dict[str, ModelInfo]:
        return {name: m for (owner, name), m in self.registry.models.items() if owner == method}

    def scenes_for(self, method: str) -> dict[str, SceneInfo]:
        return {name: s for (owner, name), s in self.registry.scenes.items() if owner == method}

    def metrics_for(self, method: str) -> dict[str, MetricInfo]:
        """The metrics of ``method`` and the method-independent ones."""
        return {name: m for (owner, name), m in self.registry.metrics.items() if owner in (None, method)}

    def scene(self, method: str, name: str) -> SceneInfo:
        """Another plugin's scene, by its method and name (how plugins share scenario generators)."""
        scenes = self.scenes_for(method)
        if name not in scenes:
            raise unknown(f"scene of method {method!r}:", name, scenes)
        return scenes[name]

    def model(self, method: str, name: str) -> ModelInfo:
        models = self.models_for(method)
        if name not in models:
            raise unknown(f"model for method {method!r}:", name, models)
        return models[name]

    def metric(self, name: str, method: str | None = None) -> MetricInfo:
        """A registered metric: ``method``'s own, or a method-independent one."""
        metrics = self.metrics_for(method) if method else \
            {n: m for (owner, n), m in self.registry.metrics.items() if owner is None}
        if name not in metrics:
            raise unknown("metric" + (f" of method {method!r}" if method else ""), name, metrics)
        return metrics[name]

    def register_commands(self, app) -> None:
        for impl in self.pm.hook.register_commands.get_hookimpls():
            try:
                impl.function(app=app)
            except Exception as exc:
                info = self.info.setdefault(impl.plugin_name, PluginInfo(impl.plugin_name, str(impl.plugin)))
                info.error = f"register_commands failed: {_one_line(exc)}"
                self.broken.append(info)


def _one_line(exc: BaseException) -> str:
    text = f"{type(exc).__name__}: {exc}".strip().splitlines()
    where = traceback.extract_tb(exc.__traceback__)
    loc = f" ({where[-1].filename}:{where[-1].lineno})" if where else ""
    return (text[0] if text else type(exc).__name__) + loc


_PLUGINS: Plugins | None = None


def get_plugins() -> Plugins:
    """The process-wide plugin set, loaded once."""
    global _PLUGINS
    if _PLUGINS is None:
        _PLUGINS = Plugins()
    return _PLUGINS


def reset_plugins() -> None:
    global _PLUGINS
    _PLUGINS = None
