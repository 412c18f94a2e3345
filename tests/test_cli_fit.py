"""`fitme fit` end to end on a sample photo (few iterations), and its errors."""

import json

import numpy as np
import pytest
from click.testing import CliRunner

from fitme_cli.cli import main


@pytest.fixture(scope="module")
def photo(tmp_path_factory, models_root):
    from fitme_cli.io.images import write_sample_photo

    return write_sample_photo("astronaut", tmp_path_factory.mktemp("photos") / "astronaut.jpg")


def test_fit_writes_an_avatar(photo, tmp_path):
    out = tmp_path / "avatar"
    r = CliRunner().invoke(main, ["fit", str(photo), "-o", str(out), "--iterations", "3", "--tune-iterations", "1",
                                  "--render-size", "128", "--threads", "2"])
    assert r.exit_code == 0, r.output
    rep = json.loads((out / "avatar.json").read_text())
    assert rep["schema"] == "0.1" and len(rep["inputs"]) == 1 and len(rep["inputs"][0]["sha256"]) == 64
    assert np.isfinite(rep["final_losses"]["inversion"]["total"]) and rep["final_losses"]["tuning"] is not None
    assert set(rep["timings"]) >= {"detect_s", "invert_s", "tune_s", "total_s"}
    for kind in ("albedo", "specular", "normals"):
        for ext in ("png", "exr"):
            assert (out / "maps" / f"avatar_{kind}.{ext}").is_file()
    from safetensors.torch import load_file

    params = load_file(str(out / "params.safetensors"))
    assert params["ws"].ndim == 3 and params["camera_rotation"].shape == (1, 3, 3) and params["p_e"].shape[0] == 1
    import cv2

    assert cv2.imread(str(out / "astronaut.fit.png")).shape == (128, 3 * 128, 3)
    # an existing avatar is not replaced without --force
    r = CliRunner().invoke(main, ["fit", str(photo), "-o", str(out), "--iterations", "1", "--tune-iterations", "0"])
    assert r.exit_code == 17 and "--force" in r.output


def test_fit_errors(tmp_path):
    r = CliRunner().invoke(main, ["fit", str(tmp_path / "missing.jpg"), "-o", str(tmp_path / "a")])
    assert r.exit_code == 10 and "missing.jpg" in r.output
    blank = tmp_path / "blank.png"
    import cv2

    cv2.imwrite(str(blank), np.full((200, 200, 3), 128, np.uint8))
    r = CliRunner().invoke(main, ["fit", str(blank), "-o", str(tmp_path / "b")])
    assert r.exit_code == 16, r.output
    r = CliRunner().invoke(main, ["fit", str(blank), "-o", str(tmp_path / "c"), "--effects", "glitter"])
    assert r.exit_code == 2 and "unknown effect" in r.output
