"""Helpers that build tiny ONNX models with the onnx helper API and write a manifest (no torch)."""

from __future__ import annotations

import json

import pytest

onnx = pytest.importorskip("onnx")
from onnx import TensorProto, helper  # noqa: E402

from relightcli.nets.manifest import sha256_file  # noqa: E402


def tensor(name: str, channels: int | str = 3):
    return helper.make_tensor_value_info(name, TensorProto.FLOAT, ["N", channels, "H", "W"])


def save_graph(path, nodes, inputs, outputs, opset: int = 17, initializer=()):
    graph = helper.make_graph(nodes, "toy", inputs, outputs, initializer=list(initializer))
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", opset)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, path)
    return path


def scalar(name: str, value: float):
    """A float constant for a graph's initializer list."""
    return helper.make_tensor(name, TensorProto.FLOAT, [], [value])


def contract(names_channels):
    return [{"name": n, "shape": ["N", c, "H", "W"], "dtype": "float32"} for n, c in names_channels]


def write_manifest(directory, models: dict):
    """models: name -> entry without sha256 (computed here from the file unless given)."""
    table = {}
    for name, entry in models.items():
        entry = dict(entry)
        path = directory / entry["file"]
        entry.setdefault("sha256", sha256_file(path) if path.is_file() else "0" * 64)
        entry.setdefault("multiple", 16)
        table[name] = entry
    (directory / "manifest.json").write_text(json.dumps({"version": 1, "models": table}))
