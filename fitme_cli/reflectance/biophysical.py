"""A biophysical skin colour model: melanin and haemoglobin concentrations -> linear sRGB diffuse albedo.

Two-layer Kubelka-Munk model after Donner & Jensen (2006) and Jimenez et al. (2010):

- epidermis (``EPIDERMIS_MM`` thick): eumelanin + pheomelanin absorption (Donner & Jensen's power
  laws) plus a melanin-free baseline, and its own scattering. The scattering is what keeps very dark
  skin from turning red: light that never reaches the dermis is still reflected, with the melanin's
  (fairly flat) spectrum, so dark skin is a dim brown, not a deep red.
- dermis (semi-infinite): oxy- and deoxy-haemoglobin absorption (Prahl's molar extinction, whole
  blood at 150 g/l) times the blood volume fraction, plus a baseline, over a lambda^-1.42 reduced
  scattering (Jacques 2013).

Layers combine with the Kubelka-Munk adding formula R = R_e + T_e^2 R_d / (1 - R_e R_d). Spectra
(400-700 nm, 10 nm) integrate to XYZ with the Wyman-Sloan-Shirley (2013) fit of the CIE 1931
matching functions, then to linear sRGB, white-balanced so a perfect white reflector is (1, 1, 1).

The two public parameters are normalised to [0, 1]:

- ``melanin`` m -> epidermal melanin volume fraction C_m = 0.002 + 0.6 m^1.6 (m = 0 lighter than MST 1,
  m = 0.4 ~ MST 7, m = 1 ~ MST 10);
- ``haemoglobin`` h -> dermal blood volume fraction C_h = 0.002 + 0.15 h (h ~ 0.2 is typical
  facial skin, ~ 0.5 flushed cheeks, ~ 0.9 lips).
"""

from __future__ import annotations

import numpy as np

__all__ = ["WAVELENGTHS", "skin_rgb", "skin_spectrum", "melanin_fraction", "blood_fraction", "spectrum_to_rgb"]

WAVELENGTHS = np.arange(400.0, 701.0, 10.0)  # nm

EPIDERMIS_MM = 0.12
_EPI_SCATTER = 2.0  # KM S of the epidermis, 1/mm (at 500 nm; ~ lambda^-1)

# Prahl's molar extinction coefficients (cm^-1 / M), 400..700 nm in 10 nm steps
_HBO2 = np.array([266232, 466840, 480360, 228680, 102580, 62816, 44480, 33209, 26629, 23684, 20933, 20035, 24202,
                  39957, 53236, 43016, 32613, 44496, 50104, 14401, 3200, 1506, 942, 610, 442, 368, 320, 294, 278,
                  276, 290], np.float64)
_HB = np.array([223296, 303956, 407560, 528600, 413280, 103292, 23389, 16156, 14550, 16684, 20035, 25774, 31590,
                39036, 46592, 53412, 53788, 45072, 37020, 28324, 14677, 9444, 6510, 5149, 4345, 3750, 3227, 2795,
                2408, 2141, 1794], np.float64)
# whole blood: 150 g/l haemoglobin, 64500 g/mol; ln(10) for decadic extinction; cm^-1 -> mm^-1
_BLOOD = 2.303 * 150.0 / 64500.0 / 10.0


def melanin_fraction(m):
    """Epidermal melanin volume fraction for the normalised ``melanin`` parameter in [0, 1]."""
    return 0.002 + 0.6 * np.clip(m, 0.0, 1.0) ** 1.6


def blood_fraction(h):
    """Dermal blood volume fraction for the normalised ``haemoglobin`` parameter in [0, 1]."""
    return 0.002 + 0.15 * np.clip(h, 0.0, 1.0)


def _g(x, mu, s1, s2):
    s = np.where(x < mu, s1, s2)
    return np.exp(-0.5 * ((x - mu) / s) ** 2)


