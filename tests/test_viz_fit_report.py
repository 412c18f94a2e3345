"""The fit's pictures: the per-photo panel and the loss curves."""

import numpy as np
import pytest

from fitme_cli.viz.fit_report import fit_panel, loss_curve


def test_loss_curve_draws_one_panel_per_stage_with_the_total_in_black():
    hist = [{"total": 1.0 / (i + 1), "photometric": 0.5 / (i + 1), "w": 1e-5 * (i + 1)} for i in range(30)]
    img = loss_curve({"inversion": hist, "tuning": hist[:5], "empty": []}, "title")
    assert img.dtype == np.uint8 and img.shape == (24 + 340, 2 * 520, 3)
    black = (img.max(-1) < 30)
    assert black[:, :520].sum() > 500 and black[:, 520:].sum() > 300  # axes, labels and the total's line
    single = loss_curve({"inversion": [{"total": float("nan")}]})
    assert single.shape == (340, 520, 3)  # nothing to draw: an empty panel, no error


def test_fit_panel_layout_and_bad_input():
    s = 64
    photo = np.full((s, s, 3), 100, np.uint8)
    render = np.full((s, s, 3), 110, np.uint8)
    mask = np.zeros((s, s), bool)
    mask[20:40, 20:40] = True
    lm = np.tile([[32.0, 32.0]], (68, 1))
    p = fit_panel(photo, render, mask, lm, lm + 2)
    assert p.shape == (s, 4 * s, 3)
    assert (p[30, 2 * s + 30] == 110).all() and (p[55, 2 * s + 5] == 100).all()  # render only inside the mask
    assert (p[30, 3 * s + 30] == 30).all() and (p[50, 3 * s + 50] == 0).all()  # |difference| x 3 inside, black outside
    with pytest.raises(ValueError, match="must agree"):
        fit_panel(photo, render[:10], mask, lm, lm)
