"""Loading what the other verbs saved: the two trained ToolSynth models of one training run
(train.py's ``best.pt`` holds the task-driven model as ``model`` and the task-unaware one as
``unaware``, Section 4.4.2), the cameras their mesh decoder was trained through, and a dataset's
records in memory.

Evaluation and deployment read these through this module, never through train.py.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from . import scenes as S
from . import softras

FIELDS = ["task", "tool_rgb", "tool_sil", "views", "label", "type", "target", "obstacles", "n_obstacles", "tool",
          "rgba"]
MODEL = "toolsynth"


def data_config(root: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """A toolsynth dataset's manifest and its ``data`` config section."""
    from physint_cli.datasets import read_manifest

    manifest = read_manifest(Path(root), "toolsynth")
    return manifest, manifest["config"].get("data", manifest["config"])


def load_split(root: Path, split: str, fields: list[str] = FIELDS) -> dict[str, np.ndarray]:
    """A whole split in memory (the small preset's training split: ~180 MB at 64 px)."""
    from physint_cli.datasets import ShardedDataset

    return ShardedDataset(root, split, fields, method="toolsynth", in_memory=True).arrays


def view_cameras(views: int, size: int, elevation: float = S.ELEVATION) -> softras.CameraTensors:
    """The dataset's ring of tool cameras round the origin, where the decoder places its meshes."""
    return softras.camera_tensors(S.tool_cameras(views, size, elevation=elevation))


def load_models(run_dir, device: str = "cpu"):
    """The task-driven and the task-unaware model of a toolsynth training run, in eval mode, and
    the run's meta; another method's checkpoint exits 2."""
    from physint_cli.errors import BadInput
    from physint_cli.runs import Run
    from physint_cli.training import load_trained_model, registered_model

    driven, meta = load_trained_model(run_dir, "toolsynth", "ToolSynth model", device)
    state = Run(Path(run_dir)).load_trained(device)
    if "unaware" not in state:
        raise BadInput(f"checkpoint {Run(Path(run_dir)).trained_file} holds no task-unaware model; the training "
                       f"stopped before stage 2 ended: rerun `physint train toolsynth --resume`")
    unaware = registered_model("toolsynth", meta["model"]).build(**meta["kwargs"])
    unaware.load_state_dict(state["unaware"])
    return driven, unaware.to(device).eval(), meta


def training_box(meta: dict[str, Any], which: str, model, root: Path | None = None):
    """The box round the training records' tool latents of the run's ``which`` model ("driven" or
    "unaware"), as (low, high) tensors: saved by training in ``meta["latent_box"]``; a run trained
    before that gets it by encoding the training split of ``root`` (its dataset) now."""
    import torch

    from .imagine import encode_views, latent_box

    saved = meta.get("latent_box", {}).get(which)
    device = next(model.parameters()).device
    if saved is not None:
        return tuple(torch.tensor(b, dtype=torch.float32, device=device) for b in saved)
    tools = load_split(Path(root or meta["dataset"]), "train", ["tool_rgb", "tool_sil"])
    return tuple(b.to(device) for b in latent_box(torch.as_tensor(encode_views(model, tools)).flatten(0, 1)))
