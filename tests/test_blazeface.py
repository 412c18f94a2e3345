"""BlazeFace post-processing: anchors, decoding and weighted NMS on known values."""

import numpy as np
import pytest

from fitme_cli.perception.blazeface import FULL_RANGE, SHORT_RANGE, RawDetections, decode, iou, ssd_anchors, weighted_nms


def test_anchor_counts_and_grid():
    short, full = ssd_anchors(SHORT_RANGE), ssd_anchors(FULL_RANGE)
    assert short.shape == (896, 2) and full.shape == (2304, 2)
    # stride 8 grid first (16x16, 2 anchors per cell), then stride 16 (8x8, 6 anchors per cell)
    assert np.allclose(short[0], [0.5 / 16, 0.5 / 16]) and np.allclose(short[1], short[0])
    assert np.allclose(short[512], [0.5 / 8, 0.5 / 8]) and np.allclose(short[512:518], short[512])
    assert np.allclose(full[1], [1.5 / 48, 0.5 / 48])
    assert short.min() > 0 and short.max() < 1


def test_decode_known_values():
    anchors = ssd_anchors(SHORT_RANGE)
    reg = np.zeros((896, 16), np.float32)
    reg[0, :4] = [12.8, -6.4, 25.6, 12.8]  # centre offset (0.1, -0.05), size (0.2, 0.1), in 128-px units
    reg[0, 4:6] = [6.4, 0]
    logits = np.full(896, -200.0, np.float32)
    logits[0] = 0.0
    d = decode(reg, logits, SHORT_RANGE, anchors)
    cx, cy = anchors[0] + [0.1, -0.05]
    assert np.allclose(d.boxes[0], [cx - 0.1, cy - 0.05, cx + 0.1, cy + 0.05], atol=1e-6)
    assert np.allclose(d.keypoints[0, 0], anchors[0] + [0.05, 0], atol=1e-6)
    assert d.scores[0] == pytest.approx(0.5) and d.scores[1] < 1e-30  # clipped, no overflow


def test_decode_rejects_wrong_shape():
    with pytest.raises(ValueError, match=r"expected regressors of shape \(896, 16\), got \(10, 16\)"):
        decode(np.zeros((10, 16)), np.zeros(10), SHORT_RANGE, ssd_anchors(SHORT_RANGE))


def test_weighted_nms_averages_overlaps_and_keeps_best_score():
    boxes = np.array([[0, 0, 1, 1], [0.1, 0, 1.1, 1], [5, 5, 6, 6], [0, 0, 1, 1]], np.float32)
    kps = np.repeat(boxes[:, None, :2], 6, axis=1)
    scores = np.array([0.9, 0.6, 0.8, 0.3], np.float32)
    out = weighted_nms(RawDetections(boxes, kps, scores), iou_threshold=0.3, min_score=0.5)
    assert len(out.scores) == 2 and np.allclose(out.scores, [0.9, 0.8])
    expect = (boxes[0] * 0.9 + boxes[1] * 0.6) / 1.5  # the 0.3 box is below min_score
    assert np.allclose(out.boxes[0], expect) and np.allclose(out.boxes[1], boxes[2])


def test_weighted_nms_empty():
    empty = RawDetections(np.zeros((0, 4), np.float32), np.zeros((0, 6, 2), np.float32), np.zeros(0, np.float32))
    assert len(weighted_nms(empty).scores) == 0


def test_iou_known_values():
    assert iou(np.array([0, 0, 2, 2.0]), np.array([[1, 1, 3, 3.0], [5, 5, 6, 6.0]])) == pytest.approx([1 / 7, 0])
