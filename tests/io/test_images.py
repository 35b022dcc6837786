"""Image I/O: sRGB transfer, round trips per format, orientation, and bad inputs/outputs."""

from __future__ import annotations

import errno
import os
import time
import tracemalloc
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest

from exr_testing import write_exr, write_float_exr, write_windowed_exr
from relightcli.errors import InputError, OutputError, RelightWarning, UsageError, WriteError
from relightcli.io import images
from relightcli.io.images import (
    image_size,
    linear_to_srgb,
    read_image,
    srgb_to_linear,
    write_image,
)


DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"
PHOTOS = ["coco_000000000785_skier.jpg", "coco_000000000785_skier_mask.png",
          "nasa_apollo11_aldrin_fullbody.png", "pexels_woman_with_dog.jpg"]
HDRIS = ["forest_slope_1k.hdr", "dikhololo_night_1k.hdr"]


def shared_file(*parts):
    path = DATA.joinpath(*parts)
    if not path.is_file():
        pytest.skip(f"shared data file missing: {path}")
    return path


def srgb_decode_reference(x):
    """IEC 61966-2-1 decoding in float64, written out independently of the module."""
    x = np.asarray(x, dtype=np.float64)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def listing(directory):
    return sorted(os.listdir(directory))


# --- sRGB transfer ------------------------------------------------------------------------

@pytest.mark.parametrize("encoded, linear", [(0.0, 0.0), (1.0, 1.0), (0.5, 0.21404114),
                                             (0.04045, 0.0031308), (128 / 255, 0.21586050)])
def test_srgb_to_linear_known_values(encoded, linear):
    assert srgb_to_linear(np.float32(encoded)) == pytest.approx(linear, abs=2e-7)


def test_srgb_to_linear_matches_float64_reference_everywhere():
    x = np.linspace(0.0, 1.0, 10001, dtype=np.float32)
    np.testing.assert_allclose(srgb_to_linear(x), srgb_decode_reference(x), rtol=2e-6, atol=1e-8)


def test_srgb_pair_round_trips():
    linear = np.linspace(0.0, 1.0, 10001, dtype=np.float32)
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(linear)), linear,
                               rtol=1e-5, atol=1e-7)


def test_linear_to_srgb_clips_negatives_and_keeps_dtype():
    out = linear_to_srgb(np.array([-1.0, -1e-6, 0.0], dtype=np.float64))
    assert out.dtype == np.float32
    np.testing.assert_array_equal(out, 0.0)


# --- round trips --------------------------------------------------------------------------

@pytest.mark.parametrize("name, options, tolerance", [
    ("eight.png", {}, 0.5 / 255),                # half an 8-bit step in encoded values
    ("sixteen.png", {"bits": 16}, 0.5 / 65535),
    ("half.exr", {"half": True}, 2.0**-11),      # relative: 10-bit mantissa, rounded
    ("float.exr", {"half": False}, 0.0),
])
def test_lossless_round_trip(tmp_path, name, options, tolerance, smooth_rgb):
    rgb = smooth_rgb()
    write_image(tmp_path / name, rgb, **options)
    image = read_image(tmp_path / name)
    assert image.rgb.shape == rgb.shape and image.rgb.dtype == np.float32
    if image.encoded:
        error = np.abs(linear_to_srgb(image.rgb) - linear_to_srgb(rgb)).max()
        assert error <= tolerance + 1e-6
    else:
        np.testing.assert_allclose(image.rgb, rgb, rtol=tolerance, atol=0.0)
    assert listing(tmp_path) == [name]  # no temporary file left behind


def test_jpeg_round_trip_is_close(tmp_path, smooth_rgb):
    rgb = smooth_rgb()
    write_image(tmp_path / "photo.jpg", rgb, quality=95)
    encoded_error = np.abs(linear_to_srgb(read_image(tmp_path / "photo.jpg").rgb)
                           - linear_to_srgb(rgb))
    # 4:2:0 chroma subsampling costs a few steps at colour edges; the mean stays ~1 step
    assert encoded_error.mean() <= 1.5 / 255
    assert encoded_error.max() <= 16 / 255


def test_jpeg_quality_is_applied(tmp_path, smooth_rgb):
    rgb = smooth_rgb(96, 128)
    write_image(tmp_path / "low.jpg", rgb, quality=20)
    write_image(tmp_path / "high.jpg", rgb, quality=98)
    assert (tmp_path / "low.jpg").stat().st_size < 0.7 * (tmp_path / "high.jpg").stat().st_size


