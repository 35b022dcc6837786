"""The stages of one relighting run, each a function of (frame, options, models).

`Frame` carries what earlier stages produced. Working-crop arrays are (R, R, ...) float32 in
the crop camera of relightcli.compose (world square [-1, 1]^2, orthographic along -Z);
full-frame arrays are (H, W, ...) float32. Networks see the crop as the photo shows it
(background included, as in training); their outputs are masked afterwards. Results stay at the
crop's size until an output needs them full frame: a 24 MP frame is 288 MB as float32 RGB.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from relightcli import compose
from relightcli.compose import fill_uncovered
from relightcli.io.envmap import environment_view
from relightcli.io.images import row_bands
from relightcli.errors import RelightError, RelightWarning
from relightcli.layers import DEFAULT_SPP_CAP, DEFAULT_TARGET_ERROR, INPUT_SHADOW_GRID, SHADOW_STEP


@dataclass
class Frame:
    image: np.ndarray  # (H, W, 3) linear photo
    mask: np.ndarray | None  # (H, W) person alpha; None until the mask stage when not given
    env: np.ndarray  # (h, 2h, 3) target environment, linear radiance
    box: compose.CropBox | None = None
    crop: np.ndarray | None = None  # (R, R, 3)
    crop_mask: np.ndarray | None = None  # (R, R)
    normal: np.ndarray | None = None  # (R, R, 3), zero outside the person
    geometry: object | None = None  # relightcli.nets.geometry.GeometryMaps
    ao: np.ndarray | None = None  # (R, R) the AO layer
    ao_net: np.ndarray | None = None  # (R, R) the AO net's map: the refinement's input
    albedo: np.ndarray | None = None  # (R, R, 3)
    light: np.ndarray | None = None  # (16, 32, 3) estimated input lighting
    mesh: object | None = None  # trimesh.Trimesh in the crop camera frame
    scene: object | None = None  # relightcli.render.scene.Scene of the mesh (closed by the pipeline)
    hits: object | None = None  # relightcli.render.camera.PixelGeometry: what each crop pixel sees
    coarse_shading: np.ndarray | None = None  # (R, R, 3) ray-traced
    shading: np.ndarray | None = None  # (R, R, 3) final shading under env
    relit_crop: np.ndarray | None = None  # (R, R, 3) albedo * shading, linear
    view: "PerceptionView | None" = None  # the photo as the perception nets see it
    people: list = field(default_factory=list)  # relightcli.nets.pose.Person found, in view pixels
    portrait_mask: np.ndarray | None = None  # (h, w) selfie segmentation when only a face was found
    face_fit: object | None = None  # relightcli.geometry.face.FaceFit, when the face stage found a face
    face_crop: object | None = None  # its relightcli.geometry.face.CropRect in the working crop
    bodies: list = field(default_factory=list)  # relightcli.geometry.body_fit.BodyFit per person
    body_scene: object | None = None  # Scene of the converged bodies (closed by the pipeline)
    body_maps: object | None = None  # relightcli.geometry.body_maps.BodyMaps of those bodies
    body_hits: object | None = None  # PixelGeometry: what each person pixel sees of them
    notes: dict = field(default_factory=dict)  # stage -> facts for the report
    mask_predicted: bool = False  # the mask is the segmentations' (stage_mask), not the input's

    @property
    def relit(self) -> np.ndarray:
        """(H, W, 3) full frame, linear, person only: relit_crop pasted back, anew on each
        access (the outputs composite it a band of rows at a time instead)."""
        height, width = self.image.shape[:2]
        return compose.paste_back(self.relit_crop, self.box, height, width)


# The perception nets see the photo at most this many pixels on its long side: their inputs are
# 128-256 px crops, and a full-size sRGB copy of a 24 MP photo alone is 288 MB
PERCEPTION_MAX_SIDE = 2048


@dataclass
class PerceptionView:
    """The photo as the perception nets see it: `image` (h, w, 3) float32 sRGB in [0, 1],
    shrunk by `scale` (sx, sy) from the photo (continuous pixel coordinates: view = photo x
    scale)."""

    image: np.ndarray
    scale: tuple[float, float]

    @classmethod
    def of(cls, photo: np.ndarray) -> "PerceptionView":
        """The view of a linear (H, W, 3) photo (NaN and infinite pixels count as black)."""
        from relightcli.io.images import linear_to_srgb

        height, width = photo.shape[:2]
        factor = min(1.0, PERCEPTION_MAX_SIDE / max(height, width))
        if factor < 1.0:
            size = (max(1, round(width * factor)), max(1, round(height * factor)))
            photo = cv2.resize(photo, size, interpolation=cv2.INTER_AREA)  # NaN spreads to its pixel: black below
        srgb = np.clip(linear_to_srgb(np.clip(np.nan_to_num(photo, nan=0.0, posinf=0.0, neginf=0.0), 0.0, 1.0)), 0.0, 1.0)
        return cls(srgb.astype(np.float32), (photo.shape[1] / width, photo.shape[0] / height))

    def to_photo_size(self, mask: np.ndarray, height: int, width: int) -> np.ndarray:
        """A (h, w) map of the view at the photo's (height, width), bilinear."""
        if mask.shape == (height, width):
            return mask
        return cv2.resize(mask.astype(np.float32), (width, height), interpolation=cv2.INTER_LINEAR)


class Models:
    """Network sessions, created on first use (only the stages a plan runs load theirs) and
    kept for every later item of the batch."""

    def __init__(self, threads: int):
        self.threads, self._sessions, self._lights = threads, {}, {}

    def light(self, env: np.ndarray):
        """The environment's sampling distribution, built once per map and kept (a batch or a
        turntable relights many times under the same or the same few maps)."""
        from relightcli.render.environment import EnvironmentLight

        key = id(env)
        if key not in self._lights:
            self._lights = {key: (env, EnvironmentLight(env))}  # keep one: maps are large
        return self._lights[key][1]

    def body_model(self):
        """The body model (relightcli.geometry.body_model), loaded on first use and kept."""
        if "body_model" not in self._sessions:
            from relightcli.geometry.body_model import BodyModel

            self._sessions["body_model"] = BodyModel.load()
        return self._sessions["body_model"]

    def has(self, name: str) -> bool:
        """Whether the models folder's manifest describes model `name`."""
        from relightcli.nets.manifest import load_manifest

        return name in load_manifest()

    def get(self, family: str):
        if family not in self._sessions:
            from relightcli.nets.delight import DelightNet
            from relightcli.nets.face_mesh import FaceDetector, FaceMesh
            from relightcli.nets.geometry import AONet, AOPriorNet, GeometryNet, GeometryPriorNet
            from relightcli.nets.pose import PersonDetector, PoseLandmarker
            from relightcli.nets.refine import BodyRefineNet, FaceRefineNet
            from relightcli.nets.selfie import SelfieSegmenter

            classes = {"geometry": GeometryNet, "geometry_prior": GeometryPriorNet, "ao": AONet,
                       "ao_prior": AOPriorNet, "delight": DelightNet,
                       "body_refine": BodyRefineNet, "face_refine": FaceRefineNet,
                       "person_detector": PersonDetector, "pose_landmarks": PoseLandmarker,
                       "face_detector": FaceDetector, "face_mesh": FaceMesh,
                       "selfie_segmentation": SelfieSegmenter}
            self._sessions[family] = classes[family](threads=self.threads)
        return self._sessions[family]


def stage_people(frame: Frame, options, models: Models) -> None:
    """Every person in the photo: BlazePose's person detector, then per person the landmark net
    (33 keypoints, 33 metric world landmarks, a segmentation) in a crop turned upright
    (relightcli.nets.pose), on the photo as sRGB. When the detector finds nobody and the input
    brings a mask, the landmark net looks in the mask's box (find_person_in_mask: BlazePose's
    detector misses some people its landmark net sees, e.g. T-posed synthetic figures, or a
    visor that hides the face). Without a mask it looks at the whole photo instead
    (find_person_in_photo): the detector missed the T-posed figures of 25 of the 170 synthetic
    validation photos (data/evalval512, data/evalval256), 22 are found so (the net's mask
    against the true one: IoU 0.67-0.95, mean 0.87), and so is Aldrin behind his gold visor.
    When no body is found but the face detector and face mesh find a face in the whole photo (a
    close portrait: head and shoulders), the selfie segmentation gives that person's mask. The
    report lists who was found, who the landmark net turned down, and the fallbacks that ran."""
    from relightcli.nets.face_mesh import find_face
    from relightcli.nets.pose import WHOLE_PHOTO_PRESENCE, find_people, find_person_in_mask, find_person_in_photo

    frame.view = frame.view or PerceptionView.of(frame.image)
    srgb, scale = frame.view.image, frame.view.scale
    people = find_people(srgb, models.get("person_detector"), models.get("pose_landmarks"))
    frame.people = [p for p in people if p.found]
    frame.notes["people"] = {"found": [p.summary(scale) for p in frame.people],
                             "turned_down": [p.summary(scale) for p in people if not p.found]}
    if frame.people:
        return
    if frame.mask is not None:  # the mask says where the person is: the landmark net there
        height, width = srgb.shape[:2]
        mask = cv2.resize(frame.mask.astype(np.float32), (width, height), interpolation=cv2.INTER_AREA)
        person = find_person_in_mask(srgb, mask, models.get("pose_landmarks"))
        if person is not None and person.found:
            frame.people = [person]
            frame.notes["people"]["found"] = [person.summary(scale)]
            frame.notes["people"]["from_mask"] = "no person detected: landmarks in the mask's box"
        else:  # the portrait's selfie mask would only stand in for the input's
            frame.notes["people"]["portrait"] = "no body found; the input brings the mask"
        return
    person = find_person_in_photo(srgb, models.get("pose_landmarks"))
    if person.pose.presence >= WHOLE_PHOTO_PRESENCE:
        frame.people = [person]
        frame.notes["people"]["found"] = [person.summary(scale)]
        frame.notes["people"]["whole_photo"] = "no person detected: landmarks in the whole photo"
        return
    frame.notes["people"]["whole_photo"] = f"no person detected; presence {person.pose.presence:.3f} in the whole photo"
    face, why = find_face(srgb, None, models.get("face_detector"), models.get("face_mesh"))
    if face is None:
        frame.notes["people"]["portrait"] = f"no body and no face: {why}"
        return
    frame.portrait_mask = models.get("selfie_segmentation").segment(srgb)
    frame.notes["people"]["portrait"] = {"face": face.summary(scale), "mask": "selfie segmentation"}


