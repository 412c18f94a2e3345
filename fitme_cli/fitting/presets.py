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
    # the paper's 200 inversion iterations (main text) at 256^2 (it renders 512^2 on a GPU), and 60 tuning
    # iterations, not its 20: the 262.02 kimg G, closer to its data, needs more tuning to leave it for a photo.
    # Sample photos' FaceNet likeness, 20 -> 60: 0.551 -> 0.613 (151.01 kimg G: 0.616 -> 0.642); held-out data
    # subjects' albedo Delta E 5.49 -> 5.36 (docs/fitting.md "Held-out data subjects"); ~+7 s per fit
    "default": FitPreset("default", 200, 60, 256, 0.0, 128, True),
    # 30 iterations at 128^2 on full maps (no coarse phase: it saved no time here and cost accuracy,
    # docs/benchmarks.md) and 20 tuning iterations: a preview in < 15 s. Tuning since the 262.02 kimg G: without it
    # the sample photos' likeness fell to 0.285 (151.01 kimg G: 0.345); with 10 / 15 / 20 iterations 0.324 / 0.331 /
    # 0.370, the held-out data subjects' albedo Delta E unchanged (6.65 -> 6.75 at 20). 20 took a 12 MP photo to
    # 15.2-16.0 s until the fit's G ran channels-last (store.load_generator): 13.6 s since (docs/fitting.md)
    # (12 MP photo, 2 cores: 50 inversion iterations took 16.1 s, 40 took 14.6-16.0 s; docs/fitting.md)
    "fast": FitPreset("fast", 30, 20, 128, 0.0, 128, False),
    # the supplementary's 250 inversion iterations, rendered at the paper's 512^2; tuning as long as the default's
    # (the supplementary's 30 was fewer than the default now has; 60 is not measured at 512^2)
    "best": FitPreset("best", 250, 60, 512, 0.0, 128, True),
}


def preset(name: str) -> FitPreset:
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; expected one of {', '.join(PRESETS)}")
    return PRESETS[name]
