"""Image files in and out (OpenImageIO), and the project's one sRGB transfer pair.

Convention (../shared/DESIGN.md): every image in memory is float32, linear light, (H, W, 3)
(or (H, W) for masks), with alpha kept apart as a straight (unassociated) (H, W) mask in
[0, 1]. Integer files (JPEG, PNG, TIFF, WebP, 8 or 16 bit) hold sRGB-encoded values and are
decoded on read, encoded on write; EXR and HDR hold linear values. EXIF orientation is
applied on read, so row 0 is the top of the picture as a viewer sees it.

EXR files: the display window is the image. Pixels of the data window outside it are dropped,
display pixels the data window does not cover are 0 (black, and transparent when the file has
alpha); only the first subimage (part) at its full resolution (MIP level 0) is read, and only
the channels used (grey, R G B, alpha). The size limit (`max_pixels`) applies to everything
that is decoded: the display window, the data window and one tile.

Every failure becomes an `InputError` (reading), an `OutputError` (an output that cannot be
used, found before writing) or a `WriteError` (writing failed: disk full, ...) whose message
names the file and says what to do.
"""

from __future__ import annotations

import errno
import functools
import os
import re
import secrets
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from relightcli.errors import InputError, OutputError, RelightWarning, UsageError, WriteError

DEFAULT_MAX_PIXELS = 100_000_000

_FIX_UNREADABLE = "check that the file is a complete JPEG, PNG, TIFF, WebP, EXR or HDR image"
_RAISE_LIMIT = "raise the limit with --max-pixels"
_FIX_TOO_LARGE = f"downscale the image, or {_RAISE_LIMIT}"
_FIX_UNWRITABLE = "free some disk space, or choose another -o"
_OUTPUT_FORMATS = {".png": "png", ".jpg": "jpeg", ".jpeg": "jpeg", ".exr": "exr", ".hdr": "hdr"}


# --- sRGB transfer (IEC 61966-2-1) ------------------------------------------------------

# Relative luminance of linear sRGB (Rec. 709 primaries): the one set of weights the project uses.
LUMINANCE = np.array([0.2126, 0.7152, 0.0722], np.float32)


def srgb_to_linear(x):
    """Decode sRGB-encoded values to linear light.

    x: array of any shape, encoded values (nominally [0, 1]). Returns float32, same shape.
    Piecewise curve: x / 12.92 below 0.04045, ((x + 0.055) / 1.055) ** 2.4 above.
    """
    x = np.asarray(x, dtype=np.float32)
    low = x / np.float32(12.92)
    # clip the base at 0 so the power of the (unused) branch never sees a negative number
    high = (np.maximum(x, 0.04045) + np.float32(0.055)) / np.float32(1.055)
    return np.where(x <= 0.04045, low, high ** np.float32(2.4)).astype(np.float32)


def linear_to_srgb(x):
    """Encode linear light to sRGB; negatives are clipped to 0 (values above 1 pass through).

    x: array of any shape, linear values. Returns float32, same shape.
    Piecewise curve: 12.92 x below 0.0031308, 1.055 x ** (1 / 2.4) - 0.055 above.
    """
    x = np.maximum(np.asarray(x, dtype=np.float32), np.float32(0.0))
    low = x * np.float32(12.92)
    high = np.float32(1.055) * np.maximum(x, 0.0031308) ** np.float32(1.0 / 2.4) - np.float32(0.055)
    return np.where(x <= 0.0031308, low, high).astype(np.float32)


# --- full frames, a band of rows at a time ------------------------------------------------

# Rows per band. A 24-megapixel frame is 288 MB as float32 RGB; every whole-frame expression
# (a transfer curve, a composite) would allocate several such temporaries, a band of 256 rows
# of a 6000-pixel-wide frame only 18 MB each.
BAND_ROWS = 256


def row_bands(height: int, rows: int = BAND_ROWS) -> list[slice]:
    """Slices of at most `rows` rows that cover rows 0..height, top to bottom."""
    return [slice(top, min(top + rows, height)) for top in range(0, height, rows)]


# --- reading ------------------------------------------------------------------------------

@dataclass
class Image:
    """A decoded image.

    rgb: (H, W, 3) float32, linear light. Integer files give values in [0, 1]; float files
        (EXR, HDR, float TIFF) keep their values as stored, NaN and negatives included: the
        caller decides how to repair them.
    alpha: (H, W) float32 in [0, 1], straight (unassociated) alpha, or None.
    path: the file it came from.
    encoded: True when the file held sRGB-encoded integer data that was decoded.
    bits: bits per channel in the file (8, 16, or 32 / 16 for float / half).
    """

    rgb: np.ndarray
    alpha: np.ndarray | None
    path: str
    encoded: bool
    bits: int

    @property
    def height(self) -> int:
        return int(self.rgb.shape[0])

    @property
    def width(self) -> int:
        return int(self.rgb.shape[1])