def stage_mask(frame: Frame, options, models: Models) -> None:
    """The person mask when the input brought none: the union of the people's segmentations
    (soft, the hair's edge included), or a portrait's selfie segmentation, its edges pulled to
    the photo's by a guided filter in the crop around everyone (compose.snap_mask). No person:
    the item fails, nothing is written.

    Measured (python bench/mask_iou.py, mean / worst IoU with the true mask): on the 17 of 20
    validation scenes where a person is found, 0.938 / 0.826 raw, 0.942 / 0.830 with the
    filter (radius 2 px at 512, eps 0.01: chosen there among radii 2-16 and eps 1e-4..1e-2;
    GrabCut in a 3-7 px band scored about the same at +170 ms, with a hard edge); on the 20 test
    scenes 0.962 / 0.926, where the synthetic-trained mask net + GrabCut it replaces scored
    0.903 / 0.758 (COCO skier 0.918 against 0.798)."""
    if frame.mask is not None:
        return
    if frame.people:
        union = np.max([p.pose.mask for p in frame.people], axis=0)
        count = len(frame.people)
        source = f"pose segmentation of {count} {'person' if count == 1 else 'people'}"
    elif frame.portrait_mask is not None and (frame.portrait_mask > 0.5).any():
        union, source = frame.portrait_mask, "selfie segmentation (a face, no body found)"
    else:
        raise RelightError("no person found in the photo",
                           fix="pass --mask FILE to say where the person is (white: person)")
    frame.mask = frame.view.to_photo_size(union, *frame.image.shape[:2]).copy()
    box = compose.person_crop_box(frame.mask, options.resolution)
    snapped = compose.snap_mask(compose.crop_square(frame.image, box), compose.crop_square(frame.mask, box))
    compose.replace_in_box(frame.mask, snapped, box)
    frame.mask = np.clip(frame.mask, 0.0, 1.0)
    frame.mask_predicted = True
    frame.notes["mask"] = {"source": source, "edges": "guided filter"}


def person_support(frame: Frame) -> np.ndarray:
    """(R, R, 1) float32: 1 where the crop mask is > 0, else 0. Albedo and shading are straight
    (not multiplied by the mask) on the person's pixels; the photo's mask is applied once, as
    alpha: in the composite (compose.composite) and on the layer files (over_black), which is
    what `relight eval` scores. Multiplied in, a predicted mask (a segmentation probability,
    below 1 on 48% of the pixels inside its 0.5 contour on the validation scenes at 512)
    darkened every layer, the relit person by its square, and the composite by it once more.
    Measured (`relight eval data/evalval256 --resolution 256 [--use-gt-mask]`, relit / albedo /
    shading PSNR, then SSIM), with the albedo outside the 0.5 contour taken from inside
    (stage_delight): own mask, on the 128 scenes where a person was found before, 17.03 / 17.66
    / 17.03 -> 17.61 / 17.66 / 17.04 dB, SSIM 0.625 / 0.591 / 0.582 -> 0.617 / 0.634 / 0.593;
    true mask 18.30 / 18.87 / 19.38 -> 18.35 / 18.95 / 19.43 dB, SSIM 0.710 / 0.716 / 0.713 ->
    0.732 / 0.773 / 0.761. The 20 at 512: own mask 16.93 / 16.89 / 18.61 -> 17.50 / 16.96 /
    18.62 (17 scenes), true mask 17.67 / 17.12 / 20.76 -> 17.76 / 17.19 / 20.82."""
    return (frame.crop_mask > 0)[..., None].astype(np.float32)


def stage_crop(frame: Frame, options, models: Models) -> None:
    frame.box = compose.person_crop_box(frame.mask, options.resolution)
    frame.crop = compose.crop_square(frame.image, frame.box)
    frame.crop_mask = np.clip(compose.crop_square(frame.mask, frame.box), 0.0, 1.0)
    frame.notes["crop"] = {"box": [frame.box.x0, frame.box.y0, frame.box.size], "resolution": options.resolution}


def person_keypoints_in_crop(person, view_scale, box: compose.CropBox) -> np.ndarray:
    """(33, 2) crop pixel indices (col, row) of a person's pose landmarks (view pixels):
    view -> photo (continuous) -> the working crop."""
    photo = person.pose.landmarks[:, :2] / np.asarray(view_scale, np.float64)
    return (photo - (box.x0, box.y0)) / box.scale - 0.5


def stage_body(frame: Frame, options, models: Models) -> None:
    """The body model fitted to each person found (relightcli.geometry.body_fit): their 33
    keypoints in the crop, BlazePose's visibility and world landmarks, the crop mask as the
    silhouette. frame.bodies keeps the fits (vertices in the crop's world frame);
    frame.notes["body"] per person the seconds, RMS keypoint residual (crop pixels), whether
    the fit converged (or why not) and, if it did, whether the fitted body faces the camera
    (`seen_from` front or behind: BlazePose takes some front-facing people for back views and
    the other way round, README: the body)."""
    import time

    model = models.body_model()
    silhouette = (frame.crop_mask > 0.5).astype(np.float32)
    fits, people = [], []
    for person in frame.people:
        start = time.perf_counter()
        fit = _fit_on_one_opencv_thread(model, person_keypoints_in_crop(person, frame.view.scale, frame.box),
                                        person.pose.landmarks[:, 3], person.pose.world, silhouette)
        fits.append(fit)
        residual = float(fit.residual_px)
        note = {"seconds": round(time.perf_counter() - start, 4),
                "residual_px": round(residual, 3) if np.isfinite(residual) else None,
                "converged": bool(fit.converged), "reason": fit.reason}
        if fit.converged:
            note["seen_from"] = "front" if fit.faces_camera else "behind"
        people.append(note)
    frame.bodies = fits
    frame.notes["body"] = {"people": people}


def _fit_on_one_opencv_thread(model, keypoints, visibility, world, silhouette):
    """fit_body with OpenCV on one thread and without Intel IPP: the silhouette term's OpenCV
    calls round differently with another thread count (1e-8 on the vertices), and with IPP
    its precise distance transform differed from one process to the next on the same input
    (two or three outcomes in six runs, 1e-8 on the fit's residual, a half-float step in a few
    shading pixels); an item's outputs must not depend on either (tests/test_determinism.py)."""
    from relightcli.geometry.body_fit import fit_body

    threads, ipp = cv2.getNumThreads(), cv2.ipp.useIPP()
    cv2.setNumThreads(1)
    cv2.ipp.setUseIPP(False)
    try:
        return fit_body(model, keypoints, visibility, world, silhouette)
    finally:
        cv2.setNumThreads(threads)
        cv2.ipp.setUseIPP(ipp)


def net_side(net, working: int) -> int:
    """The side a net runs at: the crop side it was trained on when that is smaller than the
    working resolution, else the working resolution. The shipped nets learned on 256-pixel crops;
    at a 512 crop they run at 256 and their maps are enlarged (the photo's own detail comes back
    through the ratio albedo and the full-resolution ray tracing). Measured on the 20 eval scenes
    at 512 (true mask, no refinement) against running them at 512: shading 17.45 vs 16.79 dB,
    relit 16.69 vs 16.79, albedo 16.64 vs 16.67, and a third of the nets' time."""
    trained = getattr(net, "trained_resolution", None)
    return min(working, trained) if trained else working


def resample(image: np.ndarray, side: int) -> np.ndarray:
    """An (R, R[, C]) map resampled to (side, side[, C]): area-averaged when shrinking,
    bilinear when enlarging; the same array when the side is already right."""
    if image.shape[0] == side:
        return image
    interpolation = cv2.INTER_AREA if side < image.shape[0] else cv2.INTER_LINEAR
    out = cv2.resize(np.asarray(image, np.float32), (side, side), interpolation=interpolation)
    return out.reshape((side, side) + image.shape[2:])


def unit(normals: np.ndarray) -> np.ndarray:
    """(..., 3) vectors scaled to length 1 (zero vectors stay zero), float32."""
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    return (normals / np.where(length > 0, length, 1.0)).astype(np.float32)


