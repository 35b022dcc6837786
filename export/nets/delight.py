"""De-lighting net: the modified HRNet of the paper's supplement, [image, normal] -> albedo + light.

Modifications to HRNet (supplement), as implemented here:
- the first stage runs at stride 1 (no stride-4 stem) and its conv blocks have no residual
  ("skip") connections;
- 6 stages; stage s >= 2 has s parallel branches, the new one at half the resolution of the
  previous lowest; modules per stage [1, 2, 2, 2, 2] for stages 2..6; 2 blocks per branch;
- lower branches are upsampled bilinearly in the fusion;
- albedo = sigmoid(1x1 conv) of the highest-resolution branch of the last stage (no HRNetV2
  concatenation of all branches);
- light = a 16x32 lat-long RGB map from the lowest branch: conv, global average pool, linear
  layer to a log-radiance map, exp (clamped to [-20, 16] in log space) so it is non-negative.
The ablations of the paper are configs: `vanilla` (stride-4 stem, residual first stage,
4 stages [1, 4, 3], albedo upsampled x4), `five_stage`, and `unet` (the geometry U-Net backbone).

Inputs: `image` (N, 3, H, W) linear RGB in [0, 1]; `normal` (N, 3, H, W) unit normals
(camera frame), 0 outside the person. H, W divisible by `multiple` (32 for the paper config).
Outputs: `albedo` (N, 3, H, W) in [0, 1], linear; `light` (N, 3, 16, 32) linear radiance,
equirectangular per DESIGN.md, in the exposure units of the input image.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import nn

from .blocks import conv_norm_act, encode_display, make_norm
from .contract import IOContract, image_spec
from .geometry import UNetBackbone, UNetConfig

LIGHT_HEIGHT, LIGHT_WIDTH = 16, 32
LOG_LIGHT_RANGE = (-20.0, 16.0)


@dataclass(frozen=True)
class HRNetConfig:
    backbone: str = "hrnet"  # "hrnet" or "unet" (ablation)
    stem_stride: int = 1  # 1 (paper) or 4 (vanilla HRNet)
    first_stage_residual: bool = False  # paper: no skip connections in the first stage
    first_stage_blocks: int = 2
    widths: tuple = (32, 64, 128, 256, 256, 256)  # one per branch; len = number of stages
    modules: tuple = (1, 2, 2, 2, 2)  # HR modules in stages 2..len(widths)
    blocks: int = 2  # basic blocks per branch per module
    light_width: int = 64
    unet: UNetConfig | None = None

    @property
    def multiple(self) -> int:
        if self.backbone == "unet":
            return self.unet.multiple
        return self.stem_stride * 2 ** (len(self.widths) - 1)


DELIGHT_CONFIGS = {
    "paper": HRNetConfig(),
    "small": HRNetConfig(widths=(6, 12, 16, 24, 32, 48), modules=(1, 1, 1, 1, 1), blocks=1,
                         first_stage_blocks=1, light_width=32),
    # the learning curve's widths around "small" (issue 47): half and twice its branches
    "small_half": HRNetConfig(widths=(4, 6, 8, 12, 16, 24), modules=(1, 1, 1, 1, 1), blocks=1,
                              first_stage_blocks=1, light_width=16),
    "small_double": HRNetConfig(widths=(12, 24, 32, 48, 64, 96), modules=(1, 1, 1, 1, 1), blocks=1,
                                first_stage_blocks=1, light_width=64),
    "vanilla": HRNetConfig(stem_stride=4, first_stage_residual=True, first_stage_blocks=4,
                           widths=(32, 64, 128, 256), modules=(1, 4, 3)),
    "five_stage": HRNetConfig(widths=(32, 64, 128, 256, 256), modules=(1, 2, 2, 2)),
    "unet": HRNetConfig(backbone="unet", unet=UNetConfig(width=64, max_width=512, n_down=5, n_res=6,
                                                          skips=True, norm="batch")),
}


class BasicBlock(nn.Module):
    """HRNet basic block: two 3x3 convs, with or without the identity shortcut."""

    def __init__(self, channels: int, residual: bool = True):
        super().__init__()
        self.residual = residual
        self.body = nn.Sequential(
            conv_norm_act(channels, channels, 3),
            nn.Conv2d(channels, channels, 3, padding=1, bias=False),
            make_norm("batch", channels),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.body(x)
        return F.relu(x + y if self.residual else y)


def downsample_path(c_in: int, c_out: int, steps: int) -> nn.Sequential:
    """`steps` stride-2 3x3 convs from branch j to the lower branch i = j + steps."""
    layers = []
    for k in range(steps):
        last = k == steps - 1
        layers.append(conv_norm_act(c_in if k == 0 else c_out, c_out, 3, stride=2,
                                    act="none" if last else "relu"))
    return nn.Sequential(*layers)


class HRModule(nn.Module):
    """Parallel branches of basic blocks, then every branch receives the sum of all branches
    resampled to its resolution (1x1 conv + bilinear upsampling from lower, strided convs from
    higher)."""

    def __init__(self, widths: tuple, blocks: int):
        super().__init__()
        self.branches = nn.ModuleList(
            nn.Sequential(*[BasicBlock(w) for _ in range(blocks)]) for w in widths
        )
        n = len(widths)
        self.fuse = nn.ModuleList()
        for i in range(n):
            row = nn.ModuleList()
            for j in range(n):
                if j == i:
                    row.append(nn.Identity())
                elif j > i:
                    row.append(conv_norm_act(widths[j], widths[i], 1, act="none"))
                else:
                    row.append(downsample_path(widths[j], widths[i], i - j))
            self.fuse.append(row)

    def forward(self, xs: list[torch.Tensor]) -> list[torch.Tensor]:
        xs = [branch(x) for branch, x in zip(self.branches, xs)]
        out = []
        for i, row in enumerate(self.fuse):
            y = xs[i]
            for j, path in enumerate(row):
                if j == i:
                    continue
                z = path(xs[j])
                if j > i:
                    z = F.interpolate(z, size=xs[i].shape[-2:], mode="bilinear", align_corners=False)
                y = y + z
            out.append(F.relu(y))
        return out


class HRNetBackbone(nn.Module):
    """Returns the highest- and lowest-resolution branch features of the last stage."""

    def __init__(self, c_in: int, cfg: HRNetConfig):
        super().__init__()
        w = cfg.widths
        if cfg.stem_stride == 1:
            self.stem = conv_norm_act(c_in, w[0], 3)
        elif cfg.stem_stride == 4:
            self.stem = nn.Sequential(conv_norm_act(c_in, 64, 3, stride=2), conv_norm_act(64, w[0], 3, stride=2))
        else:
            raise ValueError(f"stem_stride must be 1 or 4, got {cfg.stem_stride}")
        self.first_stage = nn.Sequential(
            *[BasicBlock(w[0], residual=cfg.first_stage_residual) for _ in range(cfg.first_stage_blocks)]
        )
        if len(cfg.modules) != len(w) - 1:
            raise ValueError(f"need one module count per stage after the first: {cfg.modules} vs {w}")
        self.transitions = nn.ModuleList()
        self.stages = nn.ModuleList()
        for s, n_modules in enumerate(cfg.modules, start=2):
            # A new branch at half the resolution of the previous lowest one.
            self.transitions.append(conv_norm_act(w[s - 2], w[s - 1], 3, stride=2))
            self.stages.append(nn.Sequential(*[HRModule(w[:s], cfg.blocks) for _ in range(n_modules)]))

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        xs = [self.first_stage(self.stem(x))]
        for transition, stage in zip(self.transitions, self.stages):
            xs = xs + [transition(xs[-1])]
            xs = stage(xs)
        return xs[0], xs[-1]


class LightHead(nn.Module):
    """Lowest-branch features (N, C, h, w) -> (N, 3, 16, 32) non-negative radiance."""

    def __init__(self, c_in: int, width: int):
        super().__init__()
        self.conv = conv_norm_act(c_in, width, 3)
        self.fc = nn.Linear(width, 3 * LIGHT_HEIGHT * LIGHT_WIDTH)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        pooled = self.conv(x).mean(dim=(2, 3))
        log_light = self.fc(pooled).reshape(-1, 3, LIGHT_HEIGHT, LIGHT_WIDTH)
        return torch.exp(log_light.clamp(*LOG_LIGHT_RANGE))


class DelightNet(nn.Module):
    """(image, normal) -> (albedo (N, 3, H, W), light (N, 3, 16, 32))."""

    family = "delight"
    output_names = ("albedo", "light")

    def __init__(self, cfg: HRNetConfig = DELIGHT_CONFIGS["paper"]):
        super().__init__()
        self.cfg = cfg
        if cfg.backbone == "unet":
            self.backbone = UNetBackbone(6, cfg.unet)
            high, low = cfg.unet.widths()[0], cfg.unet.widths()[-1]
        else:
            self.backbone = HRNetBackbone(6, cfg)
            high, low = cfg.widths[0], cfg.widths[-1]
        self.albedo_head = nn.Conv2d(high, 3, 1)
        self.light_head = LightHead(low, cfg.light_width)

    def forward(self, image: torch.Tensor, normal: torch.Tensor):
        x = torch.cat([encode_display(image), normal], dim=1)
        high, low = self.backbone(x)
        logits = self.albedo_head(high)
        if self.cfg.backbone == "hrnet" and self.cfg.stem_stride != 1:  # vanilla: stride-4 features
            logits = F.interpolate(logits, size=image.shape[-2:], mode="bilinear", align_corners=False)
        return torch.sigmoid(logits), self.light_head(low)

    def io_contract(self) -> IOContract:
        return IOContract(
            family=self.family,
            inputs=(
                image_spec("image", 3, "linear RGB in [0, 1], person crop"),
                image_spec("normal", 3, "unit normals, camera frame, 0 outside the person"),
            ),
            outputs=(
                image_spec("albedo", 3, "linear albedo in [0, 1]"),
                image_spec("light", 3, "lat-long radiance, DESIGN.md convention",
                           h=LIGHT_HEIGHT, w=LIGHT_WIDTH),
            ),
            multiple=self.cfg.multiple,
            colour_space="linear sRGB primaries",
            normalisation="image: clip to [0,1], x**(1/2.2)*2-1 in graph; normal: as is",
            config=asdict(self.cfg),
        )


def delight_net(size: str = "paper") -> DelightNet:
    return DelightNet(DELIGHT_CONFIGS[size])
