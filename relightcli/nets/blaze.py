"""The steps around MediaPipe's Blaze detectors and landmark nets, each a small pure function:
SSD anchors, decoding raw detections, weighted non-maximum suppression, a rotated region of
interest from two keypoints, the crop it defines and the way back to the photo.

Coordinates are continuous pixels of the photo: x right, y down, pixel (row i, col j) covers
[j, j + 1) x [i, i + 1), so its centre is (j + 0.5, i + 0.5). A rotated rectangle's rotation r
(radians) turns its axes: crop point (u, v) in [0, 1]^2 lies at
centre + R(r) ((u - 0.5) width, (v - 0.5) height), R(r) = [[cos r, -sin r], [sin r, cos r]];
r = 0 is upright, and a person's crop is turned so that their head is at its top.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from relightcli.nets.session import ModelSession


def sigmoid(x):
    """Logits -> probabilities, clipped so that no exp overflows."""
    return 1.0 / (1.0 + np.exp(-np.clip(x, -80.0, 80.0)))


def net_input(image: np.ndarray, value_range) -> np.ndarray:
    """(1, H, W, 3) float32 of an (H, W, 3) sRGB image in [0, 1] mapped linearly to the
    net's `value_range` (low, high), as MediaPipe's image-to-tensor step does."""
    low, high = value_range
    return (low + (high - low) * np.clip(image, 0.0, 1.0))[None].astype(np.float32)


@dataclass(frozen=True)
class AnchorSpec:
    """SSD anchors on a square input (MediaPipe's SsdAnchorsCalculator with fixed-size anchors:
    every anchor is a unit box centred on a feature-map cell). Layers of equal stride share a
    grid; each layer puts 2 anchors on every cell (aspect ratio 1 and the interpolated one)."""

    input_size: int
    strides: tuple[int, ...]
    anchors_per_layer: int = 2


def ssd_anchors(spec: AnchorSpec) -> np.ndarray:
    """(A, 2) float64 anchor centres (x, y) in [0, 1] of the input, in the model's order."""
    centres = []
    layer = 0
    while layer < len(spec.strides):
        stride = spec.strides[layer]
        shared = 1
        while layer + shared < len(spec.strides) and spec.strides[layer + shared] == stride:
            shared += 1
        cells = -(-spec.input_size // stride)
        y, x = np.mgrid[0:cells, 0:cells]
        grid = np.stack([(x + 0.5) / cells, (y + 0.5) / cells], axis=-1).reshape(-1, 1, 2)
        centres.append(np.repeat(grid, shared * spec.anchors_per_layer, axis=1).reshape(-1, 2))
        layer += shared
    return np.concatenate(centres)


@dataclass(frozen=True)
class Detection:
    """One detection in the photo's pixels: box (x0, y0, x1, y1), keypoints (K, 2), score."""

    box: np.ndarray
    keypoints: np.ndarray
    score: float


def decode_detections(boxes: np.ndarray, scores: np.ndarray, anchors: np.ndarray, input_size: int,
                      min_score: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Raw detector outputs -> (boxes (D, 4) x0 y0 x1 y1, keypoints (D, K, 2), scores (D,)),
    normalised to [0, 1] of the input square, for the anchors scoring at least `min_score`.

    boxes: (A, 4 + 2K) offsets of the box centre, its size and the keypoints from the anchor
    centre, in input pixels; scores: (A,) logits (clipped to +-100, then a sigmoid)."""
    score = 1.0 / (1.0 + np.exp(-np.clip(scores.astype(np.float64), -100.0, 100.0)))
    keep = score >= min_score
    raw = boxes[keep].astype(np.float64) / input_size
    centre = anchors[keep]
    middle, size = raw[:, 0:2] + centre, raw[:, 2:4]
    box = np.concatenate([middle - size / 2, middle + size / 2], axis=1)
    keypoints = raw[:, 4:].reshape(raw.shape[0], (boxes.shape[1] - 4) // 2, 2) + centre[:, None, :]
    return box, keypoints, score[keep]


def box_iou(box: np.ndarray, others: np.ndarray) -> np.ndarray:
    """(N,) intersection over union of one box (4,) with others (N, 4), x0 y0 x1 y1."""
    low = np.maximum(box[:2], others[:, :2])
    high = np.minimum(box[2:], others[:, 2:])
    inter = np.prod(np.clip(high - low, 0.0, None), axis=1)
    area = lambda b: np.prod(np.clip(b[..., 2:] - b[..., :2], 0.0, None), axis=-1)  # noqa: E731
    union = area(box) + area(others) - inter
    return np.where(union > 0, inter / np.maximum(union, 1e-12), 0.0)


def weighted_nms(boxes: np.ndarray, keypoints: np.ndarray, scores: np.ndarray,
                 iou_threshold: float) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """MediaPipe's WEIGHTED non-maximum suppression: take the best remaining detection, and
    with it every remaining one overlapping it by more than `iou_threshold`; the result is
    their score-weighted mean box and keypoints, with the best one's score. Best first."""
    order = np.argsort(-scores, kind="stable")
    remaining = list(order)
    kept = []
    while remaining:
        best = remaining[0]
        overlap = box_iou(boxes[best], boxes[remaining]) > iou_threshold
        members = np.asarray(remaining)[overlap]
        weights = scores[members] / scores[members].sum()
        kept.append((weights @ boxes[members], np.tensordot(weights, keypoints[members], axes=1),
                     float(scores[best])))
        remaining = [r for r, out in zip(remaining, overlap) if not out]
    return kept


@dataclass(frozen=True)
class RotatedRect:
    """A region of interest in photo pixels: centre (x, y), width, height, rotation (radians)."""

    centre: tuple[float, float]
    width: float
    height: float
    rotation: float

    def corners(self) -> np.ndarray:
        """(4, 2) corners in photo pixels: top-left, top-right, bottom-right, bottom-left of the crop."""
        return crop_to_photo(self, np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]))


