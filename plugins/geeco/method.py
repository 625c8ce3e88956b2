"""The geeco method: goal-conditioned end-to-end visuomotor control behind physint's four verbs
(dataset.py, train.py, evaluate.py and deploy.py hold them)."""

from __future__ import annotations

from physint_cli.method import PackageMethod

from .config import PRESETS, GeecoConfig
from .scenes import SCENES


class Geeco(PackageMethod):
    name = "geeco"
    description = "push or pick-and-place the object a target image asks for (GEECO and its ablations)"
    chapter = "6, GEECO"
    config_class = GeecoConfig
    presets = PRESETS
    backends = ("mujoco", "pybullet", "robosuite")
    scenes = SCENES
    default_model = "geeco-f"