def test_hdr_round_trip_within_shared_exponent_step(tmp_path, smooth_rgb):
    rgb = smooth_rgb() * np.float32(40.0)  # radiance above 1 is the point of .hdr
    write_image(tmp_path / "radiance.hdr", rgb)
    image = read_image(tmp_path / "radiance.hdr")
    # RGBE: 8-bit mantissas share the exponent of the largest channel, so each channel is
    # within one step, max(r, g, b) / 128, of the original
    step = rgb.max(axis=-1, keepdims=True) / 128.0
    assert (np.abs(image.rgb - rgb) <= step).all()
    assert listing(tmp_path) == ["radiance.hdr"]


@pytest.mark.parametrize("name, encoded, bits", [("a.png", True, 8), ("b.jpg", True, 8),
                                                 ("c.exr", False, 16), ("d.hdr", False, 32)])
def test_read_reports_encoding_and_bits(tmp_path, name, encoded, bits, smooth_rgb):
    write_image(tmp_path / name, smooth_rgb(8, 8))
    image = read_image(tmp_path / name)
    assert (image.encoded, image.bits, image.path) == (encoded, bits, str(tmp_path / name))


@pytest.mark.parametrize("bits, step", [(8, 1.0 / 255), (16, 1.0 / 65535)])
def test_png_rgba_round_trip_keeps_straight_alpha(tmp_path, bits, step, smooth_rgb):
    rgb = smooth_rgb(16, 20)
    alpha = np.tile(np.linspace(0.05, 1.0, 20, dtype=np.float32), (16, 1))
    write_image(tmp_path / "straight.png", rgb, alpha, bits=bits)
    image = read_image(tmp_path / "straight.png")
    np.testing.assert_allclose(image.alpha, alpha, atol=step / 2 + 1e-6)
    # straight alpha: colour keeps full precision where alpha is partial
    encoded_error = np.abs(linear_to_srgb(image.rgb) - linear_to_srgb(rgb)).max()
    assert encoded_error <= step / 2 + 1e-6


def test_exr_rgba_round_trip_unpremultiplies(tmp_path, smooth_rgb):
    rgb = smooth_rgb(16, 20)
    alpha = np.tile(np.linspace(0.05, 1.0, 20, dtype=np.float32), (16, 1))
    write_image(tmp_path / "straight.exr", rgb, alpha, half=False)
    stored = oiio.ImageInput.open(str(tmp_path / "straight.exr")).read_image(oiio.FLOAT)
    np.testing.assert_allclose(stored[..., :3], rgb * alpha[:, :, None], rtol=1e-6)
    image = read_image(tmp_path / "straight.exr")
    np.testing.assert_allclose(image.alpha, alpha, rtol=1e-7)
    np.testing.assert_allclose(image.rgb, rgb, rtol=1e-6)


@pytest.mark.parametrize("name, tolerance", [("mask_alpha.png", 1.0 / 255),
                                             ("mask_alpha.exr", 2e-3)])
def test_gray_with_alpha_round_trips(tmp_path, name, tolerance):
    gray = np.tile(np.linspace(0.1, 0.9, 12, dtype=np.float32), (5, 1))
    alpha = gray[:, ::-1].copy()
    write_image(tmp_path / name, gray, alpha)
    image = read_image(tmp_path / name)
    np.testing.assert_allclose(image.alpha, alpha, atol=tolerance)
    np.testing.assert_allclose(linear_to_srgb(image.rgb), linear_to_srgb(gray)[:, :, None]
                               .repeat(3, axis=2), atol=tolerance / alpha.min())


def test_png_bit_depth_other_than_8_or_16_is_refused(tmp_path, smooth_rgb):
    with pytest.raises(UsageError, match="deep.png"):
        write_image(tmp_path / "deep.png", smooth_rgb(4, 4), bits=12)
    assert listing(tmp_path) == []


@pytest.mark.parametrize("bits, top", [(8, 255), (16, 65535)])
def test_data_map_is_stored_without_transfer_curve(tmp_path, bits, top):
    mask = np.array([[0.0, 0.25, 0.5, 1.0]], dtype=np.float32)
    write_image(tmp_path / "mask.png", mask, bits=bits, srgb=False)
    stored = oiio.ImageInput.open(str(tmp_path / "mask.png")).read_image(oiio.FLOAT)
    np.testing.assert_array_equal(np.round(stored[..., 0] * top), np.floor(mask * top + 0.5))
    image = read_image(tmp_path / "mask.png")
    np.testing.assert_allclose(linear_to_srgb(image.rgb[..., 0]), mask, atol=0.5 / top + 1e-6)


def test_png_with_alpha_is_stored_unpremultiplied(tmp_path):
    pil_image = pytest.importorskip("PIL.Image")
    write_image(tmp_path / "half_alpha.png", np.full((4, 4, 3), 1.0, np.float32),
                np.full((4, 4), 0.5, np.float32))
    stored = np.asarray(pil_image.open(tmp_path / "half_alpha.png"))
    assert stored.shape == (4, 4, 4)
    np.testing.assert_array_equal(stored[..., :3], 255)
    np.testing.assert_array_equal(stored[..., 3], 128)


