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
