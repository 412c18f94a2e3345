"""``fitme batch``: one avatar per subject, resumable, in parallel locally or on a Ray cluster."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import click

__all__ = ["command"]


@click.command("batch")
@click.argument("source", type=click.Path(path_type=Path))
@click.option("-o", "--output", "out_root", required=True, type=click.Path(path_type=Path), help="One folder per subject goes here.")
@click.option("--export", "export", default="", help="Also export each avatar: formats for `fitme export`, e.g. glb,obj.")
@click.option("--preset", default="default", show_default=True, type=click.Choice(["fast", "default", "best"]))
@click.option("--workers", default=0, type=click.IntRange(0, 256),
              help="Subjects fitted at once (default: one per core, one thread each: 1.8x the throughput of one "
                   "worker with every core on 2 cores, docs/batch.md).")
@click.option("--threads", default=0, type=click.IntRange(0, 256), help="torch threads per worker (default: cores / workers).")
@click.option("--retry-failed", is_flag=True, help="Run subjects that failed before again (finished ones are always skipped).")
@click.option("--executor", default="local", show_default=True, type=click.Choice(["local", "ray"]))
@click.option("--address", help="Ray cluster address (e.g. auto, ray://head:10001); default: a local Ray instance.")
@click.option("--timeout", "timeout_s", default=3600.0, show_default=True, help="Seconds per subject before it is stopped.")
def command(source: Path, out_root: Path, export: str, preset: str, workers: int, threads: int, retry_failed: bool,
            executor: str, address: str | None, timeout_s: float) -> None:
    """Fit every subject of SOURCE: a folder of subject folders (SOURCE/NAME/*.jpg) or a CSV manifest
    (columns subject, photos separated by ';', optional preset, iterations, effects, seed).

    Writes OUT_ROOT/NAME/{avatar/,export/,fit.log,thumb.png,status.json} and OUT_ROOT/summary.{csv,md,html}.
    A subject whose photos and settings are unchanged and that finished is skipped on a re-run; one
    that failed is skipped unless --retry-failed. A failure never stops the batch; a kill loses only
    the subjects in flight. The exit code is 0 when every subject is done, 1 otherwise.

    \b
    Examples:
      fitme batch shoots/ -o avatars/ --export glb
      fitme batch manifest.csv -o avatars/ --executor ray --address auto
    """
    import os

    from tqdm import tqdm

    from ..batch.manifest import read_subjects, subject_key
    from ..batch.run import BatchSettings, effective_settings, run_local, run_ray
    from ..batch.summary import write_summary
    from ..errors import OutputNotWritable

    formats = tuple(f.strip() for f in export.split(",") if f.strip())
    bad = [f for f in formats if f not in ("obj", "glb", "gltf")]
    if bad:
        raise click.BadParameter(f"unknown format(s) {', '.join(bad)}; expected obj, glb, gltf", param_hint="--export")
    subjects = read_subjects(source)
    src = source.resolve()
    if out_root.resolve() == src or src in out_root.resolve().parents:
        raise OutputNotWritable("the output folder is inside the input; choose another", out_root)
    try:
        out_root.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputNotWritable(f"cannot create the output folder: {e.strerror}", out_root) from None
    if not os.access(out_root, os.W_OK):
        raise OutputNotWritable("the output folder is not writable", out_root)
    workers = workers or os.cpu_count() or 1
    s = BatchSettings(preset=preset, export=formats, workers=workers, threads=threads, retry_failed=retry_failed,
                      timeout_s=timeout_s)
    keys = [subject_key(subj, effective_settings(subj, s)) for subj in subjects]
    results = []
    bar = tqdm(total=len(subjects), desc="batch", unit="subject", file=sys.stderr, disable=None)

    def on_result(r):
        results.append(r)
        bar.set_postfix_str(f"{r.name}: {r.status}", refresh=False)
        bar.update(1)
        if r.status == "failed":
            bar.write(f"fitme: {r.name} failed: {r.error}", file=sys.stderr)

    t0 = time.perf_counter()
    try:
        if executor == "ray":
            run_ray(subjects, keys, s, out_root, on_result, address)
        else:
            run_local(subjects, keys, s, out_root, on_result)
    finally:
        bar.close()
        wall = time.perf_counter() - t0
        ran = [r for r in results if not r.status.startswith("skipped")]
        header = (f"{len(subjects)} subjects, preset {preset}, executor {executor}, {workers} worker(s); this run: "
                  f"{len(ran)} fitted in {wall:.0f} s, {len(results) - len(ran)} skipped")
        write_summary(out_root, results, header)
    done = sum(r.status.endswith("done") for r in results)
    click.echo(f"{done}/{len(subjects)} subjects done ({len(ran)} run now in {wall:.0f} s"
               + (f", {len(ran) / wall * 3600:.0f} subjects/hour" if ran and wall > 0 else "") + f"); summary: {out_root / 'summary.html'}")
    if done < len(subjects):
        sys.exit(1)
