"""`fitme detect` through click's CliRunner: output formats, overlays, batches with bad photos, and a
one-line error with a distinct exit code for each bad input."""

import json

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from fitme_cli.cli import main


@pytest.fixture(scope="module")
def photos(tmp_path_factory, astronaut, models_root):
    from fitme_cli.perception.registry import ensure_models

    ensure_models(["dlib_resnet"], models_root)
    d = tmp_path_factory.mktemp("photos")
    cv2.imwrite(str(d / "astronaut.jpg"), astronaut[..., ::-1])
    from skimage import data

    cv2.imwrite(str(d / "coffee.jpg"), data.coffee()[..., ::-1])
    full = (d / "astronaut.jpg").read_bytes()
    (d / "truncated.jpg").write_bytes(full[: len(full) // 2])
    (d / "notes.txt").write_text("not a photo")
    (d / "empty.jpg").write_bytes(b"")
    return d


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def test_help_lists_detect():
    r = run("--help")
    assert r.exit_code == 0 and "detect" in r.output and "models" in r.output


def test_single_photo_summary(photos):
    r = run("detect", photos / "astronaut.jpg")
    assert r.exit_code == 0, r.output
    assert "astronaut.jpg: face" in r.output and "yaw" in r.output


def test_json_to_stdout(photos):
    r = run("detect", photos / "astronaut.jpg", "--json")
    assert r.exit_code == 0
    doc = json.loads(r.stdout.strip().splitlines()[-1])
    face = doc["photos"][0]["faces"][0]
    assert len(face["landmarks"]) == 468 and len(face["ibug68"]) == 68 and len(face["identity"]) == 128
    assert doc["photos"][0]["width"] == 512


def test_output_file_and_overlay(photos, tmp_path):
    r = run("detect", photos / "astronaut.jpg", "-o", tmp_path / "r.json", "--overlay", tmp_path / "ov")
    assert r.exit_code == 0, r.output
    doc = json.loads((tmp_path / "r.json").read_text())
    assert doc["photos"][0]["chosen"] == 0
    ov = cv2.imread(str(tmp_path / "ov" / "astronaut.overlay.png"))
    assert ov.shape == (768, 768 * 2, 3)  # photo + zoomed face panel
    # the mesh is drawn in green on the photo half, over the face only
    green = (ov[..., 1] > 200) & (ov[..., 0] < 120) & (ov[..., 2] < 120)
    ys, xs = np.nonzero(green[:, :768])
    assert len(xs) > 100 and 250 < xs.mean() < 420 and 100 < ys.mean() < 260


def test_batch_continues_past_bad_photos(photos, tmp_path):
    names = ["notes.txt", "astronaut.jpg", "truncated.jpg", "empty.jpg", "coffee.jpg"]
    r = run("detect", *[photos / n for n in names], "-o", tmp_path / "r.json")
    assert r.exit_code == 13  # the first failure: notes.txt is not an image
    doc = json.loads((tmp_path / "r.json").read_text())
    by_name = {p["path"].split("/")[-1]: p for p in doc["photos"]}
    assert by_name["astronaut.jpg"]["chosen"] == 0
    assert by_name["truncated.jpg"]["error"]["code"] == 14
    assert by_name["empty.jpg"]["error"]["code"] == 12
    assert by_name["coffee.jpg"]["error"] == {"type": "NoFaceFound", "code": 16, "message": "no face found"}


@pytest.mark.parametrize("name,code,message", [
    ("missing.jpg", 10, "file not found"),
    (".", 11, "is a directory"),
    ("empty.jpg", 12, "file is empty"),
    ("notes.txt", 13, "not an image"),
    ("truncated.jpg", 14, "truncated"),
    ("coffee.jpg", 16, "no face found"),
])
def test_bad_input_one_line_and_exit_code(photos, name, code, message):
    path = photos / name if name != "." else photos
    r = run("detect", path)
    assert r.exit_code == code
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("fitme: error: ") and message in lines[0]
    assert "Traceback" not in r.output


def test_too_large(photos, tmp_path):
    from tests.test_images import _png_claiming

    (tmp_path / "bomb.png").write_bytes(_png_claiming(60000, 60000))
    r = run("detect", tmp_path / "bomb.png")
    assert r.exit_code == 15 and "megapixels" in r.stderr
    (tmp_path / "big.png").write_bytes(_png_claiming(11000, 11000))  # 121 MP: a 108 MP phone photo's size
    r = run("detect", tmp_path / "big.png", "--max-megapixels", "50")
    assert r.exit_code == 15 and "the limit is 50 megapixels" in r.stderr


def test_unwritable_output(photos, tmp_path):
    r = run("detect", photos / "astronaut.jpg", "-o", tmp_path / "no" / "such" / "dir" / "r.json")
    assert r.exit_code == 17 and "does not exist" in r.stderr
    (tmp_path / "f").write_text("x")
    r = run("detect", photos / "astronaut.jpg", "--overlay", tmp_path / "f")
    assert r.exit_code == 17 and "expects a directory" in r.stderr


def test_never_overwrites_an_input(photos):
    before = (photos / "astronaut.jpg").read_bytes()
    r = run("detect", photos / "astronaut.jpg", "-o", photos / "astronaut.jpg")
    assert r.exit_code == 17 and "overwrite an input" in r.stderr
    assert (photos / "astronaut.jpg").read_bytes() == before


def test_same_stem_overlays_do_not_collide(photos, tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "astronaut.jpg").write_bytes((photos / "astronaut.jpg").read_bytes())
    r = run("detect", photos / "astronaut.jpg", tmp_path / "a" / "astronaut.jpg", "--overlay", tmp_path / "ov")
    assert r.exit_code == 0
    assert sorted(p.name for p in (tmp_path / "ov").iterdir()) == ["astronaut-1.overlay.png", "astronaut.overlay.png"]


@pytest.mark.parametrize("variant", ["gray", "rgba", "png16", "cmyk", "exif_rotated"])
def test_odd_images_simply_work(photos, tmp_path, astronaut, variant):
    from PIL import Image

    p = tmp_path / f"{variant}.png"
    im = Image.fromarray(astronaut)
    if variant == "gray":
        im.convert("L").save(p)
    elif variant == "rgba":
        im.convert("RGBA").save(p)
    elif variant == "png16":
        cv2.imwrite(str(p), astronaut[..., ::-1].astype(np.uint16) * 257)
    elif variant == "cmyk":
        p = tmp_path / "cmyk.jpg"
        im.convert("CMYK").save(p, quality=95)
    else:
        exif = Image.Exif()
        exif[0x0112] = 6  # stored rotated: the viewer turns it 90 degrees clockwise
        Image.fromarray(np.ascontiguousarray(np.rot90(astronaut, 1))).save(p, exif=exif.tobytes())
    r = run("detect", p, "--json")
    assert r.exit_code == 0, r.output
    face = json.loads(r.stdout.strip().splitlines()[-1])["photos"][0]["faces"][0]
    assert 170 < face["box"][0] < 195 and abs(face["pose"]["roll"]) < 10


def test_models_list():
    r = run("models", "list")
    assert r.exit_code == 0 and "facemesh" in r.output and "CC0" in r.output
