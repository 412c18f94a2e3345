"""What a batch is made of: subjects, each with photos and optional settings, read from a folder of
subject folders or from a CSV manifest."""

from __future__ import annotations

import csv
import hashlib
import json
import re
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import InputNotFound, WrongLayout

__all__ = ["Subject", "read_subjects", "subject_key", "PHOTO_SUFFIXES"]

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".webp", ".bmp", ".tif", ".tiff", ".heic", ".heif")
_SETTING_COLUMNS = ("preset", "iterations", "effects", "seed")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._ -]{0,99}$")


@dataclass(frozen=True)
class Subject:
    """One person: ``name`` (also their output folder), ``photos`` (absolute paths, in order) and
    per-subject ``settings`` overriding the batch's (preset, iterations, effects, seed)."""

    name: str
    photos: tuple[Path, ...]
    settings: dict[str, str] = field(default_factory=dict)


def _check_name(name: str, where: str) -> str:
    if not _NAME.match(name) or name in (".", ".."):
        raise WrongLayout(f"subject name {name!r} is not usable as a folder name ({where})")
    return name


def _from_folder(root: Path) -> list[Subject]:
    subjects = []
    for d in sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")):
        photos = tuple(sorted(p.resolve() for p in d.iterdir() if p.is_file() and p.suffix.lower() in PHOTO_SUFFIXES))
        subjects.append(Subject(_check_name(d.name, str(d)), photos))
    if not subjects:
        raise WrongLayout("no subject folders found: expected INPUT/SUBJECT/photo.jpg ...", root)
    return subjects


def _from_csv(path: Path) -> list[Subject]:
    """Columns: subject, photos (paths separated by ';' or '|', relative to the CSV), and optionally
    preset, iterations, effects, seed. Several rows of one subject add photos."""
    try:
        rows = list(csv.DictReader(path.read_text(encoding="utf-8-sig").splitlines()))
    except (UnicodeDecodeError, csv.Error) as e:
        raise WrongLayout(f"not a readable CSV manifest: {e}", path) from None
    if not rows or not {"subject", "photos"} <= set(rows[0]):
        raise WrongLayout("a manifest needs the columns subject, photos (optional: " + ", ".join(_SETTING_COLUMNS) + ")", path)
    order: list[str] = []
    photos: dict[str, list[Path]] = {}
    settings: dict[str, dict[str, str]] = {}
    for i, row in enumerate(rows, start=2):
        name = _check_name((row.get("subject") or "").strip(), f"{path.name} line {i}")
        if name not in photos:
            order.append(name)
            photos[name], settings[name] = [], {}
        for raw in re.split(r"[;|]", row.get("photos") or ""):
            if raw.strip():
                p = Path(raw.strip())
                photos[name].append((p if p.is_absolute() else path.parent / p).resolve())
        for k in _SETTING_COLUMNS:
            v = (row.get(k) or "").strip()
            if v:
                settings[name][k] = v
    return [Subject(n, tuple(photos[n]), settings[n]) for n in order]


def read_subjects(source: Path) -> list[Subject]:
    """A folder of subject folders, or a .csv manifest. Subjects without photos are kept (they fail
    with a clear message in the summary, without stopping the batch)."""
    source = Path(source)
    if not source.exists():
        raise InputNotFound("batch input not found (expected a folder of subject folders or a .csv manifest)", source)
    subjects = _from_folder(source) if source.is_dir() else _from_csv(source)
    seen: set[str] = set()
    for s in subjects:
        if s.name.lower() in seen:
            raise WrongLayout(f"subject {s.name!r} appears twice (names are case-insensitive folder names)", source)
        seen.add(s.name.lower())
    return subjects


def subject_key(subject: Subject, settings: dict) -> str:
    """What makes a finished subject reusable: the photos' contents and the effective settings."""
    h = hashlib.sha256()
    for p in subject.photos:
        h.update(str(p.name).encode())
        try:
            h.update(hashlib.sha256(p.read_bytes()).digest())
        except OSError:
            h.update(b"<unreadable>")
    h.update(json.dumps(settings, sort_keys=True).encode())
    return h.hexdigest()
