"""Is a BRDF-GAN candidate worth shipping? Its card next to the shipped one's, and what each does to
fits of real photos: FaceNet similarity (the evaluation network) of the three sample photos to the
render of their fit, the fits' landmark error and their seconds per fit, per preset. Prints a Markdown table.

A better card alone is not enough: the 107 kimg state (2026-11-25) had a Fréchet distance of 0.055
against the shipped 92 kimg model's 0.063 and fitted the sample photos worse (docs/brdf_gan.md).

    python -m fitme_cli.reflectance.gan.report RUN_DIR DATA_DIR -o CAND_DIR --truncation-psi 0.5
    python benchmarks/gan_candidate.py CAND_DIR [--presets fast,default] [--threads 2] [--members 3] [--data-subjects 4]

Each model runs in its own process; on 2 cores the whole comparison takes ~50 s at the fast preset
and ~4 min with the default preset added (fits of 6 s and 35 s), times ``--members``.

One fit per photo is chaotic: the three-photo mean at the default preset moved by up to 0.07 between 1
and 2 threads (2026-11-25). ``--members M`` fits each photo M times (member 0 and M - 1 starts nudged by
1e-5, as the regression run's) and reports each photo's median.

Likeness to a photo also rewards light baked into the albedo, which a relightable avatar must not have, and no
sample photo has a true albedo. ``--data-subjects N`` adds N held-out data subjects (``fitme bench --reflectance
data``: procedural maps no generator trained on, one frontal view, photo-like): each model fits the same ones, and
the table gives the median albedo Delta E against the truth (before and after a per-channel gain: the light's
scale), the landmark error and FaceNet, over subjects x members.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

def _signed(m: dict, key: str) -> str:
    """Relative difference of the GAN's mean or std to the data's, signed, in %."""
    d, g = m[f"data_{key}"], m[f"gan_{key}"]
    return f"{100 * (g - d) / abs(d):+.0f}"


def card_rows(card: dict) -> dict[str, str]:
    m = card["metrics"]
    pc = m["per_channel"]
    fr = m["frechet_reflectance_features"]
    psi = card["sampling"]["truncation_psi"]
    # a card sampled at psi 1 has one set of metrics; one sampled below keeps the psi 1 set beside it
    psi1 = fr if psi == 1 else card.get("metrics_truncation_psi_1", {}).get("frechet_reflectance_features", {})
    mod = m["modality_consistency"]
    interp = m["interpolation_max_over_mean_step"]
    albedo = [c for c in pc if c.startswith("albedo_")]  # the card's channel names, in its order
    normals = [c for c in pc if c.startswith("normal_")]
    scale = m.get("std_ratio_by_scale")  # cards written before 2026-11-25 lack it
    return {
        "kimg": f"{card['training']['kimg']:g}",
        "albedo r/g/b mean %": " / ".join(_signed(pc[c], "mean") for c in albedo),
        "albedo r/g/b std %": " / ".join(_signed(pc[c], "std") for c in albedo),
        "specular mean / std %": f"{_signed(pc['specular'], 'mean')} / {_signed(pc['specular'], 'std')}",
        "normals x/y/z std %": " / ".join(_signed(pc[c], "std") for c in normals),
        "albedo r/g/b fine-grain std, × data": " / ".join(f"{scale[c]['fine']:.2f}" for c in albedo) if scale else "–",
        # keys must not depend on the card: two cards at different psi share one table
        "sampling ψ": f"{psi:g}",
        "Fréchet at the card's ψ (tone, detail); half vs half":
            f"{fr['gan_vs_heldout_half']:.3f} ({fr['by_part']['tone']['gan_vs_heldout_half']:.3f}, "
            f"{fr['by_part']['detail']['gan_vs_heldout_half']:.3f}); {fr['half_vs_half']:.3f}",
        "Fréchet at ψ 1": f"{psi1['gan_vs_heldout_half']:.3f}" if psi1 else "–",
        f"modality link (data {mod['data_matched']:.3f})": f"{mod['gan_matched']:+.3f}",
        "interpolation median (max)": f"{interp['median']:.2f} ({interp['max']:.2f})",
    }


def median_sims(runs: list[dict[str, float]]) -> dict[str, float]:
    """Each photo's median over the members' runs ({photo: similarity or landmark error} each, same photos)."""
    import numpy as np

    if not runs or any(set(r) != set(runs[0]) for r in runs):
        raise ValueError(f"median_sims: expected runs over the same photos, got {[sorted(r) for r in runs]}")
    return {k: float(np.median([r[k] for r in runs])) for k in runs[0]}


def preset_rows(preset: str, result: dict, members: int) -> dict[str, str]:
    """Table rows of one model's fits at one preset (a worker's JSON line): each photo's median likeness and their
    mean, each photo's median landmark error, and the median seconds per fit, so that a candidate's cost in time
    shows beside its accuracy (a wider G fits slower: docs/brdf_gan.md)."""
    import numpy as np

    sims, med = result["sims"], f", median of {members}" if members > 1 else ""
    rows = {f"{preset} preset{med}: {' / '.join(sims)}, mean":
            " / ".join(f"{v:.2f}" for v in sims.values()) + f", **{float(np.mean(list(sims.values()))):.3f}**"}
    rows[f"{preset} preset: landmark px, median per photo"] = " / ".join(f"{result['landmark_px'][k]:.1f}" for k in sims)
    rows[f"{preset} preset: s per fit, median"] = f"{float(np.median(result['fit_s'])):.1f}"
    return rows


def subject_rows(preset: str, fits: list[dict[str, float]]) -> dict[str, str]:
    """Table rows of one model's fits of the held-out data subjects at one preset: medians over subjects x members."""
    import numpy as np

    med = {k: float(np.median([f[k] for f in fits])) for k in ("delta_e", "delta_e_gain", "landmark_px", "sim")}
    return {f"{preset} preset, {len(fits)} fits of held-out data subjects: albedo ΔE (after gain), median":
            f"**{med['delta_e']:.2f}** ({med['delta_e_gain']:.2f})",
            f"{preset} preset, held-out data subjects: landmark px / FaceNet, median":
            f"{med['landmark_px']:.2f} / {med['sim']:.3f}"}


