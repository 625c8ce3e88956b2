"""The stability method: ShapeStacks behind physint's four verbs."""

from __future__ import annotations

from typing import Any

import numpy as np

from physint_cli.method import Context, Method, Unit

from . import dataset
from .config import PRESETS, StabilityConfig


class Stability(Method):
    name = "stability"
    description = "predict from an image whether a stack of shapes stands; localise, stack, counterbalance"
    chapter = "3, ShapeStacks"
    config_class = StabilityConfig
    presets = PRESETS
    backends = ("mujoco", "pybullet", "robosuite")
    scenes = ("ccs", "cubes", "all")
    default_model = "cnn"

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
