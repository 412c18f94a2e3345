"""The CI regression run: fit the sample face (the astronaut) and two synthetic subjects at the fast
preset with a small budget, and compare every accuracy metric with a committed baseline JSON.

A 15-iteration fit is chaotic: another CPU's float rounding (AVX2 against AVX-512 kernels, 1 or 2
threads) moves its result as far as a 1e-5 nudge of the starting w does. So each case is fitted
``members`` times, member 0 as is and the others from nudged starts (``FitSettings.member``), and every
metric is the median of the members. A metric regresses when its median is worse than the baseline's
by more than ``max(abs, rel * |baseline|, gain * |start - baseline|)`` (``Tolerance``; "worse" is up for
errors, down for the identity similarity; ``start`` is the same metric after 1 iteration, recorded in
the baseline): the tolerances catch a real loss of accuracy (a broken loss term, a wrong sign or
learning rate: a fit that keeps less than half of what it gains over its start), not chaos.
Improvements never fail: rewrite the baseline on purpose with ``--update-baseline``."""

from __future__ import annotations

import json
import math
import platform
from dataclasses import asdict, dataclass
from pathlib import Path

from .run import METRICS, FitSettings

__all__ = ["RegressSettings", "Tolerance", "TOLERANCES", "Regression", "run_regress", "median_metrics", "compare",
           "write_baseline", "read_baseline", "format_regressions"]


@dataclass(frozen=True)
class Tolerance:
    abs: float
    rel: float = 0.0
    gain: float = 0.0  # share of the fit's gain over its start (baseline vs start) that may be lost

    def allowed(self, baseline: float, start: float | None = None) -> float:
        g = self.gain * abs(start - baseline) if start is not None and math.isfinite(start) else 0.0
        return max(self.abs, self.rel * abs(baseline), g)


# Measured spread of one 15-iteration fit, five members (member 0 and four starts nudged by 1e-5) on one
# AVX2 machine at 1 thread (2026-11-25): synthetic_01's albedo ΔE 3.2 / 3.9 / 4.5 / 8.7 / 17.0 (the
# albedo's scale trades off with the light's: the gained ΔE stays at 2.8-3.8), its landmarks 4.0-8.4 px,
# synthetic_02's 6.8-8.4 px, the astronaut's identity 0.24-0.31. Member 0 alone went from ΔE 2.9 (the
# AVX-512 machine that wrote the previous baseline) to 8.7 here, on the same code. The medians move far
# less; the tolerances absorb what is left, and what they catch is breakage (a dropped loss term, a wrong
# sign or learning rate moves these metrics by multiples, or keeps the fit at its start).
# The identity similarity also moves with the machine in a way nudged starts do not reproduce: the
# baseline's AVX2 machine gave synthetic_01/02 medians of 0.824/0.732, two AVX-512 machines (CI and a
# session's, same code, 1 thread) 0.726-0.736/0.625-0.637, while their own 15 nudged members spread
# only 0.70-0.75/0.59-0.64 (ninth session). Forcing torch, oneDNN, MKL and numba to AVX2 on the AVX-512
# machine did not bring 0.73 back, so the rest is onnxruntime's kernels (the detector's landmarks and
# the identity embedding), which no setting here pins. Hence 0.15 for identity: the fits gain 0.17-0.22
# over their start, so a fit that gains nothing still fails.
TOLERANCES: dict[str, Tolerance] = {
    "landmark_px": Tolerance(1.5, 0.75, 0.5),
    "shape_mm": Tolerance(0.1, 0.25, 0.5),
    "shape_posed_mm": Tolerance(0.1, 0.25, 0.5),
    "albedo_l1": Tolerance(0.01, 0.5, 0.5),
    "albedo_delta_e": Tolerance(1.0, 0.4, 0.5),
    "albedo_delta_e_gain": Tolerance(0.75, 0.4, 0.5),
    "normals_deg": Tolerance(0.05, 0.25, 0.5),
    "identity_sim": Tolerance(0.15, 0.0, 0.5),
    "photometric": Tolerance(2.0, 0.3, 0.5),
}


