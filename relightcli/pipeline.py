"""One image, top to bottom: the plan of stages this input and these options need, then the stages.

The plan is a dependency closure: each requested output names the stages it needs, each stage the
stages before it; everything else is left out and the report says why. The stage functions live in
relightcli.stages; network sessions are loaded on first use and kept for the whole batch.
"""

from __future__ import annotations

import time
from concurrent.futures import wait
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path

import numpy as np

from relightcli.batch import Item, ItemReport
from relightcli.errors import InputError
from relightcli.layers import DEFAULT_ALBEDO, DEFAULT_RESOLUTION, DEFAULT_SHADOWS

# A person needs some pixels: below this side length nothing meaningful can be estimated.
MIN_SIDE = 32

# Stages in execution order, each with the stages it needs.
STAGE_NEEDS = {
    "people": (),  # person detection, pose and segmentation of everyone in the photo
    "mask": ("people",),  # from the input's alpha, --mask, or the people's segmentations
    "crop": ("mask",),  # square around the person at the working resolution
    "body": ("people", "crop"),  # body model fitted to each person's pose and silhouette
    "body_maps": ("body",),  # the fitted bodies' front/back depth and normals in the crop
    "geometry": ("crop",),  # front/back normals and depth (with the prior net: also body_maps)
    "ao": ("crop",),  # ambient occlusion net (the AO layer: also body_maps, see stage_needs)
    "reconstruct": ("geometry",),  # watertight mesh + Laplacian smoothing
    "delight": ("geometry",),  # albedo + input light (--albedo solve: also the meshes, see stage_needs)
    "face": ("people", "geometry"),  # face detector + mesh on the people's heads, morphable-model fit
    "raytrace": ("reconstruct", "body_maps"),  # coarse body shading under the target environment
    "sh_shading": ("geometry",),  # SH-9/25 irradiance from predicted normals (baselines)
    "refine": ("raytrace", "ao"),  # body refinement net
    "face_refine": ("refine", "face"),  # coarse face shading, face refinement net, composite
    "compose": ("crop",),  # relit = albedo * shading, pasted back
}

# The network families each stage uses in the usual case (a person found, a body fitted); the
# sessions of a plan's stages are created ahead on a background thread (Models.prefetch).
STAGE_MODELS = {
    "people": ("person_detector", "pose_landmarks"),
    "body": ("lift",),  # when the models folder ships it
    "geometry": ("geometry_prior",),  # "geometry" when no body fit converges
    "ao": ("ao",),
    "delight": ("delight",),
    "face": ("face_detector", "face_mesh"),
    "refine": ("body_refine",),
    "face_refine": ("face_refine",),
}

# Which stage produces the shading for each method.
SHADING_STAGE = {"raytrace": "face_refine", "raytrace-norefine": "raytrace", "sh9": "sh_shading",
                 "sh25": "sh_shading"}


def output_needs(output: str, method: str) -> tuple[str, ...]:
    """The stages an output layer needs under a method."""
    shading = SHADING_STAGE[method]
    return {
        "mask": ("mask",),
        "normal": ("geometry",),
        "ao": ("ao",),
        "albedo": ("delight",),
        "light": ("delight",),
        "mesh": ("reconstruct",),
        "body_normal": ("body_maps",),
        "body_depth": ("body_maps",),
        "shading": (shading,),
        "relit": ("delight", shading, "compose"),
        "preview": ("geometry", "delight", shading, "compose"),
    }[output]


@dataclass
class RelightOptions:
    outputs: tuple[str, ...] = ("relit",)
    method: str = "raytrace"
    albedo: str = DEFAULT_ALBEDO  # layers.ALBEDO_SOURCES
    mask_path: Path | None = None
    rotate_deg: float = 0.0
    exposure_ev: float = 0.0
    spp: int | None = None
    target_error: float | None = None
    shadows: str = DEFAULT_SHADOWS  # layers.SHADOW_STEP
    seed: int = 0
    threads: int = 1
    background: str = "keep"
    max_pixels: int = 100_000_000
    resolution: int = DEFAULT_RESOLUTION
    turntable: int = 0  # frames with the environment turned 360/N apart; 0: one image


