"""MediaPipe's selfie segmentation (converted by `python -m export.perception`): the person's
probability in a head-and-shoulders shot, for photos where the pose nets find nobody (close
portraits show no body to place a pose on). The whole photo is stretched to the net's 256x256
(as MediaPipe does) and the answer stretched back."""

from __future__ import annotations

import cv2
import numpy as np

from relightcli.nets.session import ModelSession


class SelfieSegmenter(ModelSession):
    model_name = "selfie_segmentation"
    input_names = ("image",)
    output_names = ("mask",)

    def segment(self, image: np.ndarray) -> np.ndarray:
        """(H, W) float32 person probability of `image` (H, W, 3) sRGB in [0, 1]."""
        _, side, _, _ = self.entry.inputs[0].shape
        height, width = image.shape[:2]
        small = cv2.resize(np.ascontiguousarray(image, np.float32), (side, side), interpolation=cv2.INTER_AREA)
        low, high = self.entry.config.get("value_range", (0.0, 1.0))
        out = self.run({"image": (low + (high - low) * np.clip(small, 0.0, 1.0))[None].astype(np.float32)})
        return cv2.resize(out["mask"][0, :, :, 0], (width, height), interpolation=cv2.INTER_LINEAR)
