"""The card's visual bar as a person's test: can someone tell G's triplets from the training data's?

Each round shows 16 triplets (albedo sRGB | specular ×3 | normals, full resolution), 8 generated and 8 from
the data, shuffled by a seed the judge does not see, in two pictures of 8 rows, each triplet numbered.
The judge writes down which ones are generated; ``score`` counts the hits and gives the one-sided
binomial p-value of doing at least that well by guessing. 50 % is the bar; 31 of 32 (151.01 kimg,
docs/brdf_gan.md) is "easily told apart".

    python -m fitme_cli.reflectance.gan.blind make models/ DATA_DIR -o out/blind --rounds 2
    (look at out/blind/round*.png only, write {"G": ["0-3", "0-5", ...]} to guesses.json)
    python -m fitme_cli.reflectance.gan.blind score out/blind guesses.json

For a judge who has not seen G before (a fresh person, or a helper agent), ``--reference 16`` adds
``reference_0.png`` / ``_1.png``: 16 triplets of the data, none of them in the rounds, so that the judge knows
what the data looks like; ``--key PATH`` writes the key outside the folder the judge is given; and ``--brief eye``
writes the judge's instructions, ``BRIEF.md``, into the folder: ``eye`` (the person test: decide by looking,
enlarged crops allowed, no statistic computed from the pixels) or ``measure`` (any measurement allowed: a stricter
test than a person's).
"""

from __future__ import annotations

import json
import math
import secrets
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from .latents import sample_z
from .networks import GanImages, Generator, decode_maps

__all__ = ["BRIEFS", "BlindScore", "make_rounds", "score", "record_score"]

_PER_SIDE = 8  # generated and data triplets per round

# The judges' rules. "eye" is the card's bar as the issue words it ("a person cannot easily tell apart"); helper
# judges with "measure" rules told G by statistics no person sees (a notch at 0.45 cycle in the normals' row
# spectra, a high-pass kurtosis), so the two are kept apart: name the rules in ``score --note`` (docs/brdf_gan.md,
# "372.22 kimg judged by eye").
BRIEFS = {
    "eye": """## Rules: judge by eye
- Decide only from what you **see**. Look at the sheets with an image viewer. You may make enlarged crops (one row,
  one panel, a region at 2-4x with nearest-neighbour) and brighten or contrast-stretch them for viewing: that is what
  a person with an image viewer can do.
- Do **not** compute statistics to decide: no means, histograms, spectra, correlations, level counts, classifiers or
  any other number computed from the pixels. Code may only decode, crop, enlarge, contrast-stretch and write images.
""",
    "measure": """## Rules: look and measure
- Look at the sheets, and measure anything you like from the pixels (statistics, spectra, histograms).
""",
}


def _brief(kind: str, resolution: int, reference: int) -> str:
    """The judge's instructions for a folder ``make_rounds`` wrote (Markdown)."""
    ref = (f"- `reference_0.png` ... : {reference} rows, ALL real (training data), 8 a sheet. Study them first.\n"
           if reference else "")
    return f"""# Blind test: tell generated texture maps from real ones

You are judging whether a generative model's face texture maps can be told apart from its training data.

## What is in this folder
{ref}- `round0_a.png`, `round0_b.png`, ...: 8 rows each, numbered 0-7 (a) and 8-15 (b) in the top-left corner. Each
  round has 16 rows: exactly **8 are generated (G)** and 8 are real. Ids are "ROUND-INDEX", e.g. "0-5", "1-12".

Each row is a triplet of three {resolution}x{resolution} UV maps side by side:
1. diffuse albedo (sRGB),
2. specular albedo (x3, sRGB, grey),
3. tangent-space normals shown as 2.5 n + 0.5 (flat = grey-blue; x in red, y in green).

UV layout: the face is in the middle, the scalp and hair at the top, the neck and body at the bottom.

{BRIEFS[kind]}- Work only inside this folder; do not look for keys or other files outside it. Use 1 thread.

## Deliverable
Write `guesses.json` in this folder: `{{"G": ["0-3", "0-9", ..., "1-14"]}}` with exactly 8 ids per round. Then
report your picks, your confidence per round (50 % is guessing) and the cues you used: what you saw, where, on which
ids{", with measured values for the references against your picks" if kind == "measure" else ""}.
"""


@dataclass(frozen=True)
class BlindScore:
    correct: int  # triplets judged right (generated called generated, data called data)
    total: int
    p_value: float  # P(at least ``correct`` of ``total`` by coin flips)
    missed: tuple[str, ...]  # the ids judged wrong, "round-index"


