"""Fixtures that build bad and odd image files in tmp_path at test time (nothing committed)."""

from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest

from relightcli.io.images import write_image


def make_smooth_rgb(height: int = 48, width: int = 64) -> np.ndarray:
    """(H, W, 3) float32 linear ramps in [0.02, 0.9]: smooth, so JPEG keeps it close."""
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    rgb = np.stack([x / (width - 1), y / (height - 1), 0.5 + 0.4 * np.sin(x / 9.0)], axis=-1)
    return (0.02 + 0.88 * np.clip(rgb, 0.0, 1.0)).astype(np.float32)


def png_chunk(kind: bytes, data: bytes) -> bytes:
    """One PNG chunk: length, type, data, CRC-32 over type + data."""
    crc = zlib.crc32(kind + data) & 0xFFFFFFFF
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)


def png_header_only(width: int, height: int) -> bytes:
    """A valid-looking 8-bit RGB PNG of any claimed size whose pixel data is a few bytes."""
    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    tiny_pixels = zlib.compress(b"\x00" * 16)
    return (b"\x89PNG\r\n\x1a\n" + png_chunk(b"IHDR", header) + png_chunk(b"IDAT", tiny_pixels)
            + png_chunk(b"IEND", b""))


def _truncated(tmp_path, name: str):
    """A good image file of the given name, cut to half its bytes."""
    path = tmp_path / name
    write_image(path, make_smooth_rgb())
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return path


@pytest.fixture
def smooth_rgb():
    """Factory (height=48, width=64) -> smooth (H, W, 3) float32 linear test picture."""
    return make_smooth_rgb


BAD_INPUTS = {
    "missing": lambda tmp: tmp / "does_not_exist.png",
    "empty": lambda tmp: _write_bytes(tmp / "empty_file.jpg", b""),
    "text_as_jpeg": lambda tmp: _write_bytes(tmp / "notes_renamed.jpg",
                                             b"this is a text file, not a photo\n" * 20),
    "truncated_jpeg": lambda tmp: _truncated(tmp, "cut_photo.jpg"),
    "truncated_png": lambda tmp: _truncated(tmp, "cut_photo.png"),
    "truncated_exr": lambda tmp: _truncated(tmp, "cut_render.exr"),
    "truncated_hdr": lambda tmp: _truncated(tmp, "cut_light.hdr"),
    "directory": lambda tmp: _make_dir(tmp / "folder_not_image.png"),
}


def _write_bytes(path, data: bytes):
    path.write_bytes(data)
    return path


def _make_dir(path):
    path.mkdir()
    return path


@pytest.fixture(params=sorted(BAD_INPUTS))
def bad_input(request, tmp_path):
    """(kind, path) of one unreadable input file, made in tmp_path."""
    return request.param, BAD_INPUTS[request.param](tmp_path)


@pytest.fixture(params=sorted(kind for kind in BAD_INPUTS if not kind.startswith("truncated")))
def bad_header(request, tmp_path):
    """(kind, path) of one input whose header cannot be read (truncated files keep theirs)."""
    return request.param, BAD_INPUTS[request.param](tmp_path)


@pytest.fixture
def huge_header_png(tmp_path):
    """A PNG whose IHDR claims 40000 x 40000 pixels (1.6 gigapixels) in a 1 MB file.

    The padding after IEND gets the file past OpenImageIO's own plausibility check (it
    refuses a header claiming gigabytes from a few bytes), so the caller's limit is what
    stops it."""
    path = tmp_path / "claims_huge.png"
    path.write_bytes(png_header_only(40000, 40000) + bytes(1_000_000))
    return path


@pytest.fixture
def implausible_header_png(tmp_path):
    """A 68-byte PNG whose IHDR claims 40000 x 40000 pixels (4.8 GB decoded)."""
    path = tmp_path / "bomb.png"
    path.write_bytes(png_header_only(40000, 40000))
    return path


@pytest.fixture
def exif_jpeg(tmp_path):
    """Factory: orientation -> (path, stored (H, W, 3) uint8) of a 24x40 JPEG with that EXIF
    Orientation tag. The stored picture has a bright block in its top-left corner."""
    image_module = pytest.importorskip("PIL.Image")

    def make(orientation: int):
        stored = np.full((24, 40, 3), 40, dtype=np.uint8)
        stored[:8, :16] = (250, 200, 30)
        stored[16:, 30:] = (20, 60, 230)
        picture = image_module.fromarray(stored)
        exif = picture.getexif()
        exif[0x0112] = orientation
        path = tmp_path / f"rotated_{orientation}.jpg"
        picture.save(path, quality=98, exif=exif.tobytes(), subsampling=0)
        return path, stored

    return make


@pytest.fixture
def cmyk_jpeg(tmp_path):
    """(path, expected sRGB-encoded (H, W, 3) uint8) of a CMYK JPEG written by Pillow."""
    image_module = pytest.importorskip("PIL.Image")
    stored = np.zeros((16, 24, 3), dtype=np.uint8)
    stored[:, :8] = (200, 50, 10)
    stored[:, 8:16] = (30, 180, 90)
    stored[:, 16:] = (250, 250, 250)
    path = tmp_path / "print_ready_cmyk.jpg"
    image_module.fromarray(stored).convert("CMYK").save(path, quality=98, subsampling=0)
    return path, stored
