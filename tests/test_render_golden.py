"""Golden renders of the shape model's mean face (benchmarks/render_golden.py defines the scenes and the
procedural maps; ``--update`` rewrites tests/golden/*.png), plus checks that the pictures make sense:
lit from the light's side, holes only at the eye and mouth openings, no speckles."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def golden():
    spec = importlib.util.spec_from_file_location("render_golden", REPO / "benchmarks" / "render_golden.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def images(golden, models_root):
    return golden.render_all(models_root)


NAMES = ["front_none", "front_default", "front_all_two_lights", "threequarter_default", "front_point_light",
         "threequarter_sh_ambient"]


def test_scene_list_matches(golden):
    assert list(golden.golden_scenes()) == NAMES


@pytest.mark.parametrize("name", NAMES)
def test_matches_golden_png(name, golden, images):
    path = golden.GOLDEN_DIR / f"{name}.png"
    assert path.is_file(), f"missing {path}: run python benchmarks/render_golden.py --update"
    img = images[name]
    assert img.shape == (128, 128, 3) and np.isfinite(img).all()
    mean, mx = golden.compare(img, path)
    assert mean < 1 / 255 and mx < 8 / 255, f"{name}: mean {mean * 255:.2f}/255, max {mx * 255:.1f}/255"


def _mask(img):
    return img.max(-1) > 0


def test_holes_only_at_eyes_and_mouth(images):
    from scipy import ndimage

    for name in ("front_none", "front_default", "front_point_light"):
        m = _mask(images[name])
        holes = ndimage.binary_fill_holes(m) & ~m
        lab, n = ndimage.label(holes)
        assert n <= 3, f"{name}: {n} holes (eyes and mouth are 3)"
        centres = ndimage.center_of_mass(holes, lab, range(1, n + 1))
        rows = sorted(c[0] for c in centres)
        assert all(45 <= r <= 85 for r in rows), f"{name}: holes at rows {rows}"


def test_no_silhouette_speckles(images):
    """No isolated background pixel inside the face, no isolated face pixel outside it."""
    from scipy import ndimage

    for name, img in images.items():
        m = _mask(img)
        lab, n = ndimage.label(m)
        sizes = ndimage.sum(m, lab, range(1, n + 1))
        assert n == 1 or sorted(sizes)[-2] < 2, f"{name}: stray fragments {sorted(sizes)[-5:]}"
        lab, n = ndimage.label(~m)
        sizes = ndimage.sum(~m, lab, range(1, n + 1))
        assert (np.array(sizes) >= 3).all(), f"{name}: single-pixel holes {sorted(sizes)[:5]}"


def test_lit_from_the_lights_side(images):
    """The key light of front_all_two_lights comes from the subject's left (+x) = the image's right."""
    img = images["front_all_two_lights"].mean(-1)
    m = img > 0
    cols = np.nonzero(m.any(0))[0]
    mid = (cols.min() + cols.max()) // 2
    left, right = img[:, :mid][m[:, :mid]].mean(), img[:, mid + 1:][m[:, mid + 1:]].mean()
    assert right > left + 0.03, (left, right)
    # SH environment brighter from +x: same
    img = images["threequarter_sh_ambient"].mean(-1)
    m = img > 0
    assert np.isfinite(img).all() and m.sum() > 2000


def test_specular_where_the_light_reflects(images):
    """The default effects add highlights: brighter than the diffuse-only render on the forehead/nose
    (upper middle), almost nothing at the grazing cheeks' silhouette."""
    d = images["front_default"].mean(-1) - images["front_none"].mean(-1)
    m = images["front_none"].max(-1) > 0
    assert d[m].max() > 0.05
    rows, cols = np.nonzero(d > 0.5 * d[m].max())
    assert 20 <= np.median(rows) <= 80 and 45 <= np.median(cols) <= 85
