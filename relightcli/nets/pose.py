"""People in a photo from MediaPipe's BlazePose (converted by `python -m export.perception`):
the person detector finds every person, the landmark net gives each one 33 keypoints, 33
metric 3D world landmarks and a segmentation.

The chain, after MediaPipe's pose graphs (modules/pose_detection, modules/pose_landmark):
letterbox the photo to 224 -> detector -> decode on SSD anchors -> weighted NMS -> each
detection's hip centre and scale keypoints give a rotated square (x1.25) -> crop 256 -> landmark
net -> landmarks, world landmarks and mask back into the photo. The detector's box is a face
box: the body's crop comes from its keypoints.

Images here are sRGB-encoded RGB in [0, 1], (H, W, 3) float32, as the nets were trained on.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from relightcli.nets.blaze import (
    AnchorSpec,
    Detection,
    RegionNet,
    RotatedRect,
    crop_to_photo,
    decode_detections,
    letterbox,
    net_input,
    paste_crop,
    rect_from_keypoints,
    sigmoid,
    ssd_anchors,
    weighted_nms,
)
from relightcli.nets.session import ModelSession

DETECTOR_ANCHORS = AnchorSpec(input_size=224, strides=(8, 16, 32, 32, 32))
MIN_DETECTION_SCORE = 0.5   # MediaPipe's: lower lets horses and visors in (measured on photos)
NMS_IOU = 0.3
TILE_ASPECT = 1.4           # photos longer than this x their short side are also tiled
MIN_PRESENCE = 0.5          # the landmark net's "a person is in this crop" flag
# ... for a person the detector found at a weak score: both nets only half sure is no person
# (find_people says where these were measured)
WEAK_DETECTION_SCORE = 0.6
WEAK_DETECTION_PRESENCE = 0.88
DUPLICATE_IOU = 0.5         # two detections whose people overlap this much are one person
ROI_SCALE = 1.25            # the crop around the keypoints' square
BODY_LANDMARKS = 33         # of 39: the last 6 are auxiliary (ROI keypoints)
HIP_CENTRE, ROI_EDGE = 33, 34  # the auxiliary landmarks that place the next crop


class PersonDetector(ModelSession):
    model_name = "person_detector"
    input_names = ("image",)
    output_names = ("boxes", "scores")

    def detect(self, image: np.ndarray, min_score: float = MIN_DETECTION_SCORE) -> list[Detection]:
        """Every person in `image` (H, W, 3) sRGB in [0, 1], best first: a face box and 4
        keypoints (hip centre, a point on the circle around the body, face centre, a point on
        the circle around the head) in photo pixels. The detector sees the whole photo
        letterboxed and, for a photo much wider than high or the other way, also overlapping
        squares along its long side (people stay larger in them); one weighted NMS merges all."""
        size = DETECTOR_ANCHORS.input_size
        anchors = ssd_anchors(DETECTOR_ANCHORS)
        value_range = self.entry.config.get("value_range", (-1.0, 1.0))
        boxes, keypoints, scores = [], [], []
        for x0, y0, window in detector_windows(*image.shape[:2]):
            square, (sx, sy, ox, oy) = letterbox(image[y0:y0 + window[1], x0:x0 + window[0]], size)
            out = self.run({"image": net_input(square, value_range)})
            box, points, score = decode_detections(out["boxes"][0], out["scores"][0, :, 0], anchors, size, min_score)
            scale, offset = np.array([sx, sy]), np.array([ox, oy]) - np.array([sx * x0, sy * y0])
            boxes.append(((box.reshape(-1, 2, 2) * size - offset) / scale).reshape(-1, 4))
            keypoints.append((points * size - offset) / scale)
            scores.append(score)
        merged = weighted_nms(np.concatenate(boxes), np.concatenate(keypoints), np.concatenate(scores), NMS_IOU)
        return [Detection(box, points, score) for box, points, score in merged]


def detector_windows(height: int, width: int) -> list[tuple[int, int, tuple[int, int]]]:
    """(x0, y0, (w, h)) windows of the photo the detector runs on: the whole photo, and when
    its long side exceeds TILE_ASPECT x the short one, squares of the short side spaced evenly
    along the long side, overlapping by at least a quarter."""
    windows = [(0, 0, (width, height))]
    short, long = min(height, width), max(height, width)
    if long <= TILE_ASPECT * short:
        return windows
    count = int(np.ceil((long - short) / (0.75 * short))) + 1
    for start in np.linspace(0, long - short, count).round().astype(int):
        windows.append((int(start), 0, (short, short)) if width >= height else (0, int(start), (short, short)))
    return windows


@dataclass
class Pose:
    """One person's landmarks: `landmarks` (33, 5) x, y (photo pixels), z (pixels, towards the
    camera negative, hip-centred), visibility and presence in [0, 1]; `world` (33, 3) metres,
    hip-centred, y down; `mask` the person's probability (H, W) float32 in the photo;
    `presence` the net's confidence that the crop holds a person; `next_rect` the crop its
    auxiliary landmarks place."""

    rect: RotatedRect
    presence: float
    landmarks: np.ndarray
    world: np.ndarray
    mask: np.ndarray = field(repr=False)
    next_rect: RotatedRect


class PoseLandmarker(RegionNet):
    model_name = "pose_landmarks"
    input_names = ("image",)
    output_names = ("landmarks", "presence", "segmentation", "world_landmarks")

    def landmarks(self, image: np.ndarray, rect: RotatedRect) -> Pose:
        """The pose in `rect` of `image` (H, W, 3) sRGB in [0, 1]."""
        size = self.crop_size
        out = self.run_region(image, rect)
        raw = out["landmarks"][0].reshape(-1, 5).astype(np.float64)
        points = crop_to_photo(rect, raw[:, :2] / size)
        depth = raw[:, 2:3] / size * rect.width
        landmarks = np.hstack([points, depth, sigmoid(raw[:, 3:5])])
        world = out["world_landmarks"][0].reshape(-1, 3).astype(np.float64)
        c, s = np.cos(rect.rotation), np.sin(rect.rotation)
        world[:, :2] = world[:, :2] @ np.array([[c, s], [-s, c]])  # the crop's turn undone
        height, width = image.shape[:2]
        mask = paste_crop(sigmoid(out["segmentation"][0, :, :, 0]).astype(np.float32), rect, height, width)
        next_rect = rect_from_keypoints(points[HIP_CENTRE], points[ROI_EDGE], np.pi / 2, ROI_SCALE)
        # the presence output is already a probability (a sigmoid inside the graph)
        return Pose(rect, float(out["presence"][0, 0]), landmarks[:BODY_LANDMARKS],
                    world[:BODY_LANDMARKS], mask, next_rect)

    def mirrored_segmentation(self, image: np.ndarray, rect: RotatedRect) -> np.ndarray:
        """The person's probability (H, W) float32 in the photo as the net segments the mirror
        image of the crop `rect` of `image`, mirrored back."""
        out = self.run_region(image, rect, mirror=True)
        segmentation = sigmoid(out["segmentation"][0, :, ::-1, 0]).astype(np.float32)
        return paste_crop(segmentation, rect, *image.shape[:2])


@dataclass
class Person:
    """A person found in the photo: the detection, and the pose when its crop holds a person."""

    detection: Detection
    pose: Pose | None
    min_presence: float = MIN_PRESENCE

    @property
    def found(self) -> bool:
        return self.pose is not None and self.pose.presence >= self.min_presence

    def summary(self, scale=(1.0, 1.0)) -> dict:
        """What the report says of this person, in pixels of a photo `scale` (sx, sy) times
        smaller than the one the person was found in (1: that photo's pixels)."""
        box = lambda points: [round(float(v), 1) for v in (np.reshape(points, (-1, 2)) / scale).reshape(-1)]  # noqa: E731
        out = {"face_box": box(self.detection.box), "detection_score": round(self.detection.score, 3)}
        if self.pose is not None:
            out["presence"] = round(self.pose.presence, 3)
            corners = self.pose.rect.corners()
            out["body_box"] = box([*corners.min(axis=0), *corners.max(axis=0)])
        return out


def find_people(image: np.ndarray, detector: PersonDetector, landmarker: PoseLandmarker,
                refine: bool = True, join_views: bool = True) -> list[Person]:
    """Every person the detector finds in `image` (H, W, 3) sRGB in [0, 1], best first, each
    with its pose (None when the landmark net says the crop holds no person; kept for the
    report). With `refine`, the landmarks run a second time in the crop their own auxiliary
    landmarks place (MediaPipe's tracking step, here on one photo: the detector's keypoints
    are coarse), and the pass with the higher presence is kept. A detection whose person
    overlaps one found before (mask IoU > DUPLICATE_IOU) is the same person seen twice and
    is left out. No weaker detections are tried when none scores MIN_DETECTION_SCORE:
    measured on 40 photos without a person (crops of the HDRIs in ../shared/data/hdri), taking
    the best of those above 0.1 whose crop the landmark net accepts found a "person" in 22,
    the 0.5 threshold alone in 3.

    A weak detection (score under WEAK_DETECTION_SCORE) needs WEAK_DETECTION_PRESENCE from the
    landmark net: MediaPipe's 0.5 let in a dog standing up to hug a woman (detection 0.55,
    presence 0.84). `python bench/people_presence.py data/evalval512 data/evaltrain512
    data/evalval256v7 hdri photos=../shared/data/photos` (validation only): of 247 real people
    detected, the 15 at a weak score had presences 0.27 (turned down at 0.5 already), 0.91 and
    0.98-1.00, the face-painted portrait of the photos 0.999; a presence of 0.88 for every detection
    would have turned down one real person more (presence 0.55, score 0.68). Of the 6 false
    "people" in views of the HDRIs, one is weak (0.54, presence 0.97: still taken).

    With `join_views`, each found person's segmentation is joined with the net's on the mirror
    image of the crop, and with the other refinement pass's when that one saw a person too
    (joined_segmentation): a limb the net misplaces drops out of one view more often than of
    all (own mask, 60 validation people: 46 -> 51 with every limb kept, relit +0.13 dB for the
    mirror, +0.04 more for the other pass; docs/RESULTS.md, "Every limb kept?"). A caller
    bringing its own mask has no use for them."""
    return _people(image, detector.detect(image), landmarker, refine, WEAK_DETECTION_PRESENCE, join_views)


def find_person_in_mask(image: np.ndarray, mask: np.ndarray, landmarker: PoseLandmarker,
                        refine: bool = True, join_views: bool = False) -> Person | None:
    """The person a mask (h, w) in [0, 1] of `image` outlines, when the detector found none:
    the landmark net run in the square around the mask's bounding box (as the detector's
    keypoints would place it: centred, half side the box's larger half extent x ROI_SCALE,
    upright), then, with `refine`, in the crop its own landmarks place. None for an empty mask;
    the person's `found` says whether the landmark net sees a person there. The detection is a
    stand-in: the mask's box, score 0. `join_views` as in find_people."""
    rows, cols = np.nonzero(mask > 0.5)
    if rows.size == 0:
        return None
    x0, x1, y0, y1 = cols.min(), cols.max() + 1.0, rows.min(), rows.max() + 1.0
    centre = np.array([(x0 + x1) / 2.0, (y0 + y1) / 2.0])
    edge = centre - np.array([0.0, max(x1 - x0, y1 - y0) / 2.0])  # straight up: the crop upright
    stand_in = Detection(np.array([x0, y0, x1, y1], np.float64), np.stack([centre, edge]), 0.0)
    return _people(image, [stand_in], landmarker, refine, join_views=join_views)[0]


# The landmark net's presence a person found in the whole photo needs (find_person_in_photo).
# `python bench/whole_photo_presence.py data/evalval512 data/evalval256`: on 120 views of the
# HDRIs in ../shared/data/hdri (no person in them) it reached 0.9948 (22 views at >= 0.5); on
# the 25 validation photos where the detector finds nobody it is >= 0.995 in 22
WHOLE_PHOTO_PRESENCE = 0.995


def find_person_in_photo(image: np.ndarray, landmarker: PoseLandmarker, refine: bool = True) -> Person:
    """The landmark net run on the whole photo (image (h, w, 3) sRGB), for when the detector
    found nobody: BlazePose's detector finds a person by the face and misses some people (a
    gold visor over the face, T-posed synthetic figures, even seen from behind) whom the
    landmark net, shown the whole photo, finds. A whole photo is no detector's crop: take the
    person only at a presence of WHOLE_PHOTO_PRESENCE (over a landscape the net's presence
    passes MIN_PRESENCE in one view of five)."""
    height, width = image.shape[:2]
    return find_person_in_mask(image, np.ones((height, width), np.float32), landmarker, refine, join_views=True)


def _people(image, detections, landmarker, refine, weak_needs=MIN_PRESENCE,
            join_views: bool = True) -> list[Person]:
    people = []
    for detection in detections:
        rect = rect_from_keypoints(detection.keypoints[0], detection.keypoints[1], np.pi / 2, ROI_SCALE)
        pose = first = landmarker.landmarks(image, rect)
        if refine:  # the crop from the detector's keypoints may be off by so much that its
            second = landmarker.landmarks(image, pose.next_rect)  # presence is low: judge the better one
            pose = second if second.presence > pose.presence else pose
        weak = detection.score < WEAK_DETECTION_SCORE
        person = Person(detection, pose, weak_needs if weak else MIN_PRESENCE)
        if person.found and join_views:
            views = [landmarker.mirrored_segmentation(image, pose.rect)]
            if first is not pose and first.presence >= MIN_PRESENCE:  # the other crop's, already made
                views.append(first.mask)
            pose.mask = joined_segmentation(pose.mask, *views)
        if person.found and any(_mask_iou(person, other) > DUPLICATE_IOU for other in people if other.found):
            continue
        people.append(person)
    return people


def joined_segmentation(own: np.ndarray, *others: np.ndarray) -> np.ndarray:
    """A person's probability (H, W): the largest of the net's segmentations of its views."""
    return np.maximum.reduce([own, *others])


def _mask_iou(a: Person, b: Person) -> float:
    first, second = a.pose.mask > 0.5, b.pose.mask > 0.5
    union = np.logical_or(first, second).sum()
    return float(np.logical_and(first, second).sum() / union) if union else 0.0