def _worker(presets: list[str], threads: int, members: int, subjects: Path | None) -> None:
    """In a process whose FITME_MODELS_DIR is the model under test: one JSON line per preset."""
    import torch

    torch.set_num_threads(threads)
    from fitme_cli.bench.dataset import list_subjects, load_subject
    from fitme_cli.bench.realphotos import collect_photos, run_real_photos
    from fitme_cli.bench.run import FitSettings, fit_photos, load_models

    models, photos = load_models(), collect_photos(None)
    for preset in presets:
        runs, landmarks, secs, fits = [], [], [], []
        for m in range(members):
            settings = FitSettings.from_preset(preset).member(m, 1e-5)
            res = run_real_photos(models, photos, settings)
            runs.append({r.photo: r.render_sim for r in res})
            landmarks.append({r.photo: r.landmark_px for r in res})
            secs += [r.fit_s for r in res]
            for d in list_subjects(subjects) if subjects else []:
                truth = load_subject(d).views([0])
                try:
                    x = fit_photos([truth.photos[0]], models, settings, truth.focal_35mm, truth).metrics
                finally:
                    models.restore_generator()
                fits.append({"subject": d.name, "member": m, "delta_e": x.albedo_delta_e,
                             "delta_e_gain": x.albedo_delta_e_gain, "landmark_px": x.landmark_px, "sim": x.identity_sim})
        print(json.dumps({"preset": preset, "sims": median_sims(runs), "members": runs,
                          "landmark_px": median_sims(landmarks), "fit_s": secs, "subjects": fits}), flush=True)


def _models_with(candidate: Path, shipped: Path, out: Path) -> Path:
    """A models folder: every shipped file linked, brdf_gan.{safetensors,json} from the candidate."""
    out.mkdir()
    for f in shipped.iterdir():
        if not f.name.startswith("brdf_gan."):
            (out / f.name).symlink_to(f.resolve())
    for name in ("brdf_gan.safetensors", "brdf_gan.json"):
        (out / name).symlink_to((candidate / name).resolve())
    return out


def _fit_photos(models_dir: Path, presets: list[str], threads: int, members: int,
                subjects: Path | None) -> dict[str, dict]:
    env = dict(os.environ, FITME_MODELS_DIR=str(models_dir))
    proc = subprocess.run([sys.executable, __file__, "--worker", ",".join(presets), "--threads", str(threads),
                           "--members", str(members)] + (["--subjects-dir", str(subjects)] if subjects else []),
                          env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"fits with {models_dir} failed:\n{proc.stderr[-2000:]}")
    rows = [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]
    return {r["preset"]: r for r in rows}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("candidate", type=Path, nargs="?", help="folder with the candidate's brdf_gan.{safetensors,json}")
    ap.add_argument("--presets", default="fast,default")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--members", type=int, default=1, help="fits per photo; each photo's median is reported")
    ap.add_argument("--data-subjects", type=int, default=0, help="held-out data subjects each model also fits")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--subjects-dir", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args()
    presets = [p for p in (args.worker or args.presets).split(",") if p]
    if args.worker:
        _worker(presets, args.threads, args.members, args.subjects_dir)
        return
    from fitme_cli.perception.store import models_dir

    shipped = models_dir()
    cand = args.candidate
    if args.members < 1:
        ap.error(f"--members must be >= 1, got {args.members}")
    if cand is None or not (cand / "brdf_gan.safetensors").is_file() or not (cand / "brdf_gan.json").is_file():
        ap.error(f"expected a folder with brdf_gan.safetensors and brdf_gan.json, got {cand}")
    cards = {"shipped": json.loads((shipped / "brdf_gan.json").read_text()),
             "candidate": json.loads((cand / "brdf_gan.json").read_text())}
    if args.data_subjects < 0:
        ap.error(f"--data-subjects must be >= 0, got {args.data_subjects}")
    with tempfile.TemporaryDirectory() as tmp:
        subjects = None
        if args.data_subjects:  # the same subjects for both models: their maps do not come from either
            from fitme_cli.bench.dataset import BenchSetSettings, make_bench_set

            subjects = Path(tmp) / "subjects"
            make_bench_set(subjects, BenchSetSettings(n_subjects=args.data_subjects, n_views=1, reflectance="data"))
        fits = {"shipped": _fit_photos(shipped, presets, args.threads, args.members, subjects),
                "candidate": _fit_photos(_models_with(cand, shipped, Path(tmp) / "models"), presets, args.threads,
                                         args.members, subjects)}
    print(json.dumps(fits), file=sys.stderr)  # minutes of fits: keep them even if the table fails
    rows = {k: card_rows(c) for k, c in cards.items()}
    for p in presets:
        for k in fits:
            rows[k].update(preset_rows(p, fits[k][p], args.members))
            if fits[k][p]["subjects"]:
                rows[k].update(subject_rows(p, fits[k][p]["subjects"]))
    print("| | shipped | candidate |\n|---|---|---|")
    for key in dict.fromkeys([*rows["shipped"], *rows["candidate"]]):
        print(f"| {key} | {rows['shipped'].get(key, '–')} | {rows['candidate'].get(key, '–')} |")


if __name__ == "__main__":
    main()
