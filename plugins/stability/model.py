"""Stability predictors: f(x; θ) of Eq. 3.2 (thesis Section 3.4.1).

Every constructor returns a ``torch.nn.Module`` that maps a float image batch ``(N, 3, H, W)``
with values in ``[0, 1]`` to ONE unscaled logit per image, shape ``(N,)`` (the trailing
singleton dimension is squeezed away).  Label convention of the thesis: ``y = 1`` unstable,
``y = 0`` stable, so ``torch.sigmoid(model(x))`` is the predicted probability of *unstable*.
Inputs are normalised inside the model (``(x - 0.5) / 0.5``, i.e. to ``[-1, 1]``, the
Inception preprocessing; all models are trained from scratch, so one convention serves all).

Models (``MODELS`` / ``build(name, **kwargs)``):

- ``"cnn"``  :func:`compact_cnn`   the CPU default, 0.69M parameters, any input ≥ 16 px.
- ``"alexnet"`` :func:`alexnet`    the thesis's baseline, Krizhevsky et al. 2012 (single tower).
- ``"inception-v4"`` :func:`inception_v4`  the thesis's reference model, Szegedy et al. 2017.

Training (Eq. 3.2 and the Inception-v4 solver): :func:`logistic_loss`, :func:`rmsprop_for`.
"""

from __future__ import annotations

from typing import Callable

import torch
import torch.nn.functional as F
from torch import nn

from physint_cli.training import adamw_cosine  # noqa: F401  (the stability presets' solver; it lives in the core)

__all__ = ["MODELS", "build", "compact_cnn", "alexnet", "inception_v4", "rmsprop_for", "logistic_loss",
           "n_params", "Normalize", "adamw_cosine"]


# --------------------------------------------------------------------------------------------
# shared pieces
# --------------------------------------------------------------------------------------------

class Normalize(nn.Module):
    """``[0, 1]`` images → ``(x - mean) / std`` per channel (default: to ``[-1, 1]``)."""

    def __init__(self, mean: float | tuple[float, float, float] = 0.5, std: float | tuple[float, float, float] = 0.5):
        super().__init__()
        self.register_buffer("mean", torch.as_tensor(mean, dtype=torch.float32).reshape(-1, 1, 1).expand(3, 1, 1).clone())
        self.register_buffer("std", torch.as_tensor(std, dtype=torch.float32).reshape(-1, 1, 1).expand(3, 1, 1).clone())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.mean) / self.std


class _Classifier(nn.Module):
    """normalise → features → head → logit ``(N,)``."""

    def __init__(self, features: nn.Module, head: nn.Module, in_size: int, name: str):
        super().__init__()
        self.normalize = Normalize()
        self.features = features
        self.head = head
        self.in_size = in_size
        self.name = name

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.dim() != 4 or x.shape[1] != 3:
            raise ValueError(f"{self.name}: expected a float image batch (N, 3, H, W), got shape {tuple(x.shape)}")
        return self.head(self.features(self.normalize(x))).squeeze(-1)   # f(x; θ), one logit per image


def _init_weights(module: nn.Module) -> None:
    for m in module.modules():
        if isinstance(m, nn.Conv2d):
            nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            if m.bias is not None:
                nn.init.zeros_(m.bias)
        elif isinstance(m, nn.BatchNorm2d):
            nn.init.ones_(m.weight)
            nn.init.zeros_(m.bias)
        elif isinstance(m, nn.Linear):
            nn.init.normal_(m.weight, 0.0, 0.01)
            nn.init.zeros_(m.bias)


def _check_size(name: str, in_size: int, minimum: int) -> None:
    if int(in_size) < minimum:
        raise ValueError(f"{name}: in_size={in_size} is too small; the architecture needs at least {minimum}x{minimum} pixels")


