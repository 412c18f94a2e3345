"""`fitme fit` and `fitme tune` end to end on sample photos (few iterations), the avatar directory, and errors."""

import json

import numpy as np
import pytest
from click.testing import CliRunner

from fitme_cli.cli import main

QUICK = ["--preset", "fast", "--iterations", "3", "--render-size", "128", "--threads", "2"]


@pytest.fixture(scope="module")
def photos(tmp_path_factory, models_root):
    from fitme_cli.io.images import write_sample_photo

    d = tmp_path_factory.mktemp("photos")
    return {n: write_sample_photo(n, d / f"{n}.jpg") for n in ("astronaut", "grace_hopper")}


@pytest.fixture(scope="module")
def avatar(photos, tmp_path_factory):
    out = tmp_path_factory.mktemp("fit") / "avatar"
    r = CliRunner().invoke(main, ["fit", str(photos["astronaut"]), "-o", str(out), *QUICK, "--tune-iterations", "1"])
    assert r.exit_code == 0, r.output
    return out, r.output


def test_fit_writes_the_documented_avatar_directory(avatar):
    import cv2
    from safetensors.torch import load_file

    out, output = avatar
    rep = json.loads((out / "avatar.json").read_text())
    assert rep["schema"] == "1.2" and rep["settings"]["preset"] == "fast"
    (inp,) = rep["inputs"]
    assert len(inp["sha256"]) == 64 and inp["name"] == "astronaut" and inp["size"] == [512, 512]
    q = inp["quality"]
    assert -1 <= q["identity_similarity"] <= 1 and 0 <= q["landmark_error_px"] < 30
    assert set(rep["timings"]) >= {"detect_s", "invert_s", "tune_s", "write_s", "total_s", "peak_memory_mib"}
    assert len(rep["history"]["inversion"]) == 3 and len(rep["history"]["tuning"]) == 1
    assert np.isfinite(rep["final_losses"]["inversion"]["total"]) and rep["final_losses"]["tuning"] is not None
    assert rep["effects"]["chosen"] == ["specular", "subsurface"]  # fast: no selector, the base effects
    for kind in ("albedo", "specular", "normals"):
        for ext in ("png", "exr"):
            assert (out / "maps" / f"avatar_{kind}.{ext}").is_file()
    params = load_file(str(out / "params.safetensors"))
    assert params["ws"].ndim == 3 and params["camera_rotation"].shape == (1, 3, 3) and params["p_e"].shape[0] == 1
    assert params["photo_crop"].shape == (1, 128, 128, 3)
    assert params["fitted_vertices"].shape[0] == 1 and params["fitted_vertices"].shape[2] == 3
    from fitme_cli.fitting.invert import InversionSettings

    assert params["noise_gain"].tolist() == [InversionSettings().noise_gain]  # what the maps were made with
    assert load_file(str(out / "generator_tuned.safetensors"))  # the tuned layers
    ph = out / "photos" / "astronaut"
    assert cv2.imread(str(ph / "panel.png")).shape == (128, 4 * 128, 3)
    lm = json.loads((ph / "landmarks68.json").read_text())
    assert np.array(lm["fitted"]).shape == (68, 2) and np.array(lm["detected"]).shape == (68, 2)
    verts = [ln for ln in (ph / "mesh_camera.obj").read_text().splitlines() if ln.startswith("v ")]
    z = np.array([float(v.split()[3]) for v in verts])
    assert len(verts) == 12409 or len(verts) > 10000
    assert 200 < np.median(z) < 3000  # in front of the camera, in mm
    assert cv2.imread(str(out / "loss_curve.png")) is not None
    assert "identity similarity" in output and "peak memory" in output
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".")]  # no staging left behind


def test_fit_refuses_a_non_empty_directory_and_replaces_it_atomically_with_force(avatar, photos, monkeypatch):
    out, _ = avatar
    r = CliRunner().invoke(main, ["fit", str(photos["astronaut"]), "-o", str(out), *QUICK])
    assert r.exit_code == 17 and "--force" in r.output
    before = (out / "avatar.json").read_bytes()
    import fitme_cli.fitting.outputs as outputs

    def broken(*a, **k):
        raise KeyboardInterrupt  # a Ctrl-C while the new avatar is being written

    monkeypatch.setattr(outputs, "write_avatar", broken)
    r = CliRunner().invoke(main, ["fit", str(photos["astronaut"]), "-o", str(out), *QUICK, "--force"])
    assert r.exit_code == 130
    assert (out / "avatar.json").read_bytes() == before  # the old avatar, untouched
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".")]


