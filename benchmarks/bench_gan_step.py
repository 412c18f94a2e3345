"""Time one BRDF-GAN training step (G step, D step, lazy R1 every 16th) at the training run's size, for G's
256² width and with or without ``torch.compile`` of G's synthesis: what a wider top block costs, and what
compiling wins back; then the run's setting (32, compiled) with G's 64² and 128² layers twice as wide
(``--g-channel-base 8192``), that under bfloat16 autocast (``--bf16``), that reading the layout (``--layout``: 15 maps
from 64² up) and scaled by it (``--layout-gain``), and with the local D (``--patch-weight``, 4 crops of 64²).
Random inputs, no drift terms (they add ~20 % in the real run, docs/brdf_gan.md).

    python benchmarks/bench_gan_step.py [--g-channel-min 1,32] [--compile off,on] [--steps 8] [--threads 2]
"""

from __future__ import annotations

import argparse
import time

import torch

from fitme_cli.reflectance.gan.data import LAYOUT_CHANNELS
from fitme_cli.reflectance.gan.networks import GanSettings
from fitme_cli.reflectance.gan.train import TrainSettings, can_bf16, can_compile, compile_synthesis, new_state, train_step


def step_rate(g_channel_min: int, compiled: bool, steps: int, batch: int, patch_weight: float = 0.0,
              g_channel_base: int | None = None, bf16: bool = False, layout_channels: int = 0,
              layout_gain: bool = False) -> tuple[float, float, float]:
    """(images/s, warm-up s, G parameters in M) for the 186-kimg run's settings with G's floor ``g_channel_min``
    and G's own channel base ``g_channel_base``, the local D at ``patch_weight`` (0: none), ``bf16`` autocast and
    ``layout_channels`` layout maps read from 64² up (and ``layout_gain``: scaling the features)."""
    gan = GanSettings(channel_base=4096, g_channel_min=g_channel_min, g_channel_base=g_channel_base, d_joint_branch=True,
                      layout_channels=layout_channels, layout_gain=layout_gain)
    state = new_state(gan, TrainSettings(batch=batch, channels_last=True, patch_weight=patch_weight, bf16=bf16))
    if compiled:
        compile_synthesis(state)
    reals = torch.randn(batch, 7, gan.resolution, gan.resolution)
    t0 = time.perf_counter()
    for _ in range(3):  # the first G and D steps compile
        train_step(state, reals)
    warm = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(steps):
        train_step(state, reals)
    return batch * steps / (time.perf_counter() - t0), warm, sum(p.numel() for p in state.G.parameters()) / 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--g-channel-min", default="1,32", help="comma-separated floors on G's channels [1,32]")
    ap.add_argument("--compile", default="off,on", help="comma-separated: off, on [off,on]")
    ap.add_argument("--steps", type=int, default=8)
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--no-patch", action="store_true", help="skip the row with the local D")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    modes = [m.strip() == "on" for m in a.compile.split(",")]
    if any(modes) and not can_compile():
        print("no C++ compiler: compiled rows skipped")
        modes = [m for m in modes if not m]
    print(f"BRDF-GAN training step, 256², batch {a.batch}, {a.threads} threads, {a.steps} timed steps")
    for floor in (int(v) for v in a.g_channel_min.split(",")):
        for compiled in modes:
            rate, warm, params = step_rate(floor, compiled, a.steps, a.batch)
            top = GanSettings(channel_base=4096, g_channel_min=floor).g_channels(256)
            print(f"  G's 256² {top:3d} ch (G {params:.2f} M)  compile {'on ' if compiled else 'off'}: "
                  f"{rate:5.2f} images/s  ({rate * 3.6:4.1f} kimg/h; first 3 steps {warm:5.1f} s)", flush=True)
    compiled = can_compile()
    for bf16 in (False, True):
        rate, warm, params = step_rate(32, compiled, a.steps, a.batch, g_channel_base=8192, bf16=bf16)
        print(f"  G's 256²  32 ch, 64² / 128² 128 / 64 ch (G {params:.2f} M)  compile {'on ' if compiled else 'off'}"
              f"{', bf16' if bf16 else ''}: {rate:5.2f} images/s  ({rate * 3.6:4.1f} kimg/h; first 3 steps {warm:5.1f} s)",
              flush=True)
    bf16 = can_bf16()
    for gain in (False, True):
        rate, warm, params = step_rate(32, compiled, a.steps, a.batch, g_channel_base=8192, bf16=bf16,
                                       layout_channels=len(LAYOUT_CHANNELS), layout_gain=gain)
        print(f"  the same{', bf16' if bf16 else ''}, + {len(LAYOUT_CHANNELS)} layout maps from 64²"
              f"{' as inputs and gains' if gain else ''} (G {params:.2f} M): "
              f"{rate:5.2f} images/s  ({rate * 3.6:4.1f} kimg/h; first 3 steps {warm:5.1f} s)", flush=True)
    if not a.no_patch:
        rate, warm, _ = step_rate(32, compiled, a.steps, a.batch, patch_weight=0.5)
        print(f"  G's 256²  32 ch, compile {'on ' if compiled else 'off'}, + local D (4 crops of 64², 32 ch): "
              f"{rate:5.2f} images/s  ({rate * 3.6:4.1f} kimg/h; first 3 steps {warm:5.1f} s)", flush=True)


if __name__ == "__main__":
    main()
