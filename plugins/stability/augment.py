"""Physically plausible image augmentation for the stability predictor (thesis Section 3.4.1).

"During training, we augment the training images by randomising colours, varying aspect-ratios,
and applying random cropping, vertical flipping and minimal in-plane rotation. We ensure that all
data augmentations still yield physically plausible, upright towers."

Implemented with torch ops only (no torchvision):

- :func:`colour_jitter`  brightness, contrast, saturation, hue rotation, per-channel shifts.
- :func:`change_aspect`  stretch the width and squeeze the height (or vice versa) by different
  factors, then crop/pad (edge-replicate) back to the frame.
- :func:`random_crop`    a random window of ≥ ``min_scale`` of each side, resized back.
- :func:`flip_lr`        the thesis's "vertical flipping": a mirror about the *vertical axis*
  (left ↔ right).  An up-down flip would turn towers upside down, so it is never applied.
- :func:`rotate`         small in-plane rotations (at most ``MAX_ROTATION_DEG`` = 5°), so
  towers stay upright (it looks like a slight camera roll).

:class:`TrainTransform` composes them (all geometric ones as ONE affine warp, so the image is
resampled once) and :class:`EvalTransform` only converts and resizes.  Both take uint8 images
``(H, W, 3)`` or ``(N, H, W, 3)`` (numpy or torch) and return float32 tensors ``(3, h, w)`` or
``(N, 3, h, w)`` in ``[0, 1]``.  The individual functions work on float ``(3, H, W)`` or
``(N, 3, H, W)`` tensors and take an optional ``torch.Generator`` for reproducible draws.
"""

from __future__ import annotations

import math
from typing import Sequence

import torch
import torch.nn.functional as F

__all__ = ["MAX_ROTATION_DEG", "to_float", "resize", "colour_jitter", "change_aspect", "random_crop", "flip_lr",
           "rotate", "TrainTransform", "EvalTransform"]

MAX_ROTATION_DEG = 5.0
"""Largest in-plane rotation any function here applies: towers must stay upright."""

# ITU-R BT.601 luma weights, used for grey levels (contrast, saturation).
_LUMA = (0.299, 0.587, 0.114)


# --------------------------------------------------------------------------------------------
# conversion and shape helpers
# --------------------------------------------------------------------------------------------

def _size2(size: int | Sequence[int]) -> tuple[int, int]:
    if isinstance(size, int):
        return size, size
    h, w = size
    return int(h), int(w)


def to_float(images) -> torch.Tensor:
    """uint8 ``(H, W, 3)`` / ``(N, H, W, 3)`` (numpy or torch) → float32 ``(3, H, W)`` / ``(N, 3, H, W)``
    in ``[0, 1]``.  Float inputs (channels last) are taken to be in ``[0, 1]`` already."""
    x = torch.as_tensor(images)
    if x.dim() not in (3, 4) or x.shape[-1] != 3:
        raise ValueError(f"expected RGB images (H, W, 3) or (N, H, W, 3), got shape {tuple(x.shape)}")
    x = x.movedim(-1, -3).contiguous()          # transpose first: bytes, not floats, for uint8
    return x.to(torch.float32).div_(255.0) if x.dtype == torch.uint8 else x.to(torch.float32)


def _batched(x: torch.Tensor) -> tuple[torch.Tensor, bool]:
    if x.dim() == 3:
        return x.unsqueeze(0), True
    if x.dim() == 4:
        return x, False
    raise ValueError(f"expected a float image (3, H, W) or batch (N, 3, H, W), got shape {tuple(x.shape)}")


def resize(x: torch.Tensor, size: int | Sequence[int]) -> torch.Tensor:
    """Bilinear, anti-aliased resize of float ``(3, H, W)`` / ``(N, 3, H, W)`` images to ``size``."""
    xb, single = _batched(x)
    h, w = _size2(size)
    if xb.shape[-2:] != (h, w):
        xb = F.interpolate(xb, size=(h, w), mode="bilinear", align_corners=False, antialias=True).clamp_(0.0, 1.0)
    return xb[0] if single else xb


