"""RELATE's generator, relationship module and discriminator (thesis Section 5.3, Appendix 5.D).

Scene latents: a background appearance z_0 ~ U[-1, 1]^{N_b} and per object an appearance
z_k ~ U[-1, 1]^{N_f} and an independent pose sample theta_hat_k ~ U[-r, r]^2 (Section 5.3.1).
Gamma corrects the poses from pairwise messages (Eqs. 5.1, 5.2). Each object's feature window comes
from a learned constant through AdaIN layers (Psi_f, Table 5.D.2), is translated bilinearly to its
pose on the scene's feature grid, and the windows and the background's map (Psi_b, Table 5.D.3) are
composed by an element-wise max (a sum for balls-in-bowl); the renderer G (Table 5.D.4) turns the
composed map into the image. The discriminator (Table 5.D.10) shares its backbone with the position
regressor P; style heads read the mean and variance of its intermediate maps (Section 5.3.3).

Pose convention: theta in [-1, 1]^2 is the object's centre in the image, x right and y down (the
coordinates of ``torch.nn.functional.grid_sample``); an absent object sits at ``ABSENT`` (off the canvas).
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F
from torch.nn.utils.parametrizations import spectral_norm

ABSENT = -2.0
SLOPE = 0.2


class AdaIN(nn.Module):
    """x -> gamma(z) * IN(x) + beta(z), gamma and beta from ReLU(W z + b) (Appendix 5.D)."""

    def __init__(self, channels: int, z_dim: int):
        super().__init__()
        self.norm = nn.InstanceNorm2d(channels, affine=False)
        self.style = nn.Linear(z_dim, 2 * channels)

    def forward(self, x: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        gamma, beta = F.relu(self.style(z)).chunk(2, dim=1)
        return gamma[..., None, None] * self.norm(x) + beta[..., None, None]


class ObjectDecoder(nn.Module):
    """Psi_f (Table 5.D.2): a learned constant T_f (one per object where objects have fixed identities,
    as the balls) through AdaIN(z_k) - conv - AdaIN - conv - AdaIN, zero-padded to the feature grid."""

    def __init__(self, z_dim: int, channels: int, out_channels: int, window: int, grid: int, constants: int = 1):
        super().__init__()
        self.constant = nn.Parameter(0.02 * torch.randn(constants, channels, window, window))
        self.ada = nn.ModuleList([AdaIN(channels, z_dim), AdaIN(channels, z_dim), AdaIN(out_channels, z_dim)])
        self.conv = nn.ModuleList([nn.Conv2d(channels, channels, 3, padding=1), nn.Conv2d(channels, out_channels, 3, padding=1)])
        self.pad = ((grid - window) // 2, grid - window - (grid - window) // 2)

    def forward(self, z: torch.Tensor, slot: torch.Tensor) -> torch.Tensor:
        """z: (N, N_f) appearances; slot: (N,) which constant each object uses."""
        x = self.constant[slot % len(self.constant)]
        x = self.ada[0](x, z)
        x = self.ada[1](F.leaky_relu(self.conv[0](x), SLOPE), z)
        x = self.ada[2](F.leaky_relu(self.conv[1](x), SLOPE), z)
        return F.pad(x, (*self.pad, *self.pad))


class BackgroundDecoder(nn.Module):
    """Psi_b (Table 5.D.3): T_b through AdaIN(z_0) - LReLU - conv - AdaIN - LReLU - conv - AdaIN - LReLU."""

    def __init__(self, z_dim: int, channels: int, grid: int, side: int | None = None):
        super().__init__()
        self.grid, side = grid, side or grid  # a coarser map (side < grid) is upsampled bilinearly to the grid
        self.constant = nn.Parameter(0.02 * torch.randn(1, channels, side, side))
        self.ada = nn.ModuleList([AdaIN(channels, z_dim) for _ in range(3)])
        self.conv = nn.ModuleList([nn.Conv2d(channels, channels, 3, padding=1) for _ in range(2)])

    def forward(self, z0: torch.Tensor) -> torch.Tensor:
        x = F.leaky_relu(self.ada[0](self.constant.expand(len(z0), -1, -1, -1), z0), SLOPE)
        for conv, ada in zip(self.conv, self.ada[1:]):
            x = F.leaky_relu(ada(conv(x), z0), SLOPE)
        if x.shape[-1] != self.grid:
            x = F.interpolate(x, size=(self.grid, self.grid), mode="bilinear", align_corners=False)
        return x


def present_mask(batch: int, low: int, high: int, slots: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """(B, slots) bool: the first n slots present, n uniform in [low, high] (K ~ U{K_min..K_max}, Section 5.3.1)."""
    n = torch.randint(low, high + 1, (batch,), generator=generator)
    return torch.arange(slots)[None] < n[:, None]


def mlp(sizes: list[int], last: nn.Module | None = None) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
        layers.append(nn.Linear(a, b))
        if i < len(sizes) - 2:
            layers.append(nn.LeakyReLU(SLOPE))
    if last is not None:
        layers.append(last)
    return nn.Sequential(*layers)


def pairwise_sum(pair: nn.Module, state: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
    """h_k = sum over the other present objects q of pair(state_k, state_q) (Eqs. 5.2, 5.4): (B, K, hidden)."""
    b, k, _ = state.shape
    pairs = torch.cat([state[:, :, None].expand(b, k, k, -1), state[:, None].expand(b, k, k, -1)], dim=3)
    mask = present[:, None, :] & present[:, :, None] & ~torch.eye(k, dtype=torch.bool, device=state.device)
    return (pair(pairs) * mask[..., None]).sum(dim=2)


class Relation(nn.Module):
    """Gamma (Eqs. 5.1, 5.2): theta_k = theta_hat_k + 0.5 * zeta_k with zeta_k = f(theta_hat_k, z_k, z_0, h_k)
    and h_k = sum over the other present objects q of g(theta_hat_k, z_k, theta_hat_q, z_q): weights shared
    over objects and a sum over messages, so it takes any number of objects in any order. Table 5.D.5 (g:
    2 (N_f + 2) -> 32 -> 32 -> 32) and 5.D.6 (f: 32 + N_f + 2 + N_b -> 32 -> 32 -> 2, tanh). ``residual=False``
    is the ablation without the residual (theta = 0.5 * zeta)."""

    def __init__(self, z_dim: int, z_bg: int, hidden: int = 32, residual: bool = True):
        super().__init__()
        self.pair = mlp([2 * (z_dim + 2), hidden, hidden, hidden])
        self.out = mlp([hidden + z_dim + 2 + z_bg, hidden, hidden, 2], nn.Tanh())
        self.residual = residual

    def forward(self, theta_hat: torch.Tensor, z: torch.Tensor, z0: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        """theta_hat: (B, K, 2), z: (B, K, N_f), z0: (B, N_b), present: (B, K) bool."""
        state = torch.cat([theta_hat, z], dim=2)  # (B, K, N_f + 2)
        h = pairwise_sum(self.pair, state, present)  # Eq. 5.2: sum over q != k
        zeta = self.out(torch.cat([h, state, z0[:, None].expand(*theta_hat.shape[:2], -1)], dim=2))
        theta = 0.5 * zeta + (theta_hat if self.residual else 0.0)  # Eq. 5.1
        return torch.where(present[..., None], theta, torch.full_like(theta, ABSENT))


class Dynamics(nn.Module):
    """The video model's Gamma (Eq. 5.4): the start poses theta_k(0) from the static Gamma, the last three
    velocities V_k(0) = e_v(z_k, theta_k(0), z_0) (Table 5.D.7), then per step the NPE-style update
    v_k(t+1) = f_v(theta_k(t), z_k, V_k(t), z_0, h_k(t)) with h_k(t) the sum over the other present objects q of
    g_v(theta_k, z_k, V_k, theta_q, z_q, V_q), and theta_k(t+1) = theta_k(t) + v_k(t+1). Velocities are in image
    units per frame, tanh-bounded by ``max_speed``."""

    def __init__(self, z_dim: int, z_bg: int, past: int = 3, hidden: int = 32, max_speed: float = 0.25,
                 residual: bool = True):
        super().__init__()
        self.start = Relation(z_dim, z_bg, hidden, residual)
        self.past, self.max_speed = past, max_speed
        state = z_dim + 2 + 2 * past
        self.encode_velocity = mlp([z_dim + 2 + z_bg, 128, 128, 2 * past], nn.Tanh())  # e_v
        self.pair = mlp([2 * state, hidden, hidden, hidden])  # g_v
        self.out = mlp([hidden + state + z_bg, hidden, hidden, 2], nn.Tanh())  # f_v

    def forward(self, theta_hat: torch.Tensor, z: torch.Tensor, z0: torch.Tensor, present: torch.Tensor,
                steps: int) -> torch.Tensor:
        """(B, steps, K, 2): the poses of ``steps`` frames; absent objects stay at ``ABSENT``."""
        b, k, _ = theta_hat.shape
        theta = self.start(theta_hat, z, z0, present)
        theta = torch.where(present[..., None], theta.clamp(-1.0, 1.0), theta)
        on = present[..., None].float()
        background = z0[:, None].expand(b, k, -1)
        velocities = self.max_speed * self.encode_velocity(torch.cat([z, theta.detach(), background], 2))
        velocities = (velocities * on).reshape(b, k, self.past, 2)  # V_k(0): v(-2), v(-1), v(0)
        out = [theta]
        for _ in range(steps - 1):
            state = torch.cat([theta, z, velocities.flatten(2)], dim=2)
            h = pairwise_sum(self.pair, state, present)  # h_k^d(t), Eq. 5.4
            v = self.max_speed * self.out(torch.cat([h, state, background], dim=2)) * on
            theta = theta + v  # theta_k(t+1) = theta_k(t) + v_k(t+1)
            velocities = torch.cat([velocities[:, :, 1:], v[:, :, None]], dim=2)
            out.append(theta)
        return torch.stack(out, dim=1)


class Stacking(nn.Module):
    """The ordered Gamma (Eq. 5.3) for towers: the base at theta_1 = theta_hat_1 + 0.5 f_0(theta_hat_1, z_1, z_0)
    (Table 5.D.9) and each block placed relative to the one below, theta_k = theta_{k-1} + f_1(theta_{k-1},
    z_{k-1}, z_0) (Table 5.D.8), f_1's offset bounded as the released code's: at most 0.2 sideways and 0.1-0.4
    upwards (y points down). The present blocks are the first ones, bottom up."""

    def __init__(self, z_dim: int, z_bg: int, residual: bool = True):
        super().__init__()
        self.base = mlp([2 + z_dim + z_bg, 128, 64, 2], nn.Tanh())  # f_0
        self.next = mlp([2 + z_dim + z_bg, 128, 64, 2])  # f_1
        self.residual = residual

    def forward(self, theta_hat: torch.Tensor, z: torch.Tensor, z0: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        base = 0.5 * self.base(torch.cat([theta_hat[:, 0], z[:, 0], z0], dim=1))
        theta = [base + (theta_hat[:, 0] if self.residual else 0.0)]
        for k in range(1, theta_hat.shape[1]):
            o = self.next(torch.cat([theta[-1], z[:, k - 1], z0], dim=1))
            step = torch.stack([0.2 * torch.tanh(o[:, 0]), -(0.1 + 0.3 * torch.sigmoid(o[:, 1]))], dim=1)
            theta.append(theta[-1] + step)  # Eq. 5.3: on top of the block below
        theta = torch.stack(theta, dim=1)
        return torch.where(present[..., None], theta, torch.full_like(theta, ABSENT))


class Renderer(nn.Module):
    """G (Table 5.D.4): from the composed feature grid to the image, one stride-2 transposed conv per
    doubling (each followed by a 3x3 conv), then a 3x3 conv to RGB and tanh."""

    def __init__(self, channels: int, grid: int, size: int, min_channels: int = 16):
        super().__init__()
        layers: list[nn.Module] = []
        c = channels
        for _ in range(int(round(math.log2(size // grid)))):
            nc = max(min_channels, c // 2)
            layers += [nn.ConvTranspose2d(c, nc, 4, stride=2, padding=1), nn.LeakyReLU(SLOPE),
                       nn.Conv2d(nc, nc, 3, padding=1), nn.LeakyReLU(SLOPE)]
            c = nc
        layers += [nn.Conv2d(c, 3, 3, padding=1), nn.Tanh()]
        self.net = nn.Sequential(*layers)

    def forward(self, w: torch.Tensor) -> torch.Tensor:
        return self.net(w)


def translate(window: torch.Tensor, theta: torch.Tensor, scale: torch.Tensor | None = None) -> torch.Tensor:
    """[Psi_hat]_u = [Psi]_{(u - theta) / s}: the window (centred on the grid) moved to theta and scaled by s
    (1 unless the scale-augmented model predicts it, Section 5.A.2), bilinear, zeros outside."""
    n = len(window)
    s = torch.ones(n, device=window.device, dtype=window.dtype) if scale is None else scale
    affine = torch.zeros(n, 2, 3, device=window.device, dtype=window.dtype)
    affine[:, 0, 0] = affine[:, 1, 1] = 1.0 / s
    affine[:, :, 2] = -theta / s[:, None]
    grid = F.affine_grid(affine, list(window.shape), align_corners=False)
    return F.grid_sample(window, grid, mode="bilinear", padding_mode="zeros", align_corners=False)


class Generator(nn.Module):
    """Psi_b, Psi_f, Gamma and G of Fig. 5.3.1. ``relation``: "full", "no-residual" or None (BlockGAN2D:
    theta = theta_hat)."""

    def __init__(self, size: int = 32, grid: int = 8, window: int = 4, z_obj: int = 8, z_bg: int = 3,
                 channels: int = 64, objects: int = 2, fixed_objects: bool = True, compose: str = "sum",
                 pose_range: tuple[float, float, float, float] = (-0.8, 0.8, -0.8, 0.8), relation: str | None = "full",
                 video: bool = False, max_speed: float = 0.25, scale: bool = False, ordered: bool = False,
                 background_grid: int | None = None):
        super().__init__()
        self.size, self.grid, self.z_obj, self.z_bg, self.objects = size, grid, z_obj, z_bg, objects
        self.fixed_objects, self.compose, self.pose_range = fixed_objects, compose, tuple(pose_range)
        self.video = video
        self.background = BackgroundDecoder(z_bg, channels, grid, background_grid)
        self.object = ObjectDecoder(z_obj, 2 * channels, channels, window, grid, objects if fixed_objects else 1)
        if video:
            self.relation = Dynamics(z_obj, z_bg, max_speed=max_speed, residual=relation == "full")
        elif ordered:
            self.relation = Stacking(z_obj, z_bg, residual=relation == "full") if relation else None
        else:
            self.relation = Relation(z_obj, z_bg, residual=relation == "full") if relation else None
        self.render = Renderer(channels, grid, size)
        # sc (Table 5.A.2): H'_k = H' (1 + sc(z_0, theta_k, z_k)), the scale-augmented model of Section 5.A.2
        self.scale = mlp([z_obj + 2 + z_bg, 32, 32, 1], nn.Tanh()) if scale else None

    # -- sampling the scene latents (Section 5.3.1) ------------------------------------------------------------
    def sample(self, batch: int, present: torch.Tensor | None = None, objects: int | None = None,
               bg_range: float = 1.0, generator: torch.Generator | None = None) -> dict[str, torch.Tensor]:
        k = objects or self.objects
        dev = self.background.constant.device
        u = lambda *shape: torch.rand(*shape, generator=generator, device=dev) * 2 - 1  # noqa: E731
        x0, x1, y0, y1 = self.pose_range
        theta_hat = torch.stack([x0 + (x1 - x0) * (u(batch, k) + 1) / 2, y0 + (y1 - y0) * (u(batch, k) + 1) / 2], dim=2)
        if present is None:
            present = torch.ones(batch, k, dtype=torch.bool, device=dev)
        # objects of fixed identity (the balls) have one look each: a constant style vector of ones (App. 5.D.1)
        z = torch.ones(batch, k, self.z_obj, device=dev) if self.fixed_objects else u(batch, k, self.z_obj)
        return {"z0": bg_range * u(batch, self.z_bg), "z": z, "theta_hat": theta_hat, "present": present}

    def poses(self, latents: dict[str, torch.Tensor], use_relation: bool = True, frames: int = 1) -> torch.Tensor:
        """(B, K, 2) poses; the video model's (B, frames, K, 2) trajectories (Gamma bypassed: standing still)."""
        theta_hat, present = latents["theta_hat"], latents["present"]
        if self.video and use_relation:
            return self.relation(theta_hat, latents["z"], latents["z0"], present, frames)
        if self.relation is None or not use_relation:
            theta = torch.where(present[..., None], theta_hat, torch.full_like(theta_hat, ABSENT))
        else:
            theta = self.relation(theta_hat, latents["z"], latents["z0"], present)
        return theta[:, None].expand(-1, frames, -1, -1) if self.video else theta

    def still_poses(self, latents: dict[str, torch.Tensor], use_relation: bool = True) -> torch.Tensor:
        """(B, K, 2): a still scene's poses; the video model's first frame."""
        theta = self.poses(latents, use_relation)
        return theta[:, 0] if self.video else theta

    def object_maps(self, z: torch.Tensor, theta: torch.Tensor, z0: torch.Tensor) -> torch.Tensor:
        """(B, K, C, g, g): every object's window translated to its pose (and scaled, Section 5.A.2)."""
        b, k, _ = z.shape
        slot = torch.arange(k, device=z.device).repeat(b)
        windows = self.object(z.reshape(b * k, -1), slot)
        scale = None
        if self.scale is not None:
            scale = 1.0 + self.scale(torch.cat([z0[:, None].expand(b, k, -1), theta, z], dim=2)).reshape(b * k)
            scale = scale.clamp(min=0.1)  # (1 + tanh) > 0: a window never vanishes or flips
        return translate(windows, theta.reshape(b * k, 2), scale).reshape(b, k, *windows.shape[1:])

    def compose_maps(self, background: torch.Tensor, objects: torch.Tensor, keep: torch.Tensor) -> torch.Tensor:
        """W = max (or sum) over the background's map and the kept objects' maps."""
        if self.compose == "sum":
            return background + (objects * keep[:, :, None, None, None]).sum(dim=1)
        hidden = torch.where(keep[:, :, None, None, None], objects, torch.full_like(objects, -1e4))
        return torch.maximum(background, hidden.max(dim=1).values)

    def forward(self, latents: dict[str, torch.Tensor], use_relation: bool = True, keep: torch.Tensor | None = None,
                theta: torch.Tensor | None = None, frames: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
        """Images (B, 3, size, size) in [-1, 1] and the poses theta (B, K, 2). ``keep`` (B, K) leaves objects
        out of the composition (the position loss's single-object images, the toggle score); ``theta``
        overrides the poses (editing). The video model renders clips (B, frames, 3, size, size) from
        trajectories (B, frames, K, 2), as does any ``theta`` with a time axis."""
        if theta is None:
            theta = self.poses(latents, use_relation, frames)
        if theta.dim() == 4:  # a clip: every frame is a scene of the same latents at that frame's poses
            b, t = theta.shape[:2]
            per_frame = {key: value.repeat_interleave(t, dim=0) for key, value in latents.items()}
            keep = None if keep is None else keep.repeat_interleave(t, dim=0)
            images, _ = self.forward(per_frame, keep=keep, theta=theta.reshape(b * t, *theta.shape[2:]))
            return images.reshape(b, t, *images.shape[1:]), theta
        objects = self.object_maps(latents["z"], theta, latents["z0"])
        keep = latents["present"] if keep is None else keep & latents["present"]
        w = self.compose_maps(self.background(latents["z0"]), objects, keep)
        return self.render(w), theta


class Discriminator(nn.Module):
    """D (Table 5.D.10): 5x5 stride-2 convs with spectral norm, instance norm after all but the first, to
    a 4x4 map; a logit, the position regressor P (tanh, 2 numbers) on the same features, and a style head
    per normalised layer on the mean and variance of its maps before the norm (Section 5.3.3). ``frames``
    > 1: a clip's frames stacked along the channels (the video discriminator)."""

    def __init__(self, size: int = 32, channels: int = 32, frames: int = 1, max_channels: int = 512):
        super().__init__()
        layers, norms, styles = [], [], []
        c_in, c = 3 * frames, channels
        for i in range(int(round(math.log2(size // 4)))):
            layers.append(spectral_norm(nn.Conv2d(c_in, c, 5, stride=2, padding=2)))
            if i:
                norms.append(nn.InstanceNorm2d(c, affine=True))
                styles.append(nn.Linear(2 * c, 1))
            c_in, c = c, min(max_channels, 2 * c)
        self.convs, self.norms, self.styles = nn.ModuleList(layers), nn.ModuleList(norms), nn.ModuleList(styles)
        self.logit = spectral_norm(nn.Linear(16 * c_in, 1))
        self.position = spectral_norm(nn.Linear(16 * c_in, 2))

    def backbone(self, x: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
        style_logits = []
        for i, conv in enumerate(self.convs):
            x = conv(x)
            if i:
                stats = torch.cat([x.mean(dim=(2, 3)), x.var(dim=(2, 3))], dim=1)
                style_logits.append(self.styles[i - 1](stats))
                x = self.norms[i - 1](x)
            x = F.leaky_relu(x, SLOPE)
        return x.flatten(1), style_logits

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
        features, styles = self.backbone(x)
        return self.logit(features).squeeze(1), styles

    def regress(self, x: torch.Tensor) -> torch.Tensor:
        """P(I): the pose of the one object in a generated image, in [-1, 1]^2."""
        return torch.tanh(self.position(self.backbone(x)[0]))


def init_weights(module: nn.Module) -> None:
    """N(0, 0.02) for every weight (N(1, 0.02) for the instance norms' scales) and zero biases (Appendix 5.D.1)."""
    if isinstance(module, (nn.Conv2d, nn.ConvTranspose2d, nn.Linear, nn.InstanceNorm2d)):
        weight = module.parametrizations.weight.original if hasattr(module, "parametrizations") else module.weight
        if weight is not None:
            nn.init.normal_(weight, 1.0 if isinstance(module, nn.InstanceNorm2d) else 0.0, 0.02)
        if module.bias is not None:
            nn.init.zeros_(module.bias)


class Relate(nn.Module):
    """The generator and discriminator of one RELATE model (``arm``: full, no-residual, no-position, blockgan2d)."""

    def __init__(self, arm: str = "full", size: int = 32, grid: int = 8, window: int = 4, z_obj: int = 8, z_bg: int = 3,
                 channels: int = 64, d_channels: int = 32, objects: int = 2, fixed_objects: bool = True,
                 compose: str = "sum", pose_range=(-0.8, 0.8, -0.8, 0.8), variant: str = "static", clip: int = 1,
                 max_speed: float = 0.25, scale: bool = False, background_grid: int | None = None):
        super().__init__()
        self.arm, self.variant, self.clip = arm, variant, clip
        relation = {"full": "full", "no-residual": "no-residual", "no-position": "full", "blockgan2d": None}[arm]
        self.generator = Generator(size, grid, window, z_obj, z_bg, channels, objects, fixed_objects, compose,
                                   pose_range, relation, video=variant == "video", max_speed=max_speed, scale=scale,
                                   ordered=variant == "ordered", background_grid=background_grid)
        self.discriminator = Discriminator(size, d_channels, frames=clip)
        self.apply(init_weights)

    @property
    def position_loss(self) -> bool:
        return self.arm in ("full", "no-residual")