def _triplets(imgs: GanImages, G: Generator) -> np.ndarray:
    """(B, R, 3R, 3) uint8: albedo sRGB | specular x3 sRGB (as ``report.closeup``: the raw specular is too dark to
    judge) | normals 2.5 n + 0.5 (as ``train.sample_grid``). Every specular first goes through the 8 linear bits that
    ``fitme dataset`` stores it in (the data's are there already): unquantized, G's x3 specular showed 159-222 grey
    levels against the data's at most 86, and a judge told every G triplet by counting them (2026-11-30). The albedo
    is stored as 8-bit sRGB, as the sheet shows it; the normals in 16 bits."""
    from ...ops.srgb import linear_to_srgb

    m = decode_maps(imgs, G.settings)
    stored = (m.specular.clamp(0, 1) * 255).round() / 255
    spec = linear_to_srgb((3 * stored).clamp(0, 1)).expand(-1, 3, -1, -1)
    x = torch.cat([linear_to_srgb(m.albedo), spec, (m.normals * 2.5 + 0.5).clamp(0, 1)], 3)
    return (x.permute(0, 2, 3, 1).clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)


def make_rounds(G: Generator, data: torch.Tensor, out_dir: Path, rounds: int = 2, seed: int | None = None,
                reference: int = 0, key_path: Path | None = None, brief: str | None = None) -> list[Path]:
    """Write ``roundR_a.png`` / ``roundR_b.png`` (8 numbered triplets each) into ``out_dir`` and the key to
    ``key_path`` (default ``out_dir / "key.json"``). ``data``: (N, 7, R, R) network space, N >= 8 * ``rounds`` +
    ``reference`` (``data.load_dataset``; no data triplet shows twice); G samples at psi 1 with random noise, as the card does. ``seed`` None draws one from
    the OS, so the judge cannot know the order. ``reference`` > 0 also writes ``reference_0.png``, ``_1.png``, ...
    (8 unnumbered rows each): that many data triplets that no round shows. ``brief`` (a key of ``BRIEFS``) also
    writes the judge's rules to ``BRIEF.md``. Returns the rounds' paths, then the reference sheets', then the brief's."""
    import cv2

    from ...io.atomic import atomic_write_bytes, atomic_write_image

    r = G.settings.resolution
    if rounds < 1:
        raise ValueError(f"expected rounds >= 1, got {rounds}")
    if reference < 0:
        raise ValueError(f"expected reference >= 0, got {reference}")
    if brief is not None and brief not in BRIEFS:
        raise ValueError(f"expected brief None or one of {sorted(BRIEFS)}, got {brief!r}")
    need = _PER_SIDE * rounds + reference
    if data.ndim != 4 or data.shape[1:] != (7, r, r) or len(data) < need:
        raise ValueError(f"expected data of shape (N >= {need}, 7, {r}, {r}), got {tuple(data.shape)}")
    rng = np.random.default_rng(secrets.randbits(32) if seed is None else seed)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    pool = np.arange(len(data))
    if reference:  # drawn first, and kept out of the rounds
        pool = rng.permutation(len(data))
        shown, pool = pool[:reference], pool[reference:]
    # every round's data triplets at once: drawn per round, one sample could show in two rounds (a judge saw the same
    # triplet twice, 2026-11-30)
    real_idx = rng.choice(pool, _PER_SIDE * rounds, replace=False).reshape(rounds, _PER_SIDE)
    key, paths = {}, []
    for rd in range(rounds):
        with torch.no_grad():
            fake = _triplets(G(sample_z(_PER_SIDE, G.settings.z_dim, int(rng.integers(1 << 30))), noise_mode="random"), G)
        real = _triplets(GanImages.split(data[real_idx[rd]].float()), G)
        items = [("G", f) for f in fake] + [("data", d) for d in real]
        order = rng.permutation(len(items))
        for half in range(2):
            rows = []
            for j in range(_PER_SIDE):
                k = half * _PER_SIDE + j
                label, img = items[order[k]]
                key[f"{rd}-{k}"] = label
                img = img.copy()
                cv2.putText(img, str(k), (4, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (255, 255, 0), 2, cv2.LINE_AA)
                rows.append(np.pad(img, ((2, 2), (0, 0), (0, 0)), constant_values=255))
            path = out_dir / f"round{rd}_{'ab'[half]}.png"
            atomic_write_image(path, np.concatenate(rows, 0))
            paths.append(path)
    for start in range(0, reference, _PER_SIDE):
        part = _triplets(GanImages.split(data[shown[start : start + _PER_SIDE]].float()), G)
        path = out_dir / f"reference_{start // _PER_SIDE}.png"
        atomic_write_image(path, np.concatenate([np.pad(t, ((2, 2), (0, 0), (0, 0)), constant_values=255) for t in part], 0))
        paths.append(path)
    if brief is not None:
        paths.append(out_dir / "BRIEF.md")
        atomic_write_bytes(paths[-1], _brief(brief, r, reference).encode())
    atomic_write_bytes(Path(key_path) if key_path is not None else out_dir / "key.json", json.dumps(key, indent=0).encode())
    return paths


def score(key: dict[str, str], generated: list[str]) -> BlindScore:
    """``key``: id -> "G" or "data" (``key.json``); ``generated``: the ids the judge called generated."""
    unknown = sorted(set(generated) - set(key))
    if unknown:
        raise ValueError(f"guesses name ids that are not in the key: {unknown[:5]} (ids look like {next(iter(key), '0-0')!r})")
    if any(v not in ("G", "data") for v in key.values()):
        raise ValueError(f"expected key values 'G' or 'data', got {sorted(set(key.values()))}")
    called = set(generated)
    missed = tuple(k for k, v in key.items() if (k in called) != (v == "G"))
    n, c = len(key), len(key) - len(missed)
    p = sum(math.comb(n, i) for i in range(c, n + 1)) / 2**n
    return BlindScore(c, n, p, missed)


def main(argv: list[str] | None = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    mk = sub.add_parser("make", help="write the rounds and the key")
    mk.add_argument("generator", type=Path, help="a models folder (brdf_gan.safetensors) or a training checkpoint")
    mk.add_argument("data_dir", type=Path)
    mk.add_argument("-o", "--out", type=Path, required=True)
    mk.add_argument("--rounds", type=int, default=2)
    mk.add_argument("--reference", type=int, default=0, help="also write this many data triplets no round shows, for a "
                    "judge who has not seen the data (reference_*.png; 16 is two sheets)")
    mk.add_argument("--key", type=Path, help="write the key here instead of OUT/key.json (out of the judge's sight)")
    mk.add_argument("--brief", choices=sorted(BRIEFS), help="also write the judge's rules, OUT/BRIEF.md: 'eye' (the "
                    "person test: by looking only) or 'measure' (any statistic allowed)")
    sc = sub.add_parser("score", help="score a judge's guesses against the key")
    sc.add_argument("out", type=Path, help="the rounds' folder (its key.json) or the key file itself")
    sc.add_argument("guesses", type=Path, help='JSON {"G": ["0-3", ...]}: the triplets judged generated')
    sc.add_argument("--card", type=Path, help="also record the score as the model card's person_test (brdf_gan.json)")
    sc.add_argument("--note", default="", help="recorded with it: who judged, what gave G away")
    args = ap.parse_args(argv)
    from ...errors import FitmeError

    if args.cmd == "make":
        from .data import load_dataset
        from .store import load_generator
        from .train import load_checkpoint

        try:
            G = load_checkpoint(args.generator).G_ema if args.generator.is_file() else load_generator(args.generator)
            data = load_dataset(args.data_dir, G.settings, progress=False)
            paths = make_rounds(G, data, args.out, args.rounds, reference=args.reference, key_path=args.key,
                                brief=args.brief)
        except (FitmeError, OSError, ValueError) as e:
            print(f"blind make: {e}", file=sys.stderr)
            return 2
        for p in paths:
            print(p)
        return 0
    try:
        key = json.loads((args.out if args.out.is_file() else args.out / "key.json").read_text())
        guesses = json.loads(args.guesses.read_text())
        if not isinstance(guesses, dict) or not isinstance(guesses.get("G"), list):
            raise ValueError(f'expected {args.guesses} to hold {{"G": ["0-3", ...]}}, got {str(guesses)[:80]}')
        s = score(key, guesses["G"])
        print(f"{s.correct} of {s.total} right ({100 * s.correct / s.total:.0f} %), p = {s.p_value:.2g} by guessing; "
              f"wrong: {', '.join(s.missed) or 'none'}")
        if args.card:
            record_score(args.card, s, args.note)
    except (FitmeError, OSError, ValueError) as e:  # json.JSONDecodeError is a ValueError
        print(f"blind score: {e}", file=sys.stderr)
        return 2
    return 0


def record_score(card_path: Path, s: BlindScore, note: str) -> None:
    """Write ``s`` into a model card (JSON) as ``person_test``, atomically; the rest of the card is kept."""
    from ...io.atomic import atomic_write_bytes

    card = json.loads(Path(card_path).read_text())
    card["person_test"] = {"right": s.correct, "of": s.total, "p_value_by_guessing": float(f"{s.p_value:.3g}"),
                           "note": note, "how": "python -m fitme_cli.reflectance.gan.blind (docs/brdf_gan.md)"}
    atomic_write_bytes(Path(card_path), (json.dumps(card, indent=2) + "\n").encode())


if __name__ == "__main__":
    raise SystemExit(main())
