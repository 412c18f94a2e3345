"""Running one subject, and running many on local worker processes or on a Ray cluster.

Each subject runs ``fitme fit`` (and optionally ``fitme export``) in its own process: a crash, a
NaN or an out-of-memory kill takes only that subject down, and a subject's memory is returned when
it ends. A subject is finished when ``OUT_ROOT/NAME/status.json`` exists, written atomically after
everything else, with the key of its inputs and settings: a re-run skips it, a kill loses at most
the subjects in flight.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import subprocess
import sys
import tarfile
import tempfile
import time
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from dataclasses import asdict, dataclass
from pathlib import Path

from .manifest import Subject

__all__ = ["BatchSettings", "SubjectResult", "effective_settings", "run_subject", "run_local", "run_ray", "load_status"]


@dataclass(frozen=True)
class BatchSettings:
    preset: str = "default"
    export: tuple[str, ...] = ()  # formats for `fitme export` (e.g. glb, obj); empty: no export
    workers: int = 2  # the CLI's default is the number of cores
    threads: int = 0  # torch threads per worker; 0: cores // workers
    retry_failed: bool = False
    timeout_s: float = 3600.0  # per subject


@dataclass(frozen=True)
class SubjectResult:
    """status: done | failed | skipped-done | skipped-failed; seconds: this run's wall time (or the
    finished run's, when skipped); identity: mean identity similarity of photo and render."""

    name: str
    status: str
    seconds: float
    identity: float | None
    landmark_px: float | None
    photos: int
    error: str | None
    key: str


def effective_settings(subject: Subject, s: BatchSettings) -> dict:
    """The batch's settings with the subject's overrides: what the fit actually runs with."""
    out = {"preset": s.preset, "export": list(s.export)}
    out.update(subject.settings)
    return out


def load_status(out_dir: Path) -> dict | None:
    try:
        return json.loads((Path(out_dir) / "status.json").read_text())
    except (OSError, ValueError):
        return None


