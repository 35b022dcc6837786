"""Geometry module: pix2pixHD-like U-Nets from the image alone (paper Sec. 3.1, trained separately).

- `geometry` net: front normal, back normal, front depth, back depth, person mask. What the paper
  gets from PIFuHD we get from this net: the two depth maps (front and back surface along the
  camera ray) and the mask make a watertight, pixel-aligned mesh; the back normals shade it.
- `ao` net: ambient occlusion (1 ch, sigmoid) with skip connections, as the paper says.
- `geometry_prior` and `ao_prior` nets: the same, with a fitted body's maps as a second input.

Both are the same encoder/decoder (7x7 stem, `n_down` stride-2 convs, residual bottleneck,
bilinear-upsample + conv decoder, optional U-Net skips, 7x7 head); only the heads differ.

Input: `image`, (N, 3, H, W) float32 linear RGB in [0, 1] (clipped), gamma-encoded inside the
graph. H, W divisible by 2**n_down.
Depth convention: camera-frame Z (+Z toward the viewer) in units where the square crop spans
[-1, 1] in X and Y; back depth = front depth - softplus(thickness) so back <= front always.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import torch
import torch.nn.functional as F
from torch import nn

from .blocks import ResidualBlock, conv_norm_act, encode_display
from .contract import IOContract, image_spec


@dataclass(frozen=True)
class UNetConfig:
    width: int = 64  # channels after the stem; doubles at each downsampling
    max_width: int = 1024
    n_down: int = 4
    n_res: int = 9  # residual blocks in the bottleneck
    skips: bool = True
    norm: str = "instance"  # pix2pixHD uses instance norm

    @property
    def multiple(self) -> int:
        return 2**self.n_down

    def widths(self) -> list[int]:
        return [min(self.width * 2**k, self.max_width) for k in range(self.n_down + 1)]


GEOMETRY_CONFIGS = {
    "paper": UNetConfig(width=64, max_width=1024, n_down=4, n_res=9, skips=True),
    "small": UNetConfig(width=12, max_width=96, n_down=4, n_res=2, skips=True, norm="batch"),
    # the learning curve's widths around "small" (issue 49): half and twice its channels
    "small_half": UNetConfig(width=6, max_width=48, n_down=4, n_res=2, skips=True, norm="batch"),
    "small_double": UNetConfig(width=24, max_width=192, n_down=4, n_res=2, skips=True, norm="batch"),
}
AO_CONFIGS = GEOMETRY_CONFIGS


class UNetBackbone(nn.Module):
    """Encoder / residual bottleneck / decoder. Returns the full-resolution features,
    (N, cfg.width, H, W), and the bottleneck's, (N, widths[-1], H / multiple, W / multiple)."""

    def __init__(self, c_in: int, cfg: UNetConfig):
        super().__init__()
        w = cfg.widths()
        self.cfg = cfg
        self.stem = conv_norm_act(c_in, w[0], 7, norm=cfg.norm)
        self.down = nn.ModuleList(
            conv_norm_act(w[k], w[k + 1], 3, stride=2, norm=cfg.norm) for k in range(cfg.n_down)
        )
        self.bottleneck = nn.Sequential(*[ResidualBlock(w[-1], norm=cfg.norm) for _ in range(cfg.n_res)])
        # Decoder step k goes from level k+1 to level k; with skips it also sees the encoder's level k.
        self.up = nn.ModuleList(
            conv_norm_act(w[k + 1] + (w[k] if cfg.skips else 0), w[k], 3, norm=cfg.norm)
            for k in reversed(range(cfg.n_down))
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        feats = [self.stem(x)]
        for down in self.down:
            feats.append(down(feats[-1]))
        y = bottleneck = self.bottleneck(feats[-1])
        for up, skip in zip(self.up, reversed(feats[:-1])):
            y = F.interpolate(y, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            if self.cfg.skips:
                y = torch.cat([y, skip], dim=1)
            y = up(y)
        return y, bottleneck


def unit_vectors(v: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """(N, 3, H, W) -> same shape, each pixel's vector scaled to unit length."""
    return v * torch.rsqrt((v * v).sum(dim=1, keepdim=True) + eps)


class GeometryNet(nn.Module):
    """image -> (front_normal, back_normal, front_depth, back_depth, mask), all (N, C, H, W)."""

    family = "geometry"
    output_names = ("front_normal", "back_normal", "front_depth", "back_depth", "mask")

    def __init__(self, cfg: UNetConfig = GEOMETRY_CONFIGS["paper"]):
        super().__init__()
        self.cfg = cfg
        self.backbone = UNetBackbone(3, cfg)
        # 3 + 3 normal, front depth, thickness, mask logit
        self.head = nn.Conv2d(cfg.width, 9, 7, padding=3)

    def forward(self, image: torch.Tensor):
        h = self.head(self.backbone(encode_display(image))[0])
        front_depth = h[:, 6:7]
        back_depth = front_depth - F.softplus(h[:, 7:8])
        return (
            unit_vectors(h[:, 0:3]),
            unit_vectors(h[:, 3:6]),
            front_depth,
            back_depth,
            torch.sigmoid(h[:, 8:9]),
        )

    def io_contract(self) -> IOContract:
        return IOContract(
            family=self.family,
            inputs=(image_spec("image", 3, "linear RGB in [0, 1], person crop"),),
            outputs=(
                image_spec("front_normal", 3, "unit normals, camera frame, +Z to viewer"),
                image_spec("back_normal", 3, "unit normals of the back surface"),
                image_spec("front_depth", 1, "camera Z, crop spans [-1, 1] in X and Y"),
                image_spec("back_depth", 1, "camera Z of the back surface, <= front_depth"),
                image_spec("mask", 1, "person alpha in [0, 1]"),
            ),
            multiple=self.cfg.multiple,
            colour_space="linear sRGB primaries",
            normalisation="clip to [0,1], x**(1/2.2)*2-1 inside the graph",
            config=asdict(self.cfg),
        )


def near_zero(head: nn.Conv2d) -> nn.Conv2d:
    """`head` with its initial weights scaled by 0.1 and no bias: a prior net's corrections
    start small, so it starts from the prior."""
    with torch.no_grad():
        head.weight.mul_(0.1)
        head.bias.zero_()
    return head


def inverse_softplus(y: torch.Tensor) -> torch.Tensor:
    """x with softplus(x) = y, for y > 0 (written with log and exp: ONNX has no expm1)."""
    return y + torch.log(1.0 - torch.exp(-y))


class GeometryPriorNet(nn.Module):
    """(image, prior) -> the GeometryNet's five maps, learned as corrections of a fitted body.

    prior (N, 9, H, W): relightcli.nets.geometry.prior_channels of the fitted bodies (front and
    back normals, front and back depth made translation-invariant, coverage), zero where no body
    covers a pixel. The outputs start from the prior: normals are unit(prior + head), the front
    depth prior + head, the thickness softplus(head + softplus^-1(prior thickness + 0.02)); where
    the prior is zero the head predicts from the image alone, as the GeometryNet does."""

    family = "geometry_prior"
    output_names = GeometryNet.output_names
    prior_channels = 9

    def __init__(self, cfg: UNetConfig = GEOMETRY_CONFIGS["small"]):
        super().__init__()
        self.cfg = cfg
        self.backbone = UNetBackbone(3 + self.prior_channels, cfg)
        self.head = near_zero(nn.Conv2d(cfg.width, 9, 7, padding=3))  # start near the prior

    def forward(self, image: torch.Tensor, prior: torch.Tensor):
        h = self.head(self.backbone(torch.cat([encode_display(image), prior], dim=1))[0])
        front_depth = prior[:, 6:7] + h[:, 6:7]
        thickness = (prior[:, 6:7] - prior[:, 7:8]).clamp(min=0.0) + 0.02
        back_depth = front_depth - F.softplus(h[:, 7:8] + inverse_softplus(thickness))
        return (
            unit_vectors(prior[:, 0:3] + h[:, 0:3]),
            unit_vectors(prior[:, 3:6] + h[:, 3:6]),
            front_depth,
            back_depth,
            torch.sigmoid(h[:, 8:9]),
        )

    def io_contract(self) -> IOContract:
        contract = GeometryNet.io_contract(self)
        prior = image_spec("prior", self.prior_channels, "fitted body: front/back normals, front/back depth "
                           "(minus the mean front depth), coverage; zero off the body "
                           "(relightcli.nets.geometry.prior_channels)")
        return replace(contract, family=self.family, inputs=contract.inputs + (prior,))


class AONet(nn.Module):
    """image -> ambient occlusion (N, 1, H, W) in [0, 1] (1 = unoccluded)."""

    family = "ao"
    output_names = ("ao",)

    def __init__(self, cfg: UNetConfig = AO_CONFIGS["paper"]):
        super().__init__()
        self.cfg = cfg
        self.backbone = UNetBackbone(3, cfg)
        self.head = nn.Conv2d(cfg.width, 1, 7, padding=3)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.head(self.backbone(encode_display(image))[0]))

    def io_contract(self) -> IOContract:
        return IOContract(
            family=self.family,
            inputs=(image_spec("image", 3, "linear RGB in [0, 1], person crop"),),
            outputs=(image_spec("ao", 1, "ambient occlusion in [0, 1], 1 = open"),),
            multiple=self.cfg.multiple,
            colour_space="linear sRGB primaries",
            normalisation="clip to [0,1], x**(1/2.2)*2-1 inside the graph",
            config=asdict(self.cfg),
        )


class AOPriorNet(nn.Module):
    """(image, prior) -> ambient occlusion (N, 1, H, W) in [0, 1], learned as a correction of
    the fitted bodies' ray-traced AO.

    prior (N, 10, H, W): relightcli.nets.geometry.ao_prior_channels, the GeometryPriorNet's nine
    channels and the bodies' AO (zero where no fit converged). Where a body covers a pixel the
    output starts from its AO, sigmoid(head + coverage x logit(body AO)); elsewhere the head
    predicts from the image alone, as the AONet does."""

    family = "ao_prior"
    output_names = AONet.output_names
    prior_channels = 10

    def __init__(self, cfg: UNetConfig = AO_CONFIGS["small"]):
        super().__init__()
        self.cfg = cfg
        self.backbone = UNetBackbone(3 + self.prior_channels, cfg)
        self.head = near_zero(nn.Conv2d(cfg.width, 1, 7, padding=3))  # start near the prior

    def forward(self, image: torch.Tensor, prior: torch.Tensor) -> torch.Tensor:
        h = self.head(self.backbone(torch.cat([encode_display(image), prior], dim=1))[0])
        body = prior[:, 9:10].clamp(0.02, 0.98)
        return torch.sigmoid(h + prior[:, 8:9] * torch.log(body / (1.0 - body)))

    def io_contract(self) -> IOContract:
        contract = AONet.io_contract(self)
        prior = image_spec("prior", self.prior_channels, "fitted body: the geometry prior's nine channels "
                           "and the bodies' ray-traced AO (relightcli.nets.geometry.ao_prior_channels)")
        return replace(contract, family=self.family, inputs=contract.inputs + (prior,))


def geometry_net(size: str = "paper") -> GeometryNet:
    return GeometryNet(GEOMETRY_CONFIGS[size])


def geometry_prior_net(size: str = "small") -> GeometryPriorNet:
    return GeometryPriorNet(GEOMETRY_CONFIGS[size])


def ao_net(size: str = "paper") -> AONet:
    return AONet(AO_CONFIGS[size])