def set_io_threads(n: int) -> None:
    """Set OpenImageIO's global worker thread count (0 = one per core)."""
    if int(n) != n or n < 0:
        raise UsageError(f"I/O thread count must be a whole number >= 0, got {n}",
                         fix="pass 0 for one thread per core")
    oiio.attribute("threads", int(n))


def _open_input(path: str | Path, max_pixels: int | None = None) -> oiio.ImageInput:
    """Open a file for reading (header only), or raise InputError naming what went wrong.
    `max_pixels`: when OpenImageIO refuses a header for its own size limit, report ours."""
    path = str(path)
    if not os.path.exists(path):
        raise InputError("file not found", path=path, fix="check the path")
    if os.path.isdir(path):
        raise InputError("is a directory, not an image file", path=path, fix="pass an image file")
    if not os.path.isfile(path):  # a FIFO would block the read, /dev/zero never end
        raise InputError("not a regular file (a pipe, device or socket)", path=path,
                         fix="pass an image file saved on disk")
    if not os.access(path, os.R_OK):
        raise InputError("permission denied", path=path,
                         fix="make the file readable (chmod a+r) or run as a user who may read it")
    if os.path.getsize(path) == 0:
        raise InputError("file is empty (0 bytes)", path=path, fix=_FIX_UNREADABLE)
    oiio.geterror()  # drop any stale global error so the message below is about this file
    config = oiio.ImageSpec()
    # keep PNG/TIFF alpha straight instead of letting OIIO premultiply it
    config.attribute("oiio:UnassociatedAlpha", 1)
    image_input = oiio.ImageInput.open(path, config)
    if image_input is None:
        reason = oiio.geterror() or "unknown error"
        _check_claimed_size(reason, path, max_pixels)
        raise InputError(f"not a readable image: {reason}", path=path, fix=_FIX_UNREADABLE)
    return image_input


def _check_claimed_size(reason: str, path: str, max_pixels: int | None) -> None:
    """OpenImageIO refuses a huge header before we see it ("Image claimed to be WxH, ...
    exceeds the N MB limit"): give the --max-pixels message when the size is over ours."""
    claimed = re.search(r"claimed to be (\d+)x(\d+)", reason)
    if claimed and max_pixels is not None:
        width, height = int(claimed.group(1)), int(claimed.group(2))
        _refuse_pixel_count(width, height, path, max_pixels)


def _oriented_size(spec: oiio.ImageSpec) -> tuple[int, int]:
    """(width, height) of the display window as seen after EXIF orientation."""
    width, height = spec.full_width or spec.width, spec.full_height or spec.height
    if spec.get_int_attribute("Orientation", 1) in (5, 6, 7, 8):
        return height, width
    return width, height


