"""`relight shade` in process: files written, values right, errors mapped."""

from __future__ import annotations

import argparse

import numpy as np
import pytest
import trimesh

from relightcli.cli import shade
from relightcli.errors import InputError, OutputError

L_CONST = (0.5, 1.0, 2.0)


def _parse(argv, threads=1):
    parser = argparse.ArgumentParser()
    shade.add_arguments(parser)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--overwrite", action="store_true")
    return shade.run(parser.parse_args(argv), threads)


@pytest.fixture
def inputs(tmp_path):
    from relightcli.io.images import write_image

    mesh_path = tmp_path / "ball.obj"
    trimesh.creation.icosphere(subdivisions=3).export(mesh_path)
    hdr_path = tmp_path / "constant.exr"
    write_image(hdr_path, np.broadcast_to(np.float32(L_CONST), (16, 32, 3)).copy(), half=False)
    return mesh_path, hdr_path


def _read(path):
    import OpenImageIO as oiio

    image = oiio.ImageInput.open(str(path))
    pixels = image.read_image(format="float")
    image.close()
    return pixels


def test_shade_writes_shading_error_and_mask(inputs, tmp_path):
    mesh, hdr = inputs
    out = tmp_path / "shading.exr"
    report = _parse([str(mesh), "--hdr", str(hdr), "-o", str(out), "--res", "24", "20", "--spp", "8",
                     "--error-map", str(tmp_path / "err.exr"), "--mask-map", str(tmp_path / "mask.exr")])
    assert set(report) >= {"spp", "rays", "seconds", "mrays_per_s", "rel_error"}
    shading, mask = _read(out), _read(tmp_path / "mask.exr")[..., 0]
    assert shading.shape[:2] == (20, 24) and mask.shape == (20, 24)
    # Furnace through the whole command: a smooth-shaded sphere under a constant map
    lit = shading[mask > 0.5][:, :3]
    assert np.median(np.abs(lit / np.array(L_CONST) - 1)) < 0.01
    assert np.all(shading[mask < 0.5][:, :3] == 0)
    # Default rect = bounds + 5%: the sphere's silhouette spans ~1/1.1 of the width
    assert abs(mask[10].sum() / 24 - 1 / 1.1) < 0.1
    assert report["rays"] >= 24 * 20 and report["rel_error"] >= 0


def test_shade_target_error_and_json_fields(inputs, tmp_path):
    mesh, hdr = inputs
    report = _parse([str(mesh), "--hdr", str(hdr), "-o", str(tmp_path / "s.exr"), "--res", "16", "16",
                     "--target-error", "0.05", "--strategy", "env"])
    assert report["rel_error"] <= 0.05 and report["strategy"] == "env" and report["spp"] >= 16


def test_missing_mesh_is_an_input_error_naming_the_file(inputs, tmp_path):
    _, hdr = inputs
    with pytest.raises(InputError, match="nothere.obj"):
        _parse([str(tmp_path / "nothere.obj"), "--hdr", str(hdr), "-o", str(tmp_path / "s.exr")])


def test_unreadable_mesh_is_an_input_error(inputs, tmp_path):
    _, hdr = inputs
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99\nend_header\n\x00")
    with pytest.raises(InputError, match="bad.ply"):
        _parse([str(bad), "--hdr", str(hdr), "-o", str(tmp_path / "s.exr")])


def test_existing_output_needs_overwrite(inputs, tmp_path):
    mesh, hdr = inputs
    out = tmp_path / "s.exr"
    out.write_bytes(b"old")
    with pytest.raises(OutputError):
        _parse([str(mesh), "--hdr", str(hdr), "-o", str(out), "--res", "8", "8", "--spp", "4"])
    _parse([str(mesh), "--hdr", str(hdr), "-o", str(out), "--res", "8", "8", "--spp", "4", "--overwrite"])
    assert _read(out).shape[:2] == (8, 8)


def test_exit_codes_through_the_dispatcher(inputs, tmp_path):
    cli = pytest.importorskip("relightcli.cli")
    if not hasattr(cli, "main"):
        pytest.skip("relightcli.cli.main not there yet")
    mesh, hdr = inputs
    ok = cli.main(["shade", str(mesh), "--hdr", str(hdr), "-o", str(tmp_path / "a.exr"),
                   "--res", "8", "8", "--spp", "4", "--threads", "1"])
    missing = cli.main(["shade", str(tmp_path / "none.obj"), "--hdr", str(hdr), "-o", str(tmp_path / "b.exr")])
    assert (ok, missing) == (0, 4)


