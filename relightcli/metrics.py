"""Image error metrics: MSE, PSNR and SSIM, optionally over a foreground mask.

All functions take two images `a`, `b` of the same shape, (H, W) or (H, W, C), any float
dtype (computed in float64), and an optional mask (H, W): boolean, or numbers where > 0.5
counts as inside. Which colour space the values are in is the caller's choice; the
evaluation protocol (../shared/DESIGN.md) feeds sRGB-encoded values clipped to [0, 1].
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter

# SSIM of Wang et al. 2004: Gaussian window of 11 taps, sigma 1.5
SSIM_SIGMA = 1.5
SSIM_TRUNCATE = 3.5  # scipy's truncation, in sigmas: radius int(3.5 * 1.5 + 0.5) = 5
SSIM_RADIUS = int(SSIM_TRUNCATE * SSIM_SIGMA + 0.5)
SSIM_K1 = 0.01
SSIM_K2 = 0.03


def _as_channels(a, b):
    """Both images as (H, W, C) float64, after checking that their shapes agree."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape:
        raise ValueError(f"images differ in shape: {a.shape} and {b.shape}")
    if a.ndim not in (2, 3):
        raise ValueError(f"images must be (H, W) or (H, W, C), got {a.shape}")
    if a.ndim == 2:
        return a[:, :, None], b[:, :, None]
    return a, b


def _as_mask(mask, shape: tuple[int, int]):
    """(H, W) boolean mask (all True when `mask` is None); empty masks are refused."""
    if mask is None:
        return np.ones(shape, dtype=bool)
    mask = np.asarray(mask)
    if mask.shape != shape:
        raise ValueError(f"mask must have shape {shape}, got {mask.shape}")
    mask = mask if mask.dtype == bool else mask > 0.5
    if not mask.any():
        raise ValueError("mask selects no pixel: the metric is undefined on an empty mask")
    return mask


def mse(a, b, mask=None) -> float:
    """Mean squared difference over the masked pixels and all channels."""
    a, b = _as_channels(a, b)
    mask = _as_mask(mask, a.shape[:2])
    return float(np.mean((a[mask] - b[mask]) ** 2))


def psnr(a, b, mask=None, data_range: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB, 10 log10(data_range^2 / MSE); inf when equal."""
    error = mse(a, b, mask)
    if error == 0.0:
        return float("inf")
    return float(10.0 * np.log10(data_range**2 / error))


def ssim_map(a, b, data_range: float = 1.0):
    """Per-pixel SSIM (Wang et al. 2004), (H, W, C) float64.

    Local statistics come from a Gaussian window (sigma 1.5, 11 taps) with reflected borders
    and population (not sample) covariance, the constants are C1 = (K1 R)^2,
    C2 = (K2 R)^2 with R = data_range.
    """
    a, b = _as_channels(a, b)

    def local_mean(x):
        # smooth within each channel only (sigma 0 along the channel axis)
        return gaussian_filter(x, sigma=(SSIM_SIGMA, SSIM_SIGMA, 0.0),
                               truncate=SSIM_TRUNCATE, mode="reflect")

    mean_a, mean_b = local_mean(a), local_mean(b)
    var_a = local_mean(a * a) - mean_a * mean_a
    var_b = local_mean(b * b) - mean_b * mean_b
    cov_ab = local_mean(a * b) - mean_a * mean_b
    c1 = (SSIM_K1 * data_range) ** 2
    c2 = (SSIM_K2 * data_range) ** 2
    # SSIM = luminance-contrast-structure product, Wang et al. 2004, eq. 13
    numerator = (2.0 * mean_a * mean_b + c1) * (2.0 * cov_ab + c2)
    denominator = (mean_a**2 + mean_b**2 + c1) * (var_a + var_b + c2)
    return numerator / denominator


def ssim(a, b, mask=None, data_range: float = 1.0) -> float:
    """Mean SSIM over the masked pixels, channels averaged.

    Pixels within 5 (the window radius) of the image border are left out of the mean, as
    scikit-image does: there the window reaches into reflected, made-up data. Without a mask
    this equals skimage's `structural_similarity(a, b, gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False, data_range=data_range, channel_axis=-1)`. Images must be at
    least 11x11; a mask must keep at least one pixel away from the border.
    """
    a, b = _as_channels(a, b)
    height, width = a.shape[:2]
    if min(height, width) < 2 * SSIM_RADIUS + 1:
        raise ValueError(f"SSIM needs images of at least {2 * SSIM_RADIUS + 1}x"
                         f"{2 * SSIM_RADIUS + 1} pixels, got {width}x{height}")
    mask = _as_mask(mask, (height, width))
    interior = np.zeros_like(mask)
    interior[SSIM_RADIUS:height - SSIM_RADIUS, SSIM_RADIUS:width - SSIM_RADIUS] = True
    keep = mask & interior
    if not keep.any():
        raise ValueError("mask selects no pixel away from the image border: SSIM is undefined")
    per_channel = ssim_map(a, b, data_range)[keep].mean(axis=0)
    return float(per_channel.mean())