def n_params(model: nn.Module, trainable_only: bool = True) -> int:
    """Number of (trainable) parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad or not trainable_only)


# --------------------------------------------------------------------------------------------
# compact CNN: the CPU default
# --------------------------------------------------------------------------------------------

def _conv_bn_relu(c_in: int, c_out: int, stride: int = 1, pool: bool = False) -> nn.Sequential:
    """3x3 conv → (2x2 max pool) → BN → ReLU.  Pooling right after the convolution gives BN and
    ReLU, memory-bound on a CPU, a quarter of the pixels (ReLU commutes with max pooling)."""
    layers: list[nn.Module] = [nn.Conv2d(c_in, c_out, 3, stride=stride, padding=1, bias=False)]
    if pool:
        layers.append(nn.MaxPool2d(2))
    return nn.Sequential(*layers, nn.BatchNorm2d(c_out), nn.ReLU(inplace=True))


def compact_cnn(in_size: int = 64, width: int = 32, dropout: float = 0.3) -> nn.Module:
    """A small VGG-style CNN for CPU training (the ``tiny``/``small`` presets).

    Four stages of 3x3 conv-BN-ReLU layers (``width``, ``2·width``, ``4·width``, ``4·width``
    channels), each ending in 2x2 max pooling (between its last convolution and that one's BN),
    pooled to a 4x4 grid that is *flattened*, not averaged: stability depends on where the
    objects are relative to each other (Eq. 3.1), and global average pooling, which throws that
    layout away, left an earlier version of this network at chance on ShapeStacks while this one
    learns. Then FC(128)-ReLU and one logit.
    ``width=20`` (the small preset) → 330,917 parameters, ``width=32`` → 688,289. At
    ``in_size >= 128`` the first convolution has stride 2, so the cost and the receptive field
    relative to the image stay about those at 64.
    Output: logits ``(N,)``.
    """
    _check_size("compact_cnn", in_size, 16)
    w = int(width)
    stem_stride = 2 if in_size >= 128 else 1
    features = nn.Sequential(
        _conv_bn_relu(3, w, stem_stride, pool=True),
        _conv_bn_relu(w, 2 * w), _conv_bn_relu(2 * w, 2 * w, pool=True),
        _conv_bn_relu(2 * w, 4 * w), _conv_bn_relu(4 * w, 4 * w, pool=True),
        _conv_bn_relu(4 * w, 4 * w, pool=True),
        nn.AdaptiveAvgPool2d(4), nn.Flatten(),  # keep a coarse 4x4 layout of the scene
    )
    head = nn.Sequential(nn.Dropout(dropout), nn.Linear(4 * w * 16, 128), nn.ReLU(inplace=True),
                         nn.Dropout(dropout), nn.Linear(128, 1))
    model = _Classifier(features, head, in_size, "compact_cnn")
    _init_weights(model)
    return model


# --------------------------------------------------------------------------------------------
# AlexNet (Krizhevsky, Sutskever & Hinton 2012)
# --------------------------------------------------------------------------------------------

def alexnet(in_size: int = 224, dropout: float = 0.5) -> nn.Module:
    """AlexNet, the thesis's baseline, in the standard single-tower form.

    The single-GPU variant of Krizhevsky's "One weird trick" (2014) also used by torchvision and
    tf-slim's ``alexnet_v2``: conv 11x11/4 ×64 → max-pool 3/2 → conv 5x5 ×192 → max-pool 3/2 →
    conv 3x3 ×384, ×256, ×256 → max-pool 3/2 → 6x6 (adaptive) → dropout → FC 4096 → dropout →
    FC 4096 → FC 1.  No local response normalisation (it was dropped in that variant).
    Parameters: 61,100,840 with 1000 ImageNet classes, hence 57,007,937 with our single logit.
    Adaptive average pooling to 6x6 makes any input ≥ 63 px work.  Output: logits ``(N,)``.
    """
    _check_size("alexnet", in_size, 63)
    features = nn.Sequential(
        nn.Conv2d(3, 64, 11, stride=4, padding=2), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2),
        nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2),
        nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(inplace=True),
        nn.Conv2d(384, 256, 3, padding=1), nn.ReLU(inplace=True),
        nn.Conv2d(256, 256, 3, padding=1), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2),
        nn.AdaptiveAvgPool2d(6), nn.Flatten(),
    )
    head = nn.Sequential(
        nn.Dropout(dropout), nn.Linear(256 * 6 * 6, 4096), nn.ReLU(inplace=True),
        nn.Dropout(dropout), nn.Linear(4096, 4096), nn.ReLU(inplace=True),
        nn.Linear(4096, 1),
    )
    model = _Classifier(features, head, in_size, "alexnet")
    _init_weights(model)
    return model


# --------------------------------------------------------------------------------------------
# Inception-v4 (Szegedy, Ioffe, Vanhoucke & Alemi 2017, "Inception-v4, Inception-ResNet and the
# Impact of Residual Connections on Learning"); figure numbers below are the paper's.
# --------------------------------------------------------------------------------------------

class _BasicConv(nn.Module):
    """conv (no bias) → BatchNorm (ε = 0.001, as in the TF reference) → ReLU.  ``padding``: 'valid'
    (0) as the paper's "V" marked layers, otherwise 'same' for odd kernels."""

    def __init__(self, c_in: int, c_out: int, kernel: int | tuple[int, int], stride: int = 1, valid: bool = False):
        super().__init__()
        kh, kw = (kernel, kernel) if isinstance(kernel, int) else kernel
        padding = (0, 0) if valid else (kh // 2, kw // 2)
        self.conv = nn.Conv2d(c_in, c_out, (kh, kw), stride=stride, padding=padding, bias=False)
        self.bn = nn.BatchNorm2d(c_out, eps=1e-3)
        self.out_channels = c_out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.relu(self.bn(self.conv(x)), inplace=True)


class _Branches(nn.Module):
    """Parallel branches concatenated along channels (an Inception block)."""

    def __init__(self, *branches: nn.Module, out_channels: int):
        super().__init__()
        self.branches = nn.ModuleList(branches)
        self.out_channels = out_channels

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.cat([b(x) for b in self.branches], dim=1)


class _AvgPoolSame(nn.Module):
    """3x3 average pooling, stride 1, 'same' padding, padded cells not counted (TF semantics)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.avg_pool2d(x, 3, stride=1, padding=1, count_include_pad=False)


class _MaxPoolValid(nn.Module):
    """3x3 max pooling, stride 2, 'valid' padding; keeps ``out_channels`` = its input's."""

    def __init__(self, channels: int):
        super().__init__()
        self.out_channels = channels

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.max_pool2d(x, 3, stride=2)


class _Stem(nn.Module):
    """Figure 3: 299x299x3 → 35x35x384 (224 → 25x25)."""

    def __init__(self, ch: Callable[[int], int]):
        super().__init__()
        C = _BasicConv
        self.conv1 = C(3, ch(32), 3, stride=2, valid=True)          # 149x149x32
        self.conv2 = C(ch(32), ch(32), 3, valid=True)               # 147x147x32
        self.conv3 = C(ch(32), ch(64), 3)                           # 147x147x64
        self.mix1 = _Branches(_MaxPoolValid(ch(64)),                # 73x73x160
                              C(ch(64), ch(96), 3, stride=2, valid=True), out_channels=ch(64) + ch(96))
        c = self.mix1.out_channels
        self.mix2 = _Branches(                                      # 71x71x192
            nn.Sequential(C(c, ch(64), 1), C(ch(64), ch(96), 3, valid=True)),
            nn.Sequential(C(c, ch(64), 1), C(ch(64), ch(64), (7, 1)), C(ch(64), ch(64), (1, 7)),
                          C(ch(64), ch(96), 3, valid=True)),
            out_channels=2 * ch(96))
        c = self.mix2.out_channels
        self.mix3 = _Branches(C(c, ch(192), 3, stride=2, valid=True), _MaxPoolValid(c),   # 35x35x384
                              out_channels=ch(192) + c)
        self.out_channels = self.mix3.out_channels

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.mix3(self.mix2(self.mix1(self.conv3(self.conv2(self.conv1(x))))))


def _inception_a(c: int, ch: Callable[[int], int]) -> _Branches:
    """Figure 4: the 35x35 grid module, 384 → 384 channels."""
    C = _BasicConv
    return _Branches(
        nn.Sequential(_AvgPoolSame(), C(c, ch(96), 1)),
        C(c, ch(96), 1),
        nn.Sequential(C(c, ch(64), 1), C(ch(64), ch(96), 3)),
        nn.Sequential(C(c, ch(64), 1), C(ch(64), ch(96), 3), C(ch(96), ch(96), 3)),
        out_channels=4 * ch(96))


def _reduction_a(c: int, ch: Callable[[int], int], k: int = 192, l: int = 224, m: int = 256, n: int = 384) -> _Branches:
    """Figure 7 with Table 1's Inception-v4 filter counts k=192, l=224, m=256, n=384: 35 → 17, 384 → 1024."""
    C = _BasicConv
    return _Branches(
        _MaxPoolValid(c),
        C(c, ch(n), 3, stride=2, valid=True),
        nn.Sequential(C(c, ch(k), 1), C(ch(k), ch(l), 3), C(ch(l), ch(m), 3, stride=2, valid=True)),
        out_channels=c + ch(n) + ch(m))


def _inception_b(c: int, ch: Callable[[int], int]) -> _Branches:
    """Figure 5: the 17x17 grid module, 1024 → 1024 channels."""
    C = _BasicConv
    return _Branches(
        nn.Sequential(_AvgPoolSame(), C(c, ch(128), 1)),
        C(c, ch(384), 1),
        nn.Sequential(C(c, ch(192), 1), C(ch(192), ch(224), (1, 7)), C(ch(224), ch(256), (7, 1))),
        nn.Sequential(C(c, ch(192), 1), C(ch(192), ch(192), (1, 7)), C(ch(192), ch(224), (7, 1)),
                      C(ch(224), ch(224), (1, 7)), C(ch(224), ch(256), (7, 1))),
        out_channels=ch(128) + ch(384) + 2 * ch(256))


def _reduction_b(c: int, ch: Callable[[int], int]) -> _Branches:
    """Figure 8: 17 → 8, 1024 → 1536 channels."""
    C = _BasicConv
    return _Branches(
        _MaxPoolValid(c),
        nn.Sequential(C(c, ch(192), 1), C(ch(192), ch(192), 3, stride=2, valid=True)),
        nn.Sequential(C(c, ch(256), 1), C(ch(256), ch(256), (1, 7)), C(ch(256), ch(320), (7, 1)),
                      C(ch(320), ch(320), 3, stride=2, valid=True)),
        out_channels=c + ch(192) + ch(320))


class _InceptionC(nn.Module):
    """Figure 6: the 8x8 grid module, 1536 → 1536 channels (the 1x3 / 3x1 splits are concatenated)."""

    def __init__(self, c: int, ch: Callable[[int], int]):
        super().__init__()
        C = _BasicConv
        self.b0 = nn.Sequential(_AvgPoolSame(), C(c, ch(256), 1))
        self.b1 = C(c, ch(256), 1)
        self.b2 = C(c, ch(384), 1)
        self.b2_1x3, self.b2_3x1 = C(ch(384), ch(256), (1, 3)), C(ch(384), ch(256), (3, 1))
        self.b3 = nn.Sequential(C(c, ch(384), 1), C(ch(384), ch(448), (1, 3)), C(ch(448), ch(512), (3, 1)))
        self.b3_3x1, self.b3_1x3 = C(ch(512), ch(256), (3, 1)), C(ch(512), ch(256), (1, 3))
        self.out_channels = 6 * ch(256)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b2, b3 = self.b2(x), self.b3(x)
        return torch.cat([self.b0(x), self.b1(x), self.b2_1x3(b2), self.b2_3x1(b2),
                          self.b3_3x1(b3), self.b3_1x3(b3)], dim=1)


def inception_v4(in_size: int = 224, dropout: float = 0.2, width_multiplier: float = 1.0) -> nn.Module:
    """Inception-v4 (Szegedy et al. 2017, Figure 9), the thesis's reference stability predictor.

    stem (Fig. 3) → 4 × Inception-A (Fig. 4) → Reduction-A (Fig. 7; k, l, m, n = 192, 224, 256,
    384) → 7 × Inception-B (Fig. 5) → Reduction-B (Fig. 8) → 3 × Inception-C (Fig. 6) → average
    pooling → dropout (keep 0.8, i.e. ``dropout=0.2``) → linear → one logit.  Filter counts as in
    the paper; every convolution is conv → BatchNorm → ReLU as in the reference implementation.
    The paper's input is 299x299 (8x8 final grid); the thesis uses 224x224 (5x5 final grid), which
    works because the last pooling is adaptive; the architecture needs at least 75x75.
    Parameters: 41,144,353 at ``width_multiplier=1`` (the 1000-class model's 42,679,816 less
    the 1536x999 weights and 999 biases of the other classes).  ``width_multiplier`` scales every filter count (rounded, ≥ 1) for thin
    versions in tests and on CPUs.  Output: logits ``(N,)``.
    """
    _check_size("inception_v4", in_size, 75)
    if width_multiplier <= 0:
        raise ValueError(f"inception_v4: width_multiplier must be > 0, got {width_multiplier}")

    def ch(c: int) -> int:
        return max(1, int(round(c * width_multiplier)))

    stem = _Stem(ch)
    layers: list[nn.Module] = [stem]
    c = stem.out_channels
    for _ in range(4):
        layers.append(_inception_a(c, ch)); c = layers[-1].out_channels
    layers.append(_reduction_a(c, ch)); c = layers[-1].out_channels
    for _ in range(7):
        layers.append(_inception_b(c, ch)); c = layers[-1].out_channels
    layers.append(_reduction_b(c, ch)); c = layers[-1].out_channels
    for _ in range(3):
        layers.append(_InceptionC(c, ch)); c = layers[-1].out_channels
    features = nn.Sequential(*layers, nn.AdaptiveAvgPool2d(1), nn.Flatten())
    head = nn.Sequential(nn.Dropout(dropout), nn.Linear(c, 1))
    model = _Classifier(features, head, in_size, "inception_v4")
    _init_weights(model)
    return model


# --------------------------------------------------------------------------------------------
# registry
# --------------------------------------------------------------------------------------------

MODELS: dict[str, Callable[..., nn.Module]] = {"cnn": compact_cnn, "alexnet": alexnet, "inception-v4": inception_v4}


def build(name: str, **kwargs) -> nn.Module:
    """``MODELS[name](**kwargs)``; an unknown name raises ``ValueError`` listing the known ones."""
    try:
        constructor = MODELS[name]
    except KeyError:
        raise ValueError(f"unknown stability model {name!r}; choose from {', '.join(MODELS)}") from None
    return constructor(**kwargs)


# --------------------------------------------------------------------------------------------
# training: Eq. 3.2 and the solver of Szegedy et al. 2017
# --------------------------------------------------------------------------------------------

# Inception-v4 paper, Section 4 ("Training Methodology"): "our best models were achieved using
# RMSProp with decay of 0.9 and ε = 1.0. We used a learning rate of 0.045, decayed every two
# epochs using an exponential rate of 0.94."  The thesis (Section 3.4.1) trains both AlexNet and
# Inception-v4 with these solver hyper-parameters for 80 epochs.
PAPER_SOLVER = {"lr": 0.045, "alpha": 0.9, "eps": 1.0, "momentum": 0.0, "epochs_per_decay": 2, "decay_rate": 0.94}
# CPU default (not from the paper): the paper's lr assumes 20 replicas x batch 32 and long runs; a
# small model trained for minutes on one CPU converges better with lr 1e-3 and a small ε.
CPU_SOLVER = {"lr": 1e-3, "alpha": 0.9, "eps": 1e-6, "momentum": 0.0, "epochs_per_decay": 2, "decay_rate": 0.94}


def rmsprop_for(model: nn.Module, paper: bool = True, *, lr: float | None = None, steps_per_epoch: int = 1,
                weight_decay: float = 0.0) -> tuple[torch.optim.RMSprop, torch.optim.lr_scheduler.StepLR]:
    """RMSProp and its exponential step decay: ``(optimizer, scheduler)``.

    ``paper=True``: the Inception-v4 solver (``PAPER_SOLVER``): lr 0.045, decay (torch's
    ``alpha``) 0.9, ε 1.0, lr × 0.94 every two epochs.  The paper states no momentum, so none
    (tf-slim's training script defaults to momentum 0.9 — pass your own optimizer for that).
    Note: TensorFlow adds ε inside the square root (``sqrt(ms + ε)``), torch outside
    (``sqrt(ms) + ε``); with ε = 1 and ``ms ≪ 1`` both give steps ≈ lr·g.
    ``paper=False``: ``CPU_SOLVER`` (lr 1e-3, ε 1e-6, same decay schedule).  ``lr`` overrides
    the learning rate.

    The scheduler is a ``StepLR(step_size=2 · steps_per_epoch, gamma=0.94)``: call
    ``scheduler.step()`` once per epoch (default ``steps_per_epoch=1``), or after every optimiser
    step if you pass the number of steps per epoch.
    """
    s = PAPER_SOLVER if paper else CPU_SOLVER
    opt = torch.optim.RMSprop(model.parameters(), lr=s["lr"] if lr is None else lr, alpha=s["alpha"], eps=s["eps"],
                              momentum=s["momentum"], weight_decay=weight_decay)
    sched = torch.optim.lr_scheduler.StepLR(opt, step_size=s["epochs_per_decay"] * max(1, int(steps_per_epoch)),
                                            gamma=s["decay_rate"])
    return opt, sched


def logistic_loss(logits: torch.Tensor, labels: torch.Tensor, reduction: str = "mean") -> torch.Tensor:
    """Eq. 3.2: L(θ; D) = -Σ y log σ(f(x; θ)) + (1 - y) log(1 - σ(f(x; θ))), labels 1 = unstable.

    ``reduction="sum"`` is Eq. 3.2 exactly; the default ``"mean"`` divides it by the batch size.
    """
    # Eq. 3.2 (binary cross-entropy on the unscaled logits f(x; θ))
    return F.binary_cross_entropy_with_logits(logits.reshape(-1), labels.reshape(-1).to(logits.dtype), reduction=reduction)
