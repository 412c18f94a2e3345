"""Progress and resource reporting shared by the long-running commands."""

from __future__ import annotations

import resource
import sys

__all__ = ["StageBar", "peak_memory_mib"]

_SHOWN = ("total", "landmarks", "photometric", "identity", "perceptual")


class StageBar:
    """One tqdm bar over all stages' iterations: the description is the stage, the postfix the current
    losses. Silent when stderr is not a terminal (tqdm's ``disable=None``)."""

    def __init__(self, total: int):
        from tqdm import tqdm

        self._bar = tqdm(total=total, desc="fit", unit="it", file=sys.stderr, disable=None)

    def callback(self, stage: str):
        def cb(i: int, n: int, losses: dict[str, float]) -> None:
            self._bar.set_description(f"{stage} {i + 1}/{n}")
            self._bar.set_postfix({k: f"{v:.3g}" for k, v in losses.items() if k in _SHOWN}, refresh=False)
            self._bar.update(1)
        return cb

    def close(self) -> None:
        self._bar.close()


def peak_memory_mib() -> float:
    """Peak resident memory of this process so far (Linux reports ru_maxrss in KiB)."""
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss / 1024 if sys.platform != "darwin" else rss / 2**20
