"""The shape model: mean, identity basis and prior, symmetry, correspondences, expressions, mesh."""

import collections
import json

import numpy as np
import pytest
import torch

from fitme_cli.shape.model import ShapeModel, load_shape_model, vertex_normals, vertex_tangents
from fitme_cli.shape.regions import REGIONS


@pytest.fixture(scope="module")
def root(models_root):
    from fitme_cli.perception.registry import ensure_models

    return ensure_models(["dlib_resnet", "shape_model"], models_root)


@pytest.fixture(scope="module")
def model(root) -> ShapeModel:
    return load_shape_model(root).double()


@pytest.fixture(scope="module")
def card(root):
    return json.loads((root / "shape_model.json").read_text())


def test_zero_coefficients_reproduce_the_mean(model):
    ps, pe = model.zeros(2)
    out = model(ps, pe)
    assert torch.equal(out.vertices[0], model.mean) and out.vertices.shape == (2, model.mean.shape[0], 3)


def test_resolution_and_proportions(model, card):
    assert model.mean.shape[0] >= 10_000 and model.n_identity >= 80
    m = card["metrics"]
    assert m["ipd_mm"] == pytest.approx(63.0, abs=0.1)
    assert 140 <= m["head_breadth_mm"] <= 165 and 190 <= m["head_height_menton_to_vertex_mm"] <= 240
    assert 50 <= m["neck_below_chin_mm"] <= 120
    # face vertices (the first 468 carry the landmarks) are denser than the rest of the head
    v = model.mean.numpy()
    t = model.triangles.numpy()
    edge = np.linalg.norm(v[t[:, 0]] - v[t[:, 1]], axis=1)
    on_face = (t < 468).any(1)
    assert np.median(edge[on_face]) < np.median(edge[~on_face])


def test_basis_orthonormal_and_eigenvalues_ordered(model):
    u = model.identity_basis.reshape(-1, model.n_identity)
    assert torch.allclose(u.T @ u, torch.eye(model.n_identity, dtype=u.dtype), atol=1e-4)
    lam = model.identity_eigenvalues
    assert (lam > 0).all() and (lam[:-1] >= lam[1:]).all()


def test_mean_is_mirror_symmetric(model):
    v, m = model.mean, model.mirror
    assert torch.allclose(v[m] * torch.tensor([-1.0, 1.0, 1.0], dtype=v.dtype), v, atol=1e-3)
    assert torch.equal(m[m], torch.arange(len(m)))


def test_prior_is_mirror_symmetric(model):
    """A mirrored sample is (as good as) in the model and exactly as likely as the sample."""
    g = torch.Generator().manual_seed(0)
    ps = model.sample_identity(8, g).double()
    u = model.identity_basis.reshape(-1, model.n_identity)
    d = torch.einsum("vck,bk->bvc", model.identity_basis, ps)
    mirrored = d[:, model.mirror] * torch.tensor([-1.0, 1.0, 1.0], dtype=d.dtype)
    p_m = mirrored.reshape(8, -1) @ u
    residual = (mirrored.reshape(8, -1) - p_m @ u.T).norm(dim=1) / d.reshape(8, -1).norm(dim=1)
    assert residual.max() < 0.05
    ratio = model.identity_prior(p_m) / model.identity_prior(ps)
    assert torch.allclose(ratio, torch.ones_like(ratio), atol=0.1)


def test_samples_are_plausible_without_spikes(model):
    """At 3 sigma along the leading components, no vertex jumps away from its neighbours."""
    t = model.triangles
    for k in range(5):
        for sign in (-3.0, 3.0):
            ps = torch.zeros(1, model.n_identity, dtype=torch.float64)
            ps[0, k] = sign * model.identity_eigenvalues[k].sqrt()
            v = model.vertices(ps, torch.zeros(1, model.n_expressions, dtype=torch.float64))[0]
            e0 = (model.mean[t[:, 0]] - model.mean[t[:, 1]]).norm(dim=1)
            e1 = (v[t[:, 0]] - v[t[:, 1]]).norm(dim=1)
            assert (e1 / e0).max() < 1.6 and (e1 / e0).min() > 0.6
            n = vertex_normals(v[None], t)[0]
            n0 = vertex_normals(model.mean[None], t)[0]
            assert ((n * n0).sum(-1) > 0.5).float().mean() > 0.995  # no folds


def test_priors_known_values(model):
    ps = torch.zeros(1, model.n_identity, dtype=torch.float64)
    ps[0, 0] = 2 * model.identity_eigenvalues[0].sqrt()
    assert model.identity_prior(ps).item() == pytest.approx(4.0)
    pe = torch.zeros(1, model.n_expressions, dtype=torch.float64)
    pe[0, model.expression_names.index("jawOpen")] = 1.0
    assert model.expression_prior(pe).item() == pytest.approx(4.0)  # (1 / 0.5)^2