def image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) in pixels as `read_image` would return it, from the header only."""
    image_input = _open_input(path)
    try:
        return _oriented_size(image_input.spec())
    finally:
        image_input.close()


def check_decoded_size(spec: oiio.ImageSpec, path: str, max_pixels: int, *, what: str = "image",
                       fix: str = _FIX_TOO_LARGE, raise_limit: str | None = _RAISE_LIMIT) -> None:
    """Refuse, from the header, a file that would decode more than `max_pixels` pixels: its
    display window (the image), its data window (every stored pixel is decoded before the
    display window is cut out of it) or one tile (decoded whole, even for a small image).
    `what` names the file's role in messages, `fix` says what to do about a large image,
    `raise_limit` how to raise the limit (None: it cannot be). Raises InputError."""
    width, height = _oriented_size(spec)
    _refuse_pixel_count(width, height, path, max_pixels, what=what, fix=fix)
    full = f"{spec.full_width}x{spec.full_height}{spec.full_x:+d}{spec.full_y:+d}"
    or_raise = "" if raise_limit is None else f", or {raise_limit}"
    stored = spec.width * spec.height * max(spec.depth, 1)
    if stored > max_pixels:
        raise InputError(
            f"{what}'s data window (the pixels stored, all decoded) is {spec.width}x{spec.height} = "
            f"{stored} pixels, more than the limit of {max_pixels}, for a {width}x{height} image",
            path=path, fix=f"crop the data window to the display window, e.g. oiiotool {path} --crop "
                           f"{full} -o OUT{or_raise}")
    tile = spec.tile_width * spec.tile_height * max(spec.tile_depth, 1)
    if tile > max_pixels:
        raise InputError(
            f"{what} is stored in tiles of {spec.tile_width}x{spec.tile_height} = {tile} pixels, "
            f"more than the limit of {max_pixels} (each tile is decoded whole)", path=path,
            fix=f"save it as scanlines, e.g. oiiotool {path} --scanline -o OUT{or_raise}")


def _refuse_pixel_count(width: int, height: int, path: str, max_pixels: int, *,
                        what: str = "image", fix: str = _FIX_TOO_LARGE) -> None:
    if width * height > max_pixels:
        raise InputError(
            f"{what} is {width}x{height} = {width * height} pixels, more than the limit of "
            f"{max_pixels}", path=path, fix=fix)


def _stored_as_codes(spec: oiio.ImageSpec) -> bool:
    """8- or 16-bit integer channels, all of one type: read as stored, decoded by table."""
    return spec.format.basetype in (oiio.UINT8, oiio.UINT16) and not spec.channelformats


def _read_pixels(image_input: oiio.ImageInput, path: str, channels: list[int]) -> np.ndarray:
    """The data window of subimage 0, MIP level 0, as (H, W, C) holding `channels` (file
    channel indices) in that order: uint8 / uint16 codes as stored when `_stored_as_codes`, else
    float32 (other integers scaled to [0, 1]). Channels the image does not use (an EXR's
    render passes) are never decoded into memory."""
    spec = image_input.spec()
    fmt = spec.format if _stored_as_codes(spec) else oiio.FLOAT
    return read_channels(
        lambda first, stop: _checked(image_input.read_image(0, 0, first, stop, fmt), image_input, path),
        channels)


def read_channels(read, channels: list[int]) -> np.ndarray:
    """`channels` (file channel indices, in this order) as (H, W, C), from `read(first, stop)`:
    an OIIO read of the file's channels first..stop - 1 as (H, W, stop - first). One read of
    their span when it is at most 4 channels wide, else one read per channel: memory holds
    only the channels used, whatever lies between them."""
    first, stop = min(channels), max(channels) + 1
    if stop - first <= 4:
        pixels = read(first, stop)
        order = [c - first for c in channels]
        return pixels if order == list(range(pixels.shape[2])) else pixels[:, :, order]
    return np.concatenate([read(c, c + 1) for c in channels], axis=2)


def _checked(pixels, image_input: oiio.ImageInput, path: str) -> np.ndarray:
    """What an OIIO read returned, as (H, W, C); InputError when the read failed."""
    # JPEG reports a truncated stream only through has_error, with pixels returned
    if pixels is None or image_input.has_error:
        reason = image_input.geterror() or oiio.geterror() or "read failed"
        raise InputError(f"cannot decode pixels (truncated or corrupt?): {reason}",
                         path=path, fix=_FIX_UNREADABLE)
    pixels = np.asarray(pixels)
    return pixels[:, :, None] if pixels.ndim == 2 else pixels


def _to_display_window(pixels: np.ndarray, spec: oiio.ImageSpec) -> np.ndarray:
    """The display window of an EXR (the image) cut from its data window (the pixels stored):
    stored pixels outside it are dropped, display pixels with none stored are 0."""
    full_w, full_h = spec.full_width, spec.full_height
    if (spec.x, spec.y, spec.width, spec.height) == (spec.full_x, spec.full_y, full_w, full_h):
        return pixels
    canvas = np.zeros((full_h, full_w, pixels.shape[2]), dtype=pixels.dtype)
    x0, y0 = spec.x - spec.full_x, spec.y - spec.full_y
    cx0, cy0 = max(x0, 0), max(y0, 0)
    cx1, cy1 = min(x0 + spec.width, full_w), min(y0 + spec.height, full_h)
    if cx1 > cx0 and cy1 > cy0:
        canvas[cy0:cy1, cx0:cx1] = pixels[cy0 - y0:cy1 - y0, cx0 - x0:cx1 - x0]
    return canvas


def channel_layout(spec: oiio.ImageSpec, path: str) -> tuple[list[int], int | None]:
    """(the file's channel indices of R, G, B, the alpha channel's index or None) for gray,
    gray+alpha, RGB, RGBA or named R, G, B(, A) channels among more (gray: [0, 0, 0])."""
    names = [name.upper() for name in spec.channelnames]
    count = spec.nchannels
    if count == 1:
        return [0, 0, 0], None
    if count == 2:
        return [0, 0, 0], 1
    named_rgb = all(c in names for c in "RGB")
    if count in (3, 4) or named_rgb:
        rgb_index = [names.index(c) for c in "RGB"] if named_rgb else [0, 1, 2]
        alpha_index = spec.alpha_channel if spec.alpha_channel >= 0 else (3 if count == 4 else None)
        return rgb_index, alpha_index
    raise InputError(f"unsupported channel layout: {count} channels {spec.channelnames}",
                     path=path, fix="save the image as gray, RGB or RGBA")


def _read_rgb_alpha(image_input: oiio.ImageInput, path: str):
    """(rgb (H, W, 3), alpha (H, W) or None) of the display window, as `_read_pixels` decodes
    them (grey repeated into the three channels)."""
    spec = image_input.spec()
    rgb_index, alpha_index = channel_layout(spec, path)
    channels = list(dict.fromkeys(rgb_index + ([] if alpha_index is None else [alpha_index])))
    pixels = _to_display_window(_read_pixels(image_input, path, channels), spec)
    alpha = None if alpha_index is None else pixels[:, :, channels.index(alpha_index)]
    if len(set(rgb_index)) == 1:
        return np.repeat(pixels[:, :, :1], 3, axis=2), alpha
    return pixels[:, :, :3], alpha  # a view, no copy


def _apply_orientation(array: np.ndarray, orientation: int) -> np.ndarray:
    """Turn stored pixels (H, W, ...) into display orientation per EXIF tag 0x0112 (1..8)."""
    if orientation == 2:
        return array[:, ::-1]
    if orientation == 3:
        return array[::-1, ::-1]
    if orientation == 4:
        return array[::-1]
    if orientation == 5:
        return np.swapaxes(array, 0, 1)
    if orientation == 6:
        return np.rot90(array, k=-1)  # stored rotated 90 ccw: turn clockwise
    if orientation == 7:
        return np.swapaxes(array, 0, 1)[::-1, ::-1]
    if orientation == 8:
        return np.rot90(array, k=1)
    return array


@functools.lru_cache(maxsize=4)
def _decode_table(bits: int, srgb: bool) -> np.ndarray:
    """Every code of a `bits`-bit channel as float32: code * (1 / max), exactly the scaling
    OIIO applies when it converts integers to float, then sRGB-decoded when `srgb`."""
    top = (1 << bits) - 1
    values = np.arange(top + 1, dtype=np.float32) * np.float32(1.0 / top)
    table = srgb_to_linear(values) if srgb else values
    table.flags.writeable = False  # shared by every later read
    return table


def _decode_codes(codes: np.ndarray, srgb: bool) -> np.ndarray:
    """uint8 / uint16 codes (H, W[, C]) -> float32 values in [0, 1], linear when `srgb`.

    A table lookup, a band of rows at a time: the transfer curve on the whole frame would
    make several float frames of temporaries, and indexing with the whole frame would first
    turn every code into an 8-byte index."""
    table = _decode_table(codes.dtype.itemsize * 8, srgb)
    values = np.empty(codes.shape, np.float32)
    for rows in row_bands(codes.shape[0]):
        values[rows] = table[codes[rows]]
    return values


def _unpremultiply(rgb: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Straight colour from associated (premultiplied) colour; 0 where alpha is 0."""
    safe = np.where(alpha > 0, alpha, 1.0)[:, :, None]
    return np.where(alpha[:, :, None] > 0, rgb / safe, 0.0).astype(np.float32)


