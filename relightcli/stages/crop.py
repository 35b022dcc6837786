"""The working crop: a square around the person at the working resolution, where every later
stage works."""

from __future__ import annotations

import numpy as np

from relightcli import compose
from relightcli.stages.frame import Frame, Models


def stage_crop(frame: Frame, options, models: Models) -> None:
    frame.box = compose.person_crop_box(frame.mask, options.resolution)
    frame.crop = compose.crop_square(frame.image, frame.box)
    frame.crop_mask = np.clip(compose.crop_square(frame.mask, frame.box), 0.0, 1.0)
    frame.notes["crop"] = {"box": [frame.box.x0, frame.box.y0, frame.box.size], "resolution": options.resolution}


def person_keypoints_in_crop(person, view_scale, box: compose.CropBox) -> np.ndarray:
    """(33, 2) crop pixel indices (col, row) of a person's pose landmarks (view pixels):
    view -> photo (continuous) -> the working crop."""
    photo = person.pose.landmarks[:, :2] / np.asarray(view_scale, np.float64)
    return (photo - (box.x0, box.y0)) / box.scale - 0.5
