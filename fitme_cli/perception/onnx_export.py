"""Export a torch module to ONNX for onnxruntime: one way, shared by every converter."""

from __future__ import annotations

import io
import warnings

import torch

__all__ = ["export_onnx"]


def export_onnx(module: torch.nn.Module, example: torch.Tensor, input_name: str, output_names: list[str]) -> bytes:
    """Trace ``module`` to ONNX (opset 17) with a dynamic batch axis; returns the serialised model."""
    buf = io.BytesIO()
    axes = {input_name: {0: "batch"}, **{n: {0: "batch"} for n in output_names}}
    with warnings.catch_warnings():
        # The TorchScript exporter warns about our static shape checks and its own constant folding;
        # both are expected. (The dynamo exporter needs onnxscript, which we do not ship.)
        warnings.simplefilter("ignore")
        torch.onnx.export(
            module, (example,), buf, dynamo=False, opset_version=17,
            input_names=[input_name], output_names=output_names, dynamic_axes=axes,
        )
    return buf.getvalue()
