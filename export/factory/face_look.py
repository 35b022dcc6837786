"""Procedural albedo of the ICT face model for the landmark data: skin, lips, brows, lash lines,
eyes, mouth interior, hair cap and beard, painted as functions of each surface point's position
on the *neutral* model.

Painting on neutral coordinates (cm, model frame: +X the subject's left, +Y up, +Z out of the
face) makes every feature follow identity and expression for free: a vertex keeps its neutral
position whatever the coefficients, so lips stay on the lips when the mouth smiles. Front
features (lips, brows, lash lines, beard) come from a "front plane" texture in neutral x-y,
rasterised once from the model's own 68 landmarks; the eye and mouth openings are the
triangle fans `export/face_model.py` closes the holes with, told apart by their centre vertex.

No texture exists for the ICT model, so everything here is synthetic: skin from the Monk skin
tone scale (the body data's `albedo.skin_tone`, light to very dark drawn uniformly), hair
colours from `albedo.sample_hair_colour`.
"""

from __future__ import annotations

import functools
from dataclasses import asdict, dataclass

import cv2
import numpy as np
from scipy.ndimage import map_coordinates

from export.factory import albedo as body_albedo
from relightcli.geometry.face_model import FaceModel

# Front-plane texture over neutral x in [-9, 9] cm, y in [-12, 10] cm
PLANE_X, PLANE_Y, PLANE_CM_PER_TEXEL = (-9.0, 9.0), (-12.0, 10.0), 0.04
# iBUG-68 groups (face_model.py docstring)
BROWS = (range(17, 22), range(22, 27))
UPPER_LIDS = ((36, 37, 38, 39), (42, 43, 44, 45))
LOWER_LIDS = ((39, 40, 41, 36), (45, 46, 47, 42))
OUTER_LIP = range(48, 60)
NOSE_BOTTOM = 33
MOUTH_CORNER = 54
IRIS_COLOURS = np.array([[0.04, 0.02, 0.01], [0.10, 0.05, 0.025], [0.14, 0.10, 0.05],
                         [0.07, 0.11, 0.06], [0.09, 0.14, 0.21], [0.15, 0.16, 0.17]], np.float32)


@dataclass(frozen=True)
class FaceLook:
    """What one synthetic face looks like (all colours linear RGB albedo in [0, 1])."""

    skin: tuple
    skin_scale: float          # position on the Monk scale, 0 lightest .. 1 darkest
    hair: tuple
    hair_name: str
    lip: tuple
    iris: tuple
    sclera: tuple
    brow_width_cm: float       # half-thickness of the brow band
    brow_strength: float       # 0 invisible .. 1 the hair colour
    lash_strength: float
    hairline_cm: float         # neutral y of the front hairline (brows are at ~6 cm)
    hair_back_cm: float        # neutral y down to which hair covers the back of the head
    bald: bool
    beard: float               # 0 none .. 1 full beard
    gaze: tuple                # iris offset (x, y) in cm from the opening's centre
    teeth: bool
    noise_seed: int

    def as_dict(self) -> dict:
        return asdict(self)


