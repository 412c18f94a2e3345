import numpy as np
import pytest
import torch

from fitme_cli.fitting.pose import initial_camera
from fitme_cli.render.camera import Camera, project


def _rot(yaw_deg):
    a = np.deg2rad(yaw_deg)
    ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    return np.diag([1.0, -1.0, -1.0]) @ ry


@pytest.mark.parametrize("yaw", [0.0, 30.0, -60.0])
def test_recovers_a_known_camera(models_root, yaw):
    from fitme_cli.shape.model import load_shape_model

    sm = load_shape_model(models_root)
    pts = sm.mean[sm.landmarks].numpy()
    cam = Camera(torch.tensor([[900.0, 900.0]]), torch.tensor([[320.0, 240.0]]),
                 torch.tensor(_rot(yaw)[None], dtype=torch.float32), torch.tensor([[5.0, -10.0, 550.0]]), 640, 480)
    px = project(torch.from_numpy(pts)[None], cam)[0, :, :2].numpy()
    px += np.random.default_rng(0).normal(0, 0.5, px.shape)  # half-pixel landmark noise
    est = initial_camera(px, pts, 640, 480, 900.0)
    assert np.allclose(est.rotation[0].numpy(), cam.rotation[0].numpy(), atol=0.02)
    assert np.allclose(est.translation[0].numpy(), cam.translation[0].numpy(), atol=[3, 3, 15])
    reproj = project(torch.from_numpy(pts)[None], est)[0, :, :2].numpy()
    assert np.abs(reproj - px).mean() < 1.0


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match=r"expected \(N, 2\) landmarks and \(N, 3\) model points"):
        initial_camera(np.zeros((10, 3)), np.zeros((10, 3)), 640, 480, 900.0)
    with pytest.raises(ValueError, match="at least 6 landmarks"):
        initial_camera(np.zeros((10, 2)), np.zeros((10, 3)), 640, 480, 900.0, weights=np.r_[np.ones(3), np.zeros(7)])
