"""Settings variants and running them: one child process per variant (``python -m fitme_cli.bench.sweep``)
fits every benchmark subject with that variant, so the peak memory reported (the child's
``ru_maxrss``) is that variant's own: the largest of its fits, plus the interpreter, torch and the
models (~the floor every real ``fitme fit`` pays too). Fit time is measured inside the child around
detect + invert + tune, so model loading and process start-up are not counted."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path

__all__ = ["Variant", "RunResult", "variants", "run_variant", "run_sweep", "fit_case"]


@dataclass(frozen=True)
class Variant:
    """One point of the sweep: a preset, optionally with one setting changed, on 1 or 3 views."""

    name: str
    preset: str = "fast"
    views: int = 1
    iterations: int | None = None  # None: the preset's
    render_size: int | None = None
    coarse_resolution: int | None = None  # the map resolution of the coarse phase (the generator stops there)
    coarse_fraction: float | None = None
    tune_iterations: int | None = None
    forced_effects: tuple[tuple[str, bool], ...] = ()

    def __post_init__(self) -> None:
        if self.views not in (1, 3):
            raise ValueError(f"Variant.views must be 1 or 3, got {self.views}")
        if self.preset not in ("fast", "default", "best"):
            raise ValueError(f"Variant.preset must be fast, default or best, got {self.preset!r}")

    def settings(self):
        from .run import FitSettings

        over = {k: v for k, v in (("iterations", self.iterations), ("render_size", self.render_size),
                                  ("coarse_resolution", self.coarse_resolution), ("coarse_fraction", self.coarse_fraction),
                                  ("tune_iterations", self.tune_iterations)) if v is not None}
        return FitSettings.from_preset(self.preset, forced_effects=tuple(self.forced_effects), **over)

    @staticmethod
    def from_dict(d: dict) -> Variant:
        d = dict(d)
        d["forced_effects"] = tuple(tuple(x) for x in d.get("forced_effects", ()))
        return Variant(**d)


def variants(quick: bool) -> list[Variant]:
    """The presets and the single-setting changes, each relative to the fast preset (30 iterations at
    128^2 on full maps, no effect selection: specular and subsurface on, 20 tuning iterations); every change row
    must change the settings (tested: the coarse-map rows once set a resolution for a coarse phase
    the fast preset no longer had)."""
    coarse = [Variant(f"coarse 40 % at {r}²", coarse_fraction=0.4, coarse_resolution=r) for r in (64, 128)]
    old_default = Variant("preset default, coarse 40 % at 128²", "default", coarse_fraction=0.4, coarse_resolution=128)
    v = [Variant("preset fast"), Variant("preset default", "default")]
    if quick:
        return v + [Variant("iterations 20", iterations=20), coarse[1],
                    Variant("render 256", render_size=256), Variant("-specular", forced_effects=(("specular", False),)),
                    Variant("+shadows", forced_effects=(("shadows", True),)), Variant("no tuning", tune_iterations=0),
                    Variant("preset fast, 3 views", views=3)]
    v += [old_default, Variant("preset best", "best")]
    v += [Variant(f"iterations {n}", iterations=n) for n in (20, 100, 200)]
    v += [Variant(f"render {r}", render_size=r) for r in (256, 384)]
    v += coarse
    v += [Variant("-specular", forced_effects=(("specular", False),)), Variant("-subsurface", forced_effects=(("subsurface", False),))]
    v += [Variant(f"+{e}", forced_effects=((e, True),)) for e in ("sh_ambient", "shadows", "multi_light")]
    v += [Variant("no tuning", tune_iterations=0), Variant("tune 10", tune_iterations=10), Variant("tune 40", tune_iterations=40)]
    v += [Variant("preset fast, 3 views", views=3), Variant("preset default, 3 views", "default", views=3)]
    return v


@dataclass(frozen=True)
class RunResult:
    """One fit of one subject with one variant. status: "ok", "no face" (detection found none: a clean
    failure) or "error: ..."; the metrics are NaN unless ok. peak_mib: the variant process's peak so far."""

    variant: str
    subject: str
    views: int
    status: str
    landmark_px: float = math.nan
    shape_mm: float = math.nan
    shape_posed_mm: float = math.nan
    albedo_l1: float = math.nan
    albedo_delta_e: float = math.nan
    albedo_delta_e_gain: float = math.nan
    normals_deg: float = math.nan
    identity_sim: float = math.nan
    photometric: float = math.nan
    fit_s: float = math.nan
    peak_mib: float = math.nan
    repeat: int = 0

    @staticmethod
    def from_dict(d: dict) -> RunResult:
        names = {f.name for f in fields(RunResult)}
        return RunResult(**{k: v for k, v in d.items() if k in names})


