"""Which effects a scene calls for. The renderer computes nothing for an effect that is off; the
selector turns effects on only where the photo shows them, and the user can force any of them.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace

import numpy as np

__all__ = ["EFFECT_NAMES", "Effects", "SelectorSettings", "EffectChoice", "parse_effects", "highlight_fraction",
           "select_effects"]


@dataclass(frozen=True)
class Effects:
    specular: bool = True  # Blinn-Phong specular from A_S and the detail normals N_S
    subsurface: bool = True  # per-channel blur of diffuse irradiance over the skin
    sh_ambient: bool = False  # order-2 spherical-harmonics environment instead of a constant ambient
    shadows: bool = False  # self-shadowing from each light (shadow maps)
    multi_light: bool = False  # every light in the scene; off: only the first (key) light

    @staticmethod
    def all() -> Effects:
        return Effects(**{f.name: True for f in fields(Effects)})

    @staticmethod
    def none() -> Effects:
        return Effects(**{f.name: False for f in fields(Effects)})

    def on(self) -> list[str]:
        return [k for k, v in asdict(self).items() if v]


EFFECT_NAMES = tuple(f.name for f in fields(Effects))


def parse_effects(spec: str) -> dict[str, bool]:
    """'+shadows,-specular' / 'shadows,specular=off' / 'all' / 'none' -> forced values {name: bool}."""
    forced: dict[str, bool] = {}
    for raw in (s.strip() for s in spec.split(",")):
        if not raw:
            continue
        if raw in ("all", "none"):
            forced.update({n: raw == "all" for n in EFFECT_NAMES})
            continue
        value = True
        if raw[0] in "+-":
            value, raw = raw[0] == "+", raw[1:]
        elif "=" in raw:
            raw, v = raw.split("=", 1)
            if v not in ("on", "off", "1", "0", "true", "false"):
                raise ValueError(f"effect value must be on or off, got {v!r}")
            value = v in ("on", "1", "true")
        name = raw.replace("-", "_")
        if name not in EFFECT_NAMES:
            raise ValueError(f"unknown effect {raw!r}; expected one of {', '.join(EFFECT_NAMES)}")
        forced[name] = value
    return forced


@dataclass(frozen=True)
class SelectorSettings:
    # specular highlights are a few pixels wide; on a face narrower than this they cannot be fitted
    min_face_px_for_specular: float = 96.0
    # share of skin pixels that must look like highlights (bright and desaturated)
    min_highlight_fraction: float = 0.003
    # a second light, SH ambient or shadows stay off unless they lower the fit-so-far's photometric
    # residual by at least this fraction
    min_residual_gain: float = 0.05


@dataclass(frozen=True)
class EffectChoice:
    effects: Effects
    reasons: dict[str, str]  # effect -> why it is on or off (for the fit report)


def highlight_fraction(skin_rgb: np.ndarray) -> float:
    """(N, 3) sRGB [0, 1] skin pixels -> the share that are highlights: brighter than the skin's
    median by 3 robust deviations and at most 60 % as saturated."""
    if len(skin_rgb) < 32:
        return 0.0
    lum = skin_rgb @ np.array([0.2126, 0.7152, 0.0722])
    mx, mn = skin_rgb.max(1), skin_rgb.min(1)
    sat = (mx - mn) / np.maximum(mx, 1e-6)
    med = np.median(lum)
    mad = np.median(np.abs(lum - med)) * 1.4826 + 1e-3
    return float(((lum > med + 3 * mad) & (sat < 0.6 * np.median(sat))).mean())


def select_effects(face_width_px: float, skin_rgb: np.ndarray, residuals: dict[str, float] | None = None,
                   forced: dict[str, bool] | None = None, s: SelectorSettings = SelectorSettings()) -> EffectChoice:
    """Decide the effects for one scene.

    face_width_px: the face's width in the photo; skin_rgb: (N, 3) sRGB skin pixels; residuals: the
    photometric residual of the fit so far (after 40 % of the inversion) with the base effects ("base")
    and with one extra effect each ("multi_light", "sh_ambient", "shadows"); forced: user overrides,
    which always win."""
    reasons: dict[str, str] = {}
    on: dict[str, bool] = {}
    frac = highlight_fraction(skin_rgb)
    if face_width_px < s.min_face_px_for_specular:
        on["specular"] = False
        reasons["specular"] = f"off: face {face_width_px:.0f} px wide < {s.min_face_px_for_specular:.0f} px"
    elif frac < s.min_highlight_fraction:
        on["specular"] = False
        reasons["specular"] = f"off: highlights on {100 * frac:.2f} % of skin < {100 * s.min_highlight_fraction:.2f} %"
    else:
        on["specular"] = True
        reasons["specular"] = f"on: highlights on {100 * frac:.2f} % of skin"
    on["subsurface"] = face_width_px >= s.min_face_px_for_specular / 2
    reasons["subsurface"] = (f"{'on' if on['subsurface'] else 'off'}: face {face_width_px:.0f} px wide "
                             f"({'>=' if on['subsurface'] else '<'} {s.min_face_px_for_specular / 2:.0f} px)")
    base = (residuals or {}).get("base")
    for name in ("multi_light", "sh_ambient", "shadows"):
        r = (residuals or {}).get(name)
        if base is None or r is None or base <= 0:
            on[name] = False
            reasons[name] = "off: not measured"
            continue
        gain = (base - r) / base
        on[name] = gain > s.min_residual_gain
        reasons[name] = f"{'on' if on[name] else 'off'}: residual {'-' if gain >= 0 else '+'}{abs(100 * gain):.1f} % (threshold {100 * s.min_residual_gain:.0f} %)"
    for name, value in (forced or {}).items():
        if name not in EFFECT_NAMES:
            raise ValueError(f"unknown effect {name!r}")
        on[name] = value
        reasons[name] = f"{'on' if value else 'off'}: forced by the user"
    return EffectChoice(replace(Effects.none(), **on), reasons)
