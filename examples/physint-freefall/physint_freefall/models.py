"""Networks of the freefall plugin (torch is imported only when a model is built)."""

from __future__ import annotations


def TimeToGroundMLP(hidden: int = 32, layers: int = 2):  # noqa: N802 (a constructor)
    """h (metres) -> t (seconds): a small MLP; it has to learn the square root itself."""
    import torch.nn as nn

    blocks, width = [], 1
    for _ in range(layers):
        blocks += [nn.Linear(width, hidden), nn.Tanh()]
        width = hidden
    blocks.append(nn.Linear(width, 1))
    return nn.Sequential(*blocks)


def PixelMLP(in_shape=(3, 64, 64), num_outputs: int = 1, hidden: int = 64, pool: int = 8):  # noqa: N802
    """Average-pool an image by ``pool`` and classify the pixels with a two-layer MLP."""
    import torch.nn as nn

    c, h, w = in_shape
    return nn.Sequential(nn.AvgPool2d(pool), nn.Flatten(), nn.Linear(c * (h // pool) * (w // pool), hidden), nn.ReLU(),
                         nn.Linear(hidden, num_outputs))
