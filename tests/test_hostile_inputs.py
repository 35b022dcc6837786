"""Hostile inputs and resource limits (issue 22), run through the CLI in-process: inputs that
must never be overwritten, effort options with caps, odd files where an image should be."""

from __future__ import annotations

import json
import os
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest

from relightcli.cli import MAX_SPP, default_threads, main
from relightcli.io.images import write_image


@pytest.fixture
def env_path(tmp_path):
    path = tmp_path / "env.hdr"
    write_image(path, np.full((8, 16, 3), 0.5, np.float32))
    return path


def rgba_photo(path: Path, opaque: bool = True) -> Path:
    rgb = np.random.default_rng(0).uniform(0.05, 0.9, (48, 40, 3)).astype(np.float32)
    alpha = np.zeros((48, 40), np.float32)
    if opaque:
        alpha[4:40, 4:30] = 1.0
    write_image(path, rgb, alpha)
    return path


def grey_mask(path: Path) -> Path:
    mask = np.zeros((48, 40), np.float32)
    mask[4:40, 4:30] = 1.0
    write_image(path, mask, srgb=False)
    return path


def run_json(capsys, argv):
    code = main(argv + ["--json"])
    captured = capsys.readouterr()
    return code, (json.loads(captured.out) if captured.out.strip() else None), captured.err


# --- item 1: no input is ever an output target ------------------------------------------------

def test_output_naming_the_mask_is_refused_even_with_overwrite(tmp_path, env_path, capsys):
    photo, mask = rgba_photo(tmp_path / "a.png"), grey_mask(tmp_path / "m.png")
    before = mask.read_bytes()
    argv = [str(photo), "--hdr", str(env_path), "--mask", str(mask), "-o", str(mask), "--overwrite"]
    assert main(argv) == 2
    assert "would overwrite the input" in capsys.readouterr().err
    assert mask.read_bytes() == before


def test_output_naming_the_hdr_is_refused_even_with_overwrite(tmp_path, env_path):
    photo = rgba_photo(tmp_path / "a.png")
    before = env_path.read_bytes()
    assert main([str(photo), "--hdr", str(env_path), "-o", str(env_path), "--overwrite"]) == 2
    assert env_path.read_bytes() == before


def test_layer_output_naming_the_hdr_is_refused(tmp_path):
    # the light layer of a.png is a_light.hdr: the map itself here
    photo = rgba_photo(tmp_path / "a.png")
    env = tmp_path / "a_light.hdr"
    write_image(env, np.full((8, 16, 3), 0.5, np.float32))
    before = env.read_bytes()
    argv = [str(photo), "--hdr", str(env), "-o", str(tmp_path / "a.png"), "--outputs", "mask,light", "--overwrite"]
    assert main(argv) == 2
    assert env.read_bytes() == before


def test_output_reaching_the_mask_through_a_symlink_is_refused(tmp_path, env_path):
    photo, mask = rgba_photo(tmp_path / "a.png"), grey_mask(tmp_path / "m.png")
    link = tmp_path / "link.png"
    link.symlink_to(mask)
    before = mask.read_bytes()
    assert main([str(photo), "--hdr", str(env_path), "--mask", str(mask), "-o", str(link), "--overwrite"]) == 2
    assert mask.read_bytes() == before and link.is_symlink()


def test_output_reaching_the_mask_through_a_relative_path_is_refused(tmp_path, env_path, monkeypatch):
    photo, mask = rgba_photo(tmp_path / "a.png"), grey_mask(tmp_path / "m.png")
    (tmp_path / "sub").mkdir()
    monkeypatch.chdir(tmp_path / "sub")
    before = mask.read_bytes()
    assert main([str(photo), "--hdr", str(env_path), "--mask", str(mask), "-o", "../m.png", "--overwrite"]) == 2
    assert mask.read_bytes() == before


def test_output_that_is_a_hard_link_to_the_mask_is_refused(tmp_path, env_path):
    photo, mask = rgba_photo(tmp_path / "a.png"), grey_mask(tmp_path / "m.png")
    hard = tmp_path / "hard.png"
    os.link(mask, hard)
    before = mask.read_bytes()
    assert main([str(photo), "--hdr", str(env_path), "--mask", str(mask), "-o", str(hard), "--overwrite"]) == 2
    assert mask.read_bytes() == before


