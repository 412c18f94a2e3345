"""What a BRDF-GAN checkpoint's D knows: does it memorise the training maps, or tell G's from any data map, and
where does it look? Prints D's logits on training maps, held-out maps (never trained on) and G's samples, with and
without ADA's augmentation at p = 1; writes a heat map of the mean |dD/dx| (rows: G's samples, held-out maps;
columns: albedo, specular, normals, each summed over its channels, one colour scale per column).

    fitme dataset HELD_DIR -n 256 --size 256 --seed 1      # samples are a function of (seed, index): seed 1 is unseen
    python benchmarks/gan_discriminator.py DATA_DIR HELD_DIR CKPT -o saliency.png [--n 128] [--threads 2]

If held-out maps score as the training ones, D has not memorised them, and more data (``fitme dataset`` makes any
amount) would not change what it tells G by; if G's samples score far below both, G's maps differ from the data in
ways D sees in every sample. 256^2 at 128 maps: ~2.5 min on 1 thread.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch


def _logits(D, x: torch.Tensor, p: float, chunk: int = 16) -> torch.Tensor:
    from fitme_cli.reflectance.gan.ada import augment

    torch.manual_seed(0)
    return torch.cat([D(augment(x[i : i + chunk], p) if p > 0 else x[i : i + chunk]) for i in range(0, len(x), chunk)]).flatten()


def _saliency(D, x: torch.Tensor, chunk: int = 16) -> torch.Tensor:
    """(3, R, R): mean |dD/dx| over the maps, summed over albedo (0:3), specular (3) and normals (4:7)."""
    total = torch.zeros(x.shape[1:])
    for i in range(0, len(x), chunk):
        xi = x[i : i + chunk].clone().requires_grad_(True)
        D(xi).sum().backward()
        total += xi.grad.abs().sum(0)
    g = total / len(x)
    return torch.stack([g[:3].sum(0), g[3], g[4:].sum(0)])


def _heat_map(rows: list[torch.Tensor]) -> np.ndarray:
    """rows of (3, R, R) -> (len(rows) * R, 3 * R, 3) uint8 BGR, each column scaled by its 99.5th percentile."""
    import cv2

    m = torch.stack(rows).numpy()
    cols = []
    for c in range(m.shape[1]):
        scale = max(float(np.percentile(m[:, c], 99.5)), 1e-12)
        cols.append([cv2.applyColorMap((np.clip(m[r, c] / scale, 0, 1) * 255).astype(np.uint8), cv2.COLORMAP_INFERNO)
                     for r in range(m.shape[0])])
    return np.concatenate([np.concatenate([cols[c][r] for c in range(len(cols))], 1) for r in range(m.shape[0])], 0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data_dir", type=Path)
    ap.add_argument("held_dir", type=Path)
    ap.add_argument("checkpoint", type=Path)
    ap.add_argument("-o", "--output", type=Path, required=True, help="heat map PNG")
    ap.add_argument("--n", type=int, default=128, help="maps of each kind (a multiple of 16)")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    if args.n < 16 or args.n % 16:
        ap.error(f"--n must be a positive multiple of 16, got {args.n}")
    torch.set_num_threads(args.threads)

    from fitme_cli.io.atomic import atomic_write_bytes
    from fitme_cli.reflectance.gan.data import load_dataset
    from fitme_cli.reflectance.gan.train import load_checkpoint

    state = load_checkpoint(args.checkpoint)
    train = load_dataset(args.data_dir, state.gan, limit=args.n).float()
    held = load_dataset(args.held_dir, state.gan, limit=args.n).float()
    if len(held) < args.n or len(train) < args.n:
        raise SystemExit(f"need {args.n} maps in each folder, got {len(train)} training and {len(held)} held-out")
    z = torch.randn(args.n, state.gan.z_dim, generator=torch.Generator().manual_seed(5))
    with torch.no_grad():
        fakes = torch.cat([state.G_ema(z[i : i + 16], noise_mode="const").cat() for i in range(0, args.n, 16)])
        for p in (0.0, 1.0):
            parts = []
            for name, x in (("training", train), ("held-out", held), ("G_ema", fakes)):
                lg = _logits(state.D, x, p)
                parts.append(f"{name} {float(lg.mean()):+.2f} (judged real {float((lg > 0).double().mean()):.2f})")
            print(f"{args.checkpoint} ({state.nimg / 1000:.2f} kimg), D's mean logit, ADA p {p:g}: " + "; ".join(parts),
                  flush=True)
    rows = [_saliency(state.D, fakes), _saliency(state.D, held)]
    for (name, r) in zip(("G_ema", "held-out"), rows):
        print(f"mean |dD/dx| on {name}: albedo {float(r[0].mean()):.5f}, specular {float(r[1].mean()):.5f}, "
              f"normals {float(r[2].mean()):.5f}")
    import cv2

    ok, png = cv2.imencode(".png", _heat_map(rows))
    atomic_write_bytes(args.output, png.tobytes())
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
