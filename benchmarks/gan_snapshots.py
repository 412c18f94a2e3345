"""Quick checks of BRDF-GAN training snapshots, between the full cards (docs/brdf_gan.md): for each checkpoint, the
skin's tone spread between samples and its quantiles, the skin and forehead's within-region albedo std and finest
band, and the share of full beards, each against the first 512 training maps. Prints one line per checkpoint.

    python benchmarks/gan_snapshots.py DATA_DIR CKPT... [--generator ema|g] [--latents 192]

``fitme train`` overwrites ``RUN/checkpoint.safetensors`` at every snapshot; copy each aside to compare them.
Measures (192 latents, seed 11, constant noise, against the data's first 512 maps; 3.7 min for the data and two
256^2 checkpoints on 1 thread beside a training run, which it slows ~2-fold meanwhile):
- tone spread: the std between samples of the skin's mean linear albedo (mean of r, g, b), G over data; its
  10th / 50th / 90th percentiles beside the data's. The sampling error of the ratio is ~0.05.
- skin+forehead std, band: the mean within-region std and finest Laplacian band RMS of the linear albedo, G over data.
- beards: the share of samples whose beard zone is at least 0.6 and 0.3 hair (``metrics.hair_share``).
- hairline share: the mean, std and 10th percentile over samples of the share of the hairline's reach that is hair
  by texture or colour (``metrics.soft_hairline_share``: the hairline-share term's measure), beside the data's. A low
  10th percentile is the data's receding hairlines.
- band by tone: the same finest band on the samples in the data's darkest, middle and fairest third of skin tones
  (the data's tercile bounds), G over data: whether G's detail follows the tone as the data's does.
- chroma bands: each region's band RMS (3 finest levels) of the albedo's log chromaticity on the darker and the
  lighter half of each batch of 4 (``train._albedo_chroma_bands``, the chroma-band term's measure), G over data: the
  median of the ratios on each half, and the mean |ratio - 1| over all (the term's gap). Blotches of colour: 1.22
  median, gap 0.32 at 239.00 kimg.
- added channels (only where ``g_channel_min`` widened G): the RMS of the weights of each branch's top ``conv1`` and
  ``to_image`` that read the channels the floor added, over the RMS of those reading the others. Widening starts them
  at 0 (gan/widen.py); the old ones' size is what the trained channels' weights have.
A single snapshot of the training G swings (its detail by +-20 % between snapshots 0.25 kimg apart, 2026-11-27):
compare G_ema, which ships, unless asking about the training G itself.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

_SKIN, _FOREHEAD = 1, 2  # shape.regions.REGIONS


def _measure(albedo: torch.Tensor, regions: torch.Tensor, zone: torch.Tensor,
             hairline: tuple[torch.Tensor, torch.Tensor, torch.Tensor]) -> dict[str, torch.Tensor]:
    """albedo (N, 3, R, R) linear -> per sample: skin tone, skin+forehead std and finest band, beard hair share,
    hairline hair share (hairline: reach, face, scalp masks)."""
    from fitme_cli.reflectance.gan.metrics import (hair_share, region_band_energy, region_labels, region_moments,
                                                   soft_hairline_share)

    labels = region_labels(regions)
    face = [labels.index(_SKIN), labels.index(_FOREHEAD)]
    moments = region_moments(albedo, regions)  # (N, k, 2, 3)
    return {"tone": moments[:, labels.index(_SKIN), 0].mean(1), "std": moments[:, face, 1].mean((1, 2)),
            "band": region_band_energy(albedo, regions, 1)[:, face, 0].mean((1, 2)), "hair": hair_share(albedo, zone),
            "hairline": soft_hairline_share(albedo, *hairline)}


def _added_share(G, gan) -> str:
    """'conv1 a / to_image b' (means over branches), or '' when no layer has floor-added channels."""
    r = gan.resolution
    old, new = gan.channels(r), gan.g_channels(r)
    if new == old:
        return ""
    rms = lambda t: float(t.detach().pow(2).mean().sqrt())  # noqa: E731
    shares = {"conv1": [], "to_image": []}
    for name, w in G.synthesis.named_parameters():
        layer = name.split(".")[-2] if "." in name else ""
        if f".b{r}." in name and name.endswith(".weight") and layer in shares and w.ndim == 4:
            rows = w[:old] if layer == "conv1" else w  # conv1's added outputs read old inputs through their own init
            shares[layer].append(rms(rows[:, old:]) / rms(rows[:, :old]))
    return "; added channels' weights, conv1 / to_image: " + " / ".join(
        f"{sum(v) / len(v):.3f}" for v in shares.values())


def _band_by_tone(m: dict[str, torch.Tensor], ref: dict[str, torch.Tensor]) -> str:
    """'a / b / c': the finest skin+forehead band, G over data, on the data's darkest, middle and fairest third."""
    bounds = ref["tone"].double().quantile(torch.tensor([1 / 3, 2 / 3], dtype=torch.float64)).float()
    thirds = lambda t: torch.bucketize(t, bounds)  # noqa: E731  0, 1, 2
    g, d = thirds(m["tone"]), thirds(ref["tone"])
    return " / ".join(f"{float(m['band'][g == k].mean() / ref['band'][d == k].mean()):.2f}" if bool((g == k).any())
                      else "-" for k in range(3))


