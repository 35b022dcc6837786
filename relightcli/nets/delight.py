"""De-lighting at run time: [image, normal] -> albedo and a 16x32 lat-long light estimate.
Contract: export/nets/delight.py."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from relightcli.nets.layout import check_hwc, crop_padding, hwc_to_nchw, nchw_to_hwc, pad_to_multiple
from relightcli.nets.session import ModelSession


@dataclass(frozen=True)
class DelightResult:
    """albedo: (H, W, 3) float32 linear in [0, 1]. light: (16, 32, 3) float32 linear radiance,
    equirectangular in the DESIGN.md convention, in the exposure units of the input image."""

    albedo: np.ndarray
    light: np.ndarray


class DelightNet(ModelSession):
    model_name = "delight"
    input_names = ("image", "normal")
    output_names = ("albedo", "light")

    def predict(self, image: np.ndarray, normal: np.ndarray) -> DelightResult:
        """image: (H, W, 3) float32 linear RGB in [0, 1]; normal: (H, W, 3) unit normals in the
        camera frame, zero outside the person. The albedo is multiplied by the manifest's
        `calibration.albedo_gain` when it has one: the level convention a net is brought to
        (a photo cannot tell its albedo's level; nets trained alike land up to ~0.2 stops apart)."""
        check_hwc(image, 3, "image")
        check_hwc(normal, 3, "normal")
        if image.shape != normal.shape:
            raise ValueError(f"image {image.shape} and normal {normal.shape} differ in size")
        padded_image, pad = pad_to_multiple(image, self.multiple, "reflect")
        padded_normal, _ = pad_to_multiple(normal, self.multiple, "reflect")
        out = self.run({"image": hwc_to_nchw(padded_image), "normal": hwc_to_nchw(padded_normal)})
        albedo = crop_padding(nchw_to_hwc(out["albedo"]), pad)
        gain = float(self.entry.calibration.get("albedo_gain", 1.0))
        if gain != 1.0:
            albedo = albedo * np.float32(gain)
        return DelightResult(albedo=albedo, light=nchw_to_hwc(out["light"]))
