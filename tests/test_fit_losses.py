import pytest
import torch

from fitme_cli.fitting.losses import (chromaticity_loss, flip_loss, identity_loss, landmark_loss, mean_colour_loss,
                                      perceptual_loss, photometric_loss, w_prior)


def test_landmark_loss_known_values_scale_and_robustness():
    t = torch.zeros(2, 4, 2)
    p = t.clone()
    p[:, 0, 0] = 1.0  # one landmark 1 px off
    w = torch.ones(4)
    small = landmark_loss(p, t, w, torch.tensor([100.0, 1000.0]))
    assert small[0] > small[1] > 0  # the same pixel error matters less on a bigger face
    # pseudo-Huber of a 0.01-face-size error with knee 0.02, averaged over 4 points (~ d^2 / 2 when small)
    assert float(small[0]) == pytest.approx(0.02**2 * ((1 + 0.25) ** 0.5 - 1) / 4, rel=1e-4)
    assert float(small[1]) == pytest.approx(0.001**2 / 2 / 4, rel=0.01)
    p2 = t.clone()
    p2[:, 0, 0] = 1000.0  # an outlier grows linearly, not quadratically
    big = landmark_loss(p2, t, w, torch.tensor([100.0, 100.0]))
    p3 = t.clone()
    p3[:, 0, 0] = 2000.0
    bigger = landmark_loss(p3, t, w, torch.tensor([100.0, 100.0]))
    assert float(bigger[0] / big[0]) == pytest.approx(2.0, rel=0.01)
    assert landmark_loss(p, t, torch.tensor([0.0, 1, 1, 1]), torch.tensor([100.0, 100.0])).sum() == 0  # weight 0 ignores it
    with pytest.raises(ValueError, match="same shape"):
        landmark_loss(p[:, :3], t, w, torch.ones(2))


def test_mean_colour_loss():
    r = torch.zeros(1, 3, 4, 4)
    ph = torch.zeros(1, 3, 4, 4)
    ph[:, 0, :, :2] = 0.6  # red on the left half: the mean red is 0.3, the other channels 0
    m = torch.ones(1, 1, 4, 4)
    assert float(mean_colour_loss(r, ph, m)) == pytest.approx(0.1)  # |0.3| + 0 + 0, over 3 channels
    r[:, 0, :, 2:] = 0.6  # the same mean colour, pixels not lined up: no loss (photometric_loss: 0.2)
    assert float(mean_colour_loss(r, ph, m)) == pytest.approx(0.0)
    assert float(photometric_loss(r, ph, m)) == pytest.approx(0.2)
    m[..., 2:] = 0  # only the left half: render 0 against 0.6 red
    assert float(mean_colour_loss(r, ph, m)) == pytest.approx(0.2)
    assert float(mean_colour_loss(r, ph, torch.zeros_like(m))) == 0  # empty mask: no NaN
    with pytest.raises(ValueError, match=r"mean_colour_loss: got render \(1, 3, 4, 4\), photo \(1, 3, 4, 4\), mask \(1, 1, 4, 2\)"):
        mean_colour_loss(r, ph, m[..., :2])


def test_mean_colour_loss_gradcheck():
    torch.manual_seed(0)
    r = torch.rand(2, 3, 5, 5, dtype=torch.float64, requires_grad=True)
    ph = torch.rand(2, 3, 5, 5, dtype=torch.float64)
    m = (torch.rand(2, 1, 5, 5, dtype=torch.float64) > 0.4).double()
    assert torch.autograd.gradcheck(lambda x: mean_colour_loss(x, ph, m), (r,))


def test_photometric_loss():
    r = torch.zeros(1, 3, 4, 4)
    ph = torch.full((1, 3, 4, 4), 0.5)
    m = torch.zeros(1, 1, 4, 4)
    m[..., :2, :] = 1
    assert float(photometric_loss(r, ph, m)) == pytest.approx(0.5)
    ph[..., 2:, :] = 10  # outside the mask: ignored
    assert float(photometric_loss(r, ph, m)) == pytest.approx(0.5)
    assert float(photometric_loss(r, ph, torch.zeros_like(m))) == 0  # empty mask: no NaN
    with pytest.raises(ValueError, match="photometric_loss"):
        photometric_loss(r, ph, m[..., :2])


def test_identity_perceptual_and_priors():
    a = torch.randn(3, 128)
    assert torch.allclose(identity_loss(a, a), torch.zeros(3), atol=1e-6)
    assert torch.allclose(identity_loss(a, -a), torch.full((3,), 2.0), atol=1e-6)
    f = [torch.randn(2, 8, 5, 5), torch.randn(2, 4, 3, 3)]
    assert torch.allclose(perceptual_loss(f, f), torch.zeros(2))
    assert torch.allclose(perceptual_loss(f, [x * 3 for x in f]), torch.zeros(2), atol=1e-6)  # scale-free
    assert (perceptual_loss(f, [torch.randn_like(x) for x in f]) > 0.5).all()
    ws = torch.ones(2, 4, 8)
    assert torch.allclose(w_prior(ws, torch.zeros(8)), torch.ones(2))


def test_flip_and_chromaticity():
    mapped = torch.ones(4, 4, dtype=torch.bool)
    sym = torch.rand(1, 3, 4, 2)
    alb = torch.cat([sym, sym.flip(-1)], -1)
    assert float(flip_loss(alb, mapped)) == pytest.approx(0.0)
    asym = alb.clone()
    asym[..., 0] += 0.3
    assert float(flip_loss(asym, mapped)) > 0
    assert float(chromaticity_loss(alb * 0.5, alb, mapped)) == pytest.approx(0.0, abs=1e-6)  # darker, same colour
    assert float(chromaticity_loss(alb[:, [2, 1, 0]], alb, mapped)) > 0


def test_gradients_float64():
    p = torch.randn(1, 5, 2, dtype=torch.float64, requires_grad=True)
    t = torch.randn(1, 5, 2, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda x: landmark_loss(x, t, torch.ones(5, dtype=torch.float64),
                                                            torch.tensor([3.0], dtype=torch.float64)), (p,))
    r = torch.rand(1, 3, 3, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: identity_loss(x.flatten(1), torch.ones(1, 27, dtype=torch.float64)), (r,))