def test_bad_shapes_are_reported(model):
    with pytest.raises(ValueError, match=r"expected p_s of shape \(B, 100\), got \(1, 3\)"):
        model(torch.zeros(1, 3), torch.zeros(1, model.n_expressions))
    with pytest.raises(ValueError, match="batch sizes differ"):
        model(torch.zeros(2, model.n_identity), torch.zeros(1, model.n_expressions))


def test_correspondences_in_the_right_regions(model):
    lab = model.regions.numpy()
    ib = model.ibug68.numpy()
    assert np.array_equal(model.landmarks.numpy(), np.arange(468))
    assert ib.min() >= 0 and ib.max() < 468 and len(np.unique(ib)) == 68
    name = lambda i: REGIONS[lab[i]]  # noqa: E731
    assert all(name(i) == "eyes" for i in ib[36:48])
    assert all(name(i) == "lips" for i in ib[48:68])
    assert all(name(i) in ("brows", "forehead") for i in ib[17:27])
    assert all(name(i) == "nose" for i in ib[30:36])
    a5 = model.align5.numpy()
    assert [name(i) for i in a5] == ["eyes"] * 4 + ["nose"]
    v = model.mean.numpy()
    assert v[ib[36], 0] < v[ib[45], 0]  # iBUG 36 is the image-left eye corner: the subject's right (x < 0)
    counts = collections.Counter(REGIONS[i] for i in lab)
    assert all(counts[r] > 50 for r in REGIONS)


def test_uv_layout(model):
    uv = model.uv.numpy()
    assert uv.min() >= 0 and uv[:, 1].max() <= 1
    face = np.arange(468)
    # mirror-symmetric about u = 0.5 on the face
    m = model.mirror.numpy()[face]
    assert np.allclose(uv[face, 0] + uv[m, 0], 1.0, atol=1e-4) and np.allclose(uv[face, 1], uv[m, 1], atol=1e-4)
    # no triangle in UV space is flipped or degenerate where the head has area
    t = model.uv_faces.numpy()
    a = uv[t[:, 1]] - uv[t[:, 0]]
    b = uv[t[:, 2]] - uv[t[:, 0]]
    signed = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    assert (np.sign(signed) == np.sign(np.median(signed))).mean() > 0.99
    region = model.region_uv.numpy()
    assert region.shape == (512, 512) and (region == REGIONS.index("lips")).sum() > 100


def test_mesh_is_a_clean_manifold_with_three_holes(model, card):
    t = model.triangles.numpy()
    directed = collections.Counter(map(tuple, np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]).tolist()))
    assert max(directed.values()) == 1  # consistently oriented, no duplicate faces
    undirected = collections.Counter(tuple(sorted(e)) for e in directed)
    assert set(undirected.values()) <= {1, 2}
    boundary = [e for e, c in undirected.items() if c == 1]
    # boundary loops: eyes and mouth
    adj = collections.defaultdict(list)
    for a, b in boundary:
        adj[a].append(b)
        adj[b].append(a)
    seen, loops = set(), 0
    for s in adj:
        if s in seen:
            continue
        loops += 1
        stack = [s]
        while stack:
            x = stack.pop()
            if x not in seen:
                seen.add(x)
                stack += adj[x]
    assert loops == 3 and all(len(v) == 2 for v in adj.values())
    v = model.mean.numpy()
    area = 0.5 * np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1)
    assert area.min() > 1e-3  # no degenerate triangles
    assert card["metrics"]["min_angle_deg"] > 5.0 and card["metrics"]["min_angle_median_deg"] > 30


def test_normals_point_outward_and_tangents_are_a_frame(model):
    ps, pe = model.zeros(1)
    out = model(ps, pe)
    v, n, tg = out.vertices[0], out.normals[0], out.tangents[0]
    centre = v.mean(0)
    assert ((n * (v - centre)).sum(-1) > 0).double().mean() > 0.97
    assert torch.allclose(n.norm(dim=-1), torch.ones(len(n), dtype=n.dtype), atol=1e-6)
    assert (tg[:, :3] * n).sum(-1).abs().max() < 1e-6
    assert set(tg[:, 3].unique().tolist()) <= {-1.0, 1.0}
    # the tangent follows +u: around the front of the face +u runs toward the subject's left (+x)
    nose = 4
    assert tg[nose, 0] > 0.9


def test_expressions_are_named_and_localized(model, card):
    names = model.expression_names
    assert len(names) == 52 and {"jawOpen", "mouthSmileLeft", "eyeBlinkLeft", "browInnerUp"} <= set(names)
    v = model.mean.numpy()
    back = v[:, 2] < v[[234, 454], 2].mean() - 40
    nonzero = 0
    for i, n in enumerate(names):
        d = np.linalg.norm(model.expression_basis[:, :, i].numpy(), axis=1)
        if d.max() == 0:
            assert n.startswith("eyeLook") or n == "tongueOut"
            continue
        nonzero += 1
        assert 1.0 < d.max() < 30.0, n
        assert d[back].max() < 0.05, f"{n} moves the back of the head"
        if n.endswith("Left") and not n.startswith(("jaw", "mouthLeft")):
            assert d[v[:, 0] < -25].max() < 0.05, f"{n} moves the right side"
        if n.startswith("eye"):
            assert d[v[:, 1] < v[2, 1]].max() < 0.05, f"{n} moves below the nose"
        if n.startswith(("jaw", "mouth")):
            assert d[v[:, 1] > v[168, 1]].max() < 0.05, f"{n} moves above the nose bridge"
    assert nonzero >= 40