@dataclass(frozen=True)
class RegressSettings:
    """The regression budget: the fast preset cut to ``iterations``, ``members`` fits per case (medians)."""

    iterations: int = 15
    # subjects the detector finds under the shipped G (125 kimg wide): its seed 1 is not found; seed 2's first
    # z is bearded (make_subject now redraws it, docs/fitting_synthetic.md); new weights, new subjects
    synthetic_seeds: tuple[int, ...] = (3, 4)
    sample_photos: tuple[str, ...] = ("astronaut",)
    synthetic_size: int = 512
    members: int = 5
    jitter: float = 1e-5  # InversionSettings.start_jitter of members 1 ...

    def __post_init__(self) -> None:
        if self.members < 1:
            raise ValueError(f"RegressSettings.members must be >= 1, got {self.members}")
        if self.iterations < 1:
            raise ValueError(f"RegressSettings.iterations must be >= 1, got {self.iterations}")

    def fit_settings(self) -> FitSettings:
        return FitSettings.from_preset("fast", iterations=self.iterations)

    def synthetic_cases(self) -> tuple[str, ...]:
        """The synthetic subjects' case names (``run_regress``'s and the baseline's keys), in seed order."""
        return tuple(f"synthetic_{seed:02d}" for seed in self.synthetic_seeds)

    def as_json(self) -> dict:
        # through JSON, so tuples compare equal to the lists a baseline file reads back as
        return json.loads(json.dumps({"fit": asdict(self.fit_settings()), "synthetic_seeds": list(self.synthetic_seeds),
                "sample_photos": list(self.sample_photos), "synthetic_size": self.synthetic_size,
                "members": self.members, "jitter": self.jitter}))


@dataclass(frozen=True)
class Regression:
    subject: str
    metric: str
    baseline: float
    current: float
    allowed: float  # the tolerance in the metric's unit

    def __str__(self) -> str:
        if not math.isfinite(self.current):
            return f"{self.subject}: {self.metric} missing (baseline {self.baseline:.4g})"
        return (f"{self.subject}: {self.metric} {self.current:.4g} vs baseline {self.baseline:.4g} "
                f"(worse by {abs(self.current - self.baseline):.4g} > allowed {self.allowed:.4g})")


def run_regress(s: RegressSettings = RegressSettings(), models=None, log=lambda msg: None,
                start: bool = False) -> dict[str, dict[str, float]]:
    """Fit every regression case ``s.members`` times; returns {subject: {metric: median}} (NaN where not
    measurable; a subject most of whose fits failed has {"status": ...} only, which ``compare`` reports
    as missing metrics). The cases are regenerated in memory, deterministically: nothing to write.
    ``start``: instead, the metrics after 1 iteration of member 0 (where the fit starts from)."""
    import time
    from dataclasses import replace

    from ..fitting.synthetic import SyntheticSettings, make_subject
    from ..io.images import sample_photo
    from .run import fit_photos, load_models

    models = models or load_models()
    fs = s.fit_settings()
    # the start is where the fit starts from: 1 iteration, and no tuning (the fast preset tunes since the 262.02 kimg G)
    members = [replace(fs, iterations=1, tune_iterations=0)] if start else [fs.member(m, s.jitter) for m in range(s.members)]
    cases = []
    for name in s.sample_photos:
        img = sample_photo(name)
        cases.append((name, [img.rgb], img.focal_length_35mm, None))
    for name, seed in zip(s.synthetic_cases(), s.synthetic_seeds):
        subj = make_subject(models.G, models.shape_model, models.renderer,
                            SyntheticSettings(size=s.synthetic_size, n_views=1, seed=seed))
        cases.append((name, list(subj.photos), subj.settings.focal_35mm, subj))
    out: dict[str, dict[str, float]] = {}
    for name, photos, focal, truth in cases:
        t = time.perf_counter()
        runs = [_metrics(lambda: fit_photos(photos, models, f, focal, truth)) for f in members]
        out[name] = median_metrics(runs)
        log(f"regress: {name}, {len(members)} fit(s) in {time.perf_counter() - t:.1f} s")
    return out


def median_metrics(runs: list[dict[str, float]]) -> dict[str, float]:
    """Per metric, the median over the runs that did not fail (NaN where none measured it); when most
    runs failed, the first failure's {"status": ...}."""
    import numpy as np

    ok = [r for r in runs if "status" not in r]
    if 2 * len(ok) <= len(runs):
        failed = [r for r in runs if "status" in r]
        return {"status": failed[0]["status"] if failed else "no fits"}
    out = {}
    for k in METRICS:
        vals = [float(r[k]) for r in ok if r.get(k) is not None and math.isfinite(float(r[k]))]
        out[k] = float(np.median(vals)) if vals else math.nan
    return out


