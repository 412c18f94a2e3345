"""The sweep's results as a CSV (one row per fit), a Markdown table (one row per variant: medians over
its successful fits) and accuracy-vs-time Pareto plots (PNG, matplotlib Agg)."""

from __future__ import annotations

import csv
import math
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

from .run import METRICS
from .sweep import RunResult

__all__ = ["VariantSummary", "summarise", "write_csv", "markdown_table", "pareto_front", "pareto_plots"]


@dataclass(frozen=True)
class VariantSummary:
    """One variant: medians over its successful fits (NaN when none)."""

    variant: str
    views: int
    n_ok: int
    n_runs: int
    fit_s: float  # median wall time of one fit
    peak_mib: float  # the largest over the variant's process
    metrics: dict[str, float]  # METRICS name -> median


def summarise(results: list[RunResult]) -> list[VariantSummary]:
    """Group by variant (first-seen order) and take medians over the ok runs."""
    order: dict[str, list[RunResult]] = {}
    for r in results:
        order.setdefault(r.variant, []).append(r)
    out = []
    for name, rs in order.items():
        ok = [r for r in rs if r.status == "ok"]

        def med(key: str) -> float:
            vals = [getattr(r, key) for r in ok if math.isfinite(getattr(r, key))]
            return float(np.median(vals)) if vals else math.nan
        peaks = [r.peak_mib for r in rs if math.isfinite(r.peak_mib)]
        out.append(VariantSummary(name, rs[0].views, len(ok), len(rs), med("fit_s"), max(peaks) if peaks else math.nan,
                                  {k: med(k) for k in METRICS}))
    return out


def write_csv(results: list[RunResult], path: Path) -> None:
    names = [f.name for f in fields(RunResult)]
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, names)
        w.writeheader()
        for r in results:
            w.writerow(asdict(r))


def _fmt(x: float, nd: int) -> str:
    return "–" if not math.isfinite(x) else f"{x:.{nd}f}"


_COLUMNS = [("landmark_px", "landmarks px", 2), ("shape_mm", "shape mm", 3), ("shape_posed_mm", "posed shape mm", 3),
            ("albedo_l1", "albedo L1", 4), ("albedo_delta_e", "albedo ΔE", 2), ("albedo_delta_e_gain", "ΔE after gain", 2),
            ("normals_deg", "normals °", 3), ("identity_sim", "identity sim", 3), ("photometric", "photometric (levels)", 1)]


def markdown_table(summaries: list[VariantSummary]) -> str:
    head = "| setting | views | ok | fit s (median) | peak MiB | " + " | ".join(c[1] for c in _COLUMNS) + " |"
    sep = "|---|---:|---:|---:|---:|" + "---:|" * len(_COLUMNS)
    rows = [f"| {s.variant} | {s.views} | {s.n_ok}/{s.n_runs} | {_fmt(s.fit_s, 1)} | {_fmt(s.peak_mib, 0)} | "
            + " | ".join(_fmt(s.metrics[k], nd) for k, _, nd in _COLUMNS) + " |" for s in summaries]
    return "\n".join([head, sep, *rows]) + "\n"


def pareto_front(times: list[float], errors: list[float]) -> list[int]:
    """Indices of the points no other point beats on both time and error (lower is better for both),
    sorted by time; NaN points are never on it."""
    idx = [i for i in range(len(times)) if math.isfinite(times[i]) and math.isfinite(errors[i])]
    idx.sort(key=lambda i: (times[i], errors[i]))
    front, best = [], math.inf
    for i in idx:
        if errors[i] < best:
            front.append(i)
            best = errors[i]
    return front


def pareto_plots(summaries: list[VariantSummary], path: Path,
                 metrics: tuple[str, ...] = ("landmark_px", "shape_mm", "albedo_delta_e", "identity_sim", "photometric"),
                 title: str = "fitme bench: accuracy vs time", threads: int = 1) -> Path:
    """One panel per metric: every variant at (median fit time, median metric), the Pareto front joined."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bad = [m for m in metrics if m not in METRICS]
    if bad:
        raise ValueError(f"pareto_plots: unknown metrics {bad}; expected some of {', '.join(METRICS)}")
    fig, axes = plt.subplots(1, len(metrics), figsize=(4.2 * len(metrics), 4.2), squeeze=False)
    t = [s.fit_s for s in summaries]
    for ax, m in zip(axes[0], metrics):
        higher = METRICS[m]
        y = [s.metrics[m] for s in summaries]
        front = pareto_front(t, [-v if higher else v for v in y])  # the front of "error", lower better
        for i, s in enumerate(summaries):
            if math.isfinite(t[i]) and math.isfinite(y[i]):
                ax.scatter(t[i], y[i], s=22, c="tab:red" if i in front else "tab:blue", marker="s" if s.views == 3 else "o")
                ax.annotate(s.variant, (t[i], y[i]), fontsize=6, xytext=(3, 2), textcoords="offset points")
        if front:
            ax.plot([t[i] for i in front], [y[i] for i in front], "r--", lw=1)
        ax.set_xlabel(f"median fit time, s ({threads} thread{'s' if threads != 1 else ''})")
        ax.set_ylabel(m + (" (higher better)" if higher else " (lower better)"))
        ax.grid(alpha=0.3)
    fig.suptitle(title + " — red: Pareto front; squares: 3 views")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)
