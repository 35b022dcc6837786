"""Building blocks shared by the net families: conv + norm + activation, residual blocks,
and the in-graph encodings of linear-light inputs.

Every block keeps the spatial size unless it says otherwise, so a net's only size constraint is
the number of stride-2 steps it takes (its `multiple`).
"""

from __future__ import annotations

import torch
from torch import nn

# Inputs arrive in linear light; nets see a perceptual encoding computed inside the graph so the
# runtime has nothing to get wrong. 1/2.2 is close to sRGB and has a cheap, exportable form.
DISPLAY_GAMMA = 2.2
# Clamping log(1 + x) at 0 keeps a negative residual from producing negative shading.
LOG_SHADING_MAX = 16.0  # exp(16) - 1 ~ 8.9e6: far beyond any normalised shading


def encode_display(x: torch.Tensor) -> torch.Tensor:
    """Linear RGB in [0, 1] (values outside are clipped) -> gamma-encoded, centred on 0, in [-1, 1]."""
    return x.clamp(1e-6, 1.0).pow(1.0 / DISPLAY_GAMMA) * 2.0 - 1.0


def encode_log_shading(x: torch.Tensor) -> torch.Tensor:
    """Non-negative linear shading (normalised by its per-image scale) -> log(1 + x).
    Written as log(1 + x) and exp(y) - 1 (not log1p / expm1) because the ONNX exporter has no
    expm1; in fp32 the difference is below 1e-7 absolute."""
    return torch.log(1.0 + x.clamp_min(0.0))


def decode_log_shading(y: torch.Tensor) -> torch.Tensor:
    """Inverse of `encode_log_shading`, clamped so the result is >= 0 and finite."""
    return torch.exp(y.clamp(0.0, LOG_SHADING_MAX)) - 1.0


def conv_norm_act(
    c_in: int,
    c_out: int,
    kernel: int = 3,
    stride: int = 1,
    act: str = "relu",
    norm: str = "batch",
    order: str = "norm_act",
) -> nn.Sequential:
    """Conv (same padding) followed by norm and activation; `order="act_norm"` puts the activation
    first (the face U-Net of the supplement: conv + LeakyReLU + BatchNorm)."""
    layers: list[nn.Module] = [
        nn.Conv2d(c_in, c_out, kernel, stride=stride, padding=kernel // 2, bias=norm == "none")
    ]
    norm_layer = make_norm(norm, c_out)
    act_layer = make_act(act)
    layers += [norm_layer, act_layer] if order == "norm_act" else [act_layer, norm_layer]
    return nn.Sequential(*layers)


def make_norm(kind: str, channels: int) -> nn.Module:
    if kind == "batch":
        return nn.BatchNorm2d(channels)
    if kind == "instance":
        return nn.InstanceNorm2d(channels, affine=True)
    if kind == "none":
        return nn.Identity()
    raise ValueError(f"unknown norm {kind!r}: use 'batch', 'instance' or 'none'")


def make_act(kind: str) -> nn.Module:
    if kind == "relu":
        return nn.ReLU(inplace=True)
    if kind == "leaky":
        return nn.LeakyReLU(0.2, inplace=True)
    if kind == "none":
        return nn.Identity()
    raise ValueError(f"unknown activation {kind!r}: use 'relu', 'leaky' or 'none'")


class ResidualBlock(nn.Module):
    """x + conv(act(norm(conv(x)))): two 3x3 convs, same width, no activation after the sum
    (pix2pixHD / EDSR style, keeps the identity path clean)."""

    def __init__(self, channels: int, act: str = "relu", norm: str = "batch", order: str = "norm_act"):
        super().__init__()
        self.body = nn.Sequential(
            conv_norm_act(channels, channels, 3, act=act, norm=norm, order=order),
            nn.Conv2d(channels, channels, 3, padding=1, bias=norm == "none"),
            make_norm(norm, channels),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.body(x)


def count_parameters(net: nn.Module) -> int:
    return sum(p.numel() for p in net.parameters())
