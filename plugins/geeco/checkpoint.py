"""Loading what the other verbs saved: a trained GEECO controller (train.py's best checkpoint) and
a dataset's optional fields and start states (dataset.py's demonstrations).

Evaluation, deployment and DAgger read these through this module, never through train.py.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from . import scenes as S

OPTIONAL_FIELDS = ["backdrop"]  # not in datasets recorded before data.backgrounds


def load_controller(run_dir, device: str = "cpu"):
    """The best checkpoint of a trained GEECO run, in eval mode, and its meta."""
    from physint_cli.training import load_trained_model

    return load_trained_model(run_dir, "geeco", "GEECO controller", device)


def with_optional(root: Path, fields: list[str]) -> list[str]:
    """``fields`` and those of ``OPTIONAL_FIELDS`` that the dataset at ``root`` holds."""
    from physint_cli.datasets import read_manifest

    return fields + [f for f in OPTIONAL_FIELDS if f in read_manifest(Path(root), "geeco")["schema"]]


def episodes_of(demos: dict[str, np.ndarray], scene: str, skill: str) -> list[S.Episode]:
    """The start states of recorded demonstrations (layout, task, seed and background video), to run
    again: training's validation episodes and DAgger's rollouts start from them."""
    backdrops = demos.get("backdrop", np.full(len(demos["layout"]), -1))
    return [S.Episode.rebuild(scene, skill, demos["layout"][i], demos["task"][i], demos["seed"][i], backdrops[i])
            for i in range(len(demos["layout"]))]
