"""Hostile files and options from the reliability sweep, through the command line.

A: what is decoded is limited before decoding (EXR data windows, tiles; photos, masks, maps, the
eval truth). The memory bombs run `relight` in a subprocess whose address space is limited to
MEMORY_LIMIT: decoding one whole cannot fit, so a reader that tried would fail the test.
B: `relight shade` caps its render and checks its outputs before any work.
C: no wrong numbers with exit 0: float EXR where half would lose values, no NaN or Inf written,
maps too bright to integrate refused, huge or non-finite angles and albedos handled.
D: messages that name the file and say what to do; a failed write is an output error.
"""

from __future__ import annotations

import math
import os
import resource
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from exr_testing import write_exr, write_float_exr
from relightcli.cli import MAX_SPP, main
from relightcli.cli import shade
from relightcli.errors import RelightWarning
from relightcli.io.images import read_image, write_image

# Address space of a subprocess that meets a bomb: relight with its models loaded needs ~1 GB
MEMORY_LIMIT = 2 << 30


@pytest.fixture(scope="module")
def bomb(tmp_path_factory) -> Path:
    """A 128 x 64 EXR storing 24000 x 24000 grey half floats: 1.2 MB on disk, 2.3 GB decoded
    as float32 (6.9 GB as RGB), beyond MEMORY_LIMIT."""
    return write_exr(tmp_path_factory.mktemp("bomb") / "bomb.exr", display=(128, 64),
                     data=(0, 0, 24000, 24000))


def relight_limited(*argv, file_size: int | None = None) -> subprocess.CompletedProcess:
    """`relight ARGV` in a subprocess limited to MEMORY_LIMIT of address space and, with
    `file_size`, to files of that many bytes (a write beyond fails with EFBIG, as on a full
    disk it fails with ENOSPC)."""
    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, MEMORY_LIMIT))
        if file_size is not None:
            signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # the write fails instead of killing
            resource.setrlimit(resource.RLIMIT_FSIZE, (file_size, file_size))

    return subprocess.run([sys.executable, "-m", "relightcli", *map(str, argv)], preexec_fn=limit,
                          capture_output=True, text=True)


@pytest.fixture
def env_path(tmp_path) -> Path:
    path = tmp_path / "env.hdr"
    write_image(path, np.full((8, 16, 3), 0.5, np.float32))
    return path


@pytest.fixture
def photo(tmp_path) -> Path:
    """A 48 x 40 RGBA photo: the alpha is the person (no person detection needed)."""
    rgb = np.random.default_rng(0).uniform(0.05, 0.9, (48, 40, 3)).astype(np.float32)
    alpha = np.zeros((48, 40), np.float32)
    alpha[4:40, 4:30] = 1.0
    path = tmp_path / "photo.png"
    write_image(path, rgb, alpha)
    return path


@pytest.fixture
def ball(tmp_path) -> Path:
    path = tmp_path / "ball.obj"
    trimesh.creation.icosphere(subdivisions=2).export(path)
    return path


def constant_map(path: Path, radiance: float) -> Path:
    return write_float_exr(path, np.full((8, 16, 3), radiance, np.float32))


# --- A: size limits on what is decoded --------------------------------------------------------

def test_photo_storing_a_huge_data_window_is_refused_before_decoding(bomb, env_path, tmp_path):
    run = relight_limited(bomb, "--hdr", env_path, "-o", tmp_path / "out.png")
    assert run.returncode == 4, run.stderr
    assert "bomb.exr" in run.stderr and "data window" in run.stderr and "24000x24000" in run.stderr
    assert "--max-pixels" in run.stderr and not (tmp_path / "out.png").exists()


def test_mask_storing_a_huge_data_window_is_refused_before_decoding(bomb, photo, env_path, tmp_path):
    run = relight_limited(photo, "--mask", bomb, "--hdr", env_path, "-o", tmp_path / "out.png")
    assert run.returncode == 4, run.stderr
    assert "bomb.exr" in run.stderr and "data window" in run.stderr


