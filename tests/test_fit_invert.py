"""Smoke test of the inversion loop on a synthetic photo with a known pose (a tiny random generator)."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from fitme_cli.fitting.invert import InversionSettings, PhotoInput, invert, member_settings
from fitme_cli.reflectance.gan.networks import GanSettings, Generator, decode_maps
from fitme_cli.reflectance.maps import ReflectanceMaps
from fitme_cli.render import Camera, Effects, Lights, Renderer
from fitme_cli.render.camera import project

pytestmark = pytest.mark.usefixtures("one_thread")


def _synthetic_photo(sm, size: int, maps: ReflectanceMaps, lights: Lights, effects: Effects = Effects.none()):
    """A render of the mean face through a frontal camera, as a PhotoInput with exact landmarks.
    Returns (photo, camera, landmarks (468, 2))."""
    cam = Camera.looking_at_face(1, size, size, distance_mm=420, focal_35mm=50)
    shp = sm(*sm.zeros(1))
    with torch.no_grad():
        photo = Renderer.for_shape_model(sm)(shp.vertices, shp.normals, shp.tangents, maps, cam, lights, effects)
    crop = (photo.image[0].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
    lm = project(shp.vertices[:, sm.landmarks], cam)[0, :, :2].numpy().astype(np.float32)
    i68 = lm[np.linspace(0, 467, 68).astype(int)]  # any 68 spread points suffice for the chip transform here
    p = PhotoInput(crop, lm, i68, photo.mask[0, 0].numpy(), float(cam.focal[0, 0]), np.array([size / 2, size / 2]), np.eye(2, 3))
    return p, cam, lm


def test_inversion_keeps_the_landmarks_and_fits_the_light(models_root):
    from fitme_cli.perception.dlib_resnet import load_dlib_resnet
    from fitme_cli.shape.model import load_shape_model

    torch.manual_seed(0)
    sm = load_shape_model(models_root)
    size = 128
    G = Generator(GanSettings(resolution=16, branch_resolution=16, channel_base=64, channel_max=16, z_dim=16, w_dim=16))
    bright = Lights(torch.full((1, 3), 0.9), torch.tensor([[[0.0, 0.0, 1.0]]]), torch.full((1, 1, 3), 0.6))
    with torch.no_grad():  # the "photo": the mean face, W average, under a brighter light than the start
        maps = decode_maps(G.synthesis(G.w_avg.view(1, 1, -1).repeat(1, G.settings.num_ws, 1), noise_mode="const"), G.settings)
    p, cam, lm = _synthetic_photo(sm, size, maps, bright)
    s = InversionSettings(iterations=15, render_size=size, coarse_resolution=8, effects=Effects.none(), select_effects=False,
                          lambdas=(100.0, 0.5, 0.0, 0.0, 5e-2, 5e-4, 5e-4))
    res = invert([p], G, sm, load_dlib_resnet(models_root), sm.landmarks, np.arange(10), s)
    h = res.history
    assert len(h) == 15 and all(np.isfinite(list(r.values())).all() for r in h)
    assert h[-1]["photometric"] < 0.5 * h[0]["photometric"]  # the lights moved toward the photo's
    pred = project(sm(res.p_s, res.p_e).vertices[:, sm.landmarks], res.cameras)[0, :, :2].numpy()
    assert np.abs(pred - lm).mean() < 1.0  # PnP start; the loop keeps the landmarks within a pixel
    assert res.maps.albedo.shape == (1, 3, 16, 16) and res.p_e.shape == (1, sm.n_expressions)


def test_tuning_trains_only_the_middle_layers_and_lowers_its_loss(models_root):
    from fitme_cli.fitting.invert import TuningSettings, tune
    from fitme_cli.perception.dlib_resnet import load_dlib_resnet
    from fitme_cli.shape.model import load_shape_model

    torch.manual_seed(1)
    sm = load_shape_model(models_root)
    G = Generator(GanSettings(resolution=32, branch_resolution=32, channel_base=128, channel_max=16, z_dim=16, w_dim=16))
    lights = Lights(torch.full((1, 3), 0.5), torch.tensor([[[0.0, 0.0, 1.0]]]), torch.full((1, 1, 3), 0.5))
    reddish = ReflectanceMaps(torch.tensor([0.5, 0.2, 0.15]).view(1, 3, 1, 1).expand(1, 3, 32, 32).clone(),
                              torch.full((1, 1, 32, 32), 0.2), torch.tensor([0.0, 0, 1]).view(1, 3, 1, 1).expand(1, 3, 32, 32).clone())
    p, cam, _ = _synthetic_photo(sm, 96, reddish, lights)
    ws = G.ws(torch.randn(1, 16)).detach()
    with torch.no_grad():
        maps0 = decode_maps(G.synthesis(ws, noise_mode="const"), G.settings)
    from fitme_cli.fitting.invert import InversionResult

    inv = InversionResult(ws, *sm.zeros(1), cam, lights, maps0, [], Effects.none(), None, {})
    before = {k: v.clone() for k, v in G.state_dict().items()}
    res = tune([p], G, inv, sm, load_dlib_resnet(models_root), sm.landmarks, np.arange(10),
               torch.ones(32, 32, dtype=torch.bool), TuningSettings(iterations=12, lr=1e-2, effects=Effects.none()))
    middle = G.synthesis.middle_layers(4)
    changed = {k for k, v in G.state_dict().items() if not torch.equal(v, before[k])}
    assert changed and changed == set(res.layers)
    assert all(any(f".{m.split('.')[0]}.{m.split('.')[1]}." in k for m in middle) for k in changed)
    assert res.history[-1]["photometric"] < res.history[0]["photometric"]
    assert all(np.isfinite(list(r.values())).all() for r in res.history)


def test_effect_selection_runs_at_select_fraction_and_user_overrides_win(models_root):
    from fitme_cli.perception.dlib_resnet import load_dlib_resnet
    from fitme_cli.shape.model import load_shape_model

    torch.manual_seed(2)
    sm = load_shape_model(models_root)
    G = Generator(GanSettings(resolution=16, branch_resolution=16, channel_base=64, channel_max=16, z_dim=16, w_dim=16))
    side = Lights(torch.full((1, 3), 0.3), torch.tensor([[[0.0, 0.0, 1.0], [-1.0, 0.0, 0.3]]]),
                  torch.tensor([[[0.5] * 3, [0.9] * 3]]))
    with torch.no_grad():
        maps = decode_maps(G.synthesis(G.w_avg.view(1, 1, -1).repeat(1, G.settings.num_ws, 1), noise_mode="const"), G.settings)
    p, _, _ = _synthetic_photo(sm, 96, maps, side, effects=Effects(specular=False, subsurface=False, multi_light=True))
    s = InversionSettings(iterations=6, render_size=96, coarse_resolution=8, coarse_fraction=0.5,
                          lambdas=(100.0, 0.5, 0.0, 0.0, 5e-2, 5e-4, 5e-4), forced_effects=(("shadows", True),),
                          selection_steps=15)
    res = invert([p], G, sm, load_dlib_resnet(models_root), sm.landmarks, np.arange(10), s)
    r = res.coarse_residuals
    assert set(r) == {"base", "shadows", "multi_light", "sh_ambient"} and all(np.isfinite(list(r.values())))
    assert r["multi_light"] < r["base"]  # a strong second light in the photo: a fitted fill light helps
    assert res.choice is not None and res.effects == res.choice.effects
    assert res.selected_at == 2  # select_fraction 0.4 of 6 iterations, whatever the coarse phase
    assert res.effects.shadows and "forced" in res.choice.reasons["shadows"]
    assert res.effects.multi_light == (r["multi_light"] < 0.95 * r["base"])
    assert res.lights.count == (2 if res.effects.multi_light else 1)
    assert all(np.isfinite(list(h.values())).all() for h in res.history)


def _w_average_photo(models_root):
    """(shape model, tiny G, a 64^2 photo of the mean face wearing G's W-average maps under a frontal light)."""
    from fitme_cli.shape.model import load_shape_model

    torch.manual_seed(3)
    sm = load_shape_model(models_root)
    G = Generator(GanSettings(resolution=16, branch_resolution=16, channel_base=64, channel_max=16, z_dim=16, w_dim=16))
    lights = Lights(torch.full((1, 3), 0.5), torch.tensor([[[0.0, 0.0, 1.0]]]), torch.full((1, 1, 3), 0.5))
    with torch.no_grad():
        maps = decode_maps(G.synthesis(G.w_avg.view(1, 1, -1).repeat(1, G.settings.num_ws, 1), noise_mode="const"), G.settings)
    p, _, _ = _synthetic_photo(sm, 64, maps, lights)
    return sm, G, p


@pytest.mark.parametrize("forced", [("sh_ambient",), ("multi_light",), ("sh_ambient", "multi_light")])
def test_effects_forced_without_the_selector_get_their_lights(models_root, forced):
    from fitme_cli.perception.dlib_resnet import load_dlib_resnet

    sm, G, p = _w_average_photo(models_root)
    s = InversionSettings(iterations=3, render_size=64, coarse_resolution=8, select_effects=False,
                          effects=Effects(specular=False, subsurface=False), forced_effects=tuple((f, True) for f in forced),
                          lambdas=(100.0, 0.5, 0.0, 0.0, 5e-2, 5e-4, 5e-4))
    res = invert([p], G, sm, load_dlib_resnet(models_root), sm.landmarks, np.arange(10), s)
    assert all(getattr(res.effects, f) for f in forced)
    assert (res.lights.sh is not None) == ("sh_ambient" in forced)
    assert res.lights.count == (2 if "multi_light" in forced else 1)
    assert all(np.isfinite(list(h.values())).all() for h in res.history)


@pytest.mark.parametrize("one_colour", [True, False])
def test_the_sh_environment_is_fitted_in_one_colour(models_root, one_colour):
    from fitme_cli.perception.dlib_resnet import load_dlib_resnet
    from fitme_cli.shape.model import load_shape_model

    torch.manual_seed(3)
    sm = load_shape_model(models_root)
    G = Generator(GanSettings(resolution=16, branch_resolution=16, channel_base=64, channel_max=16, z_dim=16, w_dim=16))
    sh = torch.zeros(1, 9, 3)
    sh[0, 0] = 1.8
    sh[0, 3] = torch.tensor([0.9, -0.6, 0.0])  # red from one side, green from the other
    lights = Lights(torch.full((1, 3), 0.5), torch.tensor([[[0.0, 0.0, 1.0]]]), torch.full((1, 1, 3), 0.3), sh=sh)
    with torch.no_grad():
        maps = decode_maps(G.synthesis(G.w_avg.view(1, 1, -1).repeat(1, G.settings.num_ws, 1), noise_mode="const"), G.settings)
    p, _, _ = _synthetic_photo(sm, 64, maps, lights, Effects(specular=False, subsurface=False, sh_ambient=True))
    s = InversionSettings(iterations=8, lr=0.05, render_size=64, coarse_resolution=8, select_effects=False,
                          effects=Effects(specular=False, subsurface=False, sh_ambient=True), sh_one_colour=one_colour,
                          lambdas=(100.0, 0.5, 0.0, 0.0, 5e-2, 5e-4, 5e-4))
    fitted = invert([p], G, sm, load_dlib_resnet(models_root), sm.landmarks, np.arange(10), s).lights.sh[0]
    # each coefficient's colour against band 0's: one colour leaves none; free, the photo's red-green gradient shows
    c0 = fitted[0] / fitted[0].mean()
    off = (fitted[1:] - fitted[1:].mean(-1, keepdim=True) * c0).abs().max()
    assert (off < 1e-3) if one_colour else (off > 0.05)


def test_start_jitter_nudges_only_the_start_and_is_seeded(models_root):
    from fitme_cli.perception.dlib_resnet import load_dlib_resnet

    sm, G, p = _w_average_photo(models_root)
    desc = load_dlib_resnet(models_root)

    def start_w(m):
        s = member_settings(InversionSettings(iterations=1, lr=1e-12, render_size=64, select_effects=False,
                                              effects=Effects(specular=False, subsurface=False),
                                              lambdas=(100.0, 0.5, 0.0, 0.0, 5e-2, 5e-4, 5e-4)), m, 1e-3)
        return invert([p], G, sm, desc, sm.landmarks, np.arange(10), s).ws[0, 0]

    w_avg = G.w_avg.detach()
    plain = start_w(0)  # member 0: the settings as given, no nudge
    torch.testing.assert_close(plain, w_avg, atol=1e-9, rtol=0)  # lr 1e-12: the result is the start
    a, b, c = start_w(1), start_w(1), start_w(2)
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert 0.5e-3 < float((a - w_avg).std()) < 2e-3


def test_inversion_settings_are_checked():
    from fitme_cli.fitting.invert import InversionSettings

    with pytest.raises(ValueError, match=r"start_jitter must be finite and >= 0, got -1e-05"):
        InversionSettings(start_jitter=-1e-5)

    with pytest.raises(ValueError, match=r"noise_gain must be in \[0, 1\], got -0.1"):
        InversionSettings(noise_gain=-0.1)
    with pytest.raises(ValueError, match=r"select_fraction must be in \[0, 1\], got 1.5"):
        InversionSettings(select_fraction=1.5)
    with pytest.raises(ValueError, match=r"coarse_fraction must be in \[0, 1\], got -0.2"):
        InversionSettings(coarse_fraction=-0.2)

    with pytest.raises(ValueError, match=r"hair_weight must be finite and >= 0, got -0.5"):
        InversionSettings(hair_weight=-0.5)


def _problem(models_root, photo):
    from fitme_cli.fitting.invert import _Problem
    from fitme_cli.perception.dlib_resnet import load_dlib_resnet
    from fitme_cli.shape.model import load_shape_model

    sm = load_shape_model(models_root)
    return _Problem([photo], sm, load_dlib_resnet(models_root), sm.landmarks, np.arange(10), 1.0, photo.crop.shape[0])


def test_hair_mask_is_the_scalp_inside_the_silhouette_outside_the_skin(models_root):
    from fitme_cli.fitting.invert import _HAIR_MARGIN

    sm, _, p = _w_average_photo(models_root)
    pb = _problem(models_root, p)
    scalp_tri = int(torch.nonzero(pb.scalp_triangle)[0, 0])
    face_tri = int(torch.nonzero(~pb.scalp_triangle)[0, 0])
    tri = torch.full((1, 64, 64), scalp_tri, dtype=torch.long)
    tri[0, :, :4] = -1  # background on the left
    tri[0, :, 40:] = face_tri  # a face triangle on the right
    pb.skin = torch.zeros_like(pb.skin)
    pb.skin[0, 0, :8] = 1  # photo skin along the top
    want = torch.zeros(1, 1, 64, 64)
    want[0, 0, 8:, 4 + _HAIR_MARGIN:40] = 1
    assert torch.equal(pb.hair_mask(tri), want)
    assert torch.equal(pb.hair_mask(torch.full((1, 64, 64), -1)), torch.zeros(1, 1, 64, 64))


def _dark_haired_photo(models_root):
    """(shape model, tiny G, the W-average photo with its scalp darkened to a fifth: dark hair; the skin
    mask is the rest of the head)."""
    from fitme_cli.render import Renderer

    sm, G, p = _w_average_photo(models_root)
    with torch.no_grad():
        shp = sm(*sm.zeros(1))
        cam = Camera.looking_at_face(1, 64, 64, distance_mm=420, focal_35mm=50)
        flat = ReflectanceMaps(*[torch.zeros(1, c, 8, 8) for c in (3, 1, 3)])
        light = Lights(torch.ones(1, 3), torch.tensor([[[0.0, 0.0, 1.0]]]), torch.zeros(1, 1, 3))
        tri = Renderer.for_shape_model(sm)(shp.vertices, shp.normals, shp.tangents, flat, cam, light, Effects.none()).fragments.triangle[0]
    scalp_tri = _problem(models_root, p).scalp_triangle
    scalp = (scalp_tri[tri.clamp(min=0)] & (tri >= 0)).numpy()
    assert scalp.sum() > 50  # the top of the head is in view
    crop = p.crop.copy()
    crop[scalp] = (crop[scalp] * 0.2).astype(np.uint8)
    dark = PhotoInput(crop, p.landmarks, p.ibug68, (p.skin * ~scalp).astype(np.float32), p.focal_px, p.principal, p.to_photo)
    return sm, G, dark


def test_hair_term_moves_only_the_maps(models_root):
    """Through the shared render the term moved the head to hide a cap from the scalp (docs/fitting.md)."""
    sm, G, dark = _dark_haired_photo(models_root)
    pb = _problem(models_root, dark)
    with torch.no_grad():
        maps = decode_maps(G.synthesis(G.w_avg.view(1, 1, -1).repeat(1, G.settings.num_ws, 1), noise_mode="const"), G.settings)
    albedo = maps.albedo.clone().requires_grad_(True)
    p_s, p_e = (z.clone().requires_grad_(True) for z in sm.zeros(1))
    cam = Camera.looking_at_face(1, 64, 64, distance_mm=420, focal_35mm=50)
    trans = cam.translation.clone().requires_grad_(True)
    colour = torch.full((1, 1, 3), 0.5, requires_grad=True)
    cam = Camera(cam.focal, cam.principal, cam.rotation, trans, 64, 64)
    lights = Lights(torch.full((1, 3), 0.5), torch.tensor([[[0.0, 0.0, 1.0]]]), colour)
    terms = pb.evaluate(ReflectanceMaps(albedo, maps.specular, maps.normals), p_s, p_e, cam, lights,
                        Effects(specular=False, subsurface=False), with_identity=False)
    assert float(terms["hair"].detach()) > 0
    grads = torch.autograd.grad(terms["hair"].sum(), (albedo, p_s, p_e, trans, colour), allow_unused=True)
    assert float(grads[0].abs().sum()) > 0
    assert all(g is None or float(g.abs().sum()) == 0 for g in grads[1:])
    photometric = torch.autograd.grad(terms["photometric"].sum(), (trans, colour))  # the skin term still moves them
    assert all(float(g.abs().sum()) > 0 for g in photometric)


def test_hair_term_pulls_the_rendered_scalp_toward_the_photos_hair(models_root):
    """The skin mask leaves the scalp out, so without the hair term nothing fits its colour (the fast
    preset kept w_avg's grey hair on a dark-haired man, docs/fitting.md)."""
    from fitme_cli.perception.dlib_resnet import load_dlib_resnet

    sm, G, dark = _dark_haired_photo(models_root)
    # no skin pixels: a tiny random G cannot darken the scalp without the face, which the skin term
    # would forbid; here the hair's share is 1 and nothing else moves W
    dark = replace(dark, skin=np.zeros_like(dark.skin))
    desc = load_dlib_resnet(models_root)
    pb = _problem(models_root, dark)
    scalp_mean = {}
    for w in (0.0, 5.0):  # lr 0.1 and weight 5: in 15 steps at 1e-2 a tiny G's W hardly moves its maps
        s = InversionSettings(iterations=15, lr=0.1, render_size=64, select_effects=False,
                              effects=Effects(specular=False, subsurface=False),
                              lambdas=(100.0, 0.5, 0.0, 0.0, 5e-2, 5e-4, 5e-4), hair_weight=w)
        res = invert([dark], G, sm, desc, sm.landmarks, np.arange(10), s)
        assert ("hair" in res.history[-1]) == (w > 0)
        with torch.no_grad():
            shp = sm(res.p_s, res.p_e)
            out = pb.renderer(shp.vertices, shp.normals, shp.tangents, res.maps, res.cameras, res.lights, res.effects)
            m = pb.hair_mask(out.fragments.triangle)
            scalp_mean[w] = float((out.image * m).sum() / (3 * m.sum()))
    target = float((pb.photo * m).sum() / (3 * m.sum()))
    assert target < scalp_mean[5.0] < scalp_mean[0.0] - 0.05, (scalp_mean, target)


def test_tuning_fits_the_hair_too(models_root):
    from fitme_cli.fitting.invert import InversionResult, TuningSettings, tune
    from fitme_cli.perception.dlib_resnet import load_dlib_resnet

    sm, G, dark = _dark_haired_photo(models_root)
    dark = replace(dark, skin=np.zeros_like(dark.skin))  # as above: only the hair term sees colour
    ws = G.w_avg.view(1, 1, -1).repeat(1, G.settings.num_ws, 1).detach()
    with torch.no_grad():
        maps0 = decode_maps(G.synthesis(ws, noise_mode="const"), G.settings)
    cam = Camera.looking_at_face(1, 64, 64, distance_mm=420, focal_35mm=50)
    lights = Lights(torch.full((1, 3), 0.5), torch.tensor([[[0.0, 0.0, 1.0]]]), torch.full((1, 1, 3), 0.5))
    inv = InversionResult(ws, *sm.zeros(1), cam, lights, maps0, [], Effects.none(), None, {})
    res = tune([dark], G, inv, sm, load_dlib_resnet(models_root), sm.landmarks, np.arange(10),
               torch.ones(16, 16, dtype=torch.bool), TuningSettings(iterations=12, lr=1e-2, effects=Effects.none()))
    assert res.history[-1]["hair"] < 0.7 * res.history[0]["hair"], (res.history[0]["hair"], res.history[-1]["hair"])
    with pytest.raises(ValueError, match=r"TuningSettings.hair_weight must be finite and >= 0, got nan"):
        TuningSettings(hair_weight=float("nan"))
