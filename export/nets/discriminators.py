"""Discriminators for adversarial training (never exported to ONNX).

- `MultiscalePatchGAN`: pix2pixHD's multi-scale PatchGAN for the body refinement: `n_scales`
  PatchGANs (4x4 convs, stride 2, LeakyReLU 0.2, instance norm) on the input pooled by 1, 2, 4..;
  conditional: it sees [condition, shading] concatenated.
- `LSGANDiscriminator`: the LSGAN (Mao et al. 2017) discriminator for the face: 5x5 stride-2
  convs 64-128-256-512 with BatchNorm (not on the first), LeakyReLU 0.2, and a linear layer to
  one unbounded score (least-squares loss, no sigmoid). Fixed input size (128x128).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from .blocks import make_norm


@dataclass(frozen=True)
class PatchGANConfig:
    width: int = 64
    n_layers: int = 3
    n_scales: int = 3
    norm: str = "instance"


PATCHGAN_CONFIGS = {
    "paper": PatchGANConfig(),
    "small": PatchGANConfig(width=16, n_layers=3, n_scales=3),
}


class PatchGAN(nn.Module):
    """(N, C, H, W) -> (N, 1, ~H/2^n_layers, ~W/2^n_layers) real/fake logits per patch."""

    def __init__(self, c_in: int, cfg: PatchGANConfig):
        super().__init__()
        layers: list[nn.Module] = [nn.Conv2d(c_in, cfg.width, 4, stride=2, padding=2), nn.LeakyReLU(0.2, True)]
        c = cfg.width
        for k in range(1, cfg.n_layers + 1):
            c_next = min(c * 2, 512)
            stride = 2 if k < cfg.n_layers else 1
            layers += [nn.Conv2d(c, c_next, 4, stride=stride, padding=2), make_norm(cfg.norm, c_next),
                       nn.LeakyReLU(0.2, True)]
            c = c_next
        layers.append(nn.Conv2d(c, 1, 4, stride=1, padding=2))
        self.body = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.body(x)


class MultiscalePatchGAN(nn.Module):
    """Returns one logit map per scale, finest first."""

    def __init__(self, c_in: int, cfg: PatchGANConfig = PATCHGAN_CONFIGS["paper"]):
        super().__init__()
        self.nets = nn.ModuleList(PatchGAN(c_in, cfg) for _ in range(cfg.n_scales))

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        out = []
        for k, net in enumerate(self.nets):
            if k > 0:
                x = F.avg_pool2d(x, 3, stride=2, padding=1, count_include_pad=False)
            out.append(net(x))
        return out


@dataclass(frozen=True)
class LSGANConfig:
    widths: tuple = (64, 128, 256, 512)
    input_size: int = 128


LSGAN_CONFIGS = {
    "paper": LSGANConfig(),
    "small": LSGANConfig(widths=(16, 32, 64, 64)),
}


class LSGANDiscriminator(nn.Module):
    """(N, C, S, S) with S = cfg.input_size -> (N, 1) least-squares score."""

    def __init__(self, c_in: int, cfg: LSGANConfig = LSGAN_CONFIGS["paper"]):
        super().__init__()
        self.cfg = cfg
        layers: list[nn.Module] = []
        c = c_in
        for k, w in enumerate(cfg.widths):
            layers += [nn.Conv2d(c, w, 5, stride=2, padding=2),
                       nn.Identity() if k == 0 else nn.BatchNorm2d(w), nn.LeakyReLU(0.2, True)]
            c = w
        self.body = nn.Sequential(*layers)
        side = cfg.input_size // 2 ** len(cfg.widths)
        self.fc = nn.Linear(c * side * side, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[-1] != self.cfg.input_size or x.shape[-2] != self.cfg.input_size:
            raise ValueError(f"LSGAN discriminator expects {self.cfg.input_size}x{self.cfg.input_size}, "
                             f"got {tuple(x.shape[-2:])}")
        return self.fc(self.body(x).flatten(1))
