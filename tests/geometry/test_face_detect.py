"""The face crop rectangle around a face box."""

from __future__ import annotations

import numpy as np

from relightcli.geometry.face_detect import CropRect, FaceBox, face_crop_rect
from relightcli.render.camera import pixel_centres


def test_crop_rect_is_a_square_around_the_box():
    box = FaceBox(left=100.0, top=50.0, width=40.0, height=50.0)
    crop = face_crop_rect(box)
    assert crop.size == 80 and crop.resolution == 128
    assert crop.left <= box.left and crop.left + crop.size >= box.left + box.width
    assert crop.top <= box.top and crop.top + crop.size >= box.top + box.height


def test_crop_world_rect_matches_the_image_pixel_centres():
    image_rect, shape = (-1.0, 1.0, 0.0, 3.0), (300, 200)
    crop = CropRect(left=37, top=120, size=64)
    centres = pixel_centres(image_rect, (shape[1], shape[0]))
    inner = pixel_centres(crop.world_rect(image_rect, shape), (64, 64))
    np.testing.assert_allclose(inner, centres[120:184, 37:101], atol=1e-12)
