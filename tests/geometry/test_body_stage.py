"""The body stage: each found person's pose landmarks carried into the working crop, and the
body model fitted to them (the fit itself is tested in test_body_fit.py)."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from relightcli import compose
from relightcli.io.images import read_image
from relightcli.pipeline import RelightOptions
from relightcli.render.camera import render_pixel_geometry
from relightcli.render.scene import Scene
from relightcli.stages.body import stage_body
from relightcli.stages.crop import person_keypoints_in_crop, stage_crop
from relightcli.stages.frame import Frame, Models
from relightcli.stages.people import stage_people

DATA = Path(__file__).resolve().parents[1] / "data"


def test_keypoints_go_from_view_pixels_to_crop_pixel_indices():
    # The view is the photo at half size; the crop's 100 pixels cover photo [10, 210) x [20, 220)
    landmarks = np.zeros((33, 5))
    landmarks[0, :2] = (5.0 + 1.0, 10.0 + 1.0)  # photo (12, 22): 2 photo px = 1 crop px past the corner
    landmarks[1, :2] = (55.0, 60.0)  # photo (110, 120): the crop's centre
    person = SimpleNamespace(pose=SimpleNamespace(landmarks=landmarks))
    box = compose.CropBox(x0=10, y0=20, size=200, resolution=100)
    pixels = person_keypoints_in_crop(person, (0.5, 0.5), box)
    # Continuous coordinate 1.0 is the right edge of pixel 0: index 0.5
    np.testing.assert_allclose(pixels[0], (0.5, 0.5))
    np.testing.assert_allclose(pixels[1], (49.5, 49.5))


def test_no_person_gives_no_body():
    frame = Frame(image=np.zeros((8, 8, 3), np.float32), mask=None, env=None,
                  crop_mask=np.zeros((8, 8), np.float32))
    stage_body(frame, RelightOptions(resolution=8), Models(1))
    assert frame.bodies == [] and frame.notes["body"] == {"people": []}


@pytest.fixture(scope="module")
def tpose_frame():
    """The T-posed MakeHuman render through the people, crop and body stages at 256."""
    image = read_image(DATA / "tpose_render.png").rgb
    mask = (cv2.imread(str(DATA / "tpose_render_mask.png"), cv2.IMREAD_GRAYSCALE) > 127).astype(np.float32)
    frame = Frame(image=image, mask=mask, env=np.ones((8, 16, 3), np.float32))
    options, models = RelightOptions(resolution=256), Models(1)
    for stage in (stage_people, stage_crop, stage_body):
        stage(frame, options, models)
    return frame, models


def test_the_tpose_render_is_fitted_and_reported(tpose_frame):
    frame, _ = tpose_frame
    (note,) = frame.notes["body"]["people"]
    assert note["converged"] and note["reason"] == "" and note["seen_from"] == "front"
    assert note["residual_px"] < 3.0  # crop pixels at 256
    assert note["seconds"] > 0
    json.dumps(frame.notes["body"])  # the report is written as JSON


def test_the_fitted_tpose_body_lies_on_the_person(tpose_frame):
    """Seen by the crop camera the fitted body stays on the person's mask. It covers about 3/4
    of it (the outline band and the hands are missed: the fit has no silhouette term yet)."""
    frame, models = tpose_frame
    (fit,) = frame.bodies
    with Scene(fit.vertices, models.body_model().triangles) as scene:
        seen = render_pixel_geometry(scene, compose.CROP_RECT, (256, 256)).mask
    person = frame.crop_mask > 0.5
    assert seen[person].mean() > 0.7
    assert (seen & ~person).sum() < 0.05 * person.sum()


def test_the_pipeline_ray_traces_the_fitted_tpose_body():
    """The shipped models end to end on the T-pose render with its mask: the people are found
    although the input brings the mask, the body is fitted, and the coarse shading averages the
    reconstruction's with the body's."""
    from relightcli.batch import ItemReport
    from relightcli.pipeline import run_stages

    image = read_image(DATA / "tpose_render.png").rgb
    mask = (cv2.imread(str(DATA / "tpose_render_mask.png"), cv2.IMREAD_GRAYSCALE) > 127).astype(np.float32)
    env = np.full((8, 16, 3), 0.5, np.float32)
    env[2, 3] = 200.0  # a sun
    options = RelightOptions(outputs=("shading",), method="raytrace-norefine", resolution=128, spp=4, threads=1)
    frame, plan = run_stages(image, mask, env, options, ItemReport("tpose"))
    assert {"people", "body", "raytrace"} <= set(plan.run)
    assert frame.bodies[0].converged and frame.body_scene is not None
    assert frame.notes["raytrace"]["body"]["rays"] > 0
    inside = frame.crop_mask > 0.5
    assert np.isfinite(frame.shading).all() and frame.shading[inside].min() >= 0
    assert frame.shading[inside].mean() > 0


def test_the_body_layers_are_written_from_the_prior_maps_alone(tmp_path):
    """--outputs body_normal,body_depth plans the body and its maps, no geometry net and no
    ray tracing; the PNG holds the camera-facing normals, the EXR front z >= back z."""
    from relightcli.batch import ItemReport
    from relightcli.pipeline import run_stages, write_layer

    image = read_image(DATA / "tpose_render.png").rgb
    mask = (cv2.imread(str(DATA / "tpose_render_mask.png"), cv2.IMREAD_GRAYSCALE) > 127).astype(np.float32)
    options = RelightOptions(outputs=("body_normal", "body_depth"), resolution=128, threads=1)
    frame, plan = run_stages(image, mask, np.ones((8, 16, 3), np.float32), options, ItemReport("tpose"))
    assert plan.run == ["people", "mask", "crop", "body", "body_maps"]
    write_layer("body_normal", tmp_path / "n.png", frame, options)
    write_layer("body_depth", tmp_path / "d.exr", frame, options)
    depth = read_image(tmp_path / "d.exr").rgb
    body = depth[..., 2] > 0.5
    assert depth.shape[:2] == image.shape[:2] and body.sum() > 0.5 * (mask > 0.5).sum()
    assert (depth[..., 0][body] >= depth[..., 1][body]).all()
    assert (depth[..., 0] - depth[..., 1])[body].mean() > 0.05  # crop units: a body has thickness
    normal = read_image(tmp_path / "n.png", srgb=False).rgb * 2.0 - 1.0
    assert np.median(normal[..., 2][body]) > 0.5  # the body faces the camera
    np.testing.assert_allclose(normal[depth[..., 2] == 0], -1.0)  # black off the body


def test_a_shipped_lifter_gives_the_fit_its_landmarks(tpose_frame, monkeypatch):
    """With lift.onnx in the models folder the fit reads the lifted world landmarks and the
    image landmarks' depths made from them (relightcli.nets.lift.image_depths)."""
    import copy

    from relightcli.nets.lift import image_depths
    from relightcli.stages import body

    frame = copy.copy(tpose_frame[0])
    frame.notes = {}
    pose = frame.people[0].pose
    shift = np.array([0.0, 0.0, 0.1])
    seen = {}
    lifter = SimpleNamespace(lift=lambda landmarks, world: world + shift)
    models = SimpleNamespace(body_model=tpose_frame[1].body_model, has=lambda name: name == "lift",
                             get=lambda name: lifter)
    monkeypatch.setattr(body, "_fit_on_one_opencv_thread", lambda *args: seen.update(world=args[3]) or
                        SimpleNamespace(residual_px=0.0, converged=False, reason="stub"))
    monkeypatch.setattr(body, "depth_side", lambda landmarks: seen.update(landmarks=landmarks))
    stage_body(frame, RelightOptions(resolution=256), models)
    np.testing.assert_allclose(seen["world"], pose.world + shift)
    np.testing.assert_allclose(seen["landmarks"], image_depths(pose.landmarks, pose.world + shift))