def _bits(spec: oiio.ImageSpec) -> int:
    return int(spec.format.size()) * 8


def _is_integer(spec: oiio.ImageSpec) -> bool:
    return spec.format.basetype not in (oiio.HALF, oiio.FLOAT, oiio.DOUBLE)


def refuse_non_finite(values: np.ndarray, path: str, what: str, fix: str) -> None:
    """Raise InputError naming `path` when `values` ((H, W[, C]) pixels) hold NaN or Inf, which
    float files (EXR, HDR, float TIFF) can store and no stage can use. `what` names the image
    ("the photo", "the mask"), `fix` what to do. Checked a band of rows at a time."""
    nan = inf = 0
    first = None
    for rows in row_bands(values.shape[0]):
        band = values[rows]
        nan += int(np.count_nonzero(np.isnan(band)))
        inf += int(np.count_nonzero(np.isinf(band)))
        if first is None and (nan or inf):
            row, column = np.argwhere(~np.isfinite(band))[0][:2]
            first = (rows.start + int(row), int(column))
    if first is not None:
        raise InputError(f"{what} holds {nan} NaN and {inf} Inf values (the first at row {first[0]}, "
                         f"column {first[1]})", path=path, fix=fix)


def image_from_array(array: np.ndarray, *, max_pixels: int = DEFAULT_MAX_PIXELS) -> Image:
    """An Image from pixels held in memory, read as `read_image` reads a file's: (H, W), (H, W,
    3) or (H, W, 4) (the fourth channel a straight alpha). uint8 / uint16 arrays are sRGB codes,
    decoded to linear as an 8/16-bit file is (alpha as data); float arrays are linear, as an EXR
    is. Raises InputError for another shape or dtype, or more than `max_pixels` pixels."""
    array = np.asarray(array)
    where = "the image array"
    if array.ndim == 2:
        array = array[:, :, None]
    if array.ndim != 3 or array.shape[2] not in (1, 3, 4) or 0 in array.shape:
        raise InputError(f"an image array must be (H, W), (H, W, 3) or (H, W, 4), got shape {array.shape}",
                         path=where, fix="pass grey, RGB or RGBA pixels")
    if array.dtype not in (np.uint8, np.uint16) and not np.issubdtype(array.dtype, np.floating):
        raise InputError(f"an image array must be uint8, uint16 or float, got {array.dtype}",
                         path=where, fix="pass sRGB codes as uint8/uint16 or linear values as float32")
    _refuse_pixel_count(array.shape[1], array.shape[0], where, max_pixels)
    channels = array.shape[2]
    rgb = np.repeat(array[..., :1], 3, axis=2) if channels == 1 else array[..., :3]
    alpha = array[..., 3] if channels == 4 else None
    encoded = array.dtype in (np.uint8, np.uint16)
    if encoded:
        rgb = _decode_codes(np.ascontiguousarray(rgb), srgb=True)
        alpha = None if alpha is None else _decode_codes(np.ascontiguousarray(alpha), srgb=False)
    else:
        rgb = np.array(rgb, dtype=np.float32)
        if alpha is not None:
            alpha = np.clip(np.nan_to_num(alpha.astype(np.float32), nan=0.0), 0.0, 1.0)
    return Image(rgb, alpha, where, encoded, array.dtype.itemsize * 8)


