"""The face stage (issue 6, issue 17): fit the ICT FaceKit model to a face's 68 landmarks, and
ray-trace the fitted face's coarse shading pixel-aligned with the face crop.

At run time the face is found by MediaPipe's face detector and face mesh
(relightcli.nets.face_mesh, on a head square placed by the pose) and its 468 points give the
68 landmarks (face_correspondence.py); `fit_face_to_landmarks` frames the 128x128 face crop
around them (`face_box_around`) and fits. `render_face_shading` renders the second part. The
parts live in
- face_model.py: the shipped linear model (models/face_model.npz) and the weak-perspective
  camera helpers (DESIGN.md pixel convention);
- face_fit.py: regularised Gauss-Newton fit of identity, expression and pose to 68 landmarks
  (optional weights, robust loss, optional depth), and the fitted mesh;
- face_detect.py: the 128x128 face crop rectangle;
- face_correspondence.py: the 468 -> 68 table.
"""

from __future__ import annotations

import cv2
import numpy as np

from relightcli.geometry.face_detect import FACE_CROP_MARGIN, CropRect, FaceBox, face_crop_rect
from relightcli.geometry.face_fit import FaceFit, face_mesh, fit_face
from relightcli.geometry.face_model import (
    FaceModel,
    pixel_to_world,
    rotation_angles_deg,
    rotation_matrix,
    transform,
    world_to_pixel,
)

# Framing of the face crop around the landmarks: side = scale x the larger side of the
# landmarks' box, centre shifted up by shift x side (export/factory/faces.py
# CANONICAL_FRAMING: the framing the face refinement net's first close-ups were cut with)
CANONICAL_SCALE = 2.1
CANONICAL_SHIFT_UP = 0.08
# A fit whose weighted RMS landmark residual (pixels of the 128 crop) exceeds this does not
# explain its landmarks: skipped. Measured with the former 68-landmark net: synthetic test
# faces p99 0.86 px (max 1.05), two real photos 1.6-1.9, scattered points ~30. It is no face
# verifier (a face-shaped layout on clothes fitted to 1.0-3.7 px); finding the face is the
# detector's job.
MAX_RESIDUAL_PX = 4.0
# Poses beyond the training range (yaw 40, pitch 25 degrees) with some margin, and faces
# whose landmarks span less than this share of the crop, are not trusted
MAX_ABS_YAW_DEG, MAX_ABS_PITCH_DEG = 60.0, 45.0
MIN_FACE_SHARE = 0.2
# Landmark noise the fit assumes (pixels of the 128 crop), chosen on the validation split of
# the former 68-landmark net's face renders: 0.5 / 1 / 2 / 3 px gave median head-rotation errors of 3.73 / 3.72 / 3.68 / 3.61 degrees and
# p90 7.1 / 6.9 / 6.7 / 6.6 (the net's mean landmark error there is 1.4 px); 2 is near the
# net's error and keeps the fit residual meaningful
LANDMARK_SIGMA_PX = 2.0
# The refined face fades into the body's shading with this Gaussian sigma (pixels of the 128
# face crop), inside the fitted face's outline (face_blend_weight)
FACE_FEATHER_PX = 2.0
# The face net's shading joins the body's in log shading, departing from it by at most a factor
# of 2 (log 2 = 0.69): on the faces of the synthetic eval scenes where it disagrees most with
# the body (a hot forehead, a dark face) it was the further off (`python bench/face_blend.py
# data/eval512 data/evalval512`, RMS log error over the changed pixels, validation / test:
# body alone 0.363 / 0.485, linear blend 0.389 / 0.487, log blend 0.398 / 0.490, held within
# +-0.35 0.334 / 0.435, within +-0.7 0.331 / 0.425)
FACE_LOG_BOUND = float(np.log(2.0))
PERSON_CROP_RECT = (-1.0, 1.0, -1.0, 1.0)  # the working crop's world square (compose.py)


def cut_crop(image, crop: CropRect) -> np.ndarray:
    """(R, R[, C]) float32 crop of an (H, W[, C]) image, zero outside it: the square
    rows top .. top + size, columns left .. left + size, area-averaged when shrinking and
    bilinear when enlarging (the same resampling as compose.crop_square)."""
    height, width = image.shape[:2]
    region = np.zeros((crop.size, crop.size) + image.shape[2:], np.float32)
    top, left = max(crop.top, 0), max(crop.left, 0)
    bottom, right = min(crop.top + crop.size, height), min(crop.left + crop.size, width)
    if bottom > top and right > left:
        region[top - crop.top:bottom - crop.top, left - crop.left:right - crop.left] = image[top:bottom, left:right]
    interpolation = cv2.INTER_AREA if crop.size >= crop.resolution else cv2.INTER_LINEAR
    out = cv2.resize(region, (crop.resolution, crop.resolution), interpolation=interpolation)
    return out.reshape((crop.resolution, crop.resolution) + image.shape[2:])


