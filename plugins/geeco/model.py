"""GEECO and its ablations (thesis Section 6.3, Fig. 6.3.2; Appendices 6.A-6.C) and the loss of Eq. 6.3.

Every variant reads an observation buffer of K = 4 (frame, joint angles) pairs and the target
image I_T, and regresses the end-effector displacement u_dEE (3), gripper logits u_GRP over
{open, no-op, close} (3) and the auxiliary positions q_EE and q_OBJ (3 each):

* ``geeco-f`` (F): s_t = psi_OBS(I_t) + psi_DYN(rho(I_{t-K+1}..I_t)) + psi_DIFF(rho(I_t, I_T)) + x_t,
  one LSTM step per window;
* ``geeco-d`` (D): s_j = psi_OBS(I_j) + psi_DIFF(rho(I_j, I_T)) + x_j for each j in the buffer,
  fed to the LSTM frame by frame (Appendix 6.B);
* ``geeco-r`` (R): s_j = psi_OBS(I_j) + (psi_OBS(I_T) - psi_OBS(I_j)) + x_j, frame by frame;
* ``e2evmc``: the unconditioned controller of James et al. (Appendix 6.C): s_j = psi_OBS(I_j) + x_j.

(+ is concatenation along channels; x is tiled over the feature map.) The LSTM (128) starts
from zeros for every window, in training and in control, so a window is judged on its own; its
output goes through FC(128) + ReLU into four linear heads (Table 6.A.2). The encoders are
Table 6.A.1's eight 3x3 convolutions (32, 48, 64, 128, 192, 256, 256, 256 filters, stride 1
then 2, ReLU), weights not shared; ``width`` scales the filters for the CPU presets, ``norm``
adds group normalisation after each convolution (not in the thesis; it speeds up learning) and
``min_side`` stops the halving at that map size (small frames keep a spatial map; see ``strides``).

``readout="keypoints"`` (not in the thesis) replaces the flattened maps by a spatial softmax per
channel: each channel becomes the expected image position (x, y) of its activation (Levine et al.,
JMLR 2016, the common readout of visuomotor policies), so where things are comes out as numbers
instead of being squeezed into channels by halving the maps down to 1x1; use it with ``min_side``
so that the maps keep a grid to take positions on.

``forward`` takes a chunk of T >= K consecutive frames and answers for each of its T - K + 1
windows, so in training every frame is encoded once however many windows share it.

``dee_bins`` > 0 (not in the thesis) classifies each axis of u_dEE over that many bins across
[-1, 1] (the expert's largest step) instead of regressing it: the loss is cross-entropy on
two-hot targets (the two bins either side of the value, weighted so their mean is the value), and
the command is the mean over the most likely bin and its neighbours. Where the demonstrations show
two different commands for states the network cannot tell apart (push on, or rise and go round),
the regression answers their average, a stall; the classifier answers one of them.

``dee_modes`` > 0 (not in the thesis) classifies the whole 3-D command instead, over that many
modes: k-means centres of the training demonstrations' commands (``command_modes``, kept in the
checkpoint as ``dee_centres``), each with a regressed offset from its centre (as behaviour
transformers do). The loss is cross-entropy on the nearest centre plus the MSE of that centre's
offset; the command is the most likely centre plus its offset. Per-axis bins choose each axis on
its own, so where the demonstrations go several ways every axis can fall to its middle bin, zero;
one class for the whole command cannot.

``command="positions"`` (not in the thesis) adds a head for the target's position q_TGT (x, y; MSE
with the other positions) and takes u_dEE from a command head instead of the ``dee`` head: an MLP
over the hand's and the object's positions over the buffer and the target's. It learns from the
demonstrations' true positions (MSE with u_dEE): alone and first (``train.fit_command_head``), or with
the network (``position_dee`` in the loss); in control it gets the hand's measured position
(proprioception) and the network's estimates q_OBJ and q_TGT. Where things are
is what the network has to see; what to do there is learned from numbers. Its network sees the
frames only, not the joint angles (``_state``).
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from .dynamic import dynamic_image

ENCODER_FILTERS = (32, 48, 64, 128, 192, 256, 256, 256)  # Table 6.A.1
BUFFER = 4  # K
HIDDEN = 128
JOINTS = 7
GRIPPER_CLASSES = 3  # open, no-op, close
VARIANTS = ("geeco-f", "geeco-d", "geeco-r", "e2evmc")
READOUTS = ("flatten", "keypoints")
COMMANDS = ("network", "positions")
COMMAND_HIDDEN = 256


class Encoder(nn.Module):
    """Table 6.A.1's eight 3x3 convolutions (stride 1, then 2), ReLU after each.

    Layers whose input is at most 2x2 run in fp32 even under bf16 autocast: in bf16 the weight
    gradients of the two layers with 1x1 inputs came out NaN in the first training steps on this
    project's CPUs (AMX, torch 2.13; a lone convolution of that shape did not reproduce it). They
    are the cheapest layers of the encoder.
    """

    def __init__(self, width: float = 1.0, norm: bool = False, image_size: int = 256, min_side: int = 1,
                 stem_stride: int = 1):
        super().__init__()
        layers: list[nn.Module] = []
        norms: list[nn.Module] = []
        channels = 3
        for i, (filters, stride) in enumerate(zip(ENCODER_FILTERS, strides(image_size, min_side, stem_stride))):
            out = max(4, int(round(filters * width)))
            layers.append(nn.Conv2d(channels, out, 3, stride=stride, padding=1))
            norms.append(nn.GroupNorm(_groups(out), out) if norm else nn.Identity())
            channels = out
        self.convs = nn.ModuleList(layers)
        self.norms = nn.ModuleList(norms)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for conv, norm in zip(self.convs, self.norms):
            if x.shape[-1] <= 2 and torch.is_autocast_enabled(x.device.type):
                with torch.autocast(x.device.type, enabled=False):
                    x = F.relu_(norm(conv(x.float())))
            else:  # ReLU in place: neither GroupNorm's nor a convolution's backward needs its output
                x = F.relu_(norm(conv(x)))
        return x


def _groups(channels: int) -> int:
    """Groups of the group normalisation after a convolution: up to 8 of at least 4 channels each,
    a divisor of ``channels`` (so any ``width`` works: 0.375 gives 18 channels, in 3 groups)."""
    groups = max(1, min(8, channels // 4))
    while channels % groups:
        groups -= 1
    return groups


def strides(size: int, min_side: int = 1, stem_stride: int = 1) -> list[int]:
    """Table 6.A.1's strides (1, then 2), except that a map is not halved below ``min_side``: at
    256 px the last map is 2x2 (the thesis); at 64 px it would be 1x1, and ``min_side`` = 4 keeps
    where things are in a 4x4 map instead of squeezing it into the channels. ``stem_stride`` = 2
    halves the frame in the first convolution too: a 128 px frame then costs about what a 64 px
    one does with Table 6.A.1's strides, while the first layer still sees every pixel."""
    out, side = [], size
    for i in range(len(ENCODER_FILTERS)):
        halve = side > min_side and (side + 1) // 2 >= min_side
        stride = (stem_stride if i == 0 else 2) if halve else 1
        out.append(stride)
        side = (side + stride - 1) // stride
    return out