def sample_look(rng: np.random.Generator) -> FaceLook:
    """A random look: skin tone uniform along the Monk scale (light to very dark equally
    represented), hair, lips, eyes, brows, hairline, sometimes a beard or baldness."""
    t = float(rng.uniform(0.0, 1.0))
    skin = body_albedo.skin_tone(t) * rng.uniform(0.95, 1.05, 3).astype(np.float32)
    hair_name, hair = body_albedo.sample_hair_colour(rng, float(rng.uniform(0.0, 1.0)))
    lip = skin * np.array([1.0, 0.62, 0.62], np.float32) * np.float32(rng.uniform(0.65, 0.95))
    if rng.random() < 0.15:  # lipstick
        lip = np.array([rng.uniform(0.3, 0.6), rng.uniform(0.01, 0.06), rng.uniform(0.02, 0.1)],
                       np.float32)
    sclera = np.array([0.55, 0.5, 0.45], np.float32) * np.float32(rng.uniform(0.5, 1.0))
    beard = 0.0
    if rng.random() < 0.15:  # stubble or a full beard, half and half
        beard = float(rng.uniform(0.2, 0.4) if rng.random() < 0.5 else rng.uniform(0.6, 0.95))
    return FaceLook(
        skin=_tup(np.clip(skin, 0, 1)), skin_scale=t, hair=_tup(hair), hair_name=hair_name,
        lip=_tup(lip), iris=_tup(IRIS_COLOURS[rng.integers(len(IRIS_COLOURS))]),
        sclera=_tup(sclera), brow_width_cm=float(rng.uniform(0.22, 0.5)),
        brow_strength=float(rng.uniform(0.4, 1.0)), lash_strength=float(rng.uniform(0.4, 0.95)),
        hairline_cm=float(rng.uniform(8.5, 12.0)), hair_back_cm=float(rng.uniform(-9.0, 1.0)),
        bald=bool(rng.random() < 0.08), beard=beard,
        gaze=(float(rng.uniform(-0.35, 0.35)), float(rng.uniform(-0.12, 0.12))),
        teeth=bool(rng.random() < 0.7), noise_seed=int(rng.integers(2 ** 31)))


def _tup(values) -> tuple:
    return tuple(float(v) for v in values)


@dataclass(frozen=True)
class FacePlane:
    """Front-plane maps of the neutral model, (H, W) float32 over PLANE_X x PLANE_Y:
    lips (soft mask), brow / upper-lid / lower-lid distances (cm), and the beard region."""

    lips: np.ndarray
    brow_distance: np.ndarray
    upper_lid_distance: np.ndarray
    lower_lid_distance: np.ndarray
    beard: np.ndarray
    eye_centres: np.ndarray     # (2, 3) neutral positions of the two eye-fan centres
    mouth_centre: np.ndarray    # (3,)
    fan_vertices: np.ndarray    # (3,) vertex ids: eye (image right), eye (image left), mouth


@functools.lru_cache(maxsize=2)
def face_plane(model: FaceModel) -> FacePlane:
    """The front-plane maps of `model`, rasterised once per process from its landmarks."""
    landmarks = model.landmark_neutral
    shape = (int(round((PLANE_Y[1] - PLANE_Y[0]) / PLANE_CM_PER_TEXEL)),
             int(round((PLANE_X[1] - PLANE_X[0]) / PLANE_CM_PER_TEXEL)))

    def texels(indices):
        xy = landmarks[list(indices), :2]
        cols = (xy[:, 0] - PLANE_X[0]) / PLANE_CM_PER_TEXEL
        rows = (PLANE_Y[1] - xy[:, 1]) / PLANE_CM_PER_TEXEL
        return np.round(np.stack([cols, rows], axis=1) * 16).astype(np.int32)  # 4 fractional bits

    def distance_to_lines(polylines, shift_cm=0.0):
        canvas = np.full(shape, 255, np.uint8)
        for line in polylines:
            points = texels(line)
            points[:, 1] -= int(round(shift_cm / PLANE_CM_PER_TEXEL * 16))
            cv2.polylines(canvas, [points], False, 0, 1, cv2.LINE_AA, shift=4)
        return cv2.distanceTransform((canvas > 128).astype(np.uint8), cv2.DIST_L2, 5) \
            * np.float32(PLANE_CM_PER_TEXEL)

    lips = np.zeros(shape, np.uint8)
    cv2.fillPoly(lips, [texels(OUTER_LIP)], 255, cv2.LINE_AA, shift=4)
    lips = cv2.GaussianBlur(lips.astype(np.float32) / 255.0, (0, 0), 2.0)
    # Beard: below a line from the moustache (under the nose) down to the mouth corners and
    # up the cheeks to the sideburns, outside the lips
    rows = PLANE_Y[1] - (np.arange(shape[0]) + 0.5) * PLANE_CM_PER_TEXEL
    cols = PLANE_X[0] + (np.arange(shape[1]) + 0.5) * PLANE_CM_PER_TEXEL
    nose_y, corner = landmarks[NOSE_BOTTOM, 1], landmarks[MOUTH_CORNER]
    edge = np.interp(np.abs(cols), [0.0, 0.8 * abs(corner[0]), abs(corner[0]) + 0.3, 6.8],
                     [nose_y - 0.4, nose_y - 0.6, corner[1] - 0.2, 1.5])
    beard = ((rows[:, None] < edge[None, :]) & (lips < 0.05)).astype(np.float32)
    centres = model.neutral[-3:].astype(np.float64)
    return FacePlane(lips=lips,
                     brow_distance=distance_to_lines(BROWS, shift_cm=-0.25),
                     upper_lid_distance=distance_to_lines(UPPER_LIDS),
                     lower_lid_distance=distance_to_lines(LOWER_LIDS),
                     beard=cv2.GaussianBlur(beard, (0, 0), 4.0),
                     eye_centres=centres[:2], mouth_centre=centres[2],
                     fan_vertices=np.arange(model.neutral.shape[0] - 3, model.neutral.shape[0]))


