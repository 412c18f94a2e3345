"""Procedural facial reflectance data (fitme_cli.reflectance.skin_data) and `fitme dataset`."""

import json

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from fitme_cli.cli import main
from fitme_cli.reflectance.augment import monk_albedo
from fitme_cli.reflectance.skin_data import SkinDataSettings, generate_sample, skin_layout, skin_rgb

S = 128


@pytest.fixture(scope="module")
def models(models_root):
    from fitme_cli.perception.registry import ensure_models

    return ensure_models(["shape_model"], models_root)


@pytest.fixture(scope="module")
def layout(models):
    return skin_layout(models, S)


@pytest.fixture(scope="module")
def layout256(models):
    return skin_layout(models, 256)


def _highpass(x, sigma):
    return x - cv2.GaussianBlur(x.astype(np.float32), (0, 0), sigma)


def test_shapes_dtypes_ranges_and_unit_normals(layout):
    for i in range(3):
        s = generate_sample(layout, 0, i, SkinDataSettings(size=S))
        assert s.albedo.shape == (S, S, 3) and s.albedo.dtype == np.float32
        assert s.specular.shape == (S, S) and s.specular.dtype == np.float32
        assert s.normals.shape == (S, S, 3) and s.normals.dtype == np.float32
        assert 0 <= s.albedo.min() and s.albedo.max() <= 1 and 0 <= s.specular.min() and s.specular.max() <= 1
        assert np.allclose(np.linalg.norm(s.normals, axis=-1), 1, atol=1e-5) and (s.normals[..., 2] > 0).all()
        json.dumps(s.params)  # JSON-able
        m = layout.masks["mapped"]
        assert 0.03 < s.specular[m].mean() < 0.35


def test_deterministic_by_seed_and_index(layout):
    a, b = generate_sample(layout, 7, 3, SkinDataSettings(size=S)), generate_sample(layout, 7, 3, SkinDataSettings(size=S))
    assert all(np.array_equal(getattr(a, k), getattr(b, k)) for k in ("albedo", "specular", "normals")) and a.params == b.params
    c, d = generate_sample(layout, 8, 3, SkinDataSettings(size=S)), generate_sample(layout, 7, 4, SkinDataSettings(size=S))
    assert not np.array_equal(a.albedo, c.albedo) and not np.array_equal(a.normals, d.normals)


def test_bad_settings_raise_clearly(layout):
    with pytest.raises(ValueError, match="power of two"):
        SkinDataSettings(size=100)
    with pytest.raises(ValueError, match="power of two"):
        SkinDataSettings(size=32)
    with pytest.raises(ValueError, match="age_range"):
        SkinDataSettings(age_range=(0.5, 0.2))
    with pytest.raises(ValueError, match="layout is for 128"):
        generate_sample(layout, 0, 0, SkinDataSettings(size=256))


def test_skin_rgb_monotone_in_melanin_and_spans_monk_scale():
    m = np.linspace(0, 1, 101)
    rgb = skin_rgb(m, 0.2)
    assert rgb.shape == (101, 3) and rgb.dtype == np.float32
    assert (np.diff(rgb, axis=0) < 0).all()  # every channel darker with more melanin
    assert (rgb[:, 0] > rgb[:, 1]).all() and (rgb[:, 1] > rgb[:, 2]).all()  # skin: R > G > B
    light, dark = rgb[0], rgb[-1]
    assert np.all(np.abs(np.log(light / monk_albedo(1))) < np.log(1.5))
    assert np.all(np.abs(np.log(dark / monk_albedo(10))) < np.log(2.5))
    # hue is not "too red" at high melanin: dark skin keeps G/R ~ 0.6 (MST 8-10 swatches: 0.45-0.8)
    assert skin_rgb(0.7, 0.2)[1] / skin_rgb(0.7, 0.2)[0] > 0.5
    # haemoglobin reddens (lowers green more than red)
    lo, hi = skin_rgb(0.1, 0.1), skin_rgb(0.1, 0.9)
    assert hi[1] / hi[0] < lo[1] / lo[0]


def test_forehead_albedo_of_extreme_melanin_matches_monk_ends(layout):
    fh = layout.masks["forehead"]
    light = generate_sample(layout, 0, 0, SkinDataSettings(size=S, melanin_range=(0.0, 0.0))).albedo[fh]
    dark = generate_sample(layout, 0, 0, SkinDataSettings(size=S, melanin_range=(1.0, 1.0))).albedo[fh]
    assert np.all(np.abs(np.log(np.median(light, 0) / monk_albedo(1))) < np.log(1.6))
    assert np.all(np.abs(np.log(np.median(dark, 0) / monk_albedo(10))) < np.log(2.5))