def read_image(path: str | Path, *, max_pixels: int = DEFAULT_MAX_PIXELS, srgb: bool = True) -> Image:
    """Read an image file into linear float32 RGB plus an optional straight alpha.

    Formats: JPEG (RGB, gray, CMYK), PNG (8/16 bit; gray, gray+alpha, RGB, RGBA), TIFF,
    WebP, EXR, HDR. What would be decoded (display window, data window, one tile:
    `check_decoded_size`) is checked against `max_pixels` from the header, before any pixel
    is decoded; an EXR's display window is the image (module docstring). srgb=False reads
    integer files as data (masks, AO: value / max, no transfer curve), the counterpart of
    write_image(..., srgb=False). Raises InputError for anything that cannot be read.
    """
    path = str(path)
    image_input = _open_input(path, max_pixels)
    try:
        spec = image_input.spec()
        check_decoded_size(spec, path, max_pixels)
        rgb, alpha = _read_rgb_alpha(image_input, path)
    finally:
        image_input.close()
    # Orientation first: on codes it moves 1 or 2 bytes per value instead of 4 (views, mostly).
    orientation = spec.get_int_attribute("Orientation", 1)
    rgb = _apply_orientation(rgb, orientation)
    alpha = None if alpha is None else _apply_orientation(alpha, orientation)
    encoded = _is_integer(spec)
    if rgb.dtype != np.float32:  # 8/16-bit codes (_stored_as_codes)
        rgb = _decode_codes(rgb, srgb)
        alpha = None if alpha is None else _decode_codes(alpha, srgb=False)
    else:
        if encoded and srgb:
            rgb = srgb_to_linear(rgb)
        if alpha is not None:
            alpha = np.clip(np.nan_to_num(alpha, nan=0.0), 0.0, 1.0).astype(np.float32)
    # OIIO flags data it hands back straight; anything else (EXR) is premultiplied
    if alpha is not None and spec.get_int_attribute("oiio:UnassociatedAlpha", 0) == 0:
        rgb = _unpremultiply(rgb, alpha)
    rgb = np.ascontiguousarray(rgb, dtype=np.float32)
    if alpha is not None:
        alpha = np.ascontiguousarray(alpha, dtype=np.float32)
    return Image(rgb=rgb, alpha=alpha, path=path, encoded=encoded, bits=_bits(spec))


# --- writing ------------------------------------------------------------------------------

def _output_format(path: str) -> str:
    extension = os.path.splitext(path)[1].lower()
    if extension not in _OUTPUT_FORMATS:
        raise OutputError(f"unsupported output format '{extension}'", path=path,
                          fix="use a .png, .jpg, .exr or .hdr file name")
    return _OUTPUT_FORMATS[extension]