def paste_crop(image, patch, weight, crop: CropRect, *, log_bound: float | None = None) -> np.ndarray:
    """The inverse of `cut_crop` with blending: a copy of the (H, W[, C]) image whose square
    `crop` window holds weight * patch + (1 - weight) * image, with the (R, R[, C]) patch and
    the (R, R) weight in [0, 1] resampled to the window (area-averaged when shrinking,
    bilinear when enlarging); the parts of the window outside the image are dropped.
    log_bound: blend positive values in log instead, the patch's log departure from the image
    held within +-log_bound: image * exp(weight * clip(log(patch / image), -b, b))."""
    out = np.array(image, np.float32, copy=True)
    height, width = out.shape[:2]
    top, left = max(crop.top, 0), max(crop.left, 0)
    bottom, right = min(crop.top + crop.size, height), min(crop.left + crop.size, width)
    if bottom <= top or right <= left:
        return out
    interpolation = cv2.INTER_AREA if crop.size <= crop.resolution else cv2.INTER_LINEAR
    size = (crop.size, crop.size)
    patch = cv2.resize(np.asarray(patch, np.float32), size, interpolation=interpolation)
    weight = np.clip(cv2.resize(np.asarray(weight, np.float32), size, interpolation=interpolation), 0.0, 1.0)
    patch = patch.reshape(size + out.shape[2:])[top - crop.top:bottom - crop.top, left - crop.left:right - crop.left]
    weight = weight[top - crop.top:bottom - crop.top, left - crop.left:right - crop.left]
    if out.ndim == 3:
        weight = weight[..., None]
    window = out[top:bottom, left:right]
    if log_bound is None:
        out[top:bottom, left:right] = weight * patch + (1.0 - weight) * window
    else:
        tiny = np.float32(1e-12)
        departure = np.log(np.maximum(patch, tiny)) - np.log(np.maximum(window, tiny))
        out[top:bottom, left:right] = window * np.exp(weight * np.clip(departure, -log_bound, log_bound))
    return out


def face_blend_weight(face_pixels, feather_px: float = FACE_FEATHER_PX) -> np.ndarray:
    """(S, S) float32 weight in [0, 1] of the refined face over the body shading: the face
    pixels of the fitted model, eroded by 2.5 x `feather_px` and blurred with that sigma, so
    the face fades into the body's shading inside the face (weight < 0.01 outside it) instead
    of at its edge, where a misfit head's outline would show as a seam."""
    inside = np.asarray(face_pixels, bool)
    if feather_px <= 0:
        return inside.astype(np.float32)
    radius = int(np.ceil(2.5 * feather_px))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1,) * 2)
    eroded = cv2.erode(inside.astype(np.uint8), kernel, borderValue=0).astype(np.float32)
    return np.clip(cv2.GaussianBlur(eroded, (0, 0), feather_px), 0.0, 1.0)


def crop_to_image(points, crop: CropRect) -> np.ndarray:
    """(N, 2) (col, row) pixels of a crop -> pixels of the image it was cut from (pixel
    centres map to pixel centres: x_image = left + (x + 0.5) size / resolution - 0.5)."""
    s = crop.size / crop.resolution
    return (np.asarray(points, np.float64) + 0.5) * s - 0.5 + np.array([crop.left, crop.top])


def image_to_crop(points, crop: CropRect) -> np.ndarray:
    """Inverse of `crop_to_image`."""
    s = crop.size / crop.resolution
    return (np.asarray(points, np.float64) - np.array([crop.left, crop.top]) + 0.5) / s - 0.5


def face_box_around(landmarks) -> FaceBox:
    """The face box whose `face_crop_rect` frames the (68, 2) landmarks (pixels) as the
    face refinement net saw faces in training: the square side CANONICAL_SCALE x the
    landmarks' larger extent, centred CANONICAL_SHIFT_UP x that side above their box's
    centre."""
    lo, hi = np.min(landmarks, axis=0), np.max(landmarks, axis=0)
    side = CANONICAL_SCALE * float(np.max(hi - lo)) / FACE_CROP_MARGIN
    cx = (lo[0] + hi[0]) / 2.0
    cy = (lo[1] + hi[1]) / 2.0 - CANONICAL_SHIFT_UP * side * FACE_CROP_MARGIN  # rows grow downward
    # +0.5: face_crop_rect takes the box in edge coordinates, the landmarks are pixel centres
    return FaceBox(left=cx + 0.5 - side / 2.0, top=cy + 0.5 - side / 2.0, width=side, height=side)


