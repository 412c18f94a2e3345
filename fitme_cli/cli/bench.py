"""``fitme bench``: what accuracy costs in time, the real-photo identity check, the stability suite and
the CI regression run (docs/benchmarks.md)."""

from __future__ import annotations

import sys
from pathlib import Path

import click

__all__ = ["command"]


@click.command("bench")
@click.option("-o", "--output", "out_dir", required=True, type=click.Path(path_type=Path, file_okay=False),
              help="BENCH_DIR: data/ (the benchmark set), results.csv, results.md, pareto.png, ...")
@click.option("--quick", is_flag=True, help="2 subjects, 9 settings, fast budgets: a few minutes at 1 thread.")
@click.option("--photos", "photos_dir", type=click.Path(path_type=Path, file_okay=False, exists=True),
              help="Real photos, one subfolder per person (the sample photos are always added).")
@click.option("--regress", "baseline", type=click.Path(path_type=Path, dir_okay=False),
              help="Only the regression run: compare with BASELINE.json, exit 1 naming each regressed metric and subject.")
@click.option("--update-baseline", is_flag=True, help="With --regress: rewrite BASELINE.json from this run.")
@click.option("--stability", is_flag=True, help="Only the stability suite: exit 1 when a case fails.")
@click.option("--subjects", type=click.IntRange(1, 50), help="Synthetic subjects (default 2 with --quick, else 4).")
@click.option("--reflectance", default="gan", show_default=True, type=click.Choice(["gan", "data"]),
              help="The subjects' maps: drawn from the shipped BRDF-GAN, or held-out procedural data that no "
                   "generator draws exactly (the same subjects for every generator).")
@click.option("--repeats", default=1, show_default=True, type=click.IntRange(1, 20), help="Fits per (setting, subject); time is the median.")
@click.option("--threads", default=1, show_default=True, type=click.IntRange(1, 256), help="torch threads per fit.")
def command(out_dir: Path, quick: bool, photos_dir: Path | None, baseline: Path | None, update_baseline: bool,
            stability: bool, subjects: int | None, reflectance: str, repeats: int, threads: int) -> None:
    """Benchmark `fitme fit` on synthetic subjects with ground truth and on real photos.

    \b
    Without --regress / --stability: writes the benchmark set to OUT/data, fits every subject with
    each setting (one process per setting, so its peak memory is its own), and writes OUT/results.csv
    (one row per fit), OUT/results.md (medians per setting, real photos) and OUT/pareto.png.

    \b
    Examples:
      fitme bench --quick -o out/bench
      fitme bench -o out/bench --photos ~/faces
      fitme bench -o out/regress --regress tests/bench_baseline.json
      fitme bench -o out/stability --stability
    """
    import torch

    if update_baseline and baseline is None:
        raise click.UsageError("--update-baseline needs --regress BASELINE.json")
    torch.set_num_threads(threads)
    out_dir.mkdir(parents=True, exist_ok=True)
    failed = False
    if baseline is not None:
        failed |= _regress(out_dir, baseline, update_baseline)
    if stability:
        failed |= _stability(out_dir)
    if baseline is None and not stability:
        _sweep(out_dir, quick, photos_dir, subjects, reflectance, repeats, threads)
    if failed:
        sys.exit(1)


def _log(msg: str) -> None:
    click.echo(msg, err=True)


def _regress(out_dir: Path, baseline: Path, update: bool) -> bool:
    import json

    from ..bench.regress import RegressSettings, compare, format_regressions, read_baseline, run_regress, write_baseline
    from ..bench.run import METRICS

    s = RegressSettings()
    base = None if update else read_baseline(baseline, s)  # fail on a bad baseline before fitting
    current = run_regress(s, log=_log)
    (out_dir / "regress.json").write_text(json.dumps(current, indent=1) + "\n")
    for sub, m in current.items():
        click.echo(f"{sub}: " + ", ".join(f"{k} {v:.4g}" for k, v in m.items() if k in METRICS and v == v)
                   + (f" [{m['status']}]" if "status" in m else ""))
    if update:
        start = run_regress(s, log=_log, start=True)
        write_baseline(baseline, current, s, start)
        click.echo(f"baseline written to {baseline}")
        return False
    regs = compare(current, base)
    if regs:
        click.echo(f"regression: {len(regs)} metric(s) worse than {baseline}:\n{format_regressions(regs)}")
        return True
    click.echo(f"regression: every metric within tolerance of {baseline}")
    return False


def _stability(out_dir: Path) -> bool:
    import json
    from dataclasses import asdict

    from ..bench.stability import run_stability, stability_table

    res = run_stability(log=_log)
    table = stability_table(res)
    (out_dir / "stability.md").write_text(table)
    (out_dir / "stability.json").write_text(json.dumps([asdict(r) for r in res], indent=1, default=float) + "\n")
    click.echo(table)
    bad = [r.case for r in res if not r.passed]
    click.echo(f"stability: {len(res) - len(bad)}/{len(res)} passed" + (f"; FAILED: {', '.join(bad)}" if bad else ""))
    return bool(bad)


def _sweep(out_dir: Path, quick: bool, photos_dir: Path | None, subjects: int | None, reflectance: str, repeats: int,
           threads: int) -> None:
    import json
    import platform
    import time
    from dataclasses import asdict

    from ..bench.dataset import BenchSetSettings, make_bench_set
    from ..bench.realphotos import collect_photos, real_photos_table, run_real_photos
    from ..bench.report import markdown_table, pareto_plots, summarise, write_csv
    from ..bench.run import FitSettings, load_models
    from ..bench.sweep import run_sweep, variants

    t0 = time.perf_counter()
    n = subjects or (2 if quick else 4)
    try:
        photos = collect_photos(photos_dir)  # fail on a bad --photos before the long part
    except ValueError as e:
        raise click.BadParameter(str(e), param_hint="--photos") from None
    models = load_models()
    dirs = make_bench_set(out_dir / "data", BenchSetSettings(n_subjects=n, reflectance=reflectance), models)
    _log(f"bench: {n} subjects ({reflectance} maps) in {out_dir / 'data'}")
    vs = variants(quick)
    results = run_sweep(vs, dirs, out_dir / "runs", threads, repeats, log=_log)
    write_csv(results, out_dir / "results.csv")
    summaries = summarise(results)
    pareto_plots(summaries, out_dir / "pareto.png", threads=threads)
    fit_people = {"astronaut"} | ({p.name for p in photos_dir.iterdir() if p.is_dir()} if photos_dir else set())
    if not quick:
        fit_people |= {"grace_hopper", "camera"}
    real = run_real_photos(models, photos, FitSettings.from_preset("fast"), fit_people, log=_log)
    machine = f"{platform.machine()}, {__import__('os').cpu_count()} CPUs, torch {__import__('torch').__version__}, {threads} thread(s)"
    md = (f"# fitme bench{' --quick' if quick else ''}\n\n{machine}; total {time.perf_counter() - t0:.0f} s. Times are wall "
          f"clock of detect + invert + tune per fit (median over {n} subjects x {repeats} repeat(s)); peak MiB is the "
          "setting's process (interpreter, torch and models included).\n\n## Synthetic subjects\n\n" + markdown_table(summaries)
          + "\n## Real photos (fast preset; FaceNet cosine)\n\n" + real_photos_table(real))
    (out_dir / "results.md").write_text(md)
    (out_dir / "real_photos.json").write_text(json.dumps([asdict(r) for r in real], indent=1) + "\n")
    click.echo(md)
