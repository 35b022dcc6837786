"""Face detection on real photographs, the skip path, and the face crop rectangle."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from relightcli.geometry.face_detect import CropRect, FaceBox, detect_face, face_crop_rect
from relightcli.geometry.face_model import FaceModel
from relightcli.render.camera import pixel_centres

PHOTOS = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "photos"


@pytest.fixture(scope="module")
def model():
    return FaceModel.load()


def read_photo(name):
    from relightcli.io.images import read_image

    path = PHOTOS / name
    if not path.is_file():
        pytest.skip(f"sample photo not found: {path}")
    return read_image(path).rgb


# Face centres (col, row) read off the photos by eye, and a radius in pixels
@pytest.mark.parametrize("name, centre, radius", [
    ("pexels_woman_with_dog.jpg", (213, 196), 25),
    ("pexels_portrait_face_paint.png", (430, 480), 80),
])
def test_finds_the_face_in_a_real_photo(model, name, centre, radius):
    image = read_photo(name)
    box, reason = detect_face(image, model=model)
    assert box is not None, reason
    height, width = image.shape[:2]
    assert 0 <= box.left and box.left + box.width <= width
    assert 0 <= box.top and box.top + box.height <= height
    assert np.hypot(box.centre[0] - centre[0], box.centre[1] - centre[1]) < radius


def test_mask_excludes_faces_outside_the_person(model):
    image = read_photo("pexels_woman_with_dog.jpg")
    mask = np.zeros(image.shape[:2], np.float32)
    mask[:, 400:] = 1.0            # the dog's side of the picture only
    box, reason = detect_face(image, mask, model=model)
    assert box is None and "skipped" in reason


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_texture_has_no_face(model, seed):
    rng = np.random.default_rng(seed)
    image = rng.random((360, 280, 3)).astype(np.float32)
    box, reason = detect_face(image, model=model)
    assert box is None and "no frontal or profile face" in reason


@pytest.mark.parametrize("sigma", [2.0, 4.0, 8.0])
def test_smooth_texture_has_no_face(model, sigma):
    rng = np.random.default_rng(int(sigma))
    image = cv2.GaussianBlur(rng.random((400, 300, 3)).astype(np.float32), (0, 0), sigma)
    box, reason = detect_face(np.clip(image, 0, 1), model=model)
    assert box is None and "skipped" in reason


def test_back_of_head_has_no_face(model):
    # A back view: a dark, hair-textured head ellipse on shoulders against a light background
    rng = np.random.default_rng(3)
    image = np.full((300, 240, 3), 0.6, np.float32)
    rows, cols = np.mgrid[0:300, 0:240]
    head = ((cols - 120) / 45.0) ** 2 + ((rows - 110) / 58.0) ** 2 < 1.0
    body = (rows > 170) & (np.abs(cols - 120) < 100 - (300 - rows) * 0.3)
    hair = 0.03 + 0.02 * cv2.GaussianBlur(rng.random((300, 240)).astype(np.float32), (0, 0), 1.5)
    image[head] = hair[head, None]
    image[body] = [0.2, 0.25, 0.4]
    box, reason = detect_face(image, model=model)
    assert box is None and "skipped" in reason


def test_a_face_below_the_minimum_size_is_skipped_with_that_reason(model):
    image = read_photo("pexels_woman_with_dog.jpg")
    box, reason = detect_face(image, model=model, min_size=200)
    assert box is None and "smaller than 200 px" in reason


def test_crop_rect_is_a_square_around_the_box():
    box = FaceBox(left=100.0, top=50.0, width=40.0, height=50.0, angle=0.0, neighbours=9)
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
