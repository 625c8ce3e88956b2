"""The Method interface a plugin implements, and the Context each verb receives.

A method is the software form of one thesis chapter. It declares its config and presets, the
backends and scenes it supports, and implements four verbs. Dataset generation and batch
evaluation are split into *work units* so the core can run them in local processes or on Ray;
the method only says how to make the units and how to do one.
"""

from __future__ import annotations

import dataclasses
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from .errors import BadInput


@dataclass
class Unit:
    """One independent piece of work (a dataset shard, a batch of evaluation episodes)."""

    split: str
    index: int
    count: int
    seed: int
    params: dict[str, Any] = field(default_factory=dict)

    @property
    def name(self) -> str:
        return f"{self.split}-{self.index:05d}"


def unit_seed(seed: int, *keys: int | str) -> int:
    """A seed for one unit that depends only on the base seed and the unit's identity."""
    words = [seed] + [k if isinstance(k, int) else int.from_bytes(k.encode()[:8].ljust(8, b"\0"), "little") for k in keys]
    return int(np.random.SeedSequence(words).generate_state(1)[0])


def split_units(counts: dict[str, int], per_unit: int, seed: int, **params: Any) -> list[Unit]:
    """Cut ``{split: n_items}`` into units of at most ``per_unit`` items with deterministic seeds."""
    units = []
    for split, total in counts.items():
        for index, start in enumerate(range(0, total, max(1, per_unit))):
            n = min(per_unit, total - start)
            units.append(Unit(split, index, n, unit_seed(seed, split, index), {"start": start, **params}))
    return units


@dataclass
class Context:
    """What a verb is run with. Picklable, so work units can run in other processes."""

    method: str
    config: Any
    preset: str
    backend: str
    scene: str
    seed: int = 0
    device: str = "cpu"
    workers: int = 1
    ray: str | None = None
    data: Path | None = None  # dataset directory (train, eval)
    run: Path | None = None  # this verb's run directory
    source_run: Path | None = None  # the trained run (eval, deploy)
    # the verb options of the command line (None where not given)
    model: str | None = None  # --model: a network registered for this method (train)
    task: str | None = None  # --task: the deployment task (deploy)
    target: str | None = None  # --target: what to deploy towards, in the method's own words (deploy)
    episodes: int | None = None  # --episodes: also set as eval.episodes / deploy.episodes where the config has it
    resume: bool = False  # --resume: continue ``run`` from its last checkpoint (train)
    quiet: bool = False

    def verb_options(self) -> dict[str, Any]:
        """The verb options that were given, as run.json records them."""
        names = ("model", "task", "target", "episodes", "resume")
        return {k: getattr(self, k) for k in names if getattr(self, k) not in (None, False)}

    def output(self):
        """This verb's run directory as a :class:`~physint_cli.runs.Run` (where train saves its model)."""
        from .runs import Run

        if self.run is None:
            raise RuntimeError("this context has no run directory")
        return Run(self.run)

    def trained(self):
        """The trained run that eval and deploy use, as a :class:`~physint_cli.runs.Run`."""
        from .runs import Run

        if self.source_run is None:
            raise BadInput(f"no trained {self.method} run; train one with `physint train {self.method}` or pass --run DIR")
        return Run(self.source_run)

    def log(self, message: str) -> None:
        if not self.quiet:
            print(message, file=sys.stderr, flush=True)

    def make_sim(self, scene: Any, backend: str | None = None):
        """A live simulation of a backend-neutral scene on this context's (or another) backend."""
        from .plugins import get_plugins

        return get_plugins().backend(backend or self.backend).make(scene)

    def map(self, fn, units: list[Unit], description: str = "working") -> list[Any]:
        """Run ``fn(context, unit)`` over units with --workers/--ray; results in unit order."""
        from .parallel import map_units

        return map_units(fn, self, units, description=description)

    def with_(self, **changes: Any) -> Context:
        return dataclasses.replace(self, **changes)