def fit_case(models, subject_dir: Path, variant: Variant, repeat: int = 0) -> RunResult:
    """Fit one subject (its first view, or all three) with the variant; a NoFaceFound is recorded, not raised."""
    from ..cli.progress import peak_memory_mib
    from ..errors import NoFaceFound
    from .dataset import load_subject

    truth = load_subject(subject_dir)
    truth = truth.views([0]) if variant.views == 1 else truth.views(list(range(min(3, truth.n_views))))
    try:
        out = fit_photos_for(models, truth, variant)
    except NoFaceFound:
        return RunResult(variant.name, truth.name, variant.views, "no face", peak_mib=peak_memory_mib(), repeat=repeat)
    except Exception as e:  # noqa: BLE001 - a crash is a result the table must show, not the end of the sweep
        return RunResult(variant.name, truth.name, variant.views, f"error: {type(e).__name__}: {e}"[:300],
                         peak_mib=peak_memory_mib(), repeat=repeat)
    m = asdict(out.metrics)
    m.pop("iterations")
    return RunResult(variant.name, truth.name, variant.views, "ok", **m, peak_mib=peak_memory_mib(), repeat=repeat)


def fit_photos_for(models, truth, variant: Variant):
    from .run import fit_photos

    return fit_photos(list(truth.photos), models, variant.settings(), truth.focal_35mm, truth)


def _child(spec_path: Path, out_path: Path) -> None:
    import torch

    from ..ops.memory import retain_freed_memory

    retain_freed_memory()  # as `fitme fit` does
    spec = json.loads(Path(spec_path).read_text())
    torch.set_num_threads(int(spec["threads"]))
    from .run import load_models

    models = load_models()
    variant = Variant.from_dict(spec["variant"])
    res = [asdict(fit_case(models, Path(d), variant, r)) for r in range(int(spec["repeats"])) for d in spec["subjects"]]
    Path(out_path).write_text(json.dumps(res, indent=1) + "\n")


def run_variant(variant: Variant, subjects: list[Path], work: Path, threads: int = 1, repeats: int = 1,
                timeout_s: float | None = None) -> list[RunResult]:
    """Run the variant in a child process over ``subjects``; a child that dies is recorded per subject."""
    import os

    work.mkdir(parents=True, exist_ok=True)
    slug = "".join(c if c.isalnum() else "_" for c in variant.name)
    spec, out = work / f"{slug}.spec.json", work / f"{slug}.results.json"
    spec.write_text(json.dumps({"variant": asdict(variant), "subjects": [str(s) for s in subjects], "threads": threads,
                                "repeats": repeats}))
    out.unlink(missing_ok=True)
    env = os.environ | {"OMP_NUM_THREADS": str(threads)}  # else OpenMP spins on every core
    try:
        r = subprocess.run([sys.executable, "-m", "fitme_cli.bench.sweep", str(spec), str(out)], capture_output=True,
                           text=True, env=env, timeout=timeout_s)
        err = None if r.returncode == 0 and out.exists() else f"error: child exit {r.returncode}: {r.stderr[-300:]}"
    except subprocess.TimeoutExpired:
        err = f"error: timed out after {timeout_s} s"
    if err:
        return [RunResult(variant.name, Path(s).name, variant.views, err) for s in subjects]
    return [RunResult.from_dict(d) for d in json.loads(out.read_text())]


def run_sweep(vs: list[Variant], subjects: list[Path], work: Path, threads: int = 1, repeats: int = 1,
              log=print) -> list[RunResult]:
    results: list[RunResult] = []
    for v in vs:
        t = time.perf_counter()
        rs = run_variant(v, subjects, work, threads, repeats)
        ok = [r for r in rs if r.status == "ok"]
        log(f"bench: {v.name}: {len(ok)}/{len(rs)} ok in {time.perf_counter() - t:.0f} s")
        results += rs
    return results


if __name__ == "__main__":
    _child(Path(sys.argv[1]), Path(sys.argv[2]))