@dataclass
class Plan:
    run: list[str]
    skipped: dict[str, str] = field(default_factory=dict)  # stage -> why it does not run

    def as_dict(self) -> dict:
        return {"run": self.run, "skipped": self.skipped}


def stage_needs(stage: str, options: RelightOptions) -> tuple[str, ...]:
    """The stages `stage` needs under these options: the de-lighting's light solve
    (--albedo solve) ray-traces the mesh and the fitted bodies as the shading does; the geometry
    refines the fitted bodies' maps when the prior net ships; the AO layer blends in the fitted
    bodies' traced AO."""
    if stage == "delight" and options.albedo == "solve":
        return STAGE_NEEDS["delight"] + ("reconstruct", "body_maps")
    if stage == "geometry" and _ships("geometry_prior"):
        return STAGE_NEEDS["geometry"] + ("body_maps",)
    if stage == "ao" and "ao" in options.outputs:
        return STAGE_NEEDS["ao"] + ("body_maps",)
    return STAGE_NEEDS[stage]


def plan_stages(options: RelightOptions, *, has_alpha: bool) -> Plan:
    """Decide which stages run. `has_alpha`: the input brings an alpha channel or a mask file
    (--mask, or the photo's own NAME_mask file)."""
    needed: set[str] = set()
    pending = [stage for output in options.outputs for stage in output_needs(output, options.method)]
    while pending:
        stage = pending.pop()
        if stage not in needed:
            needed.add(stage)
            pending.extend(stage_needs(stage, options))
    run = [stage for stage in STAGE_NEEDS if stage in needed]
    skipped = {stage: "no requested output needs it" for stage in STAGE_NEEDS if stage not in needed}
    if options.method in ("sh9", "sh25"):
        skipped["raytrace"] = f"--method {options.method} shades with spherical harmonics"
    if options.method == "raytrace-norefine":
        skipped["refine"] = "--method raytrace-norefine"
    if "face_refine" in run and not _ships("face_refine"):
        for stage in ("face", "face_refine"):
            run.remove(stage)
            skipped[stage] = ("models/manifest.json has no face_refine model: the body "
                              "refinement's shading is used over the face too")
    if "people" in run and has_alpha and "face" not in run and "body" not in run:
        run.remove("people")
        skipped["people"] = ("the input brings an alpha channel or a mask file (only the face and "
                             "body stages need the people)")
    return Plan(run, skipped)


def planned_models(options: RelightOptions) -> list[str]:
    """The network families the plan's stages use, in the order they are first needed: the
    stages that run with or without the input's own mask (a mask can leave out `people`)."""
    stages = set(plan_stages(options, has_alpha=True).run) & set(plan_stages(options, has_alpha=False).run)
    families = [family for stage in STAGE_NEEDS if stage in stages for family in STAGE_MODELS.get(stage, ())]
    if "geometry_prior" in families and not _ships("geometry_prior"):
        families[families.index("geometry_prior")] = "geometry"
    return [family for family in families if family != "lift" or _ships("lift")]


def _ships(model: str) -> bool:
    """Whether the models folder describes `model` (the face refinement: the face stage's
    consumer; the geometry prior net: the body maps'; the landmark lifter: the body fit's)."""
    from relightcli.errors import RelightError
    from relightcli.nets.manifest import load_manifest

    try:
        return model in load_manifest()
    except RelightError:
        return False  # a broken manifest is reported when the models load


class RelightWorker:
    """Relights items one after another; picklable, so a process pool or a Ray actor can hold
    one. `setup()` prepares what every item of the batch shares (threads, model sessions)."""

    def __init__(self, env, options: RelightOptions, models=None):
        self.env, self.options = env, options
        self.models = models

    def setup(self) -> None:
        if self.models is None:
            self.models = prepared_models(self.options)

    def __call__(self, item: Item) -> ItemReport:
        return relight_item(item, self.env, self.options, self.models)

    def __getstate__(self):
        return {"env": self.env, "options": self.options, "models": None}  # sessions stay per process