def test_mirrored_expressions_pair_up(model):
    names = model.expression_names
    flip = torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)
    for n in names:
        if n.endswith("Left") and n.replace("Left", "Right") in names:
            left = model.expression_basis[:, :, names.index(n)]
            right = model.expression_basis[:, :, names.index(n.replace("Left", "Right"))]
            assert torch.allclose(left[model.mirror] * flip, right, atol=0.05), n


def test_gradients_float64():
    """vertex_normals and vertex_tangents on a small open mesh (a pyramid's sides)."""
    v = torch.tensor([[0, 0, 1.0], [1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]], dtype=torch.float64)[None]
    v = (v + 0.05 * torch.randn(v.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(0))).requires_grad_()
    f = torch.tensor([[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 1]])
    uv = torch.tensor([[0.5, 0.5], [1, 0.5], [0.5, 1], [0, 0.5], [0.5, 0]], dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda x: vertex_normals(x, f), (v,))
    assert torch.autograd.gradcheck(lambda x: vertex_tangents(x, f, uv, f, vertex_normals(x, f))[..., :3], (v,))


def test_model_gradients_reach_coefficients(model):
    ps, pe = model.zeros(1)
    ps.requires_grad_(True)
    pe.requires_grad_(True)
    out = model(ps, pe)
    (out.vertices[0, :468].sum() + out.normals.sum()).backward()
    assert ps.grad.abs().sum() > 0 and pe.grad.abs().sum() > 0


def test_build_does_not_depend_on_the_blas_thread_count(root, tmp_path):
    # Built in one thread against models/ (built with the default threads). Before the basis was
    # diagonalised per coordinate, y/z pairs came out rotated and signs flipped: up to 2x the basis's
    # largest entry apart (2026-11-28). Now they agree to float32 rounding.
    import os
    import subprocess
    import sys

    from safetensors import safe_open

    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    code = "import sys; from pathlib import Path; from fitme_cli.shape.build import build; build(Path(sys.argv[1]))"
    subprocess.run([sys.executable, "-c", code, str(tmp_path)], env=env, check=True, timeout=600)
    with safe_open(tmp_path / "shape_model.safetensors", "pt") as a, safe_open(root / "shape_model.safetensors", "pt") as b:
        assert a.metadata() == b.metadata() and sorted(a.keys()) == sorted(b.keys())
        for name in a.keys():
            x, y = a.get_tensor(name), b.get_tensor(name)
            if name.startswith("identity_"):
                torch.testing.assert_close(x, y, rtol=1e-5, atol=1e-6 * float(y.abs().max()), msg=name)
            else:
                assert torch.equal(x, y), name


def test_basis_signs_do_not_hang_on_a_near_tie():
    """The largest entries of an antisymmetric vector are a mirror pair; a last-bit change must not flip it."""
    from fitme_cli.shape.build import _fix_signs

    u = np.array([[0.5], [-0.5 * (1 - 1e-15)], [0.1]])
    v = np.array([[0.5 * (1 - 1e-15)], [-0.5], [0.1]])
    np.testing.assert_allclose(_fix_signs(u), _fix_signs(v), atol=1e-14)
    np.testing.assert_array_equal(_fix_signs(-u), _fix_signs(u))


def test_fast_normals_and_tangents_match_the_index_add_reference(root):
    """forward() accumulates per-face values with one CSR product; the plain index_add loop is the reference."""
    m = load_shape_model(root).double()  # its own copy: the shared fixture stays float32
    p_s = m.sample_identity(2, torch.Generator().manual_seed(3)).requires_grad_(True)
    p_e = torch.zeros(2, m.n_expressions, dtype=torch.float64)
    out = m(p_s, p_e)
    n_ref = vertex_normals(out.vertices, m.triangles)
    t_ref = vertex_tangents(out.vertices, m.triangles, m.uv, m.uv_faces, n_ref)
    torch.testing.assert_close(out.normals, n_ref, rtol=0, atol=1e-12)
    torch.testing.assert_close(out.tangents, t_ref, rtol=0, atol=1e-12)
    w = torch.sin(out.vertices.detach())
    g_fast = torch.autograd.grad((out.normals * w).sum() + (out.tangents[..., :3] * w).sum(), p_s)[0]
    out2 = m(p_s, p_e)
    n2 = vertex_normals(out2.vertices, m.triangles)
    t2 = vertex_tangents(out2.vertices, m.triangles, m.uv, m.uv_faces, n2)
    g_ref = torch.autograd.grad((n2 * w).sum() + (t2[..., :3] * w).sum(), p_s)[0]
    torch.testing.assert_close(g_fast, g_ref, rtol=1e-9, atol=1e-12)
