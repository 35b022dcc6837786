"""The whole product on the shipped example with real ONNX sessions: small random-weight nets
exported into a temporary models folder (what the networks say is noise; what is checked is
the plumbing: every stage runs, every layer is written at the photo's size, finite, reported)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from relightcli.cli import main
from relightcli.io.images import read_image

torch = pytest.importorskip("torch")

REPO = Path(__file__).resolve().parents[1]
EXAMPLES = REPO / "examples"


@pytest.fixture(scope="module")
def random_models(tmp_path_factory):
    from export.nets import build_net
    from export.manifest import update_manifest
    from export.onnx_export import export_onnx

    folder = tmp_path_factory.mktemp("models")
    shutil.copy(REPO / "models" / "manifest.json", folder / "manifest.json")
    for name in ("face_model.npz", "face_refine.onnx", "person_detector.onnx", "pose_landmarks.onnx",
                 "face_detector.onnx", "face_mesh.onnx", "face_correspondence.npz",  # the face path as shipped
                 "body_model.npz"):
        shutil.copy(REPO / "models" / name, folder / name)
    torch.manual_seed(0)
    torch.set_num_threads(1)
    for family in ("geometry", "ao", "delight", "body_refine"):
        entry = export_onnx(build_net(family, "small"), folder / f"{family}.onnx", height=64, width=64)
        update_manifest(folder, family, entry)
    return folder


def test_every_layer_of_the_example(random_models, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("RELIGHT_MODELS_DIR", str(random_models))
    out = tmp_path / "skier.png"
    layers = "relit,albedo,normal,ao,shading,mask,mesh,light,preview"
    code = main([str(EXAMPLES / "skier.jpg"), "--mask", str(EXAMPLES / "skier_mask.png"),
                 "--hdr", str(EXAMPLES / "noon_grass.hdr"), "-o", str(out), "--outputs", layers,
                 "--resolution", "64", "--spp", "4", "--threads", "1", "--albedo", "solve", "--json"])
    report = json.loads(capsys.readouterr().out)
    assert code == 0, report
    item = report["items"][0]
    assert item["plan"]["run"] == ["people", "mask", "crop", "body", "body_maps", "geometry", "ao", "reconstruct",
                                   "delight", "face", "raytrace", "refine", "face_refine", "compose"]
    assert item["stages"]["delight"]["light"] == "inverse rendering" and item["stages"]["delight"]["pixels"] > 0
    # The skier's face (goggles, 30 px) is found by the face mesh in the head square his pose places
    face, = item["stages"]["face"]["faces"]
    assert face["path"] == "face mesh" and face["head"] == "person 0" and item["stages"]["face"]["fitted"] == 1
    assert set(item["seconds"]) >= set(item["plan"]["run"]) | {"load", "write", "total"}
    assert item["stages"]["raytrace"]["rays"] > 0
    photo = read_image(EXAMPLES / "skier.jpg")
    for name in ("relit", "albedo", "normal", "ao", "shading", "mask"):
        image = read_image(item["outputs"][name])
        assert image.rgb.shape == photo.rgb.shape, name
        assert np.isfinite(image.rgb).all(), name
    light = read_image(item["outputs"]["light"]).rgb
    assert light.shape == (16, 32, 3) and np.isfinite(light).all() and light.min() >= 0
    import trimesh

    mesh = trimesh.load(item["outputs"]["mesh"], process=False)
    assert mesh.is_watertight and len(mesh.faces) > 100
    # Outside the person the relit photo keeps the original (background keep).
    relit = read_image(item["outputs"]["relit"]).rgb
    mask = read_image(EXAMPLES / "skier_mask.png", srgb=False).rgb[..., 0]
    outside = mask < 0.01
    np.testing.assert_allclose(relit[outside], photo.rgb[outside], atol=2e-3)


@pytest.mark.parametrize("method", ["sh9", "raytrace-norefine"])
def test_methods_skip_what_they_do_not_need(random_models, tmp_path, capsys, monkeypatch, method):
    monkeypatch.setenv("RELIGHT_MODELS_DIR", str(random_models))
    code = main([str(EXAMPLES / "skier.jpg"), "--mask", str(EXAMPLES / "skier_mask.png"),
                 "--hdr", str(EXAMPLES / "kloofendal_overcast.hdr"), "-o", str(tmp_path / "o.exr"),
                 "--method", method, "--resolution", "64", "--spp", "4", "--threads", "1", "--json"])
    item = json.loads(capsys.readouterr().out)["items"][0]
    assert code == 0, item
    assert "refine" not in item["plan"]["run"] and "ao" not in item["plan"]["run"]
    relit = read_image(tmp_path / "o.exr").rgb
    assert np.isfinite(relit).all() and relit.max() > 0


def test_several_maps_write_the_lit_layers_once_per_map_as_single_runs_do(random_models, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("RELIGHT_MODELS_DIR", str(random_models))
    from relightcli.io.images import write_image

    overcast = tmp_path / "grey sky.hdr"  # a name with a space: used as it is
    write_image(overcast, np.full((16, 32, 3), 0.7, np.float32))
    common = [str(EXAMPLES / "skier.jpg"), "--mask", str(EXAMPLES / "skier_mask.png"), "--outputs",
              "relit,albedo,shading,preview", "--method", "raytrace-norefine", "--resolution", "48",
              "--spp", "4", "--threads", "1", "--json"]
    code = main(common + ["--hdr", str(EXAMPLES / "noon_grass.hdr"), "--hdr", str(overcast),
                          "-o", str(tmp_path / "both" / "s.png")])
    item = json.loads(capsys.readouterr().out)["items"][0]
    assert code == 0, item
    assert item["stages"]["scene_builds"] == 1
    assert sorted(p.name for p in (tmp_path / "both").iterdir()) == [
        "s_albedo.png", "s_grey sky.png", "s_noon_grass.png", "s_preview_grey sky.png",
        "s_preview_noon_grass.png", "s_shading_grey sky.exr", "s_shading_noon_grass.exr"]
    for env, name in ((EXAMPLES / "noon_grass.hdr", "noon_grass"), (overcast, "grey sky")):
        alone = tmp_path / name / "s.png"
        assert main(common + ["--hdr", str(env), "-o", str(alone)]) == 0
        capsys.readouterr()
        for layer in ("", "_shading", "_preview"):
            ext = ".exr" if layer == "_shading" else ".png"
            assert (tmp_path / "both" / f"s{layer}_{name}{ext}").read_bytes() == (alone.parent / f"s{layer}{ext}").read_bytes()
        assert (tmp_path / "both" / "s_albedo.png").read_bytes() == (alone.parent / "s_albedo.png").read_bytes()


def test_turntable_writes_numbered_frames_and_builds_the_scene_once(random_models, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("RELIGHT_MODELS_DIR", str(random_models))
    code = main([str(EXAMPLES / "skier.jpg"), "--mask", str(EXAMPLES / "skier_mask.png"),
                 "--hdr", str(EXAMPLES / "noon_grass.hdr"), "-o", str(tmp_path / "s.png"),
                 "--outputs", "relit,albedo", "--turntable", "3", "--method", "raytrace-norefine",
                 "--resolution", "48", "--spp", "4", "--threads", "1", "--json"])
    item = json.loads(capsys.readouterr().out)["items"][0]
    assert code == 0, item
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s_albedo.png", "s_turn000.png", "s_turn001.png", "s_turn002.png"]
    assert item["stages"]["scene_builds"] == 1
    frames = [read_image(tmp_path / f"s_turn{k:03d}.png").rgb for k in range(3)]
    assert not np.allclose(frames[0], frames[1])
