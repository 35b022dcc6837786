"""Between the full photo and the square working crop, and back: crop box, crop, paste-back;
relit = albedo * shading; backgrounds; display exposure; the preview sheet.

Full-frame work (paste-back, compositing) goes a band of rows at a time (io.images.row_bands),
so a 24-megapixel photo costs its result arrays and no frame-sized temporaries.

The crop's orthographic camera spans the world square [-1, 1] x [-1, 1] (CROP_RECT): pixel
(i, j) of an R x R crop has its centre at x = -1 + (j + 0.5) 2/R, y = 1 - (i + 0.5) 2/R
(DESIGN.md's pixel-centre formula), the same square the geometry nets predict depth in.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from relightcli.errors import InputError
from relightcli.io.images import LUMINANCE, linear_to_srgb, row_bands, srgb_to_linear

CROP_RECT = (-1.0, 1.0, -1.0, 1.0)  # x0, x1, y0, y1 of the working crop


@dataclass(frozen=True)
class CropBox:
    """A square of `size` full-frame pixels with its top-left corner at (x0, y0); it may reach
    outside the photo (that part is padded). `resolution` is the working crop's side."""

    x0: int
    y0: int
    size: int
    resolution: int

    @property
    def scale(self) -> float:
        """Full-frame pixels per crop pixel."""
        return self.size / self.resolution


def person_crop_box(mask: np.ndarray, resolution: int, margin: float = 0.08, path=None) -> CropBox:
    """The square around the person: the mask's bounding box (mask > 0.5), its longer side
    grown by `margin` on each side, centred on the box. mask: (H, W) in [0, 1]."""
    rows = np.flatnonzero((mask > 0.5).any(axis=1))
    cols = np.flatnonzero((mask > 0.5).any(axis=0))
    if rows.size == 0:
        raise InputError("no person found: the mask is empty", path=path,
                         fix="check --mask, or use a photo where the person is clearly visible")
    height, width = rows[-1] + 1 - rows[0], cols[-1] + 1 - cols[0]
    size = int(np.ceil(max(height, width) * (1.0 + 2.0 * margin)))
    size = max(size, 8)
    cy, cx = (rows[0] + rows[-1] + 1) / 2.0, (cols[0] + cols[-1] + 1) / 2.0
    return CropBox(int(round(cx - size / 2.0)), int(round(cy - size / 2.0)), size, resolution)


# The people's soft mask pulled to the photo's edges by a guided filter (He et al. 2013) in
# the crop, guided by the sRGB photo: radius SNAP_RADIUS x the crop side, regularisation
# SNAP_EPS. Chosen on the 20 validation scenes (data/evalval512) among radii 2-16 px at 512 and
# eps 1e-4..1e-2: wider radii or smaller eps follow background texture into the mask
SNAP_RADIUS, SNAP_EPS = 2 / 512, 0.01


