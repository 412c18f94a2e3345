"""Pictures of a fit: the per-photo panel and the loss curves."""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["fit_panel", "loss_curve"]


def fit_panel(photo: np.ndarray, render: np.ndarray, mask: np.ndarray, detected68: np.ndarray,
              fitted68: np.ndarray) -> np.ndarray:
    """photo | photo with detected (green) and fitted (red) iBUG-68 points | render over the photo |
    absolute difference x3 inside the mesh. photo, render: (S, S, 3) uint8 sRGB; mask: (S, S) bool;
    landmarks: (68, 2) pixels of the same image. Returns (S, 4 S, 3) uint8."""
    if photo.shape != render.shape or photo.ndim != 3 or mask.shape != photo.shape[:2]:
        raise ValueError(f"fit_panel: photo {photo.shape}, render {render.shape}, mask {mask.shape} must agree")
    s = photo.shape[0]
    over = photo.copy()
    r = max(1, s // 200)
    for pts, colour in ((detected68, (0, 220, 0)), (fitted68, (255, 40, 40))):
        for x, y in np.asarray(pts, np.float64):
            if np.isfinite(x) and np.isfinite(y):
                cv2.circle(over, (int(round(x)), int(round(y))), r, colour, -1, cv2.LINE_AA)
    comp = photo.copy()
    comp[mask] = render[mask]
    diff = np.zeros_like(photo)
    d = np.abs(render.astype(np.int16) - photo.astype(np.int16)) * 3
    diff[mask] = np.clip(d, 0, 255).astype(np.uint8)[mask]
    panel = np.concatenate([photo, over, comp, diff], 1)
    scale = 0.3 if s < 200 else 0.45
    for i, label in enumerate(("photo", "landmarks (green detected, red fitted)" if s >= 256 else "landmarks", "render",
                               "|difference| x3")):
        cv2.putText(panel, label, (i * s + 3, 10 if s < 200 else 16), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 2, cv2.LINE_AA)
        cv2.putText(panel, label, (i * s + 3, 10 if s < 200 else 16), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)
    return panel


def loss_curve(stages: dict[str, list[dict[str, float]]], title: str = "") -> np.ndarray:
    """Weighted losses per iteration, one panel per stage (e.g. inversion, tuning), log scale.
    Returns an (H, W, 3) uint8 RGB image."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    stages = {k: v for k, v in stages.items() if v}
    fig, axes = plt.subplots(1, max(1, len(stages)), figsize=(5.5 * max(1, len(stages)), 3.6), dpi=100, squeeze=False)
    for ax, (name, hist) in zip(axes[0], stages.items()):
        keys = [k for k in hist[0] if k != "total"] + ["total"]
        for k in keys:
            y = np.array([h.get(k, np.nan) for h in hist], np.float64)
            if np.all(~np.isfinite(y) | (y <= 0)):
                continue
            ax.plot(np.arange(1, len(y) + 1), np.where(y > 0, y, np.nan), lw=2.2 if k == "total" else 1.2,
                    color="black" if k == "total" else None, label=k)
        ax.set_yscale("log")
        ax.set_xlabel("iteration")
        ax.set_title(name)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper right")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.canvas.draw()
    img = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    plt.close(fig)
    return img
