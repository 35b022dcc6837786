"""Full-body shading refinement: a MIMO-UNet-style net (Cho et al. 2021) with 4 downsamplings,
so 5 scales, multi-scale inputs and outputs, FAM / SCM / AFF blocks; predicts a residual.

Residual space. Shading is HDR (a sun can be 1e5 x the sky), so the runtime first divides the
coarse shading by one per-image scale (`relightcli.nets.body_refine.shading_scale`: the 95th
percentile over the person / 0.8, as in the evaluation protocol) and the graph works in
log(1 + s) of that normalised shading: residual added there, output = exp(clamp(., 0, 16)) - 1.
Log space keeps the residual's size comparable between shadow and lit regions, and the
clamp keeps the output >= 0 and finite.

Inputs: `coarse_shading` (N, 3, H, W) normalised linear shading >= 0; `ao` (N, 1, H, W) in [0, 1].
Scale k (k = 0..4, size H/2^k) sees [log shading, AO] at k = 0 and AO average-pooled at k >= 1
(the paper's multi-scale input); the residual base at scale k is the pooled coarse shading.
Outputs: `shading` (N, 3, H, W) and `shading_s1`..`shading_s4` (N, 3, H/2^k, W/2^k), the
lower scales used by the multi-scale training loss. H, W divisible by 16.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import nn

from .blocks import ResidualBlock, conv_norm_act, decode_log_shading, encode_log_shading
from .contract import IOContract, image_spec

N_SCALES = 5


@dataclass(frozen=True)
class MIMOConfig:
    width: int = 32  # channels at full scale, doubling per scale up to max_width
    max_width: int = 256
    n_res: int = 8  # residual blocks per encoder / decoder block (MIMO-UNet uses 8)

    def widths(self) -> list[int]:
        return [min(self.width * 2**k, self.max_width) for k in range(N_SCALES)]

    @property
    def multiple(self) -> int:
        return 2 ** (N_SCALES - 1)


BODY_REFINE_CONFIGS = {
    "paper": MIMOConfig(width=32, max_width=256, n_res=8),
    # AFF resamples every encoder level to every scale, so the summed width at full resolution
    # sets the small net's cost: max_width 32 (sum 120 channels) halves the time of 64 (184).
    "small": MIMOConfig(width=8, max_width=32, n_res=1),
}


def res_stack(channels: int, n: int) -> nn.Sequential:
    return nn.Sequential(*[ResidualBlock(channels, norm="none") for _ in range(n)])


class SCM(nn.Module):
    """Shallow convolutional module: features (N, C, h, w) from a downsampled input (N, c_in, h, w)."""

    def __init__(self, c_in: int, channels: int):
        super().__init__()
        self.body = nn.Sequential(
            conv_norm_act(c_in, channels // 4, 3, norm="none"),
            conv_norm_act(channels // 4, channels // 2, 1, norm="none"),
            conv_norm_act(channels // 2, channels // 2, 3, norm="none"),
            conv_norm_act(channels // 2, channels - c_in, 1, norm="none"),
        )
        self.merge = nn.Conv2d(channels, channels, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.merge(torch.cat([x, self.body(x)], dim=1))


class FAM(nn.Module):
    """Feature attention module: encoder features x refined by the SCM features y: x + conv(x * y)."""

    def __init__(self, channels: int):
        super().__init__()
        self.conv = nn.Conv2d(channels, channels, 3, padding=1)

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        return x + self.conv(x * y)


class AFF(nn.Module):
    """Asymmetric feature fusion: all encoder outputs, resampled to one scale, fused by 1x1 + 3x3."""

    def __init__(self, c_in: int, channels: int):
        super().__init__()
        self.body = nn.Sequential(
            conv_norm_act(c_in, channels, 1, norm="none"),
            nn.Conv2d(channels, channels, 3, padding=1),
        )

    def forward(self, feats: list[torch.Tensor], level: int) -> torch.Tensor:
        """body(concat of feats resampled to feats[level]'s size), computed without that concat:
        the 1x1 convolution's share of each level is applied at the coarser of its two sizes
        and only its output resampled (bilinear resampling is linear with weights summing to
        1, so it commutes with a 1x1 convolution and its bias: the same function). At the full
        scale of a 512 crop the concat held 120 channels: the exported net ran 0.78 -> 0.32 s
        on one thread, the process's peak memory 0.74 -> 0.53 GB (issue 50)."""
        size = feats[level].shape[-2:]
        conv, rest = self.body[0][0], self.body[0][1:]
        weights = torch.split(conv.weight, [f.shape[1] for f in feats], dim=1)
        total = conv.bias.view(1, -1, 1, 1)
        for k, (f, weight) in enumerate(zip(feats, weights)):
            if k < level:  # finer: resampled down first
                f = F.interpolate(f, size=size, mode="bilinear", align_corners=False)
            part = F.conv2d(f, weight)
            if k > level:  # coarser: its share resampled up
                part = F.interpolate(part, size=size, mode="bilinear", align_corners=False)
            total = total + part
        return self.body[1:](rest(total))


class BodyRefineNet(nn.Module):
    """(shading, ao) -> refined shading at 5 scales, finest first."""

    family = "body_refine"
    output_names = ("shading",) + tuple(f"shading_s{k}" for k in range(1, N_SCALES))

    def __init__(self, cfg: MIMOConfig = BODY_REFINE_CONFIGS["paper"]):
        super().__init__()
        self.cfg = cfg
        w = cfg.widths()
        self.head = conv_norm_act(4, w[0], 3, norm="none")
        self.down = nn.ModuleList(conv_norm_act(w[k], w[k + 1], 3, stride=2, norm="none")
                                  for k in range(N_SCALES - 1))
        self.scm = nn.ModuleList(SCM(1, w[k]) for k in range(1, N_SCALES))
        self.fam = nn.ModuleList(FAM(w[k]) for k in range(1, N_SCALES))
        self.encoders = nn.ModuleList(res_stack(w[k], cfg.n_res) for k in range(N_SCALES))
        self.aff = nn.ModuleList(AFF(sum(w), w[k]) for k in range(N_SCALES - 1))
        # Decoder at scale k: merge the upsampled coarser features with AFF_k, then residual blocks.
        self.up = nn.ModuleList(conv_norm_act(w[k + 1], w[k], 3, norm="none") for k in range(N_SCALES - 1))
        self.merge = nn.ModuleList(conv_norm_act(2 * w[k], w[k], 1, norm="none") for k in range(N_SCALES - 1))
        self.decoders = nn.ModuleList(res_stack(w[k], cfg.n_res) for k in range(N_SCALES))
        self.outputs = nn.ModuleList(nn.Conv2d(w[k], 3, 3, padding=1) for k in range(N_SCALES))

    def forward(self, coarse_shading: torch.Tensor, ao: torch.Tensor):
        # Multi-scale inputs: pooled linear shading (residual bases) and pooled AO (SCM inputs).
        shadings, aos = [coarse_shading], [ao]
        for _ in range(N_SCALES - 1):
            shadings.append(F.avg_pool2d(shadings[-1], 2))
            aos.append(F.avg_pool2d(aos[-1], 2))
        bases = [encode_log_shading(s) for s in shadings]

        feats = [self.encoders[0](self.head(torch.cat([bases[0], ao], dim=1)))]
        for k in range(1, N_SCALES):
            x = self.fam[k - 1](self.down[k - 1](feats[-1]), self.scm[k - 1](aos[k]))
            feats.append(self.encoders[k](x))

        y = self.decoders[-1](feats[-1])
        residuals = [self.outputs[-1](y)]
        for k in reversed(range(N_SCALES - 1)):
            size = feats[k].shape[-2:]
            y = self.up[k](F.interpolate(y, size=size, mode="bilinear", align_corners=False))
            y = self.merge[k](torch.cat([y, self.aff[k](feats, k)], dim=1))
            y = self.decoders[k](y)
            residuals.insert(0, self.outputs[k](y))
        return tuple(decode_log_shading(b + r) for b, r in zip(bases, residuals))

    def io_contract(self) -> IOContract:
        outputs = [image_spec("shading", 3, "refined shading, normalised linear, >= 0")]
        outputs += [image_spec(f"shading_s{k}", 3, f"refined shading at 1/{2**k} scale") for k in range(1, N_SCALES)]
        return IOContract(
            family=self.family,
            inputs=(
                image_spec("coarse_shading", 3, "coarse ray-traced shading / shading_scale, >= 0"),
                image_spec("ao", 1, "ambient occlusion in [0, 1]"),
            ),
            outputs=tuple(outputs),
            multiple=self.cfg.multiple,
            colour_space="linear sRGB primaries, shading units of DESIGN.md",
            normalisation="shading divided by shading_scale (p95 over mask / 0.8) outside; "
                          "log(1+x) in graph, residual in that space, exp(y)-1 out",
            config=asdict(self.cfg),
        )


def body_refine_net(size: str = "paper") -> BodyRefineNet:
    return BodyRefineNet(BODY_REFINE_CONFIGS[size])
