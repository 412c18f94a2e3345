"""benchmarks/gan_candidate.py: the card table and the candidate's models folder (the fits themselves take
minutes and are what the script is run for, not tested here)."""

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "benchmarks" / "gan_candidate.py"


@pytest.fixture(scope="module")
def gc():
    spec = importlib.util.spec_from_file_location("gan_candidate", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _card(albedo_r_gan_mean=0.22, frechet=0.055):
    ch = {k: {"data_mean": 0.2, "gan_mean": 0.2, "data_std": 0.1, "gan_std": 0.1}
          for k in ("albedo_r", "albedo_g", "albedo_b", "specular", "normal_x", "normal_y", "normal_z")}
    ch["albedo_r"]["gan_mean"] = albedo_r_gan_mean
    ch["normal_z"]["gan_std"] = 0.08
    fr = {"gan_vs_heldout_half": frechet, "half_vs_half": 0.002,
          "by_part": {"tone": {"gan_vs_heldout_half": 0.03}, "detail": {"gan_vs_heldout_half": 0.02}}}
    return {"training": {"kimg": 107.0}, "sampling": {"truncation_psi": 0.5},
            "metrics": {"per_channel": ch, "frechet_reflectance_features": fr,
                        "modality_consistency": {"gan_matched": -0.06, "data_matched": 0.376},
                        "interpolation_max_over_mean_step": {"median": 1.169, "max": 1.429}}}


def test_card_rows_sign_the_differences_to_the_data(gc):
    rows = gc.card_rows(_card())
    assert rows["kimg"] == "107"
    assert rows["albedo r/g/b mean %"] == "+10 / +0 / +0"
    assert rows["normals x/y/z std %"] == "+0 / +0 / -20"
    assert rows["sampling ψ"] == "0.5"
    assert rows["Fréchet at the card's ψ (tone, detail); half vs half"] == "0.055 (0.030, 0.020); 0.002"
    assert rows["Fréchet at ψ 1"] == "–"  # this ψ 0.5 card kept no ψ 1 set
    psi1 = _card(frechet=0.028)
    psi1["sampling"]["truncation_psi"] = 1.0
    rows1 = gc.card_rows(psi1)
    assert rows1.keys() == rows.keys()  # cards at different ψ share one table
    assert rows1["Fréchet at ψ 1"] == "0.028" and rows1["sampling ψ"] == "1"
    assert rows["modality link (data 0.376)"] == "-0.060"
    assert rows["interpolation median (max)"] == "1.17 (1.43)"
    assert rows["albedo r/g/b fine-grain std, × data"] == "–"  # an older card without the std by scale
    card = _card()
    card["metrics"]["std_ratio_by_scale"] = {c: {"between": 1.0, "coarse": 1.0, "fine": f}
                                             for c, f in (("albedo_r", 1.384), ("albedo_g", 1.5), ("albedo_b", 0.9))}
    assert gc.card_rows(card)["albedo r/g/b fine-grain std, × data"] == "1.38 / 1.50 / 0.90"


def test_the_shipped_card_has_every_row(gc):
    rows = gc.card_rows(json.loads((REPO / "models" / "brdf_gan.json").read_text()))
    assert len(rows) == 11 and all(v and v != "nan" and v != "–" for v in rows.values())


def test_models_folder_takes_the_gan_from_the_candidate_and_the_rest_from_the_shipped(gc, tmp_path):
    shipped, cand = tmp_path / "shipped", tmp_path / "cand"
    shipped.mkdir(), cand.mkdir()
    for name in ("facenet.onnx", "brdf_gan.safetensors", "brdf_gan.json", "brdf_gan.wprior.safetensors"):
        (shipped / name).write_text("shipped " + name)
    for name in ("brdf_gan.safetensors", "brdf_gan.json"):
        (cand / name).write_text("candidate " + name)
    out = gc._models_with(cand, shipped, tmp_path / "models")
    assert sorted(p.name for p in out.iterdir()) == ["brdf_gan.json", "brdf_gan.safetensors", "facenet.onnx"]
    assert (out / "facenet.onnx").read_text() == "shipped facenet.onnx"
    assert (out / "brdf_gan.safetensors").read_text() == "candidate brdf_gan.safetensors"
    # the shipped W prior is derived from the shipped generator: the candidate derives its own


def test_a_folder_without_a_candidate_is_refused(tmp_path):
    r = subprocess.run([sys.executable, str(SCRIPT), str(tmp_path)], capture_output=True, text=True)
    assert r.returncode == 2 and "expected a folder with brdf_gan.safetensors and brdf_gan.json" in r.stderr


def test_median_sims_per_photo_and_same_photos_only(gc):
    runs = [{"astronaut": 0.3, "a": 0.9}, {"astronaut": 0.5, "a": 0.1}, {"astronaut": 0.4, "a": 0.2}]
    assert gc.median_sims(runs) == {"astronaut": 0.4, "a": 0.2}
    assert gc.median_sims(runs[:1]) == runs[0]
    with pytest.raises(ValueError, match="same photos"):
        gc.median_sims([{"astronaut": 0.3}, {"b": 0.3}])
    with pytest.raises(ValueError, match="same photos"):
        gc.median_sims([])


def test_bad_member_count_is_refused(tmp_path):
    r = subprocess.run([sys.executable, str(SCRIPT), str(tmp_path), "--members", "0"], capture_output=True, text=True)
    assert r.returncode == 2 and "--members must be >= 1, got 0" in r.stderr


def test_preset_rows_show_likeness_landmarks_and_time(gc):
    result = {"sims": {"astronaut": 0.45, "camera": 0.65}, "landmark_px": {"astronaut": 4.44, "camera": 2.14},
              "fit_s": [38.0, 41.0, 40.0, 39.0]}
    rows = gc.preset_rows("default", result, 3)
    assert rows == {"default preset, median of 3: astronaut / camera, mean": "0.45 / 0.65, **0.550**",
                    "default preset: landmark px, median per photo": "4.4 / 2.1",
                    "default preset: s per fit, median": "39.5"}
    assert list(gc.preset_rows("fast", result, 1))[0] == "fast preset: astronaut / camera, mean"  # one member: no median


def test_subject_rows_take_medians_over_every_fit(gc):
    fits = [{"subject": f"subject_0{i}", "member": 0, "delta_e": de, "delta_e_gain": 2.0 + i, "landmark_px": 2.5,
             "sim": 0.8 + i / 100} for i, de in enumerate((10.0, 4.0, 5.0))]
    rows = gc.subject_rows("default", fits)
    assert rows == {"default preset, 3 fits of held-out data subjects: albedo ΔE (after gain), median": "**5.00** (3.00)",
                    "default preset, held-out data subjects: landmark px / FaceNet, median": "2.50 / 0.810"}


def test_a_negative_subject_count_is_refused(tmp_path):
    for name in ("brdf_gan.safetensors", "brdf_gan.json"):
        (tmp_path / name).write_text("{}")
    r = subprocess.run([sys.executable, str(SCRIPT), str(tmp_path), "--data-subjects", "-1"], capture_output=True, text=True)
    assert r.returncode == 2 and "--data-subjects must be >= 0, got -1" in r.stderr
