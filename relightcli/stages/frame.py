"""What every stage shares: the `Frame` that carries what earlier stages produced, the network
sessions (`Models`), the photo as the perception nets see it, and the resampling of crop maps.

Working-crop arrays are (R, R, ...) float32 in the crop camera of relightcli.compose (world
square [-1, 1]^2, orthographic along -Z); full-frame arrays are (H, W, ...) float32. Results stay
at the crop's size until an output needs them full frame: a 24 MP frame is 288 MB as float32 RGB.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import cv2
import numpy as np

from relightcli import compose


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
    input_shading: np.ndarray | None = None  # (R, R, 3) what the photo was divided by (--albedo solve, ratio)
    mesh: object | None = None  # geometry.mesh.TriangleMesh in the crop camera frame
    scene: object | None = None  # relightcli.render.scene.Scene of the mesh (closed by the pipeline)
    hits: object | None = None  # relightcli.render.camera.PixelGeometry: what each crop pixel sees
    coarse_shading: np.ndarray | None = None  # (R, R, 3) ray-traced
    shading: np.ndarray | None = None  # (R, R, 3) final shading under env
    relit_crop: np.ndarray | None = None  # (R, R, 3) albedo * shading, linear
    view: "PerceptionView | None" = None  # the photo as the perception nets see it
    people: list = field(default_factory=list)  # relightcli.nets.pose.Person found, in view pixels
    portrait_mask: np.ndarray | None = None  # (h, w) selfie segmentation when only a face was found
    faces: list = field(default_factory=list)  # FoundFace per face the face stage fitted
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


@dataclass
class FoundFace:
    """A face the face stage fitted: whose head it is ("person 0"), the fitted model
    (relightcli.geometry.face.FaceFit) and its face crop (relightcli.geometry.face.CropRect)
    in the working crop; `rendered`: (the environment, the fitted head's coarse shading and face
    pixels under it) when made ahead of the face refinement (stages.face.render_faces_ahead)."""

    head: str
    fit: object
    crop: object
    rendered: tuple | None = None


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
    kept for every later item of the batch. `prefetch` creates the sessions a plan will use on
    a background thread while the process goes on: ONNX Runtime builds a session without the
    GIL (0.4-0.5 s for the default plan's nine on 2 cores), so it overlaps the imports and the
    first stages."""

    def __init__(self, threads: int, resolution: int | None = None):
        """resolution: the working crop's side the items will run at; each net's session is
        then built for the side it runs at (run_size); None: for any side."""
        self.threads, self.resolution, self._sessions, self._lights = threads, resolution, {}, {}
        self._pending, self._executor = {}, None  # family -> Future of its session
        self._building = threading.Lock()  # held by the prefetch thread while it builds

    def prefetch(self, families, tables=()) -> None:
        """Start creating these families' sessions, in order, on one background thread; `get`
        waits for a pending one, and raises what its creation raised. `tables`: functions of
        no argument called after them on that thread, to fill their caches (numpy releases
        the GIL in their products and sums); what they raise is dropped (the stage that needs
        the table computes it again and raises there). Nothing may be imported on that thread
        (the session classes and ONNX Runtime are imported here first; a table's module must
        be too): an extension module's import loads a library while holding the GIL, and
        threadpoolctl's scan of the loaded libraries (`paused`) holds the loader's lock while
        it waits for the GIL: the two threads would wait on each other for ever."""
        from concurrent.futures import ThreadPoolExecutor

        from relightcli.nets.session import import_onnxruntime

        _session_classes()
        import_onnxruntime()
        families = [f for f in dict.fromkeys(families) if f not in self._sessions and f not in self._pending]
        if not families and not tables:
            return
        self._executor = self._executor or ThreadPoolExecutor(max_workers=1, thread_name_prefix="relight-models")
        for family in families:
            self._pending[family] = self._executor.submit(self._while_building, self._create, family,
                                                          self.run_size(family))
        for table in tables:
            self._executor.submit(self._while_building, table)

    def paused(self):
        """A context in which the prefetch thread builds nothing (it finishes the session or
        table in hand first): for what must not run beside it, such as threadpoolctl's scan of
        the loaded libraries (see `prefetch`)."""
        return self._building

    def _while_building(self, task, *args):
        with self._building:
            return task(*args)

    def stop_prefetch(self) -> None:
        """Drop the sessions not yet started (a run that ends early does not wait for them)."""
        if self._executor is not None:
            self._executor.shutdown(wait=False, cancel_futures=True)
            self._executor = None
            self._pending = {f: p for f, p in self._pending.items() if not p.cancelled()}

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
            pending = self._pending.pop(family, None)
            self._sessions[family] = pending.result() if pending is not None \
                else self._create(family, self.run_size(family))
        return self._sessions[family]

    def _create(self, family: str, run_size: int | None):
        return _session_classes()[family](threads=self.threads, run_size=run_size)

    def run_size(self, family: str) -> int | None:
        """The side (padded to the model's multiple) a family's net runs at in a crop of
        `resolution`: the working side for the body refinement, the face crop's for the face
        refinement, net_side's for the nets that learned on a side; None when unknown (the
        session for each shape is then built at its first run: ModelSession)."""
        from relightcli.errors import MissingDependencyError
        from relightcli.geometry.face_detect import FACE_CROP_SIZE
        from relightcli.nets.manifest import model_entry

        if self.resolution is None:
            return None
        try:
            entry = model_entry(_session_classes()[family].model_name)
        except MissingDependencyError:  # raised again where the session is asked for
            return None
        fixed = {"body_refine": self.resolution, "face_refine": FACE_CROP_SIZE}
        side = fixed.get(family, net_side(entry, self.resolution) if entry.trained_resolution else None)
        return None if side is None else -(-side // entry.multiple) * entry.multiple


def one_blas_thread(models=None):
    """threadpoolctl's limit of numpy's and scipy's BLAS to one thread (a context manager, or
    `restore_original_limits()`), its scan of the loaded libraries made while `models`'s
    prefetch thread builds nothing (Models.prefetch says why)."""
    import contextlib

    from threadpoolctl import threadpool_limits

    with getattr(models, "paused", contextlib.nullcontext)():
        return threadpool_limits(limits=1, user_api="blas")


def _session_classes() -> dict:
    """Each model family's session class. Imported here, on the calling thread: `prefetch`
    imports them (and ONNX Runtime) before its thread starts, so that thread only builds."""
    from relightcli.nets.delight import DelightNet
    from relightcli.nets.face_mesh import FaceDetector, FaceMesh
    from relightcli.nets.geometry import AONet, AOPriorNet, GeometryNet, GeometryPriorNet
    from relightcli.nets.lift import Lifter
    from relightcli.nets.pose import PersonDetector, PoseLandmarker
    from relightcli.nets.refine import BodyRefineNet, FaceRefineNet
    from relightcli.nets.selfie import SelfieSegmenter

    return {"geometry": GeometryNet, "geometry_prior": GeometryPriorNet, "ao": AONet,
            "ao_prior": AOPriorNet, "delight": DelightNet,
            "body_refine": BodyRefineNet, "face_refine": FaceRefineNet,
            "person_detector": PersonDetector, "pose_landmarks": PoseLandmarker,
            "face_detector": FaceDetector, "face_mesh": FaceMesh,
            "selfie_segmentation": SelfieSegmenter, "lift": Lifter}


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
