"""Face shading refinement: the 128x128 U-Net of the supplement; predicts a residual.

Encoder 64-128-256-512 (7x7 first conv, then stride-2 3x3 convs), a 512 bottleneck with 3
residual blocks, decoder 256-128-64-64 (bilinear x2 + 3x3 conv, U-Net concatenation of the
encoder level), 7x7 last conv. Every conv is conv + LeakyReLU(0.2) + BatchNorm, in that order
(as the supplement lists it), followed by one residual block.

Inputs: `body_shading` (N, 3, H, W), the face crop of the refined body shading, and
`face_shading` (N, 3, H, W), the coarse ray-traced face shading, both linear and divided by the
same per-image `shading_scale` as the body net. Output: `shading` (N, 3, H, W) =
exp(log(1 + body_shading) + residual) - 1, clamped >= 0. Trained at 128x128; H, W divisible by 8.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import nn

from .blocks import ResidualBlock, conv_norm_act, decode_log_shading, encode_log_shading
from .contract import IOContract, image_spec

FACE_SIZE = 128


@dataclass(frozen=True)
class FaceUNetConfig:
    encoder: tuple = (64, 128, 256, 512)
    decoder: tuple = (256, 128, 64, 64)
    n_bottleneck: int = 3

    @property
    def multiple(self) -> int:
        return 2 ** (len(self.encoder) - 1)


FACE_REFINE_CONFIGS = {
    "paper": FaceUNetConfig(),
    "small": FaceUNetConfig(encoder=(16, 32, 64, 64), decoder=(64, 32, 16, 16), n_bottleneck=2),
}


def conv_block(c_in: int, c_out: int, kernel: int = 3, stride: int = 1) -> nn.Sequential:
    """conv + LeakyReLU + BatchNorm, then a residual block in the same style."""
    return nn.Sequential(
        conv_norm_act(c_in, c_out, kernel, stride=stride, act="leaky", order="act_norm"),
        ResidualBlock(c_out, act="leaky", order="act_norm"),
    )


class FaceRefineNet(nn.Module):
    """(body_shading, face_shading) -> refined face shading (N, 3, H, W)."""

    family = "face_refine"
    output_names = ("shading",)

    def __init__(self, cfg: FaceUNetConfig = FACE_REFINE_CONFIGS["paper"]):
        super().__init__()
        self.cfg = cfg
        enc, dec = cfg.encoder, cfg.decoder
        if len(dec) != len(enc):
            raise ValueError(f"decoder needs {len(enc)} widths, got {dec}")
        self.encoders = nn.ModuleList(
            [conv_block(6, enc[0], 7)] + [conv_block(enc[k - 1], enc[k], 3, stride=2) for k in range(1, len(enc))]
        )
        self.bottleneck = nn.Sequential(
            *[ResidualBlock(enc[-1], act="leaky", order="act_norm") for _ in range(cfg.n_bottleneck)]
        )
        # Decoder step k upsamples (except the last, at full resolution) and concatenates the skip.
        self.decoders = nn.ModuleList()
        c = enc[-1]
        for k in range(len(dec) - 1):
            skip = enc[len(enc) - 2 - k]
            self.decoders.append(conv_block(c + skip, dec[k], 3))
            c = dec[k]
        self.last_block = conv_block(c, dec[-1], 3)
        self.out = nn.Conv2d(dec[-1], 3, 7, padding=3)

    def forward(self, body_shading: torch.Tensor, face_shading: torch.Tensor) -> torch.Tensor:
        base = encode_log_shading(body_shading)
        x = torch.cat([base, encode_log_shading(face_shading)], dim=1)
        skips = []
        for encoder in self.encoders:
            x = encoder(x)
            skips.append(x)
        y = self.bottleneck(skips.pop())
        for decoder in self.decoders:
            skip = skips.pop()
            y = F.interpolate(y, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            y = decoder(torch.cat([y, skip], dim=1))
        return decode_log_shading(base + self.out(self.last_block(y)))

    def io_contract(self) -> IOContract:
        return IOContract(
            family=self.family,
            inputs=(
                image_spec("body_shading", 3, "face crop of the refined body shading / shading_scale"),
                image_spec("face_shading", 3, "coarse face shading / the same shading_scale"),
            ),
            outputs=(image_spec("shading", 3, "refined face shading, normalised linear, >= 0"),),
            multiple=self.cfg.multiple,
            colour_space="linear sRGB primaries, shading units of DESIGN.md",
            normalisation="both divided by shading_scale outside; log(1+x) in graph, residual "
                          f"added to log(1+body_shading); trained at {FACE_SIZE}x{FACE_SIZE}",
            config=asdict(self.cfg),
        )


def face_refine_net(size: str = "paper") -> FaceRefineNet:
    return FaceRefineNet(FACE_REFINE_CONFIGS[size])