def _threads(s: BatchSettings) -> int:
    return s.threads or max(1, (os.cpu_count() or 1) // max(1, s.workers))


def _fit_command(photos: list[Path], avatar: Path, eff: dict, threads: int) -> list[str]:
    cmd = [sys.executable, "-m", "fitme_cli", "fit", *map(str, photos), "-o", str(avatar), "--preset", eff["preset"],
           "--threads", str(threads), "--force"]
    for k in ("iterations", "effects", "seed"):
        if eff.get(k):
            cmd += [f"--{k}", str(eff[k])]
    return cmd


def _run_in(work: Path, photos: list[Path], eff: dict, threads: int, timeout_s: float) -> dict:
    """Fit (and export) into ``work``; returns the status record (without the key)."""
    t0 = time.perf_counter()
    (work / _MARKER).write_text("written by fitme batch\n")
    env = dict(os.environ, OMP_NUM_THREADS=str(threads))
    log = work / "fit.log"
    status = {"status": "failed", "error": None, "exit_code": None}
    if not photos:
        status["error"] = "no photos"
    else:
        try:
            with open(log, "w") as f:
                r = subprocess.run(_fit_command(photos, work / "avatar", eff, threads), stdout=f, stderr=subprocess.STDOUT,
                                   env=env, timeout=timeout_s)
            status["exit_code"] = r.returncode
            ok = (work / "avatar" / "avatar.json").is_file()
            if ok and eff.get("export"):
                with open(log, "a") as f:
                    e = subprocess.run([sys.executable, "-m", "fitme_cli", "export", str(work / "avatar"), "-o",
                                        str(work / "export"), "--format", ",".join(eff["export"]), "--force"],
                                       stdout=f, stderr=subprocess.STDOUT, env=env, timeout=timeout_s)
                if e.returncode != 0:
                    ok = False
                    status["error"] = f"export failed (exit {e.returncode}); see fit.log"
            if ok:
                status["status"] = "done"
                if r.returncode != 0:  # fitted, but some photos were skipped
                    status["warning"] = _last_error(log)
            elif status["error"] is None:
                status["error"] = _last_error(log) or f"fit exited with {r.returncode}"
        except subprocess.TimeoutExpired:
            status["error"] = f"timed out after {timeout_s:.0f} s"
    status["seconds"] = round(time.perf_counter() - t0, 2)
    rep = _read_json(work / "avatar" / "avatar.json")
    if rep:
        q = [i["quality"] for i in rep.get("inputs", [])]
        status["identity"] = round(sum(x["identity_similarity"] for x in q) / len(q), 4) if q else None
        status["landmark_px"] = round(sum(x["landmark_error_px"] for x in q) / len(q), 3) if q else None
        _thumbnail(work)
    return status


def _read_json(p: Path) -> dict | None:
    try:
        return json.loads(p.read_text())
    except (OSError, ValueError):
        return None


def _last_error(log: Path) -> str | None:
    try:
        lines = [ln for ln in log.read_text(errors="replace").splitlines() if "error" in ln.lower() or "skipped" in ln.lower()]
    except OSError:
        return None
    return lines[-1].strip()[:300] if lines else None


def _thumbnail(work: Path) -> None:
    """photo | render of the first photo, 128 px high: for the summary page."""
    import cv2
    import numpy as np

    panels = sorted((work / "avatar" / "photos").glob("*/panel.png"))
    if not panels:
        return
    p = cv2.imread(str(panels[0]))
    if p is None:
        return
    s = p.shape[0]
    thumb = np.concatenate([p[:, :s], p[:, 2 * s:3 * s]], 1)
    cv2.imwrite(str(work / "thumb.png"), cv2.resize(thumb, (256, 128), interpolation=cv2.INTER_AREA))


def _write_status(out_dir: Path, status: dict) -> None:
    from ..io.atomic import atomic_write_bytes

    atomic_write_bytes(out_dir / "status.json", (json.dumps(status, indent=1) + "\n").encode())


def _result(name: str, status: dict, photos: int, skipped: bool) -> SubjectResult:
    st = status["status"]
    return SubjectResult(name, f"skipped-{st}" if skipped else st, float(status.get("seconds", 0.0)), status.get("identity"),
                         status.get("landmark_px"), photos, status.get("error"), status.get("key", ""))


_MARKER = ".fitme-batch"  # in every subject folder the batch writes, before status.json exists


def _foreign(out: Path) -> bool:
    """A folder in the way that the batch did not write (no marker, no status.json, not empty): never
    replaced. A subject killed between moving its folder into place and writing status.json has the marker."""
    return (out.is_dir() and not (out / "status.json").is_file() and not (out / _MARKER).is_file()
            and any(out.iterdir()))


def run_subject(subject: Subject, key: str, s: BatchSettings, out_root: Path) -> SubjectResult:
    """Run one subject on this machine into OUT_ROOT/NAME (replaced), status.json last."""
    out = Path(out_root) / subject.name
    if _foreign(out) or (out.exists() and not out.is_dir()):
        return SubjectResult(subject.name, "failed", 0.0, None, None, len(subject.photos),
                             f"{out} exists and was not written by fitme batch; move it away", key)
    work = Path(tempfile.mkdtemp(prefix=f".{subject.name}.", suffix=".tmp", dir=out_root))
    try:
        status = _run_in(work, list(subject.photos), effective_settings(subject, s), _threads(s), s.timeout_s)
        status["key"] = key
        status["settings"] = effective_settings(subject, s)
        _replace_dir(work, out)
        work = None
        _write_status(out, status)
    finally:
        if work is not None:
            shutil.rmtree(work, ignore_errors=True)
    return _result(subject.name, status, len(subject.photos), False)


def _replace_dir(new: Path, out: Path) -> None:
    old = None
    if out.exists():
        old = out.with_name(f".{out.name}.old-{os.getpid()}")
        os.rename(out, old)
    os.rename(new, out)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def _skip(subject: Subject, key: str, s: BatchSettings, out_root: Path) -> SubjectResult | None:
    st = load_status(Path(out_root) / subject.name)
    if not st or st.get("key") != key:
        return None
    if st.get("status") == "done" or (st.get("status") == "failed" and not s.retry_failed):
        return _result(subject.name, st, len(subject.photos), True)
    return None


def run_local(subjects: list[Subject], keys: list[str], s: BatchSettings, out_root: Path, on_result) -> None:
    """Worker processes on this machine (each subject's fit is a child process; threads here only wait)."""
    todo = []
    for subj, key in zip(subjects, keys):
        skipped = _skip(subj, key, s, out_root)
        if skipped:
            on_result(skipped)
        else:
            todo.append((subj, key))
    with ThreadPoolExecutor(max_workers=max(1, s.workers)) as pool:
        running: dict[Future, Subject] = {}
        it = iter(todo)
        for _ in range(max(1, s.workers)):
            nxt = next(it, None)
            if nxt is not None:
                running[pool.submit(run_subject, nxt[0], nxt[1], s, out_root)] = nxt[0]
        while running:
            done, _ = wait(running, return_when=FIRST_COMPLETED)
            for f in done:
                subj = running.pop(f)
                try:
                    on_result(f.result())
                except Exception as e:  # a bug in the runner itself: report, keep going
                    on_result(SubjectResult(subj.name, "failed", 0.0, None, None, len(subj.photos), f"internal error: {e}", ""))
                nxt = next(it, None)
                if nxt is not None:
                    running[pool.submit(run_subject, nxt[0], nxt[1], s, out_root)] = nxt[0]


# ---- Ray ------------------------------------------------------------------------------------------
# A Ray task gets the photos' bytes (workers need not share a file system with the driver), fits in a
# temporary directory on its node and returns the subject's folder as a tar; the driver unpacks it
# into OUT_ROOT and writes status.json last, as the local executor does.

def _ray_task(name: str, photos: list[tuple[str, bytes]], eff: dict, threads: int, timeout_s: float) -> tuple[dict, bytes]:
    with tempfile.TemporaryDirectory(prefix=f"fitme-{name}-") as tmp:
        work = Path(tmp) / "work"
        (work / "photos").mkdir(parents=True)
        paths = []
        for fname, data in photos:
            p = work / "photos" / fname
            p.write_bytes(data)
            paths.append(p)
        status = _run_in(work, paths, eff, threads, timeout_s)
        shutil.rmtree(work / "photos", ignore_errors=True)
        buf = io.BytesIO()
        with tarfile.open(fileobj=buf, mode="w") as tar:
            tar.add(work, arcname=".")
        return status, buf.getvalue()


def run_ray(subjects: list[Subject], keys: list[str], s: BatchSettings, out_root: Path, on_result,
            address: str | None = None) -> None:
    """Each subject is a Ray task asking for ``threads`` CPUs; at most ``workers`` in flight per CPU
    budget the cluster decides. ``address``: an existing cluster ("auto", "ray://host:10001"), or None
    for a local instance."""
    try:
        import ray
    except ImportError:
        from ..errors import FitmeError

        raise FitmeError("--executor ray needs Ray: pip install 'fitme-cli[ray]'") from None
    started = not ray.is_initialized()
    if started:
        ray.init(address=address, include_dashboard=False, log_to_driver=False, configure_logging=False)
    try:
        threads = _threads(s)
        task = ray.remote(num_cpus=threads, max_retries=1)(_ray_task)
        pending = {}
        for subj, key in zip(subjects, keys):
            skipped = _skip(subj, key, s, out_root)
            if skipped:
                on_result(skipped)
                continue
            photos, unreadable = [], []
            for i, p in enumerate(subj.photos):
                try:
                    photos.append((f"{i:03d}_{p.name}", p.read_bytes()))
                except OSError as e:
                    unreadable.append(f"{p}: {e.strerror or e}")
            ref = task.remote(subj.name, photos, effective_settings(subj, s), threads, s.timeout_s)
            pending[ref] = (subj, key, unreadable)
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            for ref in done:
                subj, key, unreadable = pending.pop(ref)
                try:
                    status, data = ray.get(ref)
                except Exception as e:  # the task or its node died
                    status, data = {"status": "failed", "error": f"ray task failed: {type(e).__name__}: {e}", "seconds": 0.0}, None
                status["key"] = key
                status["settings"] = effective_settings(subj, s)
                status["executor"] = "ray"
                if unreadable:
                    status["unreadable_photos"] = unreadable
                out = Path(out_root) / subj.name
                if _foreign(out) or (out.exists() and not out.is_dir()):
                    on_result(SubjectResult(subj.name, "failed", 0.0, None, None, len(subj.photos),
                                            f"{out} exists and was not written by fitme batch; move it away", key))
                    continue
                work = Path(tempfile.mkdtemp(prefix=f".{subj.name}.", suffix=".tmp", dir=out_root))
                if data:
                    with tarfile.open(fileobj=io.BytesIO(data)) as tar:
                        tar.extractall(work, filter="data")
                _replace_dir(work, out)
                _write_status(out, status)
                on_result(_result(subj.name, status, len(subj.photos), False))
    finally:
        if started:
            ray.shutdown()


def settings_json(s: BatchSettings) -> dict:
    return asdict(s)
