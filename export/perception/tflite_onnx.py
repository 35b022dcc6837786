"""TFLite flatbuffer -> ONNX for the MediaPipe perception models (after tf2onnx's tflite
handlers): one small handler per TFLite op, registered by name in HANDLERS; an op without a
handler fails loudly with its name.

Layout: TFLite activations are NHWC, ONNX convolutions NCHW. Inside the ONNX graph every 4-D
activation is NCHW: the graph input is transposed once on the way in and every 4-D output once
on the way out, so the ONNX model keeps the TFLite model's I/O shapes (optionally renamed).

Constants are folded at conversion: fp16 weights (DEQUANTIZE of a constant) and sparse weights
(DENSIFY of a constant, TFLite's sparse tensor format) become dense float32 values, stored as
float16 initializers with a Cast to float32 where every value is a float16 (Graph.constant).
Reads the flatbuffer with the `tflite` package's generated schema; writes with onnx.helper.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

OPSET = 17
# TFLite enums (schema.fbs)
SAME, VALID = 0, 1
ACTIVATIONS = {0: None, 1: "Relu", 2: "ReluN1To1", 3: "Relu6", 4: "Tanh"}
NUMPY_TYPES = {0: np.float32, 1: np.float16, 2: np.int32, 3: np.uint8, 4: np.int64, 9: np.int8}
DENSE, SPARSE_CSR = 0, 1
# NHWC axis -> NCHW axis
NHWC_TO_NCHW_AXIS = {0: 0, 1: 2, 2: 3, 3: 1}


class ConversionError(RuntimeError):
    """The model uses something this converter does not handle (named in the message)."""


# ----------------------------------------------------------------------------- sparse tensors
@dataclass(frozen=True)
class DimMetadata:
    """One traversal level of a TFLite sparse tensor: DENSE with `dense_size`, or SPARSE_CSR
    with `segments` (row pointers into `indices`) and `indices`."""

    format: int
    dense_size: int = 0
    segments: np.ndarray | None = None
    indices: np.ndarray | None = None


def densify(values: np.ndarray, shape: tuple[int, ...], traversal_order, block_map,
            levels: list[DimMetadata]) -> np.ndarray:
    """The dense tensor (shape) of TFLite's sparse encoding: `values` are the stored
    elements in traversal order; levels[k] describes traversal level k, which walks
    dimension traversal_order[k] (dims >= len(shape) are block dims: block dim j refines
    original dim block_map[j], in blocks of levels[...].dense_size)."""
    rank = len(shape)
    order = list(traversal_order)
    # Expand level by level: one row per path through the levels so far
    coords = np.zeros((1, len(order)), np.int64)
    parent = np.zeros(1, np.int64)  # the row's position at the previous level
    for level, meta in enumerate(levels):
        if meta.format == DENSE:
            size = meta.dense_size
            coords = np.repeat(coords, size, axis=0)
            step = np.tile(np.arange(size), parent.size)
            coords[:, level] = step
            parent = np.repeat(parent, size) * size + step
        elif meta.format == SPARSE_CSR:
            starts, ends = meta.segments[parent], meta.segments[parent + 1]
            counts = ends - starts
            coords = np.repeat(coords, counts, axis=0)
            position = np.repeat(starts - np.cumsum(counts) + counts, counts) + np.arange(counts.sum())
            coords[:, level] = meta.indices[position]
            parent = position
        else:
            raise ConversionError(f"sparse dimension format {meta.format} is not handled")
    if coords.shape[0] != values.size:
        raise ConversionError(f"sparse tensor: {coords.shape[0]} positions for {values.size} values")
    # Traversal coordinates -> original coordinates: dim d = block index * block size + offset
    dims = np.zeros((coords.shape[0], rank), np.int64)
    for level, dim in enumerate(order):
        if dim < rank:
            dims[:, dim] += coords[:, level] * _block_size(dim, order, block_map, levels, rank)
        else:
            dims[:, block_map[dim - rank]] += coords[:, level]
    dense = np.zeros(shape, values.dtype)
    dense[tuple(dims.T)] = values.reshape(-1)
    return dense


def _block_size(dim, order, block_map, levels, rank) -> int:
    for j, original in enumerate(block_map):
        if original == dim:
            return levels[order.index(rank + j)].dense_size
    return 1


# ----------------------------------------------------------------------------- the converter
@dataclass
class Graph:
    """The ONNX graph being built; `layout[name]` is "nchw" for 4-D activations kept NCHW."""

    nodes: list = field(default_factory=list)
    initializers: list = field(default_factory=list)
    layout: dict = field(default_factory=dict)
    counter: int = 0

    def fresh(self, stem: str) -> str:
        self.counter += 1
        return f"{stem}__{self.counter}"

    def node(self, op: str, inputs: list[str], outputs: list[str] | None = None, **attributes) -> str:
        outputs = outputs or [self.fresh(op.lower())]
        self.nodes.append(helper.make_node(op, inputs, outputs, name=self.fresh(op), **attributes))
        return outputs[0]

    def constant(self, array: np.ndarray, stem: str = "const") -> str:
        """An initializer; a float32 one whose every value is a float16 (the fp16 weights) is
        stored as float16 and cast back to float32 in the graph: half the file, the same values
        (ONNX Runtime folds the Cast when it builds the session)."""
        array = np.ascontiguousarray(array)
        name = self.fresh(stem)
        if array.dtype == np.float32 and array.size >= HALF_MIN_SIZE and is_float16_exact(array):
            self.initializers.append(numpy_helper.from_array(array.astype(np.float16), f"{name}_fp16"))
            self.node("Cast", [f"{name}_fp16"], [name], to=TensorProto.FLOAT)
        else:
            self.initializers.append(numpy_helper.from_array(array, name))
        return name


# Smaller float32 constants (biases, shapes' scalars) stay float32: a Cast would save little
HALF_MIN_SIZE = 1024


def is_float16_exact(array: np.ndarray) -> bool:
    """Whether every value of a float32 array survives a round trip through float16."""
    return bool(np.array_equal(array.astype(np.float16).astype(np.float32), array))


class Converter:
    """Converts subgraph 0 of a TFLite model (bytes) to an onnx.ModelProto."""

    def __init__(self, model_bytes: bytes, rename: dict[str, str] | None = None):
        import tflite

        self.tflite = tflite
        self.buffer = model_bytes
        self.model = tflite.Model.GetRootAsModel(model_bytes, 0)
        if self.model.SubgraphsLength() != 1:
            raise ConversionError(f"{self.model.SubgraphsLength()} subgraphs: only single-graph models are handled")
        self.subgraph = self.model.Subgraphs(0)
        self.rename = rename or {}
        self.graph = Graph()
        self.constants: dict[int, np.ndarray] = {}
        self.names: dict[int, str] = {}
        self.op_names = {v: k for k, v in tflite.BuiltinOperator.__dict__.items() if not k.startswith("_")}

    # --- tensors
    def tensor(self, index: int):
        return self.subgraph.Tensors(index)

    def shape(self, index: int) -> tuple[int, ...]:
        return tuple(int(s) for s in self.tensor(index).ShapeAsNumpy())

    def name(self, index: int) -> str:
        return self.names.setdefault(index, f"t{index}")

    def constant_value(self, index: int) -> np.ndarray | None:
        """The tensor's value when it is a constant (stored or folded), else None."""
        if index in self.constants:
            return self.constants[index]
        tensor = self.tensor(index)
        data = self.model.Buffers(tensor.Buffer()).DataAsNumpy()
        if isinstance(data, int) or data.size == 0:
            return None
        if tensor.Type() not in NUMPY_TYPES:
            raise ConversionError(f"tensor {tensor.Name().decode()}: type {tensor.Type()} is not handled")
        array = np.frombuffer(data.tobytes(), NUMPY_TYPES[tensor.Type()])
        if tensor.Sparsity() is None:
            array = array.reshape(self.shape(index))
        self.constants[index] = array
        return array

    def activation(self, index: int) -> str:
        """The ONNX name of an activation input (a constant input is an error here)."""
        if self.constant_value(index) is not None:
            raise ConversionError(f"tensor {self.tensor(index).Name().decode()} is a constant where an activation is expected")
        return self.name(index)

    def operand(self, index: int, like: int) -> str:
        """An elementwise operand: an activation as it is, a constant broadcast the way TFLite
        broadcasts it against tensor `like` (NHWC), moved to NCHW when `like` is."""
        value = self.constant_value(index)
        if value is None:
            return self.name(index)
        value = value.astype(np.float32)
        if self.graph.layout.get(self.name(like)) == "nchw":
            value = value.reshape((1,) * (4 - value.ndim) + value.shape).transpose(0, 3, 1, 2)
        return self.graph.constant(value)

    # --- conversion
    def convert(self) -> onnx.ModelProto:
        graph = self.graph
        inputs = []
        for k in range(self.subgraph.InputsLength()):
            index = self.subgraph.Inputs(k)
            shape = self.shape(index)
            public = self.rename.get(self.tensor(index).Name().decode(), self.tensor(index).Name().decode())
            inputs.append(helper.make_tensor_value_info(public, TensorProto.FLOAT, list(shape)))
            if len(shape) == 4:
                self.names[index] = graph.node("Transpose", [public], [graph.fresh("input_nchw")], perm=[0, 3, 1, 2])
                graph.layout[self.names[index]] = "nchw"
            else:
                self.names[index] = public
        for k in range(self.subgraph.OperatorsLength()):
            self.convert_operator(self.subgraph.Operators(k))
        outputs = []
        for k in range(self.subgraph.OutputsLength()):
            index = self.subgraph.Outputs(k)
            shape = self.shape(index)
            public = self.rename.get(self.tensor(index).Name().decode(), self.tensor(index).Name().decode())
            source = self.name(index)
            if graph.layout.get(source) == "nchw":
                graph.node("Transpose", [source], [public], perm=[0, 2, 3, 1])
            else:
                graph.node("Identity", [source], [public])
            outputs.append(helper.make_tensor_value_info(public, TensorProto.FLOAT, list(shape)))
        onnx_graph = helper.make_graph(graph.nodes, "converted", inputs, outputs, graph.initializers)
        model = helper.make_model(onnx_graph, opset_imports=[helper.make_opsetid("", OPSET)],
                                  producer_name="relightcli export.perception")
        model.ir_version = 8
        onnx.checker.check_model(model, full_check=True)
        return model

    def op_name(self, op) -> str:
        code = self.model.OperatorCodes(op.OpcodeIndex())
        builtin = max(code.BuiltinCode(), code.DeprecatedBuiltinCode())
        if builtin == self.tflite.BuiltinOperator.CUSTOM:
            return "CUSTOM:" + code.CustomCode().decode()
        return self.op_names.get(builtin, str(builtin))

    def convert_operator(self, op) -> None:
        name = self.op_name(op)
        handler = HANDLERS.get(name)
        if handler is None:
            raise ConversionError(f"TFLite op {name} has no handler (export/perception/tflite_onnx.py)")
        inputs = [int(i) for i in op.InputsAsNumpy()] if op.InputsLength() else []
        outputs = [int(i) for i in op.OutputsAsNumpy()]
        handler(self, op, inputs, outputs)

    def options(self, op, cls):
        table = op.BuiltinOptions()
        options = cls()
        options.Init(table.Bytes, table.Pos)
        return options

    def emit(self, output: int, op: str, inputs: list[str], nchw: bool, fused: int = 0, **attributes) -> None:
        """Add `op` writing tensor `output`, then its fused activation."""
        graph = self.graph
        target = self.name(output)
        activation = ACTIVATIONS.get(fused, "?")
        if activation == "?":
            raise ConversionError(f"fused activation {fused} is not handled")
        result = graph.node(op, inputs, [target if activation is None else graph.fresh(target)], **attributes)
        if activation == "Relu":
            graph.node("Relu", [result], [target])
        elif activation == "Relu6":
            graph.node("Clip", [result, graph.constant(np.float32(0.0)), graph.constant(np.float32(6.0))], [target])
        elif activation == "ReluN1To1":
            graph.node("Clip", [result, graph.constant(np.float32(-1.0)), graph.constant(np.float32(1.0))], [target])
        elif activation == "Tanh":
            graph.node("Tanh", [result], [target])
        if nchw:
            graph.layout[target] = "nchw"


