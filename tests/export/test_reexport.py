"""The body refinement's AFF computed without its concat is the same function, and
`export.reexport` rebuilds a shipped file from its own weights with today's code (read by name,
or, where the exporter folded the BatchNorms into the convolutions, by their order)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx")

import torch.nn.functional as F  # noqa: E402

from export.manifest import update_manifest  # noqa: E402
from export.nets import build_net  # noqa: E402
from export.nets.body_refine import AFF  # noqa: E402
from export.onnx_export import export_onnx  # noqa: E402
from export.reexport import net_from_onnx, reexport  # noqa: E402
from relightcli.nets.manifest import sha256_file  # noqa: E402


def concat_forward(self, feats, level):
    """AFF's forward as the shipped body refinement was exported with it (its weights then
    kept their parameter names in the graph)."""
    size = feats[level].shape[-2:]
    return self.body(torch.cat([f if k == level else F.interpolate(f, size=size, mode="bilinear", align_corners=False)
                                for k, f in enumerate(feats)], dim=1))


@pytest.mark.parametrize("level", [0, 1, 2])
def test_aff_equals_its_concat_form(level):
    """body(concat of every level bilinearly resampled to `level`'s size): the definition the
    net was trained with, against the forward that never builds the concat."""
    torch.manual_seed(level)
    widths = [4, 8, 16]
    aff = AFF(sum(widths), widths[level]).eval()
    with torch.no_grad():
        aff.body[0][0].bias.normal_()  # a bias that matters: resampling must carry it unchanged
        feats = [torch.randn(2, w, 40 // 2**k, 24 // 2**k) for k, w in enumerate(widths)]
        expected, got = concat_forward(aff, feats, level), aff(feats, level)
    assert got.shape == expected.shape
    assert torch.allclose(got, expected, atol=1e-5, rtol=1e-5)


def shipped_like(tmp_path, monkeypatch):
    """(net, path, entry): a small body refinement exported with the concat form."""
    torch.manual_seed(0)
    net = build_net("body_refine", "small").eval()
    path = tmp_path / "body_refine.onnx"
    with monkeypatch.context() as patched:
        patched.setattr(AFF, "forward", concat_forward)
        entry = export_onnx(net, path, 64, 64)
    return net, path, entry


def test_reexport_keeps_the_function_and_the_record(tmp_path, monkeypatch):
    net, path, entry = shipped_like(tmp_path, monkeypatch)
    update_manifest(tmp_path, "body_refine", {**entry, "metrics": {"shading_psnr_refined": 17.3}})
    before = sha256_file(path)
    shutil.copy(path, tmp_path / "before.onnx")

    record = reexport(path, side=64, tolerance=1e-5)

    manifest = json.loads((tmp_path / "manifest.json").read_text())["models"]["body_refine"]
    assert manifest["sha256"] == sha256_file(path)
    assert manifest["metrics"] == {"shading_psnr_refined": 17.3}  # what was measured stays
    assert manifest["reexported"]["from_sha256"] == before == record["from_sha256"]
    assert record["max_relative_difference"] <= 1e-5
    rebuilt = net_from_onnx(tmp_path / "before.onnx")
    for name, value in net.state_dict().items():  # the weights read back from the file are the net's
        assert np.array_equal(rebuilt.state_dict()[name].numpy(), value.numpy()), name
    assert not (tmp_path / "body_refine.new.onnx").exists()
    # the fused graph's convolutions do not line up with the module's: said, not guessed
    with pytest.raises(SystemExit, match="cannot be read back"):
        reexport(path, side=64, tolerance=1e-5)


def test_reexport_refuses_a_changed_function(tmp_path, monkeypatch):
    """A forward that no longer computes the file's function replaces nothing."""
    _, path, entry = shipped_like(tmp_path, monkeypatch)
    update_manifest(tmp_path, "body_refine", entry)
    before = path.read_bytes()

    def changed(self, feats, level):
        size = feats[level].shape[-2:]
        return self.body(torch.cat([F.interpolate(f, size=size, mode="nearest") for f in feats], dim=1))

    monkeypatch.setattr(AFF, "forward", changed)
    with pytest.raises(SystemExit, match="nothing replaced"):
        reexport(path, side=64, tolerance=1e-5)
    assert path.read_bytes() == before
    assert not (tmp_path / "body_refine.new.onnx").exists()


def test_the_shipped_de_lighting_net_is_read_back_from_its_folded_graph():
    """Its exporter folded every BatchNorm into the convolution before it (unnamed
    initializers) and dropped the last HRNet module's fusions no head reads: the torch module
    rebuilt from the file computes the file's function (to be fine-tuned, its checkpoint gone)."""
    from pathlib import Path

    import onnxruntime as ort

    from export.onnx_export import person_like_inputs

    path = Path(__file__).resolve().parents[2] / "models" / "delight.onnx"
    net = net_from_onnx(path)
    feeds = person_like_inputs(net.io_contract(), 96, 96, seed=5)
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    expected = session.run(None, feeds)
    with torch.no_grad():
        rebuilt = net(*(torch.from_numpy(feeds[spec.name]) for spec in net.io_contract().inputs))
    for want, got in zip(expected, rebuilt):
        assert np.abs(want - got.numpy()).max() <= 1e-5 * np.abs(want).max()
    norms = [m for m in net.modules() if isinstance(m, torch.nn.BatchNorm2d)]
    assert norms and all(float(m.running_mean.abs().max()) == 0.0 for m in norms)  # the folded ones