def check_output_path(path: str | Path, *, overwrite: bool = True) -> None:
    """Refuse, before any work, an output file `write_image` could not write: a format it does
    not know (from the extension), a directory, an existing file without `overwrite`, a folder
    that does not exist or that this user may not write into. Raises OutputError."""
    path = str(path)
    if os.path.isdir(path):
        raise OutputError("is a directory", path=path, fix="give a file name, not a directory")
    _output_format(path)
    if not overwrite and os.path.lexists(path):
        raise OutputError("file exists", path=path, fix="pass --overwrite or choose another name")
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise OutputError("output folder does not exist", path=path, fix="create the folder first")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise OutputError("output folder is not writable", path=path,
                          fix="choose another output location with -o, or make the folder writable")


# Half floats (IEEE 754 binary16): the largest finite value, and the smallest normal one (below
# it a value keeps fewer than 11 significant bits, and below 2**-24 it becomes 0)
# zlib's level for PNG files. Measured on 8-bit photos (bench/whole_process.py's notes in
# docs/RESULTS.md): 640x425 / 962x640, OpenImageIO's default 6 took 0.085 / 0.186 s for 379 /
# 823 kB; 2 takes 0.028 / 0.085 s for 408 / 870 kB (2.2-3x faster, 6-8% larger); 1 is no
# faster, 3 and 4 gain 2% of size for 30% more time. (EXR: zip, the default, is both the
# smallest and among the fastest of zip, zips, piz, rle, pxr24.)
PNG_COMPRESSION = 2

HALF_MAX = 65504.0
HALF_MIN_NORMAL = 2.0 ** -14
# A half-float EXR must keep the values within this many stops of a layer's brightest as
# normal halves: darker ones are noise next to it
HALF_KEPT_STOPS = 10


def fits_half(array) -> bool:
    """True when a half-float EXR keeps `array` as float32 would, to half's precision: no
    finite value beyond +-HALF_MAX (it would become Inf) and the brightest value at least
    2**HALF_KEPT_STOPS x HALF_MIN_NORMAL, so that every value within HALF_KEPT_STOPS stops of
    it stays a normal half (a layer exposed far down, e.g. by --exposure -16, would round to
    a few subnormal steps or to 0). Non-finite values are not counted (`write_image` repairs
    them). array: any shape, (H, ...) checked a band of rows at a time."""
    array = np.asarray(array)
    if array.size == 0:
        return True
    top = 0.0
    for rows in row_bands(array.shape[0]):
        band = np.abs(array[rows])
        finite = band[np.isfinite(band)]
        if finite.size:
            top = max(top, float(finite.max()))
    return top <= HALF_MAX and (top == 0.0 or top >= HALF_MIN_NORMAL * 2.0 ** HALF_KEPT_STOPS)


def _repair_non_finite(array: np.ndarray, path: str, what: str) -> np.ndarray:
    """`array` with NaN set to 0 and +-Inf to the largest finite magnitude in it (0 if none),
    with a RelightWarning counting them; `array` itself when all its values are finite."""
    bad = sum(int(np.count_nonzero(~np.isfinite(array[rows]))) for rows in row_bands(array.shape[0]))
    if bad == 0:
        return array
    finite = np.isfinite(array)
    largest = float(np.abs(array[finite]).max()) if finite.any() else 0.0
    nan, inf = int(np.count_nonzero(np.isnan(array))), int(np.count_nonzero(np.isinf(array)))
    warnings.warn(f"{path}: the {what} to write had {nan} NaN and {inf} Inf values; wrote NaN "
                  f"as 0 and Inf as the largest finite value ({largest:g})",
                  RelightWarning, stacklevel=3)
    repaired = np.nan_to_num(array, nan=0.0, posinf=largest, neginf=-largest)
    return repaired.astype(np.float32, copy=False)


def _check_arrays(rgb, alpha, path: str):
    """rgb as (H, W, 3) or (H, W) float32, alpha as (H, W) float32 or None (NaN and values
    outside [0, 1] are repaired where the format needs it: _quantize, the EXR branch)."""
    rgb = np.asarray(rgb, dtype=np.float32)
    if rgb.ndim == 3 and rgb.shape[2] == 1:
        rgb = rgb[:, :, 0]
    if not (rgb.ndim == 2 or (rgb.ndim == 3 and rgb.shape[2] == 3)) or 0 in rgb.shape[:2]:
        raise ValueError(f"{path}: image to write must be (H, W, 3) or (H, W), got {rgb.shape}")
    if alpha is not None:
        alpha = np.asarray(alpha, dtype=np.float32)
        if alpha.shape != rgb.shape[:2]:
            raise ValueError(f"{path}: alpha must be {rgb.shape[:2]}, got {alpha.shape}")
    return rgb, alpha


