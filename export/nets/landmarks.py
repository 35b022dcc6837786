"""Face landmarks: a 128x128 face crop -> the 68 iBUG-order landmarks in its pixels.

Two heads on one small convolutional encoder (stride-2 3x3 conv + residual block per level,
widths `widths`, down to 4x4):
- "heatmap" (the shipped one): a light U-Net decoder back to stride 4 (32x32 for a 128 crop),
  one logit map per landmark, and a soft-argmax: the softmax over the map's cells weights the
  cells' pixel coordinates, so the output is a differentiable expected position with
  sub-pixel resolution, and the net stays translation-equivariant;
- "regression": the 4x4 features -> two linear layers -> 136 offsets from the crop's centre
  (kept for the comparison in the model card).

Input `image` (N, 3, 128, 128): the face crop, linear RGB in [0, 1] (the runtime's own
values). In the graph: clip, gamma 1/2.2, then each image standardised to zero mean and unit
deviation (exposure and contrast vary a lot between photos). Output `landmarks` (N, 68, 2)
float32: (col, row) in pixels of the input, pixel (i, j)'s centre at (j, i) (DESIGN.md).
The size is fixed: the landmarks are in the crop's pixels and the net learned one framing.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import nn

from .blocks import ResidualBlock, conv_norm_act, encode_display
from .contract import IOContract, TensorSpec, image_spec

CROP = 128
N_LANDMARKS = 68


@dataclass(frozen=True)
class LandmarkConfig:
    widths: tuple = (16, 32, 64, 96, 96)    # levels at strides 2, 4, 8, 16, 32
    head: str = "heatmap"                    # "heatmap" (soft-argmax) or "regression"
    heatmap_stride: int = 4
    hidden: int = 256                        # regression head only

    @property
    def multiple(self) -> int:
        return 2 ** len(self.widths)


LANDMARK_CONFIGS = {
    "small": LandmarkConfig(),
    "regression_small": LandmarkConfig(head="regression"),
}


def standardise(x: torch.Tensor) -> torch.Tensor:
    """Per image: gamma-encode, then zero mean and unit standard deviation over all pixels."""
    x = encode_display(x)
    mean = x.mean(dim=(1, 2, 3), keepdim=True)
    std = (x - mean).pow(2).mean(dim=(1, 2, 3), keepdim=True).add(1e-4).sqrt()
    return (x - mean) / std


def soft_argmax(logits: torch.Tensor, stride: int) -> torch.Tensor:
    """(N, L, h, w) logits -> (N, L, 2) expected (col, row) in input pixels: cell (a, b)
    covers input pixels [b s, (b + 1) s) x [a s, (a + 1) s), its centre at b s + (s - 1) / 2."""
    n, count, h, w = logits.shape
    weights = torch.softmax(logits.reshape(n, count, h * w), dim=-1).reshape(n, count, h, w)
    cols = torch.arange(w, dtype=logits.dtype, device=logits.device) * stride + (stride - 1) / 2.0
    rows = torch.arange(h, dtype=logits.dtype, device=logits.device) * stride + (stride - 1) / 2.0
    col = (weights.sum(dim=2) * cols).sum(dim=-1)
    row = (weights.sum(dim=3) * rows).sum(dim=-1)
    return torch.stack([col, row], dim=-1)


def level(c_in: int, c_out: int) -> nn.Sequential:
    """Stride-2 conv + BN + ReLU, then a residual block: one encoder level."""
    return nn.Sequential(conv_norm_act(c_in, c_out, 3, stride=2), ResidualBlock(c_out))


class LandmarkNet(nn.Module):
    """image (N, 3, 128, 128) linear RGB -> landmarks (N, 68, 2) (col, row) pixels."""

    family = "landmarks"
    output_names = ("landmarks",)

    def __init__(self, cfg: LandmarkConfig = LANDMARK_CONFIGS["small"]):
        super().__init__()
        if cfg.head not in ("heatmap", "regression"):
            raise ValueError(f"unknown landmark head {cfg.head!r}")
        self.cfg = cfg
        widths = (3,) + tuple(cfg.widths)
        self.encoder = nn.ModuleList(level(a, b) for a, b in zip(widths[:-1], widths[1:]))
        if cfg.head == "heatmap":
            # Decoder from the deepest level up to the heatmap level (stride 2 ** (k + 1) is
            # encoder level k), concatenating that level's features at each step
            self.heatmap_level = cfg.heatmap_stride.bit_length() - 2
            ups, channels = [], cfg.widths[-1]
            for skip in reversed(cfg.widths[self.heatmap_level:-1]):
                ups.append(conv_norm_act(channels + skip, skip, 3))
                channels = skip
            self.decoder = nn.ModuleList(ups)
            self.head = nn.Conv2d(channels, N_LANDMARKS, 1)
        else:
            self.head = nn.Sequential(nn.Flatten(), nn.Linear(cfg.widths[-1] * (CROP // cfg.multiple) ** 2,
                                                              cfg.hidden),
                                      nn.ReLU(inplace=True), nn.Linear(cfg.hidden, 2 * N_LANDMARKS))

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        x = standardise(image)
        features = []
        for module in self.encoder:
            x = module(x)
            features.append(x)
        if self.cfg.head == "regression":
            return (CROP - 1) / 2.0 + self.head(x).reshape(-1, N_LANDMARKS, 2)
        skips = features[self.heatmap_level:-1][::-1]
        for conv, skip in zip(self.decoder, skips):
            x = F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            x = conv(torch.cat([x, skip], dim=1))
        return soft_argmax(self.head(x), self.cfg.heatmap_stride)

    def io_contract(self) -> IOContract:
        return IOContract(
            family=self.family,
            inputs=(image_spec("image", 3, "face crop, linear RGB in [0, 1]", h=CROP, w=CROP),),
            outputs=(TensorSpec("landmarks", ("N", N_LANDMARKS, 2), "float32",
                                "68 iBUG landmarks, (col, row) pixels of the crop, "
                                "pixel (i, j)'s centre at (j, i)"),),
            multiple=self.cfg.multiple,
            colour_space="linear sRGB primaries",
            normalisation="clip to [0,1], x**(1/2.2)*2-1, then per-image standardisation, inside the graph",
            dynamic_hw=False,
            config=asdict(self.cfg),
        )
