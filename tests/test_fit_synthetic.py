"""Fit accuracy against ground truth: the metrics (fitting/metrics.py) on known values, the synthetic
subject (fitting/synthetic.py), and recovery tests that fit synthetic photos with ``invert`` as
``fitme fit`` does (detect -> prepare_photo -> invert) and score the result against the truth."""

import math
import time
from dataclasses import replace

import numpy as np
import pytest
import torch

from fitme_cli.fitting.metrics import (albedo_error, face_uv_mask, face_vertex_mask, fit_landmarks_px, landmark_error_px,
                                       linear_rgb_to_lab, normal_angular_error_deg, point_to_mesh_distance,
                                       rigid_alignment, shape_error_mm)
from fitme_cli.fitting.synthetic import SyntheticSettings, make_subject, off_tone_fraction, view_yaws

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def models(one_thread):
    """(generator, shape model, dlib descriptor, renderer, FaceMesh topology), loaded once."""
    return _load_models()


def _load_models():
    from fitme_cli.perception.dlib_resnet import load_dlib_resnet
    from fitme_cli.perception.registry import ensure_models
    from fitme_cli.reflectance.gan.store import load_generator
    from fitme_cli.render import Renderer
    from fitme_cli.shape.facemesh_topology import read_facemesh_topology
    from fitme_cli.shape.model import load_shape_model

    root = ensure_models(["blazeface_short", "blazeface_full", "facemesh", "dlib_resnet", "shape_model"])
    sm = load_shape_model(root)
    return load_generator(root), sm, load_dlib_resnet(root), Renderer.for_shape_model(sm), read_facemesh_topology()