def test_lift_takes_the_facets_off_a_coarse_balls_terminator(tmp_path):
    from relightcli.io.envmap import texel_solid_angles, uv_to_direction
    from relightcli.io.images import write_image

    mesh_path = tmp_path / "coarse.obj"
    trimesh.creation.icosphere(subdivisions=2).export(mesh_path)
    # a small sun low over the ball's right side, toward the camera (+Z)
    height, row, col = 256, 105, 417
    env = np.zeros((height, 2 * height, 3), np.float32)
    env[row, col] = 1000.0
    hdr_path = tmp_path / "sun.exr"
    write_image(hdr_path, env, half=False)
    sun = uv_to_direction((col + 0.5) / (2 * height), (row + 0.5) / height)
    scale = 1000.0 * texel_solid_angles(height, 2 * height)[row, col] / np.pi
    shaded = {}
    for lift in ("0", "1"):
        out = tmp_path / f"lift{lift}.exr"
        _parse([str(mesh_path), "--hdr", str(hdr_path), "-o", str(out), "--res", "64", "64",
                "--spp", "8", "--lift", lift, "--mask-map", str(tmp_path / "mask.exr"), "--overwrite"])
        shaded[lift] = _read(out)[..., 0]
    # the smooth ball's shading where the sun is 0.1-0.3 off its horizon, from the coverage mask
    # and the ball's normals (unit sphere at the origin; --rect is its bounds + 5%)
    x, y = np.meshgrid((np.arange(64) + 0.5) / 64 * 2.2 - 1.1, 1.1 - (np.arange(64) + 0.5) / 64 * 2.2)
    z = np.sqrt(np.clip(1.0 - x ** 2 - y ** 2, 0.0, None))
    cosine = np.stack([x, y, z], axis=-1) @ sun
    near = (_read(tmp_path / "mask.exr")[..., 0] > 0) & (x ** 2 + y ** 2 < 0.8) & (cosine > 0.1) & (cosine < 0.3)
    assert near.sum() > 20
    assert (shaded["0"][near] < 0.5 * scale * cosine[near]).any()
    np.testing.assert_allclose(shaded["1"][near], scale * cosine[near], rtol=0.15)


def test_lift_outside_its_range_is_refused(inputs, tmp_path):
    mesh_path, hdr_path = inputs
    with pytest.raises(SystemExit):
        _parse([str(mesh_path), "--hdr", str(hdr_path), "-o", str(tmp_path / "s.exr"), "--lift", "-1"])


def test_denoise_brings_a_noisy_render_closer_to_the_converged_one(tmp_path):
    # A box on a ground plate under a map of many small bright lamps: the plate's partial
    # shadows are noisy at 8 samples per pixel
    from relightcli.io.images import write_image

    box = trimesh.creation.box(extents=(0.6, 0.6, 0.6))
    box.apply_translation((0.0, 0.0, 0.3))
    plate = trimesh.creation.box(extents=(2.0, 2.0, 0.02))
    mesh_path = tmp_path / "scene.obj"
    trimesh.util.concatenate([box, plate]).export(mesh_path)
    rng = np.random.default_rng(2)
    env = np.full((32, 64, 3), 0.05, np.float32)
    env[rng.integers(0, 16, 40), rng.integers(0, 64, 40)] = 40.0
    hdr = tmp_path / "lamps.exr"
    write_image(hdr, env, half=False)
    common = [str(mesh_path), "--hdr", str(hdr), "--res", "64", "64", "--rect", "-1", "1", "-1", "1"]
    _parse(common + ["-o", str(tmp_path / "ref.exr"), "--spp", "1024", "--seed", "9"])
    plain = _parse(common + ["-o", str(tmp_path / "raw.exr"), "--spp", "8", "--error-map", str(tmp_path / "e1.exr")])
    report = _parse(common + ["-o", str(tmp_path / "den.exr"), "--spp", "8", "--denoise",
                              "--error-map", str(tmp_path / "e2.exr")])
    reference, raw, filtered = (_read(tmp_path / f"{n}.exr")[..., :3] for n in ("ref", "raw", "den"))
    lit = reference.mean(axis=-1) > 0

    def error(image):
        return float(np.sqrt(np.mean((image[lit] - reference[lit]) ** 2)))

    assert error(filtered) < 0.75 * error(raw)
    # the error map and the reported error are the Monte Carlo error before filtering
    np.testing.assert_array_equal(_read(tmp_path / "e1.exr"), _read(tmp_path / "e2.exr"))
    assert report["rel_error"] == plain["rel_error"] and report["denoised"] and not plain["denoised"]
