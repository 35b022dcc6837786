"""The Python API: relight from a notebook, a web service or a pipeline without the CLI.

    import relightcli

    result = relightcli.relight("examples/skier.jpg", "examples/noon_grass.hdr",
                                mask="examples/skier_mask.png", outputs=("relit", "albedo"))
    result.layers["relit"]        # (H, W, 3) float32, linear
    result.report["seconds"]      # per stage
    result.save("out/skier.png")  # out/skier.png, out/skier_albedo.png: the CLI's files

    relighter = relightcli.Relighter(resolution=256)   # the networks load once
    for photo in photos:
        relighter.relight(photo, "sky.hdr").save(f"out/{photo.stem}.png")

The options are the CLI's, by the same names (`--target-error` is `target_error`); inputs are
files or arrays. The pipeline is the CLI's own (relightcli.pipeline), so for the same inputs,
options and seed `save` writes the same bytes as `relight`.
"""

from __future__ import annotations

import argparse
import contextlib
import time
import warnings
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import numpy as np

from relightcli.errors import InputError, RelightWarning, UsageError
from relightcli.pipeline import RelightOptions

# The CLI's names for the options that RelightOptions names otherwise
_RENAMED = {"rotate": "rotate_deg", "exposure": "exposure_ev"}
_NOT_OPTIONS = ("mask_path", "turntable")  # mask= is an argument; a turntable is relight() per angle


@dataclass
class Result:
    """One relit photo: `layers`, the requested output layers as arrays, full frame (made on
    first use); `report`, the CLI's JSON report of the item (stages run and skipped, seconds,
    notes, warnings); `save(out)`, the layers written as `relight` writes them.

    Layers as arrays: relit (H, W, 3) linear RGB over the background (H, W, 4 with the mask as
    alpha for background "transparent"), albedo and shading (H, W, 3) linear, straight times
    the mask (over black), mask and ao (H, W) in [0, 1], normal and body_normal (H, W, 3) as
    (n + 1) / 2, body_depth (H, W, 3), light (16, 32, 3) linear radiance, mesh a
    trimesh.Trimesh, preview the sheet (h, w, 3) sRGB-encoded in [0, 1]."""

    report: dict
    frame: object = field(repr=False)  # relightcli.stages.Frame
    options: RelightOptions = field(repr=False)
    source: Path | None = None  # the photo's file, when it came from one
    _layers: dict = field(default_factory=dict, repr=False)

    @property
    def layers(self) -> dict:
        for name in self.options.outputs:
            if name not in self._layers:
                self._layers[name] = self._layer(name)
        return self._layers

    def _layer(self, name: str):
        from relightcli.compose import preview_sheet
        from relightcli.stages.compose import layer_image, preview_tiles

        if name == "mesh":
            return self.frame.mesh.to_trimesh()
        if name == "light":
            return self.frame.light
        if name == "preview":
            return preview_sheet(preview_tiles(self.frame, self.options))
        array, alpha, _ = layer_image(name, self.frame, self.options, hdr=True)
        if name in ("mask", "ao"):
            return array
        return array if alpha is None else np.concatenate([array, alpha[..., None]], axis=-1)

    def save(self, out: str | Path, *, overwrite: bool = True) -> dict[str, Path]:
        """Write the layers as `relight PHOTO -o OUT` does: `out` a file (the relit image; .png,
        .jpg, .exr or .hdr) with the other layers beside it (out_albedo.png, ...), or a folder
        (a name without an extension), where they are named after the photo ('image' for an
        array). The files appear together or not at all; never over the photo or its mask.
        Returns {layer: path}."""
        from relightcli import batch
        from relightcli.batch import ItemReport
        from relightcli.pipeline import write_layer

        # an array's files are named 'image'; its stand-in path is no file any output can be
        source = self.source or Path("/dev/null/image.png")
        read_only = [self.options.mask_path] if self.options.mask_path else []
        (item,) = batch.plan_items([(source, Path(source.stem))], out, self.options.outputs, read_only=read_only)
        error = batch.output_error(item)  # a folder where a file goes, a name too long, ...
        if error is not None:
            raise error
        existing = batch.existing_outputs(item)
        if existing and not overwrite:
            raise UsageError("output exists", path=existing[0], fix="pass overwrite=True or another path")
        batch.prepare_output_dirs([item])

        def write(staged):
            for name, path in staged.outputs.items():
                write_layer(name, path, self.frame, self.options)
            return ItemReport(str(source))

        batch.relight_staged(item, write, contextlib.nullcontext())
        return dict(item.outputs)


