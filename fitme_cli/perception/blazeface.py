"""BlazeFace post-processing: SSD anchors, box/keypoint decoding, weighted non-maximum suppression.

Follows MediaPipe's ``SsdAnchorsCalculator``, ``TensorsToDetectionsCalculator`` and weighted NMS
(``NonMaxSuppressionCalculator`` with WEIGHTED), re-implemented from their documented behaviour.
Coordinates here are normalised to the network input square, [0, 1], x right, y down.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["AnchorSpec", "SHORT_RANGE", "FULL_RANGE", "ssd_anchors", "RawDetections", "decode", "weighted_nms", "iou"]


@dataclass(frozen=True)
class AnchorSpec:
    input_size: int
    strides: tuple[int, ...]
    interpolated_scale_aspect_ratio: float  # 1.0 adds a second anchor per layer, 0.0 none
    score_clip: float = 80.0  # raw logits are clipped before the sigmoid (exp(80) fits in float32)


SHORT_RANGE = AnchorSpec(128, (8, 16, 16, 16), 1.0)
FULL_RANGE = AnchorSpec(192, (4,), 0.0)


def ssd_anchors(spec: AnchorSpec) -> np.ndarray:
    """Anchor centres, (N, 2) float32 in [0, 1]. Consecutive layers with one stride share a grid."""
    centres = []
    i = 0
    strides = spec.strides
    while i < len(strides):
        per_cell = 0
        j = i
        while j < len(strides) and strides[j] == strides[i]:
            per_cell += 1 + (spec.interpolated_scale_aspect_ratio > 0)
            j += 1
        n = int(np.ceil(spec.input_size / strides[i]))
        ys, xs = np.meshgrid((np.arange(n) + 0.5) / n, (np.arange(n) + 0.5) / n, indexing="ij")
        grid = np.stack([xs.ravel(), ys.ravel()], axis=1)
        centres.append(np.repeat(grid, per_cell, axis=0))
        i = j
    return np.concatenate(centres).astype(np.float32)


@dataclass(frozen=True)
class RawDetections:
    """Decoded candidates before suppression, in input-square coordinates [0, 1]."""

    boxes: np.ndarray  # (N, 4) float32 x0, y0, x1, y1
    keypoints: np.ndarray  # (N, 6, 2) float32: eye, eye, nose tip, mouth, tragion, tragion
    scores: np.ndarray  # (N,) float32 in [0, 1]


def decode(regressors: np.ndarray, logits: np.ndarray, spec: AnchorSpec, anchors: np.ndarray) -> RawDetections:
    """regressors (N, 16) and logits (N,) or (N, 1) from the network -> RawDetections (all N)."""
    if regressors.shape != (anchors.shape[0], 16):
        raise ValueError(f"expected regressors of shape ({anchors.shape[0]}, 16), got {regressors.shape}")
    r = regressors.astype(np.float32).reshape(-1, 8, 2) / spec.input_size
    centre = r[:, 0] + anchors
    half = r[:, 1] / 2
    boxes = np.concatenate([centre - half, centre + half], axis=1)
    keypoints = r[:, 2:] + anchors[:, None, :]
    z = np.clip(logits.reshape(-1).astype(np.float32), -spec.score_clip, spec.score_clip)
    return RawDetections(boxes, keypoints, 1.0 / (1.0 + np.exp(-z)))


def iou(box: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    x0 = np.maximum(box[0], boxes[:, 0])
    y0 = np.maximum(box[1], boxes[:, 1])
    x1 = np.minimum(box[2], boxes[:, 2])
    y1 = np.minimum(box[3], boxes[:, 3])
    inter = np.clip(x1 - x0, 0, None) * np.clip(y1 - y0, 0, None)
    area = lambda b: np.clip(b[..., 2] - b[..., 0], 0, None) * np.clip(b[..., 3] - b[..., 1], 0, None)  # noqa: E731
    union = area(box) + area(boxes) - inter
    return np.where(union > 0, inter / np.maximum(union, 1e-12), 0.0)


def weighted_nms(det: RawDetections, iou_threshold: float = 0.3, min_score: float = 0.5) -> RawDetections:
    """MediaPipe's weighted NMS: each kept face is the score-weighted mean of the candidates it absorbs.

    The kept score is the best candidate's score. Output is sorted by score, descending.
    """
    keep = det.scores >= min_score
    boxes, kps, scores = det.boxes[keep], det.keypoints[keep], det.scores[keep]
    order = np.argsort(-scores, kind="stable")
    boxes, kps, scores = boxes[order], kps[order], scores[order]
    out_b, out_k, out_s = [], [], []
    remaining = np.arange(len(scores))
    while remaining.size:
        top = remaining[0]
        overlap = iou(boxes[top], boxes[remaining]) > iou_threshold
        members = remaining[overlap]
        w = scores[members][:, None]
        out_b.append((boxes[members] * w).sum(0) / w.sum())
        out_k.append((kps[members] * w[:, :, None]).sum(0) / w.sum())
        out_s.append(scores[top])
        remaining = remaining[~overlap]
    if not out_s:
        return RawDetections(np.zeros((0, 4), np.float32), np.zeros((0, 6, 2), np.float32), np.zeros(0, np.float32))
    return RawDetections(
        np.asarray(out_b, np.float32), np.asarray(out_k, np.float32), np.asarray(out_s, np.float32)
    )