def prepared_models(options: RelightOptions):
    """`load_models`, with the sessions the plan uses being created on a background thread,
    and after them the light solve's transport table (0.17 s, once per process) and the
    irradiance tables' kernel (0.04-0.06 s, once per process) where the plan traces rays."""
    models, families = load_models(options.threads, options.resolution), planned_models(options)
    models.prefetch(families)
    solve = options.albedo == "solve" and "delight" in families
    tables = []
    # imported here, while the sessions build: the prefetch thread may import nothing
    if solve:
        from relightcli.render.inverse import LIGHT_HEIGHT, transport_table

        tables.append(partial(transport_table, LIGHT_HEIGHT))
    if solve or "raytrace" in plan_stages(options, has_alpha=True).run:
        from relightcli.render.environment import irradiance_kernel

        tables.append(irradiance_kernel)
    if tables:
        models.prefetch((), tables=tables)
    return models


def load_models(threads: int, resolution: int | None = None):
    """OpenCV's and OpenImageIO's threads set to `threads`, and the network sessions (loaded on
    first use, each built for the side it runs at in a `resolution` crop) that every item of a
    batch shares."""
    import cv2

    from relightcli.io.images import set_io_threads
    from relightcli.stages.frame import Models

    cv2.setNumThreads(threads)
    set_io_threads(threads)
    return Models(threads, resolution)


def relight_item(item: Item, env, options: RelightOptions, models=None) -> ItemReport:
    """Run the planned stages on one input and write its outputs. Raises project errors.

    env: one environment map, or a list of them: the lighting stages run once per map. With
    options.turntable = N, they run N times under the (one) map turned 360/N degrees apart
    (`turntable_lightings`: one turned map at a time). Outputs keyed 'relit#003' /
    'shading#003' / 'preview#003' receive lighting 3."""
    report = ItemReport(str(item.input))
    with _timed(report, "load"):
        image, mask, mask_source = read_input(item.input, item.mask, options)
    maps = list(env) if isinstance(env, (list, tuple)) else [env]
    lightings = turntable_lightings(maps[0], options.turntable) if options.turntable else maps

    def write_lit_layers(k, frame):
        with _timed(report, "write"):
            for key, path in item.outputs.items():
                name, _, index = key.partition("#")
                if index and int(index) == k:
                    write_layer(name, path, frame, options)
                    report.outputs[key] = str(path)

    frame, plan = run_stages(image.rgb, mask, maps[0], options, report, models, lightings=lightings,
                             on_lighting=write_lit_layers,
                             mask_source=mask_source)
    report.details["plan"] = plan.as_dict()
    with _timed(report, "write"):
        for key, path in item.outputs.items():
            if "#" not in key:
                write_layer(key, path, frame, options)
                report.outputs[key] = str(path)
    report.details["stages"] = frame.notes
    return report


def turntable_lightings(env: np.ndarray, frames: int):
    """The (h, 2h, 3) map `env` turned 360/frames degrees apart, frames 0, 1, ..., each made
    when it is asked for: a run keeps one or two turned maps, never all of them (300 frames of a
    1024 x 512 map would take 1.9 GB, 100000 more memory than a machine has)."""
    from relightcli.io.envmap import rotate_envmap

    for k in range(frames):
        yield rotate_envmap(env, 360.0 * k / frames)


def read_input(path: Path, own_mask: Path | None, options: RelightOptions):
    """(the photo's Image, its (H, W) person mask or None, the report's word for where the mask
    came from) for the photo at `path`; `own_mask`: its own NAME_mask file (batch.pair_masks)."""
    from relightcli.io.images import read_image

    return photo_and_mask(read_image(path, max_pixels=options.max_pixels), path, own_mask, options)


