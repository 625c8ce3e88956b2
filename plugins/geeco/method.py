"""The geeco method: goal-conditioned end-to-end visuomotor control behind physint's four verbs."""

from __future__ import annotations

from typing import Any

import numpy as np

from physint_cli.method import Context, Method, Unit

from . import dataset
from .config import PRESETS, GeecoConfig
from .scenes import SCENES


class Geeco(Method):
    name = "geeco"
    description = "push or pick-and-place the object a target image asks for (GEECO and its ablations)"
    chapter = "6, GEECO"
    config_class = GeecoConfig
    presets = PRESETS
    backends = ("mujoco", "pybullet", "robosuite")
    scenes = SCENES
    default_model = "geeco-f"

    def dataset_units(self, ctx: Context) -> list[Unit]:
        return dataset.plan_units(ctx)

    def generate(self, ctx: Context, unit: Unit) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        return dataset.generate(ctx, unit)

    def summarize_dataset(self, ctx: Context, stats: list[dict[str, Any]]) -> dict[str, Any]:
        return dataset.summarize(stats)

    def train(self, ctx: Context) -> dict[str, Any]:
        from .train import train

        return train(ctx)

    def evaluate(self, ctx: Context) -> dict[str, Any]:
        from .evaluate import evaluate

        return evaluate(ctx)

    def deploy(self, ctx: Context) -> dict[str, Any]:
        from .deploy import deploy

        return deploy(ctx)
