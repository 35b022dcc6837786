"""Geometry module at run time: `GeometryNet` (normals, depths, mask) and `AONet` (ambient
occlusion) from the person crop alone; `GeometryPriorNet` and `AOPriorNet` with a fitted body's
maps as well. Contracts: export/nets/geometry.py."""

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
        return self._maps(self.run({"image": hwc_to_nchw(padded)}), pad)

    def _maps(self, out: dict, pad) -> GeometryMaps:
        """The session's NCHW outputs, cropped back to the image, as GeometryMaps."""
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


# Channels of the prior a GeometryPriorNet reads, in this order
PRIOR_CHANNELS = ("front_normal_x", "front_normal_y", "front_normal_z", "back_normal_x", "back_normal_y",
                  "back_normal_z", "front_depth", "back_depth", "mask")


def prior_channels(mask: np.ndarray, front_normal: np.ndarray, back_normal: np.ndarray,
                   front_depth: np.ndarray, back_depth: np.ndarray, side: int) -> np.ndarray:
    """(side, side, 9) float32: a fitted body's maps in the crop (relightcli.geometry.body_maps,
    any square resolution) as the prior net reads them (PRIOR_CHANNELS). Normals area-averaged
    and renormalised, depths made translation-invariant like the net's own (minus the mean front
    depth over the body; the crop spans [-1, 1], so they are already in the net's unit), the
    body's coverage in [0, 1]; all zero where no body covers a pixel. The data factory
    (export/factory/coarse.py) and the runtime (stages.geometry.stage_geometry) both call this."""
    import cv2

    covered = np.asarray(mask, np.float32)
    inside = covered > 0.5
    mean = float(front_depth[inside].mean()) if inside.any() else 0.0
    maps = np.concatenate([front_normal, back_normal, np.where(inside, front_depth - mean, 0.0)[..., None],
                           np.where(inside, back_depth - mean, 0.0)[..., None]], axis=-1).astype(np.float32)
    maps = np.concatenate([maps * covered[..., None], covered[..., None]], axis=-1)
    if maps.shape[0] != side:
        interpolation = cv2.INTER_AREA if side < maps.shape[0] else cv2.INTER_LINEAR
        maps = cv2.resize(maps, (side, side), interpolation=interpolation)
    # area averaging blends the edge with zeros: undo it for depth, renormalise the normals
    weight = maps[..., 8:9]
    safe = np.where(weight > 1e-6, weight, 1.0)
    out = np.zeros_like(maps)
    for lo in (0, 3):
        normal = maps[..., lo:lo + 3]
        length = np.linalg.norm(normal, axis=-1, keepdims=True)
        out[..., lo:lo + 3] = np.where(length > 1e-6, normal / np.where(length > 1e-6, length, 1.0), 0.0)
    out[..., 6:8] = np.where(weight > 1e-6, maps[..., 6:8] / safe, 0.0)
    out[..., 8] = maps[..., 8]
    return out


class GeometryPriorNet(GeometryNet):
    """Person crop + a fitted body's prior maps (prior_channels) -> `GeometryMaps`: the net
    learned the clothed person as corrections of the naked body where it covers the crop, and
    the maps from the image alone elsewhere."""

    model_name = "geometry_prior"
    input_names = ("image", "prior")

    def predict(self, image: np.ndarray, prior: np.ndarray) -> GeometryMaps:
        """image: (H, W, 3) float32 linear RGB in [0, 1]; prior: (H, W, 9) from prior_channels."""
        check_hwc(image, 3, "image")
        check_hwc(prior, len(PRIOR_CHANNELS), "prior")
        padded, pad = pad_to_multiple(image, self.multiple, "reflect")
        prior_padded, _ = pad_to_multiple(prior, self.multiple, "zero")
        return self._maps(self.run({"image": hwc_to_nchw(padded), "prior": hwc_to_nchw(prior_padded)}), pad)


def ao_prior_channels(prior: np.ndarray, body_ao: np.ndarray) -> np.ndarray:
    """(side, side, 10) float32: `prior_channels` (side, side, 9) and the fitted bodies'
    ray-traced AO (relightcli.stages.geometry.body_ao, any square resolution, zero where no fit
    converged) resampled to the same side, as the AO prior net reads them. The data factory
    (export/factory/coarse.py --prior-ao) and the runtime (stages.geometry.stage_ao) both call this."""
    import cv2

    side = prior.shape[0]
    ao = np.asarray(body_ao, np.float32)
    if ao.shape[0] != side:
        interpolation = cv2.INTER_AREA if side < ao.shape[0] else cv2.INTER_LINEAR
        ao = cv2.resize(ao, (side, side), interpolation=interpolation)
    return np.concatenate([prior, np.clip(ao, 0.0, 1.0)[..., None]], axis=-1).astype(np.float32)


class AOPriorNet(AONet):
    """Person crop + the fitted bodies' maps and AO (ao_prior_channels) -> ambient occlusion:
    the net learned the clothed person's AO as corrections of the bodies' where they cover the
    crop, and from the image alone elsewhere."""

    model_name = "ao_prior"
    input_names = ("image", "prior")

    def predict(self, image: np.ndarray, prior: np.ndarray) -> np.ndarray:
        """image: (H, W, 3) float32 linear RGB in [0, 1]; prior: (H, W, 10) from
        ao_prior_channels -> (H, W) float32 AO in [0, 1], 1 = open."""
        check_hwc(image, 3, "image")
        check_hwc(prior, len(PRIOR_CHANNELS) + 1, "prior")
        padded, pad = pad_to_multiple(image, self.multiple, "reflect")
        prior_padded, _ = pad_to_multiple(prior, self.multiple, "zero")
        out = self.run({"image": hwc_to_nchw(padded), "prior": hwc_to_nchw(prior_padded)})
        return crop_padding(nchw_to_hwc(out["ao"]), pad)[..., 0]
