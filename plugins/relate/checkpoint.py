"""What train, evaluate and deploy share: the dataset's header, its frames as the model sees them, a
trained model, and image grids."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch.nn import functional as F

from physint_cli.errors import BadInput


def dataset_header(root) -> dict[str, Any]:
    from physint_cli.datasets import read_manifest

    if root is None:
        raise BadInput("relate needs a dataset: pass --data DIR (from `physint dataset relate`)")
    return read_manifest(root, "relate")


def real_frames(arrays: dict[str, np.ndarray], size: int) -> torch.Tensor:
    """Every frame of a split as uint8 (N, 3, size, size), resized by area averaging."""
    frames = arrays["frames"].reshape(-1, *arrays["frames"].shape[-3:])
    out = []
    for start in range(0, len(frames), 1024):
        x = torch.from_numpy(frames[start:start + 1024]).permute(0, 3, 1, 2).float()
        if x.shape[-1] != size:
            x = F.interpolate(x, size=(size, size), mode="area")
        out.append(x.round().clamp(0, 255).to(torch.uint8))
    return torch.cat(out)


def to_unit(images: torch.Tensor) -> torch.Tensor:
    """uint8 images to [-1, 1], the generator's tanh range."""
    return images.float() / 127.5 - 1.0


def sample_grid(model: Relate, n: int = 16, seed: int = 0) -> np.ndarray:
    """An image grid (uint8 HxWx3) of ``n`` generated scenes with all objects present."""
    g = model.generator
    latents = g.sample(n, generator=torch.Generator().manual_seed(seed))
    with torch.no_grad():
        if g.video:  # a clip per row: the first n // 8 scenes over 8 frames, every other frame
            clips, _ = g({k: v[:max(1, n // 8)] for k, v in latents.items()}, frames=16)
            return image_grid(clips[:, ::2].flatten(0, 1))
        images, _ = g(latents)
    return image_grid(images)


def to_uint8(images: torch.Tensor) -> np.ndarray:
    """Generated images (N, 3, H, W) in [-1, 1] as uint8 (N, H, W, 3)."""
    return ((images.clamp(-1, 1) + 1) * 127.5).round().to(torch.uint8).permute(0, 2, 3, 1).cpu().numpy()


def image_grid(images: torch.Tensor, columns: int = 8) -> np.ndarray:
    pics = to_uint8(images)
    rows = -(-len(pics) // columns)
    pad = np.zeros((rows * columns - len(pics), *pics.shape[1:]), np.uint8)
    pics = np.concatenate([pics, pad])
    h, w = pics.shape[1:3]
    return pics.reshape(rows, columns, h, w, 3).transpose(0, 2, 1, 3, 4).reshape(rows * h, columns * w, 3)


def load_model(run_dir, device: str = "cpu"):
    """The trained RELATE model of a run (eval mode) and its meta; another method's checkpoint exits 2."""
    from physint_cli.training import load_trained_model

    return load_trained_model(run_dir, "relate", "RELATE model", device)
