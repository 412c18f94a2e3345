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


def _faces(astronaut: np.ndarray) -> dict[str, np.ndarray]:
    from skimage import data

    return {"astronaut": astronaut, "cameraman": np.repeat(data.camera()[..., None], 3, axis=2)}


def bench_identity_agreement(root: Path, astronaut: np.ndarray) -> None:
    """dlib: our chip + ONNX vs dlib's compute_face_descriptor with dlib's own 68-point predictor.
    FaceNet: our torch and ONNX vs OpenCV's cv2.dnn on the same crop."""
    import dlib

    from fitme_cli.perception import dlib_resnet, facenet
    from fitme_cli.perception.face_chip import extract_chip
    from fitme_cli.perception.onnx_runner import onnx_session
    from fitme_cli.perception.store import package_file

    sp = package_file("face-recognition-models", "face_recognition_models",
                      "models/shape_predictor_68_face_landmarks.dat", "CC0-1.0").path
    predictor = dlib.shape_predictor(str(sp))
    facerec = dlib.face_recognition_model_v1(str(dlib_resnet.source_file().path))
    torch_dlib = dlib_resnet.load_dlib_resnet(root)
    torch_fn = facenet.load_facenet(root)
    net = facenet.read_net(facenet.source_file().path)
    print("\n## identity networks on real faces (scikit-image astronaut and cameraman)")
    for name, img in _faces(astronaut).items():
        h, w = img.shape[:2]
        box = {"astronaut": (175, 76, 265, 166), "cameraman": (190, 110, 270, 200)}[name]
        shape = predictor(img, dlib.rectangle(*box))
        lm = np.array([[p.x, p.y] for p in shape.parts()], np.float64)
        ref = np.array(facerec.compute_face_descriptor(img, shape))
        onnx = dlib_resnet.face_descriptor_onnx(img, lm, root)
        chip = extract_chip(img, lm)
        with torch.no_grad():
            t = torch_dlib(torch.from_numpy(chip.astype(np.float32) / 255).permute(2, 0, 1)[None]).numpy()[0]
        print(f"  dlib_resnet {name:10s} |torch-ONNX| {np.abs(t - onnx).max():.1e}   |ONNX-dlib| {np.abs(onnx - ref).max():.1e}")
        crop = facenet.facenet_crop(img, lm)
        x = np.ascontiguousarray((crop.astype(np.float32) / 255).transpose(2, 0, 1)[None])
        o = onnx_session(root / "facenet.onnx").run(None, {"image": x})[0][0]
        with torch.no_grad():
            t = torch_fn(torch.from_numpy(x)).numpy()[0]
            r = facenet.cv2dnn_embedding(net, facenet.prewhiten(torch.from_numpy(x)).numpy()).reshape(-1)
        print(f"  facenet     {name:10s} |torch-ONNX| {np.abs(t - o).max():.1e}   |ONNX-cv2.dnn| {np.abs(o - r).max():.1e}")


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
    bench_identity_agreement(root, astronaut)
    bench_detect(astronaut, 3 if args.quick else 7)
    if not args.quick:
        bench_build()


if __name__ == "__main__":
    main()