class Relighter:
    """Relights many photos with the networks loaded once. `options`: the defaults of every
    `relight` call (the CLI's options by name: outputs, method, albedo, rotate, exposure, spp,
    target_error, shadows, seed, background, resolution, max_pixels); `threads`: for ONNX
    Runtime, OpenCV, OpenImageIO and the ray tracer (default: the cores available). Not for
    several threads at once: one Relighter per thread or process."""

    def __init__(self, *, threads: int | None = None, **options):
        from relightcli.cli import default_threads
        from relightcli.pipeline import prepared_models

        threads = _checked_threads(threads, default_threads())
        self.options = _options(RelightOptions(threads=threads), options)
        # the sessions its options' plan uses start building on a background thread now
        self.models = prepared_models(self.options)

    def relight(self, image, hdr, *, mask=None, **options) -> Result:
        """Relight one photo under one environment map.

        image: a photo's path, or an (H, W[, 3 | 4]) array (uint8 / uint16: sRGB codes; float:
        linear RGB; a fourth channel is the person's alpha). hdr: an equirectangular map's path
        (.hdr, .exr), or an (h, 2h, 3) float array of linear radiance. mask: the person mask, a
        path or an (H, W) array in [0, 1] (default: the photo's alpha, else the people found).
        options: this call's, over the Relighter's. Raises relightcli.errors.RelightError
        (UsageError for options, InputError for inputs) with the file and the fix."""
        from relightcli.batch import ItemReport
        from relightcli.pipeline import run_stages

        start = time.perf_counter()
        options = _options(self.options, options)
        report = ItemReport(str(image) if _is_path(image) else "image array")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", RelightWarning)
            photo, person, mask_source, options = _read_photo(image, mask, options)
            env = _environment(hdr, options)
            frame, plan = run_stages(photo.rgb, person, env, options, report, self.models, mask_source=mask_source)
        report.seconds["total"] = round(time.perf_counter() - start, 4)
        report.details["plan"] = plan.as_dict()
        report.details["stages"] = frame.notes
        for warning in caught:
            if issubclass(warning.category, RelightWarning):
                report.warnings.append(str(warning.message))
            warnings.warn_explicit(warning.message, warning.category, warning.filename, warning.lineno)
        return Result(report.as_dict(), frame, options, Path(image) if _is_path(image) else None)


def relight(image, hdr, *, mask=None, threads: int | None = None, **options) -> Result:
    """Relight one photo (see Relighter.relight; `threads` and the options as Relighter's).
    For many photos, a Relighter loads the networks once instead of once per call."""
    return Relighter(threads=threads).relight(image, hdr, mask=mask, **options)


def _is_path(value) -> bool:
    return isinstance(value, (str, Path))


def _read_photo(image, mask, options: RelightOptions):
    """(the photo's Image, its mask or None, the mask's source note, the options with the mask
    file) from a path or an array and a mask path, array or None."""
    from relightcli.io.images import image_from_array
    from relightcli.pipeline import photo_and_mask, read_input

    if _is_path(mask):
        options = replace(options, mask_path=Path(mask))
    if _is_path(image):
        photo, person, source = read_input(Path(image), None, options)
    else:
        array = image_from_array(image, max_pixels=options.max_pixels)
        photo, person, source = photo_and_mask(array, array.path, None, options)
    if mask is not None and not _is_path(mask):
        person, source = _mask_array(mask, photo.rgb.shape[:2]), "the mask array"
    return photo, person, source, options