def rect_from_keypoints(centre: np.ndarray, edge: np.ndarray, target_angle: float,
                        scale: float) -> RotatedRect:
    """MediaPipe's alignment-points rectangle, then its scaling: a square centred on `centre`
    whose half side is the distance to `edge` (photo pixels), times `scale`, turned so that the
    direction centre -> edge points at `target_angle` (radians, counter-clockwise from +x as
    seen on screen: pi/2 is up)."""
    dx, dy = float(edge[0] - centre[0]), float(edge[1] - centre[1])
    side = 2.0 * np.hypot(dx, dy) * scale
    rotation = _wrap_angle(target_angle - np.arctan2(-dy, dx))
    return RotatedRect((float(centre[0]), float(centre[1])), side, side, rotation)


def rect_around_points(points: np.ndarray, rotation: float, scale: float) -> RotatedRect:
    """The square with the given rotation around `points` (N, 2) photo pixels: the bounding box
    of the points in the rotated frame, its long side times `scale`."""
    c, s = np.cos(rotation), np.sin(rotation)
    local = points @ np.array([[c, -s], [s, c]])  # photo -> rect axes: R(r)^T p
    low, high = local.min(axis=0), local.max(axis=0)
    middle = np.array([[c, -s], [s, c]]) @ ((low + high) / 2)
    side = float((high - low).max()) * scale
    return RotatedRect((float(middle[0]), float(middle[1])), side, side, rotation)


def _wrap_angle(angle: float) -> float:
    return float(angle - 2.0 * np.pi * np.floor((angle + np.pi) / (2.0 * np.pi)))


def crop_to_photo(rect: RotatedRect, uv: np.ndarray) -> np.ndarray:
    """Crop points (N, 2) in [0, 1]^2 (u right, v down) -> photo pixels (N, 2)."""
    c, s = np.cos(rect.rotation), np.sin(rect.rotation)
    local = (np.asarray(uv, np.float64) - 0.5) * [rect.width, rect.height]
    return local @ np.array([[c, s], [-s, c]]) + rect.centre


