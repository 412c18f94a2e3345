"""Perception benchmark: prints the figures issue 2 asks for.

- per network: max |torch - ONNX| and max |ONNX - independent reference| on real inputs
- `fitme models build` time into an empty directory (a fresh machine)
- `detect` time per 12 MP photo (median after load), portrait and small-face cases

Run: make bench (or .venv/bin/python benchmarks/bench_perception.py [--quick])
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import torch


def _12mp_portrait(astronaut: np.ndarray) -> np.ndarray:
    return cv2.resize(astronaut, (4000, 3000), interpolation=cv2.INTER_CUBIC)


def _12mp_small_face(astronaut: np.ndarray) -> np.ndarray:
    from skimage import data

    canvas = cv2.resize(data.coffee(), (4000, 3000))
    k = 40 / 96
    small = cv2.resize(astronaut, None, fx=k, fy=k, interpolation=cv2.INTER_AREA)
    canvas[1200 : 1200 + small.shape[0], 2500 : 2500 + small.shape[1]] = small
    return canvas


def bench_build() -> None:
    from fitme_cli.perception.registry import build_models

    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        reports = build_models(root=Path(d))
        total = time.perf_counter() - t0
    print("\n## fitme models build into an empty directory")
    for r in reports:
        print(f"  {r.name:16s} {r.seconds:6.1f} s")
    print(f"  {'total':16s} {total:6.1f} s")


def bench_tflite_agreement(root: Path) -> None:
    from ai_edge_litert.interpreter import Interpreter

    from fitme_cli.perception.onnx_runner import onnx_session
    from fitme_cli.perception.registry import MODELS
    from fitme_cli.perception.tflite_convert import load_tflite_net

    print("\n## TFLite networks: max abs difference on random inputs (10 draws)")
    for name in ("blazeface_short", "blazeface_full", "facemesh"):
        net = load_tflite_net(root, name)
        _, h, w, c = net.graph.shapes[net.graph.inputs[0]]
        interp = Interpreter(model_path=str(MODELS[name].source().path))
        interp.allocate_tensors()
        sess = onnx_session(root / f"{name}.onnx")
        names = [net.graph.names[i] for i in net.graph.outputs]
        d_to, d_or = 0.0, 0.0
        for seed in range(10):
            lo = 0.0 if name == "facemesh" else -1.0
            x = np.random.default_rng(seed).uniform(lo, 1, (1, h, w, c)).astype(np.float32)
            with torch.no_grad():
                t = [o.numpy() for o in net(torch.from_numpy(x.transpose(0, 3, 1, 2).copy()))]
            o = sess.run(None, {"image": x.transpose(0, 3, 1, 2).copy()})
            interp.set_tensor(interp.get_input_details()[0]["index"], x)
            interp.invoke()
            for det in interp.get_output_details():
                j = names.index(det["name"])
                r = interp.get_tensor(det["index"])
                d_to = max(d_to, float(np.abs(t[j] - o[j]).max()))
                d_or = max(d_or, float(np.abs(o[j] - r).max()))
        print(f"  {name:16s} |torch-ONNX| {d_to:.2e}   |ONNX-LiteRT| {d_or:.2e}")


def bench_detect(astronaut: np.ndarray, repeats: int) -> None:
    from fitme_cli.perception.detect import DetectSettings, detect

    print(f"\n## detect per 12 MP photo (median of {repeats}, after load; 2 CPU cores)")
    for label, img in (("portrait face", _12mp_portrait(astronaut)), ("40-px face", _12mp_small_face(astronaut))):
        detect(img, DetectSettings())  # warm-up: sessions, first-use costs
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            det = detect(img, DetectSettings())
            times.append(time.perf_counter() - t0)
        print(f"  {label:14s} {statistics.median(times):6.2f} s  (detect {det.seconds['detect']:.2f} s, "
              f"landmarks+identity {det.seconds['landmarks']:.2f} s)")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="fewer repeats, no build timing")
    args = ap.parse_args()
    from skimage import data

    from fitme_cli.perception.registry import MODELS, ensure_models

    root = ensure_models(list(MODELS))
    astronaut = data.astronaut()
    bench_tflite_agreement(root)
    try:
        from fitme_cli.perception import dlib_resnet, facenet  # noqa: F401

        for mod in (dlib_resnet, facenet):
            if hasattr(mod, "benchmark_agreement"):
                mod.benchmark_agreement(root)
    except ImportError:
        pass
    bench_detect(astronaut, 3 if args.quick else 7)
    if not args.quick:
        bench_build()


if __name__ == "__main__":
    main()
