"""Training losses (paper Sec. 3-4), all on NCHW float tensors.

The paper's perceptual term is a VGG feature distance; no pretrained weights exist here, so
`perceptual` is weight-free: (1 - MS-SSIM) + L1 of image gradients. Masks are (N, 1, H, W)
in [0, 1]; a masked loss averages over the person only, which is where the targets (albedo,
normal, AO, shading) are defined.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from relightcli.io.envmap import texel_solid_angles

EPS = 1e-8
# MS-SSIM scale weights (Wang, Simoncelli, Bovik 2003), finest first.
MS_SSIM_WEIGHTS = (0.0448, 0.2856, 0.3001, 0.2363, 0.1333)
SSIM_SIGMA = 1.5
SSIM_RADIUS = 5  # 11-tap window, as relightcli.metrics
SSIM_K1, SSIM_K2 = 0.01, 0.03
SSIM_FLOOR = 1e-4  # cs and SSIM are clamped here before the fractional powers (negative -> NaN)


def _masked_mean(values: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """Mean of (N, C, H, W) `values` over the pixels weighted by (N, 1, H, W) `mask`."""
    if mask is None:
        return values.mean()
    channels = values.shape[1]
    return (values * mask).sum() / (mask.sum() * channels + EPS)


def masked_l1(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean |pred - target| over the masked pixels and all channels (over all pixels without a mask)."""
    return _masked_mean((pred - target).abs(), mask)


