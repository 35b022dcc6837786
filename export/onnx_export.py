"""Export the relighting nets to ONNX and check them against torch (timm's utils/onnx.py pattern).

`export_onnx` writes the graph (opset >= 17, dynamic N/H/W where the contract says so), stores
the I/O contract in the model's metadata_props (key "relightcli.contract", JSON), runs
`onnx.checker.check_model`, and returns the `models/manifest.json` entry (with sha256).
`parity` compares ONNX Runtime against torch on the same realistic input (`person_like_inputs`).
`quantize_int8` is the optional QDQ static quantisation; whether to ship its output is decided
later by the validation rule (< 0.3 dB drop).

The legacy TorchScript exporter (`dynamo=False`) is used: the dynamo exporter needs onnxscript,
which the project does not depend on; the legacy one handles every op these nets use.

    python -m export.onnx_export --size small --out models   # random weights, for plumbing tests
"""

from __future__ import annotations

import argparse
import io
import json
import warnings
from pathlib import Path
from typing import Iterable

import numpy as np
import onnx
import torch

from export.nets import FAMILIES, build_net
from export.nets.contract import IOContract
from export.manifest import update_manifest
from relightcli.nets.manifest import sha256_file

OPSET = 17
METADATA_KEY = "relightcli.contract"
SYMBOLIC_DIMS = {"N", "H", "W"}


def dynamic_axes(contract: IOContract) -> dict[str, dict[int, str]]:
    """torch.onnx dynamic_axes from the symbolic dims of the contract ("N", "H", "W")."""
    axes = {}
    for t in contract.inputs + contract.outputs:
        dims = {k: d for k, d in enumerate(t.shape) if d in SYMBOLIC_DIMS}
        if dims:
            axes.setdefault(t.name, {}).update(dims)
    return axes


def person_like_inputs(contract: IOContract, height: int, width: int, seed: int = 0) -> dict[str, np.ndarray]:
    """Realistic NCHW float32 inputs for `contract`: a smooth background with a person-like
    blob (head ellipse over a body ellipse), normals of that ellipsoid, AO darker at its rim, HDR
    shading with a lit side and a shadow. Not noise: parity on noise hides real differences
    in smooth regions and exaggerates others."""
    rng = np.random.default_rng(seed)
    y, x = np.meshgrid(np.linspace(-1, 1, height, dtype=np.float32),
                       np.linspace(-1, 1, width, dtype=np.float32), indexing="ij")
    body = ((x / 0.35) ** 2 + ((y - 0.15) / 0.7) ** 2)
    head = ((x / 0.15) ** 2 + ((y + 0.65) / 0.18) ** 2)
    r2 = np.minimum(body, head)
    mask = (r2 < 1).astype(np.float32)
    nz = np.sqrt(np.clip(1 - r2, 0, 1))
    gx = np.where(body < head, x / 0.35, x / 0.15)
    gy = np.where(body < head, -(y - 0.15) / 0.7, -(y + 0.65) / 0.18)
    normal = np.stack([gx, gy, nz]) / np.sqrt(gx**2 + gy**2 + nz**2 + 1e-8)
    normal = normal * mask
    colour = rng.uniform(0.2, 0.8, size=(3, 1, 1)).astype(np.float32)
    background = np.stack([0.3 + 0.2 * y, 0.4 + 0.1 * x, 0.5 - 0.1 * y * x])
    texture = 0.05 * np.sin(12 * x + 7 * y)
    image = np.clip(mask * (colour * (0.5 + 0.5 * nz) + texture) + (1 - mask) * background, 0, 1)
    ao = np.clip(1 - 0.6 * (1 - nz) * mask, 0, 1)[None]
    shading = (0.2 + 3.0 * np.clip(normal[0] * 0.7 + normal[2] * 0.7, 0, None)) * ao[0]
    shading = np.stack([shading, 0.9 * shading, 0.8 * shading])
    # a fitted body's prior (relightcli.nets.geometry.prior_channels): the ellipsoid's normals,
    # its back mirrored in z, depths of a 0.3-thick slab, coverage
    back = normal * np.array([1, 1, -1], np.float32)[:, None, None]
    prior = np.concatenate([normal, back, 0.15 * nz[None] * mask, -0.15 * nz[None] * mask, mask[None]])
    library = {
        "image": image, "normal": normal, "ao": ao, "coarse_shading": shading, "prior": prior,
        "body_shading": shading, "face_shading": shading * (1 + 0.1 * np.cos(9 * x)),
    }
    feeds = {}
    for t in contract.inputs:
        if t.name not in library:
            raise KeyError(f"no realistic example for input {t.name!r}")
        value = library[t.name]
        if t.name == "prior" and t.shape[1] == prior.shape[0] + 1:  # the AO prior: the body's AO too
            value = np.concatenate([prior, ao * mask[None]])
        feeds[t.name] = value[None].astype(np.float32)
    return feeds