def fit_face_to_landmarks(landmarks, crop_shape, *, model: FaceModel | None = None,
                          image_rect=PERSON_CROP_RECT, depth=None,
                          landmark_sigma_px: float = LANDMARK_SIGMA_PX,
                          max_residual_px: float = MAX_RESIDUAL_PX):
    """Fit the face model to a face's 68 iBUG landmarks found in the person crop.

    landmarks (68, 2) float (col, row) pixels of the (R, R) person crop (`crop_shape`);
    image_rect: the crop's world rectangle (x0, x1, y0, y1), by default the working crop's
    [-1, 1]^2; depth: optional (R, R) world z of the visible surface (e.g. the geometry net's
    front depth), which places the face along z. Returns (FaceFit, info) with the fit in the
    128x128 face crop's frame (`fit.rect`; `info["crop"]` = [left, top, size, resolution] in
    pixels of the person crop, framed by face_box_around), or (None, info) with
    info["skipped"] saying why (too small, a fit that does not explain the landmarks).
    """
    model = model or FaceModel.load()
    box = face_box_around(landmarks)
    crop = face_crop_rect(box)
    info = {"box": [round(float(v), 1) for v in (box.left, box.top, box.width, box.height)],
            "crop": [crop.left, crop.top, crop.size, crop.resolution]}
    local = image_to_crop(landmarks, crop)
    rect = crop.world_rect(image_rect, crop_shape)
    face_depth = None if depth is None else cut_crop(np.asarray(depth, np.float32), crop)
    fit = fit_face(local, model, rect, (crop.resolution, crop.resolution), depth=face_depth,
                   landmark_sigma_px=landmark_sigma_px)
    yaw, pitch, roll = rotation_angles_deg(fit.rotation)
    info.update(landmarks=int(local.shape[0]), inliers=int(fit.inliers.sum()),
                residual_px=round(fit.residual_px, 2),
                angles_deg=[round(yaw, 1), round(pitch, 1), round(roll, 1)])
    problem = implausible_fit(fit, local, max_residual_px)
    if problem:
        info["skipped"] = f"{problem}: face stage skipped"
        return None, info
    return fit, info


def implausible_fit(fit: FaceFit, landmarks, max_residual_px: float = MAX_RESIDUAL_PX) -> str:
    """Why a fit of the (68, 2) landmarks is not trusted ("" when it is)."""
    yaw, pitch, _ = rotation_angles_deg(fit.rotation)
    if not fit.residual_px <= max_residual_px:
        return (f"face model fit residual {fit.residual_px:.1f} px > {max_residual_px} px "
                "(landmarks the face model does not explain)")
    if abs(yaw) > MAX_ABS_YAW_DEG or abs(pitch) > MAX_ABS_PITCH_DEG:
        return f"fitted head pose (yaw {yaw:.0f}, pitch {pitch:.0f} degrees) outside the trusted range"
    extent = float(np.max(landmarks.max(axis=0) - landmarks.min(axis=0)))
    if extent < MIN_FACE_SHARE * fit.resolution[0]:
        return f"landmarks span {extent:.0f} px of the {fit.resolution[0]} px face crop (no face found in it)"
    return ""


def render_face_shading(fit: FaceFit, light, *, resolution: int | None = None, spp: int = 64,
                        target_error: float | None = 0.02, seed: int = 0, threads: int = 1):
    """Coarse face shading: the fitted head ray-traced under `light` (an EnvironmentLight in
    the camera frame, DESIGN.md) by `shade_environment`, pixel-aligned with the face crop.

    resolution: the square's side (default the fit's crop, 128; larger renders the same
    rectangle finer). The whole fitted head (face, scalp, neck) is in the scene, so it
    shadows itself, but nothing else is (no body, no hair). Returns (shading (S, S, 3)
    float32 linear, DESIGN.md units, 0 where the head is not seen; face_mask (S, S) bool:
    pixels that see the face proper, not the neck or the back of the head).
    """
    from relightcli.render import Scene, render_pixel_geometry, shade_environment
    from relightcli.render.scene import corner_angle_normals

    size = int(resolution or fit.resolution[0])
    mesh = face_mesh(fit)
    normals = corner_angle_normals(mesh.vertices, mesh.faces)
    with Scene(mesh.vertices, mesh.faces, vertex_normals=normals, threads=threads) as scene:
        geometry = render_pixel_geometry(scene, fit.rect, (size, size))
        result = shade_environment(scene, geometry, light, spp=spp, target_error=target_error,
                                   seed=seed, workers=threads)
        face_mask = _face_pixels(scene, fit, size)
    return result.mean, face_mask & geometry.mask


def _face_pixels(scene, fit: FaceFit, size: int) -> np.ndarray:
    """(S, S) bool: the primary ray of the pixel first hits a face-region triangle."""
    from relightcli.render import pixel_centres

    centres = pixel_centres(fit.rect, (size, size)).reshape(-1, 2)
    origins = np.empty((centres.shape[0], 3))
    origins[:, :2] = centres - scene.centre[:2]
    origins[:, 2] = scene.bounds_local[1, 2] + 0.01 * scene.diagonal
    directions = np.tile([0.0, 0.0, -1.0], (origins.shape[0], 1))
    prim = scene.intersect(origins, directions).prim
    on_face = np.all(fit.model.face_region[fit.model.triangles], axis=1)
    return ((prim >= 0) & on_face[np.maximum(prim, 0)]).reshape(size, size)


__all__ = ["CropRect", "FaceBox", "FaceFit", "FaceModel", "crop_to_image", "cut_crop",
           "face_blend_weight", "face_box_around", "face_crop_rect", "face_mesh", "fit_face",
           "fit_face_to_landmarks", "image_to_crop", "implausible_fit", "paste_crop",
           "pixel_to_world", "render_face_shading", "rotation_angles_deg", "rotation_matrix",
           "transform", "world_to_pixel"]
