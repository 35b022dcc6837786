"""Every net family at small size, random weights: ONNX export passes the checker, carries its
contract, and ONNX Runtime matches torch (fp32 max abs diff <= 1e-4) on realistic inputs."""

from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx")

from export.nets import FAMILIES, build_net  # noqa: E402
from export.nets.blocks import count_parameters  # noqa: E402
from export.onnx_export import METADATA_KEY, export_onnx, main, parity, person_like_inputs, quantize_int8  # noqa: E402
from relightcli.nets.manifest import load_manifest, sha256_file  # noqa: E402

torch.set_num_threads(1)
PARITY_TOL = 1e-4


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """family -> (net, onnx path, manifest entry), exported once per module."""
    out = tmp_path_factory.mktemp("onnx")
    result = {}
    for family in FAMILIES:
        torch.manual_seed(0)
        net = build_net(family, "small").eval()
        path = out / f"{family}.onnx"
        result[family] = (net, path, export_onnx(net, path, 64, 64))
    return result


def parity_size(multiple):
    """A size other than the export's and not square, so the H/W axes must really be dynamic."""
    return 2 * multiple * 3, multiple * 5


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_onnx_runtime_matches_torch(exported, family):
    net, path, entry = exported[family]
    feeds = person_like_inputs(net.io_contract(), *parity_size(entry["multiple"]), seed=1)
    diffs = parity(net, path, feeds)
    assert max(diffs.values()) <= PARITY_TOL, diffs


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_contract_is_in_metadata_and_manifest_entry(exported, family):
    net, path, entry = exported[family]
    props = {p.key: p.value for p in onnx.load(path).metadata_props}
    stored = json.loads(props[METADATA_KEY])
    assert [t["name"] for t in stored["inputs"]] == [t["name"] for t in entry["inputs"]]
    assert stored["multiple"] == entry["multiple"] == net.io_contract().multiple
    assert entry["sha256"] == sha256_file(path)


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_small_config_is_small(family):
    assert count_parameters(build_net(family, "small")) <= 1_000_000


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_export_declares_dynamic_hw(exported, family):
    net, path, _ = exported[family]
    graph_input = onnx.load(path).graph.input[0]
    dims = [d.dim_param or d.dim_value for d in graph_input.type.tensor_type.shape.dim]
    assert dims[0] == "N" and dims[2:] == ["H", "W"]


def _runtime_predict(family, models_dir, h, w):
    """Run the family's runtime class on an odd-sized (h, w) person-like input."""
    from relightcli.nets.delight import DelightNet
    from relightcli.nets.geometry import AONet, AOPriorNet, GeometryNet, GeometryPriorNet
    from relightcli.nets.refine import BodyRefineNet, FaceRefineNet

    feeds = person_like_inputs(build_net(family, "small").io_contract(), h, w)
    hwc = {k: np.ascontiguousarray(v[0].transpose(1, 2, 0)) for k, v in feeds.items()}
    if family == "geometry":
        return GeometryNet(models_dir=models_dir, threads=1).predict(hwc["image"]).front_normal
    if family == "geometry_prior":
        return GeometryPriorNet(models_dir=models_dir, threads=1).predict(hwc["image"], hwc["prior"]).front_normal
    if family == "ao":
        return AONet(models_dir=models_dir, threads=1).predict(hwc["image"])
    if family == "ao_prior":
        return AOPriorNet(models_dir=models_dir, threads=1).predict(hwc["image"], hwc["prior"])
    if family == "delight":
        return DelightNet(models_dir=models_dir, threads=1).predict(hwc["image"], hwc["normal"]).albedo
    if family == "body_refine":
        return BodyRefineNet(models_dir=models_dir, threads=1).predict(hwc["coarse_shading"], hwc["ao"][..., 0])
    return FaceRefineNet(models_dir=models_dir, threads=1).predict(hwc["body_shading"], hwc["face_shading"], 2.0)


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_exported_models_load_through_the_runtime(tmp_path, family):
    torch.manual_seed(0)
    main(["--families", family, "--out", str(tmp_path)])
    assert set(load_manifest(tmp_path)) == {family}
    out = _runtime_predict(family, tmp_path, 50, 70)
    assert out.shape[:2] == (50, 70) and out.dtype == np.float32 and np.isfinite(out).all()


def test_int8_quantisation_runs_and_stays_close(exported, tmp_path):
    import onnxruntime as ort

    net, path, _ = exported["face_refine"]
    calibration = [person_like_inputs(net.io_contract(), 64, 64, seed=s) for s in range(4)]
    quantised = quantize_int8(path, tmp_path / "face_int8.onnx", calibration)
    feeds = person_like_inputs(net.io_contract(), 64, 64, seed=9)
    ref = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(None, feeds)[0]
    got = ort.InferenceSession(str(quantised), providers=["CPUExecutionProvider"]).run(None, feeds)[0]
    assert any(n.op_type == "QuantizeLinear" for n in onnx.load(quantised).graph.node)
    assert np.isfinite(got).all()
    # int8 of an untrained net: only a sanity bound (relative to the output's range).
    assert np.abs(got - ref).max() <= 0.1 * (ref.max() - ref.min() + 1e-6)