def test_sixteen_bit_precision_is_kept(tmp_path):
    ramp = np.tile(np.linspace(0.0, 1.0, 4096, dtype=np.float32), (2, 1))
    write_image(tmp_path / "ramp16.png", ramp, bits=16)
    image = read_image(tmp_path / "ramp16.png")
    assert image.bits == 16
    assert len(np.unique(image.rgb[..., 0])) > 256


@pytest.mark.parametrize("bits, srgb", [(8, True), (8, False), (16, True), (16, False)])
def test_every_integer_code_decodes_as_through_float(tmp_path, bits, srgb):
    # 8/16-bit files are decoded by a table of every code; it must give what OIIO's conversion
    # to float followed by the transfer curve gives.
    codes = np.arange(1 << bits).astype(np.uint8 if bits == 8 else np.uint16).reshape(-1, 256)
    path = str(tmp_path / "codes.png")
    output = oiio.ImageOutput.create(path)
    output.open(path, oiio.ImageSpec(256, codes.shape[0], 1, oiio.UINT8 if bits == 8 else oiio.UINT16))
    output.write_image(codes)
    output.close()
    as_float = oiio.ImageInput.open(path).read_image(oiio.FLOAT)[:, :, 0]
    expected = srgb_to_linear(as_float) if srgb else as_float
    np.testing.assert_array_equal(read_image(path, srgb=srgb).rgb[:, :, 0], expected)


def traced_peak(action) -> int:
    """Peak bytes allocated through Python and numpy while action() runs."""
    tracemalloc.start()
    try:
        action()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


# Issue "End to end": a 24 MP photo must relight in 1.5 GB, where one float32 RGB frame is
# 288 MB. Decoding or encoding a whole frame at once took 5-6 frames of float temporaries.
def test_writing_a_large_frame_makes_no_frame_sized_float_temporaries(tmp_path):
    rgb = np.full((16 * images.BAND_ROWS, 256, 3), 0.5, np.float32)
    peak = traced_peak(lambda: write_image(tmp_path / "large.png", rgb))
    assert peak < rgb.nbytes  # the uint8 pixels (a quarter) and band-sized temporaries


def test_reading_a_large_frame_makes_no_frame_sized_float_temporaries(tmp_path):
    write_image(tmp_path / "large.png", np.full((16 * images.BAND_ROWS, 256, 3), 0.5, np.float32))
    frame_bytes = 16 * images.BAND_ROWS * 256 * 3 * 4
    peak = traced_peak(lambda: read_image(tmp_path / "large.png"))
    assert peak < 2 * frame_bytes  # the float result, the 8-bit codes, band-sized temporaries


def test_gray_map_writes_one_channel_and_reads_as_three_equal(tmp_path):
    gray = np.tile(np.linspace(0.0, 1.0, 30, dtype=np.float32), (10, 1))
    write_image(tmp_path / "ao.png", gray)
    assert oiio.ImageInput.open(str(tmp_path / "ao.png")).spec().nchannels == 1
    image = read_image(tmp_path / "ao.png")
    assert image.rgb.shape == (10, 30, 3) and image.alpha is None
    np.testing.assert_array_equal(image.rgb[..., 0], image.rgb[..., 1])
    np.testing.assert_array_equal(image.rgb[..., 0], image.rgb[..., 2])
    np.testing.assert_allclose(linear_to_srgb(image.rgb[..., 0]), linear_to_srgb(gray),
                               atol=0.5 / 255 + 1e-6)


def test_gray_alpha_png_reads_as_gray_rgb_and_alpha(tmp_path):
    pil_image = pytest.importorskip("PIL.Image")
    stored = np.zeros((6, 9, 2), dtype=np.uint8)
    stored[..., 0] = 128
    stored[..., 1] = np.arange(9) * 30
    pil_image.fromarray(stored, mode="LA").save(tmp_path / "gray_alpha.png")
    image = read_image(tmp_path / "gray_alpha.png")
    np.testing.assert_allclose(image.rgb, 0.2158605, atol=1e-6)
    np.testing.assert_allclose(image.alpha, stored[..., 1] / 255.0, atol=1e-6)


def test_one_by_one_image_reads(tmp_path):
    write_image(tmp_path / "dot.png", np.full((1, 1, 3), 0.21404114, np.float32))
    image = read_image(tmp_path / "dot.png")
    assert image.rgb.shape == (1, 1, 3)
    np.testing.assert_allclose(image.rgb, 0.21586050, atol=1e-6)  # 0.5 encoded -> 128/255


