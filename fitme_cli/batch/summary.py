"""The batch summary: summary.csv, summary.md and summary.html (thumbnails: photo beside render)."""

from __future__ import annotations

import csv
import html
import io
from pathlib import Path

from .run import SubjectResult

__all__ = ["write_summary"]

_COLUMNS = ("subject", "status", "seconds", "photos", "identity_similarity", "landmark_error_px", "error")


def _row(r: SubjectResult) -> dict:
    return {"subject": r.name, "status": r.status, "seconds": f"{r.seconds:.1f}", "photos": r.photos,
            "identity_similarity": "" if r.identity is None else f"{r.identity:.3f}",
            "landmark_error_px": "" if r.landmark_px is None else f"{r.landmark_px:.2f}", "error": r.error or ""}


def write_summary(out_root: Path, results: list[SubjectResult], header: str) -> dict[str, Path]:
    from ..io.atomic import atomic_write_bytes

    out_root = Path(out_root)
    rows = [_row(r) for r in sorted(results, key=lambda r: r.name)]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=_COLUMNS)
    w.writeheader()
    w.writerows(rows)
    atomic_write_bytes(out_root / "summary.csv", buf.getvalue().encode())
    md = [f"# fitme batch\n\n{header}\n", "| subject | status | s | photos | identity | landmark px | thumbnail | error |",
          "|---|---|---:|---:|---:|---:|---|---|"]
    cells = []
    for r, row in zip(sorted(results, key=lambda r: r.name), rows):
        thumb = f"{r.name}/thumb.png"
        has = (out_root / thumb).is_file()
        md.append(f"| {r.name} | {r.status} | {row['seconds']} | {r.photos} | {row['identity_similarity']} | "
                  f"{row['landmark_error_px']} | {f'![]({thumb})' if has else ''} | {row['error'].replace('|', '/')} |")
        colour = "#2e7d32" if r.status.endswith("done") else "#c62828"
        img = f'<img src="{html.escape(thumb)}" width="256" height="128">' if has else ""
        cells.append(f"<tr><td>{html.escape(r.name)}</td><td style='color:{colour}'>{html.escape(r.status)}</td>"
                     f"<td>{row['seconds']}</td><td>{r.photos}</td><td>{row['identity_similarity']}</td>"
                     f"<td>{row['landmark_error_px']}</td><td>{img}</td><td>{html.escape(row['error'])}</td></tr>")
    atomic_write_bytes(out_root / "summary.md", ("\n".join(md) + "\n").encode())
    page = ("<!doctype html><meta charset='utf-8'><title>fitme batch</title>"
            "<style>body{font-family:sans-serif}td,th{padding:4px 8px;border-bottom:1px solid #ddd}</style>"
            f"<h1>fitme batch</h1><p>{html.escape(header)}</p><table><tr><th>subject</th><th>status</th><th>s</th>"
            "<th>photos</th><th>identity</th><th>landmark px</th><th>photo | render</th><th>error</th></tr>"
            + "".join(cells) + "</table>")
    atomic_write_bytes(out_root / "summary.html", page.encode())
    return {"csv": out_root / "summary.csv", "md": out_root / "summary.md", "html": out_root / "summary.html"}
