"""One image, top to bottom: the plan of stages this input and these options need, and the stages.

The plan is a dependency closure: each requested output names the stages it needs, each stage the
stages before it; everything else is left out and the report says why. Stages whose trained
networks are not shipped raise MissingDependencyError naming the model file and the fix.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from relightcli.batch import Item, ItemReport
from relightcli.errors import InputError, MissingDependencyError

METHODS = ("raytrace", "raytrace-norefine", "sh9", "sh25")

# A person needs some pixels: below this side length nothing meaningful can be estimated.
MIN_SIDE = 32

# Stages in execution order, each with the stages it needs.
STAGE_NEEDS = {
    "load": (),
    "mask": ("load",),
    "crop": ("mask",),
    "geometry": ("crop",),  # normal, AO, back-side geometry nets
    "delight": ("geometry",),  # albedo + input-light estimate
    "reconstruct": ("geometry",),  # watertight mesh + Laplacian smoothing
    "face": ("reconstruct",),  # face detection, morphable-model fit, face shading
    "raytrace": ("reconstruct",),  # coarse body shading under the target environment
    "sh_shading": ("geometry",),  # SH-9/25 irradiance from predicted normals (baselines)
    "refine": ("raytrace", "face"),  # body refinement net, then face refinement
    "compose": (),  # relit = albedo * shading, paste-back, background
}

# Which stage produces the shading for each method.
SHADING_STAGE = {"raytrace": "refine", "raytrace-norefine": "raytrace", "sh9": "sh_shading", "sh25": "sh_shading"}


def output_needs(output: str, method: str) -> tuple[str, ...]:
    """The stages an output layer needs under a method."""
    shading = SHADING_STAGE[method]
    return {
        "mask": ("mask",),
        "normal": ("geometry",),
        "ao": ("geometry",),
        "albedo": ("delight",),
        "light": ("delight",),
        "mesh": ("reconstruct",),
        "shading": (shading,),
        "relit": ("delight", shading, "compose"),
        "preview": ("geometry", "delight", shading, "compose"),
    }[output]


@dataclass
class RelightOptions:
    outputs: tuple[str, ...] = ("relit",)
    method: str = "raytrace"
    mask_path: Path | None = None
    rotate_deg: float = 0.0
    exposure_ev: float = 0.0
    spp: int | None = None
    target_error: float | None = None
    seed: int = 0
    threads: int = 1
    background: str = "keep"
    max_pixels: int = 100_000_000
    resolution: int = 512


@dataclass
class Plan:
    run: list[str]
    skipped: dict[str, str] = field(default_factory=dict)  # stage -> why it does not run

    def as_dict(self) -> dict:
        return {"run": self.run, "skipped": self.skipped}


def plan_stages(options: RelightOptions, *, has_alpha: bool) -> Plan:
    """Decide which stages run. `has_alpha`: the input brings an alpha channel or --mask."""
    needed: set[str] = set()
    pending = [stage for output in options.outputs for stage in output_needs(output, options.method)]
    while pending:
        stage = pending.pop()
        if stage not in needed:
            needed.add(stage)
            pending.extend(STAGE_NEEDS[stage])
    run = [stage for stage in STAGE_NEEDS if stage in needed]
    skipped = {stage: "no requested output needs it" for stage in STAGE_NEEDS if stage not in needed}
    if options.method in ("sh9", "sh25"):
        skipped["raytrace"] = f"--method {options.method} shades with spherical harmonics"
    if options.method == "raytrace-norefine":
        skipped["refine"] = "--method raytrace-norefine"
    if "mask" in needed and has_alpha:
        skipped["mask_net"] = "the input brings an alpha channel or --mask"
    return Plan(run, skipped)


class RelightWorker:
    """Relights items one after another; picklable, so a process pool or a Ray actor can hold
    one. `setup()` loads what is shared by every item of the batch (network sessions) once."""

    def __init__(self, env, options: "RelightOptions"):
        self.env, self.options = env, options

    def setup(self) -> None:
        import cv2

        from relightcli.io.images import set_io_threads

        cv2.setNumThreads(self.options.threads)
        set_io_threads(self.options.threads)

    def __call__(self, item: Item) -> ItemReport:
        return relight_item(item, self.env, self.options)


def relight_item(item: Item, env, options: RelightOptions) -> ItemReport:
    """Run the planned stages on one input and write its outputs. Raises project errors."""
    from relightcli.io.images import read_image

    report = ItemReport(str(item.input))
    with _timed(report, "load"):
        image = read_image(item.input, max_pixels=options.max_pixels)
        _check_usable_size(image, item.input)
        mask = _input_mask(image, options, item.input)
    plan = plan_stages(options, has_alpha=mask is not None)
    report.details["plan"] = plan.as_dict()
    state = {"image": image, "mask": mask, "env": env}
    for stage in plan.run[1:]:
        with _timed(report, stage):
            STAGES[stage](state, options)
    with _timed(report, "write"):
        for name, path in item.outputs.items():
            _write_layer(name, path, state)
            report.outputs[name] = str(path)
    return report


def _check_usable_size(image, path) -> None:
    height, width = image.rgb.shape[:2]
    if min(height, width) < MIN_SIDE:
        raise InputError(
            f"image is {width}x{height} pixels, too small to hold a person",
            path=path,
            fix=f"use a photo at least {MIN_SIDE} pixels on each side (512 or more works best)",
        )


def _input_mask(image, options: RelightOptions, input_path):
    """The person mask from --mask or the input's alpha, (H, W) float32 in [0, 1], or None."""
    from relightcli.io.images import read_image

    if options.mask_path is not None:
        mask_image = read_image(options.mask_path, max_pixels=options.max_pixels)
        if mask_image.rgb.shape[:2] != image.rgb.shape[:2]:
            raise InputError(
                f"mask is {mask_image.rgb.shape[1]}x{mask_image.rgb.shape[0]} but the photo "
                f"{input_path} is {image.rgb.shape[1]}x{image.rgb.shape[0]}",
                path=options.mask_path,
                fix="pass a mask of the same size as the photo",
            )
        # A grey mask file is data, not colour: undo the sRGB decode read_image applied.
        from relightcli.io.images import linear_to_srgb

        values = mask_image.alpha if mask_image.alpha is not None and mask_image.alpha.min() < 1 else None
        if values is None:
            values = linear_to_srgb(mask_image.rgb[..., 0]) if mask_image.encoded else mask_image.rgb[..., 0]
        return values.clip(0.0, 1.0).astype("float32")
    if image.alpha is not None and float(image.alpha.min()) < 1.0:
        return image.alpha
    return None