def test_photo_with_nan_reads_without_crashing(tmp_path, smooth_rgb):
    rgb = smooth_rgb(8, 8)
    rgb[3, 4] = np.nan
    write_float_exr(tmp_path / "nan_photo.exr", rgb)  # write_image would write the NaN as 0
    image = read_image(tmp_path / "nan_photo.exr")
    assert np.isnan(image.rgb[3, 4]).all()
    assert np.isfinite(np.delete(image.rgb.reshape(-1, 3), 3 * 8 + 4, axis=0)).all()


def test_exr_data_window_is_placed_in_display_window(tmp_path):
    path = str(tmp_path / "windowed.exr")
    spec = oiio.ImageSpec(3, 2, 3, oiio.FLOAT)
    spec.x, spec.y = 4, 1
    spec.full_x, spec.full_y, spec.full_width, spec.full_height = 0, 0, 8, 5
    output = oiio.ImageOutput.create(path)
    output.open(path, spec)
    output.write_image(np.full((2, 3, 3), 0.7, np.float32))
    output.close()
    image = read_image(path)
    expected = np.zeros((5, 8, 3), np.float32)
    expected[1:3, 4:7] = 0.7
    np.testing.assert_array_equal(image.rgb, expected)


def test_sixteen_bit_tiff_reads_and_decodes(tmp_path):
    path = str(tmp_path / "scan16.tif")
    stored = np.tile(np.arange(0, 65536, 64, dtype=np.uint16), (2, 1))  # 1024 levels
    stored = np.repeat(stored[:, :, None], 3, axis=2)
    output = oiio.ImageOutput.create(path)
    output.open(path, oiio.ImageSpec(1024, 2, 3, oiio.UINT16))
    output.write_image(stored)
    output.close()
    image = read_image(path)
    assert (image.encoded, image.bits) == (True, 16)
    np.testing.assert_allclose(image.rgb, srgb_decode_reference(stored / 65535.0), atol=1e-6)


def test_lossless_webp_with_alpha_reads(tmp_path):
    pil_image = pytest.importorskip("PIL.Image")
    stored = np.zeros((6, 8, 4), dtype=np.uint8)
    stored[..., :3] = (200, 100, 30)
    stored[..., 3] = np.arange(8) * 32 + 10
    pil_image.fromarray(stored, mode="RGBA").save(tmp_path / "sticker.webp", lossless=True)
    image = read_image(tmp_path / "sticker.webp")
    np.testing.assert_allclose(image.rgb, srgb_decode_reference(stored[..., :3] / 255.0),
                               atol=1e-6)
    np.testing.assert_allclose(image.alpha, stored[..., 3] / 255.0, atol=1e-6)


def test_cmyk_jpeg_reads_as_plausible_rgb(cmyk_jpeg):
    path, expected = cmyk_jpeg
    image = read_image(path)
    assert image.rgb.shape == expected.shape
    encoded = np.round(linear_to_srgb(image.rgb) * 255.0)
    assert np.abs(encoded - expected).max() <= 4


@pytest.mark.parametrize("orientation", range(1, 9))
def test_exif_orientation_matches_pillow(exif_jpeg, orientation):
    pil_image = pytest.importorskip("PIL.Image")
    pil_ops = pytest.importorskip("PIL.ImageOps")
    path, _ = exif_jpeg(orientation)
    reference = np.asarray(pil_ops.exif_transpose(pil_image.open(path)), dtype=np.float32)
    image = read_image(path)
    assert image.rgb.shape == reference.shape
    encoded = linear_to_srgb(image.rgb) * 255.0
    assert np.abs(encoded - reference).max() <= 3.0
    assert image_size(path) == (reference.shape[1], reference.shape[0])


def test_exif_orientation_6_puts_top_left_block_top_right(exif_jpeg):
    path, stored = exif_jpeg(6)  # stored 24x40; displayed turned 90 degrees clockwise
    image = read_image(path)
    assert image.rgb.shape == (40, 24, 3)
    bright = linear_to_srgb(image.rgb[..., 0]) > 0.9
    rows, cols = np.nonzero(bright)
    # stored rows 0..7, cols 0..15 -> displayed rows 0..15, cols 16..23
    assert (rows.min(), rows.max(), cols.min(), cols.max()) == (0, 15, 16, 23)


def test_image_size_reads_header(tmp_path):
    write_image(tmp_path / "wide.exr", np.zeros((7, 13, 3), np.float32))
    assert image_size(tmp_path / "wide.exr") == (13, 7)


def test_set_io_threads_sets_oiio_attribute():
    before = oiio.get_int_attribute("threads")
    try:
        images.set_io_threads(3)
        assert oiio.get_int_attribute("threads") == 3
    finally:
        oiio.attribute("threads", before)


