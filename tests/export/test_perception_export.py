"""The TFLite -> ONNX conversion of the MediaPipe models: sparse decoding and padding by
construction, then the whole export command against the shipped files (same bytes) and
against the TFLite interpreter on real photos (parity)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from export.perception.tflite_onnx import DENSE, HALF_MIN_SIZE, SPARSE_CSR, DimMetadata, Graph, densify, same_pads

REPO = Path(__file__).resolve().parents[2]


def csr(matrix: np.ndarray):
    """Row pointers, column indices and values of a 2-D matrix's nonzeros."""
    rows, cols = np.nonzero(matrix)
    segments = np.concatenate([[0], np.cumsum(np.bincount(rows, minlength=matrix.shape[0]))])
    return segments, cols, matrix[rows, cols]


def test_densify_decodes_a_csr_matrix():
    rng = np.random.default_rng(0)
    matrix = rng.normal(size=(6, 9)) * (rng.uniform(size=(6, 9)) < 0.3)
    segments, cols, values = csr(matrix)
    levels = [DimMetadata(DENSE, dense_size=6), DimMetadata(SPARSE_CSR, segments=segments, indices=cols)]
    np.testing.assert_array_equal(densify(values, (6, 9), [0, 1], [], levels), matrix)


def test_densify_decodes_a_conv_weight_sparse_along_its_last_dim():
    # The layout of the person detector's weights: (O, 1, 1, I), dense O, 1, 1, CSR over I
    rng = np.random.default_rng(1)
    weight = (rng.normal(size=(5, 1, 1, 8)) * (rng.uniform(size=(5, 1, 1, 8)) < 0.5)).astype(np.float16)
    segments, cols, values = csr(weight.reshape(5, 8))
    levels = [DimMetadata(DENSE, dense_size=5), DimMetadata(DENSE, dense_size=1), DimMetadata(DENSE, dense_size=1),
              DimMetadata(SPARSE_CSR, segments=segments, indices=cols)]
    got = densify(values, weight.shape, [0, 1, 2, 3], [], levels)
    assert got.dtype == np.float16
    np.testing.assert_array_equal(got, weight)


def test_densify_decodes_block_sparsity():
    # A 4x6 matrix in 2x3 blocks; only blocks (0, 1) and (1, 0) are stored, each dense
    matrix = np.zeros((4, 6), np.float32)
    matrix[0:2, 3:6] = np.arange(6).reshape(2, 3) + 1
    matrix[2:4, 0:3] = np.arange(6).reshape(2, 3) + 10
    values = np.concatenate([matrix[0:2, 3:6].ravel(), matrix[2:4, 0:3].ravel()])
    levels = [DimMetadata(DENSE, dense_size=2),                                    # block rows
              DimMetadata(SPARSE_CSR, segments=np.array([0, 1, 2]), indices=np.array([1, 0])),  # block cols
              DimMetadata(DENSE, dense_size=2), DimMetadata(DENSE, dense_size=3)]  # inside a block
    np.testing.assert_array_equal(densify(values, (4, 6), [0, 1, 2, 3], [0, 1], levels), matrix)


@pytest.mark.parametrize("size, kernel, stride, expected", [
    (224, 3, 2, (0, 1)),   # even size, stride 2: TensorFlow puts the odd pixel after
    (112, 5, 1, (2, 2)),
    (7, 3, 2, (1, 1)),
    (8, 1, 1, (0, 0)),
])
def test_same_pads_follow_tensorflow(size, kernel, stride, expected):
    assert same_pads(size, kernel, stride) == expected
    before, after = expected
    assert (size + before + after - kernel) // stride + 1 == -(-size // stride)  # SAME keeps ceil(size / stride)


def test_fp16_weights_are_stored_as_fp16_and_cast_back_to_the_same_values():
    import onnx
    from onnx import helper, numpy_helper
    from onnxruntime import InferenceSession

    rng = np.random.default_rng(0)
    half = rng.normal(size=(4, HALF_MIN_SIZE)).astype(np.float16).astype(np.float32)
    full = half + np.float32(1e-6)  # not a float16 any more
    graph = Graph()
    names = [graph.constant(a) for a in (half, full, half[:1, :8])]
    stored = {i.name: numpy_helper.to_array(i).dtype for i in graph.initializers}
    assert stored == {f"{names[0]}_fp16": np.float16, names[1]: np.float32, names[2]: np.float32}
    outputs = [helper.make_tensor_value_info(n, onnx.TensorProto.FLOAT, None) for n in names]
    model = helper.make_model(helper.make_graph(graph.nodes, "g", [], outputs, graph.initializers),
                              opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    got = InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"]).run(None, {})
    for value, want in zip(got, (half, full, half[:1, :8])):
        assert value.dtype == np.float32 and np.array_equal(value, want)


# ----------------------------------------------------------------------------- the export command
@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """`python -m export.perception` into a fresh folder (downloads the pinned wheel with pip
    once into export/.cache), with the parity check."""
    pytest.importorskip("tflite")
    pytest.importorskip("ai_edge_litert")
    from export.perception.build import main

    out = tmp_path_factory.mktemp("perception")
    main(["--out", str(out)])
    return out


def test_the_export_reproduces_the_shipped_models_byte_for_byte(exported):
    from export.perception.build import MODELS

    built = json.loads((exported / "manifest.json").read_text())["models"]
    shipped = json.loads((REPO / "models" / "manifest.json").read_text())["models"]
    for spec in MODELS:
        assert built[spec.name]["sha256"] == shipped[spec.name]["sha256"], spec.name
        assert (exported / spec.file).stat().st_size <= 20 * 1024 * 1024
    assert (exported / "LICENSE.mediapipe").read_bytes() == (REPO / "models" / "LICENSE.mediapipe").read_bytes()
    assert "Apache License" in (REPO / "models" / "LICENSE.mediapipe").read_text()
    assert (exported / "NOTICE").read_text() == (REPO / "models" / "NOTICE").read_text()


def test_onnx_runtime_matches_the_tflite_interpreter_on_real_photos(exported):
    from export.perception.build import MODELS

    built = json.loads((exported / "manifest.json").read_text())["models"]
    for spec in MODELS:
        errors = built[spec.name]["metrics"]["parity_max_relative_error"]
        for output, error in errors.items():
            if output.endswith("_side_changes"):
                assert error <= 1e-4, (spec.name, output, error)      # at most ~6 of 65536 pixels
            elif output in spec.thresholds:
                assert error <= 1e-2, (spec.name, output, error)      # logits of +-1000: see the side test
            else:
                assert error <= 1e-3, (spec.name, output, error)


def test_an_op_without_a_handler_is_named(monkeypatch):
    pytest.importorskip("tflite")
    from export.perception import tflite_onnx
    from export.perception.build import MEDIAPIPE, MODELS, fetch, read_member

    monkeypatch.delitem(tflite_onnx.HANDLERS, "PAD")
    face_detector = next(m for m in MODELS if m.name == "face_detector")
    with pytest.raises(tflite_onnx.ConversionError, match="PAD"):
        tflite_onnx.convert_tflite(read_member(fetch(MEDIAPIPE), face_detector.member))
