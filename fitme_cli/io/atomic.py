"""Atomic writes: a temporary file in the target's directory, fsync, then rename. A crash or a full
disk never leaves a half-written output, and readers see the old file or the new one."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from ..errors import OutputNotWritable

__all__ = ["publish_file", "atomic_write_bytes", "atomic_write_image"]


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def publish_file(tmp: Path, path: Path) -> None:
    """Rename a finished temporary file over ``path`` with the permissions a new file would get (some
    writers, e.g. safetensors, create theirs 0600)."""
    os.chmod(tmp, 0o666 & ~_umask())
    os.replace(tmp, path)


def atomic_write_bytes(path: Path, data: bytes) -> None:
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as e:
        raise OutputNotWritable(f"cannot write here: {e.strerror or e}", path) from None
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; outputs get the usual permissions
        os.replace(tmp, path)
    except OSError as e:
        Path(tmp).unlink(missing_ok=True)
        raise OutputNotWritable(f"cannot write: {e.strerror or e}", path) from None
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_image(path: Path, rgb: np.ndarray, quality: int = 95) -> None:
    """Write an (H, W, 3) uint8 RGB image as PNG or JPEG (by suffix), atomically."""
    import cv2

    path = Path(path)
    if not isinstance(rgb, np.ndarray) or rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"expected an (H, W, 3) uint8 RGB image, got {getattr(rgb, 'shape', type(rgb))} {getattr(rgb, 'dtype', '')}")
    ext = path.suffix.lower()
    if ext not in (".png", ".jpg", ".jpeg"):
        raise OutputNotWritable(f"unsupported image type {ext!r}; expected .png, .jpg or .jpeg", path)
    params = [cv2.IMWRITE_JPEG_QUALITY, quality] if ext != ".png" else [cv2.IMWRITE_PNG_COMPRESSION, 3]
    ok, buf = cv2.imencode(ext, np.ascontiguousarray(rgb[..., ::-1]), params)
    if not ok:
        raise OutputNotWritable("image encoding failed", path)
    atomic_write_bytes(path, buf.tobytes())