def test_map_storing_a_huge_data_window_is_refused_before_decoding(bomb, photo, tmp_path):
    run = relight_limited(photo, "--hdr", bomb, "-o", tmp_path / "out.png")
    assert run.returncode == 4, run.stderr
    assert "bomb.exr: environment map's data window" in run.stderr


def test_shade_map_storing_a_huge_data_window_is_refused_before_decoding(bomb, ball, tmp_path):
    run = relight_limited("shade", ball, "--hdr", bomb, "-o", tmp_path / "s.exr", "--res", 8, 8)
    assert run.returncode == 4, run.stderr
    assert "bomb.exr: environment map's data window" in run.stderr


def test_eval_truth_storing_a_huge_data_window_is_refused_before_decoding(bomb, tmp_path):
    scene = tmp_path / "data" / "scene0"
    scene.mkdir(parents=True)
    grey = np.full((64, 128, 3), 0.5, np.float32)
    write_image(scene / "input.png", grey)
    write_image(scene / "target.hdr", grey[:8, :16])
    write_image(scene / "gt_mask.png", np.ones((64, 128), np.float32), srgb=False)
    for name in ("gt_albedo.exr", "gt_relit.exr"):
        write_image(scene / name, grey)
    (scene / "gt_shading.exr").symlink_to(bomb)
    run = relight_limited("eval", tmp_path / "data", "--method", "sh9", "--use-gt-mask")
    assert run.returncode == 4, run.stderr
    assert "gt_shading.exr" in run.stderr and "data window" in run.stderr


def test_photo_in_one_huge_tile_is_refused_before_decoding(env_path, tmp_path):
    # 445 bytes: a 128 x 64 image in one 40000 x 40000 tile, which the reader decodes whole (19 GB)
    tiled = write_exr(tmp_path / "tiled.exr", display=(128, 64), data=(0, 0, 128, 64), tile=40000)
    run = relight_limited(tiled, "--hdr", env_path, "-o", tmp_path / "out.png")
    assert run.returncode == 4, run.stderr
    assert "tiled.exr: image is stored in tiles of 40000x40000" in run.stderr


def test_a_photo_is_its_display_window(env_path, tmp_path, capsys):
    # the stored pixels overhang the 40 x 48 display window by 8 on every side: the outputs are
    # 40 x 48, and the person (alpha) is what the display window holds of the stored alpha
    import OpenImageIO as oiio

    spec = oiio.ImageSpec(56, 64, 4, oiio.FLOAT)
    spec.x = spec.y = -8
    spec.full_width, spec.full_height = 40, 48
    pixels = np.zeros((64, 56, 4), np.float32)
    pixels[..., :3] = 0.4
    pixels[20:50, 14:40, 3] = 1.0
    path = str(tmp_path / "overscan.exr")
    output = oiio.ImageOutput.create(path)
    output.open(path, spec)
    output.write_image(pixels)
    output.close()
    assert main([path, "--hdr", str(env_path), "-o", str(tmp_path / "out.png"), "--outputs", "mask"]) == 0
    mask = read_image(tmp_path / "out_mask.png", srgb=False).rgb[..., 0]
    assert mask.shape == (48, 40)
    np.testing.assert_array_equal(mask > 0.5, pixels[8:56, 8:48, 3] > 0.5)


# --- B: shade's caps and outputs, before any work ---------------------------------------------

@pytest.fixture
def no_work(monkeypatch):
    """Fail the test if shade reads the mesh (the first piece of work)."""
    def refuse(path):
        raise AssertionError("shade read the mesh before refusing its options")

    monkeypatch.setattr(shade, "load_mesh", refuse)


def test_shade_res_beyond_its_cap_is_refused_before_any_work(ball, env_path, tmp_path, capsys, no_work):
    argv = ["shade", str(ball), "--hdr", str(env_path), "-o", str(tmp_path / "s.exr")]
    assert main(argv + ["--res", "50000", "50000"]) == 2
    err = capsys.readouterr().err
    assert "--res 50000 50000 is 2500000000 pixels, more than the limit of 4194304" in err
    assert "--max-pixels" in err