def snap_mask(crop: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(R, R) float32 soft mask in [0, 1]: `mask` (R, R) with its edges pulled to the edges of
    `crop` (R, R, 3) float32 linear; NaN and infinite pixels count as black."""
    guide = linear_to_srgb(np.clip(np.nan_to_num(crop, nan=0.0, posinf=0.0, neginf=0.0), 0.0, 1.0))
    radius = max(1, round(SNAP_RADIUS * mask.shape[0]))
    snapped = cv2.ximgproc.guidedFilter(np.ascontiguousarray(guide, np.float32),
                                        np.ascontiguousarray(mask, np.float32), radius, SNAP_EPS)
    return np.clip(snapped, 0.0, 1.0).astype(np.float32)


def replace_in_box(full: np.ndarray, crop: np.ndarray, box: CropBox) -> np.ndarray:
    """`full` (H, W[, C]) with the box's part replaced by the (R, R[, C]) crop pasted back
    (bilinear); in place, returned."""
    height, width = full.shape[:2]
    ys, xs = _overlap(box.y0, box.size, height), _overlap(box.x0, box.size, width)
    if ys and xs:
        band = paste_back(crop, box, height, width, slice(*ys))
        full[ys[0]:ys[1], xs[0]:xs[1]] = band[:, xs[0]:xs[1]]
    return full


def crop_square(image: np.ndarray, box: CropBox) -> np.ndarray:
    """(H, W[, C]) float32 full frame -> (R, R[, C]) crop, zero outside the photo; area
    averaging when shrinking, bilinear when enlarging."""
    height, width = image.shape[:2]
    region = np.zeros((box.size, box.size) + image.shape[2:], np.float32)
    ys, xs = _overlap(box.y0, box.size, height), _overlap(box.x0, box.size, width)
    if ys and xs:
        region[ys[0] - box.y0:ys[1] - box.y0, xs[0] - box.x0:xs[1] - box.x0] = image[ys[0]:ys[1], xs[0]:xs[1]]
    interpolation = cv2.INTER_AREA if box.size >= box.resolution else cv2.INTER_LINEAR
    out = cv2.resize(region, (box.resolution, box.resolution), interpolation=interpolation)
    return out.reshape((box.resolution, box.resolution) + image.shape[2:])


def outside_photo(box: CropBox, height: int, width: int) -> np.ndarray:
    """(R, R) bool: the working crop's pixels whose centres fall beyond a height x width
    photo's edge (the padded part of a box that reaches outside it)."""
    centres = (np.arange(box.resolution) + 0.5) * box.scale
    rows = (box.y0 + centres < 0) | (box.y0 + centres >= height)
    cols = (box.x0 + centres < 0) | (box.x0 + centres >= width)
    return rows[:, None] | cols[None, :]


def paste_back(crop: np.ndarray, box: CropBox, height: int, width: int, rows: slice | None = None) -> np.ndarray:
    """(R, R[, C]) crop -> (height, width[, C]) full frame, zero outside the box. Bilinear.

    rows: a slice (step 1) of the full frame's rows to return, default all. The box is warped a
    band of rows at a time, so the result is the only array of the frame's size."""
    top, bottom, _ = (rows or slice(None)).indices(height)
    out = np.zeros((max(bottom - top, 0), width) + crop.shape[2:], np.float32)
    y_lo, y_hi = max(box.y0, top), min(box.y0 + box.size, bottom)  # rows of the box among them
    xs = _overlap(box.x0, box.size, width)
    if y_hi <= y_lo or not xs:
        return out
    crop = np.ascontiguousarray(crop, dtype=np.float32)
    s = box.resolution / box.size
    for band in row_bands(y_hi - y_lo):
        y0, y1 = y_lo + band.start, y_lo + band.stop
        # Map each visible full-frame pixel centre into crop pixel coordinates (inverse warp).
        matrix = np.array([[s, 0.0, (xs[0] - box.x0 + 0.5) * s - 0.5],
                           [0.0, s, (y0 - box.y0 + 0.5) * s - 0.5]])
        visible = cv2.warpAffine(crop, matrix, (xs[1] - xs[0], y1 - y0),
                                 flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE)
        out[y0 - top:y1 - top, xs[0]:xs[1]] = visible.reshape(visible.shape[:2] + crop.shape[2:])
    return out


def _overlap(start: int, size: int, limit: int):
    lo, hi = max(start, 0), min(start + size, limit)
    return (lo, hi) if hi > lo else None


def relight(albedo: np.ndarray, shading: np.ndarray) -> np.ndarray:
    """relit = albedo * shading, element-wise, linear light (DESIGN.md)."""
    return (albedo * shading).astype(np.float32)


# The photo / shading ratio is ill-conditioned where the estimated input shading is dark (noise
# and clipping divided by almost nothing): below RATIO_DARK x the person's median shading the
# net's albedo takes over, fully at RATIO_DARK and not at all from 4 x RATIO_DARK on
RATIO_DARK = 0.05


def ratio_albedo(image: np.ndarray, input_shading: np.ndarray, fallback: np.ndarray,
                 mask: np.ndarray) -> np.ndarray:
    """Albedo as image / input_shading (the inverse of `relight`), at least 0, blended into
    `fallback` where the shading is too dark to divide by (RATIO_DARK). All (H, W, 3) float32
    linear except mask (H, W) in [0, 1]; the fallback alone when the person's shading is black.
    Not clipped at 1: that is anchor_albedo's, after the level is set (clipped before, the
    level was taken from a tail cut at the light's level, not the albedo's; validation / test
    relit -0.01 / +0.03 dB, `python bench/light_solve.py`)."""
    level = input_shading.mean(axis=-1)
    inside = level[mask > 0.5]
    median = float(np.median(inside)) if inside.size else 0.0
    if not median > 0:
        return np.asarray(fallback, np.float32)
    weight = np.clip((level / median - RATIO_DARK) / (3 * RATIO_DARK), 0.0, 1.0)[..., None]
    ratio = np.maximum(image / np.maximum(input_shading, 1e-6 * median), 0.0)
    return (weight * ratio + (1.0 - weight) * fallback).astype(np.float32)


# Rounds of shading_the_photo_shows: the local mean taken again without the dips lifted so far (a
# dip darkens its own surroundings' mean: an 8-px dip to 8% under a Gaussian of 8 px is lifted
# to 69% in one round, 95% in two, 99% in three)
DIP_ROUNDS = 3


def shading_the_photo_shows(shading: np.ndarray, photo: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    """`shading` (H, W, 3) raised where it is darker, against its surroundings, than the
    photo (H, W, 3) is against its own: in log luminance, the shading may fall below its local
    mean (a Gaussian of `sigma` px over the mask's pixels, mask (H, W) > 0.5) at most as far as
    the photo falls below its own. A shadow the photo shows (a cast shadow, a crease) stays; a
    dip of the estimated shading the photo does not show (the mesh occluding itself where the
    real surface is lit) would make the albedo, the photo divided by it, a bright spot."""
    inside = (mask > 0.5).astype(np.float32)
    if not inside.any():
        return shading
    log_shading = np.log(np.maximum(shading @ LUMINANCE, 1e-12))
    log_photo = np.log(np.maximum(photo @ LUMINANCE, 1e-12))
    weight = np.maximum(cv2.GaussianBlur(inside, (0, 0), sigma), 1e-6)

    def local(values):
        return cv2.GaussianBlur(values * inside, (0, 0), sigma) / weight

    photo_dip = np.minimum(log_photo - local(log_photo), 0.0)
    lifted = log_shading
    for _ in range(DIP_ROUNDS):  # the local mean again without the dips already lifted
        lifted = np.maximum(log_shading, local(lifted) + photo_dip)
    lift = np.where(inside > 0, np.exp(lifted - log_shading), 1.0)
    return (shading * lift[..., None]).astype(np.float32)


# Pixels of the person's outline whose photo colour mixes in the background (anti-aliasing,
# blur, an imprecise mask): the ring of mask pixels within RATIO_RING px of the outside
RATIO_RING = 1
# The outline ring's albedo: this share of the de-lighting net's, the rest the nearest pixel's
# inside the ring (the photo over the light there, at the net's level). Validation, true mask,
# relit / albedo dB (`relight eval DATA --use-gt-mask`), the net's alone -> the nearest pixel's
# alone -> the mean (0.5): 20 at 512 18.009 / 17.264 -> 18.091 / 17.236 -> 18.092 / 17.314;
# 120 at 256 in training poses 17.111 / 17.759 -> 17.295 / 17.820 -> 17.253 / 17.878; 150 at
# 256 17.973 / 18.335 -> 18.110 / 18.343 -> 18.113 / 18.449. The level then matched inside the
# ring instead of over the whole person: 18.144 / 17.354, 18.132 / 18.507, 17.260 / 17.934
OUTLINE_NET_SHARE = 0.5


def anchor_albedo(ratio: np.ndarray, net_albedo: np.ndarray, mask: np.ndarray,
                  ring: int = RATIO_RING, gain: float | None = None) -> np.ndarray:
    """The ratio albedo's detail and colour at the net's level: one gain for all channels, so
    that the mean over the person and the channels equals the net albedo's (the lighting's
    estimated intensity is less sure than the net's albedo level; its colour is not: the net's
    albedo greys strongly coloured clothes, where the photo over the light keeps their colour),
    clipped to [0, 1] (the means taken inside the outline ring). On the outline ring, where the
    photo mixes in the background, the mean of the net's albedo and the nearest pixel's inside
    the ring (OUTLINE_NET_SHARE). (H, W, 3) float32 linear, mask (H, W); gain: albedo_gain's,
    when the caller has it already.

    Measured against a gain per channel (`relight eval DATA [--use-gt-mask]`, relit / albedo
    dB): 150 validation scenes at 256 (`python -m export.factory.eval_scenes data/factory256p
    data/evalval256 --split val`, `--resolution 256 --use-gt-mask`) 17.63 / 18.19 -> 17.70 /
    18.27; data/evalval512 true mask 16.81 / 16.32 -> 16.77 / 16.14, own mask 16.25 / 16.22 ->
    16.22 / 16.05; test (data/eval512) true mask 18.06 / 18.54 -> 19.03 / 19.84, own mask
    17.89 / 18.33 -> 18.67 / 19.47 (its green and red outfits came out grey)."""
    inside = mask > 0.5
    if not inside.any():
        return np.asarray(ratio, np.float32)
    core = _inside_ring(inside, ring)
    gain = albedo_gain(ratio, net_albedo, mask, ring) if gain is None else gain
    out = np.clip(ratio * np.float32(gain), 0.0, 1.0)
    if ring > 0:
        outline = inside & ~core
        nearest = fill_uncovered(out, core, outline) if core.any() else net_albedo
        out[outline] = (OUTLINE_NET_SHARE * net_albedo[outline]
                        + (1.0 - OUTLINE_NET_SHARE) * nearest[outline])
    return out.astype(np.float32)


def albedo_gain(ratio: np.ndarray, net_albedo: np.ndarray, mask: np.ndarray, ring: int = RATIO_RING) -> float:
    """The one gain anchor_albedo gives the ratio albedo: the net albedo's mean over the person
    and the channels over the ratio's, both inside the outline ring (where the photo is the
    person's alone); 1 with no person or a black ratio."""
    inside = mask > 0.5
    if not inside.any():
        return 1.0
    core = _inside_ring(inside, ring)
    level = core if core.any() else inside
    have, want = float(ratio[level].mean()), float(net_albedo[level].mean())
    return want / have if have > 1e-6 else 1.0


def _inside_ring(inside: np.ndarray, ring: int) -> np.ndarray:
    return cv2.erode(inside.astype(np.uint8), np.ones((2 * ring + 1,) * 2, np.uint8), borderValue=0) > 0


def fill_uncovered(values: np.ndarray, covered: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    """(H, W, ...) values with the nearest covered pixel's copied into wanted-but-uncovered
    pixels (unchanged where nothing is covered)."""
    holes = wanted & ~covered
    if not holes.any() or not covered.any():
        return values
    box, inner, nearest, _ = _nearest_covered(values, covered, holes)
    filled = values.copy()
    filled[box][inner] = nearest
    return filled


def fill_smooth(values: np.ndarray, covered: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    """(H, W, C) values with wanted-but-uncovered pixels filled from the covered ones: within
    FILL_NEAREST_PX of a covered pixel the nearest one's values (fill_uncovered), further in
    smoothly (pull-push: the covered values averaged over ever coarser 2 x 2 blocks, then each
    level's gaps filled from the next coarser one, bilinearly), the two blended over
    FILL_BLEND_PX. Unchanged elsewhere and where nothing is covered. A hole wider than a few
    pixels (the mesh missing between two people, behind an arm) gets no wedges of one
    neighbour's value; a thin rim keeps its neighbour's."""
    holes = wanted & ~covered
    if not holes.any() or not covered.any():
        return values
    box, inner, nearest, distance = _nearest_covered(values, covered, holes)
    share = np.clip((distance - FILL_NEAREST_PX) / FILL_BLEND_PX, 0.0, 1.0)[:, None]
    if share.any():
        smooth = _pull_push(values[box], covered[box])[inner]
        nearest = (1.0 - share) * nearest + share * smooth
    out = values.copy()
    out[box][inner] = nearest.astype(values.dtype)
    return out


def _nearest_covered(values: np.ndarray, covered: np.ndarray, holes: np.ndarray):
    """(box, the holes inside it, the nearest covered pixel's values at each hole, its distance
    in pixels). The transform runs over the box around the covered pixels and the holes only: it
    holds every pixel that can be nearest, so the answer is the whole image's at a fraction of
    its cost (a person fills about half a square crop; issue 50)."""
    from scipy.ndimage import distance_transform_edt

    box = bounding_box(covered | holes)
    inner = holes[box]
    distance, (rows, cols) = distance_transform_edt(~covered[box], return_indices=True)
    return box, inner, values[box][rows[inner], cols[inner]], distance[inner]


# fill_smooth: hole pixels this close to a covered one copy it; the smooth fill takes over
# across the next FILL_BLEND_PX (validation, own mask: the smooth fill everywhere lost 0.035 dB
# of relit against the nearest pixel's copy, a thin rim being most of the holes there)
FILL_NEAREST_PX = 2.0
FILL_BLEND_PX = 4.0


def _pull_push(values: np.ndarray, covered: np.ndarray) -> np.ndarray:
    """(H, W, C) float32: the covered pixels' values, and everywhere else a smooth fill from
    them (pull-push over 2 x 2 blocks, bilinear push). Non-finite values count as uncovered."""
    known = covered & np.isfinite(values).all(axis=-1)  # (a NaN would spread over every level)
    finest = np.where(known[..., None], values, 0.0).astype(np.float32)
    scale = float(np.abs(finest).max()) if known.any() else 0.0
    if not scale > 0:
        return finest
    weight, summed = known.astype(np.float32), finest / np.float32(scale)  # (sums of 4 stay finite)
    pyramid = []  # each coarser level's (values, weights in [0, 1])
    while weight.min() == 0 and max(weight.shape) > 1:  # (nothing finite: the coarsest level is 0)
        total = _block_sum(weight)
        level = _block_sum(summed) / np.maximum(total, 1e-12)[..., None]
        weight = np.minimum(total, 1.0)
        summed = level * weight[..., None]
        pyramid.append((level, weight))
    if not pyramid:
        return finest
    filled = pyramid[-1][0]
    for level, weight in reversed(pyramid[:-1]):
        filled = level * weight[..., None] + _upsample_half(filled, weight.shape) * (1.0 - weight[..., None])
    return np.where(known[..., None], finest, _upsample_half(filled, known.shape) * np.float32(scale))


def _block_sum(image: np.ndarray) -> np.ndarray:
    """The sums of an (H, W, ...) image's 2 x 2 blocks (zeros beyond an odd edge)."""
    if image.shape[0] % 2 or image.shape[1] % 2:
        padded = np.zeros((image.shape[0] + image.shape[0] % 2, image.shape[1] + image.shape[1] % 2)
                          + image.shape[2:], image.dtype)
        padded[:image.shape[0], :image.shape[1]] = image
        image = padded
    return image[0::2, 0::2] + image[1::2, 0::2] + image[0::2, 1::2] + image[1::2, 1::2]


def _upsample_half(image: np.ndarray, shape: tuple) -> np.ndarray:
    """(H, W, C) bilinear from an (h, w, C) image of 2 x 2 blocks' means (block i's centre at
    fine coordinate 2i + 0.5: fine pixel 2i is 3/4 block i and 1/4 block i - 1, 2i + 1 is 3/4
    block i and 1/4 block i + 1), cropped to `shape`; held beyond the edges."""
    def axis(image, size):
        padded = np.concatenate([image[:1], image, image[-1:]])
        fine = np.empty((2 * image.shape[0],) + image.shape[1:], image.dtype)
        fine[0::2] = 0.75 * image + 0.25 * padded[:-2]
        fine[1::2] = 0.75 * image + 0.25 * padded[2:]
        return fine[:size]

    rows = axis(image, shape[0])
    return axis(rows.swapaxes(0, 1), shape[1]).swapaxes(0, 1)


def bounding_box(mask: np.ndarray, margin: int = 0) -> tuple[slice, slice]:
    """(rows, columns) slices of the smallest box holding every True pixel of an (H, W) mask,
    grown by `margin` pixels on every side within the image (empty slices for an empty mask)."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return slice(0, 0), slice(0, 0)
    return (slice(max(int(rows[0]) - margin, 0), int(rows[-1]) + margin + 1),
            slice(max(int(cols[0]) - margin, 0), int(cols[-1]) + margin + 1))


def display_exposure(relit: np.ndarray, mask: np.ndarray, target: float) -> float:
    """The factor that maps the 95th percentile of the person's luminance to `target`, for LDR
    outputs (an HDR environment gives radiance in arbitrary units; a PNG clips at 1). 1.0 for a
    black person."""
    return exposure_for(relit[mask > 0.5] @ LUMINANCE, target)


def exposure_for(luminance: np.ndarray, target: float) -> float:
    """display_exposure from the person's luminance values, (N,) in any order."""
    if luminance.size == 0:
        return 1.0
    p95 = float(np.percentile(luminance, 95.0))
    return target / p95 if p95 > 0 else 1.0


def person_luminance(bands, mask: np.ndarray) -> np.ndarray:
    """Luminance of the pixels where mask > 0.5, (N,) float32, from `bands`: (rows, image rows)
    pairs that cover the (H, W) mask, e.g. pasted_bands(...)."""
    return np.concatenate([band[mask[rows] > 0.5] @ LUMINANCE for rows, band in bands])


def pasted_bands(crop: np.ndarray, box: CropBox, height: int, width: int):
    """(rows, paste_back(crop, box, height, width)[rows]) for bands of rows, top to bottom."""
    for rows in row_bands(height):
        yield rows, paste_back(crop, box, height, width, rows)


def parse_colour(text: str) -> np.ndarray:
    """'#RGB' or '#RRGGBB' (sRGB) -> (3,) float32 linear."""
    digits = text.lstrip("#")
    if len(digits) == 3:
        digits = "".join(c * 2 for c in digits)
    values = np.array([int(digits[i:i + 2], 16) for i in (0, 2, 4)], np.float32) / 255.0
    return srgb_to_linear(values)


# A predicted mask is a segmentation's probability, not an alpha matte: the relit output over
# the photo or the environment view is composited with it sharpened, PREDICTED_MATTE[0]..[1]
# stretched to 0..1 (relightcli.stages.compose.relit_matte), so the relit person is opaque where the
# segmentation is fairly sure (the background does not show through) and the unsure fringe,
# often background the segmentation spilled onto, is left to the background. Measured against
# the true composite (the true relit person over the same background by the true mask; `python
# bench/composite_matte.py DATA`, sRGB PSNR around the people), validation, the 148 scenes at
# 256 / 19 at 512 where a person is found, 0.2..0.8 against the mask as alpha: over the kept
# photo +0.12 / +0.09 dB, the environment view +0.39 / +0.13 (0.1..0.9 +0.09 / +0.06 and +0.25
# / +0.09, 0.35..0.65 +0.09 / +0.08 and +0.45 / +0.09, a 0.5 threshold -0.02 / +0.01 and +0.31
# / -0.02, raising the inside alone, 0..0.8, -0.14 / -0.12 and +0.28 / +0.04)
PREDICTED_MATTE = (0.2, 0.8)


def sharpened(mask: np.ndarray, matte: tuple[float, float]) -> np.ndarray:
    """(H, W) float32 mask stretched linearly from matte = (low, high) to 0..1, clipped."""
    low, high = matte
    return np.clip((mask - np.float32(low)) / np.float32(high - low), 0.0, 1.0).astype(np.float32)


def composite(relit: np.ndarray, mask: np.ndarray, background: str, *, photo: np.ndarray | None = None,
              env_view: np.ndarray | None = None, matte: tuple[float, float] | None = None):
    """Place the relit person over a background. relit, photo, env_view: (H, W, 3) float32
    linear; mask: (H, W) straight alpha, sharpened first when `matte` is given (PREDICTED_MATTE).
    Returns (rgb, alpha); alpha is None except for 'transparent'. background: keep | env |
    transparent | '#RRGGBB'."""
    if matte is not None:
        mask = sharpened(mask, matte)
    alpha = mask[..., None].astype(np.float32)
    if background == "transparent":
        return (relit * (alpha > 0)).astype(np.float32), mask.astype(np.float32)
    if background == "keep":
        behind = photo
    elif background == "env":
        behind = env_view
    else:
        behind = np.broadcast_to(parse_colour(background), relit.shape)
    if behind is None:
        raise ValueError(f"background {background!r} needs its image")
    return (relit * alpha + behind * (1.0 - alpha)).astype(np.float32), None


def composite_crop(relit: np.ndarray, box: CropBox, mask: np.ndarray, background: str, *,
                   photo: np.ndarray | None = None, env_view: np.ndarray | None = None, scale: float = 1.0,
                   out: np.ndarray | None = None, matte: tuple[float, float] | None = None,
                   detail: PhotoDetail | None = None):
    """composite() of the (R, R, 3) relit crop pasted back into the frame, relit and env_view
    times `scale` (display exposure), a band of rows at a time: the (H, W, 3) result is the
    only frame-sized array it makes, none with `out` (where to write it; it may be photo or
    env_view, each band is read before it is written). mask, photo, env_view: full frame, as
    composite(); matte as composite()'s, applied a band at a time; detail: the photo's detail
    the crop lost, put back into the relit person (PhotoDetail)."""
    height, width = mask.shape
    rgb = np.empty((height, width, 3), np.float32) if out is None else out
    for rows, person in pasted_bands(relit, box, height, width):
        if detail is not None:
            detail.apply(person, rows)
        rgb[rows], _ = composite(
            person * np.float32(scale), mask[rows], background, photo=None if photo is None else photo[rows],
            env_view=None if env_view is None else env_view[rows] * np.float32(scale), matte=matte)
    if background != "transparent":
        return rgb, None
    return rgb, mask.astype(np.float32, copy=False) if matte is None else sharpened(mask, matte)


# The photo's detail factor, per channel: the photo over its crop pasted back, this at least
# DETAIL_FLOOR (linear, below an 8-bit photo's first step, 3e-4), the factor at most DETAIL_RANGE:
# the relit is the photo times the crop's relight ratio, and a black pixel stays black. Added to
# both sides and held above 1 / DETAIL_RANGE, the floor lifted the photo's darkest pixels
# (nostrils, pupils, lash lines) against their surroundings: bright spots in 1.15% of the
# face-paint portrait's face pixels at 1e-3 and 4x, 0.73% at 1e-4 and 16x, 0.65% now (`python
# bench/face_check.py`; added to the crop's side alone, 0.63%, it darkened the dark pixels by
# the floor over the crop's value)
DETAIL_FLOOR = 1e-4
DETAIL_RANGE = 16.0


class PhotoDetail:
    """What the working crop lost of the photo's detail, to put back into the full-frame layers
    that carry it (relit, albedo): unless the crop has the photo's own pixels (box.scale 1), the
    photo over its crop pasted back (where the crop is coarser, the detail finer than a crop
    pixel; where it is finer, what enlarging and shrinking back blurred; shading and light are
    smooth at that scale, so relit = albedo x shading takes it through the albedo alone),
    inside the person's mask eroded by a crop pixel (where the crop's pixels did not mix in the
    background). A factor per channel, so the photo's colour detail comes back with its
    luminance: with one factor for the three, the crop's colour, blurred, stayed, and the relit
    face's colour departed from the photo's at every colour edge (paint, lips, the eyes' whites:
    `python bench/face_check.py`). photo: (H, W, 3) linear full frame; crop: its (R, R, 3)
    working crop; mask: (H, W)."""

    def __init__(self, photo: np.ndarray, crop: np.ndarray, box: CropBox, mask: np.ndarray):
        self.photo, self.box = photo, box
        self.active = box.scale != 1.0
        if self.active:
            self.crop = np.ascontiguousarray(crop, dtype=np.float32)
            side = 2 * int(np.ceil(box.scale)) + 1
            self.inside = cv2.erode((mask > 0.5).astype(np.uint8), np.ones((side, side), np.uint8),
                                    borderValue=0).astype(bool)
            # the columns that hold the person's inside pixels (the factor is 1 elsewhere)
            self.columns = bounding_box(self.inside)[1]

    def factor(self, rows: slice) -> np.ndarray | None:
        """(h, W, 3) float32 detail factor of the full frame's `rows` (1 outside the person),
        None when the crop has the photo's own pixels."""
        if not self.active:
            return None
        out = np.ones((len(range(*rows.indices(self.photo.shape[0]))), self.photo.shape[1], 3), np.float32)
        out[:, self.columns] = self._factor(rows, self.columns)
        return out

    def apply(self, layer: np.ndarray, rows: slice) -> np.ndarray:
        """A full-frame band (h, W, 3) of a layer times the detail factor, in place."""
        if self.active:
            layer[:, self.columns] *= self._factor(rows, self.columns)
        return layer

    def _factor(self, rows: slice, columns: slice) -> np.ndarray:
        height, width = self.photo.shape[:2]
        smooth = paste_back(self.crop, self.box, height, width, rows)[:, columns]
        floor = np.float32(DETAIL_FLOOR)
        np.maximum(smooth, floor, out=smooth)
        ratio = self.photo[rows, columns].astype(np.float32)
        ratio /= smooth
        np.clip(ratio, 0.0, DETAIL_RANGE, out=ratio)
        np.copyto(ratio, np.float32(1.0), where=~self.inside[rows, columns, None])
        return ratio


def to_display(image: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """Linear -> sRGB-encoded [0, 1] float32 for previews."""
    return linear_to_srgb(np.clip(image * scale, 0.0, 1.0))


def preview_sheet(tiles: list[tuple[str, np.ndarray]], height: int = 256) -> np.ndarray:
    """One row of display-ready tiles (sRGB-encoded [0, 1], (h, w, 3) or (h, w)), each resized
    to `height` rows, titled. Returns (height + 24, total width, 3) float32 sRGB-encoded."""
    columns = []
    for title, tile in tiles:
        if tile.ndim == 2:
            tile = np.repeat(tile[..., None], 3, axis=2)
        width = max(1, int(round(tile.shape[1] * height / tile.shape[0])))
        # shrunk by area; enlarged (the 16 x 32 input light) bilinearly, not in blocks
        interpolation = cv2.INTER_AREA if tile.shape[0] >= height else cv2.INTER_LINEAR
        resized = cv2.resize(tile.astype(np.float32), (width, height), interpolation=interpolation)
        banner = np.full((24, width, 3), 255, np.uint8)  # OpenCV draws text on 8-bit images only
        cv2.putText(banner, title, (4, 17), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
        columns.append(np.concatenate([banner / np.float32(255), np.clip(resized, 0.0, 1.0)], axis=0))
        columns.append(np.ones((height + 24, 4, 3), np.float32))
    return np.concatenate(columns[:-1], axis=1)
