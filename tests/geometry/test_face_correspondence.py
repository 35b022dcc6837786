"""The shipped face mesh -> iBUG table, and the face stage on an evaluation scene."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from relightcli.geometry.face import face_box_around, face_crop_rect
from relightcli.geometry.face_correspondence import IBUG_LANDMARKS, MESH_POINTS, load_correspondence
from relightcli.nets.manifest import sha256_file

REPO = Path(__file__).resolve().parents[2]


def test_table_is_small_and_matches_its_manifest_entry():
    entry = json.loads((REPO / "models" / "manifest.json").read_text())["models"]["face_correspondence"]
    path = REPO / "models" / entry["file"]
    assert entry["kind"] == "data" and "MIT" in entry["license"] and "Apache-2.0" in entry["license"]
    assert sha256_file(path) == entry["sha256"] and path.stat().st_size < 4096


def test_table_maps_every_landmark_to_mesh_points_with_unit_weights():
    table = load_correspondence()
    assert table.mesh_points.shape == table.weights.shape and table.mesh_points.shape[0] == IBUG_LANDMARKS
    assert 0 <= table.mesh_points.min() and table.mesh_points.max() < MESH_POINTS
    np.testing.assert_allclose(table.weights.sum(axis=1), 1.0)
    # a mesh whose points all sit at one place gives landmarks there; a shifted mesh shifts them
    mesh = np.random.default_rng(0).uniform(0, 100, (MESH_POINTS, 2))
    np.testing.assert_allclose(table.landmarks(mesh + [3.0, -2.0]), table.landmarks(mesh) + [3.0, -2.0])


def test_left_and_right_landmarks_come_from_different_mesh_points():
    # iBUG's eye corners 36 / 45 and mouth corners 48 / 54 mirror each other
    table = load_correspondence()
    for left, right in ((36, 45), (48, 54), (0, 16)):
        assert set(table.mesh_points[left]).isdisjoint(table.mesh_points[right])


def test_face_box_frames_the_landmarks_as_the_canonical_crop():
    landmarks = np.array([[40.0, 50.0], [80.0, 50.0], [60.0, 100.0]])
    crop = face_crop_rect(face_box_around(landmarks))
    assert crop.size == round(2.1 * 50)
    assert abs(crop.left + crop.size / 2 - 60.5) <= 0.5
    assert abs(crop.top + crop.size / 2 - (75.5 - 0.08 * crop.size)) <= 0.5


def test_the_face_stage_fits_the_face_of_an_evaluation_scene():
    folder = REPO / "data" / "evalval512" / "val_000001"
    if not folder.is_dir():
        pytest.skip("the validation scenes are not here (data/evalval512)")
    import sys

    sys.path.insert(0, str(REPO / "bench"))
    from face_hits import face_note

    from relightcli.evaluate import load_scene
    from relightcli.pipeline import RelightOptions
    from relightcli.stages.frame import Models

    options = RelightOptions(threads=1)
    note, _ = face_note(load_scene(folder), options, Models(1))
    assert "skipped" not in note, note
    face, = note["faces"]
    assert face["path"] == "face mesh" and face["head"] == "person 0"
    assert face["residual_px"] < 2.0 and face["landmarks"] == 68


def _frame_without_a_face(pixel_value):
    from relightcli.pipeline import RelightOptions
    from relightcli.stages.crop import stage_crop
    from relightcli.stages.frame import Frame

    image = np.full((120, 90, 3), pixel_value, np.float32)
    mask = np.zeros((120, 90), np.float32)
    mask[20:110, 30:60] = 1.0
    frame = Frame(image=image, mask=mask, env=np.ones((4, 8, 3), np.float32))
    stage_crop(frame, RelightOptions(resolution=64), None)
    return frame


@pytest.mark.parametrize("pixel_value", [0.4, np.nan])
def test_no_people_and_no_face_skips_with_the_reason(pixel_value):
    from relightcli.stages.face import stage_face
    from relightcli.stages.frame import Models

    frame = _frame_without_a_face(pixel_value)
    stage_face(frame, None, Models(1))
    assert frame.faces == []
    assert "person crop (no person found): no face detected" in frame.notes["face"]["skipped"]


def test_a_head_outside_the_photo_skips_with_the_reason():
    from relightcli.nets.blaze import Detection
    from relightcli.nets.pose import Person, Pose
    from relightcli.stages.face import stage_face
    from relightcli.stages.frame import Models

    frame = _frame_without_a_face(0.4)
    landmarks = np.zeros((33, 5))
    landmarks[:11, :2] = np.random.default_rng(0).uniform(900, 910, (11, 2))
    rect = None  # the pose's own crops play no part here
    pose = Pose(rect, 1.0, landmarks, np.zeros((33, 3)), np.zeros((120, 90), np.float32), rect)
    frame.people = [Person(Detection(np.zeros(4), np.zeros((4, 2)), 0.9), pose)]
    stage_face(frame, None, Models(1))
    assert frame.faces == [] and "person 0: the head square lies outside the photo" in frame.notes["face"]["skipped"]


def test_a_two_person_photo_gets_two_face_fits():
    """Every person's face takes the face path, each with its own fit and face crop: the skier
    beside his mirror image."""
    from relightcli.io.images import read_image
    from relightcli.pipeline import RelightOptions
    from relightcli.stages import STAGES
    from relightcli.stages.frame import Frame, Models

    skier = read_image(REPO / "examples" / "skier.jpg").rgb
    photo = np.concatenate([skier, skier[:, ::-1]], axis=1)
    frame = Frame(image=photo, mask=None, env=np.ones((4, 8, 3), np.float32))
    options, models = RelightOptions(resolution=256, threads=1), Models(1)
    for stage in ("people", "mask", "crop", "geometry", "face"):
        STAGES[stage](frame, options, models)
    note = frame.notes["face"]
    assert [face["head"] for face in note["faces"]] == ["person 0", "person 1"], note
    assert note["fitted"] == 2 and [face.head for face in frame.faces] == ["person 0", "person 1"]
    left, right = (face.crop for face in frame.faces)
    assert left.left + left.size <= right.left  # two faces, one crop each, side by side
    assert "skipped" not in note


def test_two_heads_on_one_face_fit_it_once():
    """Two people one behind the other can place their head squares on the same face: it is
    fitted once, and the report says whose face the second head found."""
    from relightcli.io.images import read_image
    from relightcli.pipeline import RelightOptions
    from relightcli.stages import STAGES
    from relightcli.stages.frame import Frame, Models

    frame = Frame(image=read_image(REPO / "examples" / "skier.jpg").rgb, mask=None, env=np.ones((4, 8, 3), np.float32))
    options, models = RelightOptions(resolution=256, threads=1), Models(1)
    STAGES["people"](frame, options, models)
    frame.people = frame.people * 2
    for stage in ("mask", "crop", "geometry", "face"):
        STAGES[stage](frame, options, models)
    first, second = frame.notes["face"]["faces"]
    assert first["path"] == "face mesh" and second["skipped"] == "the same face as person 0's"
    assert len(frame.faces) == 1