def _rgb_weights() -> np.ndarray:
    lam = WAVELENGTHS
    x = 1.056 * _g(lam, 599.8, 37.9, 31.0) + 0.362 * _g(lam, 442.0, 16.0, 26.7) - 0.065 * _g(lam, 501.1, 20.4, 26.2)
    y = 0.821 * _g(lam, 568.8, 46.9, 40.5) + 0.286 * _g(lam, 530.9, 16.3, 31.1)
    z = 1.217 * _g(lam, 437.0, 11.8, 36.0) + 0.681 * _g(lam, 459.0, 26.0, 13.8)
    m = np.array([[3.2406, -1.5372, -0.4986], [-0.9689, 1.8758, 0.0415], [0.0557, -0.2040, 1.0570]])
    w = (m @ np.stack([x, y, z])).T  # (L, 3)
    return w / w.sum(0, keepdims=True)  # white balance: flat reflectance 1 -> (1, 1, 1)


_W = _rgb_weights()


def spectrum_to_rgb(spectrum: np.ndarray) -> np.ndarray:
    """(..., L) reflectance at WAVELENGTHS -> (..., 3) linear sRGB (not clipped)."""
    return np.asarray(spectrum) @ _W


def _km_layer(k, s, d):
    """Kubelka-Munk reflectance and transmittance of a layer (K, S per mm, thickness d mm)."""
    a = 1.0 + k / s
    b = np.sqrt(a * a - 1.0)
    bsd = np.minimum(b * s * d, 30.0)
    sh, ch = np.sinh(bsd), np.cosh(bsd)
    den = a * sh + b * ch
    return sh / den, b / den


def skin_spectrum(melanin, haemoglobin, eumelanin: float = 0.7, oxygenation: float = 0.75) -> np.ndarray:
    """(..., L) diffuse reflectance spectrum at WAVELENGTHS. ``melanin`` and ``haemoglobin`` are the
    normalised [0, 1] parameters (broadcast together); ``eumelanin``: eumelanin share of the melanin
    (the rest pheomelanin); ``oxygenation``: oxy-haemoglobin share of the blood."""
    lam = WAVELENGTHS
    cm = melanin_fraction(np.asarray(melanin, np.float64))[..., None]
    ch = blood_fraction(np.asarray(haemoglobin, np.float64))[..., None]
    mu_eu = 6.6e10 * lam**-3.33  # 1/mm
    mu_ph = 2.9e14 * lam**-4.75
    mu_base = 0.0244 + 8.53 * np.exp(-(lam - 154.0) / 66.2)
    mu_epi = cm * (eumelanin * mu_eu + (1.0 - eumelanin) * mu_ph) + (1.0 - cm) * mu_base
    mu_blood = _BLOOD * (oxygenation * _HBO2 + (1.0 - oxygenation) * _HB)
    mu_derm = ch * mu_blood + (1.0 - ch) * mu_base
    s_epi = _EPI_SCATTER * (500.0 / lam)
    s_derm = 4.6 * (lam / 500.0) ** -1.42
    re, te = _km_layer(2.0 * mu_epi, s_epi, EPIDERMIS_MM)
    kd = 2.0 * mu_derm / s_derm
    rd = 1.0 + kd - np.sqrt(kd * kd + 2.0 * kd)
    return re + te * te * rd / (1.0 - re * rd)


def skin_rgb(melanin, haemoglobin, eumelanin: float = 0.7, oxygenation: float = 0.75) -> np.ndarray:
    """Linear sRGB diffuse albedo, shape broadcast(melanin, haemoglobin) + (3,), float32 in [0, 1].

    Monotone decreasing in ``melanin`` in every channel; ``melanin`` 0 .. 1 spans the Monk Skin Tone
    scale: (0.68, 0.49, 0.40) at m = 0 down to (0.024, 0.016, 0.009) at m = 1 (haemoglobin 0.2)."""
    rgb = spectrum_to_rgb(skin_spectrum(melanin, haemoglobin, eumelanin, oxygenation))
    return np.clip(rgb, 0.0, 1.0).astype(np.float32)
