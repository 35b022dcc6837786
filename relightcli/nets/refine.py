"""Shading refinement at run time: `BodyRefineNet` (full body) and `FaceRefineNet` (face crop).
Contracts: export/nets/body_refine.py and export/nets/face_refine.py.

Shading is HDR, so both nets see shading divided by one per-image scale (`shading_scale`) and
the result is multiplied back; the face net uses the scale of its face crop of the body
shading (the person's pixels of the crop), for both of its inputs.
"""

from __future__ import annotations

import numpy as np

from relightcli.errors import NumericalError
from relightcli.nets.layout import check_hwc, crop_padding, hwc_to_nchw, nchw_to_hwc, pad_to_multiple
from relightcli.nets.session import ModelSession

SCALE_PERCENTILE = 95.0
SCALE_TARGET = 0.8  # the percentile maps to 0.8, as in the evaluation protocol (DESIGN.md)


def shading_scale(shading: np.ndarray, mask: np.ndarray | None = None) -> float:
    """One positive scale for (H, W, 3) linear shading: the 95th percentile of its values over
    the person (mask > 0.5; all pixels when mask is None), RGB pooled, divided by 0.8.
    1.0 when that percentile is 0 (a black or empty map)."""
    values = shading if mask is None else shading[mask > 0.5]
    if values.size == 0:
        return 1.0
    p = float(np.percentile(values, SCALE_PERCENTILE))
    return p / SCALE_TARGET if p > 0 else 1.0


def _check_finite(array: np.ndarray, what: str) -> None:
    if not np.all(np.isfinite(array)):
        raise NumericalError(f"{what} has NaN or infinite values", fix="check the ray-traced shading stage")


class BodyRefineNet(ModelSession):
    model_name = "body_refine"
    input_names = ("coarse_shading", "ao")
    output_names = ("shading",)

    def predict(self, shading: np.ndarray, ao: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
        """shading: (H, W, 3) float32 coarse linear shading >= 0; ao: (H, W) float32 in [0, 1];
        mask: (H, W) person alpha for the scale. Returns (H, W, 3) float32 refined shading,
        same units."""
        check_hwc(shading, 3, "shading")
        if ao.shape != shading.shape[:2]:
            raise ValueError(f"ao {ao.shape} does not match shading {shading.shape}")
        _check_finite(shading, "coarse shading")
        scale = shading_scale(shading, mask)
        padded_s, pad = pad_to_multiple(shading / np.float32(scale), self.multiple, "reflect")
        padded_ao, _ = pad_to_multiple(ao, self.multiple, "reflect")
        out = self.run({"coarse_shading": hwc_to_nchw(padded_s), "ao": hwc_to_nchw(padded_ao)})
        return crop_padding(nchw_to_hwc(out["shading"]), pad) * np.float32(scale)


class FaceRefineNet(ModelSession):
    model_name = "face_refine"
    input_names = ("body_shading", "face_shading")
    output_names = ("shading",)

    def predict(self, body_shading: np.ndarray, face_shading: np.ndarray, scale: float) -> np.ndarray:
        """body_shading: (S, S, 3) face crop of the refined body shading; face_shading: (S, S, 3)
        coarse ray-traced face shading (S = 128 in training); scale: `shading_scale` of the
        body crop over the person's pixels of the crop.
        All float32 linear >= 0. Returns the refined (S, S, 3) face shading, same units."""
        check_hwc(body_shading, 3, "body_shading")
        check_hwc(face_shading, 3, "face_shading")
        if body_shading.shape != face_shading.shape:
            raise ValueError(f"body crop {body_shading.shape} and face {face_shading.shape} differ in size")
        if not scale > 0:
            raise ValueError(f"scale must be positive, got {scale}")
        _check_finite(face_shading, "coarse face shading")
        s = np.float32(scale)
        padded_b, pad = pad_to_multiple(body_shading / s, self.multiple, "reflect")
        padded_f, _ = pad_to_multiple(face_shading / s, self.multiple, "reflect")
        out = self.run({"body_shading": hwc_to_nchw(padded_b), "face_shading": hwc_to_nchw(padded_f)})
        return crop_padding(nchw_to_hwc(out["shading"]), pad) * s
