"""A real photo that ships in a package (scikit-image's astronaut), fitted at the fast preset's
budget (inversion, then tuning): the loss decreases, gradients stay finite, and the evaluation network
(FaceNet, not used by the fit) finds the render more like the photo than the starting render."""

import numpy as np
import pytest
import torch

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def fitted(models_root):
    from fitme_cli.fitting.invert import InversionSettings, invert, prepare_photo
    from fitme_cli.fitting.presets import preset
    from fitme_cli.fitting.skin_mask import photo_skin_mask
    from fitme_cli.io.images import sample_photo
    from fitme_cli.perception.detect import DetectSettings, detect
    from fitme_cli.perception.dlib_resnet import load_dlib_resnet
    from fitme_cli.reflectance.gan.store import load_generator
    from fitme_cli.shape.facemesh_topology import read_facemesh_topology
    from fitme_cli.shape.model import load_shape_model

    topo = read_facemesh_topology()
    img = sample_photo("astronaut")
    lm = detect(img.rgb, DetectSettings()).face.landmarks
    p = prepare_photo(img.rgb, lm.points[:, :2], lm.ibug68, img.focal_length_35mm, 128, 1.6,
                      lambda c, pts: photo_skin_mask(c, pts, topo.triangles, topo.contours))
    sm, desc = load_shape_model(models_root), load_dlib_resnet(models_root)
    jaw = np.unique(topo.contours["face_oval"])
    fast = preset("fast")
    base = dict(render_size=128, coarse_fraction=fast.coarse_fraction, select_effects=False)
    start = invert([p], load_generator(models_root), sm, desc, sm.landmarks, jaw, InversionSettings(iterations=1, lr=0.0, **base))
    G = load_generator(models_root)
    res = invert([p], G, sm, desc, sm.landmarks, jaw, InversionSettings(iterations=fast.iterations, **base))
    if fast.tune_iterations:  # as `fitme fit --preset fast`: the render after tuning is what the user gets
        from dataclasses import replace

        from fitme_cli.fitting.invert import TuningSettings, tune
        from fitme_cli.shape.regions import region_masks

        mapped = torch.from_numpy(region_masks(sm.region_uv.numpy().astype(np.uint8), G.settings.resolution)["mapped"])
        tr = tune([p], G, res, sm, desc, sm.landmarks, jaw, mapped, TuningSettings(iterations=fast.tune_iterations))
        res = replace(res, maps=tr.maps)
    return p, sm, desc, G, start, res


def _similarity(p, sm, res, models_root) -> float:
    from fitme_cli.perception.facenet import facenet_embedding_onnx
    from fitme_cli.render import Renderer
    from fitme_cli.render.shading import srgb_to_linear

    with torch.no_grad():
        shp = sm(res.p_s, res.p_e)
        bg = srgb_to_linear(torch.from_numpy(p.crop).permute(2, 0, 1)[None].float() / 255)
        out = Renderer.for_shape_model(sm)(shp.vertices, shp.normals, shp.tangents, res.maps, res.cameras, res.lights,
                                           res.effects, background=bg)
    img = (out.image[0].permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)
    return float(np.dot(facenet_embedding_onnx(p.crop, p.ibug68, models_root), facenet_embedding_onnx(img, p.ibug68, models_root)))


def test_astronaut_fit_lowers_the_loss_with_finite_gradients(fitted):
    p, sm, desc, G, _, res = fitted
    h = res.history
    assert all(np.isfinite(list(r.values())).all() for r in h)
    first, last = np.mean([r["total"] for r in h[:5]]), np.mean([r["total"] for r in h[-5:]])
    assert last < 0.8 * first, (first, last)
    # one more evaluation at the result: every parameter's gradient is finite
    from fitme_cli.fitting.invert import _Problem
    from fitme_cli.reflectance.gan.networks import decode_maps

    pb = _Problem([p], sm, desc, sm.landmarks, np.arange(10), 0.3, 128)
    ws = res.ws.clone().requires_grad_()
    p_s, p_e = res.p_s.clone().requires_grad_(), res.p_e.clone().requires_grad_()
    maps = decode_maps(G.synthesis(ws, noise_mode="const"), G.settings)
    terms = pb.evaluate(maps, p_s, p_e, res.cameras, res.lights, res.effects)
    sum(t.sum() for t in terms.values()).backward()
    for t in (ws, p_s, p_e):
        assert torch.isfinite(t.grad).all() and t.grad.abs().sum() > 0


def test_astronaut_render_looks_more_like_her_to_the_evaluation_network(fitted, models_root):
    p, sm, _, _, start, res = fitted
    before, after = _similarity(p, sm, start, models_root), _similarity(p, sm, res, models_root)
    # measured: 0.03 -> 0.37 with the 35 kimg BRDF-GAN (the fast preset: 30 iterations at 128^2, no coarse phase); ~0.48
    # at the default preset. The 92 kimg model (2026-11-24): 0.123 -> 0.353 at noise gain 0.35, 0.13 -> 0.22 at full
    # noise (0.18-0.25 over 24-60 iterations: why InversionSettings.noise_gain exists). For scale:
    # her own photo, transformed, scores 0.83-1.00 and other people's photos 0.12-0.33 (docs/perception.md). The 262.02
    # kimg G (2026-11-29), closer to its data, gains less at this budget: 0.072 -> 0.187 without tuning, 0.228 with 10
    # tuning iterations, 0.271 with the fast preset's 20 (since 2026-11-30); a fit that does nothing stays at 0.07
    assert after > before + 0.12 and after > 0.2, (before, after)
