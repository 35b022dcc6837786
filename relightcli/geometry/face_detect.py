"""Find the face in a person crop with OpenCV cascades, and the 128x128 crop around it.

Cascades: OpenCV's own `cv2.data.haarcascades` frontal and profile faces when the installed
wheel bundles them (OpenCV 4), else the LBP frontal-face cascade shipped inside the face model
file (OpenCV 5 wheels bundle none). Faces turned in the image plane can be found by also
trying the picture rotated (off by default); a profile cascade runs on the picture and its
mirror when OpenCV bundles one.
No usable face (a back view, a face smaller than `min_size`, nothing inside the mask) is not
an error: `detect_face` returns (None, reason) and the face stage is skipped.
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass, replace

import cv2
import numpy as np

from relightcli.errors import InputError
from relightcli.geometry.face_model import FaceModel
from relightcli.io.images import linear_to_srgb

MIN_FACE_PX = 24
# In-plane rotations tried in turn (degrees, counter-clockwise); the first that finds a face
# wins. Upright only by default: with the LBP fallback cascade, turned pictures of textures
# (hair, fur, foliage) gave as many false faces as turned faces gave true ones.
ROTATIONS = (0.0,)
# Overlapping detections needed; 6 rejects the false faces the LBP cascade finds in smooth
# noise, hair and fur (4-5 neighbours) and keeps the frontal faces of the sample photos (8-14)
MIN_NEIGHBOURS = 6
# With a person mask, the cascades scan its bounding box plus this margin only
SEARCH_MARGIN_PX = 16
SCALE_STEP = 1.05
# A detection counts as inside the mask when this share of its box is person
MIN_MASK_COVER = 0.5
FACE_CROP_SIZE = 128
FACE_CROP_MARGIN = 1.6


@dataclass(frozen=True)
class FaceBox:
    """A detected face in pixels of the image: the axis-aligned box (left, top, width,
    height) holding the (possibly rotated) detection, the in-plane angle in degrees at which
    it was found, and the cascade's neighbour count as a confidence."""

    left: float
    top: float
    width: float
    height: float
    angle: float
    neighbours: int

    @property
    def centre(self) -> tuple[float, float]:
        return self.left + self.width / 2.0, self.top + self.height / 2.0


@dataclass(frozen=True)
class CropRect:
    """A square crop of the image: rows top .. top + size, columns left .. left + size
    (may reach outside the image: pad when cutting), sampled at `resolution` pixels."""

    left: int
    top: int
    size: int
    resolution: int = FACE_CROP_SIZE

    def world_rect(self, image_rect, image_shape) -> tuple:
        """(x0, x1, y0, y1) world rectangle of the crop, given the world rectangle of the
        whole (H, W) image (DESIGN.md: pixel edges at x0 + j (x1 - x0) / W)."""
        x0, x1, y0, y1 = (float(c) for c in image_rect)
        height, width = image_shape[:2]
        dx, dy = (x1 - x0) / width, (y1 - y0) / height
        return (x0 + self.left * dx, x0 + (self.left + self.size) * dx,
                y1 - (self.top + self.size) * dy, y1 - self.top * dy)


def detect_face(image_rgb_linear, mask=None, *, model: FaceModel | None = None,
                min_size: int = MIN_FACE_PX, rotations=ROTATIONS):
    """The most confident face in the image, or None and why.

    image_rgb_linear (H, W, 3) float32 linear RGB; mask (H, W) float in [0, 1], optional: the
    person (a face must lie mostly inside it). rotations: in-plane angles (degrees) tried in
    turn. Returns (FaceBox, "") or (None, reason).
    """
    grey = _grey_8bit(image_rgb_linear)
    if mask is not None and np.asarray(mask).shape != grey.shape:
        raise InputError(f"face mask shape {np.asarray(mask).shape} differs from the image "
                         f"{grey.shape}", fix="pass the person mask of the same image")
    cascades = _cascades(model)
    (x0, y0), region = _search_region(grey, mask)
    seen_small = False
    for angle in rotations:
        boxes = [replace(b, left=b.left + x0, top=b.top + y0) for b in _detect_rotated(region, angle, cascades)]
        seen_small |= any(min(b.width, b.height) < min_size for b in boxes)
        boxes = [b for b in boxes if min(b.width, b.height) >= min_size and _inside(b, mask)]
        if boxes:
            return max(boxes, key=lambda b: (b.neighbours, b.width * b.height)), ""
    if seen_small:
        return None, f"face smaller than {min_size} px: face stage skipped"
    return None, "no frontal or profile face found (back view or face hidden): face stage skipped"


def face_crop_rect(box: FaceBox, *, margin: float = FACE_CROP_MARGIN,
                   resolution: int = FACE_CROP_SIZE) -> CropRect:
    """The square crop around a face box for the face refinement net: side = margin times
    the box's larger side, centred on the box (pixels of the image)."""
    side = max(1, int(round(margin * max(box.width, box.height))))
    cx, cy = box.centre
    return CropRect(left=int(round(cx - side / 2.0)), top=int(round(cy - side / 2.0)),
                    size=side, resolution=resolution)


# ---------------------------------------------------------------------------- internals