def _stage_mask(state, options):
    if state["mask"] is None:
        _require_model("mask", "predicts the person mask; pass --mask FILE or an RGBA input instead")


def _stage_not_shipped(name: str, what: str):
    def run(state, options):
        _require_model(name, what)

    return run


def _require_model(name: str, what: str):
    raise MissingDependencyError(
        f"the '{name}' network ({what}) is not shipped in this build",
        path=Path(__file__).resolve().parents[1] / "models" / "manifest.json",
        fix="install a release with trained models, or ask only for outputs this build can make: --outputs mask with an RGBA input or --mask",
    )


def _stage_compose(state, options):
    _require_model("compose", "needs albedo and shading")


STAGES = {
    "mask": _stage_mask,
    "crop": lambda state, options: None,
    "geometry": _stage_not_shipped("geometry", "normals, AO and back-side geometry"),
    "delight": _stage_not_shipped("delight", "albedo and input lighting"),
    "reconstruct": _stage_not_shipped("geometry", "the mesh is built from its outputs"),
    "face": lambda state, options: None,
    "raytrace": _stage_not_shipped("geometry", "the mesh to ray trace"),
    "sh_shading": _stage_not_shipped("geometry", "normals for SH shading"),
    "refine": _stage_not_shipped("refine_body", "shading refinement"),
    "compose": _stage_compose,
}


def _write_layer(name: str, path: Path, state) -> None:
    from relightcli.io.images import write_image

    if name == "mask":
        write_image(path, state["mask"], bits=8, srgb=False)
        return
    raise MissingDependencyError(f"output '{name}' cannot be made by this build", path=path)


@contextmanager
def _timed(report: ItemReport, stage: str):
    """Record a stage's wall time into the report, also when it raises."""
    start = time.perf_counter()
    try:
        yield
    finally:
        report.seconds[stage] = round(time.perf_counter() - start, 4)