# --- items 4 and 6: caps on the effort options ------------------------------------------------

RELIGHT = ["a.png", "--hdr", "env.hdr", "-o", "out.png"]


@pytest.mark.parametrize("value", ["1", "15", "2049", "100000"])
def test_resolution_outside_its_range_is_a_usage_error(value, capsys):
    assert main(RELIGHT + ["--resolution", value]) == 2
    err = capsys.readouterr().err
    assert "--resolution" in err and "16..2048" in err


def test_resolution_range_applies_to_eval(tmp_path, capsys):
    assert main(["eval", str(tmp_path), "--resolution", "100000"]) == 2
    assert "16..2048" in capsys.readouterr().err


@pytest.mark.parametrize("command", [RELIGHT, ["eval", "data"], ["shade", "m.obj", "--hdr", "e.hdr", "-o", "s.exr"]],
                         ids=["relight", "eval", "shade"])
def test_spp_above_the_cap_is_a_usage_error(command, capsys):
    assert main(command + ["--spp", str(MAX_SPP + 1)]) == 2
    err = capsys.readouterr().err
    assert "--spp" in err and f"1..{MAX_SPP}" in err


def test_spp_at_the_cap_is_accepted():
    from relightcli.cli import relight_parser

    assert relight_parser().parse_args(RELIGHT + ["--spp", str(MAX_SPP)]).spp == MAX_SPP


def test_threads_above_the_cores_are_lowered_with_a_warning(capsys):
    too_many = default_threads() + 1
    code, report, err = run_json(capsys, ["info", "--threads", str(too_many)])
    assert code == 0 and report["threads"] == default_threads()
    assert f"--threads {too_many}" in err and "core" in err


def test_threads_on_a_ray_cluster_are_not_lowered(monkeypatch):
    from relightcli import cli

    seen = {}
    monkeypatch.setattr(cli, "run_relight", lambda args: seen.setdefault("threads", args.threads) and 0)
    cli.main(RELIGHT + ["--engine", "ray", "--address", "auto", "--threads", "64"])
    assert seen["threads"] == 64


# --- item 7: smaller ones ---------------------------------------------------------------------

