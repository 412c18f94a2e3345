"""Effects: parsing user overrides, the selector's decisions, and that an effect that is off costs nothing."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fitme_cli.reflectance.maps import ReflectanceMaps
from fitme_cli.render import Camera, Effects, Lights, Renderer, RenderSettings, select_effects
from fitme_cli.render.effects import EFFECT_NAMES, highlight_fraction, parse_effects


pytestmark = pytest.mark.usefixtures("one_thread")


def test_parse_effects():
    assert parse_effects("+shadows,-specular") == {"shadows": True, "specular": False}
    assert parse_effects("sh-ambient=on, multi_light=off") == {"sh_ambient": True, "multi_light": False}
    assert parse_effects("none") == {n: False for n in EFFECT_NAMES}
    assert parse_effects("all,-shadows")["shadows"] is False and parse_effects("all,-shadows")["specular"] is True
    assert parse_effects("") == {}
    with pytest.raises(ValueError, match="unknown effect 'glitter'"):
        parse_effects("glitter")
    with pytest.raises(ValueError, match="on or off, got 'maybe'"):
        parse_effects("shadows=maybe")


def _skin(n=4000, highlights=0.0, seed=0):
    rng = np.random.default_rng(seed)
    skin = np.clip(np.array([0.75, 0.55, 0.45]) + rng.normal(0, 0.02, (n, 3)), 0, 1)
    k = int(highlights * n)
    skin[:k] = np.clip(0.97 + rng.normal(0, 0.01, (k, 3)), 0, 1)  # bright, nearly white
    return skin


def test_highlight_fraction_known_values():
    assert highlight_fraction(_skin(highlights=0.0)) < 0.002
    assert highlight_fraction(_skin(highlights=0.05)) == pytest.approx(0.05, abs=0.01)
    assert highlight_fraction(np.zeros((10, 3))) == 0.0  # too few pixels to judge


def test_selector_turns_effects_on_only_where_the_scene_calls_for_them():
    shiny = select_effects(400, _skin(highlights=0.02))
    assert shiny.effects.specular and "highlights on 2.0" in shiny.reasons["specular"]
    matte = select_effects(400, _skin(highlights=0.0))
    assert not matte.effects.specular and "highlights" in matte.reasons["specular"]
    tiny = select_effects(40, _skin(highlights=0.02))
    assert not tiny.effects.specular and "40 px wide" in tiny.reasons["specular"]
    assert not tiny.effects.subsurface
    res = {"base": 1.0, "multi_light": 0.90, "sh_ambient": 0.98, "shadows": 1.02}
    c = select_effects(400, _skin(), residuals=res)
    assert c.effects.multi_light and not c.effects.sh_ambient and not c.effects.shadows
    assert "-10.0 %" in c.reasons["multi_light"] and "+2.0 %" in c.reasons["shadows"]
    forced = select_effects(40, _skin(), residuals=res, forced={"specular": True, "multi_light": False})
    assert forced.effects.specular and not forced.effects.multi_light
    assert forced.reasons["specular"] == "on: forced by the user"
    assert set(c.reasons) == set(EFFECT_NAMES)


def _scene(models_root):
    from fitme_cli.shape.model import load_shape_model

    sm = load_shape_model(models_root)
    out = sm(*sm.zeros(1))
    maps = ReflectanceMaps(torch.full((1, 3, 64, 64), 0.4), torch.full((1, 1, 64, 64), 0.3),
                           torch.tensor([0, 0, 1.0]).view(1, 3, 1, 1).expand(1, 3, 64, 64).clone())
    cam = Camera.looking_at_face(1, 64, 64, distance_mm=450, focal_35mm=60)
    return sm, out, maps, cam


def test_effects_that_are_off_are_not_computed(models_root, monkeypatch):
    import fitme_cli.render.renderer as rmod

    sm, out, maps, cam = _scene(models_root)
    r = Renderer.for_shape_model(sm, RenderSettings(components=True))
    calls = {"specular": 0, "subsurface": 0, "shadows": 0}

    def counting(name, fn):
        def wrapped(*a, **k):
            calls[name] += 1
            return fn(*a, **k)
        return wrapped

    monkeypatch.setattr(rmod, "specular_reflectance", counting("specular", rmod.specular_reflectance))
    monkeypatch.setattr(rmod, "specular_pixels", counting("specular", rmod.specular_pixels))
    monkeypatch.setattr(rmod, "subsurface_scatter", counting("subsurface", rmod.subsurface_scatter))
    monkeypatch.setattr(rmod, "light_visibility", counting("shadows", rmod.light_visibility))
    lights = Lights.frontal(1)
    o = r(out.vertices, out.normals, out.tangents, maps, cam, lights, Effects.none())
    assert calls == {"specular": 0, "subsurface": 0, "shadows": 0} and o.specular is None
    o = r(out.vertices, out.normals, out.tangents, maps, cam, lights, Effects.all())
    assert calls == {"specular": 1, "subsurface": 1, "shadows": 1} and o.specular is not None
    assert o.specular.max() > 0


def test_each_effect_changes_the_image(models_root):
    sm, out, maps, cam = _scene(models_root)
    r = Renderer.for_shape_model(sm)
    base = Lights.frontal(1)
    side = torch.nn.functional.normalize(torch.tensor([[[0.3, 0.4, 1.0], [-1.0, 0.0, 0.2]]]), dim=-1)
    lights = Lights(base.ambient, side, torch.tensor([[[0.7] * 3, [0.6] * 3]]), sh=base.sh)
    ref = r(out.vertices, out.normals, out.tangents, maps, cam, lights, Effects.none()).image
    for name in EFFECT_NAMES:
        img = r(out.vertices, out.normals, out.tangents, maps, cam, lights, Effects(**{n: n == name for n in EFFECT_NAMES})).image
        assert (img - ref).abs().max() > 1e-3, name


def test_single_colour_sh_known_values_and_bad_input():
    from fitme_cli.render.lights import single_colour_sh

    sh = torch.zeros(2, 9, 3)
    sh[0, 0] = torch.tensor([2.0, 1.0, 0.0])  # band 0: warm; chromaticity (2, 1, 0) / 1 (+ eps)
    sh[0, 3] = torch.tensor([0.0, 0.6, 0.0])  # a green-only gradient: grey level 0.2
    sh[1] = 0.7  # grey: unchanged
    out = single_colour_sh(sh, eps=0.0)
    torch.testing.assert_close(out[0, 0], torch.tensor([2.0, 1.0, 0.0]))
    torch.testing.assert_close(out[0, 3], torch.tensor([0.4, 0.2, 0.0]))  # the gradient now in band 0's colour
    assert (out[0, [1, 2, 4, 5, 6, 7, 8]] == 0).all()
    torch.testing.assert_close(out[1], sh[1])
    torch.testing.assert_close(out.mean(-1), sh.mean(-1))  # each coefficient keeps its grey level
    black = single_colour_sh(torch.zeros(1, 9, 3).index_fill_(1, torch.tensor([2]), 0.3))
    torch.testing.assert_close(black[0, 2], torch.full((3,), 0.3))  # a black band 0 gives a grey environment
    for bad in (torch.zeros(9, 3), torch.zeros(1, 4, 3), torch.zeros(1, 9, 1)):
        with pytest.raises(ValueError, match=r"expected \(B, 9, 3\)"):
            single_colour_sh(bad)


def test_single_colour_sh_keeps_every_direction_in_one_colour_and_gradcheck():
    from fitme_cli.render.lights import sh_basis, single_colour_sh

    g = torch.Generator().manual_seed(0)
    sh = torch.randn(3, 9, 3, generator=g, dtype=torch.float64) * 0.3
    sh[:, 0] = sh[:, 0].abs() + 1.0
    n = torch.nn.functional.normalize(torch.randn(3, 500, 3, generator=g, dtype=torch.float64), dim=-1)
    irr = torch.einsum("bnk,bkc->bnc", sh_basis(n), single_colour_sh(sh))
    chroma = (sh[:, 0].clamp(min=0) + 1e-4) / (sh[:, 0].clamp(min=0) + 1e-4).mean(-1, keepdim=True)
    torch.testing.assert_close(irr, irr.mean(-1, keepdim=True) * chroma[:, None])  # every normal lit in one colour
    free = torch.einsum("bnk,bkc->bnc", sh_basis(n), sh)
    assert not torch.allclose(free, free.mean(-1, keepdim=True) * chroma[:, None], atol=1e-3)  # the input was not
    assert torch.autograd.gradcheck(single_colour_sh, (sh.clone().requires_grad_(True),))