def photo_and_mask(image, path, own_mask: Path | None, options: RelightOptions):
    """read_input for a decoded Image (a file's, or an array's: relightcli.api)."""
    from relightcli.io.images import refuse_non_finite

    check_usable_size(image, path)
    refuse_non_finite(image.rgb, path, "the photo",
                      "save it with finite values (NaN and Inf replaced, e.g. by 0), or as PNG/JPEG")
    mask_path, mask_source = _mask_file(options.mask_path, own_mask)
    return image, input_mask(image, mask_path, options.max_pixels, path), mask_source


def run_stages(image: np.ndarray, mask, env, options: RelightOptions, report: ItemReport, models=None,
               *, lightings=None, on_lighting=None, mask_source=None):
    """Plan and run the stages on arrays. Returns (frame, plan).

    mask: the input's (H, W) person mask or None; mask_source says where it came from (the
    report's "mask" note; default "alpha channel").
    lightings: environments to relight under in turn (default [env]), any iterable, taken one
    at a time (a turntable's are made as they are asked for). The stages that do not depend on
    the lighting run once, the others once per environment, each followed by
    on_lighting(index, frame). Stage times add up over the lightings."""
    from relightcli.stages import LIGHTING_STAGES
    from relightcli.stages.frame import Frame, Models, one_blas_thread

    models = models or Models(options.threads, options.resolution)
    plan = plan_stages(options, has_alpha=mask is not None)
    frame = Frame(image=image, mask=mask, env=env)
    if mask is not None:
        frame.notes["mask"] = {"source": mask_source or "alpha channel"}
    # numpy's and scipy's BLAS on one thread for the whole item: relightcli/__init__.py asks for
    # it before they load, but a process that loaded numpy first (a Python caller, pytest) kept
    # OpenBLAS's default threads, and with two people the body fits' products split across
    # them rounded differently: other bytes than the CLI's for the same photo
    blas = one_blas_thread(models)
    one_lighting = lightings is None or (isinstance(lightings, (list, tuple)) and len(lightings) == 1
                                         and lightings[0] is env)
    side = SideLine(frame, options, models, report, one_lighting) if options.threads >= 2 else None
    try:
        for stage in (s for s in plan.run if s not in LIGHTING_STAGES):
            if side is not None and side.takes(stage, plan):
                side.start(stage)
                continue
            _run_stage(stage, frame, options, models, report, side)
        for index, lighting in enumerate(lightings or [env]):
            frame.env = lighting
            for stage in (s for s in plan.run if s in LIGHTING_STAGES):
                _run_stage(stage, frame, options, models, report, side)
            if on_lighting is not None:
                on_lighting(index, frame)
        if side is not None:
            side.close()
    finally:
        if side is not None:
            side.close(quietly=True)  # after an error here: the scenes it traces close next
        blas.restore_original_limits()
        for scene in (frame.scene, frame.body_scene):
            if scene is not None:
                scene.close()
    return frame, plan


def _run_stage(stage: str, frame, options: RelightOptions, models, report: ItemReport, side) -> None:
    """One stage on the calling thread, once the side line's stages it waits for are done; on
    one core for tracing while the side line has work (each line then takes a core)."""
    from relightcli.stages import STAGES

    if side is not None:
        side.wait_before(stage)
        options = side.options_beside(options)
    with _timed(report, stage):
        STAGES[stage](frame, options, models)