def test_tune_continues_on_the_avatar(avatar, tmp_path):
    import shutil

    from safetensors.torch import load_file

    from fitme_cli.fitting.invert import InversionSettings

    src, _ = avatar
    out = tmp_path / "copy"
    shutil.copytree(src, out)
    layers0 = load_file(str(out / "generator_tuned.safetensors"))
    r = CliRunner().invoke(main, ["tune", str(out), "--iterations", "2", "--threads", "2"])
    assert r.exit_code == 0, r.output
    rep = json.loads((out / "avatar.json").read_text())
    assert len(rep["history"]["tuning"]) == 3 and rep["settings"]["tune_iterations"] == 3
    layers1 = load_file(str(out / "generator_tuned.safetensors"))
    assert set(layers1) == set(layers0) and any(not np.array_equal(layers0[k], layers1[k]) for k in layers0)
    assert rep["history"]["inversion"] == json.loads((src / "avatar.json").read_text())["history"]["inversion"]
    assert load_file(str(out / "params.safetensors"))["noise_gain"].tolist() == load_file(str(src / "params.safetensors"))["noise_gain"].tolist()
    # an avatar from before noise_gain (schema 1.0) was fitted at full noise, and reads so
    from safetensors.torch import save_file

    from fitme_cli.fitting.avatar import load_avatar

    old = tmp_path / "old"
    shutil.copytree(src, old)
    params = load_file(str(old / "params.safetensors"))
    del params["noise_gain"]
    save_file(params, str(old / "params.safetensors"))
    assert load_avatar(old).inversion.noise_gain == 1.0 and load_avatar(src).inversion.noise_gain == InversionSettings().noise_gain
    # not an avatar: clear errors
    r = CliRunner().invoke(main, ["tune", str(tmp_path / "nope")])
    assert r.exit_code == 23 and "not an avatar" in r.output
    (tmp_path / "empty").mkdir()
    r = CliRunner().invoke(main, ["tune", str(tmp_path / "empty")])
    assert r.exit_code == 23 and "avatar.json" in r.output
    (out / "params.safetensors").write_bytes(b"garbage")
    r = CliRunner().invoke(main, ["tune", str(out)])
    assert r.exit_code == 23 and "unreadable" in r.output


def test_tune_refuses_an_avatar_whose_w_another_generator_would_turn_into_other_maps(avatar, tmp_path):
    import shutil

    from fitme_cli.io.maps import read_map, write_map

    src, _ = avatar
    out = tmp_path / "copy"
    shutil.copytree(src, out)
    # what models/brdf_gan.safetensors being replaced looks like from inside: W no longer makes these maps
    path = out / "maps" / "avatar_albedo.exr"
    write_map(path, (read_map(path).linear * 0.97).astype(np.float32), "exr16")
    before = (out / "params.safetensors").read_bytes()
    r = CliRunner().invoke(main, ["tune", str(out), "--iterations", "1", "--threads", "2"])
    assert r.exit_code == 26, r.output  # ModelMismatch
    assert "not the generator this avatar was fitted with" in r.output and "Traceback" not in r.output
    assert (out / "params.safetensors").read_bytes() == before  # untouched


def test_fit_is_deterministic_with_a_seed(photos, tmp_path):
    """Bit-identical on one thread; with more, torch's parallel reductions reorder float sums (measured
    differences up to 1e-6 after 2 iterations), so the CLI test pins --threads 1."""
    import torch
    from safetensors.torch import load_file

    threads = torch.get_num_threads()
    outs = []
    for k in range(2):
        out = tmp_path / f"a{k}"
        r = CliRunner().invoke(main, ["fit", str(photos["astronaut"]), "-o", str(out), *QUICK, "--iterations", "2",
                                      "--seed", "3", "--threads", "1"])
        assert r.exit_code == 0, r.output
        outs.append(load_file(str(out / "params.safetensors")))
    torch.set_num_threads(threads)
    assert all(np.array_equal(outs[0][k], outs[1][k]) for k in outs[0])


def test_fit_skips_a_bad_photo_and_refuses_different_people(photos, tmp_path):
    out = tmp_path / "a"
    r = CliRunner().invoke(main, ["fit", str(photos["astronaut"]), str(tmp_path / "missing.jpg"), "-o", str(out),
                                  *QUICK, "--iterations", "2", "--noise-gain", "1"])
    assert r.exit_code == 10 and "skipped" in r.output and (out / "avatar.json").is_file()
    rep = json.loads((out / "avatar.json").read_text())
    assert len(rep["inputs"]) == 1
    from safetensors.torch import load_file

    assert rep["settings"]["inversion"]["noise_gain"] == 1.0 and load_file(str(out / "params.safetensors"))["noise_gain"].tolist() == [1.0]
    r = CliRunner().invoke(main, ["fit", str(photos["astronaut"]), str(photos["grace_hopper"]), "-o", str(tmp_path / "b"),
                                  *QUICK, "--iterations", "2"])
    assert r.exit_code == 24 and "different people" in r.output and not (tmp_path / "b").exists()


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
    r = CliRunner().invoke(main, ["fit", str(blank), "-o", str(tmp_path / "c"), "--noise-gain", "1.5"])
    assert r.exit_code == 2 and "--noise-gain" in r.output
    r = CliRunner().invoke(main, ["fit", str(blank), "-o", str(tmp_path / "d"), "--device", "cuda:7"])
    import torch

    if not torch.cuda.is_available():
        assert r.exit_code == 25 and "CUDA" in r.output
    r = CliRunner().invoke(main, ["fit", str(blank), "-o", str(blank)])
    assert r.exit_code == 17
    # --force replaces an avatar, never a directory of other files
    docs = tmp_path / "documents"
    docs.mkdir()
    (docs / "thesis.tex").write_text("precious")
    r = CliRunner().invoke(main, ["fit", str(blank), "-o", str(docs), "--force"])
    assert r.exit_code == 17 and "not an avatar" in r.output and (docs / "thesis.tex").read_text() == "precious"
