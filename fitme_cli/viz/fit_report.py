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


_COLOURS = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189), (140, 86, 75),
            (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207)]


def _plot_panel(hist: list[dict[str, float]], name: str, w: int, h: int) -> np.ndarray:
    """One stage's weighted losses on a log scale, drawn with OpenCV (matplotlib's import and layout
    cost a second of every fit)."""
    img = np.full((h, w, 3), 255, np.uint8)
    left, right, top, bottom = 58, 130, 28, 34
    keys = [k for k in hist[0] if k != "total"] + ["total"]
    series = {k: np.array([r.get(k, np.nan) for r in hist], np.float64) for k in keys}
    pos = np.concatenate([v[np.isfinite(v) & (v > 0)] for v in series.values()] + [np.array([1e-3, 1.0])])
    lo, hi = np.floor(np.log10(pos.min())), np.ceil(np.log10(pos.max()))
    hi = max(hi, lo + 1)
    n = max(len(hist), 2)

    def xy(i, v):
        x = left + (w - left - right) * i / (n - 1)
        y = top + (h - top - bottom) * (hi - np.log10(v)) / (hi - lo)
        return int(round(x)), int(round(y))

    font = cv2.FONT_HERSHEY_SIMPLEX
    for d in range(int(lo), int(hi) + 1):
        _, y = xy(0, 10.0**d)
        cv2.line(img, (left, y), (w - right, y), (225, 225, 225), 1)
        cv2.putText(img, f"1e{d}", (4, y + 4), font, 0.35, (80, 80, 80), 1, cv2.LINE_AA)
    cv2.rectangle(img, (left, top), (w - right, h - bottom), (0, 0, 0), 1)
    for t in np.linspace(0, n - 1, 5):
        x, _ = xy(t, 1.0)
        cv2.putText(img, f"{int(round(t)) + 1}", (x - 8, h - bottom + 14), font, 0.35, (80, 80, 80), 1, cv2.LINE_AA)
    cv2.putText(img, "iteration", ((left + w - right) // 2 - 24, h - 6), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, name, (left, top - 8), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    for j, k in enumerate(keys):
        v = series[k]
        ok = np.isfinite(v) & (v > 0)
        if not ok.any():
            continue
        colour = (0, 0, 0) if k == "total" else _COLOURS[j % len(_COLOURS)]
        pts = np.array([xy(i, v[i]) for i in range(len(v)) if ok[i]], np.int32)
        cv2.polylines(img, [pts], False, colour, 2 if k == "total" else 1, cv2.LINE_AA)
        ly = top + 12 + 14 * j
        cv2.line(img, (w - right + 8, ly - 4), (w - right + 22, ly - 4), colour, 2)
        cv2.putText(img, k, (w - right + 26, ly), font, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
    return img


def loss_curve(stages: dict[str, list[dict[str, float]]], title: str = "") -> np.ndarray:
    """Weighted losses per iteration, one panel per stage (e.g. inversion, tuning), log scale.
    Returns an (H, W, 3) uint8 RGB image."""
    stages = {k: v for k, v in stages.items() if v}
    if not stages:
        stages = {"(no iterations)": [{"total": float("nan")}]}
    panels = [_plot_panel(hist, name, 520, 340) for name, hist in stages.items()]
    img = np.concatenate(panels, 1)
    if title:
        bar = np.full((24, img.shape[1], 3), 255, np.uint8)
        cv2.putText(bar, title, (8, 17), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
        img = np.concatenate([bar, img], 0)
    return img
