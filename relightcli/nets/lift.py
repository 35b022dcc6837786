"""The landmark lifter (a models folder's lift.onnx, trained by export/lift.py; none ships:
docs/RESULTS.md, "The fit's landmarks lifted"): BlazePose's world landmarks corrected from
everything BlazePose said of the person, for the body fit.

BlazePose's world landmarks carry too little depth and turn the torso short (docs/RESULTS.md,
"What limits the fit"); the lifter reads the pose's image landmarks (hip-centred, scaled by the
body's extent), their depths, visibility and presence, and the world landmarks, and adds a
correction to the world landmarks. Its input is `features(landmarks, world)`; `mirrored` is the
same person in the mirror image (x negated, left and right swapped), the training's augmentation.
"""

from __future__ import annotations

import numpy as np

from relightcli.nets.session import ModelSession

# BlazePose's left and right landmarks, each with its mirror's index
MIRROR = np.array([0, 4, 5, 6, 1, 2, 3, 8, 7, 10, 9, 12, 11, 14, 13, 16, 15, 18, 17, 20, 19, 22, 21,
                   24, 23, 26, 25, 28, 27, 30, 29, 32, 31])
HIPS = (23, 24)
FEATURES = 33 * 8


def features(landmarks: np.ndarray, world: np.ndarray) -> np.ndarray:
    """(FEATURES,) float32: the image landmarks (33, 5: x, y, z pixels, visibility, presence)
    about their hips' midpoint over the body's extent in x or y, the depths over the same, the
    visibility and presence, and the world landmarks (33, 3) metres as they are."""
    centre = landmarks[HIPS, :2].mean(axis=0)
    extent = max(float(np.ptp(landmarks[:, :2], axis=0).max()), 1e-6)
    image = np.c_[(landmarks[:, :2] - centre) / extent, landmarks[:, 2:3] / extent, landmarks[:, 3:5]]
    return np.c_[image, world].astype(np.float32).ravel()


def mirrored(landmarks: np.ndarray, world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pose of the mirror image (about x = 0; features() centres it anyway)."""
    landmarks, world = landmarks[MIRROR].copy(), world[MIRROR].copy()
    landmarks[:, 0] *= -1.0
    world[:, 0] *= -1.0
    return landmarks, world


def image_depths(landmarks: np.ndarray, world: np.ndarray) -> np.ndarray:
    """The image landmarks with their depths taken from `world` (metres), in their pixels: the
    world's depth scaled by the landmarks' extent over the world's (what the fit's turn witness,
    body_fit.depth_side, reads)."""
    out = landmarks.copy()
    extent = np.ptp(landmarks[:, :2], axis=0).max() / max(float(np.ptp(world[:, :2], axis=0).max()), 1e-9)
    out[:, 2] = world[:, 2] * extent
    return out


class Lifter(ModelSession):
    model_name = "lift"
    input_names = ("features",)
    output_names = ("correction",)

    def lift(self, landmarks: np.ndarray, world: np.ndarray) -> np.ndarray:
        """(33, 3) the world landmarks corrected: the mean of the lifter's answer for the pose and
        for its mirror image (mirrored back), which keeps a mirrored photo's fit mirrored."""
        pair = np.stack([features(landmarks, world), features(*mirrored(landmarks, world))])
        correction = self.run({"features": pair})["correction"].reshape(2, 33, 3).astype(np.float64)
        back = correction[1][MIRROR] * np.array([-1.0, 1.0, 1.0])
        return world + 0.5 * (correction[0] + back)
