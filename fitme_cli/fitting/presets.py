"""Fit presets: what accuracy costs in time. Figures measured on this 2-core CPU are in docs/fitting.md."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["FitPreset", "PRESETS", "preset"]


@dataclass(frozen=True)
class FitPreset:
    name: str
    iterations: int  # inversion iterations
    tune_iterations: int  # 0: no tuning
    render_size: int  # fitting crop side in pixels
    # share of the inversion with the synthesis stopped at coarse_resolution. 0 in every preset since the
    # 92 kimg generator: its 256^2 branch blocks change the colours, not only the detail, so a W fitted
    # on 128^2 maps leaves the albedo at half its brightness (default preset, 4 synthetic subjects:
    # albedo L1 0.228 with a 40 % coarse phase; docs/fitting.md "Coarse-to-fine")
    coarse_fraction: float
    # 128, not 64: with the 35 kimg generator already, a W fitted on 64^2 maps jumped at the switch and
    # did not recover (synthetic subjects, 50 iterations: albedo Delta E 11.0 / 9.5 with 64, 2.5 / 3.4
    # with 128, for the same time)
    coarse_resolution: int
    select_effects: bool  # run the effect selector (costs ~3 x selection_steps renders)


PRESETS = {
    # the paper's 200 + 20 iterations (main text) at 256^2 (it renders 512^2 on a GPU)
    "default": FitPreset("default", 200, 20, 256, 0.0, 128, True),
    # 30 iterations at 128^2 on full maps (no coarse phase: it saved no time here and cost accuracy,
    # docs/benchmarks.md), no tuning: a preview in < 15 s
    # (12 MP photo, 2 cores: 50 iterations took 16.1 s, 40 took 14.6-16.0 s; docs/fitting.md)
    "fast": FitPreset("fast", 30, 0, 128, 0.0, 128, False),
    # the supplementary's 250 + 30, rendered at the paper's 512^2
    "best": FitPreset("best", 250, 30, 512, 0.0, 128, True),
}


def preset(name: str) -> FitPreset:
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; expected one of {', '.join(PRESETS)}")
    return PRESETS[name]
