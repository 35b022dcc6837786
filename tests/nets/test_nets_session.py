"""ModelSession: manifest lookup, sha256, load failures, I/O contract, threads, providers."""

from __future__ import annotations

import json

import numpy as np
import pytest

from relightcli.errors import EXIT_MISSING, MissingDependencyError, UsageError
from relightcli.nets.geometry import AONet
from relightcli.nets.manifest import list_models, load_manifest, models_dir
from relightcli.nets.session import CPU_PROVIDER, CUDA_PROVIDER, ModelSession, select_providers

from onnx_toys import contract, save_graph, tensor, write_manifest


def test_loads_and_runs(ao_model_dir):
    session = AONet(models_dir=ao_model_dir, threads=1)
    out = session.run({"image": np.ones((1, 3, 16, 32), np.float32)})
    assert out["ao"].shape == (1, 1, 16, 32)
    assert CPU_PROVIDER in session.providers


def test_sha_mismatch_names_the_file(ao_model_dir):
    manifest = json.loads((ao_model_dir / "manifest.json").read_text())
    manifest["models"]["ao"]["sha256"] = "f" * 64
    (ao_model_dir / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(MissingDependencyError, match=r"ao\.onnx.*sha256") as info:
        AONet(models_dir=ao_model_dir)
    assert info.value.exit_code == EXIT_MISSING


def test_sha_check_can_be_skipped(ao_model_dir):
    manifest = json.loads((ao_model_dir / "manifest.json").read_text())
    manifest["models"]["ao"]["sha256"] = "f" * 64
    (ao_model_dir / "manifest.json").write_text(json.dumps(manifest))
    assert AONet(models_dir=ao_model_dir, verify_sha256=False).multiple == 16


def test_missing_file_names_the_file(ao_model_dir):
    (ao_model_dir / "ao.onnx").unlink()
    with pytest.raises(MissingDependencyError, match=r"ao\.onnx.*not found"):
        AONet(models_dir=ao_model_dir)


def test_missing_manifest(tmp_path):
    with pytest.raises(MissingDependencyError, match="manifest.json"):
        AONet(models_dir=tmp_path)


def test_model_not_in_manifest(ao_model_dir):
    with pytest.raises(MissingDependencyError, match="'delight' is not in the manifest"):
        ModelSession("delight", models_dir=ao_model_dir)


def test_corrupt_file_with_matching_sha(tmp_path):
    (tmp_path / "ao.onnx").write_bytes(b"not a protobuf at all")
    write_manifest(tmp_path, {"ao": {"file": "ao.onnx", "inputs": contract([("image", 3)]),
                                     "outputs": contract([("ao", 1)])}})
    with pytest.raises(MissingDependencyError, match=r"ao\.onnx.*cannot load"):
        AONet(models_dir=tmp_path)


def test_graph_input_name_differs_from_manifest(tmp_path):
    from onnx import helper

    save_graph(tmp_path / "ao.onnx", [helper.make_node("ReduceMean", ["img"], ["ao"], axes=[1], keepdims=1)],
               [tensor("img", 3)], [tensor("ao", 1)])
    write_manifest(tmp_path, {"ao": {"file": "ao.onnx", "inputs": contract([("image", 3)]),
                                     "outputs": contract([("ao", 1)])}})
    with pytest.raises(MissingDependencyError, match=r"ao\.onnx.*graph inputs \['img'\]"):
        AONet(models_dir=tmp_path)


def test_graph_rank_differs_from_manifest(ao_model_dir):
    manifest = json.loads((ao_model_dir / "manifest.json").read_text())
    manifest["models"]["ao"]["outputs"] = [{"name": "ao", "shape": ["N", "H", "W"], "dtype": "float32"}]
    (ao_model_dir / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(MissingDependencyError, match="rank 4, manifest says 3"):
        AONet(models_dir=ao_model_dir)


def test_fixed_channel_count_differs_from_manifest(ao_model_dir):
    manifest = json.loads((ao_model_dir / "manifest.json").read_text())
    manifest["models"]["ao"]["inputs"][0]["shape"] = ["N", 4, "H", "W"]
    (ao_model_dir / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(MissingDependencyError, match="axis 1 is 3, manifest says 4"):
        AONet(models_dir=ao_model_dir)


def test_family_class_needs_its_outputs(ao_model_dir):
    manifest = json.loads((ao_model_dir / "manifest.json").read_text())
    manifest["models"]["ao"]["outputs"][0]["name"] = "occlusion"
    (ao_model_dir / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(MissingDependencyError, match=r"outputs lack \['ao'\]"):
        AONet(models_dir=ao_model_dir)


@pytest.mark.parametrize("threads", [1, 2])
def test_thread_setting_reaches_onnxruntime(ao_model_dir, threads):
    session = AONet(models_dir=ao_model_dir, threads=threads)
    assert session.session.get_session_options().intra_op_num_threads == threads


@pytest.mark.parametrize("threads", [0, -1, 1.5])
def test_bad_thread_count_is_a_usage_error(ao_model_dir, threads):
    with pytest.raises(UsageError, match="threads"):
        AONet(models_dir=ao_model_dir, threads=threads)


def test_run_rejects_size_not_divisible_by_multiple(ao_model_dir):
    session = AONet(models_dir=ao_model_dir, threads=1)
    with pytest.raises(ValueError, match="not divisible by 16"):
        session.run({"image": np.ones((1, 3, 17, 32), np.float32)})


@pytest.mark.parametrize(
    "available, expected",
    [
        (["CPUExecutionProvider"], [CPU_PROVIDER]),
        (["AzureExecutionProvider", "CPUExecutionProvider"], [CPU_PROVIDER]),
        (["CPUExecutionProvider", "CUDAExecutionProvider"], [CUDA_PROVIDER, CPU_PROVIDER]),
    ],
)
def test_select_providers_puts_cuda_first(available, expected):
    assert select_providers(available) == expected


def test_models_dir_env_override(monkeypatch, tmp_path):
    monkeypatch.setenv("RELIGHT_MODELS_DIR", str(tmp_path))
    assert models_dir() == tmp_path


def test_models_dir_default_is_next_to_package(monkeypatch):
    import relightcli
    from pathlib import Path

    monkeypatch.delenv("RELIGHT_MODELS_DIR", raising=False)
    assert models_dir() == Path(relightcli.__file__).resolve().parents[1] / "models"


def test_list_models_reports_presence_and_sha(ao_model_dir):
    write_manifest(ao_model_dir, {
        "ao": {"file": "ao.onnx", "inputs": contract([("image", 3)]), "outputs": contract([("ao", 1)])},
        "delight": {"file": "delight.onnx", "inputs": [], "outputs": []},
    })
    status = {s.name: s for s in list_models(ao_model_dir, verify=True)}
    assert (status["ao"].present, status["ao"].sha256_ok) == (True, True)
    assert (status["delight"].present, status["delight"].sha256_ok) == (False, None)


@pytest.mark.parametrize("text", ["{not json", '{"version": 2, "models": {}}', '{"version": 1}'])
def test_malformed_manifest(tmp_path, text):
    (tmp_path / "manifest.json").write_text(text)
    with pytest.raises(MissingDependencyError, match="manifest"):
        load_manifest(tmp_path)


def test_manifest_entry_without_sha(tmp_path):
    (tmp_path / "manifest.json").write_text(json.dumps({"version": 1, "models": {"ao": {
        "file": "ao.onnx", "inputs": [], "outputs": [], "multiple": 16}}}))
    with pytest.raises(MissingDependencyError, match="lacks sha256"):
        load_manifest(tmp_path)


@pytest.mark.parametrize("calibration", [{"albedo_gain": 0}, {"albedo_gain": "0.85"}, {"albedo_gain": float("nan")}, [0.85]])
def test_a_calibration_that_is_not_a_positive_gain_names_the_manifest(tmp_path, calibration):
    (tmp_path / "manifest.json").write_text(json.dumps({"version": 1, "models": {"delight": {
        "file": "delight.onnx", "sha256": "0" * 64, "inputs": [], "outputs": [], "multiple": 32,
        "calibration": calibration}}}))
    with pytest.raises(MissingDependencyError, match="albedo_gain") as error:
        load_manifest(tmp_path)
    assert "manifest.json" in str(error.value)


def test_each_input_shape_runs_on_a_session_built_for_it_whatever_was_prepared(ao_model_dir):
    """run_size: the session for (1, C, S, S) is built up front; any other shape gets its own the
    first time it comes. A shape gives the same bytes whichever sizes the process prepared."""
    prepared, unprepared = AONet(models_dir=ao_model_dir, threads=1, run_size=32), AONet(models_dir=ao_model_dir, threads=1)
    assert list(prepared.session.get_inputs()[0].shape) == [1, 3, 32, 32]
    rng = np.random.default_rng(0)
    for shape in ((1, 3, 32, 32), (1, 3, 16, 32), (2, 3, 32, 32), (1, 3, 32, 32)):
        image = rng.random(shape, dtype=np.float32)
        a, b = prepared.run({"image": image})["ao"], unprepared.run({"image": image})["ao"]
        assert a.tobytes() == b.tobytes()
        np.testing.assert_allclose(a, image.mean(axis=1, keepdims=True), rtol=1e-6)
    assert sorted(prepared._shaped) == sorted(unprepared._shaped) == [
        (("N", 1), ("H", 16), ("W", 32)), (("N", 1), ("H", 32), ("W", 32)), (("N", 2), ("H", 32), ("W", 32))]


def test_each_family_is_built_for_the_side_it_runs_at_in_the_crop():
    from relightcli.stages.frame import Models

    at_512, at_200 = Models(1, 512), Models(1, 200)
    assert at_512.run_size("body_refine") == 512  # the refinement runs at the working side
    assert at_512.run_size("delight") == at_512.run_size("geometry_prior") == 256  # net_side
    assert at_512.run_size("face_refine") == 128  # the face crop's side
    assert at_512.run_size("pose_landmarks") is None  # a fixed-shape graph
    multiple = load_manifest()["delight"].multiple  # a side the net cannot take is padded up
    assert at_200.run_size("delight") % multiple == 0 and 200 <= at_200.run_size("delight") < 200 + multiple
    assert Models(1).run_size("body_refine") is None  # no resolution given: any side