@pytest.mark.parametrize("name", ["out.gif", "out.txt", "out.tiff"])
def test_unsupported_output_format_is_refused(tmp_path, env_path, capsys, name):
    photo = rgba_photo(tmp_path / "a.png")
    out = tmp_path / name
    assert main([str(photo), "--hdr", str(env_path), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "unsupported output format" in err and name in err and ".png" in err
    assert not out.exists()


def test_output_without_extension_is_a_folder(tmp_path, env_path, capsys):
    # A file needs an extension: a bare name is a folder, as it is for many inputs.
    photo = rgba_photo(tmp_path / "a.png")
    out = tmp_path / "out"
    code, report, _ = run_json(capsys, [str(photo), "--hdr", str(env_path), "-o", str(out), "--outputs", "mask"])
    assert code == 0
    assert report["items"][0]["outputs"]["mask"] == str(out / "a_mask.png")


def test_output_ending_in_a_slash_is_a_folder(tmp_path, env_path, capsys):
    photo = rgba_photo(tmp_path / "a.png")
    out = tmp_path / "results.v2"
    code, report, _ = run_json(capsys, [str(photo), "--hdr", str(env_path), "-o", f"{out}/", "--outputs", "mask"])
    assert code == 0
    assert report["items"][0]["outputs"]["mask"] == str(out / "a_mask.png")


@pytest.mark.parametrize("name", ["out.jpg", "out.JPEG", "out.hdr"])
def test_transparent_background_into_a_format_without_alpha_is_refused(tmp_path, env_path, capsys, name):
    photo = rgba_photo(tmp_path / "a.png")
    assert main([str(photo), "--hdr", str(env_path), "-o", str(tmp_path / name), "--background", "transparent"]) == 2
    assert "alpha" in capsys.readouterr().err


def test_unreadable_input_says_permission_denied(tmp_path, env_path, capsys, monkeypatch):
    # We run as root, for whom chmod 000 changes nothing: deny the read through os.access.
    photo = rgba_photo(tmp_path / "a.png")
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda path, mode, **kw: False if str(path) == str(photo) else real_access(path, mode, **kw))
    code, report, _ = run_json(capsys, [str(photo), "--hdr", str(env_path), "-o", str(tmp_path / "o.png"), "--outputs", "mask"])
    assert code == 4
    error = report["items"][0]["error"]
    assert "permission denied" in error and "complete" not in error


def test_output_folder_equal_to_input_folder_is_refused(tmp_path, env_path, capsys):
    photos = tmp_path / "photos"
    photos.mkdir()
    rgba_photo(photos / "a.png")
    assert main([str(photos), "--hdr", str(env_path), "-o", str(photos)]) == 2
    assert "the output folder is the input folder" in capsys.readouterr().err


def test_input_folder_inside_the_output_folder_is_refused(tmp_path, env_path, capsys):
    photos = tmp_path / "out" / "photos"
    photos.mkdir(parents=True)
    rgba_photo(photos / "a.png")
    assert main([str(photos), "--hdr", str(env_path), "-o", str(tmp_path / "out")]) == 2
    assert "inside the output folder" in capsys.readouterr().err


def test_same_file_listed_twice_is_relit_once(tmp_path, env_path, capsys):
    photo = rgba_photo(tmp_path / "a.png")
    link = tmp_path / "b.png"
    link.symlink_to(photo)
    argv = [str(photo), str(photo), str(link), "--hdr", str(env_path), "-o", str(tmp_path / "out"), "--outputs", "mask"]
    code, report, _ = run_json(capsys, argv)
    assert code == 0
    assert [item["input"] for item in report["items"]] == [str(photo)]


def test_fifo_as_hdr_is_not_a_regular_file(tmp_path, capsys):
    photo = rgba_photo(tmp_path / "a.png")
    fifo = tmp_path / "env.hdr"
    os.mkfifo(fifo)
    assert main([str(photo), "--hdr", str(fifo), "-o", str(tmp_path / "o.png")]) == 4
    assert "not a regular file" in capsys.readouterr().err


def test_dev_zero_as_hdr_is_not_a_regular_file(tmp_path, capsys):
    photo = rgba_photo(tmp_path / "a.png")
    assert main([str(photo), "--hdr", "/dev/zero", "-o", str(tmp_path / "o.png")]) == 4
    assert "not a regular file" in capsys.readouterr().err


def test_fully_transparent_input_names_the_alpha_channel(tmp_path, env_path, capsys):
    photo = rgba_photo(tmp_path / "a.png", opaque=False)
    code, report, _ = run_json(capsys, [str(photo), "--hdr", str(env_path), "-o", str(tmp_path / "o.png")])
    assert code == 4
    assert "alpha channel" in report["items"][0]["error"]


def test_mesh_is_written_with_the_permissions_of_an_image(tmp_path):
    import trimesh

    from relightcli.geometry.mesh import save_mesh

    old = os.umask(0o022)
    try:
        path = save_mesh(trimesh.creation.box(), tmp_path / "body.ply")
    finally:
        os.umask(old)
    assert path.stat().st_mode & 0o777 == 0o644


def huge_png_header(path: Path, side: int = 100_000) -> Path:
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", side, side, 8, 2, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(b"\0" * 8))
                     + chunk(b"IEND", b""))
    return path


def test_huge_header_gets_the_max_pixels_message(tmp_path, env_path, capsys):
    photo = huge_png_header(tmp_path / "huge.png")
    code, report, _ = run_json(capsys, [str(photo), "--hdr", str(env_path), "-o", str(tmp_path / "o.png"), "--outputs", "mask"])
    assert code == 4
    error = report["items"][0]["error"]
    assert "100000x100000" in error and "--max-pixels" in error


def test_batch_failing_for_a_missing_model_and_other_causes_exits_3():
    from relightcli.batch import ItemReport, exit_code

    reports = [ItemReport("a.png", error="model missing", exit_code=3),
               ItemReport("b.png", error="unreadable", exit_code=4)]
    assert exit_code(reports) == 3
    assert exit_code(reports + [ItemReport("c.png")]) == 1


def test_output_extensions_are_the_formats_images_writes():
    from relightcli.io.images import _OUTPUT_FORMATS
    from relightcli.layers import OUTPUT_EXTENSIONS

    assert set(OUTPUT_EXTENSIONS) == set(_OUTPUT_FORMATS)
