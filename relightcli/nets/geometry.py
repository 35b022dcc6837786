"""Geometry module at run time: `GeometryNet` (normals, depths, mask) and `AONet` (ambient
occlusion), both from the person crop alone. Contracts: export/nets/geometry.py."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from relightcli.nets.layout import check_hwc, crop_padding, hwc_to_nchw, nchw_to_hwc, pad_to_multiple
from relightcli.nets.session import ModelSession


@dataclass(frozen=True)
class GeometryMaps:
    """All (H, W, ...) float32 in the camera frame of DESIGN.md (+Z toward the viewer).

    front_normal, back_normal: (H, W, 3) unit vectors. front_depth, back_depth: (H, W) camera Z,
    the square crop spanning [-1, 1] in X and Y; back_depth <= front_depth. mask: (H, W) in [0, 1].
    """

    front_normal: np.ndarray
    back_normal: np.ndarray
    front_depth: np.ndarray
    back_depth: np.ndarray
    mask: np.ndarray


class GeometryNet(ModelSession):
    """Person crop -> `GeometryMaps`."""

    model_name = "geometry"
    input_names = ("image",)
    output_names = ("front_normal", "back_normal", "front_depth", "back_depth", "mask")

    def predict(self, image: np.ndarray) -> GeometryMaps:
        """image: (H, W, 3) float32 linear RGB, values in [0, 1] (the net clips)."""
        check_hwc(image, 3, "image")
        padded, pad = pad_to_multiple(image, self.multiple, "reflect")
        out = self.run({"image": hwc_to_nchw(padded)})
        maps = {k: crop_padding(nchw_to_hwc(out[k]), pad) for k in self.output_names}
        return GeometryMaps(
            front_normal=maps["front_normal"],
            back_normal=maps["back_normal"],
            front_depth=maps["front_depth"][..., 0],
            back_depth=maps["back_depth"][..., 0],
            mask=maps["mask"][..., 0],
        )


class AONet(ModelSession):
    """Person crop -> ambient occlusion."""

    model_name = "ao"
    input_names = ("image",)
    output_names = ("ao",)

    def predict(self, image: np.ndarray) -> np.ndarray:
        """image: (H, W, 3) float32 linear RGB in [0, 1] -> (H, W) float32 AO in [0, 1], 1 = open."""
        check_hwc(image, 3, "image")
        padded, pad = pad_to_multiple(image, self.multiple, "reflect")
        out = self.run({"image": hwc_to_nchw(padded)})
        return crop_padding(nchw_to_hwc(out["ao"]), pad)[..., 0]