def export_onnx(net: torch.nn.Module, path: str | Path, height: int = 256, width: int = 256,
                opset: int = OPSET, extra: dict | None = None) -> dict:
    """Export `net` (with `io_contract()`) to `path`; returns its manifest entry.

    height, width: the trace size.
    extra: fields merged into the entry (training_data, metrics, ...).
    """
    if opset < 17:
        raise ValueError(f"opset must be >= 17, got {opset}")
    path = Path(path)
    contract = net.io_contract()
    net = net.eval()
    feeds = person_like_inputs(contract, height, width)
    args = tuple(torch.from_numpy(feeds[t.name]) for t in contract.inputs)
    buffer = io.BytesIO()
    with torch.no_grad(), warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=DeprecationWarning)  # legacy exporter notice
        torch.onnx.export(net, args, buffer, dynamo=False, opset_version=opset,
                          input_names=[t.name for t in contract.inputs],
                          output_names=[t.name for t in contract.outputs],
                          dynamic_axes=dynamic_axes(contract), do_constant_folding=True)
    model = onnx.load_from_string(buffer.getvalue())
    contract_dict = contract.to_dict()
    onnx.helper.set_model_props(model, {METADATA_KEY: json.dumps(contract_dict, sort_keys=True),
                                        "relightcli.multiple": str(contract.multiple)})
    model.producer_name = "relightcli.export"
    onnx.checker.check_model(model, full_check=True)
    path.parent.mkdir(parents=True, exist_ok=True)
    onnx.save(model, path)
    entry = {
        "file": path.name,
        "sha256": sha256_file(path),
        "inputs": [{k: t[k] for k in ("name", "shape", "dtype")} for t in contract_dict["inputs"]],
        "outputs": [{k: t[k] for k in ("name", "shape", "dtype")} for t in contract_dict["outputs"]],
        "multiple": contract.multiple,
        "colour_space": contract.colour_space,
        "normalisation": contract.normalisation,
        "config": {"family": contract.family, **contract.config},
        "training_data": {},
        "metrics": {},
    }
    entry.update(extra or {})
    return entry


def parity(net: torch.nn.Module, path: str | Path, feeds: dict[str, np.ndarray]) -> dict[str, float]:
    """Max |ONNX Runtime - torch| per output, fp32, on the same NCHW feeds (CPU, 1 thread)."""
    import onnxruntime as ort

    contract = net.io_contract()
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    session = ort.InferenceSession(str(path), sess_options=options, providers=["CPUExecutionProvider"])
    names = [t.name for t in contract.outputs]
    ort_out = session.run(names, feeds)
    with torch.no_grad():
        torch_out = net.eval()(*(torch.from_numpy(feeds[t.name]) for t in contract.inputs))
    if isinstance(torch_out, torch.Tensor):
        torch_out = (torch_out,)
    return {n: float(np.max(np.abs(o - t.numpy()))) for n, o, t in zip(names, ort_out, torch_out)}


class _CalibrationReader:
    """onnxruntime.quantization CalibrationDataReader over an iterable of feed dicts."""

    def __init__(self, feeds: Iterable[dict[str, np.ndarray]]):
        self._it = iter(feeds)

    def get_next(self):
        return next(self._it, None)


def quantize_int8(src: str | Path, dst: str | Path, calibration: Iterable[dict[str, np.ndarray]]) -> Path:
    """Static int8 QDQ quantisation of `src` (per-channel weights, int8 activations) calibrated
    on `calibration` feeds; writes `dst`. Accepting it (< 0.3 dB drop) is the caller's call."""
    from onnxruntime.quantization import QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    dst = Path(dst)
    prepared = dst.with_suffix(".prep.onnx")
    # symbolic shape inference cannot resolve the dynamic H x W of these nets; ONNX shape
    # inference suffices for the QDQ pass
    quant_pre_process(str(src), str(prepared), skip_symbolic_shape=True)
    try:
        quantize_static(str(prepared), str(dst), _CalibrationReader(calibration),
                        quant_format=QuantFormat.QDQ, per_channel=True,
                        activation_type=QuantType.QInt8, weight_type=QuantType.QInt8)
    finally:
        prepared.unlink(missing_ok=True)
    return dst


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="small", help="config size: paper or small")
    parser.add_argument("--out", default="models", help="models directory")
    parser.add_argument("--families", nargs="*", default=sorted(FAMILIES))
    args = parser.parse_args(argv)
    torch.manual_seed(0)
    for family in args.families:
        net = build_net(family, args.size)
        entry = export_onnx(net, Path(args.out) / f"{family}.onnx",
                            extra={"training_data": {"note": "random weights (untrained)"}})
        update_manifest(args.out, family, entry)


if __name__ == "__main__":
    main()
