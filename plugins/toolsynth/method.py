"""The toolsynth method: task-driven tool imagination behind physint's four verbs (dataset.py,
train.py, evaluate.py and deploy.py hold them)."""

from __future__ import annotations

from physint_cli.method import PackageMethod

from .config import PRESETS, ToolsynthConfig


class Toolsynth(PackageMethod):
    name = "toolsynth"
    description = "imagine a stick or hook that reaches a target, by gradient descent in a tool latent space"
    chapter = "4, tool imagination"
    config_class = ToolsynthConfig
    presets = PRESETS
    backends = ("mujoco", "pybullet", "robosuite")
    default_scene = "reaching"
    default_model = "toolsynth"
