"""Fixtures: tiny ONNX models plus a manifest in tmp_path (no torch)."""

from __future__ import annotations

import pytest

onnx = pytest.importorskip("onnx")
from onnx import helper  # noqa: E402
from onnx_toys import contract, save_graph, scalar, tensor, write_manifest  # noqa: E402


@pytest.fixture
def ao_model_dir(tmp_path):
    """Model "ao": ao = mean of the image over channels (an identity-like graph for layouts)."""
    save_graph(tmp_path / "ao.onnx",
               [helper.make_node("ReduceMean", ["image"], ["ao"], axes=[1], keepdims=1)],
               [tensor("image", 3)], [tensor("ao", 1)])
    write_manifest(tmp_path, {"ao": {"file": "ao.onnx", "inputs": contract([("image", 3)]),
                                     "outputs": contract([("ao", 1)])}})
    return tmp_path


@pytest.fixture
def body_model_dir(tmp_path):
    """Model "body_refine": shading = coarse_shading * (1 + 0 * mean(ao)), i.e. identity."""
    nodes = [
        helper.make_node("ReduceMean", ["ao"], ["ao_mean"], axes=[1, 2, 3], keepdims=1),
        helper.make_node("Mul", ["ao_mean", "zero"], ["ao_zero"]),
        helper.make_node("Add", ["coarse_shading", "ao_zero"], ["shading"]),
    ]
    save_graph(tmp_path / "body.onnx", nodes, [tensor("coarse_shading", 3), tensor("ao", 1)],
               [tensor("shading", 3)], initializer=[scalar("zero", 0.0)])
    write_manifest(tmp_path, {"body_refine": {
        "file": "body.onnx", "inputs": contract([("coarse_shading", 3), ("ao", 1)]),
        "outputs": contract([("shading", 3)])}})
    return tmp_path