# --- bad inputs ---------------------------------------------------------------------------

def test_bad_input_raises_input_error_naming_file(bad_input, tmp_path):
    kind, path = bad_input
    before = listing(tmp_path)
    with pytest.raises(InputError) as caught:
        read_image(path)
    assert path.name in str(caught.value), kind
    assert caught.value.path == str(path)
    assert caught.value.fix
    assert listing(tmp_path) == before


def test_bad_header_image_size_raises_input_error(bad_header):
    kind, path = bad_header
    with pytest.raises(InputError, match=path.name):
        image_size(path)


def test_huge_header_is_refused_before_decoding(huge_header_png):
    start = time.perf_counter()
    with pytest.raises(InputError) as caught:
        read_image(huge_header_png)
    assert time.perf_counter() - start < 1.0  # decoding 1.6 gigapixels would take far longer
    message = str(caught.value)
    assert huge_header_png.name in message and "40000x40000" in message
    assert "--max-pixels" in message


def test_implausible_header_is_refused(tmp_path, implausible_header_png):
    path = implausible_header_png
    before = listing(tmp_path)
    with pytest.raises(InputError, match="bomb.png"):
        read_image(path)
    assert listing(tmp_path) == before


def test_huge_header_size_is_read_from_header(huge_header_png):
    assert image_size(huge_header_png) == (40000, 40000)


def test_max_pixels_is_inclusive(tmp_path, smooth_rgb):
    write_image(tmp_path / "small.png", smooth_rgb(10, 20))
    assert read_image(tmp_path / "small.png", max_pixels=200).rgb.shape == (10, 20, 3)
    with pytest.raises(InputError, match="small.png"):
        read_image(tmp_path / "small.png", max_pixels=199)


def test_unsupported_channel_layout_is_refused(tmp_path):
    path = str(tmp_path / "five_channels.exr")
    spec = oiio.ImageSpec(4, 3, 5, oiio.FLOAT)
    spec.channelnames = ("u", "v", "w", "x", "y")
    output = oiio.ImageOutput.create(path)
    output.open(path, spec)
    output.write_image(np.zeros((3, 4, 5), np.float32))
    output.close()
    with pytest.raises(InputError, match="five_channels.exr"):
        read_image(path)


# --- bad outputs and atomic writes --------------------------------------------------------

def test_output_under_a_regular_file_is_refused(tmp_path, smooth_rgb):
    blocker = tmp_path / "not_a_directory"
    blocker.write_text("a file standing where the output directory should be")
    target = blocker / "relit.png"
    with pytest.raises(OutputError) as caught:
        write_image(target, smooth_rgb(4, 4))
    assert "relit.png" in str(caught.value) and "-o" in str(caught.value)
    assert listing(tmp_path) == ["not_a_directory"]


def test_output_in_missing_directory_is_refused(tmp_path, smooth_rgb):
    with pytest.raises(OutputError, match="relit.png"):
        write_image(tmp_path / "no_such_dir" / "relit.png", smooth_rgb(4, 4))
    assert listing(tmp_path) == []


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes through chmod 0o500")
def test_output_in_read_only_directory_is_refused(tmp_path, smooth_rgb):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        with pytest.raises(OutputError, match="relit.png"):
            write_image(locked / "relit.png", smooth_rgb(4, 4))
        assert listing(locked) == []
    finally:
        locked.chmod(0o700)


@pytest.mark.skipif(not os.path.isdir("/sys/kernel"), reason="needs Linux sysfs")
def test_output_where_even_root_cannot_create_files_is_refused(smooth_rgb):
    # sysfs never lets anyone, root included, create a regular file
    target = "/sys/relightcli_output_probe.png"
    with pytest.raises(OutputError, match="relightcli_output_probe.png"):
        write_image(target, smooth_rgb(4, 4))
    assert not os.path.exists(target)


@pytest.mark.parametrize("name", ["relit.tiff", "relit", "relit.webp"])
def test_unsupported_output_extension_is_refused(tmp_path, name, smooth_rgb):
    with pytest.raises(OutputError, match=name):
        write_image(tmp_path / name, smooth_rgb(4, 4))
    assert listing(tmp_path) == []


def test_overwrite_false_keeps_existing_file(tmp_path, smooth_rgb):
    target = tmp_path / "keep.png"
    target.write_bytes(b"previous result")
    with pytest.raises(OutputError, match="keep.png"):
        write_image(target, smooth_rgb(4, 4), overwrite=False)
    assert target.read_bytes() == b"previous result"


