"""The face chain (relightcli.nets.face_mesh): its SSD anchors and decoding on synthetic raw
tensors, the regions of interest, and the shipped face detector + face mesh on real photos."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from relightcli.nets.blaze import Detection, RotatedRect, decode_detections, ssd_anchors
from relightcli.nets.face_mesh import (
    DETECTOR_ANCHORS,
    MESH_POINTS,
    FaceDetector,
    FaceMesh,
    face_rect,
    find_face,
    head_rect,
)

REPO = Path(__file__).resolve().parents[2]
PHOTOS = REPO / ".." / "shared" / "data" / "photos"


def photo(path: Path) -> np.ndarray:
    if not path.is_file():
        pytest.skip(f"{path} is not here")
    return cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0


@pytest.fixture(scope="module")
def nets():
    return FaceDetector(threads=1), FaceMesh(threads=1)


def test_short_range_detector_has_896_anchors_on_two_grids():
    anchors = ssd_anchors(DETECTOR_ANCHORS)
    assert anchors.shape == (896, 2)
    # 16 x 16 cells x 2 anchors at stride 8, then 8 x 8 cells x 6 anchors (three layers of stride 16)
    np.testing.assert_allclose(anchors[0], [0.5 / 16, 0.5 / 16])
    np.testing.assert_allclose(anchors[511], [15.5 / 16, 15.5 / 16])
    np.testing.assert_allclose(anchors[512:518], np.tile([0.5 / 8, 0.5 / 8], (6, 1)))


def test_decoding_places_the_box_and_keypoints_from_their_anchor():
    anchors = ssd_anchors(DETECTOR_ANCHORS)
    boxes = np.zeros((896, 16), np.float32)
    scores = np.full(896, -20.0, np.float32)
    k = 600
    boxes[k, :4] = [6.4, -12.8, 32.0, 16.0]   # centre offset and size, 128 px units
    boxes[k, 4:6] = [-8.0, 0.0]               # first keypoint offset
    scores[k] = 3.0
    box, keypoints, score = decode_detections(boxes, scores, anchors, 128, 0.5)
    centre = anchors[k] + [0.05, -0.1]
    np.testing.assert_allclose(box, [[centre[0] - 0.125, centre[1] - 0.0625, centre[0] + 0.125, centre[1] + 0.0625]])
    np.testing.assert_allclose(keypoints[0, 0], anchors[k] + [-0.0625, 0.0])
    np.testing.assert_allclose(score, [1.0 / (1.0 + np.exp(-3.0))])


def test_face_rect_levels_the_eyes_and_scales_the_box():
    eyes = np.array([[40.0, 50.0], [60.0, 30.0]] + [[0.0, 0.0]] * 4)  # left eye up-right of the right eye
    rect = face_rect(Detection(np.array([30.0, 20.0, 70.0, 80.0]), eyes, 0.9))
    assert rect.centre == (50.0, 50.0) and rect.width == rect.height == pytest.approx(90.0)
    # the crop's +u axis runs along right eye -> left eye
    u_axis = rect.corners()[1] - rect.corners()[0]
    np.testing.assert_allclose(u_axis / np.linalg.norm(u_axis), [np.sqrt(0.5), -np.sqrt(0.5)], atol=1e-9)


def test_head_rect_is_a_square_around_the_pose_face_landmarks():
    landmarks = np.zeros((33, 5))
    landmarks[:11, :2] = np.random.default_rng(0).uniform(90, 110, (11, 2))
    landmarks[5, :2], landmarks[2, :2] = (95, 100), (105, 100)  # eyes level
    rect = head_rect(landmarks)
    assert rect.rotation == 0.0 and rect.width == rect.height
    assert np.all(np.abs(landmarks[:11, :2] - rect.centre) <= rect.width / 6 + 1e-9)


@pytest.mark.parametrize("name", ["pexels_portrait_woman.png", "pexels_portrait_face_paint.png"])
def test_finds_the_face_in_a_portrait(nets, name):
    image = photo(PHOTOS / name)
    face, why = find_face(image, None, *nets)
    assert face is not None, why
    points = face.mesh.points
    assert points.shape == (MESH_POINTS, 3) and face.mesh.presence >= 0.5
    # the face fills much of a portrait and lies inside the detector's box (grown by a margin)
    x0, y0, x1, y1 = face.detection.box
    margin = 0.3 * (x1 - x0)
    assert np.all((points[:, 0] > x0 - margin) & (points[:, 0] < x1 + margin))
    assert np.all((points[:, 1] > y0 - margin) & (points[:, 1] < y1 + margin))
    assert x1 - x0 > 0.2 * image.shape[1]


def test_the_skiers_small_face_is_found_in_the_head_square_but_not_in_the_whole_photo(nets):
    from relightcli.nets.pose import PersonDetector, PoseLandmarker, find_people

    image = photo(REPO / "examples" / "skier.jpg")
    people = [p for p in find_people(image, PersonDetector(threads=1), PoseLandmarker(threads=1)) if p.found]
    face, why = find_face(image, head_rect(people[0].pose.landmarks), *nets)
    assert face is not None, why
    nose = people[0].pose.landmarks[0, :2]
    assert np.linalg.norm(face.mesh.points[:, :2].mean(axis=0) - nose) < 20  # the face is ~30 px
    assert find_face(image, None, *nets)[0] is None


def test_a_head_square_outside_the_photo_skips_with_the_reason(nets):
    image = np.full((100, 80, 3), 0.5, np.float32)
    face, why = find_face(image, RotatedRect((500.0, 50.0), 40.0, 40.0, 0.0), *nets)
    assert face is None and "outside the photo" in why


def test_a_degenerate_head_square_skips_with_the_reason(nets):
    image = np.full((100, 80, 3), 0.5, np.float32)
    face, why = find_face(image, RotatedRect((40.0, 50.0), 0.0, 0.0, 0.0), *nets)
    assert face is None and "degenerate" in why


def test_nan_pixels_count_as_black_and_find_no_face(nets):
    image = np.full((64, 64, 3), np.nan, np.float32)
    face, why = find_face(image, None, *nets)
    assert face is None and "no face detected" in why


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_texture_has_no_face(nets, seed):
    image = np.random.default_rng(seed).random((360, 280, 3)).astype(np.float32)
    face, why = find_face(image, None, *nets)
    assert face is None and why


def test_back_of_head_has_no_face(nets):
    # A back view: a dark, hair-textured head ellipse on shoulders against a light background
    rng = np.random.default_rng(3)
    image = np.full((300, 240, 3), 0.6, np.float32)
    rows, cols = np.mgrid[0:300, 0:240]
    head = ((cols - 120) / 45.0) ** 2 + ((rows - 110) / 58.0) ** 2 < 1.0
    body = (rows > 170) & (np.abs(cols - 120) < 100 - (300 - rows) * 0.3)
    hair = 0.03 + 0.02 * cv2.GaussianBlur(rng.random((300, 240)).astype(np.float32), (0, 0), 1.5)
    image[head] = hair[head, None]
    image[body] = [0.2, 0.25, 0.4]
    face, why = find_face(image, None, *nets)
    assert face is None and why
