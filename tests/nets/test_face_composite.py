"""The face path's last step: the face refinement net runs on the face crop and its answer is
blended back into the body's shading over the fitted face, pixel-aligned, nowhere else."""

from __future__ import annotations

import numpy as np
import pytest

onnx = pytest.importorskip("onnx")
from onnx import helper  # noqa: E402
from onnx_toys import contract, save_graph, scalar, tensor, write_manifest  # noqa: E402

from relightcli import compose  # noqa: E402
from relightcli.geometry.face import CropRect, cut_crop, face_blend_weight, paste_crop  # noqa: E402
from relightcli.geometry.face_fit import fit_face  # noqa: E402
from relightcli.geometry.face_model import FaceModel, rotation_matrix, transform, world_to_pixel  # noqa: E402
from relightcli.nets.refine import FaceRefineNet  # noqa: E402
from relightcli.pipeline import RelightOptions  # noqa: E402
from relightcli.stages.face import stage_face_refine  # noqa: E402
from relightcli.stages.frame import FoundFace, Frame, Models  # noqa: E402


@pytest.fixture
def face_net_dir(tmp_path):
    """Model "face_refine": shading = face_shading + 0 * body_shading (shows the coarse face)."""
    nodes = [helper.make_node("Mul", ["body_shading", "zero"], ["body_zero"]),
             helper.make_node("Add", ["face_shading", "body_zero"], ["shading"])]
    save_graph(tmp_path / "face.onnx", nodes, [tensor("body_shading", 3), tensor("face_shading", 3)],
               [tensor("shading", 3)], initializer=[scalar("zero", 0.0)])
    write_manifest(tmp_path, {"face_refine": {
        "file": "face.onnx", "inputs": contract([("body_shading", 3), ("face_shading", 3)]),
        "outputs": contract([("shading", 3)]), "multiple": 8}})
    return tmp_path


class ToyModels(Models):
    def __init__(self, directory):
        super().__init__(threads=1)
        self._sessions["face_refine"] = FaceRefineNet(models_dir=directory, threads=1)


def test_paste_crop_undoes_cut_crop_and_keeps_the_rest():
    image = np.random.default_rng(0).uniform(0, 1, (60, 50, 3)).astype(np.float32)
    crop = CropRect(left=10, top=-4, size=32, resolution=32)  # reaches above the image
    pasted = paste_crop(np.zeros_like(image), cut_crop(image, crop), np.ones((32, 32)), crop)
    np.testing.assert_allclose(pasted[0:28, 10:42], image[0:28, 10:42], atol=1e-6)
    assert np.all(pasted[28:] == 0) and np.all(pasted[:, :10] == 0) and np.all(pasted[:, 42:] == 0)
    untouched = paste_crop(image, np.ones((32, 32, 3)), np.zeros((32, 32)), crop)
    np.testing.assert_array_equal(untouched, image)


def test_a_log_blend_holds_the_patch_within_its_bound_of_the_image():
    image = np.full((40, 40, 3), 0.5, np.float32)
    crop = CropRect(left=4, top=4, size=32, resolution=32)
    patch = np.full((32, 32, 3), 5.0, np.float32)  # 10x the image
    patch[:, :16] = 0.4  # 0.8x: within the bound
    weight = np.ones((32, 32), np.float32)
    weight[:, 24:] = 0.5
    out = paste_crop(image, patch, weight, crop, log_bound=np.log(2.0))
    np.testing.assert_allclose(out[4:36, 4:20], 0.4, rtol=1e-5)
    np.testing.assert_allclose(out[4:36, 20:28], 1.0, rtol=1e-5)  # at most 2x the image
    np.testing.assert_allclose(out[4:36, 28:36], 0.5 * np.sqrt(2.0), rtol=1e-5)  # half-way, in log
    assert np.all(out[:4] == 0.5) and np.all(out[:, :4] == 0.5)


def test_blend_weight_stays_inside_the_face_and_reaches_one():
    face = np.zeros((128, 128), bool)
    face[30:100, 40:90] = True
    weight = face_blend_weight(face)
    assert weight.dtype == np.float32 and 0.0 <= weight.min() and weight.max() <= 1.0
    assert np.all(weight[~face] < 0.01)  # the outline never shows
    assert weight[65, 65] > 0.999


def test_face_refinement_composites_the_face_net_answer_over_the_face(face_net_dir):
    model = FaceModel.load()
    size = 256
    crop = CropRect(left=100, top=12, size=64, resolution=128)
    rect = crop.world_rect(compose.CROP_RECT, (size, size))
    scale_cm = (rect[1] - rect[0]) / 128 / 0.16  # ~6 px of the face crop per cm
    centre = np.array([(rect[0] + rect[1]) / 2, (rect[2] + rect[3]) / 2 - 0.3 * scale_cm, 0.0])
    points = transform(model.landmarks(), scale_cm, rotation_matrix(10.0, 0.0, 0.0), centre)
    fit = fit_face(world_to_pixel(points, rect, (128, 128)), model, rect, (128, 128), landmark_sigma_px=0.1)

    radiance = np.float32(2.0)
    # A soft person mask (a ramp at the left, as the crop's anti-aliased edges): the body's
    # shading is already multiplied by it, and must not be multiplied again
    crop_mask = np.ones((size, size), np.float32)
    crop_mask[:, :40] = np.linspace(0.0, 1.0, 40, dtype=np.float32)
    body = 0.5 * np.repeat(crop_mask[..., None], 3, axis=2)
    frame = Frame(image=np.zeros((size, size, 3), np.float32), mask=None,
                  env=np.full((8, 16, 3), radiance, np.float32))
    frame.crop_mask = crop_mask
    frame.shading, frame.faces = body.copy(), [FoundFace("person 0", fit, crop)]
    stage_face_refine(frame, RelightOptions(spp=16, threads=1), ToyModels(face_net_dir))

    window = (slice(crop.top, crop.top + crop.size), slice(crop.left, crop.left + crop.size))
    outside = np.ones((size, size), bool)
    outside[window] = False
    np.testing.assert_array_equal(frame.shading[outside], body[outside])  # nothing else moves
    changed = np.abs(frame.shading[window] - body[window]).max(axis=-1) > 0.05
    assert changed.sum() > 300  # the face (a ~40 x 50 px region of the person crop)
    # Deep inside the face the net's answer (the coarse face: ~2 under a uniform sky of 2) wins,
    # held at twice the body's shading (FACE_LOG_BOUND)
    centre_row, centre_col = crop.top + crop.size // 2, crop.left + crop.size // 2
    centre = frame.shading[centre_row - 4:centre_row + 5, centre_col - 4:centre_col + 5].mean(axis=-1)
    assert 0.95 < np.median(centre) and centre.max() <= 2.0 * 0.5 * (1 + 1e-5)
    assert frame.notes["face_refine"]["faces"][0]["face_pixels"] > 1000


def test_face_refinement_without_a_face_changes_nothing(face_net_dir):
    frame = Frame(image=np.zeros((64, 64, 3), np.float32), mask=None, env=np.ones((8, 16, 3), np.float32))
    frame.shading = np.full((64, 64, 3), 0.5, np.float32)
    frame.notes["face"] = {"skipped": "no frontal or profile face found"}
    stage_face_refine(frame, RelightOptions(), ToyModels(face_net_dir))
    assert np.all(frame.shading == 0.5)
    assert "no frontal" in frame.notes["face_refine"]["skipped"]