# ----------------------------------------------------------------------------- handlers
def same_pads(size: int, kernel: int, stride: int, dilation: int = 1) -> tuple[int, int]:
    """TensorFlow's SAME padding of one spatial dim: (before, after), the extra pixel after."""
    effective = (kernel - 1) * dilation + 1
    total = max((-(-size // stride) - 1) * stride + effective - size, 0)
    return total // 2, total - total // 2


def _window_pads(c: Converter, x: int, kernel_hw, stride_hw, dilation_hw, padding) -> list[int]:
    """ONNX pads [top, left, bottom, right] for an NHWC input tensor x."""
    if padding == VALID:
        return [0, 0, 0, 0]
    _, height, width, _ = c.shape(x)
    top, bottom = same_pads(height, kernel_hw[0], stride_hw[0], dilation_hw[0])
    left, right = same_pads(width, kernel_hw[1], stride_hw[1], dilation_hw[1])
    return [top, left, bottom, right]


def _bias(c: Converter, inputs: list[int], channels: int) -> str:
    value = c.constant_value(inputs[2]) if len(inputs) > 2 and inputs[2] >= 0 else None
    return c.graph.constant((np.zeros(channels) if value is None else value).astype(np.float32), "bias")


def conv_2d(c: Converter, op, inputs, outputs):
    o = c.options(op, c.tflite.Conv2DOptions)
    weight = c.constant_value(inputs[1]).astype(np.float32)  # (O, KH, KW, I)
    stride, dilation = (o.StrideH(), o.StrideW()), (o.DilationHFactor(), o.DilationWFactor())
    group = c.shape(inputs[0])[3] // weight.shape[3]
    c.emit(outputs[0], "Conv", [c.activation(inputs[0]), c.graph.constant(weight.transpose(0, 3, 1, 2), "weight"),
                                _bias(c, inputs, weight.shape[0])], True, o.FusedActivationFunction(),
           strides=list(stride), dilations=list(dilation), group=group,
           pads=_window_pads(c, inputs[0], weight.shape[1:3], stride, dilation, o.Padding()))


def depthwise_conv_2d(c: Converter, op, inputs, outputs):
    o = c.options(op, c.tflite.DepthwiseConv2DOptions)
    weight = c.constant_value(inputs[1]).astype(np.float32)  # (1, KH, KW, C * multiplier)
    stride, dilation = (o.StrideH(), o.StrideW()), (o.DilationHFactor(), o.DilationWFactor())
    c.emit(outputs[0], "Conv", [c.activation(inputs[0]), c.graph.constant(weight.transpose(3, 0, 1, 2), "weight"),
                                _bias(c, inputs, weight.shape[3])], True, o.FusedActivationFunction(),
           strides=list(stride), dilations=list(dilation), group=c.shape(inputs[0])[3],
           pads=_window_pads(c, inputs[0], weight.shape[1:3], stride, dilation, o.Padding()))


def transpose_conv_bias(c: Converter, op, inputs, outputs):
    """MediaPipe's custom Convolution2DTransposeBias: options are a raw C struct
    {padding, stride_width, stride_height} of int32."""
    padding, stride_w, stride_h = np.frombuffer(op.CustomOptionsAsNumpy().tobytes()[:12], np.int32)
    weight = c.constant_value(inputs[1]).astype(np.float32)  # (O, KH, KW, I)
    (_, in_h, in_w, _), (_, out_h, out_w, _) = c.shape(inputs[0]), c.shape(outputs[0])
    pad_h = (in_h - 1) * stride_h + weight.shape[1] - out_h
    pad_w = (in_w - 1) * stride_w + weight.shape[2] - out_w
    if padding == VALID and (pad_h or pad_w) or min(pad_h, pad_w) < 0:
        raise ConversionError(f"transposed convolution to {out_h}x{out_w} is not handled")
    c.emit(outputs[0], "ConvTranspose", [c.activation(inputs[0]), c.graph.constant(weight.transpose(3, 0, 1, 2), "weight"),
                                         _bias(c, inputs, weight.shape[0])], True,
           strides=[int(stride_h), int(stride_w)],
           pads=[pad_h // 2, pad_w // 2, pad_h - pad_h // 2, pad_w - pad_w // 2])


def pool(onnx_op):
    def handler(c: Converter, op, inputs, outputs):
        o = c.options(op, c.tflite.Pool2DOptions)
        kernel, stride = (o.FilterHeight(), o.FilterWidth()), (o.StrideH(), o.StrideW())
        extra = {"count_include_pad": 0} if onnx_op == "AveragePool" else {}
        c.emit(outputs[0], onnx_op, [c.activation(inputs[0])], True, o.FusedActivationFunction(),
               kernel_shape=list(kernel), strides=list(stride),
               pads=_window_pads(c, inputs[0], kernel, stride, (1, 1), o.Padding()), **extra)
    return handler


def pad(c: Converter, op, inputs, outputs):
    pads = c.constant_value(inputs[1]).astype(np.int64)  # (rank, 2), NHWC order for 4-D
    if len(c.shape(inputs[0])) == 4:
        pads = pads[[0, 3, 1, 2]]
    c.emit(outputs[0], "Pad", [c.activation(inputs[0]), c.graph.constant(pads.T.reshape(-1), "pads")],
           len(c.shape(inputs[0])) == 4)


def elementwise(onnx_op, options_class):
    def handler(c: Converter, op, inputs, outputs):
        fused = c.options(op, getattr(c.tflite, options_class)).FusedActivationFunction() if op.BuiltinOptions() else 0
        like = next(i for i in inputs if c.constant_value(i) is None)
        c.emit(outputs[0], onnx_op, [c.operand(i, like) for i in inputs],
               c.graph.layout.get(c.name(like)) == "nchw", fused)
    return handler


def unary(onnx_op):
    def handler(c: Converter, op, inputs, outputs):
        x = c.activation(inputs[0])
        c.emit(outputs[0], onnx_op, [x], c.graph.layout.get(x) == "nchw")
    return handler


def relu6(c: Converter, op, inputs, outputs):
    x = c.activation(inputs[0])
    c.emit(outputs[0], "Relu", [x], c.graph.layout.get(x) == "nchw", 3)


def prelu(c: Converter, op, inputs, outputs):
    c.emit(outputs[0], "PRelu", [c.activation(inputs[0]), c.operand(inputs[1], inputs[0])],
           c.graph.layout.get(c.name(inputs[0])) == "nchw")


def reshape(c: Converter, op, inputs, outputs):
    x = c.activation(inputs[0])
    if c.graph.layout.get(x) == "nchw":
        x = c.graph.node("Transpose", [x], perm=[0, 2, 3, 1])
    target = c.shape(outputs[0])
    if len(target) == 4:
        nhwc = c.graph.node("Reshape", [x, c.graph.constant(np.array(target, np.int64), "shape")])
        c.emit(outputs[0], "Transpose", [nhwc], True, perm=[0, 3, 1, 2])
    else:
        c.emit(outputs[0], "Reshape", [x, c.graph.constant(np.array(target, np.int64), "shape")], False)


def concatenation(c: Converter, op, inputs, outputs):
    o = c.options(op, c.tflite.ConcatenationOptions)
    rank = len(c.shape(outputs[0]))
    axis = o.Axis() % rank
    names = [c.activation(i) for i in inputs]
    nchw = c.graph.layout.get(names[0]) == "nchw"
    if any((c.graph.layout.get(n) == "nchw") != nchw for n in names):
        raise ConversionError("concatenation of tensors in different layouts is not handled")
    c.emit(outputs[0], "Concat", names, nchw, o.FusedActivationFunction(),
           axis=NHWC_TO_NCHW_AXIS[axis] if nchw else axis)


def depth_to_space(c: Converter, op, inputs, outputs):
    o = c.options(op, c.tflite.DepthToSpaceOptions)
    # TensorFlow's depth_to_space puts channel (i * block + j) * C_out + c at offset (i, j): ONNX's DCR
    c.emit(outputs[0], "DepthToSpace", [c.activation(inputs[0])], True, blocksize=o.BlockSize(), mode="DCR")


def resize_bilinear(c: Converter, op, inputs, outputs):
    o = c.options(op, c.tflite.ResizeBilinearOptions)
    if o.AlignCorners():
        mode = "align_corners"
    elif o.HalfPixelCenters():
        mode = "half_pixel"
    else:
        mode = "asymmetric"
    n, height, width, channels = c.shape(outputs[0])
    sizes = c.graph.constant(np.array([n, channels, height, width], np.int64), "sizes")
    c.emit(outputs[0], "Resize", [c.activation(inputs[0]), "", "", sizes], True,
           mode="linear", coordinate_transformation_mode=mode)


def dequantize(c: Converter, op, inputs, outputs):
    value = c.constant_value(inputs[0])
    if value is None or c.tensor(inputs[0]).Sparsity() is not None:
        raise ConversionError("DEQUANTIZE is handled for dense constant weights only")
    if value.dtype != np.float16:
        raise ConversionError(f"DEQUANTIZE of {value.dtype} is not handled (only float16)")
    c.constants[outputs[0]] = value.astype(np.float32)


def densify_op(c: Converter, op, inputs, outputs):
    sparsity = c.tensor(inputs[0]).Sparsity()
    if sparsity is None or c.constant_value(inputs[0]) is None:
        raise ConversionError("DENSIFY is handled for constant tensors with sparsity parameters only")
    levels = []
    for k in range(sparsity.DimMetadataLength()):
        meta = sparsity.DimMetadata(k)
        if meta.Format() == DENSE:
            levels.append(DimMetadata(DENSE, dense_size=meta.DenseSize()))
        else:
            levels.append(DimMetadata(SPARSE_CSR, segments=_index_vector(c, meta.ArraySegmentsType(), meta.ArraySegments()),
                                      indices=_index_vector(c, meta.ArrayIndicesType(), meta.ArrayIndices())))
    block_map = sparsity.BlockMapAsNumpy().tolist() if sparsity.BlockMapLength() else []
    c.constants[outputs[0]] = densify(c.constant_value(inputs[0]), c.shape(outputs[0]),
                                      sparsity.TraversalOrderAsNumpy().tolist(), block_map, levels)


def _index_vector(c: Converter, kind: int, table) -> np.ndarray:
    classes = {1: c.tflite.Int32Vector, 2: c.tflite.Uint16Vector, 3: c.tflite.Uint8Vector}
    if kind not in classes:
        raise ConversionError(f"sparse index vector type {kind} is not handled")
    vector = classes[kind]()
    vector.Init(table.Bytes, table.Pos)
    return vector.ValuesAsNumpy().astype(np.int64)


HANDLERS = {
    "CONV_2D": conv_2d,
    "DEPTHWISE_CONV_2D": depthwise_conv_2d,
    "CUSTOM:Convolution2DTransposeBias": transpose_conv_bias,
    "MAX_POOL_2D": pool("MaxPool"),
    "AVERAGE_POOL_2D": pool("AveragePool"),
    "PAD": pad,
    "ADD": elementwise("Add", "AddOptions"),
    "MUL": elementwise("Mul", "MulOptions"),
    "RELU": unary("Relu"),
    "RELU6": relu6,
    "LOGISTIC": unary("Sigmoid"),
    "TANH": unary("Tanh"),
    "HARD_SWISH": unary("HardSwish"),
    "PRELU": prelu,
    "RESHAPE": reshape,
    "CONCATENATION": concatenation,
    "DEPTH_TO_SPACE": depth_to_space,
    "RESIZE_BILINEAR": resize_bilinear,
    "DEQUANTIZE": dequantize,
    "DENSIFY": densify_op,
}


def convert_tflite(model_bytes: bytes, rename: dict[str, str] | None = None) -> onnx.ModelProto:
    """The ONNX model of a TFLite model's bytes; `rename` maps TFLite I/O tensor names to
    the ONNX model's."""
    return Converter(model_bytes, rename).convert()