class Method:
    """Base class for a method plugin. Subclass it and register an instance in ``register_methods``."""

    name: ClassVar[str] = ""
    description: ClassVar[str] = ""
    chapter: ClassVar[str] = ""  # e.g. "Chapter 3, ShapeStacks"
    config_class: ClassVar[type] = object
    presets: ClassVar[dict[str, dict[str, Any]]] = {"tiny": {}, "small": {}, "paper": {}}
    backends: ClassVar[tuple[str, ...]] = ("mujoco",)
    # ``--scene`` choices: the scenes registered for this method (``register_scenes``), with
    # ``default_scene`` first; only a method that registers none uses this tuple as it is
    scenes: tuple[str, ...] = ("default",)
    default_scene: ClassVar[str | None] = None
    default_model: ClassVar[str | None] = None
    # True when ``deploy`` has agents that need no trained model (e.g. a physics oracle): with no
    # --run and no train run to fall back on, deploy then runs with ``ctx.source_run = None``
    deploys_without_run: ClassVar[bool] = False
    plugin: str = ""

    # -- dataset ------------------------------------------------------------------------------
    def dataset_units(self, ctx: Context) -> list[Unit]:
        """The shards to generate: one Unit each (use :func:`split_units`)."""
        raise NotImplementedError

    def generate(self, ctx: Context, unit: Unit) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Make one shard: ``({field: array with leading dim = n records}, stats)``."""
        raise NotImplementedError

    def summarize_dataset(self, ctx: Context, stats: list[dict[str, Any]]) -> dict[str, Any]:
        """Combine per-shard stats into the manifest's ``stats`` (e.g. an agreement rate)."""
        out: dict[str, Any] = {}
        for s in stats:
            for k, v in s.items():
                if isinstance(v, (int, float)):
                    out[k] = out.get(k, 0) + v
        return out

    # -- train / eval / deploy --------------------------------------------------------------------
    def train(self, ctx: Context) -> dict[str, Any]:
        """Train into ``ctx.run`` from ``ctx.data``; return final metrics."""
        raise NotImplementedError

    def evaluate(self, ctx: Context) -> dict[str, Any]:
        """Evaluate the trained run ``ctx.source_run``; return metrics."""
        raise NotImplementedError

    def deploy(self, ctx: Context) -> dict[str, Any]:
        """Use the trained run ``ctx.source_run`` for its downstream task; return the outcome."""
        raise NotImplementedError

    # -- helpers ------------------------------------------------------------------------------
    def check_backend(self, backend: str) -> None:
        if backend not in self.backends:
            raise BadInput(f"method {self.name!r} does not support backend {backend!r}; supported: {', '.join(self.backends)}")

    def check_scene(self, scene: str) -> None:
        if scene not in self.scenes:
            from .errors import unknown

            raise BadInput(f"method {self.name!r}: {unknown('scene', scene, self.scenes)}")


class PackageMethod(Method):
    """A method whose verbs live in modules of its own package, one module per chapter section:

    ``dataset.plan_units(ctx)``, ``dataset.generate(ctx, unit)``, ``dataset.summarize(stats)``,
    ``train.train(ctx)``, ``evaluate.evaluate(ctx)`` and ``deploy.deploy(ctx)``. Modules are
    imported when a verb first needs them (so listing plugins stays fast).
    """

    def _module(self, name: str):
        import importlib

        return importlib.import_module(f"{type(self).__module__.rsplit('.', 1)[0]}.{name}")

    def dataset_units(self, ctx: Context) -> list[Unit]:
        return self._module("dataset").plan_units(ctx)

    def generate(self, ctx: Context, unit: Unit) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        return self._module("dataset").generate(ctx, unit)

    def summarize_dataset(self, ctx: Context, stats: list[dict[str, Any]]) -> dict[str, Any]:
        return self._module("dataset").summarize(stats)

    def train(self, ctx: Context) -> dict[str, Any]:
        return self._module("train").train(ctx)

    def evaluate(self, ctx: Context) -> dict[str, Any]:
        return self._module("evaluate").evaluate(ctx)

    def deploy(self, ctx: Context) -> dict[str, Any]:
        return self._module("deploy").deploy(ctx)
