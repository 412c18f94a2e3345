"""Read a TFLite flatbuffer into a plain, JSON-serialisable op list plus float32 constants.

Only what MediaPipe's BlazeFace and FaceMesh use is supported: CONV_2D, DEPTHWISE_CONV_2D, PRELU,
RELU, ADD, MAX_POOL_2D, PAD, RESHAPE, CONCATENATION, RESIZE_BILINEAR, and DEQUANTIZE (fp16 weights,
folded here into float32 constants). Anything else raises ModelBuildError naming the op.

Layouts are TFLite's own (NHWC activations, OHWI conv kernels, 1HWC depthwise kernels); the torch
executor in ``tflite_net`` converts them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ModelBuildError

__all__ = ["TfliteOp", "TfliteGraph", "read_tflite"]

_ACTIVATIONS = {0: "none", 1: "relu", 3: "relu6"}
_PADDING = {0: "same", 1: "valid"}


@dataclass(frozen=True)
class TfliteOp:
    kind: str
    inputs: tuple[int, ...]  # tensor indices; -1 marks an absent optional input
    outputs: tuple[int, ...]
    options: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {"kind": self.kind, "inputs": list(self.inputs), "outputs": list(self.outputs), "options": self.options}

    @staticmethod
    def from_json(d: dict[str, Any]) -> "TfliteOp":
        return TfliteOp(d["kind"], tuple(d["inputs"]), tuple(d["outputs"]), dict(d["options"]))


@dataclass(frozen=True)
class TfliteGraph:
    ops: tuple[TfliteOp, ...]  # in execution order (TFLite stores them topologically sorted)
    shapes: dict[int, tuple[int, ...]]  # every tensor's static shape, NHWC for 4-D
    names: dict[int, str]
    inputs: tuple[int, ...]
    outputs: tuple[int, ...]
    constants: dict[int, np.ndarray]  # float32 weights, biases, and int shape/padding tensors

    def spec(self) -> dict[str, Any]:
        """Everything but the float weights, as JSON-able data."""
        return {
            "ops": [op.to_json() for op in self.ops],
            "shapes": {str(k): list(v) for k, v in self.shapes.items()},
            "names": {str(k): v for k, v in self.names.items()},
            "inputs": list(self.inputs),
            "outputs": list(self.outputs),
            "int_constants": {
                str(k): v.tolist() for k, v in self.constants.items() if v.dtype.kind in "iu"
            },
        }

    @staticmethod
    def from_spec(spec: dict[str, Any], float_constants: dict[int, np.ndarray]) -> "TfliteGraph":
        constants = {int(k): np.asarray(v, dtype=np.int64) for k, v in spec["int_constants"].items()}
        constants.update(float_constants)
        return TfliteGraph(
            ops=tuple(TfliteOp.from_json(o) for o in spec["ops"]),
            shapes={int(k): tuple(v) for k, v in spec["shapes"].items()},
            names={int(k): v for k, v in spec["names"].items()},
            inputs=tuple(spec["inputs"]),
            outputs=tuple(spec["outputs"]),
            constants=constants,
        )


def _op_names() -> dict[int, str]:
    import tflite

    return {v: k for k, v in vars(tflite.BuiltinOperator).items() if not k.startswith("_")}


def _tensor_array(model, graph, index: int) -> np.ndarray | None:
    import tflite

    t = graph.Tensors(index)
    buf = model.Buffers(t.Buffer())
    if buf is None or buf.DataLength() == 0:
        return None
    dtypes = {
        tflite.TensorType.FLOAT32: np.float32,
        tflite.TensorType.FLOAT16: np.float16,
        tflite.TensorType.INT32: np.int32,
        tflite.TensorType.INT64: np.int64,
    }
    if t.Type() not in dtypes:
        raise ModelBuildError(f"unsupported constant tensor type {t.Type()} in tensor {t.Name()!r}")
    data = buf.DataAsNumpy().tobytes()
    shape = tuple(int(s) for s in t.ShapeAsNumpy()) if t.ShapeLength() else ()
    return np.frombuffer(data, dtype=np.dtype(dtypes[t.Type()]).newbyteorder("<")).reshape(shape).copy()


def _options(kind: str, op) -> dict[str, Any]:
    import tflite

    table = op.BuiltinOptions()

    def init(cls):
        o = cls()
        o.Init(table.Bytes, table.Pos)
        return o

    if kind == "CONV_2D":
        o = init(tflite.Conv2DOptions)
        return {
            "padding": _PADDING[o.Padding()],
            "stride": [o.StrideH(), o.StrideW()],
            "dilation": [o.DilationHFactor(), o.DilationWFactor()],
            "activation": _ACTIVATIONS[o.FusedActivationFunction()],
        }
    if kind == "DEPTHWISE_CONV_2D":
        o = init(tflite.DepthwiseConv2DOptions)
        return {
            "padding": _PADDING[o.Padding()],
            "stride": [o.StrideH(), o.StrideW()],
            "dilation": [o.DilationHFactor(), o.DilationWFactor()],
            "depth_multiplier": o.DepthMultiplier(),
            "activation": _ACTIVATIONS[o.FusedActivationFunction()],
        }
    if kind == "MAX_POOL_2D":
        o = init(tflite.Pool2DOptions)
        return {
            "padding": _PADDING[o.Padding()],
            "stride": [o.StrideH(), o.StrideW()],
            "kernel": [o.FilterHeight(), o.FilterWidth()],
            "activation": _ACTIVATIONS[o.FusedActivationFunction()],
        }
    if kind == "ADD":
        if table is None:
            return {"activation": "none"}
        return {"activation": _ACTIVATIONS[init(tflite.AddOptions).FusedActivationFunction()]}
    if kind == "CONCATENATION":
        o = init(tflite.ConcatenationOptions)
        return {"axis": o.Axis(), "activation": _ACTIVATIONS[o.FusedActivationFunction()]}
    if kind == "RESIZE_BILINEAR":
        o = init(tflite.ResizeBilinearOptions)
        return {"align_corners": bool(o.AlignCorners()), "half_pixel_centers": bool(o.HalfPixelCenters())}
    return {}


_SUPPORTED = {
    "CONV_2D", "DEPTHWISE_CONV_2D", "PRELU", "RELU", "ADD", "MAX_POOL_2D",
    "PAD", "RESHAPE", "CONCATENATION", "RESIZE_BILINEAR", "DEQUANTIZE",
}


def read_tflite(path: Path) -> TfliteGraph:
    """Parse ``path`` (a single-subgraph float or fp16 TFLite model) into a TfliteGraph."""
    import tflite

    buf = Path(path).read_bytes()
    model = tflite.Model.GetRootAsModel(buf, 0)
    if model.SubgraphsLength() != 1:
        raise ModelBuildError(f"expected 1 subgraph, got {model.SubgraphsLength()}", path)
    g = model.Subgraphs(0)
    names = _op_names()
    shapes = {}
    tnames = {}
    constants: dict[int, np.ndarray] = {}
    for i in range(g.TensorsLength()):
        t = g.Tensors(i)
        shapes[i] = tuple(int(s) for s in t.ShapeAsNumpy()) if t.ShapeLength() else ()
        tnames[i] = t.Name().decode()
        arr = _tensor_array(model, g, i)
        if arr is not None:
            constants[i] = arr
    ops = []
    for i in range(g.OperatorsLength()):
        op = g.Operators(i)
        code = model.OperatorCodes(op.OpcodeIndex())
        kind = names.get(max(code.BuiltinCode(), code.DeprecatedBuiltinCode()), "?")
        if kind not in _SUPPORTED:
            raise ModelBuildError(f"unsupported TFLite op {kind} (operator {i})", path)
        ins = tuple(int(x) for x in op.InputsAsNumpy())
        outs = tuple(int(x) for x in op.OutputsAsNumpy())
        if kind == "DEQUANTIZE":  # fp16 weight -> float32 constant, folded away
            src = constants.get(ins[0])
            if src is None:
                raise ModelBuildError(f"DEQUANTIZE of a non-constant tensor (operator {i})", path)
            constants[outs[0]] = src.astype(np.float32)
            continue
        ops.append(TfliteOp(kind, ins, outs, _options(kind, op)))
    for k in list(constants):
        if constants[k].dtype == np.float16:
            del constants[k]  # only reachable through DEQUANTIZE, already folded
        elif constants[k].dtype.kind == "f":
            constants[k] = constants[k].astype(np.float32)
    return TfliteGraph(
        ops=tuple(ops),
        shapes=shapes,
        names=tnames,
        inputs=tuple(int(x) for x in g.InputsAsNumpy()),
        outputs=tuple(int(x) for x in g.OutputsAsNumpy()),
        constants=constants,
    )