def test_shade_max_pixels_sets_the_cap(ball, env_path, tmp_path, capsys):
    argv = ["shade", str(ball), "--hdr", str(env_path), "-o", str(tmp_path / "s.exr"), "--res", "40", "30",
            "--spp", "1"]
    assert main(argv + ["--max-pixels", "1199"]) == 2
    assert main(argv + ["--max-pixels", "1200"]) == 0


@pytest.mark.parametrize("option, name", [("-o", "shading.tiff"), ("-o", "a_folder"), ("-o", "gone/shading.exr"),
                                          ("--error-map", "error.webp"), ("--mask-map", "a_folder")])
def test_shade_outputs_are_checked_before_any_work(ball, env_path, tmp_path, capsys, no_work, option, name):
    (tmp_path / "a_folder").mkdir()
    outputs = {"-o": str(tmp_path / "s.exr"), option: str(tmp_path / name)}
    argv = ["shade", str(ball), "--hdr", str(env_path)] + [a for pair in outputs.items() for a in pair]
    assert main(argv) == 2
    assert name.split("/")[-1] in capsys.readouterr().err


def test_shade_sampling_with_a_time_budget_is_capped_like_relight(ball, env_path, tmp_path, monkeypatch):
    from relightcli.render import integrator

    asked = {}

    def record(*args, **kwargs):
        asked.update(kwargs)
        raise KeyboardInterrupt  # stop here: only the cap is looked at

    monkeypatch.setattr(integrator, "shade_environment", record)
    main(["shade", str(ball), "--hdr", str(env_path), "-o", str(tmp_path / "s.exr"), "--time-budget", "60"])
    assert asked["spp"] == MAX_SPP


# --- C: no wrong numbers written ---------------------------------------------------------------

def test_shade_under_a_bright_map_writes_float_without_inf(ball, tmp_path):
    # constant L = 1e5: the shading is 1e5 wherever the ball is, above half's 65504
    out, error = tmp_path / "s.exr", tmp_path / "err.exr"
    argv = ["shade", str(ball), "--hdr", str(constant_map(tmp_path / "bright.exr", 1e5)), "-o", str(out),
            "--res", "16", "16", "--spp", "4", "--error-map", str(error)]
    assert main(argv) == 0
    image = read_image(out)
    assert image.bits == 32 and np.isfinite(image.rgb).all() and np.isfinite(read_image(error).rgb).all()
    lit = image.rgb[image.alpha > 0.99]
    assert np.median(lit) == pytest.approx(1e5, rel=1e-3) and lit.max() <= 1e5 * (1 + 1e-3)


@pytest.mark.parametrize("albedo", ["nan", "-5", "1e30", "inf", "1.01"])
def test_shade_albedo_outside_0_to_1_is_refused_at_parse_time(ball, env_path, tmp_path, capsys, albedo):
    argv = ["shade", str(ball), "--hdr", str(env_path), "-o", str(tmp_path / "s.exr"), "--bounces", "2",
            "--albedo", albedo]
    assert main(argv) == 2
    assert "--albedo: must be between 0 and 1" in capsys.readouterr().err


def test_shade_turns_by_a_huge_angle_as_by_its_remainder(ball, tmp_path):
    env = np.random.default_rng(1).uniform(0.1, 2.0, (8, 16, 3)).astype(np.float32)
    write_float_exr(tmp_path / "sky.exr", env)
    for name, angle in (("huge.exr", "1e308"), ("rest.exr", repr(math.fmod(1e308, 360.0)))):
        assert main(["shade", str(ball), "--hdr", str(tmp_path / "sky.exr"), "-o", str(tmp_path / name),
                     "--res", "12", "12", "--spp", "4", "--rotate", angle]) == 0
    assert (tmp_path / "huge.exr").read_bytes() == (tmp_path / "rest.exr").read_bytes()