def _chroma_bands(x: torch.Tensor, regions: torch.Tensor) -> torch.Tensor:
    """(N, 7, R, R) network space, N a multiple of 4 -> (2 * m,): the mean over batches of 4 of the chroma-band
    term's measure."""
    from fitme_cli.reflectance.gan.train import _albedo_chroma_bands

    return torch.stack([_albedo_chroma_bands(x[i : i + 4].float(), regions, 3).mean(0)
                        for i in range(0, len(x) - 3, 4)]).mean(0)


def _chroma_ratio(m: torch.Tensor, ref: torch.Tensor) -> str:
    """'dark a / light b, gap c': medians of G over data per tone half, and the mean |G / data - 1|."""
    ratio = (m / ref.clamp_min(1e-6)).view(2, -1)
    return (f"dark {float(ratio[0].median()):.2f} / light {float(ratio[1].median()):.2f}, "
            f"gap {float((ratio - 1).abs().mean()):.3f}")


def _spread(x: torch.Tensor) -> str:
    return f"{float(x.mean()):.3f} +- {float(x.std()):.3f}, q10 {float(x.double().quantile(0.1)):.3f}"


def _quantiles(x: torch.Tensor) -> str:
    return "/".join(f"{float(v):.3f}" for v in x.double().quantile(torch.tensor([0.1, 0.5, 0.9], dtype=torch.float64)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data_dir", type=Path)
    ap.add_argument("checkpoints", type=Path, nargs="+")
    ap.add_argument("--generator", choices=("ema", "g"), default="ema")
    ap.add_argument("--latents", type=int, default=192)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    from fitme_cli.reflectance.gan.data import (beard_zone, hairline_reach, hairline_references, load_dataset,
                                                load_regions)
    from fitme_cli.reflectance.gan.networks import decode_albedo
    from fitme_cli.reflectance.gan.train import load_checkpoint

    data = ref = ref_chroma = regions = zone = hairline = None
    for path in args.checkpoints:
        state = load_checkpoint(path)
        G = state.G_ema if args.generator == "ema" else state.G
        if ref is None:
            r = state.gan.resolution
            regions, zone, hairline = load_regions(r), beard_zone(r), (hairline_reach(r), *hairline_references(r))
            data = load_dataset(args.data_dir, state.gan, limit=512)
            ref = _measure(torch.cat([decode_albedo(data[i : i + 64].float()[:, :3]) for i in range(0, len(data), 64)]),
                           regions, zone, hairline)
            ref_chroma = _chroma_bands(data, regions)
        z = torch.randn(args.latents, state.gan.z_dim, generator=torch.Generator().manual_seed(11))
        with torch.no_grad():
            maps = torch.cat([G(z[i : i + 32], noise_mode="const").cat() for i in range(0, len(z), 32)])
            chroma = _chroma_bands(maps, regions)
        albedo = decode_albedo(maps[:, :3])
        m = _measure(albedo, regions, zone, hairline)
        print(f"{path.name} ({state.nimg / 1000:.2f} kimg, {args.generator}): "
              f"tone spread {float(m['tone'].std() / ref['tone'].std()):.3f}, "
              f"q10/50/90 {_quantiles(m['tone'])} (data {_quantiles(ref['tone'])}); "
              f"skin+forehead std {float(m['std'].mean() / ref['std'].mean()):.3f}, "
              f"band {float(m['band'].mean() / ref['band'].mean()):.3f} (by tone, dark / mid / fair: "
              f"{_band_by_tone(m, ref)}); "
              f"beards >= 0.6 / 0.3: {float((m['hair'] >= 0.6).double().mean()):.3f} / "
              f"{float((m['hair'] >= 0.3).double().mean()):.3f} "
              f"(data {float((ref['hair'] >= 0.6).double().mean()):.3f} / {float((ref['hair'] >= 0.3).double().mean()):.3f}); "
              f"hairline share {_spread(m['hairline'])} (data {_spread(ref['hairline'])})"
              f"; chroma bands {_chroma_ratio(chroma, ref_chroma)}"
              f"{_added_share(G, state.gan)}",
              flush=True)


if __name__ == "__main__":
    main()