def feature_shape(size: int, width: float, min_side: int = 1, stem_stride: int = 1) -> tuple[int, int]:
    """(channels, side) of an encoder's output for ``size`` x ``size`` input."""
    side = size
    for stride in strides(size, min_side, stem_stride):
        side = (side + stride - 1) // stride
    return max(4, int(round(ENCODER_FILTERS[-1] * width))), side


class Geeco(nn.Module):
    def __init__(self, variant: str = "geeco-f", image_size: int = 64, width: float = 1.0, buffer: int = BUFFER,
                 norm: bool = False, min_side: int = 1, stem_stride: int = 1, dee_bins: int = 0,
                 dee_modes: int = 0, readout: str = "flatten", command: str = "network"):
        super().__init__()
        if variant not in VARIANTS:
            raise ValueError(f"variant {variant!r} is not known; valid: {', '.join(VARIANTS)}")
        if dee_bins == 1 or dee_bins < 0:
            raise ValueError(f"dee_bins must be 0 (regression) or >= 2, got {dee_bins}")
        if dee_modes == 1 or dee_modes < 0 or (dee_modes and dee_bins):
            raise ValueError(f"dee_modes must be 0 (off) or >= 2, and not with dee_bins; got {dee_modes}")
        if readout not in READOUTS:
            raise ValueError(f"readout {readout!r} is not known; valid: {', '.join(READOUTS)}")
        if command not in COMMANDS:
            raise ValueError(f"command {command!r} is not known; valid: {', '.join(COMMANDS)}")
        self.variant, self.image_size, self.width, self.buffer = variant, image_size, width, buffer
        self.readout, self.command = readout, command
        self.dee_bins, self.dee_modes = dee_bins, dee_modes
        if dee_modes:  # the k-means centres of the demonstrated commands (set_modes), saved with the weights
            self.register_buffer("dee_centres", torch.zeros(dee_modes, 3))
        enc = dict(width=width, norm=norm, image_size=image_size, min_side=min_side, stem_stride=stem_stride)
        self.obs = Encoder(**enc)  # psi_OBS
        self.dyn = Encoder(**enc) if variant == "geeco-f" else None  # psi_DYN
        self.diff = Encoder(**enc) if variant in ("geeco-f", "geeco-d") else None  # psi_DIFF
        channels, side = feature_shape(image_size, width, min_side, stem_stride)
        maps = {"geeco-f": 3, "geeco-d": 2, "geeco-r": 2, "e2evmc": 1}[variant]
        if readout == "keypoints":  # (x, y) per channel of each map, and the joint angles once
            self.state_size = maps * channels * 2 + JOINTS
            self.keypoint_temperature = nn.Parameter(torch.zeros(1))  # log temperature of the softmax, learned
        else:
            self.state_size = (maps * channels + JOINTS) * side * side
        self.lstm = nn.LSTM(self.state_size, HIDDEN, batch_first=True)
        self.fc = nn.Linear(HIDDEN, HIDDEN)
        dee_outputs = 4 * dee_modes if dee_modes else 3 * max(1, dee_bins)  # mode logits + offsets, bin logits, values
        self.heads = nn.ModuleDict({"dee": nn.Linear(HIDDEN, dee_outputs),
                                    "grip": nn.Linear(HIDDEN, GRIPPER_CLASSES),
                                    "ee": nn.Linear(HIDDEN, 3), "obj": nn.Linear(HIDDEN, 3)})
        if command == "positions":  # where the target is (x, y), and u_dEE from positions alone
            self.heads["goal"] = nn.Linear(HIDDEN, 2)
            self.command_head = nn.Sequential(
                nn.Linear(buffer * 6 + 2, COMMAND_HIDDEN), nn.ReLU(), nn.Linear(COMMAND_HIDDEN, COMMAND_HIDDEN),
                nn.ReLU(), nn.Linear(COMMAND_HIDDEN, COMMAND_HIDDEN), nn.ReLU(), nn.Linear(COMMAND_HIDDEN, 3))

    def set_modes(self, commands, seed: int = 0) -> None:
        """Fit the ``dee_modes`` centres to the scaled commands (..., 3) of the training demonstrations."""
        self.dee_centres.copy_(torch.as_tensor(command_modes(commands, self.dee_modes, seed), dtype=torch.float32))

    @property
    def conditioned(self) -> bool:
        return self.variant != "e2evmc"

    def _encode(self, net: nn.Module, images: torch.Tensor) -> torch.Tensor:
        """(N, 3, S, S) -> (N, C, s, s), channels-last for the CPU's fast convolutions."""
        return net(images.contiguous(memory_format=torch.channels_last))

    def _state(self, maps: list[torch.Tensor], joints: torch.Tensor) -> torch.Tensor:
        """Concatenate feature maps (N, C, s, s) with the tiled joint angles (N, 7); flatten (with
        ``readout="keypoints"``: each map's keypoints, then the joint angles). With ``command="positions"``
        the joint angles are zeros: the network only sees, so its estimate of where the object is
        cannot lean on where the hand is (in the demonstrations the two move together, and in
        closed loop an estimate that follows the hand leads the hand on; the command head gets the
        hand's position instead)."""
        if self.command == "positions":
            joints = torch.zeros_like(joints)
        if self.readout == "keypoints":
            points = [spatial_softmax(m, self.keypoint_temperature.exp()) for m in maps]
            return torch.cat([*points, joints.to(points[0].dtype)], dim=1)
        side = maps[0].shape[-1]
        tiled = joints[:, :, None, None].expand(-1, -1, side, side).to(maps[0].dtype)
        return torch.cat([*maps, tiled], dim=1).flatten(1)

    def forward(self, frames: torch.Tensor, joints: torch.Tensor, target: torch.Tensor | None = None,
                positions: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None) -> dict[str, torch.Tensor]:
        """frames (B, T, 3, S, S) in [0, 1], oldest first; joints (B, T, 7); target (B, 3, S, S).

        Returns each head for the W = T - K + 1 windows ending at frames K-1 .. T-1: (B, W, ...).
        With ``command="positions"`` and the demonstrations' true ``positions`` (hand (B, T, 3), object
        (B, T, 3), target (B, 2), scaled), also ``position_dee`` (B, W, 3): the command head's answer
        for each window from them (how it is trained).
        """
        out = self._heads(frames, joints, target)
        if positions is not None and self.command == "positions":
            out["position_dee"] = self.command_from_positions(*position_windows(*positions, self.buffer))
        return out

    def command_from_positions(self, hand: torch.Tensor, obj: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
        """u_dEE (..., 3) from the hand's and the object's positions over the buffer (..., K, 3) and the
        target's (..., 2), all scaled (``command="positions"``): an MLP, so the command is a function
        of where things are, and the network only has to see where they are."""
        x = torch.cat([torch.stack([hand, obj], dim=-2).flatten(-3), goal], dim=-1)  # per step: hand, object
        with torch.autocast(x.device.type, enabled=False):  # millimetres matter: bf16 keeps ~1 mm at 25 cm
            return self.command_head(x.float())

    def _heads(self, frames: torch.Tensor, joints: torch.Tensor, target: torch.Tensor | None
               ) -> dict[str, torch.Tensor]:
        """The network's heads for every window of the chunk (``forward`` without the command head)."""
        b, t = frames.shape[:2]
        k = self.buffer
        w = t - k + 1
        if w < 1:
            raise ValueError(f"need at least {k} frames, got {t}")
        if self.conditioned and target is None:
            raise ValueError(f"{self.variant} needs a target image")
        if self.variant == "geeco-f":
            last = frames[:, k - 1:].flatten(0, 1)  # the current frame I_t of each window
            windows = frames.unfold(1, k, 1).permute(0, 1, 5, 2, 3, 4).flatten(0, 1)  # (B*W, K, 3, S, S)
            tgt = target[:, None].expand(-1, w, -1, -1, -1).flatten(0, 1)
            pair = torch.stack([last, tgt], dim=1)
            maps = [self._encode(self.obs, last - 0.5), self._encode(self.dyn, dynamic_image(windows)),
                    self._encode(self.diff, dynamic_image(pair))]
            state = self._state(maps, joints[:, k - 1:].flatten(0, 1))[:, None]  # (B*W, 1, state)
        else:
            per_frame = self.frame_states(frames, joints, target)
            state = per_frame.unfold(1, k, 1).permute(0, 1, 3, 2).flatten(0, 1)  # (B*W, K, state)
        return {name: out.view(b, w, *out.shape[1:]) for name, out in self.decide(state).items()}

    def target_code(self, target: torch.Tensor) -> torch.Tensor:
        """GEECO-R's psi_OBS(I_T) of target images (B, 3, S, S): (B, C, s, s)."""
        return self._encode(self.obs, target - 0.5)

    def frame_states(self, frames: torch.Tensor, joints: torch.Tensor, target: torch.Tensor | None,
                     target_code: torch.Tensor | None = None) -> torch.Tensor:
        """D, R, E2EVMC: the state s_j of each frame on its own, (B, T, state): in control each new
        frame is encoded once and kept for the next K - 1 steps. ``target_code``: GEECO-R's
        :meth:`target_code` of ``target`` if already known (in control, once an episode)."""
        b, t = frames.shape[:2]
        flat = frames.flatten(0, 1)  # (B*T, 3, S, S)
        obs = self._encode(self.obs, flat - 0.5)
        maps = [obs]
        if self.variant == "geeco-d":
            tgt = target[:, None].expand(-1, t, -1, -1, -1).flatten(0, 1)
            maps.append(self._encode(self.diff, dynamic_image(torch.stack([flat, tgt], dim=1))))
        elif self.variant == "geeco-r":
            goal = self.target_code(target) if target_code is None else target_code  # (B, C, s, s)
            maps.append(goal.repeat_interleave(t, dim=0) - obs)
        return self._state(maps, joints.flatten(0, 1)).view(b, t, -1)

    def decide(self, state: torch.Tensor) -> dict[str, torch.Tensor]:
        """States (N, steps, state) -> heads (N, ...): the LSTM from a zero state, FC + ReLU, four heads
        (with ``dee_bins``, also ``dee_logits`` (N, 3, bins); with ``dee_modes``, ``mode_logits`` (N, modes)
        and ``mode_offsets`` (N, modes, 3); ``dee`` is read from them)."""
        out, _ = self.lstm(state)
        feature = F.relu(self.fc(out[:, -1]))
        heads = {name: head(feature) for name, head in self.heads.items()}
        if self.dee_bins:
            heads["dee_logits"] = heads["dee"].view(-1, 3, self.dee_bins)
            heads["dee"] = decode_bins(heads["dee_logits"])
        elif self.dee_modes:
            k = self.dee_modes
            heads["mode_logits"] = heads["dee"][:, :k]
            heads["mode_offsets"] = heads["dee"][:, k:].view(-1, k, 3)
            best = heads["mode_logits"].float().argmax(-1)
            rows = torch.arange(len(best), device=best.device)
            heads["dee"] = self.dee_centres[best] + heads["mode_offsets"][rows, best].float()  # centre + its offset
        return heads


def position_windows(hand: torch.Tensor, obj: torch.Tensor, goal: torch.Tensor, buffer: int = BUFFER
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per-step positions of the hand and the object (B, T, 3) and the target's (B, 2) -> the command
    head's inputs for the W = T - K + 1 windows ending at steps K-1 .. T-1: (B, W, K, 3) twice and (B, W, 2)."""
    hand_w, obj_w = (x.unfold(1, buffer, 1).transpose(-1, -2) for x in (hand, obj))
    return hand_w, obj_w, goal[:, None].expand(-1, hand_w.shape[1], -1)


def command_modes(commands, modes: int, seed: int = 0) -> "np.ndarray":
    """k-means (k-means++ start, seeded) over commands (N, 3): the (modes, 3) centres, fewer
    distinct commands than modes repeat some."""
    import numpy as np
    from scipy.cluster.vq import kmeans2

    x = np.asarray(commands, dtype=np.float64).reshape(-1, 3)
    distinct = np.unique(x, axis=0)
    if len(distinct) < modes:  # too few to cluster: every distinct command is a centre
        return distinct[np.arange(modes) % len(distinct)].astype(np.float32)
    centres, _ = kmeans2(x, modes, minit="++", seed=np.random.default_rng(seed))
    return centres.astype(np.float32)


def nearest_mode(values: torch.Tensor, centres: torch.Tensor) -> torch.Tensor:
    """(N, 3) commands -> (N,) index of the nearest centre."""
    return torch.cdist(values.float(), centres.float()).argmin(-1)


def spatial_softmax(maps: torch.Tensor, temperature: torch.Tensor) -> torch.Tensor:
    """(N, C, s, s) -> (N, 2C): per channel, the expected (x, y) in [-1, 1] under a softmax of its
    activations over the map (Levine et al. 2016)."""
    n, c, h, w = maps.shape
    p = torch.softmax(maps.float().flatten(2) / temperature, dim=-1).view(n, c, h, w)
    ys = torch.linspace(-1.0, 1.0, h, device=maps.device)
    xs = torch.linspace(-1.0, 1.0, w, device=maps.device)
    return torch.cat([(p.sum(2) * xs).sum(-1), (p.sum(3) * ys).sum(-1)], dim=1)


def bin_centres(bins: int, device=None) -> torch.Tensor:
    """The values of ``bins`` evenly spaced bins over [-1, 1] (scaled u_dEE)."""
    return torch.linspace(-1.0, 1.0, bins, device=device)


def two_hot(values: torch.Tensor, bins: int) -> torch.Tensor:
    """(...) values -> (..., bins) probabilities on the two bins either side of each value (clipped
    to [-1, 1]), weighted so that their mean is the value."""
    x = (values.float().clamp(-1.0, 1.0) + 1.0) * (bins - 1) / 2  # position in bin units
    low = x.floor().clamp(max=bins - 2)
    upper = x - low  # weight of the bin above
    out = torch.zeros(*values.shape, bins, device=values.device)
    out.scatter_(-1, low.long()[..., None], (1.0 - upper)[..., None])
    out.scatter_add_(-1, low.long()[..., None] + 1, upper[..., None])
    return out


def decode_bins(logits: torch.Tensor) -> torch.Tensor:
    """(..., bins) logits -> (...) values: the mean over the most likely bin and its two neighbours,
    so a two-peaked answer gives one peak's value, not the average of both."""
    bins = logits.shape[-1]
    centres = bin_centres(bins, logits.device)
    best = logits.float().argmax(-1, keepdim=True)
    near = (torch.arange(bins, device=logits.device) - best).abs() <= 1
    p = torch.softmax(logits.float().masked_fill(~near, float("-inf")), dim=-1)
    return (p * centres).sum(-1)


def geeco_loss(out: dict[str, torch.Tensor], batch: dict[str, torch.Tensor], aux_weight: float = 1.0,
               centres: torch.Tensor | None = None) -> tuple[torch.Tensor, dict[str, float]]:
    """Eq. 6.3: MSE(u_dEE) + CCE(u_GRP) + lambda (MSE(q_EE) + MSE(q_OBJ)), averaged over windows;
    with binned u_dEE (``dee_bins``) its cross-entropy takes the MSE's place; with command modes
    (``dee_modes``) the cross-entropy on the nearest of the model's ``centres`` plus the MSE of that
    centre's offset.

    ``batch`` holds the scaled targets ``dee``, ``ee``, ``obj`` (B, W, 3) and ``grip`` (B, W) class ids;
    with ``command="positions"`` also ``goal`` (B, 2), the target's position (MSE with the other positions),
    and the command head's ``position_dee`` in ``out`` adds its MSE to u_dEE's.
    """
    if "dee_logits" in out:  # binned u_dEE: cross-entropy on two-hot targets, per axis
        logits = out["dee_logits"].float().flatten(0, -3)  # (windows, 3, bins)
        target = two_hot(batch["dee"].reshape(-1, 3), logits.shape[-1])
        dee = -(target * F.log_softmax(logits, dim=-1)).sum(-1).mean()
    elif "mode_logits" in out:  # command modes: which centre, then the offset from it
        logits, offsets = out["mode_logits"].float().flatten(0, -2), out["mode_offsets"].float().flatten(0, -3)
        target = batch["dee"].reshape(-1, 3).float()
        mode = nearest_mode(target, centres)
        rows = torch.arange(len(mode), device=mode.device)
        dee = F.cross_entropy(logits, mode) + F.mse_loss(offsets[rows, mode], target - centres[mode])
    else:
        dee = F.mse_loss(out["dee"].float(), batch["dee"])
    grip = F.cross_entropy(out["grip"].float().flatten(0, 1), batch["grip"].flatten().long())
    aux = F.mse_loss(out["ee"].float(), batch["ee"]) + F.mse_loss(out["obj"].float(), batch["obj"])
    if "goal" in out:  # command="positions": where the target is, and the command from true positions
        aux = aux + F.mse_loss(out["goal"].float(), batch["goal"][:, None].expand_as(out["goal"]))
    if "position_dee" in out:
        dee = dee + F.mse_loss(out["position_dee"], batch["dee"])
    total = dee + grip + aux_weight * aux
    return total, {"dee": float(dee.detach()), "grip": float(grip.detach()), "aux": float(aux.detach())}
