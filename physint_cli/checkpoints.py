"""Saving and reading checkpoint files: atomic writes, and a clear error for a damaged file."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from .errors import BadInput


def save_checkpoint(path: Path, **state: Any) -> None:
    """Atomically save model/optimizer/progress state (temp file + rename)."""
    import torch

    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        torch.save(state, tmp)
        os.replace(tmp, path)
    except BaseException:  # an interrupt or a full disk leaves the previous checkpoint and no temp file
        tmp.unlink(missing_ok=True)
        raise


def load_checkpoint(path: Path, map_location: str = "cpu") -> dict[str, Any]:
    import torch

    try:
        return torch.load(path, map_location=map_location, weights_only=False)
    except Exception as exc:
        raise BadInput(f"checkpoint {path} cannot be read ({type(exc).__name__}); it may be corrupted") from None
