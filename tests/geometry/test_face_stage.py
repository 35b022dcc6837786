"""The face stage around the fit: crop geometry, the skip path, and the coarse face shading.
(The face chain itself is tested in tests/nets/test_face_mesh.py and
test_face_correspondence.py.)"""

from __future__ import annotations

import numpy as np
import pytest

from relightcli.geometry.face import (
    crop_to_image,
    cut_crop,
    fit_face_to_landmarks,
    image_to_crop,
    render_face_shading,
)
from relightcli.geometry.face_detect import CropRect
from relightcli.geometry.face_fit import fit_face
from relightcli.geometry.face_model import FaceModel, rotation_matrix, transform, world_to_pixel
from relightcli.render import EnvironmentLight

RECT = (-0.5, 0.5, 1.2, 2.2)
SCALE = 0.05  # world units per cm: 6.4 px per cm on the 128 crop


@pytest.fixture(scope="module")
def model():
    return FaceModel.load()


# --- crops -----------------------------------------------------------------------------------

def test_crop_and_image_pixels_map_back_and_forth():
    crop = CropRect(left=-7, top=13, size=90, resolution=128)
    points = np.random.default_rng(1).uniform(-5, 130, (20, 2))
    np.testing.assert_allclose(image_to_crop(crop_to_image(points, crop), crop), points, atol=1e-9)


def test_cut_crop_is_pixel_aligned_with_the_mapping():
    # A linear ramp image: its value is the column, so a crop pixel must read the image
    # column its centre maps to (bilinear enlargement is exact on a ramp)
    cols = np.tile(np.arange(200, dtype=np.float32), (200, 1))
    image = np.stack([cols, cols.T, cols], axis=-1)
    crop = CropRect(left=40, top=50, size=64, resolution=128)
    cut = cut_crop(image, crop)
    inner = (slice(4, -4), slice(4, -4))
    rows, columns = np.mgrid[0:128, 0:128]
    mapped = crop_to_image(np.stack([columns.ravel(), rows.ravel()], 1), crop).reshape(128, 128, 2)
    np.testing.assert_allclose(cut[..., 0][inner], mapped[..., 0][inner], atol=1e-3)
    np.testing.assert_allclose(cut[..., 1][inner], mapped[..., 1][inner], atol=1e-3)


def test_cut_crop_pads_outside_the_image_with_zeros():
    image = np.ones((80, 40, 3), np.float32)
    cut = cut_crop(image, CropRect(left=-40, top=0, size=80, resolution=80))
    assert np.all(cut[:, :38] == 0) and np.all(cut[:, 42:] == 1)


# --- skip path -------------------------------------------------------------------------------

def test_scattered_landmarks_skip_with_the_reason(model):
    points = np.random.default_rng(0).uniform(100, 300, (68, 2))
    fit, info = fit_face_to_landmarks(points, (512, 512), model=model)
    assert fit is None
    assert "face stage skipped" in info["skipped"] and info["residual_px"] > 0
    assert info["landmarks"] == 68 and len(info["crop"]) == 4


# --- coarse face shading ----------------------------------------------------------------------

@pytest.fixture(scope="module")
def fitted(model):
    identity = np.random.default_rng(4).normal(0.0, 1.0, model.n_identity)
    rotation = rotation_matrix(20.0, -5.0, 5.0)
    points = transform(model.landmarks(identity), SCALE, rotation, np.array([0.0, 1.7, 0.0]))
    pixels = world_to_pixel(points, RECT, (128, 128))
    return fit_face(pixels, model, RECT, (128, 128), landmark_sigma_px=0.1), pixels


def test_face_shading_under_a_constant_sky_is_the_furnace_value(fitted):
    fit, _ = fitted
    radiance = np.array([0.5, 1.0, 2.0], np.float32)
    shading, face = render_face_shading(fit, EnvironmentLight(np.broadcast_to(radiance, (8, 16, 3))),
                                        spp=16, target_error=None)
    assert shading.shape == (128, 128, 3) and face.shape == (128, 128)
    assert np.all(np.isfinite(shading)) and np.all(shading >= 0)
    ratio = shading[face] / radiance
    # Unoccluded skin sees the whole sky (ratio 1); eye sockets, nostrils and the parts the
    # nose shades see less, never more
    assert np.median(ratio) > 0.85 and ratio.max() <= 1.0 + 1e-4


def test_face_shading_is_aligned_with_the_fitted_landmarks(fitted):
    fit, pixels = fitted
    shading, face = render_face_shading(fit, EnvironmentLight(np.ones((8, 16, 3), np.float32)),
                                        spp=64, target_error=None)
    lit = shading.sum(axis=2) > 0
    # the face is where the head is lit (a few pixels in the closed mouth's slit and the
    # nostrils see no sky)
    assert np.mean(face & ~lit) < 0.001
    inner = np.rint(pixels[17:]).astype(int)          # brows, nose, eyes, mouth
    assert face[inner[:, 1], inner[:, 0]].all()
    # The same face region seen through the camera module on the face-only mesh
    from relightcli.geometry.face_fit import face_mesh
    from relightcli.render import Scene, render_pixel_geometry

    seen = render_pixel_geometry(Scene.from_trimesh(face_mesh(fit, face_only=True).to_trimesh()), RECT, (128, 128)).mask
    assert np.sum(face & seen) / np.sum(face | seen) > 0.97


def test_face_shading_at_a_finer_resolution_covers_the_same_square(fitted):
    fit, _ = fitted
    light = EnvironmentLight(np.ones((8, 16, 3), np.float32))
    _, coarse = render_face_shading(fit, light, spp=4, target_error=None)
    _, fine = render_face_shading(fit, light, resolution=256, spp=4, target_error=None)
    downsampled = fine.reshape(128, 2, 128, 2).mean(axis=(1, 3))
    assert np.mean(np.abs(downsampled - coarse)) < 0.02


def test_a_face_rendered_ahead_is_taken_only_under_its_own_environment(monkeypatch):
    """The pipeline's side line renders the fitted faces ahead under the one environment
    (stages.face.render_faces_ahead); under another (a turntable's next map) the face is
    rendered again."""
    from relightcli.stages import face as face_stage
    from relightcli.stages.frame import FoundFace, Frame

    calls = []
    monkeypatch.setattr(face_stage, "render_face", lambda frame, face, options, models: calls.append(frame.env) or
                        (f"render under {len(calls)}", None))
    sky, turned = np.ones((4, 8, 3), np.float32), np.ones((4, 8, 3), np.float32)
    frame = Frame(image=None, mask=None, env=sky)
    face = FoundFace("person 0", fit=None, crop=None)
    face_stage.render_faces_ahead(Frame(image=None, mask=None, env=sky, faces=[face]), None, None)
    assert face.rendered[0] is sky and len(calls) == 1
    assert face_stage.rendered_face(frame, face, None, None) == ("render under 1", None) and len(calls) == 1
    frame.env = turned  # equal values, another map: rendered again
    assert face_stage.rendered_face(frame, face, None, None) == ("render under 2", None) and calls[-1] is turned