@pytest.mark.parametrize("angle", ["inf", "nan"])
def test_non_finite_rotation_is_a_usage_error(ball, photo, env_path, tmp_path, capsys, angle):
    shade_argv = ["shade", str(ball), "--hdr", str(env_path), "-o", str(tmp_path / "s.exr"), "--rotate", angle]
    assert main(shade_argv) == 2
    assert main([str(photo), "--hdr", str(env_path), "-o", str(tmp_path / "o.png"), "--rotate", angle]) == 2
    assert "rotation must be a finite number" in capsys.readouterr().err


def test_map_too_bright_to_integrate_is_refused_by_relight_and_shade(ball, photo, tmp_path, capsys):
    blinding = constant_map(tmp_path / "blinding.exr", 3e38)
    assert main([str(photo), "--hdr", str(blinding), "-o", str(tmp_path / "o.png")]) == 4
    assert main(["shade", str(ball), "--hdr", str(blinding), "-o", str(tmp_path / "s.exr")]) == 4
    err = capsys.readouterr().err
    assert err.count("blinding.exr: the environment map's brightest texel is 3e+38") == 2
    assert not (tmp_path / "o.png").exists() and not (tmp_path / "s.exr").exists()


def test_a_map_or_an_exposure_past_the_ceiling_is_refused_saying_how_far_to_go(photo, tmp_path, capsys):
    # 1e20 x the map: its own fault (exit 4); 1e3 x 2**64: the option's (exit 2)
    bright = constant_map(tmp_path / "bright.exr", 1e20)
    assert main([str(photo), "--hdr", str(bright), "-o", str(tmp_path / "o.png")]) == 4
    assert "bright.exr: the environment map's brightest texel is 1e+20" in capsys.readouterr().err
    sky = constant_map(tmp_path / "sky.exr", 1e3)
    assert main([str(photo), "--hdr", str(sky), "-o", str(tmp_path / "o.png"), "--exposure", "64"]) == 2
    assert "sky.exr from 1e+03 to 1.84e+22" in capsys.readouterr().err


@pytest.fixture(scope="module")
def shading_at(tmp_path_factory):
    """exposure -> the shading layer relight writes (.exr, --method sh9) for one photo and map."""
    folder = tmp_path_factory.mktemp("exposure")
    rgb = np.random.default_rng(0).uniform(0.05, 0.9, (48, 40, 3)).astype(np.float32)
    alpha = np.zeros((48, 40), np.float32)
    alpha[4:40, 4:30] = 1.0
    write_image(folder / "photo.png", rgb, alpha)
    sky = np.random.default_rng(2).uniform(0.2, 3.0, (8, 16, 3)).astype(np.float32)
    write_float_exr(folder / "sky.exr", sky)
    layers = {}
    for stops in (0, -16, -30):
        out = folder / f"ev{-stops}.exr"
        assert main([str(folder / "photo.png"), "--hdr", str(folder / "sky.exr"), "-o", str(out),
                     "--outputs", "shading", "--method", "sh9", "--exposure", str(stops)]) == 0
        layers[stops] = read_image(folder / f"ev{-stops}_shading.exr")
    return layers


@pytest.mark.parametrize("stops", [-16, -30])
def test_exposure_scales_the_written_shading_by_its_factor(shading_at, stops):
    # half floats would have written 2**-30 x the shading as 0 and 2**-16 x it in a few steps;
    # the base layer is half (within half's rounding, 2**-11, of float32), the dark ones float32
    base, low = shading_at[0], shading_at[stops]
    assert base.bits == 16 and low.bits == 32 and base.rgb.max() > 0
    np.testing.assert_allclose(low.rgb, base.rgb * np.float32(2.0 ** stops), rtol=2.0 ** -11, atol=0)


def test_dark_shading_layers_differ_by_exactly_their_exposures(shading_at):
    np.testing.assert_array_equal(shading_at[-30].rgb, shading_at[-16].rgb * np.float32(2.0 ** -14))