def _metrics(fit) -> dict[str, float]:
    from ..errors import FitmeError

    try:
        m = asdict(fit().metrics)
    except (FitmeError, FloatingPointError) as e:
        return {"status": f"{type(e).__name__}: {e}"}
    return {k: m[k] for k in METRICS}


def compare(current: dict[str, dict[str, float]], baseline: dict, tolerances: dict[str, Tolerance] | None = None
            ) -> list[Regression]:
    """Every (subject, metric) of the baseline that the current run is worse on than allowed, or lacks.
    The baseline's "start" (the metrics after 1 iteration), where present, widens each tolerance by its
    ``gain`` share of the fit's gain over the start."""
    tol = tolerances or {k: Tolerance(**v) for k, v in baseline.get("tolerances", {}).items()} or TOLERANCES
    out = []
    starts = baseline.get("start") or {}
    for subject, base in baseline["subjects"].items():
        cur = current.get(subject, {})
        start = starts.get(subject, {})
        for metric, b in base.items():
            if metric not in METRICS or b is None or not math.isfinite(b):
                continue  # not measured for this subject (e.g. shape on a real photo)
            c = cur.get(metric, math.nan)
            c = math.nan if c is None else float(c)
            t = tol.get(metric, TOLERANCES.get(metric))
            if t is None:
                raise ValueError(f"compare: no tolerance for metric {metric!r}; expected one of {', '.join(TOLERANCES)}")
            st = start.get(metric)
            allowed = t.allowed(b, None if st is None else float(st))
            worse = (b - c) if METRICS[metric] else (c - b)
            if not math.isfinite(c) or worse > allowed:
                out.append(Regression(subject, metric, b, c, allowed))
    return out


def format_regressions(regs: list[Regression]) -> str:
    return "\n".join(f"  REGRESSION {r}" for r in regs)


def write_baseline(path: Path, current: dict[str, dict[str, float]], s: RegressSettings,
                   start: dict[str, dict[str, float]] | None = None) -> None:
    """Write the baseline: ``current`` (``run_regress``) and, when given, ``start`` (``run_regress(...,
    start=True)``), which widens the tolerances (``compare``)."""
    import torch

    from .. import __version__

    def clean(runs):
        return {sub: {k: (None if isinstance(v, float) and not math.isfinite(v) else (round(v, 5) if isinstance(v, float) else v))
                      for k, v in m.items()} for sub, m in runs.items()}
    doc = {"schema": 2, "what": "fitme bench --regress baseline: accuracy metrics per subject, medians of "
           "RegressSettings.members fits, and the metrics after 1 iteration (start) (docs/benchmarks.md)",
           "settings": s.as_json(), "tolerances": {k: asdict(v) for k, v in TOLERANCES.items()},
           "made_with": {"fitme": __version__, "torch": torch.__version__, "python": platform.python_version(),
                         "machine": platform.machine(), "threads": torch.get_num_threads()},
           "subjects": clean(current)}
    if start is not None:
        doc["start"] = clean(start)
    Path(path).write_text(json.dumps(doc, indent=1) + "\n")


def read_baseline(path: Path, s: RegressSettings) -> dict:
    """The baseline JSON; ValueError when it was made with other settings (its numbers would not compare)."""
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{p}: no such baseline; create it with `fitme bench --regress {p} --update-baseline`")
    doc = json.loads(p.read_text())
    for key in ("settings", "subjects"):
        if key not in doc:
            raise ValueError(f"{p}: not a fitme bench baseline (no {key!r})")
    if set(doc.get("start") or {}) - set(doc["subjects"]):
        raise ValueError(f"{p}: 'start' names subjects that 'subjects' does not: "
                         f"{sorted(set(doc['start']) - set(doc['subjects']))}")
    if doc["settings"] != s.as_json():
        raise ValueError(f"{p}: made with settings {doc['settings']}, this run uses {s.as_json()}; "
                         "rewrite it with --update-baseline")
    for sub, m in [*doc["subjects"].items(), *(doc.get("start") or {}).items()]:
        for k in m:
            if k != "status" and k not in METRICS:
                raise ValueError(f"{p}: subject {sub} has unknown metric {k!r}; expected some of {', '.join(METRICS)}")
    return doc