def _half_written_then(outcome):
    """A stand-in for `_write_pixels` that leaves half a file, then fails with `outcome`."""

    def fail(path, pixels, spec):
        with open(path, "wb") as handle:
            handle.write(b"\x89PNG\r\n\x1a\n partial")
        if isinstance(outcome, Exception):
            raise outcome
        return outcome

    return fail


@pytest.mark.parametrize("outcome", ["No space left on device (injected)",
                                     RuntimeError("writer crashed (injected)")],
                         ids=["writer-reports-error", "writer-raises"])
def test_failed_write_leaves_no_temporary_and_old_file_intact(tmp_path, monkeypatch, outcome,
                                                              smooth_rgb):
    target = tmp_path / "relit.png"
    target.write_bytes(b"previous result")
    monkeypatch.setattr(images, "_write_pixels", _half_written_then(outcome))
    expected = RuntimeError if isinstance(outcome, Exception) else WriteError
    with pytest.raises(expected) as caught:
        write_image(target, smooth_rgb(4, 4))
    if expected is WriteError:
        assert "relit.png" in str(caught.value)
    assert listing(tmp_path) == ["relit.png"]
    assert target.read_bytes() == b"previous result"


def test_failed_first_write_leaves_nothing(tmp_path, monkeypatch, smooth_rgb):
    monkeypatch.setattr(images, "_write_pixels", _half_written_then("injected failure"))
    with pytest.raises(WriteError, match="fresh.exr"):
        write_image(tmp_path / "fresh.exr", smooth_rgb(4, 4))
    assert listing(tmp_path) == []


def test_written_file_has_ordinary_permissions(tmp_path, smooth_rgb):
    write_image(tmp_path / "shared.png", smooth_rgb(4, 4))
    umask = os.umask(0)
    os.umask(umask)
    assert (tmp_path / "shared.png").stat().st_mode & 0o777 == 0o666 & ~umask


# --- real files from ../shared/data, against independent decoders -----------------------

@pytest.mark.parametrize("name", PHOTOS)
def test_shared_photo_matches_pillow(name):
    pil_image = pytest.importorskip("PIL.Image")
    pil_ops = pytest.importorskip("PIL.ImageOps")
    path = shared_file("photos", name)
    reference = pil_ops.exif_transpose(pil_image.open(path))
    has_alpha = "A" in reference.getbands()
    reference = np.asarray(reference.convert("RGBA" if has_alpha else "RGB"), dtype=np.float32)
    image = read_image(path)
    assert image.rgb.shape == reference.shape[:2] + (3,)
    encoded = linear_to_srgb(image.rgb) * 255.0
    # two JPEG decoders may differ by a rounding step or two (IDCT, chroma upsampling)
    assert np.abs(encoded - reference[..., :3]).max() <= 2.5
    if has_alpha:
        np.testing.assert_allclose(image.alpha * 255.0, reference[..., 3], atol=1e-3)


@pytest.mark.parametrize("name", HDRIS)
def test_shared_hdri_matches_opencv(name):
    cv2 = pytest.importorskip("cv2")
    path = shared_file("hdri", name)
    reference = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_COLOR)[..., ::-1]
    image = read_image(path)
    assert image.rgb.shape == (512, 1024, 3) and not image.encoded
    np.testing.assert_allclose(image.rgb, reference, rtol=1e-6, atol=0.0)


@pytest.mark.parametrize("bits", [8, 16])
def test_data_maps_round_trip_exactly_without_srgb(tmp_path, bits):
    values = np.array([[0.0, 0.25, 0.5, 1.0]], np.float32)
    path = tmp_path / f"data{bits}.png"
    write_image(path, values, bits=bits, srgb=False)
    back = read_image(path, srgb=False).rgb[..., 0]
    np.testing.assert_allclose(back, values, atol=0.5 / (2**bits - 1))
    assert back[0, 0] == 0.0 and back[0, 3] == 1.0


@pytest.mark.parametrize("name", ["a.exr", "a.png", "a.jpg", "a.hdr"])
def test_written_files_carry_no_time_stamp(tmp_path, name):
    """The same pixels give the same bytes: OpenEXR would stamp the time of writing."""
    rgb = np.linspace(0.0, 1.0, 8 * 6 * 3, dtype=np.float32).reshape(8, 6, 3)
    images.write_image(tmp_path / name, rgb)
    image_input = oiio.ImageInput.open(str(tmp_path / name))
    names = [attribute.name for attribute in image_input.spec().extra_attribs]
    image_input.close()
    assert "DateTime" not in names


# --- what is decoded: data windows, tiles, parts, channels (hostile sweep, case A) ----------