def _quantize(encoded: np.ndarray, bits: int) -> np.ndarray:
    """Encoded values in [0, 1] (NaN -> 0) to uint8 / uint16, rounding to nearest."""
    top = (1 << bits) - 1
    values = np.clip(np.nan_to_num(encoded, nan=0.0), 0.0, 1.0) * top + 0.5
    return np.floor(values).astype(np.uint8 if bits == 8 else np.uint16)


def _channels(rgb: np.ndarray, alpha: np.ndarray | None) -> np.ndarray:
    """(H, W, C) stack of colour (1 or 3 channels) and alpha (0 or 1 channel)."""
    colour = rgb[:, :, None] if rgb.ndim == 2 else rgb
    return colour if alpha is None else np.concatenate([colour, alpha[:, :, None]], axis=2)


def _encode_pixels(fmt: str, rgb, alpha, bits, quality: int, half: bool, srgb: bool):
    """(pixels (H, W, C), ImageSpec) ready for OIIO, per the output format's conventions."""
    if fmt in ("png", "jpeg"):
        bits = 8 if bits is None or fmt == "jpeg" else bits
        keep_alpha = alpha if fmt == "png" else None  # JPEG has no alpha
        channels = (1 if rgb.ndim == 2 else 3) + (keep_alpha is not None)
        pixels = np.empty(rgb.shape[:2] + (channels,), np.uint8 if bits == 8 else np.uint16)
        for rows in row_bands(rgb.shape[0]):  # float temporaries a band's size, not the frame's
            values = linear_to_srgb(rgb[rows]) if srgb else rgb[rows]
            pixels[rows] = _quantize(_channels(values, None if keep_alpha is None else keep_alpha[rows]), bits)
        spec = oiio.ImageSpec(rgb.shape[1], rgb.shape[0], pixels.shape[2],
                              oiio.UINT8 if bits == 8 else oiio.UINT16)
        spec.attribute("oiio:UnassociatedAlpha", 1)
        if fmt == "png":
            spec.attribute("png:compressionLevel", PNG_COMPRESSION)
        if fmt == "jpeg":
            spec.attribute("Compression", f"jpeg:{int(quality)}")
        return pixels, spec
    if fmt == "hdr":
        colour = np.repeat(rgb[:, :, None], 3, axis=2) if rgb.ndim == 2 else rgb
        spec = oiio.ImageSpec(rgb.shape[1], rgb.shape[0], 3, oiio.FLOAT)
        return np.ascontiguousarray(colour), spec
    # EXR stores associated (premultiplied) alpha by convention
    alpha = None if alpha is None else np.clip(np.nan_to_num(alpha, nan=0.0), 0.0, 1.0)
    colour = rgb if alpha is None else rgb * (alpha if rgb.ndim == 2 else alpha[:, :, None])
    pixels = _channels(colour, alpha)
    spec = oiio.ImageSpec(rgb.shape[1], rgb.shape[0], pixels.shape[2],
                          oiio.HALF if half and fits_half(colour) else oiio.FLOAT)
    if pixels.shape[2] == 1:
        spec.channelnames = ("Y",)
    elif pixels.shape[2] == 2:
        spec.channelnames = ("Y", "A")
    return np.ascontiguousarray(pixels, dtype=np.float32), spec


def _write_pixels(path: str, pixels: np.ndarray, spec: oiio.ImageSpec) -> str | None:
    """Write pixels to `path` with OIIO; returns None on success, else OIIO's error text.
    No time stamp: OpenEXR and TIFF writers add the time of writing as DateTime unless it is
    set (empty drops it), and the same pixels must give the same bytes."""
    oiio.geterror()
    spec.attribute("DateTime", "")
    image_output = oiio.ImageOutput.create(path)
    if image_output is None:
        return oiio.geterror() or "no writer for this format"
    try:
        if not image_output.open(path, spec):
            return image_output.geterror() or oiio.geterror() or "cannot open for writing"
        if not image_output.write_image(pixels):
            return image_output.geterror() or "write failed"
    finally:
        image_output.close()
    return image_output.geterror() or None