def angular_loss(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean (1 - cos angle) between (N, 3, H, W) unit normal maps over the mask."""
    cos = (pred * target).sum(dim=1, keepdim=True).clamp(-1.0, 1.0)
    return _masked_mean(1.0 - cos, mask)


def gradient_l1(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """L1 between the horizontal and vertical finite differences of `pred` and `target`,
    over pixel pairs that both lie in the mask."""
    total = pred.new_zeros(())
    for dim in (-1, -2):
        n = pred.shape[dim]
        dp = pred.narrow(dim, 1, n - 1) - pred.narrow(dim, 0, n - 1)
        dt = target.narrow(dim, 1, n - 1) - target.narrow(dim, 0, n - 1)
        m = None if mask is None else mask.narrow(dim, 1, n - 1) * mask.narrow(dim, 0, n - 1)
        total = total + _masked_mean((dp - dt).abs(), m)
    return total


def _gaussian_blur(x: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian (sigma 1.5, 11 taps), reflected borders, per channel."""
    taps = torch.arange(-SSIM_RADIUS, SSIM_RADIUS + 1, dtype=x.dtype, device=x.device)
    g = torch.exp(-0.5 * (taps / SSIM_SIGMA) ** 2)
    g = g / g.sum()
    c = x.shape[1]
    x = F.pad(x, (SSIM_RADIUS,) * 4, mode="reflect")
    x = F.conv2d(x, g.view(1, 1, 1, -1).repeat(c, 1, 1, 1), groups=c)
    return F.conv2d(x, g.view(1, 1, -1, 1).repeat(c, 1, 1, 1), groups=c)


def _ssim_terms(x: torch.Tensor, y: torch.Tensor, data_range: float):
    """Per-pixel luminance and contrast-structure terms of SSIM (Wang et al. 2004, eq. 13).
    The five local means in one blur (the loss 1.3 -> 0.8 s forward and backward on two
    (4, 3, 256, 256) pairs, two threads: the same values)."""
    mx, my, xx, yy, xy = _gaussian_blur(torch.cat([x, y, x * x, y * y, x * y], dim=1)).split(x.shape[1], dim=1)
    vx, vy, cxy = xx - mx * mx, yy - my * my, xy - mx * my
    c1, c2 = (SSIM_K1 * data_range) ** 2, (SSIM_K2 * data_range) ** 2
    luminance = (2 * mx * my + c1) / (mx * mx + my * my + c1)
    contrast_structure = (2 * cxy + c2) / (vx + vy + c2)
    return luminance, contrast_structure


def ms_ssim_scales(height: int, width: int) -> int:
    """How many MS-SSIM scales fit: up to 5, the coarsest side at least 8 pixels."""
    side = min(height, width)
    if side < 8:  # the reflected 11-tap window needs at least 6 pixels
        raise ValueError(f"MS-SSIM needs images of at least 8x8 pixels, got {width}x{height}")
    return max(1, min(len(MS_SSIM_WEIGHTS), int(math.floor(math.log2(side / 8))) + 1))


def ms_ssim(x: torch.Tensor, y: torch.Tensor, mask: torch.Tensor | None = None,
            data_range: float = 1.0) -> torch.Tensor:
    """Multi-scale SSIM (Wang et al. 2003) of (N, C, H, W) images, averaged over the batch;
    with a mask the per-scale terms are averaged over the (pooled) mask. The number of scales
    adapts to the image size (`ms_ssim_scales`) and the weights are renormalised to sum to 1."""
    n_scales = ms_ssim_scales(*x.shape[-2:])
    weights = torch.tensor(MS_SSIM_WEIGHTS[:n_scales], dtype=x.dtype)
    weights = weights / weights.sum()
    if mask is None:
        mask = torch.ones_like(x[:, :1])
    value = x.new_ones(x.shape[0])
    for k in range(n_scales):
        luminance, cs = _ssim_terms(x, y, data_range)
        term = cs if k < n_scales - 1 else luminance * cs
        # per image: mean over its mask and channels
        per_image = (term * mask).sum(dim=(1, 2, 3)) / (mask.sum(dim=(1, 2, 3)) * x.shape[1] + EPS)
        value = value * per_image.clamp_min(SSIM_FLOOR) ** weights[k]
        if k < n_scales - 1:
            x, y, mask = F.avg_pool2d(x, 2), F.avg_pool2d(y, 2), F.avg_pool2d(mask, 2)
    return value.mean()


def perceptual(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None,
               data_range: float = 1.0) -> torch.Tensor:
    """The weight-free stand-in for the paper's VGG perceptual loss:
    (1 - MS-SSIM) + gradient L1, both over the mask. 0 for identical images."""
    return (1.0 - ms_ssim(pred, target, mask, data_range)) + gradient_l1(pred, target, mask)


def light_weights(height: int = 16, width: int = 32) -> torch.Tensor:
    """(height, width) float32 texel solid angles of the lat-long map, normalised to sum to 1."""
    w = texel_solid_angles(height, width)
    return torch.from_numpy((w / w.sum()).astype(np.float32))


def light_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Solid-angle-weighted log-L2 between (N, 3, h, w) lat-long light maps (paper Sec. 3.2):
    sum over texels of w * (log(1 + pred) - log(1 + target))^2, w summing to 1, averaged over
    channels and the batch."""
    w = light_weights(*pred.shape[-2:]).to(pred.dtype)
    d2 = (torch.log1p(pred.clamp_min(0)) - torch.log1p(target.clamp_min(0))) ** 2
    return (d2 * w).sum(dim=(-2, -1)).mean()


def fft_l1(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """MIMO-UNet's frequency loss: mean L1 between the real and imaginary parts of the 2-D FFTs."""
    fp, ft = torch.fft.rfft2(pred), torch.fft.rfft2(target)
    return ((fp.real - ft.real).abs() + (fp.imag - ft.imag).abs()).mean() / 2


def pyramid(x: torch.Tensor, levels: int) -> list[torch.Tensor]:
    """x, then x average-pooled by 2, 4, ... (`levels` tensors, finest first), as the
    body-refinement net pools its inputs."""
    out = [x]
    for _ in range(levels - 1):
        out.append(F.avg_pool2d(out[-1], 2))
    return out


def lsgan_loss(scores, real: bool) -> torch.Tensor:
    """Least-squares GAN loss (Mao et al. 2017): mean (D - 1)^2 for real, mean D^2 for fake;
    `scores` is a tensor or a list (one per PatchGAN scale, averaged)."""
    if isinstance(scores, torch.Tensor):
        scores = [scores]
    target = 1.0 if real else 0.0
    return sum(((s - target) ** 2).mean() for s in scores) / len(scores)
