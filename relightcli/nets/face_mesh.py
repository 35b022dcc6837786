"""The face in a photo from MediaPipe's face detector and face mesh (converted by
`python -m export.perception`): 468 face points and the net's confidence that they are a face.

The chain, after MediaPipe's holistic and face graphs (modules/holistic_landmark,
modules/face_detection, modules/face_landmark): a head square placed by the pose's face
landmarks (0-10: nose, eyes, ears, mouth; turned from the right eye to the left, x3; a face
in a full-body shot is too small for the short-range detector on the whole photo) -> crop 128
-> detector -> decode on SSD anchors -> weighted NMS -> the best detection's box, turned from
its right eye to its left, x1.5, square -> crop 192 -> face mesh -> 468 points back into the
photo. Either confidence below 0.5 means no face (the thresholds reject false hits).

Images here are sRGB-encoded RGB in [0, 1], (H, W, 3) float32, as the nets were trained on;
points are continuous photo pixels (relightcli.nets.blaze).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from relightcli.nets.blaze import (
    AnchorSpec,
    Detection,
    RegionNet,
    RotatedRect,
    crop_rect,
    crop_to_photo,
    decode_detections,
    net_input,
    rect_around_points,
    sigmoid,
    ssd_anchors,
    weighted_nms,
)
from relightcli.nets.session import ModelSession

DETECTOR_ANCHORS = AnchorSpec(input_size=128, strides=(8, 16, 16, 16))
MIN_DETECTION_SCORE = 0.5   # MediaPipe's face detection threshold
NMS_IOU = 0.3
MIN_FACE_PRESENCE = 0.5     # the face mesh's face flag (MediaPipe's ThresholdingCalculator)
FACE_ROI_SCALE = 1.5        # the face mesh's crop around the detector's box
HEAD_CROP_SCALE = 3.0       # the detector's crop around the pose's face landmarks (holistic)
MESH_POINTS = 468
DETECTOR_RIGHT_EYE, DETECTOR_LEFT_EYE = 0, 1   # of the detector's 6 keypoints
POSE_FACE = slice(0, 11)                        # BlazePose's face landmarks
POSE_RIGHT_EYE, POSE_LEFT_EYE = 5, 2


def _eye_rotation(right_eye: np.ndarray, left_eye: np.ndarray) -> float:
    """The rotation (radians, blaze convention) that makes the right -> left eye line
    horizontal (MediaPipe's rotation vector with target angle 0)."""
    dx, dy = float(left_eye[0] - right_eye[0]), float(left_eye[1] - right_eye[1])
    return float(-np.arctan2(-dy, dx))


def head_rect(pose_landmarks: np.ndarray, scale: float = HEAD_CROP_SCALE) -> RotatedRect:
    """The square the face detector looks in: around the pose's face landmarks
    (`pose_landmarks` (33, >=2) photo pixels, BlazePose order), turned so the eyes are level,
    its side `scale` x the landmarks' extent."""
    points = np.asarray(pose_landmarks, np.float64)[POSE_FACE, :2]
    rotation = _eye_rotation(points[POSE_RIGHT_EYE], points[POSE_LEFT_EYE])
    return rect_around_points(points, rotation, scale)


def whole_image_rect(height: int, width: int) -> RotatedRect:
    """The upright square around the whole (height, width) image (letterboxed search)."""
    side = float(max(height, width))
    return RotatedRect((width / 2.0, height / 2.0), side, side, 0.0)


def face_rect(detection: Detection, scale: float = FACE_ROI_SCALE) -> RotatedRect:
    """The face mesh's square from a face detection (photo pixels): centred on its box, its
    side `scale` x the box's longer side, turned so the detected eyes are level."""
    x0, y0, x1, y1 = (float(v) for v in detection.box)
    rotation = _eye_rotation(detection.keypoints[DETECTOR_RIGHT_EYE], detection.keypoints[DETECTOR_LEFT_EYE])
    side = max(x1 - x0, y1 - y0) * scale
    return RotatedRect(((x0 + x1) / 2.0, (y0 + y1) / 2.0), side, side, rotation)


class FaceDetector(ModelSession):
    model_name = "face_detector"
    input_names = ("image",)
    output_names = ("boxes", "scores")

    def detect(self, image: np.ndarray, rect: RotatedRect,
               min_score: float = MIN_DETECTION_SCORE) -> list[Detection]:
        """Faces in the square `rect` of `image` (H, W, 3) sRGB in [0, 1], best first: an
        axis-aligned box in photo pixels (of the rect's rotated box) and 6 keypoints (right
        eye, left eye, nose tip, mouth, right ear, left ear) in photo pixels. Outside the
        photo the crop is black, as in MediaPipe's letterbox."""
        size = DETECTOR_ANCHORS.input_size
        crop = crop_rect(image, rect, size, border=cv2.BORDER_CONSTANT)
        out = self.run({"image": net_input(crop, self.entry.config.get("value_range", (-1.0, 1.0)))})
        boxes, keypoints, scores = decode_detections(out["boxes"][0], out["scores"][0, :, 0],
                                                     ssd_anchors(DETECTOR_ANCHORS), size, min_score)
        detections = []
        for box, points, score in weighted_nms(boxes, keypoints, scores, NMS_IOU):
            corners = crop_to_photo(rect, box[[0, 1, 2, 3, 0, 3, 2, 1]].reshape(4, 2))
            photo_box = np.concatenate([corners.min(axis=0), corners.max(axis=0)])
            detections.append(Detection(photo_box, crop_to_photo(rect, points), score))
        return detections


@dataclass
class FaceLandmarks:
    """The face mesh's answer in one square: `points` (468, 3) x, y photo pixels and z
    (photo pixels, towards the camera negative, relative to the face's centre), `presence`
    the net's probability that the square holds a face."""

    rect: RotatedRect
    presence: float
    points: np.ndarray


class FaceMesh(RegionNet):
    model_name = "face_mesh"
    input_names = ("image",)
    output_names = ("landmarks", "face_flag")

    def landmarks(self, image: np.ndarray, rect: RotatedRect) -> FaceLandmarks:
        """The face mesh in `rect` of `image` (H, W, 3) sRGB in [0, 1]."""
        size = self.crop_size
        out = self.run_region(image, rect)
        raw = out["landmarks"].reshape(-1, 3).astype(np.float64)
        points = np.hstack([crop_to_photo(rect, raw[:, :2] / size), raw[:, 2:3] / size * rect.width])
        # the face flag is a logit (MediaPipe applies the sigmoid after the graph)
        return FaceLandmarks(rect, float(sigmoid(out["face_flag"].reshape(-1)[0])), points)


@dataclass
class Face:
    """A face found: the detection in the photo, and the face mesh's points."""

    detection: Detection
    mesh: FaceLandmarks

    def summary(self, scale=(1.0, 1.0)) -> dict:
        """What the report says of this face, in pixels of a photo `scale` (sx, sy) times
        smaller than the one the face was found in (1: that photo's pixels)."""
        box = (np.reshape(self.detection.box, (2, 2)) / scale).reshape(-1)
        return {"detection_score": round(self.detection.score, 3),
                "face_presence": round(self.mesh.presence, 3),
                "detection_box_photo": [round(float(v), 1) for v in box]}


def find_face(image: np.ndarray, head: RotatedRect | None, detector: FaceDetector,
              mesh: FaceMesh) -> tuple[Face | None, str]:
    """The most confident face in the square `head` of `image` (H, W, 3) sRGB in [0, 1]
    (None: the whole image), with its 468 face mesh points, or (None, why not). NaN pixels
    count as black."""
    height, width = image.shape[:2]
    rect = whole_image_rect(height, width) if head is None else head
    if not (np.all(np.isfinite(rect.centre)) and np.isfinite(rect.width) and rect.width >= 1.0):
        return None, f"the head square is degenerate (side {rect.width:.3g} px)"
    image = np.clip(np.nan_to_num(image, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0).astype(np.float32)
    corners = rect.corners()
    if corners[:, 0].max() <= 0 or corners[:, 1].max() <= 0 or corners[:, 0].min() >= width \
            or corners[:, 1].min() >= height:
        return None, "the head square lies outside the photo"
    detections = detector.detect(image, rect)
    if not detections:
        return None, f"no face detected with score >= {MIN_DETECTION_SCORE} in the head square"
    best = detections[0]
    found = mesh.landmarks(image, face_rect(best))
    if found.presence < MIN_FACE_PRESENCE:
        return None, f"the face mesh's face flag {found.presence:.2f} < {MIN_FACE_PRESENCE}"
    return Face(best, found), ""
