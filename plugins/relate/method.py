"""The relate method: RELATE's physically plausible scene synthesis behind physint's four verbs
(dataset.py, train.py, evaluate.py and deploy.py hold them)."""

from __future__ import annotations

from physint_cli.method import PackageMethod

from .config import PRESETS, RelateConfig


class Relate(PackageMethod):
    name = "relate"
    description = "generate scenes whose objects are placed by a relationship module (RELATE, a structured GAN)"
    chapter = "5, RELATE"
    config_class = RelateConfig
    presets = PRESETS
    backends = ("mujoco", "pybullet", "robosuite")
    default_scene = "balls-in-bowl"
    default_model = "relate"