def _grey_8bit(image_rgb_linear) -> np.ndarray:
    """(H, W) uint8 sRGB-encoded luma, histogram-equalised (the cascades were trained on
    8-bit sRGB photographs)."""
    image = np.asarray(image_rgb_linear, dtype=np.float32)
    if image.ndim != 3 or image.shape[2] != 3:
        raise InputError(f"face detection needs an (H, W, 3) image, got {image.shape}")
    encoded = linear_to_srgb(np.clip(np.nan_to_num(image), 0.0, 1.0))
    grey = encoded @ np.array([0.299, 0.587, 0.114], np.float32)
    return cv2.equalizeHist(np.round(grey * 255.0).astype(np.uint8))


@functools.lru_cache(maxsize=2)
def _load_cascades(fallback_xml: str) -> tuple:
    """((frontal, profile-or-None)) classifiers: OpenCV's bundled Haar files when present."""
    folder = getattr(getattr(cv2, "data", None), "haarcascades", "") or ""
    frontal_path = os.path.join(folder, "haarcascade_frontalface_default.xml")
    profile_path = os.path.join(folder, "haarcascade_profileface.xml")
    if os.path.isfile(frontal_path):
        profile = cv2.CascadeClassifier(profile_path) if os.path.isfile(profile_path) else None
        return cv2.CascadeClassifier(frontal_path), profile
    storage = cv2.FileStorage(fallback_xml, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    frontal = cv2.CascadeClassifier()
    if not frontal.read(storage.getFirstTopLevelNode()):
        raise InputError("the face detector cascade in the face model file is unreadable",
                         fix="rebuild models/face_model.npz with python -m export.face_model")
    return frontal, None


def _cascades(model: FaceModel | None) -> tuple:
    return _load_cascades((model or FaceModel.load()).detector_cascade)


def _detect_rotated(grey, angle: float, cascades) -> list[FaceBox]:
    """Faces found in the picture turned by `angle`, as boxes in the original picture."""
    height, width = grey.shape
    turn = cv2.getRotationMatrix2D((width / 2.0, height / 2.0), angle, 1.0)
    turned = grey if angle == 0 else cv2.warpAffine(grey, turn, (width, height),
                                                   borderMode=cv2.BORDER_REPLICATE)
    back = cv2.invertAffineTransform(turn)
    frontal, profile = cascades
    found = [_run(frontal, turned, mirrored=False)]
    if profile is not None:
        found += [_run(profile, turned, mirrored=False), _run(profile, turned, mirrored=True)]
    return [_unrotate(rect, count, back, angle) for rects in found for rect, count in rects]


def _run(cascade, grey, *, mirrored: bool):
    """(rect, neighbours) pairs of one cascade, rects (x, y, w, h) in `grey`'s pixels."""
    image = grey[:, ::-1].copy() if mirrored else grey
    rects, counts = cascade.detectMultiScale2(image, scaleFactor=SCALE_STEP,
                                              minNeighbors=MIN_NEIGHBOURS, minSize=(12, 12))
    out = []
    for (x, y, w, h), count in zip(np.asarray(rects).reshape(-1, 4), np.ravel(counts)):
        if mirrored:
            x = grey.shape[1] - x - w
        out.append(((float(x), float(y), float(w), float(h)), int(count)))
    return out


def _unrotate(rect, count, back, angle) -> FaceBox:
    x, y, w, h = rect
    corners = np.array([[x, y, 1], [x + w, y, 1], [x, y + h, 1], [x + w, y + h, 1]])
    mapped = corners @ back.T
    lo, hi = mapped.min(axis=0), mapped.max(axis=0)
    # The axis-aligned hull of a turned square is larger: keep the detection's own size
    cx, cy = (lo + hi) / 2.0
    return FaceBox(left=cx - w / 2.0, top=cy - h / 2.0, width=w, height=h, angle=angle,
                   neighbours=count)


def _search_region(grey, mask):
    """((x0, y0), the part of `grey` worth scanning): the person's bounding box plus
    SEARCH_MARGIN_PX, since a face must lie mostly inside the mask (_inside); the whole
    picture without a mask. Scanning less is what makes a photo without a face cheap (the
    cascades cost ~0.1 s on a whole 512 crop)."""
    if mask is None:
        return (0, 0), grey
    rows, cols = np.nonzero(np.asarray(mask) > 0.5)
    if rows.size == 0:
        return (0, 0), grey[:0, :0]
    height, width = grey.shape
    y0, x0 = max(int(rows.min()) - SEARCH_MARGIN_PX, 0), max(int(cols.min()) - SEARCH_MARGIN_PX, 0)
    y1, x1 = min(int(rows.max()) + 1 + SEARCH_MARGIN_PX, height), min(int(cols.max()) + 1 + SEARCH_MARGIN_PX, width)
    return (x0, y0), grey[y0:y1, x0:x1]


def _inside(box: FaceBox, mask) -> bool:
    if mask is None:
        return True
    mask = np.asarray(mask, dtype=np.float32)
    height, width = mask.shape
    top, left = max(int(box.top), 0), max(int(box.left), 0)
    bottom = min(int(box.top + box.height), height)
    right = min(int(box.left + box.width), width)
    if bottom <= top or right <= left:
        return False
    return float(mask[top:bottom, left:right].mean()) >= MIN_MASK_COVER