def crop_matrix(rect: RotatedRect, size: int) -> np.ndarray:
    """(2, 3) float64 affine map from crop pixel indices (col, row) of a size x size crop to
    photo pixel indices (OpenCV's convention: pixel centres at integers)."""
    c, s = np.cos(rect.rotation), np.sin(rect.rotation)
    linear = np.array([[c, -s], [s, c]]) @ np.diag([rect.width / size, rect.height / size])
    offset = np.asarray(rect.centre) - 0.5 + linear @ np.array([0.5 - size / 2.0, 0.5 - size / 2.0])
    return np.hstack([linear, offset[:, None]])


def crop_rect(image: np.ndarray, rect: RotatedRect, size: int, border: int = cv2.BORDER_REPLICATE) -> np.ndarray:
    """The rect's crop of `image` (H, W, C) resampled to (size, size, C) float32, bilinear;
    an image much larger than the crop is first shrunk by area averaging (no aliasing)."""
    shrink = max(1.0, min(rect.width, rect.height) / (2.0 * size))
    matrix = crop_matrix(rect, size)
    source = image
    if shrink > 1.5:
        height, width = image.shape[:2]
        small = (max(1, round(width / shrink)), max(1, round(height / shrink)))
        source = cv2.resize(image, small, interpolation=cv2.INTER_AREA)
        # photo index p -> small index (p + 0.5) * small / photo - 0.5
        ratio = np.array([small[0] / width, small[1] / height])
        matrix = np.vstack([matrix[0] * ratio[0], matrix[1] * ratio[1]])
        matrix[:, 2] += 0.5 * ratio - 0.5
    out = cv2.warpAffine(np.ascontiguousarray(source, np.float32), matrix, (size, size),
                         flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=border, borderValue=0)
    return out.reshape(size, size, -1)


def paste_crop(crop: np.ndarray, rect: RotatedRect, height: int, width: int) -> np.ndarray:
    """A (S, S) crop map put back into the photo's (height, width) frame, bilinear; 0 outside."""
    matrix = crop_matrix(rect, crop.shape[0])
    return cv2.warpAffine(np.ascontiguousarray(crop, np.float32), matrix, (width, height),
                          flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def letterbox(image: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """The image scaled to fit a size x size square, centred, black around it. Returns the
    (size, size, C) float32 square and (4,) [sx, sy, ox, oy]: square pixel = photo pixel *
    (sx, sy) + (ox, oy), in continuous coordinates."""
    height, width = image.shape[:2]
    scale = size / max(height, width)
    new_w, new_h = max(1, round(width * scale)), max(1, round(height * scale))
    resized = cv2.resize(np.ascontiguousarray(image, np.float32), (new_w, new_h), interpolation=cv2.INTER_AREA)
    square = np.zeros((size, size) + image.shape[2:], np.float32)
    x0, y0 = (size - new_w) // 2, (size - new_h) // 2
    square[y0:y0 + new_h, x0:x0 + new_w] = resized.reshape((new_h, new_w) + image.shape[2:])
    return square, np.array([new_w / width, new_h / height, x0, y0], np.float64)


class RegionNet(ModelSession):
    """A net that looks at a rotated square of the photo (a person's or a face's crop): the
    crop resampled to the net's input side and mapped to its value range, as MediaPipe's
    image-to-tensor step does."""

    @property
    def crop_size(self) -> int:
        """The side of the square input, (1, S, S, 3)."""
        return int(self.entry.inputs[0].shape[1])

    def run_region(self, image: np.ndarray, rect: RotatedRect, mirror: bool = False) -> dict[str, np.ndarray]:
        """The net's outputs on `rect` of `image` (H, W, 3) sRGB in [0, 1] (with `mirror`, on
        the crop's mirror image: the outputs are the mirror's)."""
        crop = crop_rect(image, rect, self.crop_size)
        crop = np.ascontiguousarray(crop[:, ::-1]) if mirror else crop
        return self.run({"image": net_input(crop, self.entry.config.get("value_range", (0.0, 1.0)))})
