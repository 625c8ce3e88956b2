"""The stability method: ShapeStacks behind physint's four verbs (dataset.py, train.py,
evaluate.py and deploy.py hold them)."""

from __future__ import annotations

from physint_cli.method import PackageMethod

from .config import PRESETS, StabilityConfig


class Stability(PackageMethod):
    name = "stability"
    description = "predict from an image whether a stack of shapes stands; localise, stack, counterbalance"
    chapter = "3, ShapeStacks"
    config_class = StabilityConfig
    presets = PRESETS
    backends = ("mujoco", "pybullet", "robosuite")
    default_scene = "ccs"  # the --scene choices are the scenes registered in __init__.py
    default_model = "cnn"
    deploys_without_run = True  # the Lemma-1 oracle and random placement need no predictor
