"""FID and FVD on the published feature networks, when the user has their weights locally (nothing is downloaded).

Both networks are TorchScript archives, loaded with ``torch.jit.load`` and called the way their publishers'
metric code calls them:

* ``INCEPTION`` (FID, Heusel et al. 2017): NVlabs' ``inception-2015-12-05.pt``, the TensorFlow FID Inception
  as StyleGAN2-ADA's metrics use it: ``net(uint8 images (N, 3, H, W), return_features=True)`` -> (N, 2048);
  it resizes to 299 px itself.
* ``I3D`` (FVD, Unterthiner et al. 2018): the Kinetics-400 I3D ``i3d_torchscript.pt`` as StyleGAN-V's FVD uses
  it: ``net(clips in [-1, 1] (N, 3, T, H, W), rescale=False, resize=True, return_features=True)`` -> (N, 400).

A missing file, a file that is not TorchScript, or a network that does not answer that call with one feature
row per input exits 2 with one line, checked on two real inputs before anything is trained or generated.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from physint_cli.errors import BadInput


@dataclass(frozen=True)
class PublishedNet:
    metric: str  # FID or FVD
    key: str  # the config key that names the file
    example: str  # the file a user would pass
    video: bool
    kwargs: dict = field(default_factory=dict)

    def open(self, path: str, probe: torch.Tensor) -> FeatureNet:
        """The network at ``path``, checked on ``probe`` (two real images or clips)."""
        file = Path(path).expanduser()
        if not file.is_file():
            raise BadInput(f"{self.key}: no file at {path} (pass a local {self.example}; nothing is downloaded)")
        try:
            with warnings.catch_warnings():  # torch 2.13 deprecates TorchScript; the published networks are TorchScript
                warnings.simplefilter("ignore", DeprecationWarning)
                module = torch.jit.load(str(file), map_location="cpu").eval()
        except Exception as exc:  # torch raises RuntimeError or ValueError for a non-archive
            raise BadInput(f"{self.key}: {path} is not a TorchScript network like {self.example} "
                           f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None
        net = FeatureNet(self, module, path)
        net.features(probe[:2])
        return net


@dataclass
class FeatureNet:
    spec: PublishedNet
    module: torch.jit.ScriptModule
    path: str

    def inputs(self, x: torch.Tensor) -> torch.Tensor:
        """Images (N, 3, H, W) or clips (N, T, 3, H, W), uint8 or float in [-1, 1], as the network takes them."""
        if self.spec.video:
            x = x.float() / 127.5 - 1 if x.dtype == torch.uint8 else x.float()
            return x.permute(0, 2, 1, 3, 4).contiguous()  # (N, 3, T, H, W)
        return x if x.dtype == torch.uint8 else ((x.clamp(-1, 1) + 1) * 127.5).round().to(torch.uint8)

    @torch.no_grad()
    def features(self, x: torch.Tensor, batch: int = 32) -> np.ndarray:
        out = []
        for start in range(0, len(x), batch):
            chunk = self.inputs(x[start:start + batch])
            try:
                f = self.module(chunk, **self.spec.kwargs)
            except Exception as exc:
                raise BadInput(f"{self.spec.key}: {self.path} does not take the call {self.spec.example} takes "
                               f"({str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__})"
                               ) from None
            if not (isinstance(f, torch.Tensor) and f.ndim == 2 and len(f) == len(chunk)):
                shape = tuple(f.shape) if isinstance(f, torch.Tensor) else type(f).__name__
                raise BadInput(f"{self.spec.key}: {self.path} answers {shape} for {len(chunk)} inputs, not one feature "
                               f"row each: it is not the network {self.spec.metric} needs ({self.spec.example})")
            out.append(f.float().numpy())
        return np.concatenate(out).astype(np.float64)


INCEPTION = PublishedNet("FID", "eval.inception", "inception-2015-12-05.pt (NVlabs' TorchScript FID Inception)",
                         video=False, kwargs={"return_features": True})
I3D = PublishedNet("FVD", "eval.i3d", "i3d_torchscript.pt (the Kinetics-400 TorchScript I3D of StyleGAN-V's FVD)",
                   video=True, kwargs={"rescale": False, "resize": True, "return_features": True})