def _uniform(n: int, lo: float, hi: float, generator: torch.Generator | None) -> torch.Tensor:
    return lo + (hi - lo) * torch.rand(n, generator=generator)


# --------------------------------------------------------------------------------------------
# colour
# --------------------------------------------------------------------------------------------

def _hue_matrices(angles: torch.Tensor) -> torch.Tensor:
    """Rotations of RGB space about the grey axis (1, 1, 1)/√3 (Rodrigues): a hue shift that keeps
    grey levels grey.  ``angles`` in radians, shape (N,) → (N, 3, 3)."""
    k = torch.full((3,), 1.0 / math.sqrt(3.0))
    K = torch.tensor([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    c, s = torch.cos(angles).view(-1, 1, 1), torch.sin(angles).view(-1, 1, 1)
    return c * torch.eye(3) + s * K + (1 - c) * torch.outer(k, k)


def colour_jitter(x: torch.Tensor, brightness: float = 0.25, contrast: float = 0.25, saturation: float = 0.3,
                  hue: float = 0.08, channel_shift: float = 0.03,
                  generator: torch.Generator | None = None) -> torch.Tensor:
    """Random colours, drawn per image (colour does not change whether a tower stands).

    brightness ×U(1±brightness); contrast: blend with the image's mean grey by U(1±contrast);
    saturation: blend with the per-pixel grey by U(1±saturation); hue: rotate RGB about the grey
    axis by U(±hue) turns; channel shifts: add U(±channel_shift) to each channel.  Every step is
    affine in RGB, so they are composed into one 3x3 matrix and offset per image, applied in one
    pass and clamped to [0, 1] once.
    """
    xb, single = _batched(x)
    n = xb.shape[0]
    b = _uniform(n, 1 - brightness, 1 + brightness, generator).view(n, 1, 1)
    c = _uniform(n, 1 - contrast, 1 + contrast, generator).view(n, 1, 1)
    s = _uniform(n, 1 - saturation, 1 + saturation, generator).view(n, 1, 1)
    h = _uniform(n, -hue, hue, generator) * 2 * math.pi
    shift = _uniform(3 * n, -channel_shift, channel_shift, generator).view(n, 3, 1)

    luma = torch.tensor(_LUMA, dtype=xb.dtype)
    grey = luma.expand(3, 3)                                        # G: every channel ← the grey level
    mean_grey = (xb.mean(dim=(-2, -1)) @ luma).view(n, 1, 1)        # the image's mean grey
    # y = H (s I + (1 - s) G) (c b x + (1 - c) b m) + shift; G and H keep grey levels grey, so
    # the contrast term's grey offset passes through saturation and hue unchanged
    matrix = _hue_matrices(h) @ (s * torch.eye(3) + (1 - s) * grey) * (c * b)
    offset = (1 - c) * b * mean_grey + shift                        # (N, 3, 1)
    y = torch.baddbmm(offset, matrix, xb.flatten(2)).view_as(xb).clamp_(0.0, 1.0)
    return y[0] if single else y


# --------------------------------------------------------------------------------------------
# geometry: every transform is a 3x3 matrix in pixel units about the image centre that maps an
# OUTPUT position to the INPUT position it samples; compositions are matrix products and the
# image is resampled once (bilinear, edges replicated).
# --------------------------------------------------------------------------------------------

def _eye(n: int) -> torch.Tensor:
    return torch.eye(3).repeat(n, 1, 1)


def _flip_matrices(flip: torch.Tensor) -> torch.Tensor:
    m = _eye(flip.shape[0])
    m[:, 0, 0] = torch.where(flip, -1.0, 1.0)                       # x → -x: mirror about the vertical axis
    return m


def _scale_matrices(sx: torch.Tensor, sy: torch.Tensor, tx: torch.Tensor | None = None,
                    ty: torch.Tensor | None = None) -> torch.Tensor:
    m = _eye(sx.shape[0])
    m[:, 0, 0], m[:, 1, 1] = sx, sy
    if tx is not None:
        m[:, 0, 2], m[:, 1, 2] = tx, ty
    return m


def _rotation_matrices(degrees: torch.Tensor) -> torch.Tensor:
    a = torch.deg2rad(degrees)
    m = _eye(a.shape[0])
    m[:, 0, 0], m[:, 0, 1] = torch.cos(a), -torch.sin(a)
    m[:, 1, 0], m[:, 1, 1] = torch.sin(a), torch.cos(a)
    return m


def _warp(x: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
    """Resample ``x`` (N, 3, H, W) with output→input pixel matrices ``m`` (N, 3, 3)."""
    n, _, hgt, wid = x.shape
    d = torch.diag(torch.tensor([wid / 2.0, hgt / 2.0, 1.0]))
    d_inv = torch.diag(torch.tensor([2.0 / wid, 2.0 / hgt, 1.0]))
    theta = (d_inv @ m @ d)[:, :2, :]                               # in grid_sample's [-1, 1] coordinates
    grid = F.affine_grid(theta.to(x.dtype), [n, 3, hgt, wid], align_corners=False)
    return F.grid_sample(x, grid, mode="bilinear", padding_mode="border", align_corners=False)


def _aspect_matrices(n: int, max_change: float, generator: torch.Generator | None) -> torch.Tensor:
    # stretch one axis by √r and squeeze the other by 1/√r, r ∈ [1/(1+max_change), 1+max_change]
    log_r = _uniform(n, -math.log1p(max_change), math.log1p(max_change), generator)
    stretch_x = torch.exp(log_r / 2)
    return _scale_matrices(1.0 / stretch_x, stretch_x)               # output → input: divide by the stretch


def _crop_matrices(n: int, hgt: int, wid: int, min_scale: float, generator: torch.Generator | None) -> torch.Tensor:
    # a window of scale s ∈ [min_scale, 1] of each side, anywhere inside the frame
    s = _uniform(n, min_scale, 1.0, generator)
    tx = (2 * torch.rand(n, generator=generator) - 1) * (1 - s) * wid / 2
    ty = (2 * torch.rand(n, generator=generator) - 1) * (1 - s) * hgt / 2
    return _scale_matrices(s, s, tx, ty)


def _check_rotation(max_degrees: float) -> None:
    if abs(max_degrees) > MAX_ROTATION_DEG:
        raise ValueError(f"rotations above {MAX_ROTATION_DEG}° would no longer show upright towers; got {max_degrees}°")


def change_aspect(x: torch.Tensor, max_change: float = 0.15, generator: torch.Generator | None = None) -> torch.Tensor:
    """Vary the aspect ratio by up to ``1 + max_change``: one axis is stretched, the other squeezed
    (different factors for width and height), then the image is cropped/padded back to its frame
    (the padding replicates the edges)."""
    xb, single = _batched(x)
    y = _warp(xb, _aspect_matrices(xb.shape[0], max_change, generator))
    return y[0] if single else y


def random_crop(x: torch.Tensor, min_scale: float = 0.85, generator: torch.Generator | None = None) -> torch.Tensor:
    """Random crops: a window of ``U(min_scale, 1)`` of each side at a random position inside the
    image, resized back to the full frame.  Keep ``min_scale`` high so towers are not cut off."""
    xb, single = _batched(x)
    y = _warp(xb, _crop_matrices(xb.shape[0], xb.shape[-2], xb.shape[-1], min_scale, generator))
    return y[0] if single else y


def flip_lr(x: torch.Tensor) -> torch.Tensor:
    """Mirror float ``(..., 3, H, W)`` images about the vertical axis: column ``j`` ↔ ``W-1-j``,
    rows unchanged.  This is the thesis's "vertical flipping": a mirrored upright tower is an upright
    tower with the same stability label.  An up-down flip is never physically plausible."""
    return torch.flip(x, dims=(-1,))


def rotate(x: torch.Tensor, max_degrees: float = 4.0, generator: torch.Generator | None = None) -> torch.Tensor:
    """Small in-plane rotations by ``U(±max_degrees)`` (≤ ``MAX_ROTATION_DEG``) about the image
    centre; the corners are filled by replicating the edges."""
    _check_rotation(max_degrees)
    xb, single = _batched(x)
    deg = _uniform(xb.shape[0], -max_degrees, max_degrees, generator)
    y = _warp(xb, _rotation_matrices(deg))
    return y[0] if single else y


# --------------------------------------------------------------------------------------------
# transforms
# --------------------------------------------------------------------------------------------

class EvalTransform:
    """uint8 ``(H, W, 3)`` / ``(N, H, W, 3)`` → float ``(3, h, w)`` / ``(N, 3, h, w)`` in [0, 1],
    resized (bilinear, anti-aliased) to ``size``.  Nothing random."""

    def __init__(self, size: int | Sequence[int]):
        self.size = _size2(size)

    def __call__(self, images) -> torch.Tensor:
        return resize(to_float(images), self.size)

    def __repr__(self) -> str:
        return f"EvalTransform(size={self.size})"


class TrainTransform:
    """The thesis's training augmentation, scaled by ``strength`` (0 → same as :class:`EvalTransform`).

    Per image: one affine warp combining a small rotation (≤ 5°), an aspect ratio change, a random
    crop and, with probability ``p_flip``, a left-right mirror; a resize to ``size``; then colour
    jitter (pointwise, so it is done at the output resolution).  Magnitudes at ``strength=1``: brightness/contrast ±25 %, saturation ±30 %, hue
    ±0.08 turn, channel shifts ±0.03, aspect ratio up to ×1.15, crops keep ≥ 85 % of each side,
    rotation ±4° (always capped at ``MAX_ROTATION_DEG``).  Pass ``seed`` or a ``torch.Generator``
    for reproducible draws (otherwise torch's global generator is used).
    """

    def __init__(self, size: int | Sequence[int], strength: float = 1.0, *, seed: int | None = None,
                 generator: torch.Generator | None = None, brightness: float = 0.25, contrast: float = 0.25,
                 saturation: float = 0.3, hue: float = 0.08, channel_shift: float = 0.03, aspect: float = 0.15,
                 crop: float = 0.15, rotate_deg: float = 4.0, p_flip: float = 0.5):
        if strength < 0:
            raise ValueError(f"strength must be >= 0, got {strength}")
        if seed is not None and generator is not None:
            raise ValueError("pass either seed or generator, not both")
        self.size = _size2(size)
        self.strength = float(strength)
        self.generator = torch.Generator().manual_seed(int(seed)) if seed is not None else generator
        k = self.strength
        self.colour = dict(brightness=brightness * k, contrast=contrast * k, saturation=saturation * k,
                           hue=hue * k, channel_shift=channel_shift * k)
        self.aspect = aspect * k
        self.min_scale = max(0.5, 1.0 - crop * k)
        self.rotate_deg = min(rotate_deg * k, MAX_ROTATION_DEG)
        self.p_flip = p_flip if k > 0 else 0.0

    def __call__(self, images) -> torch.Tensor:
        x, single = _batched(to_float(images))
        if self.strength > 0:
            g, n, hgt, wid = self.generator, x.shape[0], x.shape[-2], x.shape[-1]
            # output → input: mirror, then the crop window, the aspect change and the rotation
            deg = _uniform(n, -self.rotate_deg, self.rotate_deg, g)
            flip = torch.rand(n, generator=g) < self.p_flip
            m = (_rotation_matrices(deg) @ _aspect_matrices(n, self.aspect, g)
                 @ _crop_matrices(n, hgt, wid, self.min_scale, g) @ _flip_matrices(flip))
            x = resize(_warp(x, m), self.size)     # warp at full resolution, then resize (anti-aliased)
            x = colour_jitter(x, generator=g, **self.colour)   # pointwise: cheaper after the resize
        else:
            x = resize(x, self.size)
        return x[0] if single else x

    def __repr__(self) -> str:
        return f"TrainTransform(size={self.size}, strength={self.strength})"