class SideLine:
    """A second thread that runs some stages, one after another, while the calling thread goes
    on with the others (`--threads` 2 or more; issue 50): the AO net, the de-lighting (the
    light solve and the input shading's trace) and the face fit beside the mesh's
    reconstruction, the target's ray tracing and the refinement, which read none of their
    results; with one environment, the fitted faces' renders for the face refinement too.
    Embree's traces, ONNX Runtime's nets and numpy's large array operations run without the
    GIL, so the two lines use both cores. A side stage starts where the plan has
    it, after the calling thread's stages before it; the calling thread waits for it before the
    stage in SIDE_WAITS. Each line traces on one process meanwhile, and a render gives the same
    bytes on one thread or two (tests/test_determinism.py).

    Measured (`python bench/whole_process.py --resolutions 512 --runs 5 --against` the tree
    before): one photo at 512, the item 4.27 -> 3.49 s, the whole process 5.50 -> 4.80 s. The
    target map's sampling tables built on this line beside the body fit (0.2 s off the ray
    tracing) came out slower (the item's median 3.67 -> 3.95 s over 6 runs each): the people
    and body stages, which ran beside it, slowed by more."""

    # side stage -> the calling thread's stage that needs its results
    SIDE_WAITS = {"ao": "refine", "delight": "compose", "face": "face_refine"}

    def __init__(self, frame, options: RelightOptions, models, report: ItemReport, one_lighting: bool = True):
        from concurrent.futures import ThreadPoolExecutor

        self.frame, self.options, self.models, self.report = frame, options, models, report
        self.one_lighting = one_lighting  # frame.env is the only environment: render the faces ahead
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="relight-side")
        self._running: dict = {}  # side stage -> future

    def takes(self, stage: str, plan: Plan) -> bool:
        """Whether `stage` runs on this line: a side stage whose waiting stage runs too."""
        return stage in self.SIDE_WAITS and self.SIDE_WAITS[stage] in plan.run

    def start(self, stage: str) -> None:
        from relightcli.stages import STAGES
        from relightcli.stages.shading import ensure_scenes

        if stage == "delight" and self.options.albedo == "solve":
            ensure_scenes(self.frame, self.options, self.models)  # its light solve traces them too
        options = replace(self.options, threads=1)

        def run():
            with _timed(self.report, stage):
                STAGES[stage](self.frame, options, self.models)
            if stage == "face" and self.one_lighting:
                from relightcli.stages.face import render_faces_ahead

                with _timed(self.report, "face_refine"):  # its work, done ahead
                    render_faces_ahead(self.frame, options, self.models)

        self._running[stage] = self._executor.submit(run)

    def wait_before(self, stage: str) -> None:
        """Wait for (and raise what raised in) the side stages `stage` needs."""
        for side, waiter in self.SIDE_WAITS.items():
            if waiter == stage and side in self._running:
                self._running.pop(side).result()

    def options_beside(self, options: RelightOptions) -> RelightOptions:
        return replace(options, threads=1) if self._running else options

    def close(self, quietly: bool = False) -> None:
        """Wait for what still runs, then raise the first error it raised (none `quietly`)."""
        futures, self._running = list(self._running.values()), {}
        wait(futures)
        self._executor.shutdown()
        for future in futures if not quietly else ():
            future.result()


def predict_scene(scene, options: RelightOptions, *, use_gt_mask: bool = False, models=None) -> dict:
    """For `relight eval`: relit, albedo, shading (full frame, linear) and the geometry stage's
    normals (full frame, zero off the person) of a scene folder; relit, albedo and shading as
    the product gives them, the mask applied once as alpha: the relit output over black and the
    layer files."""
    from relightcli.compose import paste_back
    from relightcli.io.envmap import load_envmap
    from relightcli.io.images import read_image
    from relightcli.stages.compose import layer_image

    image = read_image(scene.input_path, max_pixels=options.max_pixels)
    check_usable_size(image, scene.input_path)
    if image.rgb.shape[:2] != scene.mask.shape:
        raise InputError(f"the input is {image.rgb.shape[1]}x{image.rgb.shape[0]}, its truth (gt_mask.png) "
                         f"{scene.mask.shape[1]}x{scene.mask.shape[0]}", path=scene.input_path,
                         fix="regenerate the scene: the input and the truth must be the same size")
    env = load_envmap(scene.target_path)
    mask = scene.mask if use_gt_mask else None
    frame, _ = run_stages(image.rgb, mask, env, options, ItemReport(str(scene.folder)), models)
    height, width = image.rgb.shape[:2]
    return {
        "relit": layer_image("relit", frame, replace(options, background="#000000"), hdr=True)[0],
        "albedo": layer_image("albedo", frame, options)[0],
        "shading": layer_image("shading", frame, options)[0],
        "normal": None if frame.normal is None else paste_back(frame.normal, frame.box, height, width),
    }


