"""Hostile paths, run through the CLI in-process: symlink loops, dangling links and names too
long fail the item they belong to (or the run, for -o, --hdr and --mask) with the file named,
never with a traceback; every output of an item is checked before any work, so nothing fails
once files are being replaced; a photo's own mask file is never written over."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from relightcli import batch
from relightcli.cli import main
from relightcli.io.images import write_image
from tests.test_hostile_inputs import grey_mask, rgba_photo


@pytest.fixture
def env_path(tmp_path):
    path = tmp_path / "env.hdr"
    write_image(path, np.full((8, 16, 3), 0.5, np.float32))
    return path


def loop(path: Path) -> Path:
    path.symlink_to(path.name)  # a link to itself
    return path


def file_on_the_path(folder: Path) -> Path:
    """A path through a file, as if it were a folder."""
    (folder / "file").write_text("not a folder")
    return folder / "file" / "p.png"


def run_json(capsys, argv):
    code = main(argv + ["--json"])
    captured = capsys.readouterr()
    return code, (json.loads(captured.out) if captured.out.strip() else None), captured.err


def errors_by_name(report) -> dict[str, str | None]:
    return {Path(item["input"]).name: item["error"] for item in report["items"]}


# --- path errors in a folder: that entry's item fails, the batch goes on ----------------------

@pytest.mark.parametrize("make_bad, words", [
    (loop, "symlink loop"),
    (lambda path: path.symlink_to("gone.png") or path, "dangling symlink"),
], ids=["loop", "dangling"])
def test_a_broken_link_among_the_photos_fails_only_its_item(tmp_path, env_path, capsys, make_bad, words):
    folder = tmp_path / "in"
    folder.mkdir()
    rgba_photo(folder / "a.png")
    make_bad(folder / "b.png")
    code, report, _ = run_json(capsys, [str(folder), "--hdr", str(env_path), "-o", str(tmp_path / "out"), "--outputs", "mask"])
    assert code == 1
    errors = errors_by_name(report)
    assert errors["a.png"] is None and (tmp_path / "out" / "a_mask.png").is_file()
    assert "b.png" in errors["b.png"] and words in errors["b.png"]


@pytest.mark.parametrize("name", ["notes.txt", "loop"])
def test_a_looping_link_that_is_no_photo_is_left_alone(tmp_path, env_path, capsys, name):
    folder = tmp_path / "in"
    folder.mkdir()
    rgba_photo(folder / "a.png")
    loop(folder / name)
    code, report, _ = run_json(capsys, [str(folder), "--hdr", str(env_path), "-o", str(tmp_path / "out"), "--outputs", "mask"])
    assert code == 0 and list(errors_by_name(report)) == ["a.png"]


def test_a_link_back_to_the_folder_is_not_followed(tmp_path, env_path, capsys):
    folder = tmp_path / "in"
    (folder / "sub").mkdir(parents=True)
    rgba_photo(folder / "a.png")
    rgba_photo(folder / "sub" / "b.png")
    (folder / "sub" / "up").symlink_to(folder)  # in/sub/up/sub/up/... forever, if followed
    argv = [str(folder), "--recursive", "--hdr", str(env_path), "-o", str(tmp_path / "out"), "--outputs", "mask",
            "--workers", "1"]
    code, report, _ = run_json(capsys, argv)
    assert code == 0 and [item["input"] for item in report["items"]] == [str(folder / "a.png"), str(folder / "sub" / "b.png")]


def test_an_input_folder_that_cannot_be_read_says_permission_denied(tmp_path, env_path, capsys, monkeypatch):
    # We run as root, for whom chmod 000 changes nothing: deny the read through os.access.
    folder = tmp_path / "in"
    folder.mkdir()
    rgba_photo(folder / "a.png")
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda path, mode, **kw: False if str(path) == str(folder) else real_access(path, mode, **kw))
    assert main([str(folder), "--hdr", str(env_path), "-o", str(tmp_path / "out")]) == 4
    err = capsys.readouterr().err
    assert str(folder) in err and "permission denied" in err


# --- the single-file arguments: a clear error and an exit code ---------------------------------

@pytest.mark.parametrize("where, code", [("input", 4), ("hdr", 4), ("mask", 4), ("output folder", 2), ("output file", 2)])
def test_a_looping_argument_is_named_with_an_exit_code(tmp_path, env_path, capsys, where, code):
    photo, mask = rgba_photo(tmp_path / "a.png"), grey_mask(tmp_path / "m.png")
    bad = loop(tmp_path / ("bad.png" if where != "output folder" else "bad"))
    args = {"input": str(photo), "hdr": str(env_path), "mask": str(mask), "output": str(tmp_path / "out.png")}
    args[where.split()[0]] = str(bad)
    argv = [args["input"], "--hdr", args["hdr"], "--mask", args["mask"], "-o", args["output"], "--outputs", "mask"]
    code_seen, report, err = run_json(capsys, argv)
    assert code_seen == code
    text = err if report is None else report["items"][0]["error"]
    assert str(bad) in text and "symlink loop" in text


@pytest.mark.parametrize("where, code", [("input", 4), ("output", 2)])
def test_a_name_too_long_is_named_with_an_exit_code(tmp_path, env_path, capsys, where, code):
    long_name = str(tmp_path / ("x" * 300 + ".png"))
    photo = str(rgba_photo(tmp_path / "a.png")) if where == "output" else long_name
    out = long_name if where == "output" else str(tmp_path / "out.png")
    code_seen, report, err = run_json(capsys, [photo, "--hdr", str(env_path), "-o", out, "--outputs", "mask"])
    assert code_seen == code
    text = err if report is None else report["items"][0]["error"]
    assert "x" * 300 in text and "too long" in text


def test_a_photo_whose_outputs_names_are_too_long_fails_alone(tmp_path, env_path, capsys):
    # 200 bytes is a valid name; with "_mask.png" and the staging marks it is not
    folder = tmp_path / "in"
    folder.mkdir()
    rgba_photo(folder / "a.png")
    rgba_photo(folder / ("y" * 200 + ".png"))
    code, report, _ = run_json(capsys, [str(folder), "--hdr", str(env_path), "-o", str(tmp_path / "out"), "--outputs", "mask"])
    assert code == 1
    errors = errors_by_name(report)
    assert errors["a.png"] is None
    assert "y" * 200 + "_mask.png" in errors["y" * 200 + ".png"] and "too long" in errors["y" * 200 + ".png"]


@pytest.mark.parametrize("make, words", [
    (loop, "symlink loop"),
    (lambda path: path.symlink_to("gone") or path, "dangling symlink"),
    (lambda path: file_on_the_path(path.parent), "should be a folder"),
    (lambda path: path.parent / ("z" * 300), "too long"),
], ids=["loop", "dangling", "file-on-the-path", "too-long"])
def test_path_problem_names_each_path_error(tmp_path, make, words):
    problem = batch.path_problem(make(tmp_path / "p.png"))
    assert problem is not None and words in problem[0]


def test_path_problem_leaves_missing_and_good_files_to_their_reader(tmp_path):
    assert batch.path_problem(tmp_path / "missing.png") is None
    assert batch.path_problem(rgba_photo(tmp_path / "a.png")) is None


def test_resolving_a_loop_never_raises(tmp_path):
    assert batch._resolved(loop(tmp_path / "l.png")).is_absolute()


# --- every output of an item is checked before any work ---------------------------------------

@pytest.mark.parametrize("flag", ["--overwrite", "--skip-existing"])
def test_a_folder_where_an_output_goes_is_refused_before_anything_is_replaced(tmp_path, env_path, capsys, flag):
    photo = rgba_photo(tmp_path / "a.png")
    out = tmp_path / "out"
    (out / "o_mask.png").mkdir(parents=True)
    (out / "o.png").write_bytes(b"the user's earlier result")
    code, report, _ = run_json(capsys, [str(photo), "--hdr", str(env_path), "-o", str(out / "o.png"),
                                         "--outputs", "relit,mask", flag])
    assert code == 2
    item = report["items"][0]
    assert "o_mask.png" in item["error"] and "folder" in item["error"] and not item.get("skipped")
    assert (out / "o.png").read_bytes() == b"the user's earlier result"
    assert sorted(p.name for p in out.iterdir()) == ["o.png", "o_mask.png"]  # no staging files either


@pytest.mark.parametrize("make, words", [(os.mkfifo, "pipe"), (lambda path: path.symlink_to("gone.png"), "dangling")],
                         ids=["fifo", "dangling-link"])
def test_a_non_file_where_an_output_goes_is_refused(tmp_path, env_path, capsys, make, words):
    photo = rgba_photo(tmp_path / "a.png")
    make(tmp_path / "o_mask.png")
    code, report, _ = run_json(capsys, [str(photo), "--hdr", str(env_path), "-o", str(tmp_path / "o.png"),
                                         "--outputs", "mask", "--overwrite"])
    assert code == 2 and words in report["items"][0]["error"]


def test_a_refused_item_does_not_stop_the_others(tmp_path, env_path, capsys):
    folder = tmp_path / "in"
    folder.mkdir()
    rgba_photo(folder / "a.png")
    rgba_photo(folder / "b.png")
    (tmp_path / "out" / "a_mask.png").mkdir(parents=True)
    code, report, _ = run_json(capsys, [str(folder), "--hdr", str(env_path), "-o", str(tmp_path / "out"), "--outputs", "mask"])
    assert code == 1
    errors = errors_by_name(report)
    assert "a_mask.png" in errors["a.png"] and "folder" in errors["a.png"] and errors["b.png"] is None
    assert (tmp_path / "out" / "b_mask.png").is_file()


def test_existing_outputs_are_regular_files_only(tmp_path):
    (tmp_path / "folder.png").mkdir()
    os.mkfifo(tmp_path / "fifo.png")
    (tmp_path / "file.png").write_bytes(b"x")
    (tmp_path / "link.png").symlink_to("file.png")
    loop(tmp_path / "loop.png")
    item = batch.Item(tmp_path / "a.png", {name: tmp_path / f"{name}.png" for name in ("folder", "fifo", "file", "link", "loop", "none")})
    assert batch.existing_outputs(item) == [tmp_path / "file.png", tmp_path / "link.png"]


@pytest.mark.parametrize("maps, outputs", [(["env", "albedo"], "relit,albedo"), (["env", "mask"], "relit,mask"),
                                           (["sun", "preview_sun"], "relit,preview")])
def test_maps_whose_outputs_collide_are_refused_before_any_work(tmp_path, capsys, maps, outputs):
    photo = rgba_photo(tmp_path / "a.png")
    hdrs = []
    for name in maps:
        write_image(tmp_path / f"{name}.hdr", np.full((8, 16, 3), 0.5, np.float32))
        hdrs += ["--hdr", str(tmp_path / f"{name}.hdr")]
    assert main([str(photo), *hdrs, "-o", str(tmp_path / "out"), "--outputs", outputs]) == 2
    err = capsys.readouterr().err
    assert "would both be written" in err and f"rename the map '{maps[1]}'" in err
    assert not (tmp_path / "out").exists()


# --- a photo's own mask file is never written over ---------------------------------------------

@pytest.mark.parametrize("out, outputs", [("{folder}/", "mask"), ("{folder}/a.jpg", "relit,mask")], ids=["folder", "file"])
def test_the_mask_file_beside_a_photo_is_never_overwritten(tmp_path, env_path, capsys, out, outputs):
    # a_mask.png beside a.png is a's own mask by its name, though not given as an input
    photo, mask = rgba_photo(tmp_path / "a.png"), grey_mask(tmp_path / "a_mask.png")
    before = mask.read_bytes()
    argv = [str(photo), "--hdr", str(env_path), "-o", out.format(folder=tmp_path), "--outputs", outputs, "--overwrite"]
    assert main(argv) == 2
    assert f"the mask file {mask} of the photo {photo}" in capsys.readouterr().err
    assert mask.read_bytes() == before and not (tmp_path / "a.jpg").exists()


def test_a_paired_mask_is_named_with_its_photo(tmp_path, env_path, capsys):
    photo, mask = rgba_photo(tmp_path / "a.png"), grey_mask(tmp_path / "a_mask.png")
    assert main([str(photo), str(mask), "--hdr", str(env_path), "-o", str(tmp_path), "--outputs", "mask", "--overwrite"]) == 2
    assert f"the mask file {mask} of the photo {photo}" in capsys.readouterr().err


def test_skip_existing_keeps_the_mask_file_beside_a_photo(tmp_path, env_path, capsys):
    photo, mask = rgba_photo(tmp_path / "a.png"), grey_mask(tmp_path / "a_mask.png")
    before = mask.read_bytes()
    code, report, _ = run_json(capsys, [str(photo), "--hdr", str(env_path), "-o", str(tmp_path) + "/",
                                         "--outputs", "mask", "--skip-existing"])
    assert code == 0 and report["items"][0]["skipped"]
    assert mask.read_bytes() == before


# --- relight eval speaks of the scene's files, not of --mask -----------------------------------

def empty_scene(folder: Path) -> Path:
    """A scene folder whose photo shows nobody and whose true mask is empty."""
    folder.mkdir(parents=True)
    write_image(folder / "input.png", np.full((64, 64, 3), 0.4, np.float32))
    write_image(folder / "target.hdr", np.full((8, 16, 3), 0.5, np.float32))
    write_image(folder / "gt_mask.png", np.zeros((64, 64), np.float32), srgb=False)
    for name in ("gt_albedo.exr", "gt_shading.exr", "gt_relit.exr"):
        write_image(folder / name, np.full((64, 64, 3), 0.5, np.float32))
    return folder


@pytest.mark.parametrize("option, named", [(["--use-gt-mask"], "gt_mask.png"), ([], "input.png")],
                         ids=["true-mask", "predicted"])
def test_eval_names_the_scene_file_instead_of_mask(tmp_path, capsys, option, named):
    scene = empty_scene(tmp_path / "data" / "s1")
    argv = ["eval", str(tmp_path / "data"), "--method", "sh9", "--albedo", "ratio", "--resolution", "32", "--json"]
    assert main(argv + option) != 0
    error = json.loads(capsys.readouterr().out)["per_scene"][0]["error"]
    assert str(scene / named) in error and "--mask" not in error