# The nets whose maps are averaged with their maps of the mirrored crop (mirrored back): two
# runs each instead of one (0.1-0.2 s more at 512 on a slow day). Chosen on the 150
# validation scenes at 256 (`relight eval data/evalval256 --resolution 256 --use-gt-mask`,
# relit / albedo / shading dB, normals): none 18.13 / 18.80 / 19.17, 22.70 deg; the geometry
# net 18.14 / 18.81 / 19.22, 22.41; both 18.15 / 18.83 / 19.22, 22.41 (normals better in 116
# of 150 scenes, shading in 96). Test (data/eval512): relit / albedo 18.82 / 19.74 -> 18.90 /
# 19.88, normals 19.9 -> 19.7 deg.
MIRROR_AVERAGED = ("geometry", "delight")


def mirror(image: np.ndarray, vectors: tuple = ()) -> np.ndarray:
    """(H, W[, C]) image mirrored left-right (x -> -x in the camera frame), with the x component
    negated of each 3-vector whose first channel is in `vectors` (0 for a normal map). A
    lat-long light mirrors the same way, its texel columns reversed (DESIGN.md's map: u = 1/2 +
    atan2(x, -z) / 2 pi, so x -> -x takes u to 1 - u)."""
    out = np.ascontiguousarray(image[:, ::-1])
    for channel in vectors:
        out[..., channel] = -out[..., channel]
    return out


def average_geometry(g, mirrored):
    """The mean of a geometry net's GeometryMaps of a crop and `mirrored`, its maps of the
    mirrored crop: mirrored back, normals renormalised."""
    return replace(g, front_normal=unit(g.front_normal + mirror(mirrored.front_normal, (0,))),
                   back_normal=unit(g.back_normal + mirror(mirrored.back_normal, (0,))),
                   front_depth=0.5 * (g.front_depth + mirror(mirrored.front_depth)),
                   back_depth=0.5 * (g.back_depth + mirror(mirrored.back_depth)),
                   mask=0.5 * (g.mask + mirror(mirrored.mask)))


# The front normals are smoothed inside the person by a Gaussian of this share of the crop's
# side (6 px at 512) before the outline bends them: the nets' maps carry pixel noise that the
# shading inherits. Chosen on validation (true mask; relit / albedo / shading dB, normals'
# degrees; sigma at 512, half of it in pixels at 256):
#           20 at 512                      120 at 256 in training poses
#   none    18.144 / 17.354 / 21.625, 16.27  17.281 / 17.939 / 18.083, 25.44
#   2 px    18.149 / 17.358 / 21.654, 16.22  -
#   4 px    18.152 / 17.359 / 21.686, 16.20  17.301 / 17.951 / 18.108, 25.31
#   6 px    18.156 / 17.361 / 21.704, 16.24  17.304 / 17.951 / 18.112, 25.29
#   8 px    18.157 / 17.365 / 21.706, 16.34  17.301 / 17.944 / 18.109, 25.36
# 150 at 256: none 18.132 / 18.507 / 20.032, 20.31; 4 px 18.150 / 18.523 / 20.056, 20.22; 6 px
# 18.149 / 18.521 / 20.046, 20.25.
NORMAL_SIGMA = 6 / 512


def stage_geometry(frame: Frame, options, models: Models) -> None:
    """Front/back normals and depth of the person in the crop. With a converged body fit
    (stage_body_maps) the prior net refines the fitted bodies' maps into the clothed person's
    (relightcli.nets.geometry.GeometryPriorNet); without one, the net from the image alone.
    Both run on the mirrored crop too (MIRROR_AVERAGED). The note says which ran and why. The
    front normals are then smoothed inside the mask and bent toward the silhouette's near its
    outline."""
    from relightcli.geometry.silhouette import blend_silhouette_normals
    from relightcli.geometry.smoothing import smooth_normals
    from relightcli.nets.geometry import prior_channels

    maps = frame.body_maps
    with_prior = maps is not None and models.has("geometry_prior")
    net = models.get("geometry_prior" if with_prior else "geometry")
    side = net_side(net, options.resolution)
    crop = resample(frame.crop, side)
    prior = (prior_channels(maps.mask, maps.front_normal, maps.back_normal, maps.front_depth,
                            maps.back_depth, side),) if with_prior else ()
    g = net.predict(crop, *prior)
    if "geometry" in MIRROR_AVERAGED:  # the prior's front and back normals mirror too
        g = average_geometry(g, net.predict(mirror(crop), *(mirror(p, (0, 3)) for p in prior)))
    if with_prior:
        frame.notes["geometry"] = {"net": "geometry_prior", "prior": "fitted bodies"}
    else:
        why = "no geometry_prior model" if maps is not None else "no converged body fit"
        frame.notes["geometry"] = {"net": "geometry", "prior": f"none: {why}"}
    if side != options.resolution:
        size = options.resolution
        g = replace(g, front_normal=unit(resample(g.front_normal, size)), back_normal=unit(resample(g.back_normal, size)),
                    front_depth=resample(g.front_depth, size), back_depth=resample(g.back_depth, size),
                    mask=resample(g.mask, size))
    # The nets' normals are smoothed inside the person (NORMAL_SIGMA), then, near the outline,
    # where the surface turns away from the camera, pulled toward the silhouette's
    # (relightcli.geometry.silhouette)
    inside = frame.crop_mask > 0.5
    front = smooth_normals(g.front_normal, inside, NORMAL_SIGMA * options.resolution)
    beyond = compose.outside_photo(frame.box, *frame.image.shape[:2])
    g = replace(g, front_normal=blend_silhouette_normals(front, inside, beyond))
    frame.geometry = g
    frame.normal = g.front_normal * (frame.crop_mask[..., None] > 0.5)


# Where a body fit converged and the AO prior net is not in the models folder, the AO layer
# blends the net's map with the fitted bodies' own AO, ray-traced (BODY_AO_SPP samples at every
# other pixel of every other row, then upsampled: AO is smooth), the bodies' share
# BODY_AO_WEIGHT (the AO prior net, shipped, beats the blend: models/MODEL_CARD.md). AO MAE
# over the person (python bench/bench_ao.py DATA --split S --weights 0,0.5,0.7,1): the 20
# validation renders at 512 (16 fitted) 0.0642 (net), 0.0564, 0.0554, 0.0566 (bodies alone):
# 0.7 chosen; the 20 test renders (20 fitted) 0.0844 -> 0.0833. The refinement net keeps
# reading the net's map, which it was trained on: fed the blend it lost 0.08 dB of shading on
# validation (true mask, relit / shading 16.63 / 19.80 -> 16.58 / 19.72).
BODY_AO_WEIGHT = 0.7
BODY_AO_SPP = 32


