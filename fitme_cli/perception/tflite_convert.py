"""Build MediaPipe TFLite models (BlazeFace, FaceMesh) into safetensors + JSON card + ONNX, and load them."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .onnx_export import export_onnx
from .onnx_runner import onnx_session
from ..io.atomic import atomic_write_bytes
from .store import SourceFile, load_tensors, read_card, save_tensors, write_card
from .tflite_graph import TfliteGraph, read_tflite
from .tflite_net import TfliteNet

__all__ = ["build_tflite_model", "load_tflite_net"]


def build_tflite_model(
    name: str, source: SourceFile, out_dir: Path, input_range: tuple[float, float], output_names: list[str]
) -> dict[str, Any]:
    """Convert ``source`` to ``out_dir/{name}.{safetensors,json,onnx}``; returns the card.

    ``output_names`` name the graph's outputs in TFLite order (e.g. regressors, scores).
    """
    t0 = time.perf_counter()
    graph = read_tflite(source.path)
    net = TfliteNet(graph).eval()
    _, h, w, c = graph.shapes[graph.inputs[0]]
    lo, hi = input_range
    rng = np.random.default_rng(0)
    example = torch.from_numpy(rng.uniform(lo, hi, (2, c, h, w)).astype(np.float32))
    onnx_bytes = export_onnx(net, example, "image", output_names)

    floats = {f"t{k}": v for k, v in graph.constants.items() if v.dtype.kind == "f"}
    save_tensors(out_dir / f"{name}.safetensors", floats)
    atomic_write_bytes(out_dir / f"{name}.onnx", onnx_bytes)

    sess = onnx_session(out_dir / f"{name}.onnx")
    with torch.no_grad():
        ref = net(example)
    got = sess.run(None, {"image": example.numpy()})
    err = max(float(np.abs(r.numpy() - g).max()) for r, g in zip(ref, got))
    card = {
        "name": name,
        "kind": "tflite",
        "source": source.describe(),
        "input": {"name": "image", "shape": ["B", c, h, w], "layout": "NCHW RGB", "range": [lo, hi]},
        "outputs": output_names,
        "spec": graph.spec(),
        "checks": {"max_abs_torch_minus_onnx": err},
        "build_seconds": round(time.perf_counter() - t0, 3),
    }
    write_card(out_dir / f"{name}.json", card)
    return card


def load_tflite_net(models_dir: Path, name: str) -> TfliteNet:
    """The differentiable torch twin of ``models_dir/{name}.onnx``, rebuilt from its card and weights."""
    card = read_card(models_dir / f"{name}.json")
    tensors = load_tensors(models_dir / f"{name}.safetensors")
    floats = {int(k[1:]): v for k, v in tensors.items()}
    return TfliteNet(TfliteGraph.from_spec(card["spec"], floats)).eval()
