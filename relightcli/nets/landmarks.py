"""Face landmarks at run time: a 128x128 face crop -> 68 iBUG-order landmarks in its pixels.
Contract: export/nets/landmarks.py (normalisation inside the graph)."""

from __future__ import annotations

import numpy as np

from relightcli.errors import NumericalError
from relightcli.nets.layout import check_hwc, hwc_to_nchw
from relightcli.nets.session import ModelSession

FACE_CROP = 128


class LandmarkNet(ModelSession):
    model_name = "landmarks"
    input_names = ("image",)
    output_names = ("landmarks",)

    @property
    def crop_size(self) -> int:
        """The fixed crop side the model takes (128)."""
        return int(self.entry.inputs[0].shape[-1])

    def predict(self, face_crop: np.ndarray) -> np.ndarray:
        """face_crop: (S, S, 3) float32 linear RGB in [0, 1], S = `crop_size`. Returns (68, 2)
        float64 (col, row) in pixels of the crop, pixel (i, j)'s centre at (j, i)."""
        check_hwc(face_crop, 3, "face_crop")
        size = self.crop_size
        if face_crop.shape[:2] != (size, size):
            raise ValueError(f"face crop must be {size}x{size}, got {face_crop.shape[:2]}")
        out = self.run({"image": hwc_to_nchw(np.ascontiguousarray(face_crop, dtype=np.float32))})
        landmarks = out["landmarks"][0].astype(np.float64)
        if not np.all(np.isfinite(landmarks)):
            raise NumericalError("the landmark net returned non-finite values",
                                 fix="check the face crop for NaN or infinite pixels")
        return landmarks
