"""Execute a TfliteGraph in torch: differentiable, batched, exportable to ONNX.

Internally 4-D activations are NCHW (torch's native layout); tensors of other ranks keep TFLite's
layout. The module's input is NCHW; its outputs are returned in TFLite's layout (NHWC for 4-D), with
the batch dimension generalised from 1 to B.

TF 'SAME' padding is asymmetric when the total is odd (the extra pixel goes after); we compute it from
the static shapes at construction and apply it explicitly, so torch and TFLite agree to float precision.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ..errors import ModelBuildError
from .tflite_graph import TfliteGraph

__all__ = ["TfliteNet"]


def _same_pads(size: int, kernel: int, stride: int, dilation: int) -> tuple[int, int]:
    eff = (kernel - 1) * dilation + 1
    out = math.ceil(size / stride)
    total = max((out - 1) * stride + eff - size, 0)
    return total // 2, total - total // 2


def _activation(x: torch.Tensor, name: str) -> torch.Tensor:
    if name == "none":
        return x
    if name == "relu":
        return F.relu(x)
    if name == "relu6":
        return F.relu6(x)
    raise ModelBuildError(f"unsupported fused activation {name}")


def _nchw_axis(axis: int, rank: int) -> int:
    axis = axis % rank
    return (0, 2, 3, 1)[axis] if rank == 4 else axis


class TfliteNet(nn.Module):
    """A TFLite graph as an ``nn.Module``. ``forward(x)``: x (B, C, H, W) float32 -> tuple of outputs."""

    def __init__(self, graph: TfliteGraph):
        super().__init__()
        self.graph = graph
        self._params: dict[int, str] = {}
        self._pads: dict[int, tuple[int, int, int, int]] = {}
        produced = set(graph.inputs)
        for n, op in enumerate(graph.ops):
            for i in op.inputs:
                if i >= 0 and i not in graph.constants and i not in produced:
                    raise ModelBuildError(f"op {n} ({op.kind}) reads tensor {i} that nothing produced")
            produced.update(op.outputs)
            if op.kind in ("CONV_2D", "DEPTHWISE_CONV_2D"):
                w = graph.constants[op.inputs[1]]
                if op.kind == "CONV_2D":  # OHWI -> OIHW
                    w_t = w.transpose(0, 3, 1, 2)
                else:  # 1HW(C*m) -> (C*m)1HW
                    w_t = w.transpose(3, 0, 1, 2)
                self._register(op.inputs[1], w_t)
                if len(op.inputs) > 2 and op.inputs[2] >= 0:
                    self._register(op.inputs[2], graph.constants[op.inputs[2]])
                kh, kw = w.shape[1], w.shape[2]
                self._pads[n] = self._spatial_pads(op, kh, kw)
            elif op.kind == "MAX_POOL_2D":
                kh, kw = op.options["kernel"]
                self._pads[n] = self._spatial_pads(op, kh, kw)
            elif op.kind == "PRELU":
                alpha = graph.constants[op.inputs[1]].reshape(-1)
                self._register(op.inputs[1], alpha.reshape(1, -1, 1, 1))
            elif op.kind == "ADD":
                for i in op.inputs:
                    if i in graph.constants:
                        c = graph.constants[i]
                        self._register(i, c.transpose(0, 3, 1, 2) if c.ndim == 4 else c)

    def _register(self, index: int, value: np.ndarray) -> None:
        name = f"t{index}"
        if name not in self._params:
            self.register_buffer(name, torch.from_numpy(np.ascontiguousarray(value, dtype=np.float32)))
            self._params[index] = name

    def _spatial_pads(self, op, kh: int, kw: int) -> tuple[int, int, int, int]:
        if op.options["padding"] == "valid":
            return (0, 0, 0, 0)
        _, h, w, _ = self.graph.shapes[op.inputs[0]]
        sh, sw = op.options["stride"]
        dh, dw = op.options.get("dilation", [1, 1])
        top, bottom = _same_pads(h, kh, sh, dh)
        left, right = _same_pads(w, kw, sw, dw)
        return (left, right, top, bottom)

    def _value(self, index: int, values: dict[int, torch.Tensor]) -> torch.Tensor:
        if index in values:
            return values[index]
        return getattr(self, self._params[index])

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, ...]:
        g = self.graph
        _, h, w, c = g.shapes[g.inputs[0]]
        if x.ndim != 4 or tuple(x.shape[1:]) != (c, h, w):
            raise ValueError(f"expected input of shape (B, {c}, {h}, {w}), got {tuple(x.shape)}")
        values: dict[int, torch.Tensor] = {g.inputs[0]: x}
        for n, op in enumerate(g.ops):
            values[op.outputs[0]] = self._run(n, op, values)
        outs = []
        for i in g.outputs:
            v = values[i]
            outs.append(v.permute(0, 2, 3, 1) if v.ndim == 4 else v)
        return tuple(outs)

    def _run(self, n: int, op, values: dict[int, torch.Tensor]) -> torch.Tensor:
        o: dict[str, Any] = op.options
        x = self._value(op.inputs[0], values)
        if op.kind in ("CONV_2D", "DEPTHWISE_CONV_2D"):
            weight = self._value(op.inputs[1], values)
            bias = self._value(op.inputs[2], values) if len(op.inputs) > 2 and op.inputs[2] >= 0 else None
            pads = self._pads[n]
            if any(pads):
                x = F.pad(x, pads)
            groups = x.shape[1] if op.kind == "DEPTHWISE_CONV_2D" else 1
            y = F.conv2d(x, weight, bias, stride=tuple(o["stride"]), dilation=tuple(o["dilation"]), groups=groups)
            return _activation(y, o["activation"])
        if op.kind == "MAX_POOL_2D":
            pads = self._pads[n]
            if any(pads):
                x = F.pad(x, pads, value=float("-inf"))
            y = F.max_pool2d(x, tuple(o["kernel"]), tuple(o["stride"]))
            return _activation(y, o["activation"])
        if op.kind == "RELU":
            return F.relu(x)
        if op.kind == "PRELU":
            alpha = self._value(op.inputs[1], values)
            return torch.where(x >= 0, x, x * alpha)
        if op.kind == "ADD":
            y = x + self._value(op.inputs[1], values)
            return _activation(y, o["activation"])
        if op.kind == "PAD":
            p = self.graph.constants[op.inputs[1]].astype(int)  # NHWC (4, 2)
            if p.shape != (4, 2) or p[0].any():
                raise ModelBuildError(f"unsupported PAD paddings {p.tolist()}")
            return F.pad(x, (p[2, 0], p[2, 1], p[1, 0], p[1, 1], p[3, 0], p[3, 1]))
        if op.kind == "RESHAPE":
            if x.ndim == 4:
                x = x.permute(0, 2, 3, 1)
            shape = list(self.graph.shapes[op.outputs[0]])
            y = x.reshape([x.shape[0]] + shape[1:])
            return y.permute(0, 3, 1, 2) if y.ndim == 4 else y
        if op.kind == "CONCATENATION":
            parts = [self._value(i, values) for i in op.inputs]
            y = torch.cat(parts, dim=_nchw_axis(o["axis"], parts[0].ndim))
            return _activation(y, o["activation"])
        if op.kind == "RESIZE_BILINEAR":
            size = [int(s) for s in self.graph.constants[op.inputs[1]]]
            if o["half_pixel_centers"] and not o["align_corners"]:
                return F.interpolate(x, size=size, mode="bilinear", align_corners=False)
            if o["align_corners"]:
                return F.interpolate(x, size=size, mode="bilinear", align_corners=True)
            raise ModelBuildError("RESIZE_BILINEAR without half-pixel centres or aligned corners is not supported")
        raise ModelBuildError(f"unsupported op {op.kind}")