def stage_ao(frame: Frame, options, models: Models) -> None:
    """Ambient occlusion in [0, 1]: the AO net's map from the crop (frame.ao_net, the
    refinement's input, the map it was trained on). When the AO layer is asked for and a body
    fit converged, the layer (frame.ao) uses the fitted bodies' ray-traced AO (body_ao): the AO
    prior net's map from the crop, the bodies' maps and that AO (relightcli.nets.geometry.
    AOPriorNet) when the models folder has it, else the AO net's map blended with the bodies'
    AO over those people."""
    from relightcli.nets.geometry import ao_prior_channels, prior_channels

    net = models.get("ao")
    side = net_side(net, options.resolution)
    frame.ao_net = resample(net.predict(resample(frame.crop, side)), options.resolution)
    frame.ao = frame.ao_net
    if "ao" not in options.outputs or frame.body_scene is None:
        return
    usable = body_shading_pixels(frame)
    if models.has("ao_prior"):
        prior_net = models.get("ao_prior")
        side = net_side(prior_net, options.resolution)
        # traced at every other pixel of the net's side, as the data factory traced it
        body = body_ao(frame, options.seed, step=max(1, 2 * options.resolution // side))
        if body is not None:
            maps = frame.body_maps
            prior = ao_prior_channels(prior_channels(maps.mask, maps.front_normal, maps.back_normal,
                                                     maps.front_depth, maps.back_depth, side), body * usable)
            frame.ao = resample(prior_net.predict(resample(frame.crop, side), prior), options.resolution)
            frame.notes["ao"] = {"net": "ao_prior"}
        return
    body = body_ao(frame, options.seed)
    if body is not None:
        weight = np.float32(BODY_AO_WEIGHT) * usable
        frame.ao = ((1.0 - weight) * frame.ao_net + weight * body).astype(np.float32)
        frame.notes["ao"] = {"net": "ao", "body_weight": BODY_AO_WEIGHT}


def body_ao(frame: Frame, seed: int, step: int = 2) -> np.ndarray | None:
    """(R, R) float32: the fitted bodies' ambient occlusion (integrator.ambient_occlusion,
    cosine-weighted, unlimited distance), traced at every `step`-th pixel of every `step`-th
    row and upsampled (AO is smooth); person pixels the bodies do not cover take their nearest
    covered pixel's. None when the bodies cover none of the traced pixels."""
    from dataclasses import replace

    from relightcli.render.integrator import ambient_occlusion

    hits = frame.body_hits
    grid = np.zeros_like(hits.mask)
    grid[::step, ::step] = True
    if not (hits.mask & grid).any():
        return None
    traced = ambient_occlusion(frame.body_scene, replace(hits, mask=hits.mask & grid), spp=BODY_AO_SPP, seed=seed)
    coarse = fill_uncovered(traced.mean[::step, ::step, 0], traced.mask[::step, ::step],
                            np.ones(grid[::step, ::step].shape, bool))
    side = frame.crop_mask.shape[0]
    return np.clip(cv2.resize(coarse, (side, side), interpolation=cv2.INTER_LINEAR), 0.0, 1.0)


def stage_delight(frame: Frame, options, models: Models) -> None:
    """De-lighting: the input lighting (16x32) and an albedo. The net gives a light and an
    albedo from [crop, normals]. `--albedo solve` (the default) solves the light again by
    inverse rendering on the mesh (solve_input_light) and divides the crop by the ray-traced
    shading of that light (cast shadows and occlusion leave the albedo with it); `--albedo
    ratio` divides by the SH-9 irradiance of the net's light at the predicted normals; both
    blend into the net's albedo where that shading is too dark to divide by
    (compose.ratio_albedo), take the net's albedo level (one gain) and, on the outline, the
    mean of its albedo and the nearest pixel's inside (compose.anchor_albedo). `--albedo net`
    keeps the net's (the paper's).

    Measured (`relight eval DATA [--albedo ratio]`, relit / albedo PSNR, ratio -> solve): test
    scenes (data/eval512) 18.67 / 19.47 -> 18.82 / 19.74, true mask 19.04 / 19.84 -> 19.28 /
    20.17; 150 validation scenes at 256, true mask, 17.70 / 18.27 -> 18.13 / 18.80; 20 at 512
    16.77 / 16.14 -> 17.38 / 16.94; for ~0.45 s more a photo at 512. Dividing by the traced
    shading of the *true* light scores 19.67 / 19.95 (validation, 512, no refinement): the
    light's shape and level, not the division, is what is left. The input shading is traced
    with the target's effort: capped at 8 samples per pixel it lost 0.04 / 0.09 dB on
    validation for ~25% less time per image. Its rays are traced on a coarser grid instead
    (input_shadow_step): at 512 every fourth pixel scored as every second (validation, true
    mask, relit / albedo 17.800 / 17.190 -> 17.800 / 17.196; every eighth 17.794 / 17.196) with
    a quarter of the rays (~55k instead of ~220k a photo); at 256 every fourth lost 0.007 /
    0.004 dB on the 150 validation scenes, so 256 keeps every second."""
    from relightcli.render.environment import EnvironmentLight
    from relightcli.render.sh import project_sh, sh_irradiance_shading

    net = models.get("delight")
    side = net_side(net, options.resolution)
    image, normal = resample(frame.crop, side), unit(resample(frame.normal, side))
    result = net.predict(image, normal)
    if "delight" in MIRROR_AVERAGED:
        mirrored = net.predict(mirror(image), mirror(normal, (0,)))
        result = replace(result, albedo=0.5 * (result.albedo + mirror(mirrored.albedo)),
                         light=0.5 * (result.light + mirror(mirrored.light)))
    albedo = resample(result.albedo, options.resolution)
    frame.light = result.light
    if options.albedo == "solve":
        frame.light = solve_input_light(frame, albedo, options, models)
        input_shading, note = trace_shading(frame, EnvironmentLight(frame.light), options,
                                            input_shadow_step(options))
        frame.notes["delight"]["input_shading"] = {key: note[key] for key in ("shadow_step", "rays", "rel_error")}
    elif options.albedo == "ratio":
        input_shading = sh_irradiance_shading(project_sh(result.light, 2), frame.normal)
    if options.albedo != "net":
        ratio = compose.ratio_albedo(frame.crop, input_shading, albedo, frame.crop_mask)
        albedo = compose.anchor_albedo(ratio, albedo, frame.crop_mask)
    # Outside the mask's 0.5 contour a pixel mixes in the background (the photo there is mostly
    # not the person): it takes the albedo of the nearest pixel inside, so the soft edge, now
    # straight, does not carry the background's colour into the relit person
    inside = frame.crop_mask > 0.5
    albedo = fill_uncovered(albedo, inside, frame.crop_mask > 0) if inside.any() else albedo
    frame.albedo = albedo * person_support(frame)


def input_shadow_step(options) -> int:
    """The pixel step of the rays for the solved input light's shading: with `--shadows half`
    a grid of about INPUT_SHADOW_GRID pixels across the crop (never finer than the target's
    step), with `full` every pixel."""
    step = SHADOW_STEP[options.shadows]
    return max(step, options.resolution // INPUT_SHADOW_GRID) if options.shadows == "half" else step


# The light solve samples about this many of the person's pixels (a regular grid), with this
# many cosine-weighted visibility rays each. 2000 x 32 scored as 4000 x 64 on 150 validation
# scenes at 256 (`--albedo solve --use-gt-mask`, relit / albedo 18.13 / 18.80 vs 18.12 / 18.80)
# at a quarter of the rays: the de-lighting stage 0.85 -> 0.58 s at 512.
SOLVE_PIXELS = 2000
SOLVE_SAMPLES = 32
# A pixel whose photo reaches this (linear, any channel) is clipped: left out of the solve
SOLVE_CLIPPED = 0.95
# Albedo below this (the net's, channel mean) says little about the light: left out
SOLVE_DARK_ALBEDO = 0.03


def solve_input_light(frame: Frame, net_albedo: np.ndarray, options, models: Models) -> np.ndarray:
    """The input light by inverse rendering (relightcli.render.inverse): the light transport
    of a grid of the person's pixels on the same surfaces the target shading is traced on
    (mesh_transport), the net's albedo there as the albedo, the net's light as the prior.
    Pixels on the 2-px outline, clipped or with a dark albedo are left out. Returns the
    (16, 32, 3) light; frame.notes["delight"] gets the solve's residual and sizes."""
    import time

    from relightcli.render.inverse import solve_light

    start = time.perf_counter()
    ensure_scenes(frame, options, models)
    pixels = solve_pixels(frame)
    transport = mesh_transport(frame, pixels, options.seed)
    photo = frame.crop.reshape(-1, 3)[pixels].astype(np.float64)
    albedo = net_albedo.reshape(-1, 3)[pixels].astype(np.float64)
    usable = (photo.max(axis=1) < SOLVE_CLIPPED) & (albedo.mean(axis=1) >= SOLVE_DARK_ALBEDO)
    solve = solve_light(transport, photo, albedo, usable.astype(np.float64), frame.light)
    light = grey_light(solve.light)
    net_level, level = (float(np.mean(x @ compose.LUMINANCE)) for x in (frame.light, light))
    frame.notes["delight"] = {
        "light": "inverse rendering" if solve.pixels else "no usable pixel: the net's light, made grey",
        "pixels": solve.pixels, "residual": [round(r, 4) for r in solve.residual],
        "level_vs_net": round(level / net_level, 4) if net_level > 0 else None,
        "seconds": round(time.perf_counter() - start, 4)}
    return light


def grey_light(light: np.ndarray) -> np.ndarray:
    """The solved light (16, 32, 3) made colourless, its shape and luminance kept: each channel
    scaled so that the three have the same mean over the texels. The solve divides the photo
    by the net's albedo, which greys strongly coloured clothes, so their colour went into the
    solved light and out of the albedo; a white-balanced photo's light is about grey. Measured
    (`relight eval DATA --use-gt-mask`, relit / albedo dB): the solve's own colour against the
    de-lighting net's light's (the earlier choice), 150 validation scenes at 256 18.05 / 18.73 ->
    18.12 / 18.80, test (data/eval512) 18.06 / 18.61 -> 19.24 / 20.18; the net's colour against
    grey, 150 at 256 (seed 7) 17.952 / 18.303 -> 17.973 / 18.335 (albedo better in 114), 20 at
    512 17.976 / 17.213 -> 18.013 / 17.271 (16 of 20), 120 in the training split's poses 17.112
    / 17.761 -> 17.110 / 17.760. The net's colour is further from the true input light's mean
    colour than grey is (RMS of the log red/green and blue/green ratios' error 0.203 / 0.225 /
    0.265 against 0.186 / 0.207 / 0.262 on those three sets). A light with a black channel is
    kept."""
    have = light.reshape(-1, 3).mean(axis=0)
    if not (have > 0).all():
        return light
    gain = float(have @ compose.LUMINANCE) / have
    return (light * gain).astype(np.float32)


def solve_pixels(frame: Frame) -> np.ndarray:
    """Flat crop indices of a regular grid (about SOLVE_PIXELS) over the person's pixels that
    every traced surface covers, 2 px inside the outline (where the photo mixes in the
    background)."""
    inside = frame.crop_mask > 0.5
    core = cv2.erode(inside.astype(np.uint8), np.ones((5, 5), np.uint8), borderValue=0) > 0
    core &= frame.hits.mask
    if frame.body_hits is not None:
        core &= frame.body_hits.mask | ~body_shading_pixels(frame)
    stride = max(1, int(np.sqrt(core.sum() / SOLVE_PIXELS)))
    grid = np.zeros_like(core)
    grid[::stride, ::stride] = True
    return np.flatnonzero(core & grid)


def mesh_transport(frame: Frame, pixels: np.ndarray, seed: int):
    """The light transport (relightcli.render.inverse.Transport) of `pixels`, weighted over the
    reconstruction and the fitted bodies as the target shading is (trace_shading)."""
    from relightcli.render.inverse import light_transport

    transport = light_transport(frame.scene, frame.hits, pixels, samples=SOLVE_SAMPLES, seed=seed, lift=SHADOW_LIFT)
    if frame.body_scene is None:
        return transport
    body = light_transport(frame.body_scene, frame.body_hits, pixels, samples=SOLVE_SAMPLES, seed=seed,
                           lift=SHADOW_LIFT)
    weight = body_weight(frame).reshape(-1)[pixels][:, None]
    transport.matrix = ((1.0 - weight) * transport.matrix + weight * body.matrix).astype(np.float32)
    return transport


def stage_sh_shading(frame: Frame, options, models: Models) -> None:
    """RH / SFHR-style baselines: SH-9 or SH-25 irradiance of the target environment at the
    predicted normals (no visibility)."""
    from relightcli.render.sh import project_sh, sh_irradiance_shading

    order = 2 if options.method == "sh9" else 4
    coefficients = project_sh(frame.env, order)
    shading = sh_irradiance_shading(coefficients, frame.normal)
    frame.shading = np.maximum(shading, 0.0) * person_support(frame)


# The reconstruction's mesh is built on every MESH_STEP-th pixel of the crop (its maps come
# from nets that see 256 pixels: a 512 crop's maps are enlarged, a finer grid adds triangles,
# not detail) and smoothed MESH_SMOOTHING_STEPS cotangent steps (the paper's 10 on its grid).
# Chosen on validation (`relight eval data/evalval512 --use-gt-mask`, relit / shading dB):
# every pixel, 10 steps 16.68 / 20.08 (the earlier default); every second pixel, 3 / 10 / 20 /
# 40 / 80 steps 16.65 / 19.98, 16.76 / 20.28, 16.81 / 20.43, 16.82 / 20.43, 16.80 / 20.29;
# every pixel, 40 steps 16.82 / 20.47; without the true mask 16.15 / 18.08 -> 16.25 / 18.29.
# Test (data/eval512): true mask 18.13 / 18.88 -> 18.06 / 19.00, own mask 17.91 / 17.83 ->
# 17.89 / 18.00. The stage 0.08 -> 0.02 s at 512, the ray tracer's scene a quarter the size.
# Once shadow rays were lifted off the triangles (SHADOW_LIFT), less smoothing paid, true
# mask, relit / albedo / shading: 150 validation scenes at 256, 10 steps 18.27 / 18.86 / 19.32
# against 20 steps 18.20 / 18.84 / 19.21 (better in 118, 110, 122 of 150); the 20 at 512, 10 /
# 20 / 40 steps 17.67 / 17.12 / 20.75, 17.67 / 17.13 / 20.70, 17.64 / 17.12 / 20.61; and 5
# steps against 10: 150 at 256 18.30 / 18.87 / 19.38 (shading better in 112 of 150), 20 at 512
# 17.67 / 17.12 / 20.76.
MESH_STEP, MESH_SMOOTHING_STEPS = 2, 5


def stage_reconstruct(frame: Frame, options, models: Models) -> None:
    """Double-sided depth on a grid of every MESH_STEP-th crop pixel (shrink_inside), smoothed
    inside the person (see smoothing.DEPTH_SIGMA) -> watertight mesh in the crop camera frame,
    then MESH_SMOOTHING_STEPS steps of cotangent Laplacian smoothing."""
    from relightcli.geometry.mesh import reconstruct_mesh
    from relightcli.geometry.smoothing import DEPTH_SIGMA, smooth_depth, smooth_mesh

    g = frame.geometry
    side = max(frame.crop_mask.shape[0] // MESH_STEP, 2)
    mask = shrink(frame.crop_mask, side)
    sigma = DEPTH_SIGMA * side
    front = smooth_depth(shrink_inside(g.front_depth, frame.crop_mask, side), mask, sigma)
    back = np.minimum(smooth_depth(shrink_inside(g.back_depth, frame.crop_mask, side), mask, sigma), front)
    mesh = reconstruct_mesh(mask, front, back, compose.CROP_RECT)  # the back never lies in front
    frame.mesh = smooth_mesh(mesh, steps=MESH_SMOOTHING_STEPS)
    frame.notes["reconstruct"] = {"vertices": int(len(frame.mesh.vertices)), "faces": int(len(frame.mesh.faces))}


def shrink(image: np.ndarray, side: int) -> np.ndarray:
    """(side, side, ...) float32 area average of a square map (R, R, ...)."""
    import cv2

    return cv2.resize(np.ascontiguousarray(image, np.float32), (side, side), interpolation=cv2.INTER_AREA)


def shrink_inside(values: np.ndarray, mask: np.ndarray, side: int) -> np.ndarray:
    """(side, side) float32 area average of a square map (R, R) over the soft person mask
    (R, R): each coarse pixel the mean of its fine pixels weighted by the mask, so depths
    outside the person do not leak into its outline (0 where the mask is 0)."""
    weight = np.asarray(mask, np.float32)
    total, coverage = shrink(np.asarray(values, np.float32) * weight, side), shrink(weight, side)
    return np.where(coverage > 0, total / np.where(coverage > 0, coverage, 1.0), 0.0).astype(np.float32)


def build_scene(frame: Frame, options) -> None:
    """The Embree scene and the camera's primary hits: built once per photo, whatever the
    number of lightings (a turntable re-lights the same scene).

    The hits are shaded with the normal net's normals where they face the mesh's side: the
    mesh (from the depth maps, smoothed) decides what is occluded, the net's normals the
    cosine term. Measured on the 20 eval scenes (true mask, no refinement): shading 16.3 ->
    17.0 dB, relit 14.7 -> 15.0 dB against the mesh's own normals."""
    from relightcli.render.camera import render_pixel_geometry
    from relightcli.render.scene import Scene

    # One tracing process: the camera's rays take ~50 ms on one core, and the integrator
    # samples on its own forked workers; a tracing pool would spawn a process per photo
    # Area-weighted vertex normals of our own (trimesh's take ~4x longer at 512)
    frame.scene = Scene(frame.mesh.vertices, frame.mesh.faces, threads=1)
    # Only the person's pixels: the shading is multiplied by the crop mask, so nothing else is shaded
    hits = render_pixel_geometry(frame.scene, compose.CROP_RECT, (options.resolution,) * 2,
                                 where=frame.crop_mask > 0)
    frame.hits = hits.with_shading_normals(frame.geometry.front_normal, frame.crop_mask > 0.5)
    frame.notes.setdefault("scene_builds", 0)
    frame.notes["scene_builds"] += 1


# The fitted bodies' share of the coarse shading where a fit converged (stage_raytrace): 0.5
# chosen with the image-alone geometry net, 0.3 once the prior net shaped the reconstruction
# (validation, true mask, shading / relit: 0.5 19.46 / 16.52, 0.3 19.65 / 16.54, 0 18.83 / 16.13;
# python bench/bench_geometry_prior.py data/evalval512 --use-gt-mask --body-weight W), 0.2 once
# the reconstruction's normals took the outline's (relightcli.geometry.silhouette): relit /
# albedo / shading, 150 validation scenes at 256 17.917 / 18.292 / 19.961 -> 17.952 / 18.303 /
# 20.032 (relit better in 89 of 150), 20 at 512 17.967 / 17.211 / 21.469 -> 17.976 / 17.213 /
# 21.623 (0.4: 17.924 / 17.199 / 21.209)
BODY_SHADING_WEIGHT = 0.2


def stage_body_maps(frame: Frame, options, models: Models) -> None:
    """The prior maps of every converged body fit (relightcli.geometry.body_maps): front and
    back depth and normals at the person's pixels (crop mask > 0), traced once per photo in the
    Embree scene of those bodies (kept for the ray tracer, closed by the pipeline); body_hits:
    the front hits, which the ray tracer shades with the body's own normals. Nothing when no
    fit converged (the note says why). The person's pixels only: at 512 on the skier example the
    maps take 0.053 s of CPU (0.076 over the whole crop under the bodies' bounds; the ray
    tracer's own front trace of the bodies, which they replace, took 0.038)."""
    from relightcli.geometry.body_maps import bodies_scene, render_body_maps

    fitted = [fit.vertices for fit in frame.bodies if fit.converged]
    if not fitted:
        frame.notes["body_maps"] = {"skipped": "no converged body fit"}
        return
    frame.body_scene = bodies_scene(fitted, models.body_model().triangles)
    frame.body_maps = render_body_maps(frame.body_scene, options.resolution, where=frame.crop_mask > 0)
    frame.body_hits = frame.body_maps.front
    person = frame.crop_mask > 0.5
    frame.notes["body_maps"] = {"bodies": len(fitted),
                                "person_pixels_covered": round(float(frame.body_maps.mask[person].mean()), 4)
                                if person.any() else 0.0}


def body_shading_pixels(frame: Frame) -> np.ndarray:
    """(R, R) bool: the crop pixels where the fitted bodies' shading is used: all but those of
    a person whose fit did not converge (their pose segmentation), who keep the reconstruction's."""
    usable = np.ones(frame.crop_mask.shape, bool)
    height, width = frame.image.shape[:2]
    for person, fit in zip(frame.people, frame.bodies):
        if not fit.converged:
            mask = frame.view.to_photo_size(person.pose.mask, height, width)
            usable &= compose.crop_square(mask, frame.box) <= 0.5
    return usable


def _trace_note(result) -> dict:
    return {"spp_mean": float(result.passes[result.mask].mean()) if result.mask.any() else 0.0,
            "rays": result.rays, "seconds": round(result.seconds, 4), "strategy": result.strategy,
            "rel_error": result.median_relative_error(),
            "mrays_per_s": result.rays / max(result.seconds, 1e-9) / 1e6}


def stage_raytrace(frame: Frame, options, models: Models) -> None:
    """Coarse shading under the target environment, pixel-aligned with the crop: the
    reconstructed mesh ray-traced (build_scene), averaged (the bodies' share
    BODY_SHADING_WEIGHT) with the fitted naked bodies ray-traced (stage_body_maps) over the
    people whose body fit converged (the target error is the blend's, shared by the two
    renders in proportion to their weights: blend_targets). Person pixels a mesh does not
    cover (limbs thinner than two pixels on the reconstruction; clothes and hair around the naked body; the soft edge of the
    mask, where the smoothed mesh has shrunk) take the shading of the nearest covered pixel.

    Measured (issue 18): `relight eval DATA --method raytrace-norefine [--use-gt-mask]`, relit /
    albedo / shading PSNR; the weight chosen on data/evalval512 among 0, 0.3, 0.5, 0.7 and 1
    (shading 17.69, 19.25, 19.49, 19.19, 17.96 dB with the true mask):
    | scenes, mask             | reconstruction        | bodies alone          | mean (shipped)        |
    | val, true mask           | 15.92 / 16.19 / 17.69 | 15.89 / 16.19 / 17.96 | 16.57 / 16.19 / 19.49 |
    | val, own mask (17 found) | 15.14 / 16.06 / 15.10 | 15.28 / 16.06 / 15.71 | 15.80 / 16.06 / 16.55 |
    | test, true mask          | 17.81 / 18.70 / 17.40 | 17.37 / 18.70 / 17.17 | 18.06 / 18.70 / 18.62 |
    | test, own mask           | 17.19 / 18.45 / 15.85 | 16.88 / 18.45 / 15.93 | 17.48 / 18.45 / 16.89 |
    With the refinement net after it (`--method raytrace`, val, true mask): relit / shading
    16.68 / 19.63 against 15.97 / 17.92. One scene of reconstruction and bodies (primary hits
    on whichever is in front: val shading 17.57) or the body as a shadow caster behind the
    reconstruction's hits (15.87: it pokes through the clothes) lost: the two surfaces' errors
    are unlike, and the mean of their shadings beats either. So did one mesh with every surface
    (issue 18 step 4, bench/bench_fusion.py, true mask, shading val / test against 19.49 / 18.62
    shipped): ECON's screened Poisson (pymeshlab, depth 8) of the reconstruction and the bodies'
    parts neither camera sees 17.55 / 17.37 (3-6 s a photo, watertight 10/16 and 19/20), the
    union of both solids as one depth mesh 17.52 / 17.24, and either in the mean in place of the
    reconstruction 19.37 / 18.52 and 19.20 / 18.33; the mesh's cover of the person (96%, the
    rest filled from the nearest pixel) is not what limits it: smoothing it in depth only (98%)
    scored 19.46 on val. What Poisson did win, with the predicted mask (shading val 16.55 ->
    17.05, test 16.89 -> 17.43), came from covering the mask's soft edge (0 < crop mask <= 0.5,
    multiplied in, not dropped), which was left black where the smoothed meshes shrink from it;
    filling it from the nearest covered pixel as the rest gives, by `relight eval`, relit /
    albedo / shading: val true mask 16.58 / 16.19 / 19.56 (was 16.57 / 16.19 / 19.49), val own
    mask 16.15 / 16.06 / 17.88 (15.80 / 16.06 / 16.55), test true mask 18.05 / 18.70 / 18.67
    (18.06 / 18.70 / 18.62), test own mask 17.81 / 18.45 / 17.82 (17.48 / 18.45 / 16.89)."""
    ensure_scenes(frame, options, models)
    frame.coarse_shading, frame.notes["raytrace"] = trace_shading(frame, models.light(frame.env), options)
    frame.shading = frame.coarse_shading * person_support(frame)


def ensure_scenes(frame: Frame, options, models: Models) -> None:
    """Build the reconstruction's scene once per photo (the bodies' is the body_maps stage's)."""
    if frame.scene is None:
        build_scene(frame, options)


def body_weight(frame: Frame) -> np.ndarray:
    """(R, R) float32: the fitted bodies' share of the traced shading per crop pixel."""
    return np.float32(BODY_SHADING_WEIGHT) * body_shading_pixels(frame)


# Shadow rays leave the meshes lifted toward the shading normals (render.estimators.
# lifted_origins, in edge lengths): the reconstruction is shaded with the nets' normals, the
# bodies with their smooth vertex normals, and traced from the triangles themselves a grazing
# sun's terminator came out as a staircase of facets (2-3 px steps across a face).
SHADOW_LIFT = 1.0
# The traced visibility is filtered with the integrator's own error estimate (render.denoise,
# adaptive_wiener) in windows of 2 r + 1 pixels; 0: not filtered
SHADING_FILTER_RADIUS = 1


def trace_shading(frame: Frame, light, options, step: int | None = None) -> tuple[np.ndarray, dict]:
    """(shading (R, R, 3), note): the reconstruction ray-traced under `light` (an
    EnvironmentLight), blended with the fitted bodies' (body_weight) where a fit converged;
    person pixels a mesh does not cover, the mask's soft edge included, take their nearest
    covered pixel's shading (stage_raytrace). `--shadows half` traces every second pixel's rays
    (traced); step: another pixel step for the rays than `--shadows` gives."""
    spp, target = sampling_effort(options)
    wanted = frame.crop_mask > 0
    blended = frame.body_scene is not None
    own_target, body_target = blend_targets(target, BODY_SHADING_WEIGHT, body_shading_pixels(frame).all()) \
        if blended and target is not None else (target, target)
    step = SHADOW_STEP[options.shadows] if step is None else step
    own, result = traced(frame.scene, frame.hits, light, spp, own_target, options.seed, options.threads,
                         wanted, step)
    shading, note = np.ascontiguousarray(own[..., :3]), {**_trace_note(result), "shadow_step": step,
                                                         "shadow_lift": SHADOW_LIFT}
    if not blended:
        note["body"] = "no converged body fit: the reconstruction's shading alone"
        return shading, note
    body_filled, body = traced(frame.body_scene, frame.body_hits, light, spp, body_target, options.seed,
                               options.threads, wanted, step)
    weight = body_weight(frame)[..., None]
    note["body"] = {"weight": BODY_SHADING_WEIGHT, **_trace_note(body)}
    mean = (1.0 - weight) * shading + weight * body_filled[..., :3]
    # The blend's own error (the two renders are independent): what the target is met on;
    # the reconstruction's beside it over the same full-resolution pixels (its note's
    # rel_error is over the coarse grid's, where more pixels are exact than after upsampling)
    stderr = np.hypot((1.0 - weight) * own[..., 3:], weight * body_filled[..., 3:])
    pixels = wanted & frame.hits.mask
    note["reconstruction_rel_error"] = median_relative_error(shading, own[..., 3:], pixels)
    note["rel_error"] = median_relative_error(mean, stderr, pixels)
    return mean, note


def traced(scene, hits, light, spp, target, seed, threads, wanted, step) -> tuple[np.ndarray, object]:
    """(mean and standard error (R, R, 6) float32 over the pixels `wanted`, the integrator's
    ShadingResult) of the camera's hits on a scene under `light` (an EnvironmentLight).

    step 1: every hit is ray-traced. step > 1: only every step-th pixel's in both directions
    (a 1 / step^2 share of the rays), and what the rays found there, the visibility V = traced
    / unoccluded shading (cast shadows and occlusion: 1 where nothing blocks the light), is
    interpolated to every pixel and multiplied by that pixel's own unoccluded shading, exact
    from the light's irradiance table (the integrator's control variate) at its own normal: the
    normals' detail stays at full resolution, only shadows and occlusion come at the coarse
    grid's. The error reported is the coarse render's Monte Carlo error carried the same way.
    Person pixels no hit covers take the nearest covered pixel's values (fill_uncovered).

    Measured at step 2 (`relight eval DATA --use-gt-mask [--shadows full]`, relit / shading
    dB, against step 1): validation 16.81 / 20.43 (16.82 / 20.45), test 18.06 / 19.00 (18.05 /
    19.00); the shading's SSIM 0.756 / 0.658 (0.752 / 0.654). The ray tracing stage at 512
    0.40 s instead of 0.74 s (`python bench/bench_pipeline.py [--shadows full]`). The coarse
    shading itself interpolated, without the ratio, lost 0.2 dB of shading on validation.

    The visibility is filtered before it is used (SHADING_FILTER_RADIUS, at either step):
    render.denoise.adaptive_wiener with the integrator's own per-pixel error, which takes out
    the noise a map of many small lights leaves at the sample cap (dark speckles where a few
    occluded samples drew a bright lamp) and keeps a cast shadow's edge. The returned error is
    the Monte Carlo error before filtering."""
    from relightcli.render.denoise import adaptive_wiener, visibility
    from relightcli.render.integrator import shade_environment

    coarse = hits.subsampled(step)
    result = shade_environment(scene, coarse, light, spp=spp, target_error=target, seed=seed, workers=threads,
                               lift=SHADOW_LIFT)
    seen, error, unoccluded, dark = visibility(result, light, coarse.normal)
    if SHADING_FILTER_RADIUS:
        seen = adaptive_wiener(seen, error, coarse.mask & ~dark.any(axis=-1), SHADING_FILTER_RADIUS)
    if step == 1:
        mean = np.where(dark, result.mean, seen * unoccluded) if SHADING_FILTER_RADIUS else result.mean
        # means and errors filled together: one distance transform per render
        return fill_uncovered(np.concatenate([mean, result.stderr], axis=-1), hits.mask, wanted), result
    ratio = fill_uncovered(np.concatenate([seen, error], axis=-1), coarse.mask,
                           np.ones(coarse.mask.shape, bool))
    full = np.zeros(hits.mask.shape + (3,), np.float32)
    full[hits.mask] = light.irradiance(hits.normal[hits.mask])
    values = upsample(ratio.astype(np.float32), hits.mask.shape, step) * np.concatenate([full, full], axis=-1)
    return fill_uncovered(values, hits.mask, wanted), result


def upsample(image: np.ndarray, shape: tuple, step: int) -> np.ndarray:
    """(H, W, C) bilinear from a coarse image (h, w, C) whose pixel (i, j) lies on pixel
    (step i, step j) of the fine one (PixelGeometry.subsampled); held beyond its last row and
    column."""
    def axis(n, coarse):
        at = np.arange(n) / step
        low = np.minimum(at.astype(np.int64), coarse - 1)
        high = np.minimum(low + 1, coarse - 1)
        return low, high, np.clip(at - low, 0.0, 1.0).astype(np.float32)[:, None]

    r0, r1, fr = axis(shape[0], image.shape[0])
    c0, c1, fc = axis(shape[1], image.shape[1])
    rows = image[r0] * (1.0 - fr[..., None]) + image[r1] * fr[..., None]
    return rows[:, c0] * (1.0 - fc) + rows[:, c1] * fc


def blend_targets(target: float, weight: float, everywhere: bool) -> tuple[float, float]:
    """Relative-error targets of the reconstruction's and the bodies' renders whose blend
    (1 - weight) * own + weight * body reaches `target` at the least cost: a render's samples
    in proportion to its weight (minimise 1/n_own + 1/n_body at fixed (1 - w)^2 / n_own +
    w^2 / n_body), i.e. target / sqrt(1 - w) and target / sqrt(w). Where a person's fit did not
    converge (not `everywhere`) the reconstruction is shaded alone and keeps the target."""
    own = target / np.sqrt(1.0 - weight) if everywhere and weight < 1.0 else target
    body = target / np.sqrt(weight) if weight > 0.0 else target
    return float(own), float(body)


def median_relative_error(mean: np.ndarray, stderr: np.ndarray, where: np.ndarray) -> float:
    """Median over `where` of stderr / mean on the channel average (0 where the mean is 0)."""
    m, e = mean[where].mean(axis=-1), stderr[where].mean(axis=-1)
    rel = np.where(m > 0, e / np.where(m > 0, m, 1.0), 0.0)
    return float(np.median(rel)) if rel.size else 0.0


def sampling_effort(options) -> tuple[int, float | None]:
    """(spp or cap, target relative error) from --spp / --target-error."""
    if options.spp is not None:
        return options.spp, None
    return DEFAULT_SPP_CAP, options.target_error or DEFAULT_TARGET_ERROR


def person_mask_at(mask: np.ndarray, point) -> float:
    """The (R, R) mask's value at the nearest pixel to `point` (col, row) pixel indices; 0
    outside the crop."""
    col, row = (int(round(float(v))) for v in point)
    inside = 0 <= row < mask.shape[0] and 0 <= col < mask.shape[1]
    return float(mask[row, col]) if inside else 0.0


def stage_face(frame: Frame, options, models: Models) -> None:
    """Find the face and fit the ICT model to it (relightcli.geometry.face): MediaPipe's face
    detector on a head square placed by each found person's pose landmarks in turn (the person
    crop's square when no person was found), the face mesh on the best detection, its 468
    points -> the model's 68 landmarks (geometry.face_correspondence), the fit in the 128 face
    crop framed around them. Planned only when a face refinement net ships to consume the fit
    (pipeline.plan_stages). The note says which head square gave the face, or why none did."""
    from relightcli.geometry.face import CropRect, fit_face_to_landmarks
    from relightcli.geometry.face_correspondence import load_correspondence
    from relightcli.nets.blaze import RotatedRect
    from relightcli.nets.face_mesh import find_face, head_rect

    frame.view = frame.view or PerceptionView.of(frame.image)
    srgb, scale = frame.view.image, np.asarray(frame.view.scale)
    box = frame.box
    heads = [(f"person {k}", head_rect(p.pose.landmarks)) for k, p in enumerate(frame.people)]
    if not heads:  # the person crop's square, in view pixels
        centre = (box.x0 + box.size / 2.0, box.y0 + box.size / 2.0) * scale
        heads = [("person crop (no person found)", RotatedRect(tuple(centre), box.size * scale[0], box.size * scale[1], 0.0))]
    reasons = {}
    for source, head in heads:
        face, reasons[source] = find_face(srgb, head, models.get("face_detector"), models.get("face_mesh"))
        if face is None:
            continue
        # view pixels -> photo pixels (continuous) -> pixel indices of the person crop
        photo = load_correspondence().landmarks(face.mesh.points[:, :2]) / scale
        landmarks = (photo - (box.x0, box.y0)) / box.scale - 0.5
        if person_mask_at(frame.crop_mask, landmarks.mean(axis=0)) >= 0.5:
            break
        reasons[source] = "the face found lies outside the person mask"
    else:
        frame.notes["face"] = {"path": "face mesh", "skipped": "no face: " + "; ".join(
            f"{source}: {why}" for source, why in reasons.items()) + ": face stage skipped"}
        frame.face_fit, frame.face_crop = None, None
        return
    depth = np.where(frame.crop_mask > 0.5, frame.geometry.front_depth, np.nan)
    fit, info = fit_face_to_landmarks(landmarks, frame.crop.shape, depth=depth)
    frame.notes["face"] = {"path": "face mesh", "head": source, **face.summary(tuple(scale)), **info}
    frame.face_fit = fit
    frame.face_crop = CropRect(*info["crop"]) if fit is not None else None


def stage_face_refine(frame: Frame, options, models: Models) -> None:
    """The paper's face path: the fitted head ray-traced under the target environment in the
    128x128 face crop, the face net on [that crop of the refined body shading, the coarse face
    shading], and the result blended into the body's shading over the face (the face pixels
    of the fitted model, feathered: geometry.face.face_blend_weight). Nothing changes when the
    face stage found no face."""
    from relightcli.geometry.face import cut_crop, face_blend_weight, paste_crop, render_face_shading
    from relightcli.nets.refine import shading_scale

    if frame.face_fit is None:
        frame.notes["face_refine"] = {"skipped": frame.notes.get("face", {}).get("skipped", "no face fit")}
        return
    spp, target = sampling_effort(options)
    # Rendered at the face's own size in the person crop (e.g. 64 px at 512), then enlarged to
    # the net's 128 like the body crop: a quarter of the rays, and on the 89 validation
    # close-ups the net scores the same (19.64 vs 19.61 dB over the face)
    crop = frame.face_crop
    coarse, face_pixels = render_face_shading(frame.face_fit, models.light(frame.env),
                                              resolution=min(crop.size, crop.resolution), spp=spp,
                                              target_error=target, seed=options.seed, threads=1)
    coarse = resample(coarse, crop.resolution)
    face_pixels = resample(face_pixels.astype(np.float32), crop.resolution) > 0.5
    # The net learned on crops normalised by their own scale (the person's pixels of the crop)
    # (times the soft crop mask, as the net learned it)
    mask = cut_crop(frame.crop_mask, crop)
    body = cut_crop(frame.shading, crop) * mask[..., None]
    scale = shading_scale(body, mask)
    refined = models.get("face_refine").predict(body, coarse, scale)
    # frame.shading is already the person's: only the patch is cut to the person's pixels, so
    # the rest of the body keeps its values exactly
    patch = np.maximum(refined, 0.0) * (mask[..., None] > 0)
    frame.shading = paste_crop(frame.shading, patch, face_blend_weight(face_pixels), crop)
    frame.notes["face_refine"] = {"face_pixels": int(face_pixels.sum()), "scale": round(scale, 5)}


def stage_refine(frame: Frame, options, models: Models) -> None:
    """Full-body refinement net on [coarse shading, AO]: a residual on the coarse shading.
    It runs at the working resolution, not at its training side (net_side): at 256 on the 512
    eval scenes (its answer applied as a ratio to the 512 coarse shading) it lowered the
    shading (true mask 17.06 vs 17.45 dB unrefined), at 512 it raises it (17.60)."""
    refined = models.get("body_refine").predict(frame.coarse_shading, frame.ao_net, frame.crop_mask)
    frame.shading = np.maximum(refined, 0.0) * person_support(frame)


def stage_compose(frame: Frame, options, models: Models) -> None:
    """relit = albedo * shading in the crop (pasted back into the full frame by the outputs).
    An all-black target environment lights nothing: shading and relit are black, whatever
    residual the refinement nets add to zero shading, and a RelightWarning says so."""
    if not np.any(frame.env):
        warnings.warn("the target environment map is all black (no light): the relit person "
                      "is black; check the map and --exposure", RelightWarning, stacklevel=2)
        frame.shading = np.zeros_like(frame.shading)
        frame.notes["compose"] = {"black_environment": True}
    frame.relit_crop = compose.relight(frame.albedo, frame.shading)


STAGES = {
    "people": stage_people,
    "mask": stage_mask,
    "crop": stage_crop,
    "geometry": stage_geometry,
    "ao": stage_ao,
    "delight": stage_delight,
    "reconstruct": stage_reconstruct,
    "body": stage_body,
    "body_maps": stage_body_maps,
    "face": stage_face,
    "raytrace": stage_raytrace,
    "sh_shading": stage_sh_shading,
    "refine": stage_refine,
    "face_refine": stage_face_refine,
    "compose": stage_compose,
}


# Stages whose result depends on the lighting: a turntable runs only these once per frame.
LIGHTING_STAGES = ("raytrace", "sh_shading", "refine", "face_refine", "compose")


# --- turning a frame into output layers ---------------------------------------------------

def layer_image(name: str, frame: Frame, options, hdr: bool = False):
    """(array, alpha, srgb) for an image layer, full frame. `hdr`: the file keeps linear HDR
    values (EXR/HDR), so no display exposure is applied."""
    height, width = frame.image.shape[:2]
    full = lambda crop: compose.paste_back(crop, frame.box, height, width)  # noqa: E731
    if name == "mask":
        return frame.mask, None, False
    if name in ("albedo", "shading"):  # straight layers, over black at the photo's mask (alpha)
        return over_black(full(getattr(frame, name)), frame.mask), None, True
    if name == "normal":
        return full((frame.normal + 1.0) * 0.5 * (frame.crop_mask[..., None] > 0.5)), None, False
    if name == "ao":
        return full(frame.ao * frame.crop_mask), None, False
    if name == "relit":
        return relit_image(frame, options, hdr)
    if name in ("body_normal", "body_depth"):
        return full(body_layer(name, frame.body_maps, options.resolution)), None, False
    raise ValueError(f"{name} is not an image layer")


def body_layer(name: str, maps, resolution: int) -> np.ndarray:
    """(R, R, 3) crop of a body prior layer: `body_normal` (front normals as (n + 1) / 2, black
    off the bodies), `body_depth` (front z, back z, coverage in 0/1); all zero when no body fit
    converged (maps None)."""
    if maps is None:
        return np.zeros((resolution, resolution, 3), np.float32)
    covered = maps.mask[..., None]
    if name == "body_normal":
        return ((maps.front_normal + 1.0) * 0.5 * covered).astype(np.float32)
    return np.stack([maps.front_depth, maps.back_depth, maps.mask.astype(np.float32)], axis=-1)


# Display exposure of LDR outputs (see scene_exposure): a white surface facing the camera shows
# at DISPLAY_KEY (linear), so a person of albedo a facing the light shows at about a, as an
# incident-light meter exposes; the meter reads at least METER_FLOOR x the brightest direction
DISPLAY_KEY = 1.0
METER_FLOOR = 0.1


def scene_exposure(env: np.ndarray, exposure_ev: float = 0.0) -> float:
    """The display exposure of LDR outputs, from the target environment alone, never from the
    relit result (which would undo --exposure and light a person under a black map).

    An incident-light meter at the subject with its dome toward the camera (+Z), the
    photographer's rule: the factor that shows an unoccluded white surface facing the camera
    at DISPLAY_KEY, from its unoccluded shading (never less than METER_FLOOR x that of the
    brightest direction, so a map lit only from behind is not exposed for darkness). The meter
    reads the map as it was before --exposure (env / 2 ** exposure_ev), so --exposure
    multiplies the displayed linear result by exactly 2 ** exposure_ev. On the examples (skier
    photo, person mean linear luminance 0.089): 0.069 under noon_grass.hdr, 0.056 under
    kloofendal_overcast.hdr. env: (H, 2H, 3) float32 linear radiance. Returns the factor; 1.0
    for an all-black map (the person stays black; load_envmap warns).
    """
    from relightcli.io.envmap import resample_envmap, texel_directions
    from relightcli.render.environment import EnvironmentLight

    coarse = resample_envmap(env, min(64, env.shape[0])) / np.float32(2.0 ** exposure_ev)
    light = EnvironmentLight(coarse)
    normals = np.concatenate([[[0.0, 0.0, 1.0]], texel_directions(32, 64).reshape(-1, 3)])
    shading = light.irradiance(normals) @ compose.LUMINANCE
    meter = max(float(shading[0]), METER_FLOOR * float(shading.max()))
    return DISPLAY_KEY / meter if meter > 0 and np.isfinite(meter) else 1.0


def over_black(straight: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, W, 3) straight colour times the (H, W) mask as alpha, in place, a band of rows at a
    time; returned."""
    for rows in row_bands(straight.shape[0]):
        straight[rows] *= mask[rows, :, None]
    return straight


def relit_image(frame: Frame, options, hdr: bool):
    """The relit person over the requested background, (rgb, alpha, srgb). EXR/HDR files keep
    the linear relit values; LDR files show them times `scene_exposure` of the target map (the
    environment view gets the same factor, so they stay consistent; a '#RRGGBB' background and
    the kept photo are shown as they are). Over the photo or the environment view a predicted
    mask is sharpened into the alpha (relit_matte); an input mask is used as it is."""
    mask = frame.mask
    matte = relit_matte(frame, options.background)
    scale = 1.0 if hdr else scene_exposure(frame.env, options.exposure_ev)
    env_view = None
    if options.background == "env":
        env_view = background_view(frame, options)
    # The environment view is made for this output only: composite over it in place.
    rgb, alpha = compose.composite_crop(frame.relit_crop, frame.box, mask, options.background,
                                        photo=frame.image, env_view=env_view, scale=scale, out=env_view,
                                        matte=matte)
    frame.notes["relit"] = {"display_exposure": scale}
    if matte is not None:
        frame.notes["relit"]["matte"] = f"the predicted mask sharpened from {matte[0]}..{matte[1]} to 0..1"
    return rgb, alpha, True


# Backgrounds over which a predicted mask is sharpened (compose.PREDICTED_MATTE): images behind
# the person. Over a colour (and as the transparent output's alpha) the mask stays the alpha:
# sharpened, the relit person over black lost on the paper's protocol (the true person's pixels
# only: relit -0.09 dB on the 20 validation scenes at 512, -0.20 on the test scenes, SSIM +0.02
# / +0.01) while it gained around the people (black +0.65 / +0.78 dB at 256 / 512)
SHARPENED_OVER = ("keep", "env")


def relit_matte(frame: Frame, background: str) -> tuple[float, float] | None:
    """The matte the relit output is composited with over `background`: compose.PREDICTED_MATTE
    for a predicted mask over an image (SHARPENED_OVER), else None (the mask as alpha)."""
    return compose.PREDICTED_MATTE if frame.mask_predicted and background in SHARPENED_OVER else None


# Largest finite half float: an EXR layer with larger values is written as float32
HALF_MAX = 65504.0


def fits_half(array: np.ndarray) -> bool:
    """True when every value of the array is finite and within +-HALF_MAX (a half-float EXR
    keeps it finite), checked a band of rows at a time."""
    return all(bool(np.all(np.abs(array[rows]) <= HALF_MAX)) for rows in row_bands(array.shape[0]))


def background_view(frame: Frame, options) -> np.ndarray:
    """The environment seen by a 60-degree camera, rendered at most 1024 wide (the map has no
    more detail than that) and resized to the photo."""
    import cv2

    height, width = frame.image.shape[:2]
    w = min(width, 1024)
    h = max(1, round(height * w / width))
    view = environment_view(frame.env, width=w, height=h, fov_deg=60.0)
    if (h, w) != (height, width):
        view = cv2.resize(view, (width, height), interpolation=cv2.INTER_LINEAR)
    return view


def preview_tiles(frame: Frame, options) -> list:
    """Input, albedo, normal, shading, relit, the estimated input light and the target
    environment, display-ready; shading and relit at the relit output's `scene_exposure`, each
    map at its own 99th percentile."""
    alpha = frame.crop_mask[..., None]  # the layers are straight: shown over black, as the files
    crop_relit = compose.crop_square(frame.relit, frame.box) * alpha
    # relit and shading under the scene's exposure (as the relit output), not re-exposed to taste
    relit_scale = shading_scale = scene_exposure(frame.env, options.exposure_ev)
    map_scale = lambda env: 0.8 / max(float(np.percentile(env @ compose.LUMINANCE, 99.0)), 1e-12)  # noqa: E731
    return [
        ("input", compose.to_display(frame.crop)),
        ("albedo", compose.to_display(frame.albedo * alpha)),
        ("normal", (frame.normal + 1.0) * 0.5 * (frame.crop_mask[..., None] > 0.5)),
        ("shading", compose.to_display(frame.shading * alpha, shading_scale)),
        ("relit", compose.to_display(crop_relit, relit_scale)),
        ("input light", compose.to_display(frame.light, map_scale(frame.light))),
        ("environment", compose.to_display(frame.env, map_scale(frame.env))),
    ]
