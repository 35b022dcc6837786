"""Layout conversions and padding between the project's images and network tensors.

Project images are (H, W, C) or (H, W) float32; networks take (1, C, H, W) float32 with H and W
divisible by the model's `multiple`. Padding is split evenly between the two sides so the
content stays centred in the net's receptive field; `crop_padding` undoes it exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PAD_MODES = {"reflect": "reflect", "edge": "edge", "zero": "constant"}


@dataclass(frozen=True)
class Padding:
    """Rows/columns added on each side."""

    top: int
    bottom: int
    left: int
    right: int


def hwc_to_nchw(image: np.ndarray) -> np.ndarray:
    """(H, W, C) or (H, W) -> (1, C, H, W) float32, C-contiguous."""
    if image.ndim == 2:
        image = image[:, :, None]
    if image.ndim != 3:
        raise ValueError(f"expected an (H, W) or (H, W, C) image, got shape {image.shape}")
    return np.ascontiguousarray(image.transpose(2, 0, 1)[None], dtype=np.float32)


def nchw_to_hwc(tensor: np.ndarray) -> np.ndarray:
    """(1, C, H, W) -> (H, W, C) float32 (C = 1 kept; use [..., 0] for a plain map)."""
    if tensor.ndim != 4 or tensor.shape[0] != 1:
        raise ValueError(f"expected a (1, C, H, W) tensor, got shape {tensor.shape}")
    return np.ascontiguousarray(tensor[0].transpose(1, 2, 0), dtype=np.float32)


def padding_for(height: int, width: int, multiple: int) -> Padding:
    """The even split that brings (height, width) up to the next multiple of `multiple`."""
    if multiple < 1:
        raise ValueError(f"multiple must be >= 1, got {multiple}")
    extra_h = -height % multiple
    extra_w = -width % multiple
    return Padding(extra_h // 2, extra_h - extra_h // 2, extra_w // 2, extra_w - extra_w // 2)


def pad_to_multiple(image: np.ndarray, multiple: int, mode: str = "reflect") -> tuple[np.ndarray, Padding]:
    """Pad (H, W[, C]) so H and W are divisible by `multiple`.

    mode: "reflect" (mirror without repeating the edge; what the nets saw at crop borders),
    "edge" (repeat the border), or "zero" (background, for inputs already multiplied by the
    person mask). Returns the padded image and the `Padding` to pass to `crop_padding`.
    """
    if mode not in PAD_MODES:
        raise ValueError(f"unknown pad mode {mode!r}: use one of {sorted(PAD_MODES)}")
    pad = padding_for(image.shape[0], image.shape[1], multiple)
    if pad == Padding(0, 0, 0, 0):
        return image, pad
    widths = [(pad.top, pad.bottom), (pad.left, pad.right)] + [(0, 0)] * (image.ndim - 2)
    # numpy cannot reflect a single row/column; the edge is the only sensible value there.
    np_mode = "edge" if mode == "reflect" and min(image.shape[:2]) < 2 else PAD_MODES[mode]
    return np.pad(image, widths, mode=np_mode), pad


def crop_padding(image: np.ndarray, pad: Padding) -> np.ndarray:
    """Undo `pad_to_multiple` on an (H', W'[, C]) image."""
    h, w = image.shape[:2]
    return image[pad.top : h - pad.bottom, pad.left : w - pad.right]


def check_hwc(image: np.ndarray, channels: int, what: str) -> None:
    """Internal invariant: `image` is (H, W, channels)."""
    if image.ndim != 3 or image.shape[2] != channels:
        raise ValueError(f"{what} must be (H, W, {channels}), got shape {image.shape}")
