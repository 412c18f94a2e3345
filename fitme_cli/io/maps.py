"""Texture maps on disk: 8- and 16-bit PNG (sRGB-encoded) and OpenEXR (linear float), read to linear
float32 and written back in the same format, atomically."""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputNotFound, NotAnImage, OutputNotWritable
from .atomic import atomic_write_bytes

__all__ = ["MapImage", "read_map", "write_map", "srgb_to_linear", "linear_to_srgb"]


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, np.float32)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    x = np.clip(np.asarray(x, np.float32), 0.0, 1.0)
    return np.where(x <= 0.0031308, x * 12.92, 1.055 * np.power(x, 1 / 2.4) - 0.055).astype(np.float32)


@dataclass(frozen=True)
class MapImage:
    linear: np.ndarray  # (H, W, C) float32, linear light (PNGs are decoded from sRGB)
    kind: str  # "png8", "png16", "exr16" (half) or "exr32": how it was stored, and will be written back
    path: Path


def read_map(path: str | Path) -> MapImage:
    path = Path(path)
    if not path.is_file():
        raise InputNotFound("file not found", path)
    ext = path.suffix.lower()
    if ext == ".exr":
        import OpenEXR

        try:
            with OpenEXR.File(str(path)) as f:
                ch = f.channels()
                if "RGB" in ch:
                    raw = np.asarray(ch["RGB"].pixels)
                elif all(c in ch for c in "RGB"):
                    raw = np.stack([np.asarray(ch[c].pixels) for c in "RGB"], -1)
                else:
                    raise NotAnImage(f"EXR has channels {sorted(ch)}; expected RGB", path)
        except NotAnImage:
            raise
        except Exception as e:
            raise NotAnImage(f"not a readable EXR file ({e})", path) from None
        kind = "exr16" if raw.dtype == np.float16 else "exr32"
        return MapImage(raw.astype(np.float32), kind, path)
    if ext != ".png":
        raise NotAnImage(f"unsupported map type {ext!r}; expected .png (8 or 16 bit) or .exr", path)
    import cv2

    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise NotAnImage("not a readable PNG file", path)
    if raw.ndim == 2:
        raw = np.repeat(raw[..., None], 3, axis=2)
    raw = raw[..., :3][..., ::-1]  # BGR(A) -> RGB
    if raw.dtype == np.uint16:
        return MapImage(srgb_to_linear(raw / 65535.0), "png16", path)
    if raw.dtype == np.uint8:
        return MapImage(srgb_to_linear(raw / 255.0), "png8", path)
    raise NotAnImage(f"PNG sample type {raw.dtype} is not supported", path)


def write_map(path: str | Path, linear: np.ndarray, kind: str) -> None:
    """Write (H, W, 3) linear float32 as ``kind`` (see MapImage), atomically."""
    path = Path(path)
    linear = np.asarray(linear, np.float32)
    if kind in ("exr16", "exr32"):
        import OpenEXR

        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".exr", dir=path.parent)
        os.close(fd)
        try:
            header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
            dtype = np.float16 if kind == "exr16" else np.float32
            with OpenEXR.File(header, {"RGB": np.ascontiguousarray(linear.astype(dtype))}) as f:
                f.write(tmp)
            os.chmod(tmp, 0o644)
            os.replace(tmp, path)
        except OSError as e:
            Path(tmp).unlink(missing_ok=True)
            raise OutputNotWritable(f"cannot write: {e.strerror or e}", path) from None
        return
    import cv2

    srgb = linear_to_srgb(linear)[..., ::-1]
    arr = np.round(srgb * (65535 if kind == "png16" else 255)).astype(np.uint16 if kind == "png16" else np.uint8)
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(arr))
    if not ok:
        raise OutputNotWritable("PNG encoding failed", path)
    atomic_write_bytes(path, buf.tobytes())
