"""What the evaluation measures on images, real or generated (the thesis's Section 5.4, and what it could not measure).

* ``Detector``: balls-in-bowl's physical plausibility read off an image. Ball k is where the pixels of
  its fixed colour are (their centroid); the bowl is the ellipse with the second moments of the bowl's
  light pixels (a uniform ellipse of semi-axes a, b has variances a^2/4 and b^2/4 along them). A scene is
  plausible when both balls are seen, each centre lies inside the bowl, and the balls do not
  interpenetrate. Calibrated on the real test frames, whose rate is reported beside the generated ones.
* ``TruthNet``: a small CNN trained on the real training frames to regress the simulator's ground truth
  (a heat map of object centres, and for balls-in-bowl each ball's position and the bowl's shape). The
  Fréchet distance on its penultimate features is "FD-truth": like FID, but on features of a network
  that knows these scenes, trained here, so it needs no downloaded weights. It is not FID.
* ``tower_plausibility``: ShapeStacks' physical plausibility read off an image: each block's box, bottom up,
  read by a TruthNet (the tower reader) trained on real stable and unstable towers, every block resting on
  the one below, and Lemma 1 (the stability plugin's ``lemma1_side_view`` metric, through the registry)
  calling the tower as seen stable. The reader's own rates on held-out real stable and unstable towers
  say how far to trust it.
* ``frechet``: the Fréchet distance between two Gaussians fitted to feature sets (Heusel et al. 2017).
* ``toggle_distance``: Table 5.A.1's disentanglement proxy: remove object i from a generated scene, find
  the pixel that changes most, and measure its distance to where the object's pose says it is.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from . import scenes as S
from .checkpoint import to_uint8

HEAT = 8  # side of the ground truth's heat map of object centres


# -- balls-in-bowl plausibility ----------------------------------------------------------------------------------

@dataclass
class Seen:
    balls: np.ndarray  # (K, 2) pixel centres (u, v), nan where a ball is not seen
    bowl: tuple[np.ndarray, np.ndarray] | None  # (centre (2,), covariance (2, 2)) in pixels
    plausible: bool
    inside: bool
    apart: bool


class Detector:
    """Reads balls and bowl off uint8 images (H, W, 3) by colour."""

    def __init__(self, size: int, balls: int = 2):
        self.size = size
        self.colours = np.asarray([c[:3] for c in S.BALL_COLOURS[:balls]], np.float32)  # ball k has colour k
        self.radius = S.BALL_RADIUS / S.BOWL_EXTENT * size / 2  # a ball's radius in pixels
        self.min_pixels = max(1.0, 0.3 * math.pi * self.radius ** 2)  # a third of its disc

    def ball_masks(self, image: np.ndarray) -> list[np.ndarray]:
        x = image.astype(np.float32) / 255.0
        masks = []
        for colour in self.colours:  # a ball's pixels: its colour's high channels well above its low ones
            high, low = colour > 0.5, colour <= 0.5
            bright = x[..., high].min(axis=-1)
            masks.append((bright - x[..., low].max(axis=-1) > 0.25) & (bright > 0.35))
        return masks

    def __call__(self, image: np.ndarray) -> Seen:
        masks = self.ball_masks(image)
        balls = np.full((len(masks), 2), np.nan)
        for k, m in enumerate(masks):
            if m.sum() >= self.min_pixels:
                v, u = np.nonzero(m)
                balls[k] = u.mean() + 0.5, v.mean() + 0.5
        light = (image.astype(np.float32) / 255.0).min(axis=-1) > 0.55
        bowl = None
        if light.sum() >= 16:
            v, u = np.nonzero(light | np.any(masks, axis=0))  # the balls lie on the bowl: count them in
            pts = np.stack([u + 0.5, v + 0.5], axis=1)
            bowl = (pts.mean(axis=0), np.cov(pts.T) + 1e-6 * np.eye(2))
        seen = ~np.isnan(balls[:, 0])
        inside = bool(bowl is not None and seen.all() and all(self.mahalanobis(b, bowl) <= 2.0 for b in balls))
        apart = bool(seen.all() and all(np.linalg.norm(balls[i] - balls[j]) >= 1.6 * self.radius
                                        for i in range(len(balls)) for j in range(i + 1, len(balls))))
        return Seen(balls, bowl, inside and apart, inside, apart)

    @staticmethod
    def mahalanobis(point: np.ndarray, bowl) -> float:
        centre, cov = bowl
        d = point - centre
        return float(np.sqrt(d @ np.linalg.solve(cov, d)))  # <= 2 on a uniform ellipse's rim


def balls_seen(image: np.ndarray, detector: Detector) -> int:
    return int(sum(m.sum() >= detector.min_pixels for m in detector.ball_masks(image)))


def plausibility(images: np.ndarray, detector: Detector) -> dict[str, float]:
    seen = [detector(im) for im in images]
    return {"plausible": float(np.mean([s.plausible for s in seen])),
            "balls_seen": float(np.mean([not np.isnan(s.balls).any() for s in seen])),
            "inside": float(np.mean([s.inside for s in seen])), "apart": float(np.mean([s.apart for s in seen]))}


@torch.no_grad()
def decomposition(generator, latents: dict[str, torch.Tensor], detector: Detector) -> dict[str, float]:
    """Whether the objects are drawn by the object latents (Fig. 5.4.1's component-wise renders): the share
    of background-only renders that show no ball, and of one-object renders that show exactly one."""
    n, k = latents["present"].shape
    theta = generator.still_poses(latents)
    none = torch.zeros(n, k, dtype=torch.bool)
    background = to_uint8(generator(latents, keep=none, theta=theta)[0])
    single = []
    for j in range(k):
        keep = none.clone()
        keep[:, j] = True
        single += [balls_seen(im, detector) == 1 for im in to_uint8(generator(latents, keep=keep, theta=theta)[0])]
    return {"background_without_balls": float(np.mean([balls_seen(im, detector) == 0 for im in background])),
            "one_object_one_ball": float(np.mean(single))}


# -- the ground-truth regressor and FD-truth ---------------------------------------------------------------------

def truth_targets(pixels: np.ndarray, present: np.ndarray, image_size: int, bowl: np.ndarray | None) -> np.ndarray:
    """(N, T) regression targets per frame: a HEATxHEAT map of object centres (a Gaussian of one cell per
    object), then for balls-in-bowl each ball's centre in [-1, 1] and the bowl's (cos 2phi, sin 2phi, b/a)."""
    n, k = present.shape
    centres = (pixels / image_size) * HEAT - 0.5  # in heat-map cells
    grid = np.arange(HEAT)
    gy, gx = np.meshgrid(grid, grid, indexing="ij")
    d2 = (gx[None, None] - centres[:, :, 0, None, None]) ** 2 + (gy[None, None] - centres[:, :, 1, None, None]) ** 2
    heat = (np.exp(-d2 / 2.0) * present[:, :, None, None]).sum(axis=1).reshape(n, -1)
    parts = [heat]
    if bowl is not None:
        parts.append(pixels.reshape(n, -1) / image_size * 2 - 1)
        parts.append(np.stack([np.cos(2 * bowl[:, 0]), np.sin(2 * bowl[:, 0]), bowl[:, 2] / bowl[:, 1]], axis=1))
    return np.concatenate(parts, axis=1).astype(np.float32)


class TruthNet(nn.Module):
    """Four stride-2 convs to a 128-d feature (what FD-truth compares), then a linear read-out of the truth."""

    FEATURES = 128

    def __init__(self, size: int, outputs: int, width: int = 32, channels: int = 3):
        super().__init__()
        layers, c = [], channels
        for i in range(4):
            layers += [nn.Conv2d(c, width * 2 ** min(i, 2), 3, stride=2, padding=1), nn.GroupNorm(8, width * 2 ** min(i, 2)),
                       nn.ReLU()]
            c = width * 2 ** min(i, 2)
        self.conv = nn.Sequential(*layers)
        self.features = nn.Sequential(nn.Flatten(), nn.Linear(c * (size // 16) ** 2, self.FEATURES), nn.ReLU())
        self.head = nn.Linear(self.FEATURES, outputs)

    def embed(self, x: torch.Tensor) -> torch.Tensor:
        return self.features(self.conv(x))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.embed(x))


def fit_truth_net(images: torch.Tensor, targets: np.ndarray, epochs: int, batch: int = 64, seed: int = 0) -> TruthNet:
    """A TruthNet fitted to uint8 images (N, 3, s, s) and their targets (Adam 1e-3, MSE); seeded, so every
    arm's evaluation on one dataset uses the same features."""
    gen = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    net = TruthNet(images.shape[-1], targets.shape[1], channels=images.shape[1])
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    y = torch.from_numpy(targets)
    for _ in range(epochs):
        order = torch.randperm(len(images), generator=gen)
        for start in range(0, len(order), batch):
            i = order[start:start + batch]
            loss = F.mse_loss(net(images[i].float() / 127.5 - 1), y[i])
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
    return net.eval()


@torch.no_grad()
def embed(net: TruthNet, images: torch.Tensor, batch: int = 256, read_out: bool = False) -> np.ndarray:
    """Features of images in [-1, 1] (float) or uint8; with ``read_out`` the network's ground truth read off them."""
    out = []
    for start in range(0, len(images), batch):
        x = images[start:start + batch]
        x = x.float() / 127.5 - 1 if x.dtype == torch.uint8 else x
        out.append((net(x) if read_out else net.embed(x)).numpy())
    return np.concatenate(out).astype(np.float64)


# -- ShapeStacks: Lemma 1 on the towers the images show -----------------------------------------------------------

def box_targets(extent: np.ndarray, present: np.ndarray, image_size: int) -> np.ndarray:
    """The tower reader's (N, 5 K) targets: per slot (bottom up) whether a block is there and its pixel box
    (``extent``: u_min, v_min, u_max, v_max at ``image_size`` px) in [-1, 1]."""
    boxes = np.where(present[..., None] > 0, extent / image_size * 2 - 1, 0.0)
    return np.concatenate([present[..., None], boxes], axis=2).reshape(len(present), -1).astype(np.float32)


def tower_boxes(rows: np.ndarray, size: int) -> list[np.ndarray]:
    """Per row of ``box_targets`` (or the tower reader's reading of them), the tower's blocks bottom up as pixel
    boxes (n, 4): the slots read as present (> 0.5) up to the first that is not."""
    out = []
    for r in rows.reshape(len(rows), -1, 5):
        n = int(np.argmin(np.r_[r[:, 0] > 0.5, False]))
        out.append((r[:n, 1:] + 1) / 2 * size)
    return out


def tower_plausibility(towers: list[np.ndarray], lemma1, size: int) -> dict[str, float]:
    """The share of towers that rest (each block's bottom within 1/32 of the image of the top of the block below,
    and not sunk deeper than that block's height: the real towers' boxes overlap by 0.3-9 px at 32 px, the top
    faces being seen from above), that Lemma 1 calls stable as seen (``lemma1``: the stability plugin's
    ``lemma1_side_view``, on each block's (centre, width, height)), and both; and the mean number of blocks read."""
    tol = size / 32
    resting, stable = [], []
    for b in towers:
        heights = b[:, 3] - b[:, 1]
        overlap = b[1:, 3] - b[:-1, 1]  # upper block's bottom below the lower's top
        resting.append(bool(len(b) and np.all((overlap >= -tol) & (overlap <= heights[:-1]))))
        stable.append(bool(len(b) and lemma1([((u0 + u1) / 2, u1 - u0, v1 - v0) for u0, v0, u1, v1 in b])["stable"]))
    resting_, stable_ = np.array(resting), np.array(stable)
    out = {"plausible": float(np.mean(resting_ & stable_)), "stable": float(stable_.mean()),
           "resting": float(resting_.mean()), "blocks": float(np.mean([len(b) for b in towers]))}
    return out


def frechet(a: np.ndarray, b: np.ndarray) -> float:
    """||mu_a - mu_b||^2 + tr(C_a + C_b - 2 (C_a C_b)^(1/2)) (Heusel et al. 2017)."""
    mu_a, mu_b = a.mean(axis=0), b.mean(axis=0)
    c_a, c_b = np.cov(a, rowvar=False), np.cov(b, rowvar=False)
    eig = np.linalg.eigvals(c_a @ c_b)  # tr sqrt(C_a C_b) = sum of sqrt of its eigenvalues (real, >= 0)
    return float(((mu_a - mu_b) ** 2).sum() + np.trace(c_a) + np.trace(c_b) - 2 * np.sqrt(np.clip(eig.real, 0, None)).sum())


class Distances:
    """Fréchet distances of a set of images or clips to the real test set, on every feature network in use:
    ``nets`` maps a metric's name to (features function, the real test inputs it is measured against)."""

    def __init__(self, nets: dict):
        self.nets = {name: (features, features(reference)) for name, (features, reference) in nets.items()}

    def __call__(self, x: torch.Tensor) -> dict[str, float]:
        return {name: frechet(features(x), reference) for name, (features, reference) in self.nets.items()}


# -- Table 5.A.1's toggle score -----------------------------------------------------------------------------------

@torch.no_grad()
def toggle_distance(generator, scenes: int, objects: int, seed: int = 0, batch: int = 50) -> float:
    """Median over objects and scenes of the distance (pixels) from the pixel that changes most when
    object i is left out of the composition to object i's position theta_i."""
    gen = torch.Generator().manual_seed(seed)
    size, distances = generator.size, []
    for start in range(0, scenes, batch):
        n = min(batch, scenes - start)
        latents = generator.sample(n, objects=objects, generator=gen)
        full, theta = generator(latents, theta=generator.still_poses(latents))
        for i in range(objects):
            keep = torch.ones(n, objects, dtype=torch.bool)
            keep[:, i] = False
            without, _ = generator(latents, keep=keep, theta=theta)
            change = (full - without).pow(2).sum(dim=1).flatten(1)  # (n, H*W)
            top = change.argmax(dim=1)
            v, u = top // size + 0.5, top % size + 0.5
            target = (theta[:, i] + 1) / 2 * size  # theta in [-1, 1] to pixels
            distances.append(torch.sqrt((u - target[:, 0]) ** 2 + (v - target[:, 1]) ** 2).numpy())
    return float(np.median(np.concatenate(distances)))