def test_specular_higher_on_t_zone_and_lips_than_on_scalp(layout):
    m = layout.masks
    fh_centre = m["forehead"] & (np.abs(np.arange(S) - S / 2) < S * 0.04)[None, :]
    for i in range(4):
        sp = generate_sample(layout, 1, i, SkinDataSettings(size=S)).specular
        scalp = sp[m["scalp"]].mean()
        assert sp[m["nose"]].mean() > 1.5 * scalp and sp[fh_centre].mean() > 1.5 * scalp and sp[m["lips"]].mean() > 1.5 * scalp
        assert sp[m["nose"]].mean() > sp[m["skin"]].mean()


def test_pores_larger_and_denser_on_nose_than_forehead(layout256):
    young = SkinDataSettings(size=256, age_range=(0.0, 0.0), beard_probability=0.0, freckle_probability=0.0)
    m = layout256.masks
    ratios = []
    for i in range(3):
        n = generate_sample(layout256, 2, i, young).normals
        e = (_highpass(n[..., 0], 2.0) ** 2 + _highpass(n[..., 1], 2.0) ** 2)
        ratios.append(e[m["nose"]].mean() / e[m["forehead"]].mean())
    assert min(ratios) > 1.5


def test_old_sample_has_forehead_lines_young_does_not(layout256):
    m = layout256.masks
    cols = np.abs(np.arange(256) - 128) < 256 * 0.06
    fh = m["forehead"] & cols[None, :]
    energy = {}
    for age in (0.0, 1.0):
        n = generate_sample(layout256, 3, 0, SkinDataSettings(size=256, age_range=(age, age))).normals
        energy[age] = (n[..., 1][fh] ** 2).mean() / (n[..., 0][fh] ** 2).mean()  # horizontal lines tilt n along v
    assert energy[1.0] > 1.5 * energy[0.0]


def test_albedo_darkens_in_the_same_valleys_as_the_normals(layout256):
    settings = SkinDataSettings(size=256, age_range=(0.9, 0.9), beard_probability=0.0, freckle_probability=0.0)
    skin = layout256.masks["skin"] | layout256.masks["forehead"] | layout256.masks["nose"]
    rs = []
    for i in range(3):
        s = generate_sample(layout256, 4, i, settings)
        # divergence of the normals' tangential part = -laplacian(h): negative in valleys and pores
        nx, ny = s.normals[..., 0], s.normals[..., 1]
        div = np.gradient(nx, axis=1) - np.gradient(ny, axis=0)  # d/dv = -d/drow
        lum = np.log(s.albedo.mean(-1) + 1e-4)
        d, lh = _highpass(div, 2.0)[skin], _highpass(lum, 2.0)[skin]
        rs.append(np.corrcoef(d, lh)[0, 1])
        valleys, ridges = d < np.quantile(d, 0.1), d > np.quantile(d, 0.9)
        assert lh[valleys].mean() < lh[ridges].mean() - 0.03  # >3 % darker in the valleys
    assert min(rs) > 0.15 and np.mean(rs) > 0.3, rs


def _run(args):
    return CliRunner().invoke(main, ["dataset", *args], catch_exceptions=False)


def test_cli_writes_dataset_refuses_rerun_and_is_byte_identical(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    r = _run([str(a), "-n", "3", "--size", "64", "--seed", "5"])
    assert r.exit_code == 0, r.output
    files = sorted(p.name for p in a.iterdir())
    assert len([f for f in files if f.startswith("sample_")]) == 9 and "dataset.json" in files
    meta = json.loads((a / "dataset.json").read_text())
    assert meta["seed"] == 5 and len(meta["samples"]) == 3 and meta["settings"]["size"] == 64
    assert 0.0 < meta["stats"]["albedo_mean"] < 0.6 and 0.55 < meta["stats"]["normals_mean"] < 0.75
    norm = cv2.imread(str(a / "sample_00000_normals.png"), cv2.IMREAD_UNCHANGED)
    assert norm.dtype == np.uint16 and norm.shape == (64, 64, 3)
    n = norm[..., ::-1] / 65535.0 * 2 - 1  # raw encoding, not gamma: unit vectors come back
    assert np.allclose(np.linalg.norm(n, axis=-1), 1, atol=2e-3)
    r = _run([str(a), "-n", "3", "--size", "64", "--seed", "5"])
    assert r.exit_code == 17 and "--force" in r.output
    assert _run([str(a), "-n", "3", "--size", "64", "--seed", "5", "--force"]).exit_code == 0
    assert _run([str(b), "-n", "3", "--size", "64", "--seed", "5"]).exit_code == 0
    for f in files:
        assert (a / f).read_bytes() == (b / f).read_bytes(), f


def test_cli_bad_output_and_size(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    r = _run([str(blocker / "sub"), "-n", "1", "--size", "64"])
    assert r.exit_code == 17 and "cannot write" in r.output
    r = _run([str(tmp_path / "o"), "-n", "1", "--size", "100"])
    assert r.exit_code == 2 and "power of two" in r.output
