"""The hooks a physint plugin can implement.

Every hook receives a ``register`` callable (or the typer app) and calls it once per thing it
provides, as in simonw/llm. Implement them with ``@physint_cli.hookimpl`` in a module named by an
entry point in the ``physint`` group::

    [project.entry-points.physint]
    freefall = "physint_freefall"
"""

from __future__ import annotations

import pluggy

hookspec = pluggy.HookspecMarker("physint")
hookimpl = pluggy.HookimplMarker("physint")


@hookspec
def register_methods(register):
    """Register methods: ``register(method)`` with a :class:`physint_cli.registry.Method`."""


@hookspec
def register_backends(register):
    """Register simulator backends: ``register(backend)`` with a :class:`physint_cli.registry.Backend`."""


@hookspec
def register_scenes(register):
    """Register scenes: ``register(scene)`` with a :class:`physint_cli.registry.SceneInfo`."""


@hookspec
def register_models(register):
    """Register models: ``register(model)`` with a :class:`physint_cli.registry.ModelInfo`."""


@hookspec
def register_metrics(register):
    """Register metrics: ``register(metric)`` with a :class:`physint_cli.registry.MetricInfo`."""


@hookspec
def register_commands(app):
    """Add commands to the ``physint`` typer app: ``@app.command()``."""
