"""onnxruntime sessions for the converted networks: one cached session per file and thread count."""

from __future__ import annotations

import functools
from pathlib import Path

from ..errors import ModelMissing

__all__ = ["onnx_session"]


@functools.lru_cache(maxsize=16)
def _session(path: str, mtime_ns: int, threads: int):
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    opts.log_severity_level = 3
    return ort.InferenceSession(path, sess_options=opts, providers=["CPUExecutionProvider"])


def onnx_session(path: Path, threads: int = 0):
    """A cached ``onnxruntime.InferenceSession`` on the CPU. ``threads=0`` lets onnxruntime choose.

    The cache key includes the file's mtime, so a rebuilt model is picked up.
    """
    path = Path(path)
    if not path.is_file():
        raise ModelMissing("ONNX model is missing; run: fitme models build", path)
    return _session(str(path.resolve()), path.stat().st_mtime_ns, int(threads))