def check_usable_size(image, path) -> None:
    height, width = image.rgb.shape[:2]
    if min(height, width) < MIN_SIDE:
        raise InputError(
            f"image is {width}x{height} pixels, too small to hold a person",
            path=path,
            fix=f"use a photo at least {MIN_SIDE} pixels on each side (512 or more works best)",
        )


def _mask_file(option_path, own_path):
    """(the mask file to read, the report's word for where it came from): --mask before the
    photo's own NAME_mask file; (None, None) for neither."""
    if option_path is not None:
        return option_path, f"--mask {option_path}"
    return own_path, None if own_path is None else f"{own_path} (the photo's own mask)"


def input_mask(image, mask_path, max_pixels, input_path):
    """The person mask from the file `mask_path` (--mask or the photo's own NAME_mask file)
    or else the input's alpha, (H, W) float32 in [0, 1], or None."""
    from relightcli.io.images import read_image, refuse_non_finite

    if mask_path is not None:
        mask_image = read_image(mask_path, max_pixels=max_pixels, srgb=False)
        if mask_image.rgb.shape[:2] != image.rgb.shape[:2]:
            raise InputError(
                f"mask is {mask_image.rgb.shape[1]}x{mask_image.rgb.shape[0]} but the photo "
                f"{input_path} is {image.rgb.shape[1]}x{image.rgb.shape[0]}",
                path=mask_path,
                fix="pass a mask of the same size as the photo",
            )
        # A grey mask image is data; a mask given as an alpha channel wins when it has one.
        has_alpha = mask_image.alpha is not None and mask_image.alpha.min() < 1.0
        values = mask_image.alpha if has_alpha else mask_image.rgb[..., 0]
        refuse_non_finite(values, mask_path, "the mask",
                          "save the mask with values in 0..1 (1: the person, 0: the background)")
        return values.clip(0.0, 1.0).astype(np.float32, copy=False)
    if image.alpha is not None and float(image.alpha.min()) < 1.0:
        if not (image.alpha > 0.5).any():  # the crop keeps alpha > 0.5 as the person
            raise InputError("the image's alpha channel is transparent everywhere (no alpha above "
                             "0.5): no person to relight",
                             path=input_path,
                             fix="save the photo with the person opaque, or without an alpha channel")
        return image.alpha
    return None


def write_layer(name: str, path: Path, frame, options: RelightOptions) -> None:
    """Write one output layer of a finished frame (atomic writes)."""
    from relightcli.io.images import write_image
    from relightcli.stages.compose import layer_image, preview_tiles

    suffix = Path(path).suffix.lower()
    if name == "light":
        write_image(path, frame.light)
    elif name == "mesh":
        from relightcli.geometry.mesh import save_mesh

        save_mesh(frame.mesh, path)
    elif name == "preview":
        from relightcli.compose import preview_sheet

        write_image(path, preview_sheet(preview_tiles(frame, options)), srgb=False)
    else:
        hdr = suffix in (".exr", ".hdr")
        array, alpha, srgb = layer_image(name, frame, options, hdr=hdr)
        bits = 8 if name in ("mask", "relit") else 16
        write_image(path, array, alpha, bits=None if hdr or suffix in (".jpg", ".jpeg") else bits, srgb=srgb,
                    half=name != "body_depth")  # EXR: half where it keeps the values; depth float32


@contextmanager
def _timed(report: ItemReport, stage: str):
    """Add a stage's wall time to the report (also when it raises; repeated stages add up)."""
    start = time.perf_counter()
    try:
        yield
    finally:
        report.seconds[stage] = round(report.seconds.get(stage, 0.0) + time.perf_counter() - start, 4)
