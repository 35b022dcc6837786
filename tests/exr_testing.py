"""OpenEXR files written byte by byte for the hostile-input tests: a data window, tile size or
channel count far larger than the display window, for a file of a few hundred KB.

OpenImageIO can write such a file, but it compresses every tile (half a GB of zeros takes
~12 s); here every chunk holds the same zlib stream of zeros, compressed once, so a file that
decodes to gigabytes is made in milliseconds. Layout (OpenEXR "technical introduction" and
"file layout"): magic, version, header attributes, a table of chunk offsets, the chunks.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

_HALF = 1
_ZIP = 3  # zlib, 16 scanlines per chunk for scanline files; one tile per chunk for tiled ones
_TILED = 0x200


def _attribute(name: str, kind: str, value: bytes) -> bytes:
    return name.encode() + b"\0" + kind.encode() + b"\0" + struct.pack("<i", len(value)) + value


def _box(x0: int, y0: int, x1: int, y1: int) -> bytes:
    return struct.pack("<4i", x0, y0, x1, y1)


def _channel_list(names) -> bytes:
    # name, pixel type, pLinear + 3 reserved bytes, x and y sampling; then an empty name
    return b"".join(name.encode() + b"\0" + struct.pack("<iB3xii", _HALF, 0, 1, 1)
                    for name in sorted(names)) + b"\0"


def _zip_payload(values: int, value: float) -> bytes:
    """A ZIP chunk of `values` half floats all equal to `value`: the bytes split into even and
    odd halves, then each byte stored as its difference to the previous + 128 (mod 256),
    then zlib (OpenEXR's ZIP compressor)."""
    raw = np.frombuffer(np.full(values, value, "<f2").tobytes(), np.uint8)
    split = np.concatenate([raw[0::2], raw[1::2]])
    deltas = np.concatenate([split[:1], (np.diff(split.astype(np.int16)) + 128) % 256])
    return zlib.compress(deltas.astype(np.uint8).tobytes(), 9)


def write_exr(path: Path, *, display: tuple[int, int], data: tuple[int, int, int, int],
              channels=("Y",), tile: int | None = None, value: float = 0.5) -> Path:
    """A half-float ZIP-compressed EXR whose pixels all hold `value`.

    display: (width, height) of the display window at (0, 0). data: (x0, y0, width, height) of
    the data window. tile: square tile size (a tiled file), or None (scanlines, 16 a chunk).
    """
    x0, y0, width, height = data
    header = b"".join([
        _attribute("channels", "chlist", _channel_list(channels)),
        _attribute("compression", "compression", bytes([_ZIP])),
        _attribute("dataWindow", "box2i", _box(x0, y0, x0 + width - 1, y0 + height - 1)),
        _attribute("displayWindow", "box2i", _box(0, 0, display[0] - 1, display[1] - 1)),
        _attribute("lineOrder", "lineOrder", b"\0"),
        _attribute("pixelAspectRatio", "float", struct.pack("<f", 1.0)),
        _attribute("screenWindowCenter", "v2f", struct.pack("<2f", 0.0, 0.0)),
        _attribute("screenWindowWidth", "float", struct.pack("<f", 1.0)),
    ])
    if tile is not None:  # one level, rounding down
        header += _attribute("tiles", "tiledesc", struct.pack("<IIB", tile, tile, 0))
    header += b"\0"
    if tile is None:
        chunks = [(struct.pack("<i", y0 + top), min(16, height - top) * width)
                  for top in range(0, height, 16)]
    else:
        chunks = [(struct.pack("<4i", tx, ty, 0, 0),
                   min(tile, width - tx * tile) * min(tile, height - ty * tile))
                  for ty in range(-(-height // tile)) for tx in range(-(-width // tile))]
    payloads: dict[int, bytes] = {}  # every chunk of a size holds the same bytes
    version = 2 | (_TILED if tile is not None else 0)
    start = 8 + len(header) + 8 * len(chunks)
    offsets, body = [], []
    for coordinates, pixels in chunks:
        if pixels not in payloads:
            payloads[pixels] = _zip_payload(pixels * len(channels), value)
        chunk = coordinates + struct.pack("<i", len(payloads[pixels])) + payloads[pixels]
        offsets.append(start)
        start += len(chunk)
        body.append(chunk)
    path = Path(path)
    with open(path, "wb") as out:
        out.write(struct.pack("<ii", 20000630, version) + header)
        out.write(struct.pack(f"<{len(offsets)}Q", *offsets))
        out.writelines(body)
    return path


def write_float_exr(path: Path, pixels) -> Path:
    """(H, W), (H, W, 3) or (H, W, 4) values written with OpenImageIO as float32, exactly as
    they are, NaN and Inf too: relightcli's own writer never writes those, a hostile input
    file must keep them."""
    import OpenImageIO as oiio

    pixels = np.asarray(pixels, np.float32)
    pixels = pixels[:, :, None] if pixels.ndim == 2 else pixels
    spec = oiio.ImageSpec(pixels.shape[1], pixels.shape[0], pixels.shape[2], oiio.FLOAT)
    if pixels.shape[2] == 1:
        spec.channelnames = ("Y",)
    output = oiio.ImageOutput.create(str(path))
    if not (output.open(str(path), spec) and output.write_image(np.ascontiguousarray(pixels))):
        raise OSError(f"{path}: {output.geterror()}")
    output.close()
    return Path(path)


def write_windowed_exr(path: Path, pixels: np.ndarray, data_origin: tuple[int, int],
                       display_size: tuple[int, int]) -> Path:
    """Float `pixels` (h, w, channels) as an EXR (through OpenImageIO) whose data window starts
    at `data_origin` (x, y) inside, across or outside a display window of `display_size`
    (width, height) at (0, 0)."""
    import OpenImageIO as oiio

    height, width, channels = pixels.shape
    spec = oiio.ImageSpec(width, height, channels, oiio.FLOAT)
    spec.x, spec.y = data_origin
    spec.full_x, spec.full_y = 0, 0
    spec.full_width, spec.full_height = display_size
    output = oiio.ImageOutput.create(str(path))
    output.open(str(path), spec)
    output.write_image(np.ascontiguousarray(pixels, dtype=np.float32))
    output.close()
    return path