def _rot(axis: str, deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return {"x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]), "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
            "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])}[axis]


# --- metrics on known values -------------------------------------------------------------------------


def test_landmark_error_known_values_and_bad_shapes():
    a = np.random.default_rng(0).uniform(0, 100, (2, 68, 2))
    assert landmark_error_px(a, a) == 0.0
    assert landmark_error_px(a + np.array([3.0, 4.0]), a) == pytest.approx(5.0)
    assert landmark_error_px(torch.from_numpy(a[0]), a[0] - np.array([0.0, 2.0])) == pytest.approx(2.0)
    with pytest.raises(ValueError, match=r"expected target of shape \(2, 68, 2\).*got \(68, 2\)"):
        landmark_error_px(a, a[0])
    with pytest.raises(ValueError, match="expected pred of shape"):
        landmark_error_px(np.zeros((68, 3)), np.zeros((68, 3)))


def test_shape_error_is_zero_after_aligning_a_moved_mesh(models):
    _, sm, _, _, _ = models
    v = sm.mean.numpy().astype(np.float64)
    tri = sm.triangles.numpy()
    face = face_vertex_mask(sm)
    assert shape_error_mm(v, v, tri, face).mean_mm < 1e-9
    r = _rot("y", 20) @ _rot("x", -10) @ _rot("z", 5)
    moved = v @ r.T + np.array([12.0, -30.0, 250.0])
    err = shape_error_mm(moved, v, tri, face)
    assert err.mean_mm < 1e-6 and err.n_points == int(face.sum())
    np.testing.assert_allclose(err.rotation, r.T, atol=1e-9)  # the inverse motion
    assert shape_error_mm(moved, v, tri, face, alignment="none").mean_mm > 50
    # a scaled copy: the similarity alignment removes the scale, the rigid one cannot
    assert shape_error_mm(1.05 * moved, v, tri, face, alignment="similarity").mean_mm < 1e-6
    assert shape_error_mm(1.05 * moved, v, tri, face).mean_mm > 0.5
    rr, t, s = rigid_alignment(v[face], 1.05 * moved[face], similarity=True)
    assert s == pytest.approx(1.05) and np.allclose(rr, r) and np.allclose(t, 1.05 * np.array([12.0, -30.0, 250.0]))


def test_shape_error_of_an_offset_along_the_normals_is_that_offset(models):
    _, sm, _, _, _ = models
    shp = sm(*sm.zeros(1))
    v, n = shp.vertices[0].double().numpy(), shp.normals[0].double().numpy()
    tri = sm.triangles.numpy()
    face = face_vertex_mask(sm)
    err = shape_error_mm(v + 0.8 * n, v, tri, face, alignment="none")
    # a vertex moved 0.8 mm along its normal is 0.8 mm from its tangent plane; the piecewise-flat surface
    # bends toward it in concave places (the eye sockets, beside the nose), so a little less there
    assert err.median_mm == pytest.approx(0.8, abs=0.01) and 0.75 < err.mean_mm <= 0.8 + 1e-9


def test_point_to_mesh_distance_matches_brute_force():
    rng = np.random.default_rng(1)
    # a bumpy 20 x 20 grid: 722 triangles, points on both sides of it
    g = np.stack(np.meshgrid(np.arange(20.0), np.arange(20.0), indexing="ij"), -1).reshape(-1, 2)
    v = np.concatenate([g, rng.uniform(-0.5, 0.5, (len(g), 1))], 1)
    idx = np.arange(400).reshape(20, 20)
    tri = np.concatenate([np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:]], -1).reshape(-1, 3),
                          np.stack([idx[:-1, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 3)])
    q = np.concatenate([rng.uniform(0, 19, (300, 2)), rng.uniform(-3, 3, (300, 1))], 1)
    got = point_to_mesh_distance(q, v, tri)
    # brute force: the distance to a densely sampled surface (barycentric grid), an upper bound within
    # half the sampling step of the exact value
    w = np.array([(i, j, 60 - i - j) for i in range(61) for j in range(61 - i)]) / 60.0
    samples = np.einsum("sk,fkc->fsc", w, v[tri]).reshape(-1, 3)
    from scipy.spatial import cKDTree

    dense = cKDTree(samples).query(q)[0]
    assert np.all(got <= dense + 1e-9) and np.all(dense - got < 0.02)


def test_delta_e_of_known_colours():
    np.testing.assert_allclose(linear_rgb_to_lab([1.0, 1.0, 1.0]), [100.0, 0.0, 0.0], atol=0.01)
    np.testing.assert_allclose(linear_rgb_to_lab([1.0, 0.0, 0.0]), [53.24, 80.09, 67.20], atol=0.02)  # sRGB red
    np.testing.assert_allclose(linear_rgb_to_lab([0.18, 0.18, 0.18]), [49.50, 0.0, 0.0], atol=0.01)  # mid grey
    grey, white = torch.full((1, 3, 8, 8), 0.18), torch.ones(1, 3, 8, 8)
    e = albedo_error(grey, white, np.ones((8, 8), bool))
    assert e.l1_linear == pytest.approx(0.82) and e.delta_e == pytest.approx(50.50, abs=0.01)
    # a pure intensity error: the per-channel gain explains it away
    np.testing.assert_allclose(e.gain, 1 / 0.18)
    assert e.l1_linear_gain < 1e-9 and e.delta_e_gain < 1e-6
    rng = np.random.default_rng(2)
    a = rng.uniform(0.05, 0.6, (3, 16, 16))
    mask = np.zeros((16, 16), bool)
    mask[4:12, 4:12] = True
    b = a.copy()
    b[:, ~mask] = 1.0  # outside the mask: ignored
    assert albedo_error(a, b, mask).l1_linear == 0.0 and albedo_error(a, b).l1_linear > 0.1
    with pytest.raises(ValueError, match=r"mask: expected shape \(16, 16\), got \(8, 8\)"):
        albedo_error(a, b, mask[:8, :8])
    with pytest.raises(ValueError, match="pred_albedo: expected shape"):
        albedo_error(a[:1], b)
    with pytest.raises(ValueError, match="selects no texels"):
        albedo_error(a, b, np.zeros((16, 16), bool))


def test_normal_angular_error_of_rotated_normals():
    rng = np.random.default_rng(3)
    n = rng.normal(size=(500, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    assert normal_angular_error_deg(n, n) < 1e-6
    # a rotation by theta about an axis turns a vector perpendicular to the axis by exactly theta
    yz = n.copy()
    yz[:, 0] = 0
    assert normal_angular_error_deg(yz @ _rot("x", 10).T, yz) == pytest.approx(10.0, abs=1e-6)
    xy = n.copy()
    xy[:, 2] = 0
    assert normal_angular_error_deg(3 * xy @ _rot("z", 25).T, xy) == pytest.approx(25.0, abs=1e-6)  # unnormalised input
    # and a vector at angle a to the axis by 2 asin(sin a sin(theta / 2))
    a = np.arccos(np.abs(n[:, 0]))
    expected = np.degrees(2 * np.arcsin(np.sin(a) * np.sin(np.radians(10) / 2))).mean()
    assert normal_angular_error_deg(n @ _rot("x", 10).T, n) == pytest.approx(expected, abs=1e-6)
    flat = np.zeros((1, 3, 8, 8))
    flat[:, 2] = 1.0
    tilted = np.einsum("ij,bjhw->bihw", _rot("y", 7), flat)
    assert normal_angular_error_deg(torch.from_numpy(tilted), flat, np.ones((8, 8), bool)) == pytest.approx(7.0, abs=1e-6)
    with pytest.raises(ValueError, match=r"expected pred_normals of shape \(500, 3\).*got \(499, 3\)"):
        normal_angular_error_deg(n[1:], n)
    with pytest.raises(ValueError, match=r"mask: expected shape \(500,\)"):
        normal_angular_error_deg(n, n, np.ones(10, bool))


def test_shape_error_rejects_bad_inputs(models):
    _, sm, _, _, _ = models
    v, tri = sm.mean.numpy(), sm.triangles.numpy()
    with pytest.raises(ValueError, match=r"expected pred_vertices of shape \(12391, 3\).*got \(100, 3\)"):
        shape_error_mm(v[:100], v, tri)
    with pytest.raises(ValueError, match=r"mask: expected shape \(12391,\)"):
        shape_error_mm(v, v, tri, np.ones(5, bool))
    with pytest.raises(ValueError, match="alignment must be"):
        shape_error_mm(v, v, tri, alignment="affine")
    with pytest.raises(ValueError, match="face indices must be in"):
        shape_error_mm(v[:10], v[:10], tri)


def test_face_masks_leave_out_the_back_of_the_head_and_the_neck(models):
    from fitme_cli.shape.regions import REGIONS

    _, sm, _, _, _ = models
    face = face_vertex_mask(sm)
    lab = sm.regions.numpy()
    assert face.shape == (sm.mean.shape[0],) and 0.2 < face.mean() < 0.8
    assert not face[np.isin(lab, [REGIONS.index("scalp"), REGIONS.index("neck")])].any()
    assert face[sm.landmarks.numpy()].mean() > 0.9  # the landmarks are on the face
    uv = face_uv_mask(sm, 256)
    assert uv.shape == (256, 256) and 0.05 < uv.mean() < 0.8


# --- the synthetic subject ---------------------------------------------------------------------------


def test_subject_is_deterministic_and_well_formed(models):
    G, sm, _, r, _ = models
    s = SyntheticSettings(size=192, n_views=3, seed=7, background="noise")
    a, b = make_subject(G, sm, r, s), make_subject(G, sm, r, s)
    assert np.array_equal(a.photos, b.photos) and torch.equal(a.p_s, b.p_s) and torch.equal(a.ws, b.ws)
    assert not np.array_equal(make_subject(G, sm, r, replace(s, seed=8)).photos, a.photos)
    k, e = sm.n_identity, sm.n_expressions
    assert a.photos.shape == a.clean.shape == (3, 192, 192, 3) and a.photos.dtype == np.uint8
    assert a.masks.shape == (3, 192, 192) and all(0.15 < m.mean() < 0.8 for m in a.masks)
    assert a.p_s.shape == (1, k) and a.p_e.shape == (3, e) and float(a.p_e.min()) >= 0 and float(a.p_e.max()) <= 1
    assert a.ws.shape == (1, G.settings.num_ws, G.settings.w_dim)
    assert a.maps.albedo.shape == (1, 3, 256, 256) and 0 <= float(a.maps.albedo.min()) and float(a.maps.albedo.max()) <= 1
    assert a.cameras.batch == 3 and a.lights.ambient.shape == (3, 3) and a.lights.sh.shape == (3, 9, 3)
    assert a.vertices.shape == (3, sm.mean.shape[0], 3) and a.neutral.shape == (sm.mean.shape[0], 3)
    assert a.landmarks.shape == (3, 468, 2) and a.ibug68.shape == (3, 68, 2)
    assert ((a.landmarks > 0) & (a.landmarks < 192)).all()
    np.testing.assert_array_equal(a.yaws_deg, [0, 30, -30])
    # the landmarks are where the mesh is drawn (but for some on the rims of the eye and mouth holes: 94-96 %
    # measured); the degraded photo stays close to the clean render (mean 3.2-4.0 levels measured)
    for i in range(3):
        ij = np.floor(a.landmarks[i]).astype(int)
        assert a.masks[i][ij[:, 1], ij[:, 0]].mean() > 0.9
        assert np.abs(a.photos[i].astype(float) - a.clean[i]).mean() < 6
    # the first view is frontal (up to the jitter): the nose tip (landmark 4) near the landmarks' centre
    assert abs(a.landmarks[0, 4, 0] - a.landmarks[0, :, 0].mean()) < 8
    # the second view is turned toward the image's right: the nose tip moves right of the centre
    assert a.landmarks[1, 4, 0] - a.landmarks[1, :, 0].mean() > 10


def test_view_yaws_and_settings_checks(models):
    G, sm, _, r, _ = models
    np.testing.assert_array_equal(view_yaws(1, 30), [0])
    np.testing.assert_array_equal(view_yaws(2, 30), [0, 30])
    np.testing.assert_array_equal(view_yaws(5, 30), [0, 15, -15, 30, -30])
    for bad in ({"n_views": 0}, {"size": 10}, {"background": "checker"}, {"jpeg_quality": 0}, {"truncation": 1.5},
                {"ambient_range": (0.5, 0.2)}, {"noise_sigma": -1.0}, {"max_off_tone": 0.0}, {"max_redraws": -1}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            SyntheticSettings(**bad)
    with pytest.raises(ValueError, match="SyntheticSettings"):
        make_subject(G, sm, r, settings={"seed": 1})
    with pytest.raises(ValueError, match="ShapeModel"):
        make_subject(G, object(), r)


def test_off_tone_fraction_known_values(models):
    from fitme_cli.shape.regions import region_masks

    sm = models[1]
    res = 64
    skin = region_masks(sm.region_uv.numpy().astype(np.uint8), res)["skin"]
    albedo = torch.tensor([0.40, 0.25, 0.18]).view(1, 3, 1, 1).repeat(1, 1, res, res)
    assert off_tone_fraction(albedo, sm.region_uv) == 0.0
    # a dark grey "beard" on every other row of the skin region: exactly those texels are off-tone
    beard = skin & (np.arange(res)[:, None] % 2 == 0)
    albedo[0, :, torch.from_numpy(beard)] = 0.03
    assert off_tone_fraction(albedo, sm.region_uv) == pytest.approx(beard.sum() / skin.sum())
    with pytest.raises(ValueError, match=r"\(1, 3, R, R\), got \(3, 64, 64\)"):
        off_tone_fraction(albedo[0], sm.region_uv)


def test_subject_redraws_only_an_off_tone_z(models):
    G, sm, _, r, _ = models
    s = SyntheticSettings(size=64, seed=0, max_off_tone=1.0)
    first = make_subject(G, sm, r, s)
    assert first.z_redraws == 0
    strict = make_subject(G, sm, r, replace(s, max_off_tone=1e-9, max_redraws=3))
    default = make_subject(G, sm, r, SyntheticSettings(size=64, seed=0))
    for sub in (first, strict, default):
        assert sub.off_tone == pytest.approx(off_tone_fraction(sub.maps.albedo, sm.region_uv))
        # a redraw changes the reflectance only: identity, expressions, cameras and lights stay the seed's
        assert torch.equal(sub.p_s, first.p_s) and torch.equal(sub.p_e, first.p_e)
        assert torch.equal(sub.cameras.rotation, first.cameras.rotation) and torch.equal(sub.lights.colour, first.lights.colour)
        assert torch.equal(sub.z, first.z) == (sub.z_redraws == 0)
    assert 0 <= strict.z_redraws <= 3 and strict.off_tone <= first.off_tone
    assert default.off_tone <= default.settings.max_off_tone or default.z_redraws == default.settings.max_redraws


def test_subject_with_given_maps_keeps_them_and_the_seeds_scene(models):
    from fitme_cli.reflectance.maps import ReflectanceMaps

    G, sm, _, r, _ = models
    s = SyntheticSettings(size=64, seed=0, max_off_tone=1.0)
    drawn = make_subject(G, sm, r, s)
    # a flat skin colour, a brighter specular and normals tilted toward +x: nothing G draws
    albedo = torch.tensor([0.45, 0.3, 0.2]).view(1, 3, 1, 1).repeat(1, 1, 256, 256)
    normals = torch.nn.functional.normalize(torch.tensor([0.2, 0.0, 1.0]), dim=0).view(1, 3, 1, 1).repeat(1, 1, 256, 256)
    given = ReflectanceMaps(albedo, torch.full((1, 1, 256, 256), 0.3), normals)
    sub = make_subject(G, sm, r, s, maps=given)
    assert sub.z is None and sub.ws is None and sub.z_redraws == 0
    for k in ("albedo", "specular", "normals"):
        assert torch.equal(getattr(sub.maps, k), getattr(given, k))
    assert sub.off_tone == pytest.approx(off_tone_fraction(albedo, sm.region_uv))
    # the scene is the seed's: only the reflectance differs from the G-drawn subject
    assert torch.equal(sub.p_s, drawn.p_s) and torch.equal(sub.p_e, drawn.p_e)
    assert torch.equal(sub.cameras.rotation, drawn.cameras.rotation) and torch.equal(sub.lights.colour, drawn.lights.colour)
    assert np.array_equal(sub.landmarks, drawn.landmarks) and not np.array_equal(sub.clean, drawn.clean)
    with pytest.raises(ValueError, match=r"maps must be \(1, C, 256, 256\).*'albedo': \(1, 3, 128, 128\)"):
        make_subject(G, sm, r, s, maps=ReflectanceMaps(albedo[..., :128, :128], given.specular, normals))


# --- fit recovery ------------------------------------------------------------------------------------


def _fit(models, subject, iterations: int, size: int = 128, members: int = 1):
    """Fit the subject's photos as ``fitme fit --preset fast`` does: detect, prepare_photo, invert (no
    effect selection). Returns (start, fits, seconds): the start is what ``invert`` starts from (mean
    shape, no expression, W average, PnP cameras); ``fits`` one report per member: member 0 from w_avg,
    member m > 0 from w_avg nudged by 1e-5 (seed m), the spread another CPU's rounding gives a fit."""
    from fitme_cli.fitting.invert import InversionSettings, invert, member_settings, prepare_photo
    from fitme_cli.fitting.metrics import evaluate_fit
    from fitme_cli.fitting.pose import initial_camera
    from fitme_cli.fitting.presets import preset
    from fitme_cli.fitting.skin_mask import photo_skin_mask
    from fitme_cli.perception.detect import DetectSettings, detect
    from fitme_cli.reflectance.gan.networks import decode_maps
    from fitme_cli.render import Camera

    G, sm, desc, _, topo = models
    prepared = []
    for photo in subject.photos:
        lm = detect(photo, DetectSettings(identity=False)).face.landmarks
        prepared.append(prepare_photo(photo, lm.points[:, :2], lm.ibug68, subject.settings.focal_35mm, size, 1.6,
                                      lambda c, pts: photo_skin_mask(c, pts, topo.triangles, topo.contours)))
    to_photo = [p.to_photo for p in prepared]
    mean_lm = sm.mean[sm.landmarks].numpy()
    cams = [initial_camera(p.landmarks, mean_lm, size, size, p.focal_px, principal=p.principal) for p in prepared]
    cam0 = Camera(*(torch.cat([getattr(c, k) for c in cams]) for k in ("focal", "principal", "rotation", "translation")),
                  size, size)
    with torch.no_grad():
        maps0 = decode_maps(G.synthesis(G.w_avg.view(1, 1, -1).expand(1, G.settings.num_ws, -1), noise_mode="const",
                                        noise_gain=InversionSettings().noise_gain), G.settings)
    p_s0, p_e0 = sm.zeros(subject.n_views)
    start = evaluate_fit(subject, sm, p_s0[:1], p_e0, cam0, maps0, to_photo)
    pre = preset("fast")
    s = InversionSettings(iterations=iterations, render_size=size, coarse_fraction=pre.coarse_fraction,
                          coarse_resolution=pre.coarse_resolution, select_effects=False)
    t = time.perf_counter()
    fits = []
    for m in range(members):
        res = invert(prepared, G, sm, desc, sm.landmarks, np.unique(topo.contours["face_oval"]), member_settings(s, m, 1e-5))
        fits.append(evaluate_fit(subject, sm, res.p_s, res.p_e, res.cameras, res.maps, to_photo))
    seconds = (time.perf_counter() - t) / members
    return start, fits, seconds


# A 60-iteration fit is chaotic: on the same code, an AVX2 and an AVX-512 machine gave the one-view
# fit's landmarks 5.91 and 3.38 px, and five starts nudged by 1e-5 on one machine 4.1-5.9 px. So the
# recovery tests judge the median of MEMBERS fits (``_fit``), each metric on its own.
MEMBERS = 3


class _Median:
    """Per-attribute median of several FitReports: ``_Median(fits).albedo.delta_e``."""

    def __init__(self, items):
        self._items = list(items)

    def __getattr__(self, name):
        vals = [getattr(x, name) for x in self._items]
        if isinstance(vals[0], (int, float, np.floating)):
            return float(np.median(vals))
        return _Median(vals)


def test_median_report_takes_each_attribute_on_its_own():
    from types import SimpleNamespace as NS

    fits = [NS(landmark_px=5.0, albedo=NS(delta_e=1.0)), NS(landmark_px=3.0, albedo=NS(delta_e=9.0)),
            NS(landmark_px=4.0, albedo=NS(delta_e=2.0))]
    assert _Median(fits).landmark_px == 4.0 and _Median(fits).albedo.delta_e == 2.0


@pytest.fixture(scope="module")
def one_view(models):
    G, sm, _, r, _ = models
    # seed 3: under the 125 kimg wide G, seeds 0 and 2 first draw bearded z's, and the photo skin mask drops
    # beard pixels by design (skin_mask.py), so no loss sees them: the fit's albedo has no beard and Delta E
    # after the gain stays at its start (7.5 -> 7.4, checked on pictures); make_subject now redraws such a z
    # (max_off_tone), and seed 3 passes on its first z, so the figures below stand; seed 1 gives no face
    subject = make_subject(G, sm, r, SyntheticSettings(n_views=1, seed=3))
    start, fits, seconds = _fit(models, subject, 60, members=MEMBERS)
    return start, _Median(fits), seconds


@pytest.fixture(scope="module")
def three_views(models):
    G, sm, _, r, _ = models
    subject = make_subject(G, sm, r, SyntheticSettings(n_views=3, seed=1))  # seed 0's -30 degree view: no face found
    start, fits, seconds = _fit(models, subject, 60, members=MEMBERS)
    return start, _Median(fits), seconds


def test_one_view_fit_recovers_landmarks_and_albedo(one_view):
    # measured (seed 0, 60 iterations at 128^2, invert at ce308bd, 1 thread, ~12 s): start -> fit
    #   iBUG-68 landmarks 7.25 -> 3.78 px (512^2 photo; the detector itself is 7.6 px off on this render)
    #   albedo: L1 0.117 -> 0.008, Delta E 21.4 -> 1.30 (after the per-channel gain: 5.98 -> 1.09)
    #   identity shape (p_s, face region, rigid) 1.397 -> 1.392 mm; posed shape (p_s + p_e) 1.42 -> 1.51 mm
    # seeds 0-5: landmarks 3.3-5.5 px (from 5.7-9.2), Delta E 1.3-7.2 (from 12.9-39.8). Those shape figures
    # predate p_s in prior standard deviations; since: 1.397 -> 1.186 mm (the next test)
    # 92 kimg model, noise gain 0.35 (2026-11-24, 1 thread): landmarks 6.03 -> 3.38 px; Delta E 6.56 -> 2.92 (its
    # W average is already close to this subject), after the gain 5.73 -> 2.88; L1 0.027 -> 0.014; identity
    # shape 1.397 -> 1.237 mm, posed 1.416 -> 1.348 mm
    # 2026-11-25, an AVX2 machine, 1 thread, medians of 5 members (0 / nudged 1-4): landmarks 8.47 -> 4.95 px
    # (members 4.1-5.9; the start differs by machine because the detector's landmarks do: 6.03 on the AVX-512
    # one), Delta E 6.56 -> 3.01 (2.92-3.23), after the gain 5.73 -> 2.91 (2.88-2.98), L1 0.027 -> 0.014,
    # identity shape 1.473 -> 1.28 mm, posed 1.47 -> 1.40 mm. Landmarks with the landmark term off: 6.84 px
    # (the AVX-512 machine), which the absolute bound rejects
    # 125 kimg wide G (2026-11-26, AVX-512, 1 thread, training running beside it), seed 3, 5 members: landmarks
    # 9.24 -> 3.47 px (3.15-3.72), Delta E 32.0 -> 2.60 (2.54-2.67), after the gain 5.64 -> 2.16 (2.14-2.18),
    # L1 0.304 -> 0.030, identity shape 1.720 -> 1.47-1.55 mm, posed 1.746 -> 1.48-1.59 mm, normals 3.35 -> 3.46
    # 143.53 kimg G (2026-11-26, 1 thread, 3 members): landmarks 8.97 -> 2.98-3.45 px, Delta E 31.4 -> 2.62-3.07,
    # after the gain 5.45 -> 1.91-2.02, identity shape 1.720 -> 1.49-1.55 mm, normals 3.40 -> 3.49
    # 151.01 kimg G (2026-11-26, 1 thread, medians of 3 members): landmarks 8.90 -> 3.55 px, Delta E 30.5 -> 3.24,
    # after the gain 5.49 -> 1.69, L1 0.290 -> 0.025, identity shape 1.720 -> 1.49 mm, posed 1.746 -> 1.46, normals 3.37 -> 3.43
    start, fit, seconds = one_view
    assert fit.landmark_px < 6.3 and fit.landmark_px < 0.85 * start.landmark_px
    # with the coarse phase on 128^2 maps (was 64^2): landmarks 3.14 px, Delta E 5.07 (1.71 after the gain:
    # the albedo came out 13-26 % dark, the light/albedo scale ambiguity), L1 0.039
    # a second VM (2026-11-23, same code): Delta E 10.5 (2.33 after the gain), L1 0.089: 60 iterations are
    # chaotic across CPUs (docs/benchmarks.md, "Regression runs"); the bounds below hold on both
    assert fit.albedo.delta_e < 12.0 and fit.albedo.delta_e < 0.6 * start.albedo.delta_e
    assert fit.albedo.l1_linear < 0.1 and fit.albedo.l1_linear < 0.8 * start.albedo.l1_linear
    assert fit.albedo.delta_e_gain < 3.4 and fit.albedo.delta_e_gain < 0.6 * start.albedo.delta_e_gain
    # the shape only within bounds (see test_one_view_fit_improves_the_identity_shape)
    assert fit.shape.mean_mm < 1.6 and fit.shape.mean_mm <= start.shape.mean_mm + 0.1
    assert fit.shape_posed_mean_mm < 1.8 and fit.shape_posed_mean_mm <= start.shape_posed_mean_mm + 0.25
    # the 35 kimg model's detail normals were nearly flat (0.08 -> 0.07 degrees). The 92 kimg model's carry
    # grain from the generator's fixed noise, which the fit turns down (InversionSettings.noise_gain 0.35;
    # the subject has all of it): 3.77 -> 3.52 degrees. Nothing in a photo pins that grain, so the bound
    # is only that the fit does not make the normals worse than its start
    assert fit.normals_deg < 5.0 and fit.normals_deg <= start.normals_deg + 0.25


def test_one_view_fit_improves_the_identity_shape(one_view):
    # measured with p_s optimised in prior standard deviations (seed 0, 60 iterations at 128^2, 1 thread):
    # identity shape 1.397 -> 1.186 mm, posed 1.416 -> 1.227 mm. In raw units p_s did not move (1.397 -> 1.392).
    # 2026-11-24, one VM, four builds equal to within float rounding (the sRGB curve in float32 or float64,
    # its backward from the output or from a power, or scaled by 1 + 3e-7): 1.397 -> 1.279 / 1.343 / 1.321 /
    # 1.290 mm. The same perturbations moved seeds 0-9's landmark errors by up to 2.5x (one seed 3.7 ->
    # 9.1 px): a 60-iteration fit is chaotic, so the bound is what every one of them met, not the luckiest.
    start, fit, _ = one_view
    assert fit.shape.mean_mm < 0.97 * start.shape.mean_mm


def test_three_view_fit_recovers_landmarks_and_albedo(three_views):
    # measured (seed 1, views at 0 / +30 / -30 degrees, 60 iterations at 128^2, invert at ce308bd, 1 thread,
    # ~16 s): landmarks 7.17 -> 3.83 px; albedo L1 0.280 -> 0.080, Delta E 35.0 -> 8.0 (after the
    # per-channel gain 12.3 -> 2.1: the fitted albedo is too dark and the lights too bright, the ambiguity
    # 60 iterations leave); posed shape 0.94 -> 0.85 mm, identity shape 0.948 -> 0.946 mm.
    # Seeds 2-4: landmarks 4.8-6.8 px (from 9.5-12.2); where W average is already close to the subject's
    # albedo (Delta E 8.8 and 14.0 at the start) the fit makes it worse (19.8, 18.8); seed 0: no face found
    # 2026-11-25, an AVX2 machine, 1 thread, 5 members: landmarks 9.62 -> 4.64 px (4.33-5.01; the AVX-512
    # machine's start: 7.67), Delta E 28.6 -> 3.97 (3.86-4.19), after the gain 6.45 -> 2.68, identity shape
    # 0.881 -> 1.00-1.02 mm, posed 0.857 -> 0.99-1.02 mm (the start is already within 1 mm: the bounds only
    # catch a blow-up). With the landmark term off three views still give 4.0-5.0 px (the AVX-512 machine):
    # the landmark bound here checks the fit's gain, not that term (the one-view test does)
    start, fit, seconds = three_views
    assert fit.landmark_px < 5.5 and fit.landmark_px < 0.65 * start.landmark_px
    assert fit.albedo.delta_e < 11.0 and fit.albedo.delta_e < 0.4 * start.albedo.delta_e
    # 92 kimg model, noise gain 0.35 (2026-11-24, 1 thread, training paused): landmarks 7.67 -> 4.35 px; Delta E
    # 28.6 -> 4.23, after the gain 6.45 -> 2.69 (its W average starts closer than the 35 kimg model's 12.4: the
    # ratio bound was 0.3 of that start); identity shape 0.948 -> 0.867 mm, posed 0.938 -> 0.902 mm
    # 125 kimg wide G (2026-11-26, AVX-512, 5 members): landmarks 6.32 -> 3.05 px (2.88-3.69), Delta E
    # 30.0 -> 3.57 (3.34-3.73), after the gain 5.76 -> 2.86 (2.76-2.90): a closer start than 92 kimg's, so the
    # gain bounds were loosened from < 3.0 and 0.5x (the median sat 0.02 under 0.5x); identity shape 0.948 ->
    # 0.83-0.87 mm, posed 0.938 -> 0.78-0.85 mm
    # 143.53 kimg G (2026-11-26, 1 thread, 3 members): landmarks 7.66 -> 3.55-3.81 px, Delta E 19.4 -> 2.29-2.38,
    # after the gain 2.92 -> 1.95-2.00 (the best fit yet, but from a W average already close to the subject:
    # 0.68x, so the ratio bound went from 0.6x to 0.8x); identity shape 0.948 -> 0.93-0.95 mm, posed 0.938 -> 0.89-0.93
    # 151.01 kimg G (2026-11-26, 1 thread, medians of 3 members): landmarks 5.92 -> 3.17 px, Delta E 18.6 -> 1.70,
    # after the gain 2.30 -> 1.46 (0.63x), identity shape 0.948 -> 0.871 mm, posed 0.938 -> 0.813
    assert fit.albedo.delta_e_gain < 3.4 and fit.albedo.delta_e_gain < 0.8 * start.albedo.delta_e_gain
    # the second VM: identity shape 0.881 -> 0.999 mm (the start is already within 1 mm here)
    assert fit.shape.mean_mm < 1.2 and fit.shape.mean_mm <= start.shape.mean_mm + 0.25
    assert fit.shape_posed_mean_mm < 1.2 and fit.shape_posed_mean_mm <= start.shape_posed_mean_mm + 0.25


def test_fit_landmarks_px_maps_crop_pixels_to_the_photo(models):
    """The landmark metric's projection: the true scene through an identity crop reproduces the
    subject's own landmarks; a crop at half scale, shifted, maps back to the same photo pixels."""
    G, sm, _, r, _ = models
    subj = make_subject(G, sm, r, SyntheticSettings(size=128, n_views=2, seed=3))
    eye = np.tile(np.eye(2, 3), (2, 1, 1))
    lm = fit_landmarks_px(sm, subj.p_s, subj.p_e, subj.cameras, eye)
    np.testing.assert_allclose(lm, subj.ibug68, atol=1e-3)
    half = subj.cameras.with_size(64, 64)
    crop_to_photo = np.tile(np.array([[2.0, 0, 0], [0, 2.0, 0]]), (2, 1, 1))
    np.testing.assert_allclose(fit_landmarks_px(sm, subj.p_s, subj.p_e, half, crop_to_photo), subj.ibug68, atol=1e-3)
    with pytest.raises(ValueError, match=r"to_photo of shape \(2, 2, 3\)"):
        fit_landmarks_px(sm, subj.p_s, subj.p_e, subj.cameras, eye[:1])
