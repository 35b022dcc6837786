"""The Python API (relightcli.relight, Relighter, Result): the CLI's pipeline and files, inputs as
paths or arrays, options checked by the CLI's rules."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import relightcli
from relightcli.cli import main
from relightcli.errors import InputError, OutputError, RelightWarning, UsageError
from relightcli.io.envmap import load_envmap
from relightcli.io.images import read_image

REPO = Path(__file__).resolve().parents[1]
PHOTO, MASK = REPO / "examples" / "skier.jpg", REPO / "examples" / "skier_mask.png"
SKY = REPO / "examples" / "noon_grass.hdr"
LAYERS = ("relit", "albedo", "normal", "ao", "shading", "mask", "mesh", "light", "preview")
OPTIONS = {"resolution": 96, "seed": 3}


@pytest.fixture(scope="module")
def relighter():
    return relightcli.Relighter(threads=2, **OPTIONS)


def cli_files(capsys, out: Path, *extra: str) -> dict[str, bytes]:
    code = main([str(PHOTO), "--hdr", str(SKY), "-o", str(out), "--resolution", "96", "--seed", "3", "--json",
                 "--threads", "2", *extra])
    assert code == 0, capsys.readouterr().out
    capsys.readouterr()
    return {p.name: p.read_bytes() for p in sorted(out.parent.iterdir())}


def saved_files(result, out: Path) -> dict[str, bytes]:
    written = result.save(out)
    assert set(written.values()) == set(out.parent.iterdir())
    return {p.name: p.read_bytes() for p in sorted(out.parent.iterdir())}


def test_save_writes_the_same_bytes_as_the_cli(relighter, tmp_path, capsys):
    cli = cli_files(capsys, tmp_path / "cli" / "skier.png", "--outputs", ",".join(LAYERS), "--mask", str(MASK))
    result = relighter.relight(PHOTO, SKY, mask=MASK, outputs=LAYERS)
    assert saved_files(result, tmp_path / "api" / "skier.png") == cli
    assert len(cli) == len(LAYERS)


def test_a_one_call_relight_without_a_mask_matches_the_cli(tmp_path, capsys):
    # the people are found and segmented: the same stages as the CLI's, the same bytes
    cli = cli_files(capsys, tmp_path / "cli" / "skier.png", "--outputs", "relit,mask,albedo")
    result = relightcli.relight(str(PHOTO), str(SKY), outputs="relit,mask,albedo", threads=2, **OPTIONS)
    assert saved_files(result, tmp_path / "api" / "skier.png") == cli
    assert result.report["plan"]["run"][0] == "people"


def test_layers_are_linear_full_frame_arrays(relighter):
    result = relighter.relight(PHOTO, SKY, mask=MASK, outputs=LAYERS)
    photo = read_image(PHOTO).rgb
    height, width = photo.shape[:2]
    layers = result.layers
    assert set(layers) == set(LAYERS)
    for name in ("relit", "albedo", "shading", "normal"):
        assert layers[name].shape == (height, width, 3) and layers[name].dtype == np.float32, name
    assert layers["mask"].shape == layers["ao"].shape == (height, width)
    assert layers["light"].shape == (16, 32, 3)
    assert len(layers["mesh"].faces) > 0
    # linear, not display-encoded: where the person is, relit = albedo x shading (up to the
    # resampling from the crop to the photo), and the composite keeps the photo elsewhere
    mask = read_image(MASK, srgb=False).rgb[..., 0]
    inside, outside = mask > 0.999, mask == 0.0
    product = (layers["albedo"] * layers["shading"])[inside].sum(axis=-1)
    lit = product > 0  # the photo's black pixels are black in both (0 / 0)
    assert lit.mean() > 0.99
    ratio = layers["relit"][inside].sum(axis=-1)[lit] / product[lit]
    assert abs(np.median(ratio) - 1.0) < 0.01
    np.testing.assert_array_equal(layers["relit"][outside], photo[outside])
    assert result.report["seconds"]["raytrace"] > 0
    assert "delight" in result.report["stages"]


def test_arrays_in_give_the_results_of_the_files(relighter):
    from relightcli.io.images import linear_to_srgb

    from_files = relighter.relight(PHOTO, SKY, mask=MASK, outputs=("relit", "albedo"))
    photo = read_image(PHOTO).rgb
    codes = np.round(linear_to_srgb(photo) * 255).astype(np.uint8)  # the JPEG's own codes again
    mask = read_image(MASK, srgb=False).rgb[..., 0]
    from_arrays = relighter.relight(codes, load_envmap(SKY), mask=mask, outputs=("relit", "albedo"))
    for name in ("relit", "albedo"):
        np.testing.assert_array_equal(from_arrays.layers[name], from_files.layers[name])
    rgba = np.dstack([photo, mask])  # a float photo is linear; its fourth channel the mask
    from_rgba = relighter.relight(rgba, SKY, outputs=("albedo",))
    np.testing.assert_array_equal(from_rgba.layers["albedo"], from_files.layers["albedo"])
    assert from_rgba.report["stages"]["mask"]["source"] == "alpha channel"


def test_an_array_result_saves_under_the_name_image(relighter, tmp_path, monkeypatch):
    env = np.full((8, 16, 3), 0.5, np.float32)
    photo = np.dstack([np.full((64, 48, 3), 0.3, np.float32), np.zeros((64, 48), np.float32)])
    photo[10:60, 12:36, 3] = 1.0
    result = relighter.relight(photo, env, outputs=("relit", "albedo"), method="sh9")
    written = result.save(tmp_path / "out")
    assert {p.name for p in written.values()} == {"image.png", "image_albedo.png"}
    monkeypatch.chdir(tmp_path)
    assert set(result.save("image.png").values()) == {Path("image.png"), Path("image_albedo.png")}


def test_save_refuses_an_existing_file_when_asked_and_never_the_photo(relighter, tmp_path):
    photo = tmp_path / "skier.jpg"
    photo.write_bytes(PHOTO.read_bytes())
    result = relighter.relight(photo, SKY, mask=MASK, outputs=("relit",), method="sh9")
    with pytest.raises(OutputError, match="overwrite the input"):
        result.save(tmp_path / "skier.jpg")
    result.save(tmp_path / "out.png")
    with pytest.raises(UsageError, match="output exists"):
        result.save(tmp_path / "out.png", overwrite=False)
    assert photo.read_bytes() == PHOTO.read_bytes()


@pytest.mark.parametrize("options, word", [
    ({"outputs": ("relit", "albedos")}, "albedos"), ({"method": "pathtrace"}, "method"),
    ({"resolution": 8}, "resolution"), ({"resolution": 256.5}, "resolution"), ({"spp": 0}, "spp"),
    ({"spp": 8, "target_error": 0.1}, "spp and target_error"), ({"seed": -1}, "seed"),
    ({"background": "pink"}, "background"), ({"exposure": float("nan")}, "exposure"),
    ({"colour": 1}, "unknown option"), ({"turntable": 4}, "unknown option")])
def test_bad_options_are_usage_errors_naming_the_option(relighter, options, word):
    with pytest.raises(UsageError, match=word):
        relighter.relight(PHOTO, SKY, **options)


def test_bad_arrays_are_input_errors(relighter):
    with pytest.raises(InputError, match="image array"):
        relighter.relight(np.zeros((4, 5, 2), np.float32), SKY)
    with pytest.raises(InputError, match="mask array"):
        relighter.relight(np.zeros((64, 64, 3), np.float32), SKY, mask=np.ones((32, 32), np.float32))
    with pytest.raises(InputError, match="not 2:1"):
        relighter.relight(np.zeros((64, 64, 3), np.float32), np.ones((8, 8, 3), np.float32))


def test_warnings_reach_the_caller_and_the_report(relighter):
    env = np.zeros((8, 16, 3), np.float32)  # no light: a warning, a black person
    photo = np.dstack([np.full((64, 48, 3), 0.3, np.float32), np.ones((64, 48), np.float32)])
    photo[:4, :, 3] = 0.0
    with pytest.warns(RelightWarning, match="all black"):
        result = relighter.relight(photo, env, outputs=("relit",), method="sh9")
    assert any("all black" in w for w in result.report["warnings"])
    assert json.dumps(result.report)  # the report is JSON, as the CLI's


def test_the_options_of_a_relighter_are_its_calls_defaults(tmp_path):
    relighter = relightcli.Relighter(threads=1, resolution=64, method="sh9", outputs=("relit", "albedo"))
    result = relighter.relight(PHOTO, SKY, mask=MASK)
    assert result.options.resolution == 64 and set(result.layers) == {"relit", "albedo"}
    assert relighter.relight(PHOTO, SKY, mask=MASK, outputs=("mask",)).options.outputs == ("mask",)

