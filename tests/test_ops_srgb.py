"""fitme_cli.ops.srgb: the torch sRGB curve shared by the renderer, the fit and BRDF-GAN."""

import numpy as np
import torch

from fitme_cli.io.maps import linear_to_srgb as np_linear_to_srgb
from fitme_cli.io.maps import srgb_to_linear as np_srgb_to_linear
from fitme_cli.ops.srgb import linear_to_srgb, srgb_to_linear


def test_known_values_and_round_trip():
    x = torch.tensor([0.0, 0.04045, 0.5, 1.0], dtype=torch.float64)
    lin = srgb_to_linear(x)
    torch.testing.assert_close(lin, torch.tensor([0.0, 0.04045 / 12.92, 0.21404114, 1.0], dtype=torch.float64), rtol=0, atol=1e-7)
    # 3e-8 at the knee: the standard thresholds 0.04045 and 0.0031308 are not exact inverses
    torch.testing.assert_close(linear_to_srgb(lin), x, rtol=0, atol=1e-7)
    torch.testing.assert_close(linear_to_srgb(torch.tensor([-0.5, 2.0])), torch.tensor([0.0, 1.0]))  # clipped


def test_matches_the_numpy_curve_of_io_maps():
    x = np.linspace(0, 1, 1001, dtype=np.float32)
    np.testing.assert_allclose(srgb_to_linear(torch.from_numpy(x)).numpy(), np_srgb_to_linear(x), atol=1e-7)
    np.testing.assert_allclose(linear_to_srgb(torch.from_numpy(x)).numpy(), np_linear_to_srgb(x), atol=1e-6)


def test_gradients_are_finite_at_zero_and_match_finite_differences():
    x = torch.tensor([0.0, 0.01, 0.3, 0.9], dtype=torch.float64, requires_grad=True)
    for fn in (srgb_to_linear, linear_to_srgb):
        g, = torch.autograd.grad(fn(x).sum(), x)
        assert torch.isfinite(g).all()
    inner = torch.tensor([0.02, 0.3, 0.9], dtype=torch.float64, requires_grad=True)  # away from the knees
    assert torch.autograd.gradcheck(srgb_to_linear, (inner,))
    assert torch.autograd.gradcheck(linear_to_srgb, (inner,))