def test_exr_data_window_across_the_display_window_is_cut_to_it(tmp_path):
    # stored pixels 6 x 5 starting at (-2, 3) over an 8 x 6 display: the left two columns and
    # the bottom two rows fall outside (dropped), the display's top three rows and right four
    # columns have nothing stored (black and transparent)
    values = np.arange(6 * 5, dtype=np.float32).reshape(5, 6) + 1.0
    pixels = np.stack([values, 2 * values, 3 * values, np.ones_like(values)], axis=-1)
    path = write_windowed_exr(tmp_path / "overscan.exr", pixels, (-2, 3), (8, 6))
    image = read_image(path)
    assert image.rgb.shape == (6, 8, 3) and image.alpha.shape == (6, 8)
    expected = np.zeros((6, 8, 3), np.float32)
    expected[3:6, 0:4] = pixels[0:3, 2:6, :3]
    np.testing.assert_array_equal(image.rgb, expected)
    expected_alpha = np.zeros((6, 8), np.float32)
    expected_alpha[3:6, 0:4] = 1.0
    np.testing.assert_array_equal(image.alpha, expected_alpha)


def test_exr_data_window_wholly_outside_the_display_window_reads_black(tmp_path):
    pixels = np.ones((4, 4, 4), np.float32)
    image = read_image(write_windowed_exr(tmp_path / "away.exr", pixels, (20, 20), (8, 4)))
    assert image.rgb.shape == (4, 8, 3) and not image.rgb.any() and not image.alpha.any()


def test_data_window_over_the_limit_is_refused_from_the_header(tmp_path):
    # an 8 x 4 image storing 400 x 300 pixels: the display window is within the limit, the
    # pixels decoded are not
    path = write_exr(tmp_path / "overscan.exr", display=(8, 4), data=(-10, -10, 400, 300))
    with pytest.raises(InputError) as caught:
        read_image(path, max_pixels=100_000)
    message = str(caught.value)
    assert "overscan.exr" in message and "data window" in message and "400x300 = 120000" in message
    assert "--crop 8x4+0+0" in message and "--max-pixels" in message
    assert read_image(path, max_pixels=120_000).rgb.shape == (4, 8, 3)  # at the limit: read


def test_tile_over_the_limit_is_refused_from_the_header(tmp_path):
    # a 64 x 32 image in one 512 x 512 tile: the reader decodes whole tiles
    path = write_exr(tmp_path / "tiled.exr", display=(64, 32), data=(0, 0, 64, 32), tile=512)
    with pytest.raises(InputError, match=r"tiled.exr: image is stored in tiles of 512x512 = 262144"):
        read_image(path, max_pixels=100_000)
    assert read_image(path, max_pixels=262_144).rgb.shape == (32, 64, 3)


def test_only_the_first_part_is_read_and_counted(tmp_path):
    # part 0: 16 x 8 of 0.25; part 1 stores 1200 x 1000 of 0.75, more than the limit given
    # (the parts of an EXR share one display window)
    path = str(tmp_path / "parts.exr")
    specs = [oiio.ImageSpec(16, 8, 3, oiio.FLOAT), oiio.ImageSpec(1200, 1000, 3, oiio.HALF)]
    specs[1].full_width, specs[1].full_height = 16, 8
    output = oiio.ImageOutput.create(path)
    assert output.open(path, specs)
    output.write_image(np.full((8, 16, 3), 0.25, np.float32))
    output.open(path, specs[1], "AppendSubimage")
    output.write_image(np.full((1000, 1200, 3), 0.75, np.float32))
    output.close()
    image = read_image(path, max_pixels=1000)
    assert image.rgb.shape == (8, 16, 3) and (image.rgb == 0.25).all()


def test_channels_the_image_does_not_use_are_not_decoded(tmp_path):
    # R, G, B and 61 render passes: reading all would hold 64 channels of float32
    passes = tuple(f"pass{k:02d}" for k in range(61))
    path = write_exr(tmp_path / "passes.exr", display=(256, 128), data=(0, 0, 256, 128),
                     channels=("R", "G", "B") + passes, value=0.5)
    rgb_bytes = 256 * 128 * 3 * 4
    peak = traced_peak(lambda: read_image(path))
    assert peak < 4 * rgb_bytes  # every channel: 21 x rgb_bytes
    image = read_image(path)
    assert image.rgb.shape == (128, 256, 3) and (image.rgb == 0.5).all() and image.alpha is None


@pytest.mark.parametrize("channels, reads", [([0, 1, 2], [(0, 3)]), ([2, 1, 0, 3], [(0, 4)]),
                                             ([5, 6, 7], [(5, 8)]), ([0, 41, 42], [(0, 1), (41, 42), (42, 43)])])
