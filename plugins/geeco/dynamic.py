"""Dynamic images (thesis Section 6.3, Eqs. 6.1 and 6.2; Bilen et al. 2016).

An approximate rank pooling of frames I_1..I_H into one image:

    rho(I_1..I_H) = sum_t alpha_t I_t                                          (6.1)
    alpha_t = 2 (H - t + 1) - (H + 1) (Harm_H - Harm_{t-1})                     (6.2)

with Harm_t the t-th harmonic number (Harm_0 = 0). GEECO uses it twice: over the last K = 4
frames (the robot's motion) and over the pair (I_t, I_T) (what still differs from the target:
for H = 2 the weights are (-1/2, +1/2), half the difference image). The result is normalised
across all channels and pixels (zero mean, unit standard deviation) to be fed to a CNN like an
RGB image.
"""

from __future__ import annotations

import numpy as np

STD_FLOOR = 0.02  # of the [0, 1] intensity range: a (near-)static sequence is not blown up into noise


def harmonic(n: int) -> float:
    return float(sum(1.0 / i for i in range(1, n + 1)))


def rank_weights(h: int) -> np.ndarray:
    """alpha_1..alpha_H of Eq. 6.2."""
    if h < 1:
        raise ValueError(f"a dynamic image needs at least one frame, got {h}")
    harm = [harmonic(t) for t in range(h + 1)]
    return np.array([2 * (h - t + 1) - (h + 1) * (harm[h] - harm[t - 1]) for t in range(1, h + 1)])


def dynamic_image(frames, normalise: bool = True):
    """Eq. 6.1 over the frame axis 1 of a (B, H, C, Hpx, Wpx) torch tensor in [0, 1]; (B, C, Hpx, Wpx)."""
    import torch

    alpha = torch.as_tensor(rank_weights(frames.shape[1]), dtype=frames.dtype, device=frames.device)
    rho = torch.einsum("t,bt...->b...", alpha, frames)
    if not normalise:
        return rho
    mean = rho.mean(dim=(1, 2, 3), keepdim=True)
    std = rho.std(dim=(1, 2, 3), keepdim=True).clamp_min(STD_FLOOR)
    return (rho - mean) / std


def to_rgb(rho) -> np.ndarray:
    """A normalised dynamic image (C, H, W) as a viewable uint8 (H, W, 3) picture (for recordings)."""
    arr = np.asarray(rho.detach().float().cpu() if hasattr(rho, "detach") else rho, dtype=np.float32)
    arr = np.transpose(arr, (1, 2, 0))
    return np.clip(127.5 + 42.5 * arr, 0, 255).astype(np.uint8)  # +-3 standard deviations span the range
