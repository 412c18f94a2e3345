"""`fitme render`: the contact sheet (layout, lighting directions, expressions, environments) and bad inputs."""

import numpy as np
import pytest
from click.testing import CliRunner

from fitme_cli.cli import main

TINY_FIT = ["--preset", "fast", "--iterations", "2", "--render-size", "128", "--threads", "1"]
QUICK = ["--size", "96", "--turntable", "2", "--threads", "1"]


@pytest.fixture(scope="module")
def avatar(tmp_path_factory, models_root, one_thread):
    from fitme_cli.io.images import write_sample_photo

    d = tmp_path_factory.mktemp("render_fit")
    photo = write_sample_photo("astronaut", d / "astronaut.jpg")
    out = d / "avatar"
    r = CliRunner().invoke(main, ["fit", str(photo), "-o", str(out), *TINY_FIT])
    assert r.exit_code == 0, r.output
    return out


def _read(path):
    import cv2

    img = cv2.imread(str(path))
    assert img is not None, path
    return img[..., ::-1].astype(np.float64)


def test_render_writes_a_sheet_of_environments_by_yaws(avatar, tmp_path):
    out = tmp_path / "sheet.png"
    r = CliRunner().invoke(main, ["render", str(avatar), "-o", str(out), "--env", "studio,sunset,photo", *QUICK])
    assert r.exit_code == 0, r.output
    assert "3 environments (studio, sunset, photo) x 2 views" in r.output
    img = _read(out)
    assert img.shape == (3 * 96, 2 * 96, 3)
    cells = img.reshape(3, 96, 2, 96, 3)
    bg = np.median(img[:, :4].reshape(-1, 3), 0)
    for i in range(3):
        for j in range(2):
            head = np.abs(cells[i, 24:72, j, 32:64] - bg).sum(-1) > 6  # the centre of a cell shows the head
            assert head.mean() > 0.8, (i, j)  # (the back of dark hair in front light is close to the background)
            assert (np.abs(cells[i, :, j, :8] - bg).sum(-1) <= 6).mean() > 0.9  # and the border is background
    sunset, studio = cells[1, 24:72, 0, 32:64], cells[0, 24:72, 0, 32:64]
    assert sunset[..., 0].mean() / sunset[..., 2].mean() > 1.2 * studio[..., 0].mean() / studio[..., 2].mean()  # warm light
    assert not np.array_equal(cells[0, :, 0], cells[0, :, 1])  # the turntable turned


def test_light_direction_convention(avatar, tmp_path):
    """--light 90,0: from the subject's left, which the camera sees on the image's right."""
    sides = {}
    for az in (90, -90):
        out = tmp_path / f"az{az}.png"
        r = CliRunner().invoke(main, ["render", str(avatar), "-o", str(out), "--env", "dramatic", "--light", f"{az},0,2",
                                      "--size", "96", "--turntable", "1", "--no-labels", "--threads", "1"])
        assert r.exit_code == 0, r.output
        img = _read(out)
        assert img.shape == (2 * 96, 96, 3)  # dramatic + the custom row
        face = img[96 + 30:96 + 66]
        sides[az] = face[:, 52:70].mean() - face[:, 26:44].mean()  # right half minus left half
    assert sides[90] > 10 and sides[-90] < -10


def test_expression_changes_the_mouth(avatar, tmp_path):
    imgs = {}
    for name, expr in (("neutral", "neutral"), ("open", "jawOpen=1.0,mouthSmileLeft=0.5")):
        out = tmp_path / f"{name}.png"
        r = CliRunner().invoke(main, ["render", str(avatar), "-o", str(out), "--env", "studio", "--expression", expr,
                                      "--size", "128", "--turntable", "1", "--no-labels", "--threads", "1"])
        assert r.exit_code == 0, r.output
        imgs[name] = _read(out)
    diff = np.abs(imgs["open"] - imgs["neutral"]).sum(-1)
    assert diff[70:100].mean() > 3 * diff[10:40].mean()  # the lower face moves, the crown barely


@pytest.mark.parametrize("args, message", [
    (["--env", "moon"], "unknown environment moon"),
    (["--expression", "jawOpn=0.5"], "did you mean jawOpen"),
    (["--expression", "jawOpen=abc"], "must be a number"),
    (["--expression", "jawOpen=1.5"], "must be in [0, 1]"),
    (["--expression", "jawOpen"], "NAME=VALUE"),
    (["--light", "10,20,30,40"], "2 or 3 finite numbers"),
    (["--light", "10,120"], "elevation"),
    (["--turntable", "0"], "turntable"),
])
def test_bad_options_are_usage_errors(avatar, tmp_path, args, message):
    out = tmp_path / "x.png"
    r = CliRunner().invoke(main, ["render", str(avatar), "-o", str(out), *args])
    assert r.exit_code == 2, r.output
    assert message in r.output
    assert not out.exists()


def test_bad_avatar_and_output_paths(avatar, tmp_path):
    r = CliRunner().invoke(main, ["render", str(tmp_path / "nope"), "-o", str(tmp_path / "a.png")])
    assert r.exit_code == 23 and "not an avatar directory" in r.output
    r = CliRunner().invoke(main, ["render", str(avatar), "-o", str(avatar / "sheet.png")])
    assert r.exit_code == 17 and "inside the avatar directory" in r.output
    assert not (avatar / "sheet.png").exists()
    r = CliRunner().invoke(main, ["render", str(avatar), "-o", str(tmp_path / "a.bmp")])
    assert r.exit_code == 2 and ".png or .jpg" in r.output
    existing = tmp_path / "old.png"
    existing.write_bytes(b"old")
    r = CliRunner().invoke(main, ["render", str(avatar), "-o", str(existing), *QUICK])
    assert r.exit_code == 17 and "--force" in r.output and existing.read_bytes() == b"old"
    r = CliRunner().invoke(main, ["render", str(avatar), "-o", str(existing), "--env", "studio", "--force", *QUICK])
    assert r.exit_code == 0, r.output
    assert existing.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_parsers():
    from fitme_cli.export.render import (ENVIRONMENTS, PHOTO_ENVIRONMENT, parse_environments, parse_expression, parse_light,
                                         turntable_yaws)

    names = ["jawOpen", "mouthSmileLeft", "eyeBlinkLeft"]
    assert parse_expression("neutral", names).tolist() == [0, 0, 0]
    assert parse_expression("jawOpen=0.5, eyeBlinkLeft=1", names).tolist() == [0.5, 0, 1]
    assert parse_expression("fitted", names, np.array([0.1, 0.2, 0.3])).tolist() == [0.1, 0.2, 0.3]
    with pytest.raises(ValueError, match="unknown expression"):
        parse_expression("smile=1", names)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        parse_expression("jawOpen=nan", names)
    lt = parse_light("90,0,2")
    assert np.allclose(lt.direction, (1, 0, 0), atol=1e-12) and lt.colour == (2, 2, 2)
    assert np.allclose(parse_light("0,90").direction, (0, 1, 0), atol=1e-12)
    assert parse_environments("all") == (*ENVIRONMENTS, PHOTO_ENVIRONMENT)
    assert parse_environments("sunset,studio,sunset") == ("sunset", "studio")
    assert turntable_yaws(4) == [0, 90, 180, 270]