def test_read_channels_reads_a_narrow_span_once_else_each_channel(channels, reads):
    stored = np.arange(2 * 3 * 50, dtype=np.float32).reshape(2, 3, 50)
    calls = []

    def read(first, stop):
        calls.append((first, stop))
        return stored[:, :, first:stop]

    np.testing.assert_array_equal(images.read_channels(read, channels), stored[:, :, channels])
    assert calls == reads


# --- EXR half or float, and no NaN or Inf written (case C) ---------------------------------

def test_values_above_half_max_are_written_as_float32(tmp_path):
    rgb = np.full((4, 6, 3), 1e5, np.float32)
    rgb[0, 0] = 3.0
    write_image(tmp_path / "bright.exr", rgb)
    image = read_image(tmp_path / "bright.exr")
    assert image.bits == 32 and np.isfinite(image.rgb).all()
    np.testing.assert_array_equal(image.rgb, rgb)


@pytest.mark.parametrize("stops", [-16, -30, -60])
def test_a_layer_exposed_far_down_keeps_every_value(tmp_path, stops, smooth_rgb):
    # "every output changes by that factor": half would round 2**-16 x a layer to a few
    # subnormal steps and 2**-30 x it to 0
    rgb = smooth_rgb(8, 8)
    write_image(tmp_path / "dark.exr", rgb * np.float32(2.0 ** stops))
    image = read_image(tmp_path / "dark.exr")
    assert image.bits == 32
    np.testing.assert_array_equal(image.rgb, rgb * np.float32(2.0 ** stops))


def test_an_ordinary_layer_stays_half(tmp_path, smooth_rgb):
    write_image(tmp_path / "plain.exr", smooth_rgb(8, 8))
    assert read_image(tmp_path / "plain.exr").bits == 16


@pytest.mark.parametrize("top, expected", [(0.0, True), (1.0, True), (65504.0, True), (65600.0, False),
                                           (2.0 ** -4, True), (2.0 ** -4.01, False), (-7e4, False)])
def test_fits_half_bounds(top, expected):
    values = np.array([[top, top / 1024, 0.0]], np.float32)
    assert images.fits_half(values) is expected


def test_nan_and_inf_are_never_written(tmp_path, smooth_rgb):
    rgb = smooth_rgb(6, 6)
    rgb[1, 1, 0], rgb[2, 2, 1], rgb[3, 3, 2] = np.nan, np.inf, -np.inf
    for name in ("out.exr", "out.hdr", "out.png"):
        with pytest.warns(RelightWarning, match=rf"{name}: .*1 NaN and 2 Inf"):
            write_image(tmp_path / name, rgb)
        assert np.isfinite(read_image(tmp_path / name).rgb).all()
    stored = read_image(tmp_path / "out.exr").rgb
    largest = float(np.nanmax(np.abs(np.where(np.isfinite(rgb), rgb, np.nan))))
    assert stored[1, 1, 0] == 0.0
    assert stored[2, 2, 1] == pytest.approx(largest, rel=1e-3)  # half rounding
    assert stored[3, 3, 2] == pytest.approx(-largest, rel=1e-3)


# --- outputs checked before work, write failures (cases B and D) --------------------------

@pytest.mark.parametrize("name", ["shading.tiff", "a_folder"])
def test_check_output_path_refuses_what_write_image_cannot_write(tmp_path, name):
    (tmp_path / "a_folder").mkdir()
    with pytest.raises(OutputError, match=name):
        images.check_output_path(tmp_path / name)


def test_check_output_path_refuses_a_missing_folder(tmp_path):
    with pytest.raises(OutputError, match="folder does not exist"):
        images.check_output_path(tmp_path / "nowhere" / "shading.exr")


def test_disk_full_is_a_write_error_with_the_plain_reason(tmp_path, monkeypatch, smooth_rgb):
    # the codec says what libpng says on a full disk; the file system says why
    target = tmp_path / "relit.png"
    monkeypatch.setattr(images, "_write_pixels", _half_written_then(
        "Write error at position 65793, could only write 3839/8192 bytes\nWrite error at ..."))
    real_write = os.write

    def full_disk(handle, data):
        if os.fstat(handle).st_ino == _temporary_inode(tmp_path):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real_write(handle, data)

    monkeypatch.setattr(os, "write", full_disk)
    with pytest.raises(WriteError) as caught:
        write_image(target, smooth_rgb(4, 4))
    assert str(caught.value).startswith(f"{target}: cannot write the output: no space left on device")
    assert "Write error" not in str(caught.value) and caught.value.exit_code == 1
    assert listing(tmp_path) == []


def _temporary_inode(folder) -> int | None:
    """The inode of the writer's temporary file in `folder` (the one hidden file there)."""
    hidden = [p for p in Path(folder).iterdir() if p.name.startswith(".")]
    return hidden[0].stat().st_ino if hidden else None