def _mask_array(mask, shape) -> np.ndarray:
    mask = np.asarray(mask)
    if mask.shape != shape or not (np.issubdtype(mask.dtype, np.floating) or mask.dtype == bool):
        raise InputError(f"the mask array must be ({shape[0]}, {shape[1]}) float or bool like the photo, "
                         f"got {mask.shape} {mask.dtype}", path="the mask array",
                         fix="pass one value in [0, 1] per pixel of the photo")
    return np.clip(np.nan_to_num(mask.astype(np.float32), nan=0.0), 0.0, 1.0)


def _environment(hdr, options: RelightOptions) -> np.ndarray:
    from relightcli.io.envmap import envmap_from_array, load_envmap

    if _is_path(hdr):
        return load_envmap(hdr, rotate_deg=options.rotate_deg, exposure_ev=options.exposure_ev)
    return envmap_from_array(hdr, rotate_deg=options.rotate_deg, exposure_ev=options.exposure_ev)


def _checked_threads(threads, cores: int) -> int:
    if threads is None:
        return cores
    if not isinstance(threads, int) or threads < 1:
        raise UsageError(f"threads must be a whole number >= 1, got {threads!r}", fix="pass e.g. threads=2")
    return min(threads, cores)


def _options(base: RelightOptions, given: dict) -> RelightOptions:
    """`base` with the options `given` by the CLI's names, each checked by the CLI's own rules."""
    from relightcli import cli

    names = {f.name for f in fields(RelightOptions)} - set(_NOT_OPTIONS) - {"threads"}
    names = (names - set(_RENAMED.values())) | set(_RENAMED)
    unknown = sorted(set(given) - names)
    if unknown:
        raise UsageError(f"unknown option(s) {', '.join(unknown)}", fix=f"choose from {', '.join(sorted(names))}")
    checks = {
        "outputs": lambda v: cli._outputs(v if isinstance(v, str) else ",".join(v)),
        "method": _choice(cli.METHODS), "albedo": _choice(cli.ALBEDO_SOURCES),
        "shadows": _choice(tuple(cli.SHADOW_STEP)), "background": cli._background,
        "spp": lambda v: None if v is None else cli.spp_value(_whole(v)),
        "target_error": lambda v: None if v is None else cli._positive_float(v),
        "seed": lambda v: cli.seed_value(_whole(v)),
        "resolution": lambda v: cli.int_in_range(*cli.RESOLUTION_RANGE)(_whole(v)),
        "max_pixels": lambda v: cli._positive_int(_whole(v)),
        "rotate": _finite, "exposure": _finite,
    }
    values = {}
    for name, value in given.items():
        try:
            values[_RENAMED.get(name, name)] = checks[name](value)
        except (argparse.ArgumentTypeError, TypeError, ValueError) as exc:
            raise UsageError(f"{name}={value!r}: {exc}", fix=f"see `relight --help` for --{name.replace('_', '-')}") from None
    options = replace(base, **values)
    if options.spp is not None and options.target_error is not None:
        raise UsageError("spp and target_error both set the ray-tracing effort", fix="pass one of them")
    return options


def _choice(allowed):
    def check(value):
        if value not in allowed:
            raise ValueError(f"choose from {', '.join(allowed)}")
        return value
    return check


def _whole(value) -> str:
    """An integer option's value as the CLI's parsers read it (a bool or a fraction refused)."""
    if isinstance(value, bool) or not float(value).is_integer():
        raise ValueError("must be a whole number")
    return str(int(value))


def _finite(value) -> float:
    value = float(value)
    if not np.isfinite(value):
        raise ValueError("must be finite")
    return value


__all__ = ["Relighter", "Result", "relight"]
