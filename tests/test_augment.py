"""`fitme augment`: masked histogram matching to Monk Skin Tone levels (paper Eq. 2)."""

import numpy as np
import pytest
from click.testing import CliRunner

from fitme_cli.cli import main
from fitme_cli.errors import WrongLayout
from fitme_cli.io.maps import read_map, write_map
from fitme_cli.reflectance.augment import augment_albedo, monk_albedo, skin_mask
from fitme_cli.shape.regions import REGIONS, region_masks

COLOURS = {  # linear albedo per region of a synthetic light-skinned subject with dark hair and brows
    "scalp": (0.05, 0.035, 0.025), "skin": (0.55, 0.38, 0.30), "forehead": (0.56, 0.39, 0.31),
    "brows": (0.06, 0.045, 0.035), "eyes": (0.50, 0.34, 0.28), "nose": (0.57, 0.37, 0.29),
    "lips": (0.48, 0.18, 0.17), "neck": (0.54, 0.37, 0.29),
}


@pytest.fixture(scope="module")
def region_uv(models_root):
    from safetensors.numpy import load_file

    from fitme_cli.perception.registry import ensure_models

    return load_file(str(ensure_models(["shape_model"], models_root) / "shape_model.safetensors"))["region_uv"]


def synthetic_albedo(region_uv: np.ndarray, size: int = 256, seed: int = 0) -> np.ndarray:
    masks = region_masks(region_uv, size)
    rng = np.random.default_rng(seed)
    a = np.zeros((size, size, 3), np.float32)
    for name in REGIONS:
        a[masks[name]] = COLOURS[name]
    return (a * np.exp(rng.normal(0, 0.06, a.shape))).astype(np.float32)


def test_monk_albedo_known_values():
    lightest, darkest = monk_albedo(1), monk_albedo(10)
    assert lightest.shape == (3,) and 0.5 < lightest[0] < 0.65 and darkest[0] < 0.02
    assert all(monk_albedo(i).mean() > monk_albedo(i + 1).mean() for i in range(1, 10) if i not in (2,))
    with pytest.raises(ValueError, match="1..10, got 11"):
        monk_albedo(11)


def test_masked_out_texels_stay_exactly_and_skin_moves_to_the_target(region_uv):
    a = synthetic_albedo(region_uv)
    masks = region_masks(region_uv, 256)
    out, m = augment_albedo(a, masks["forehead"], masks["mapped"], level=9)
    assert np.array_equal(out[m == 0], a[m == 0])
    assert (m[masks["brows"]] == 0).mean() > 0.95 and (m[masks["scalp"]] == 0).mean() > 0.95  # hair keeps its colour
    assert (m[masks["skin"]] > 0.5).mean() > 0.97 and (m[masks["skin"]] == 1).mean() > 0.8
    skin = m == 1
    target = monk_albedo(9)
    before = np.abs(np.log(a[skin].mean(0)) - np.log(target)).max()
    after = np.abs(np.log(out[skin].mean(0)) - np.log(target)).max()
    assert after < 0.15 < before
    # texture contrast (log spread) is kept
    assert np.std(np.log(out[skin][:, 0])) == pytest.approx(np.std(np.log(a[skin][:, 0])), rel=0.15)


def test_mask_is_exactly_one_at_the_forehead_tone(region_uv):
    a = synthetic_albedo(region_uv)
    masks = region_masks(region_uv, 256)
    m = skin_mask(a, masks["forehead"], masks["mapped"])
    assert m.min() == 0 and m.max() == 1 and np.median(m[masks["forehead"]]) == 1


def test_not_an_albedo_map_is_refused(region_uv):
    masks = region_masks(region_uv, 256)
    noise = np.random.default_rng(0).uniform(0, 1, (256, 256, 3)).astype(np.float32)
    with pytest.raises(WrongLayout, match="varies too much|bluer"):
        augment_albedo(noise, masks["forehead"], masks["mapped"], 5)
    blue = np.full((256, 256, 3), (0.1, 0.2, 0.6), np.float32)
    with pytest.raises(WrongLayout, match="bluer than it is red"):
        augment_albedo(blue, masks["forehead"], masks["mapped"], 5)
    with pytest.raises(WrongLayout, match="square UV map of at least 64x64"):
        augment_albedo(np.zeros((32, 32, 3), np.float32), masks["forehead"][:32, :32], masks["mapped"][:32, :32], 5)


@pytest.mark.parametrize("kind,ext", [("png8", ".png"), ("png16", ".png"), ("exr16", ".exr"), ("exr32", ".exr")])
def test_cli_keeps_size_and_format_and_never_touches_inputs(region_uv, tmp_path, kind, ext):
    src = tmp_path / "in"
    src.mkdir()
    write_map(src / f"face{ext}", synthetic_albedo(region_uv, 128), kind)
    before = (src / f"face{ext}").read_bytes()
    r = CliRunner().invoke(main, ["augment", str(src), "-o", str(tmp_path / "out"), "--per-image", "3", "--seed", "4"])
    assert r.exit_code == 0, r.output
    outs = sorted((tmp_path / "out").iterdir())
    assert len(outs) == 3 and all(p.name.startswith("face_mst") and p.suffix == ext for p in outs)
    for p in outs:
        m = read_map(p)
        assert m.kind == kind and m.linear.shape == (128, 128, 3)
    assert (src / f"face{ext}").read_bytes() == before
    # deterministic by seed
    r2 = CliRunner().invoke(main, ["augment", str(src), "-o", str(tmp_path / "out2"), "--per-image", "3", "--seed", "4"])
    assert r2.exit_code == 0
    assert [p.name for p in outs] == sorted(p.name for p in (tmp_path / "out2").iterdir())


def test_png8_masked_out_texels_are_bit_exact(region_uv, tmp_path):
    import cv2

    src = tmp_path / "in"
    src.mkdir()
    write_map(src / "a.png", synthetic_albedo(region_uv, 128), "png8")
    r = CliRunner().invoke(main, ["augment", str(src), "-o", str(tmp_path / "out"), "--per-image", "1"])
    assert r.exit_code == 0
    a = cv2.imread(str(src / "a.png"))
    b = cv2.imread(str(next((tmp_path / "out").iterdir())))
    masks = region_masks(region_uv, 128)
    assert np.array_equal(a[masks["scalp"] & ~masks["mapped"] | ~masks["mapped"]], b[~masks["mapped"]])
    assert (a[masks["brows"]] == b[masks["brows"]]).all(axis=1).mean() > 0.95


def test_cli_bad_inputs(region_uv, tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    write_map(src / "good.png", synthetic_albedo(region_uv, 128), "png8")
    write_map(src / "photo.png", np.random.default_rng(1).uniform(0, 1, (128, 96, 3)).astype(np.float32), "png8")
    (src / "broken.exr").write_bytes(b"not an exr")
    r = CliRunner().invoke(main, ["augment", str(src), "-o", str(tmp_path / "out"), "--per-image", "2"])
    assert r.exit_code in (13, 22)
    assert "photo.png: expected a square UV map, got 96x128" in r.stderr
    assert "broken.exr: not a readable EXR file" in r.stderr
    assert len(list((tmp_path / "out").iterdir())) == 2  # the good map still ran
    r = CliRunner().invoke(main, ["augment", str(src), "-o", str(src)])
    assert r.exit_code == 17 and "input directory" in r.stderr
    r = CliRunner().invoke(main, ["augment", str(tmp_path / "missing"), "-o", str(tmp_path / "o")])
    assert r.exit_code == 10