def _plane_lookup(plane_map, xy) -> np.ndarray:
    """Bilinear lookup of a front-plane map at neutral (N, 2) x, y (cm); edges clamp."""
    cols = (xy[:, 0] - PLANE_X[0]) / PLANE_CM_PER_TEXEL - 0.5
    rows = (PLANE_Y[1] - xy[:, 1]) / PLANE_CM_PER_TEXEL - 0.5
    return map_coordinates(plane_map, [rows, cols], order=1, mode="nearest").astype(np.float32)


def smoothstep(edge0, edge1, x):
    t = np.clip((x - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _skin_variation(points, seed: int) -> np.ndarray:
    """(N,) multiplicative blotches of about +-6 %: a few random 3D sinusoids (1.5-6 cm)."""
    rng = np.random.default_rng(seed)
    directions = rng.normal(size=(6, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    frequencies = 2 * np.pi / rng.uniform(1.5, 6.0, 6)
    phases = rng.uniform(0, 2 * np.pi, 6)
    waves = np.sin(points @ (directions * frequencies[:, None]).T + phases)
    return 1.0 + 0.06 * waves.mean(axis=1) * np.sqrt(6.0)


def paint(model: FaceModel, look: FaceLook, triangles, barycentric) -> np.ndarray:
    """Albedo (N, 3) float32 of N surface points given by their triangle ids (N,) and
    barycentric weights (N, 3) (weights of the triangle's three corners)."""
    plane = face_plane(model)
    corners = model.triangles[triangles]                          # (N, 3)
    points = np.einsum("nk,nkd->nd", barycentric, model.neutral[corners].astype(np.float64))
    xy, y, z = points[:, :2], points[:, 1], points[:, 2]
    front = smoothstep(1.0, 4.0, z)                               # front features fade at the sides
    skin = np.asarray(look.skin, np.float32)
    colour = skin[None, :] * _skin_variation(points, look.noise_seed)[:, None].astype(np.float32)

    # cheeks a little redder, lips, beard, brows, lash lines (front plane)
    cheek = np.exp(-(((np.abs(points[:, 0]) - 4.3) ** 2 + (y + 0.5) ** 2) / 4.0)) * front
    colour *= (1.0 - 0.08 * cheek[:, None] * np.array([0.0, 1.0, 1.0]))
    lips = _plane_lookup(plane.lips, xy) * front
    colour = _mix(colour, np.asarray(look.lip, np.float32), lips)
    hair = np.asarray(look.hair, np.float32)
    beard = look.beard * _plane_lookup(plane.beard, xy) * smoothstep(-1.0, 2.0, z) \
        * smoothstep(-13.0, -9.0, y)
    colour = _mix(colour, hair, beard * _speckle(points, look.noise_seed))
    brow = 1.0 - smoothstep(look.brow_width_cm * 0.6, look.brow_width_cm,
                            _plane_lookup(plane.brow_distance, xy))
    colour = _mix(colour, hair * 0.6, look.brow_strength * brow * front)
    lash = (1.0 - smoothstep(0.05, 0.14, _plane_lookup(plane.upper_lid_distance, xy))) * look.lash_strength
    lash = np.maximum(lash, 0.4 * look.lash_strength
                      * (1.0 - smoothstep(0.02, 0.08, _plane_lookup(plane.lower_lid_distance, xy))))
    colour = _mix(colour, np.array([0.02, 0.015, 0.012], np.float32), lash * front)

    # scalp: hair above the hairline at the front, lower at the sides and the back
    if not look.bald:
        threshold = look.hair_back_cm + (look.hairline_cm - look.hair_back_cm) * smoothstep(-3.0, 6.0, z)
        scalp = smoothstep(threshold - 0.3, threshold + 0.3, y)
        colour = _mix(colour, hair * _speckle(points, look.noise_seed + 1)[:, None], scalp)

    colour = _paint_openings(model, plane, look, corners, barycentric, points, colour)
    return np.clip(colour, 0.0, 1.0).astype(np.float32)


def _paint_openings(model, plane, look, corners, barycentric, points, colour):
    """Eyes (sclera, iris, pupil, a dark rim where lid and lashes shade it) and the mouth
    (dark inside, teeth under the upper lip) on the fans that close the openings."""
    colour = colour.copy()
    for k, centre_vertex in enumerate(plane.fan_vertices):
        on_fan = np.any(corners == centre_vertex, axis=1)
        if not on_fan.any():
            continue
        centre_weight = np.sum(np.where(corners[on_fan] == centre_vertex, barycentric[on_fan], 0.0), axis=1)
        rim = 1.0 - smoothstep(0.15, 0.45, centre_weight)
        if k < 2:
            offset = points[on_fan, :2] - plane.eye_centres[k, :2] - np.asarray(look.gaze)
            radius = np.linalg.norm(offset, axis=1)
            eye = _mix(np.broadcast_to(np.asarray(look.sclera, np.float32), (radius.size, 3)),
                       np.asarray(look.iris, np.float32), 1.0 - smoothstep(0.52, 0.6, radius))
            eye = _mix(eye, np.array([0.01, 0.01, 0.01], np.float32), 1.0 - smoothstep(0.2, 0.26, radius))
            colour[on_fan] = eye * (1.0 - 0.6 * rim)[:, None]
        else:
            rim_y = np.sum(np.where(corners[on_fan] == centre_vertex, 0.0,
                                    barycentric[on_fan] * model.neutral[corners[on_fan], 1]), axis=1)
            rim_y /= np.maximum(1.0 - centre_weight, 1e-6)
            upper = rim_y > plane.mouth_centre[1]
            inside = np.asarray(look.lip, np.float32) * 0.12
            teeth = np.array([0.5, 0.45, 0.38], np.float32)
            show = (upper & (centre_weight < 0.6) & look.teeth)[:, None]
            colour[on_fan] = np.where(show, teeth, inside)
    return colour


def _speckle(points, seed: int) -> np.ndarray:
    """(N,) strand-like variation in [0.6, 1.2] for hair (fine sinusoids mostly along y)."""
    rng = np.random.default_rng(seed)
    f = rng.uniform(8.0, 16.0, 3)
    waves = np.sin(f[0] * points[:, 0] + 3.0 * np.sin(f[1] * points[:, 2])) * np.sin(f[2] * points[:, 2] + 1.0)
    return (0.9 + 0.3 * waves).astype(np.float32)


def _mix(a, b, t) -> np.ndarray:
    """a (1 - t) + b t, broadcasting colours (3,) or (N, 3) with weights (N,)."""
    t = np.asarray(t, np.float32)[:, None] if np.ndim(t) == 1 else np.asarray(t, np.float32)
    return (np.asarray(a, np.float32) * (1.0 - t) + np.asarray(b, np.float32) * t).astype(np.float32)
