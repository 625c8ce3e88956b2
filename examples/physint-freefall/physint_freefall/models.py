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


def PixelMLP(in_size: int = 64, hidden: int = 64, pool: int = 8):  # noqa: N802
    """A weak stability baseline: average-pool the image by ``pool`` and classify the pixels with an MLP.

    Follows the stability method's model convention: float images (N, 3, in_size, in_size) in
    [0, 1] -> one logit per image (N,), positive = unstable.
    """
    import torch.nn as nn

    side = max(1, in_size // pool)
    return nn.Sequential(nn.AdaptiveAvgPool2d(side), nn.Flatten(), nn.Linear(3 * side * side, hidden), nn.ReLU(),
                         nn.Linear(hidden, 1), nn.Flatten(0))
