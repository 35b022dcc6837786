"""The `relight` CLI, run in-process: exit codes, reports, bad inputs, nothing half-written."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from relightcli import __version__
from relightcli.cli import main
from relightcli.io.images import write_image

from exr_testing import write_float_exr

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def env_path(tmp_path):
    path = tmp_path / "env.hdr"
    env = np.full((8, 16, 3), 0.5, np.float32)
    env[1, 3] = 1e5  # a sun
    write_image(path, env)
    return path


def rgba_photo(path: Path, seed: int = 0) -> Path:
    rng = np.random.default_rng(seed)
    rgb = rng.uniform(0.05, 0.9, (48, 40, 3)).astype(np.float32)
    alpha = np.zeros((48, 40), np.float32)
    alpha[4:40, 4:30] = 1.0
    alpha[3, 4:12] = 0.5
    write_image(path, rgb, alpha)
    return path


def run_json(capsys, argv):
    code = main(argv + ["--json"])
    out = capsys.readouterr().out
    return code, json.loads(out) if out.strip() else None


def test_version(capsys):
    assert main(["--version"]) == 0
    assert __version__ in capsys.readouterr().out


def test_help_lists_every_output(capsys):
    assert main(["--help"]) == 0
    text = capsys.readouterr().out
    for name in ("relit", "albedo", "normal", "ao", "shading", "mask", "mesh", "light", "preview"):
        assert name in text


def test_help_imports_no_heavy_module():
    code = (
        "import sys; from relightcli.cli import relight_parser; relight_parser().format_help();"
        "heavy = [m for m in ('numpy', 'onnxruntime', 'OpenImageIO', 'embreex', 'cv2', 'trimesh') "
        "if m in sys.modules]; print(','.join(heavy))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=REPO)
    assert out.stdout.strip() == ""


@pytest.mark.parametrize(
    "argv",
    [
        ["photo.jpg", "-o", "out.png"],  # no --hdr
        ["photo.jpg", "--hdr", "env.hdr", "-o", "out.png", "--outputs", "relit,bogus"],
        ["photo.jpg", "--hdr", "env.hdr", "-o", "out.png", "--spp", "0"],
        ["photo.jpg", "--hdr", "env.hdr", "-o", "out.png", "--spp", "4", "--target-error", "0.1"],
    ],
    ids=["no-hdr", "unknown-output", "zero-spp", "spp-and-target-error"],
)
def test_usage_errors_exit_2(argv):
    assert main(argv) == 2


def test_skip_existing_with_overwrite_is_usage_error(tmp_path, env_path):
    photo = rgba_photo(tmp_path / "a.png")
    argv = [str(photo), "--hdr", str(env_path), "-o", str(tmp_path / "o.png"), "--skip-existing", "--overwrite"]
    assert main(argv) == 2


def test_mask_output_from_alpha(tmp_path, env_path, capsys):
    photo = rgba_photo(tmp_path / "a.png")
    out = tmp_path / "out" / "a.png"
    code, report = run_json(capsys, [str(photo), "--hdr", str(env_path), "-o", str(out), "--outputs", "mask"])
    assert code == 0, report
    item = report["items"][0]
    assert report["ok"] == 1 and report["failed"] == 0
    mask_path = Path(item["outputs"]["mask"])
    assert mask_path == tmp_path / "out" / "a_mask.png"
    from relightcli.io.images import read_image

    written = read_image(mask_path)
    assert written.encoded  # an 8-bit PNG
    # Mask values are data, written without the sRGB curve: 1 -> 255, 0.5 -> ~128, 0 -> 0.
    from relightcli.io.images import linear_to_srgb

    values = linear_to_srgb(written.rgb[..., 0])
    assert values[10, 8] == pytest.approx(1.0)
    assert values[0, 0] == pytest.approx(0.0)
    assert values[3, 5] == pytest.approx(0.5, abs=1 / 255)
    # The plan: mask from alpha, no network needed for this output.
    assert item["plan"]["run"] == ["mask"]
    assert "people" in item["plan"]["skipped"]
    assert set(item["seconds"]) >= {"load", "mask", "write", "total"}


def test_relit_without_models_exits_3_and_writes_nothing(tmp_path, env_path, capsys, monkeypatch):
    empty = tmp_path / "no_models"
    empty.mkdir()
    (empty / "manifest.json").write_text('{"version": 1, "models": {}}')
    monkeypatch.setenv("RELIGHT_MODELS_DIR", str(empty))
    photo = rgba_photo(tmp_path / "a.png")
    out = tmp_path / "out.png"
    code, report = run_json(capsys, [str(photo), "--hdr", str(env_path), "-o", str(out)])
    assert code == 3
    error = report["items"][0]["error"]
    # The first model the plan needs: the pose nets, whose people the body fit takes
    assert "manifest.json" in error and "'person_detector'" in error
    assert not out.exists()


def test_missing_input_exits_4(tmp_path, env_path, capsys):
    missing = tmp_path / "nothere.jpg"
    code, report = run_json(capsys, [str(missing), "--hdr", str(env_path), "-o", str(tmp_path / "o.png"), "--outputs", "mask"])
    assert code == 4
    assert "nothere.jpg" in report["items"][0]["error"]


@pytest.mark.parametrize("content", [b"", b"this is not a jpeg\n"], ids=["zero-bytes", "text"])
def test_unreadable_input_exits_4_and_writes_nothing(tmp_path, env_path, capsys, content):
    bad = tmp_path / "bad.jpg"
    bad.write_bytes(content)
    out_dir = tmp_path / "out"
    code, report = run_json(capsys, [str(bad), "--hdr", str(env_path), "-o", str(out_dir / "x.png"), "--outputs", "mask"])
    assert code == 4
    assert "bad.jpg" in report["items"][0]["error"]
    assert not any(p.is_file() for p in out_dir.rglob("*"))


def test_folder_mixing_good_and_bad_files(tmp_path, env_path, capsys):
    folder = tmp_path / "in"
    folder.mkdir()
    rgba_photo(folder / "good1.png", seed=1)
    rgba_photo(folder / "good2.png", seed=2)
    (folder / "broken.jpg").write_bytes(b"\xff\xd8\xff\xe0 not really")
    (folder / "empty.png").write_bytes(b"")
    (folder / "notes.txt").write_text("ignored: not an image extension")
    out = tmp_path / "out"
    code, report = run_json(capsys, [str(folder), "--hdr", str(env_path), "-o", str(out), "--outputs", "mask"])
    assert code == 1
    assert report["ok"] == 2 and report["failed"] == 2
    failed = sorted(Path(i["input"]).name for i in report["items"] if i["error"])
    assert failed == ["broken.jpg", "empty.png"]
    assert (out / "good1_mask.png").is_file() and (out / "good2_mask.png").is_file()
    assert sorted(p.name for p in out.iterdir()) == ["good1_mask.png", "good2_mask.png"]


def test_human_summary_names_the_failures(tmp_path, env_path, capsys):
    folder = tmp_path / "in"
    folder.mkdir()
    rgba_photo(folder / "good.png")
    (folder / "bad.png").write_bytes(b"")
    assert main([str(folder), "--hdr", str(env_path), "-o", str(tmp_path / "out"), "--outputs", "mask"]) == 1
    err = capsys.readouterr().err
    assert "1 ok, 1 failed" in err and "bad.png" in err


def test_hdr_in_input_folder_is_not_an_input(tmp_path, capsys):
    folder = tmp_path / "in"
    folder.mkdir()
    rgba_photo(folder / "person.png")
    env = np.full((4, 8, 3), 1.0, np.float32)
    write_image(folder / "sky.hdr", env)
    code, report = run_json(capsys, [str(folder), "--hdr", str(folder / "sky.hdr"), "-o", str(tmp_path / "out"), "--outputs", "mask"])
    assert code == 0
    assert [Path(i["input"]).name for i in report["items"]] == ["person.png"]


def test_recursive_keeps_subfolders_apart(tmp_path, env_path, capsys):
    for sub in ("a", "b"):
        (tmp_path / "in" / sub).mkdir(parents=True)
        rgba_photo(tmp_path / "in" / sub / "same.png")
    out = tmp_path / "out"
    code, _ = run_json(capsys, [str(tmp_path / "in"), "--recursive", "--hdr", str(env_path), "-o", str(out), "--outputs", "mask"])
    assert code == 0
    assert (out / "a" / "same_mask.png").is_file() and (out / "b" / "same_mask.png").is_file()


def test_output_equal_to_input_is_refused(tmp_path, env_path):
    photo = rgba_photo(tmp_path / "a.png")
    before = photo.read_bytes()
    assert main([str(photo), "--hdr", str(env_path), "-o", str(photo)]) == 2
    assert photo.read_bytes() == before


def test_layer_output_colliding_with_input_is_refused(tmp_path, env_path):
    photo = rgba_photo(tmp_path / "a.png")
    also_input = rgba_photo(tmp_path / "a_mask.png")
    before = also_input.read_bytes()
    argv = [str(photo), str(also_input), "--hdr", str(env_path), "-o", str(tmp_path), "--outputs", "mask"]
    assert main(argv) == 2
    assert also_input.read_bytes() == before


def test_unwritable_output_directory(tmp_path, env_path, capsys):
    photo = rgba_photo(tmp_path / "a.png")
    blocker = tmp_path / "file"
    blocker.write_text("a file where a folder should be")
    code = main([str(photo), "--hdr", str(env_path), "-o", str(blocker / "sub" / "out.png"), "--outputs", "mask"])
    assert code == 2
    assert "sub" in capsys.readouterr().err


def test_existing_output_refused_then_skipped_then_overwritten(tmp_path, env_path, capsys):
    photo = rgba_photo(tmp_path / "a.png")
    out = tmp_path / "o.png"
    argv = [str(photo), "--hdr", str(env_path), "-o", str(out), "--outputs", "mask"]
    assert run_json(capsys, argv)[0] == 0
    mask = tmp_path / "o_mask.png"
    mtime = mask.stat().st_mtime_ns
    code, report = run_json(capsys, argv)
    assert code == 2 and "--overwrite" in report["items"][0]["error"]
    code, report = run_json(capsys, argv + ["--skip-existing"])
    assert code == 0 and report["items"][0]["skipped"]
    assert mask.stat().st_mtime_ns == mtime
    assert run_json(capsys, argv + ["--overwrite"])[0] == 0


def test_many_inputs_to_one_file_is_usage_error(tmp_path, env_path):
    a, b = rgba_photo(tmp_path / "a.png"), rgba_photo(tmp_path / "b.png")
    assert main([str(a), str(b), "--hdr", str(env_path), "-o", str(tmp_path / "one.png")]) == 2


@pytest.mark.parametrize("shape", [(4, 12), (8, 8)], ids=["3:1", "1:1"])
def test_environment_with_wrong_aspect_exits_4(tmp_path, capsys, shape):
    photo = rgba_photo(tmp_path / "a.png")
    env = tmp_path / "bad_env.hdr"
    write_image(env, np.ones(shape + (3,), np.float32))
    code = main([str(photo), "--hdr", str(env), "-o", str(tmp_path / "o.png"), "--outputs", "mask"])
    assert code == 4
    assert "bad_env.hdr" in capsys.readouterr().err
    assert not (tmp_path / "o_mask.png").exists()


def test_tiny_environment_2x1_is_accepted(tmp_path, capsys):
    photo = rgba_photo(tmp_path / "a.png")
    env = tmp_path / "tiny.hdr"
    write_image(env, np.ones((1, 2, 3), np.float32))
    code, _ = run_json(capsys, [str(photo), "--hdr", str(env), "-o", str(tmp_path / "o.png"), "--outputs", "mask"])
    assert code == 0


def test_environment_with_nan_inf_negative_texels_warns(tmp_path, capsys):
    photo = rgba_photo(tmp_path / "a.png")
    env = np.ones((8, 16, 3), np.float32)
    env[0, 0] = np.nan
    env[1, 1] = np.inf
    env[2, 2] = -1.0
    path = write_float_exr(tmp_path / "nan.exr", env)  # write_image would repair the texels
    code = main([str(photo), "--hdr", str(path), "-o", str(tmp_path / "o.png"), "--outputs", "mask"])
    assert code == 0
    err = capsys.readouterr().err
    assert "NaN" in err or "nan" in err.lower()


def test_missing_environment_exits_4(tmp_path):
    photo = rgba_photo(tmp_path / "a.png")
    assert main([str(photo), "--hdr", str(tmp_path / "none.hdr"), "-o", str(tmp_path / "o.png")]) == 4


def test_mask_file_of_wrong_size_exits_4(tmp_path, env_path, capsys):
    photo = rgba_photo(tmp_path / "a.png")
    mask = tmp_path / "m.png"
    write_image(mask, np.ones((40, 40), np.float32), bits=8, srgb=False)
    code, report = run_json(capsys, [str(photo), "--mask", str(mask), "--hdr", str(env_path), "-o", str(tmp_path / "o.png"), "--outputs", "mask"])
    assert code == 4 and "m.png" in report["items"][0]["error"]


def grey_mask(path: Path, shape=(48, 40)) -> tuple[Path, np.ndarray]:
    mask = np.zeros(shape, np.float32)
    mask[10:44, 6:22] = 1.0
    write_image(path, mask, bits=8, srgb=False)
    return path, mask


def test_a_photos_own_mask_beside_it_is_its_mask_not_a_photo(tmp_path, env_path, capsys):
    from relightcli.io.images import read_image

    folder = tmp_path / "in"
    folder.mkdir()
    write_image(folder / "a.png", np.random.default_rng(1).uniform(0.1, 0.9, (48, 40, 3)).astype(np.float32))
    _, mask = grey_mask(folder / "a_mask.png")
    rgba_photo(folder / "b.png")
    rgba_photo(folder / "lone_mask.png")  # no photo "lone": a photo like any other
    out = tmp_path / "out"
    code, report = run_json(capsys, [str(folder), "--hdr", str(env_path), "-o", str(out), "--outputs", "mask"])
    assert code == 0, report
    assert [Path(i["input"]).name for i in report["items"]] == ["a.png", "b.png", "lone_mask.png"]
    a = report["items"][0]
    assert a["stages"]["mask"]["source"] == f"{folder / 'a_mask.png'} (the photo's own mask)"
    assert a["plan"]["run"] == ["mask"]  # no person detection: the mask is given
    written = read_image(out / "a_mask.png", srgb=False).rgb[..., 0]
    assert np.abs(written - mask).max() <= 1 / 255
    assert report["items"][1]["stages"]["mask"]["source"] == "alpha channel"


def test_a_photos_own_mask_in_a_recursive_scan_stays_in_its_folder(tmp_path, env_path, capsys):
    for sub in ("x", "y"):
        (tmp_path / "in" / sub).mkdir(parents=True)
        write_image(tmp_path / "in" / sub / "p.png", np.full((48, 40, 3), 0.5, np.float32))
    grey_mask(tmp_path / "in" / "x" / "p_mask.png")
    code, report = run_json(capsys, [str(tmp_path / "in"), "--recursive", "--hdr", str(env_path), "-o",
                                     str(tmp_path / "out"), "--outputs", "mask", "--method", "sh9"])
    items = {str(Path(i["input"]).relative_to(tmp_path / "in")): i for i in report["items"]}
    assert sorted(items) == ["x/p.png", "y/p.png"]
    assert "p_mask.png" in items["x/p.png"]["stages"]["mask"]["source"]
    assert "p_mask.png" not in json.dumps(items["y/p.png"].get("stages", {}))


def test_mask_option_and_a_photos_own_mask_file_are_refused_together(tmp_path, env_path, capsys):
    folder = tmp_path / "in"
    folder.mkdir()
    rgba_photo(folder / "a.png")
    grey_mask(folder / "a_mask.png")
    other, _ = grey_mask(tmp_path / "m.png")
    code = main([str(folder), "--mask", str(other), "--hdr", str(env_path), "-o", str(tmp_path / "out"), "--outputs", "mask"])
    assert code == 2
    assert "a_mask.png" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_several_maps_with_a_turntable_or_one_name_are_refused(tmp_path, env_path, capsys):
    photo = rgba_photo(tmp_path / "a.png")
    other = tmp_path / "other"
    other.mkdir()
    same_name = other / env_path.name
    same_name.write_bytes(env_path.read_bytes())
    base = [str(photo), "--hdr", str(env_path), "-o", str(tmp_path / "out"), "--outputs", "relit"]
    assert main(base + ["--hdr", str(same_name)]) == 2
    assert "named 'env'" in capsys.readouterr().err
    assert main(base + ["--hdr", str(tmp_path / "a.png"), "--turntable", "3"]) == 2
    assert "--turntable" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_info_json(capsys):
    code, report = run_json(capsys, ["info"])
    assert code == 0
    assert "CPUExecutionProvider" in report["providers"]
    assert report["threads"] >= 1
    assert report["version"] == __version__


def test_info_exits_3_naming_a_missing_or_corrupt_model(tmp_path, monkeypatch, capsys):
    import shutil

    from relightcli.nets.manifest import models_dir

    shutil.copy(models_dir() / "manifest.json", tmp_path / "manifest.json")
    entries = json.loads((tmp_path / "manifest.json").read_text())["models"]
    corrupt, *_ = sorted(entries)
    (tmp_path / entries[corrupt]["file"]).write_bytes(b"not the model")
    monkeypatch.setenv("RELIGHT_MODELS_DIR", str(tmp_path))
    code, report = run_json(capsys, ["info"])
    assert code == 3
    assert [m["name"] for m in report["models"] if m["present"]] == [corrupt]
    assert not report["models"][0]["sha256_ok"]


def test_one_pixel_image_exits_4(tmp_path, env_path, capsys):
    tiny = tmp_path / "tiny.png"
    write_image(tiny, np.ones((1, 1, 3), np.float32), np.ones((1, 1), np.float32))
    code, report = run_json(capsys, [str(tiny), "--hdr", str(env_path), "-o", str(tmp_path / "o.png"), "--outputs", "mask"])
    assert code == 4
    assert "tiny.png" in report["items"][0]["error"] and "1x1" in report["items"][0]["error"]


@pytest.mark.parametrize("background", ["keep", "env", "transparent", "#808080", "#fff"])
def test_background_values_accepted(background):
    from relightcli.cli import relight_parser

    args = relight_parser().parse_args(["a.jpg", "--hdr", "e.hdr", "-o", "o.png", "--background", background])
    assert args.background == background


def test_background_value_rejected():
    assert main(["a.jpg", "--hdr", "e.hdr", "-o", "o.png", "--background", "purple-ish"]) == 2