def _temporary_path(path: str) -> str:
    """Create an empty, unique temporary file next to `path`, with the same extension."""
    directory, name = os.path.split(os.path.abspath(path))
    extension = os.path.splitext(name)[1]
    while True:
        temporary = os.path.join(directory, f".{name}.tmp-{secrets.token_hex(4)}{extension}")
        try:
            # 0o666 under the umask: the final file gets the permissions a plain open() gives
            os.close(os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
            return temporary
        except FileExistsError:
            continue


def write_image(path: str | Path, rgb, alpha=None, *, bits: int | None = None,
                quality: int = 95, half: bool = True, overwrite: bool = True,
                srgb: bool = True) -> None:
    """Write linear float RGB (or a gray map) to an image file, atomically.

    rgb: (H, W, 3) or (H, W) float, linear light. alpha: (H, W) straight alpha in [0, 1] or
    None. The format comes from the extension: .png (8 or 16 `bits`, default 8, sRGB-encoded,
    alpha kept), .jpg/.jpeg (8-bit sRGB at `quality`, alpha dropped), .exr (linear,
    premultiplied alpha as the format expects; `half`: half floats where `fits_half` says they
    keep the values, else float32; False: float32), .hdr (linear RGBE, alpha dropped).
    NaN and Inf are never written: NaN becomes 0 and +-Inf the largest finite magnitude, with
    a RelightWarning.
    `srgb=False` stores data maps (masks, AO) in PNG/JPEG as they are, without the transfer
    curve (values clipped to [0, 1]); `read_image` will still decode them as sRGB, so a reader
    of such a file undoes that with `linear_to_srgb`.
    The file appears complete or not at all: pixels go to a temporary file in the same
    directory, then replace `path`. Raises OutputError for an output that cannot be used
    (`check_output_path`), WriteError when writing fails (disk full, ...), each naming `path`.
    """
    path = str(path)
    fmt = _output_format(path)
    if fmt == "png" and bits not in (None, 8, 16):
        raise UsageError(f"PNG bit depth must be 8 or 16, got {bits}", path=path,
                         fix="write 8 or 16 bits, or use .exr for float")
    rgb, alpha = _check_arrays(rgb, alpha, path)
    check_output_path(path, overwrite=overwrite)
    rgb = _repair_non_finite(rgb, path, "image")
    pixels, spec = _encode_pixels(fmt, rgb, alpha, bits, quality, half, srgb)
    try:
        temporary = _temporary_path(path)
    except OSError as error:
        if error.errno in _FULL:
            raise _write_error(path, error.strerror) from error
        raise OutputError(f"directory not writable: {error.strerror}", path=path,
                          fix="choose another output location with -o") from error
    try:
        failure = _write_pixels(temporary, pixels, spec) or _unreadable_reason(temporary)
        if failure is not None:
            raise _write_error(path, _refusal_reason(temporary) or failure)
        os.replace(temporary, path)
    except OSError as error:
        raise _write_error(path, error.strerror or str(error)) from error
    finally:
        if os.path.exists(temporary):
            os.remove(temporary)


# The file system is full, or this user's share of it: the fix is space, not another option
_FULL = (errno.ENOSPC, errno.EDQUOT)


def _write_error(path: str, reason: str) -> WriteError:
    """The error for a write that failed part-way: the plain reason (its first line, lower
    case: "no space left on device"), the output's own path."""
    reason = reason.strip().splitlines()[0] if reason.strip() else "unknown error"
    return WriteError(f"cannot write the output: {reason[:1].lower()}{reason[1:]}", path=path,
                      fix=_FIX_UNWRITABLE)


def _unreadable_reason(path: str) -> str | None:
    """None when the file just written decodes whole (every scanline, a band at a time, as
    stored), else why not. A codec's last bytes can wait in a buffer until the file is closed,
    and OIIO does not check that close: on a full disk a small PNG is cut short while its
    write reports success."""
    image_input = oiio.ImageInput.open(path)
    if image_input is None:
        return oiio.geterror() or "the file written cannot be read back"
    try:
        spec = image_input.spec()
        for rows in row_bands(spec.height):
            pixels = image_input.read_scanlines(0, 0, spec.y + rows.start, spec.y + rows.stop, 0, 0,
                                                spec.nchannels, spec.format)
            if pixels is None or image_input.has_error:
                return image_input.geterror() or "the file written is incomplete"
    finally:
        image_input.close()
    return None


def _refusal_reason(temporary: str) -> str | None:
    """Why the file system refused a write OIIO reported as failed (its own text is a codec's,
    e.g. libpng's "Write error at position ..."): the OS's reason for refusing 1 MiB more to
    the same file (ENOSPC "No space left on device", EDQUOT, EFBIG, EIO), or None when the
    file system takes it (the failure was the codec's own)."""
    try:
        handle = os.open(temporary, os.O_WRONLY | os.O_APPEND)
        try:
            os.write(handle, bytes(1 << 20))
            os.fsync(handle)
        finally:
            os.close(handle)
    except OSError as error:
        return error.strerror
    return None