def test_the_renderer_repairs_inf_texels_by_the_maps_rule():
    # one rule everywhere (README): +Inf is the map's largest finite value, not 0
    from relightcli.render.environment import EnvironmentLight

    env = np.ones((4, 8, 3), np.float32)
    env[1, 2] = 5.0
    env[0, 0, 0] = np.inf
    with pytest.warns(RelightWarning, match=r"\+Inf to the largest finite value \(5\)"):
        light = EnvironmentLight(env)
    assert light.radiance[0, 0, 0] == 5.0


# --- D: messages that name the file, write failures -------------------------------------------

def test_nan_pixel_in_an_exr_photo_is_refused_naming_the_photo(env_path, tmp_path, capsys):
    rgb = np.full((48, 40, 3), 0.5, np.float32)
    rgb[10, 7, 1] = np.nan
    photo = write_float_exr(tmp_path / "render.exr", rgb)
    assert main([str(photo), "--hdr", str(env_path), "-o", str(tmp_path / "o.png")]) == 4
    err = capsys.readouterr().err
    assert "render.exr: the photo holds 1 NaN and 0 Inf values (the first at row 10, column 7)" in err
    assert "depth map" not in err


def test_nan_mask_is_refused_naming_the_mask(photo, env_path, tmp_path, capsys):
    mask = write_float_exr(tmp_path / "matte.exr", np.full((48, 40), np.nan, np.float32))
    assert main([str(photo), "--mask", str(mask), "--hdr", str(env_path), "-o", str(tmp_path / "o.png")]) == 4
    assert "matte.exr: the mask holds 1920 NaN" in capsys.readouterr().err


def test_shade_on_a_mesh_flat_in_x_names_the_mesh_in_plain_numbers(env_path, tmp_path, capsys):
    flat = tmp_path / "wall.obj"
    trimesh.Trimesh([[0, 0, 0], [0, 1, 0], [0, 0, 1], [0, 1, 1]], [[0, 1, 2], [1, 3, 2]]).export(flat)
    assert main(["shade", str(flat), "--hdr", str(env_path), "-o", str(tmp_path / "s.exr")]) == 4
    err = capsys.readouterr().err
    assert "wall.obj: the mesh is flat in x (x 0..0, y -0.05..1.05)" in err and "--rect" in err
    assert "np.float64" not in err


def test_shade_rect_without_area_is_refused_in_plain_numbers(ball, env_path, tmp_path, capsys):
    argv = ["shade", str(ball), "--hdr", str(env_path), "-o", str(tmp_path / "s.exr"), "--rect", "1", "0", "0", "1"]
    assert main(argv) == 2
    assert "--rect 1 0 0 1 covers no area" in capsys.readouterr().err


def test_shade_write_failure_is_an_output_error_naming_the_output(ball, env_path, tmp_path):
    out = tmp_path / "out" / "shading.png"
    out.parent.mkdir()
    run = relight_limited("shade", ball, "--hdr", env_path, "-o", out, "--res", "64", "64", "--spp", "1",
                          file_size=512)
    assert run.returncode == 1, run.stderr
    assert f"relight: error: {out}: cannot write the output: file too large" in run.stderr
    assert "Write error" not in run.stderr and os.listdir(out.parent) == []


def test_relight_write_failure_fails_the_item_and_leaves_nothing(photo, env_path, tmp_path):
    out = tmp_path / "out" / "relit.png"
    out.parent.mkdir()
    run = relight_limited(photo, "--hdr", env_path, "-o", out, "--outputs", "mask", file_size=64)
    assert run.returncode == 1, run.stderr
    assert "cannot write the output: file too large" in run.stderr and "usage" not in run.stderr
    assert f"{out.parent / 'relit_mask.png'}: cannot write" in run.stderr  # not its staging file
    assert "relight-part" not in run.stderr
    assert os.listdir(out.parent) == []
