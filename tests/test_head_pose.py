"""Head pose from landmarks: known rotations of a real face's landmarks are recovered."""

import numpy as np
import pytest

from fitme_cli.perception.detect import DetectSettings, detect
from fitme_cli.perception.head_pose import face_rotation, head_pose


def _rx(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


@pytest.fixture(scope="module")
def frontal(astronaut, models_root):
    """The astronaut's landmarks rotated so that her face frame is the camera frame: pose (0, 0, 0)."""
    pts = detect(astronaut, DetectSettings(identity=False), models_root).face.landmarks.points.astype(np.float64)
    centred = pts - pts.mean(0)
    return centred @ face_rotation(pts)  # p @ R == (R^T p^T)^T


def test_frontal_is_zero(frontal):
    p = head_pose(frontal)
    assert abs(p.yaw) < 1e-6 and abs(p.pitch) < 1e-6 and abs(p.roll) < 1e-6


@pytest.mark.parametrize("yaw,pitch,roll", [(30, 0, 0), (-60, 0, 0), (0, 20, 0), (0, -25, 0), (0, 0, 90), (25, -15, 40), (-70, 10, -120)])
def test_known_rotations_are_recovered(frontal, yaw, pitch, roll):
    r = _rz(np.radians(roll)) @ _ry(np.radians(-yaw)) @ _rx(np.radians(-pitch))
    p = head_pose(frontal @ r.T)
    assert (p.yaw, p.pitch, p.roll) == pytest.approx((yaw, pitch, roll), abs=1e-6)


def test_sign_conventions(frontal):
    """yaw > 0: the nose tip (vertex 1, nearest the camera) moves toward the image's right;
    pitch > 0 (chin up): it moves up the image."""
    assert frontal[1, 2] < frontal[:, 2].mean()  # the nose tip is in front
    turned = frontal @ _ry(np.radians(-20)).T
    assert head_pose(turned).yaw > 0 and turned[1, 0] > frontal[1, 0] + 1
    raised = frontal @ _rx(np.radians(-20)).T
    assert head_pose(raised).pitch > 0 and raised[1, 1] < frontal[1, 1] - 1


def test_bad_shape():
    with pytest.raises(ValueError, match=r"expected \(468, 3\) landmarks, got \(68, 2\)"):
        head_pose(np.zeros((68, 2)))
