"""``fitme train``: train BRDF-GAN on a folder of reflectance maps (from ``fitme dataset``)."""

from __future__ import annotations

import contextlib
import json
import signal
import threading
from pathlib import Path

import click

__all__ = ["command"]


@contextlib.contextmanager
def _stop_requests():
    """Collect SIGTERM (``kill``'s default; a background job ignores Ctrl-C) and a first Ctrl-C into the
    yielded list instead of stopping mid-step: training ends after the current step, so the checkpoint
    saved then resumes exactly. A second Ctrl-C interrupts at once. Only the main thread can own signals."""
    got: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield got
        return

    def request(signum, frame):
        if signum == signal.SIGINT and got:
            raise KeyboardInterrupt
        got.append(signum)

    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGINT)}
    signal.signal(signal.SIGTERM, request)
    if previous[signal.SIGINT] is signal.default_int_handler:  # left alone where the shell ignores it
        signal.signal(signal.SIGINT, request)
    try:
        yield got
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


# flag -> (settings class name, field)
_GAN_FLAGS = ("resolution", "branch_resolution", "channel_base", "channel_max", "g_channel_min", "g_channel_base",
              "mapping_layers", "d_joint_branch", "layout_resolution", "layout_gain",
              "normal_knee", "normal_knee_slope")
_TRAIN_FLAGS = ("batch", "kimg", "r1_gamma", "ada", "snapshot_kimg", "seed", "g_lr", "d_lr", "g_top_lr_mul", "g_top_lr_from",
                "ema_kimg",
                "ada_target", "ada_color", "moment_weight", "moment_drift_weight", "link_weight",
                "coherence_weight", "band_weight", "band_levels", "spectrum_weight", "relief_weight", "colour_weight",
                "beard_weight", "tone_weight", "crown_weight", "mean_map_weight", "tone_order_weight", "detail_map_weight",
                "tone_band_weight", "chroma_band_weight", "specular_band_weight", "grain_weight", "lattice_weight",
                "chroma_grain_weight", "specular_link_weight", "specular_spectrum_weight", "texel_tail_weight",
                "eye_ring_weight", "edge_sharpness_weight", "specular_slope_weight", "forehead_rows_weight",
                "albedo_specular_link_weight", "hairline_edge_weight", "hairline_specks_weight",
                "beard_band_weight", "relief_band_weight", "nyquist_weight",
                "normal_symmetry_weight", "texel_neighbour_weight", "mouth_rows_weight", "screen_weight", "screen_levels",
                "specular_quantile_weight", "range_map_weight", "range_quantile_weight", "eye_flat_weight",
                "brow_profile_weight", "lip_ring_weight", "grain_evenness_weight", "specular_sobel_weight",
                "normal_spectrum_weight", "normal_tilt_weight", "specular_law_weight",
                "grain_overlap_weight", "normal_radial_weight", "sheet_radial_weight", "lattice_phase_weight",
                "strip_radial_weight", "strip_slope_link_weight", "hair_law_tail_weight", "sheet_axis_weight",
                "mottle_weight", "beard_specular_weight", "brow_hair_weight", "beard_texture_weight",
                "beard_share_weight", "chroma_edge_weight",
                "hairline_share_weight", "hairline_region", "side_regions", "eye_region", "brow_edge_region",
                "drift_on_ema", "patch_weight", "patch_size", "patch_count", "patch_channels", "patch_r1_gamma",
                "patch_focus", "gamut_weight", "bf16")
# the train flags a --resume may not change: every other one may (the run length, cadence, ADA, rates, EMA, terms)
_FIXED_ON_RESUME = ("batch", "r1_gamma", "seed")


def _check_layout_resolution(flags: dict, layout_channels: int) -> None:
    """--layout-resolution means nothing to a G without layout inputs: say so rather than rebuild the run for it."""
    if flags.get("layout_resolution") is not None and not layout_channels:
        raise click.BadParameter("--layout-resolution is read only with --layout (G's layout inputs)")


def _res_strength(ctx: click.Context, param: click.Parameter, values: tuple[str, ...]) -> tuple[tuple[int, float], ...]:
    """--trunk-noise RES:S, repeatable -> ((RES, S), ...); the resolution is checked against G once it is built."""
    out = []
    for v in values:
        res, sep, strength = v.partition(":")
        try:
            out.append((int(res), float(strength)))
        except ValueError:
            raise click.BadParameter(f"expected RES:S such as 16:0.2, got {v!r}", ctx, param) from None
        if not sep:
            raise click.BadParameter(f"expected RES:S such as 16:0.2, got {v!r}", ctx, param)
    return tuple(out)


@click.command("train")
@click.argument("data_dir", type=click.Path(path_type=Path))
@click.option("-o", "--output", "run_dir", required=True, type=click.Path(path_type=Path), help="Run directory: checkpoint, metrics, sample grids.")
@click.option("--config", type=click.Path(path_type=Path, dir_okay=False), help='JSON file {"gan": {...}, "train": {...}}; flags override it.')
@click.option("--resume", is_flag=True, help="Continue from the run directory's checkpoint.")
@click.option("--resolution", type=int, help="Output resolution (power of two). [256]")
@click.option("--branch-resolution", type=int, help="Blocks from this resolution up are per modality. [256]")
@click.option("--channel-base", type=int, help="Channels at resolution r: min(base / r, max); may grow on --resume. [2048]")
@click.option("--channel-max", type=int, help="May grow on --resume. [128]")
@click.option("--g-channel-min", type=click.IntRange(min=1),
              help="A floor on G's channels at every resolution (widens G's top layers, not D's); may grow on --resume. [1]")
@click.option("--g-channel-base", type=click.IntRange(min=1),
              help="G's own channel base: G's channels at r are min(this / r, --channel-max), D's stay; may grow on "
                   "--resume. [--channel-base]")
@click.option("--mapping-layers", type=int, help="[2]")
@click.option("--d-joint-branch/--no-d-joint-branch", default=None,
              help="A third D branch that sees albedos and normals together (not in the paper); may be added on --resume. [off]")
@click.option("--layout/--no-layout", default=None,
              help="G reads the data's UV layout (lips, brows, eyes, lashes, beard zone, the hairline's distance, the "
                   "hair's flow, the coordinates) at every resolution from --layout-resolution up (not in the paper); "
                   "may be added on --resume. [off]")
@click.option("--layout-resolution", type=int, help="The lowest resolution whose blocks read the layout. [64]")
@click.option("--layout-gain/--no-layout-gain", default=None,
              help="With --layout: the layout also scales the features G reads it with, texel by texel (SPADE's "
                   "gamma; not in the paper); may be added on --resume. [off]")
@click.option("--normal-knee", type=float,
              help="G's normals' tilts up to this (unit normal) are scaled by --normal-knee-slope, those above shifted "
                   "toward 0 to meet them: flat where the data is flat (not in the paper); may change on --resume. [0: off]")
@click.option("--normal-knee-slope", type=float, help="The tilt knee's slope below the knee, in (0, 1]. [0.2]")
@click.option("--channel-noise", "channel_noise", type=int, multiple=True, metavar="RES",
              help="G's trunk layers at RES^2 scale their noise per channel (StyleGAN1), not by one scalar (StyleGAN2); "
                   "repeatable; may be added on --resume, each channel starting at its layer's scalar (not in the "
                   "paper; docs/brdf_gan.md). [none]")
@click.option("--batch", type=int, help="[4]")
@click.option("--kimg", type=float, help="Train until this many thousand real images. [40]")
@click.option("--r1-gamma", type=float, help="[3.0]")
@click.option("--ada/--no-ada", default=None, help="ADA-style augmentation of D's inputs. [off]")
@click.option("--ada-target", type=click.FloatRange(0, 1, min_open=True, max_open=True),
              help="ADA raises p while E[sign(D(real))] is above this, lowers it below. [0.6]")
@click.option("--ada-color/--no-ada-color", default=None,
              help="ADA's brightness / contrast / saturation of the albedos besides flips and shifts. [on]")
@click.option("--snapshot-kimg", type=float, help="Grid, metrics and checkpoint every this many kimg. [1]")
@click.option("--g-lr", type=float, help="[0.0025]")
@click.option("--d-lr", type=float, help="[0.0025]")
@click.option("--g-top-lr-mul", type=click.FloatRange(min=0, min_open=True),
              help="G's layers at the output resolution train at this multiple of --g-lr, e.g. to let channels added by "
                   "--g-channel-min catch up; may change on --resume (not in the paper). [1]")
@click.option("--g-top-lr-from", type=int,
              help="--g-top-lr-mul applies to G's blocks from this resolution up (0: the output resolution's), e.g. the "
                   "layers --g-channel-base widens; may change on --resume (not in the paper). [0]")
@click.option("--ema-kimg", type=click.FloatRange(min=0, min_open=True),
              help="Half-life of the generator EMA (the shipped G) in kimg. [batch * 10 / 32]")
@click.option("--moment-weight", type=click.FloatRange(min=0),
              help="Pull each fake batch's per-channel mean and std to the data's (not in the paper; it also squeezes the "
                   "spread between samples: 10 took it to 0.7 of the data's in 8 kimg, docs/brdf_gan.md; may change on "
                   "--resume). [0]")
@click.option("--moment-drift-weight", type=click.FloatRange(min=0),
              help="Pull the running (~100-step) per-channel mean and std of G's batches to the data's (not in the paper; may change on --resume). [0]")
@click.option("--link-weight", type=click.FloatRange(min=0),
              help="Pull the running mean link of G's albedo detail to its normals' cavities to the data's (not in the "
                   "paper; may change on --resume). [0]")
@click.option("--coherence-weight", type=click.FloatRange(min=0),
              help="Pull the running per-region orientation coherence of G's albedo (strands on the scalp, isotropic pores "
                   "on the skin) to the data's (not in the paper; may change on --resume). [0]")
@click.option("--band-weight", type=click.FloatRange(min=0),
              help="Pull the running per-region RMS of the two finest bands of G's albedo (pores, grain) to the data's "
                   "(not in the paper; may change on --resume). [0]")
@click.option("--band-levels", type=click.IntRange(1, 3),
              help="How many of the finest bands --band-weight pulls: 1-2, 2-4, 4-8 texels (may change on --resume). [2]")
@click.option("--spectrum-weight", type=click.FloatRange(min=0),
              help="Pull the running per-region spectrum of the finest band of G's albedo to the data's: where the grain "
                   "sits in frequency, against a regular lattice (not in the paper; may change on --resume). [0]")
@click.option("--relief-weight", type=click.FloatRange(min=0),
              help="Pull the running per-region correlation of G's albedo grain with its normals' slope to the data's (~0), "
                   "against an albedo embossed like a relief lit from one side (not in the paper; may change on --resume). [0]")
@click.option("--colour-weight", type=click.FloatRange(min=0),
              help="Pull the running per-region mean and spread of each channel of G's albedo to the data's, against "
                   "regions of the wrong colour (not in the paper; may change on --resume). [0]")
@click.option("--beard-weight", type=click.FloatRange(min=0),
              help="Pull the running mean and mean square of each sample's hair share of the beard zone to the data's, "
                   "against a thin beard on every face where the data has a full one on a few (not in the paper; may "
                   "change on --resume). [0]")
@click.option("--tone-weight", type=click.FloatRange(min=0),
              help="Pull the running mean of each sample's per-region mean albedo, and the running variance of it "
                   "within each batch, to the data's (the eye openings left out): the spread of skin tones between "
                   "samples, against a narrowed range of tones (not in the paper; may change on --resume). [0]")
@click.option("--crown-weight", type=click.FloatRange(min=0),
              help="Pull the running mean of the hair's direction across the crown, column by column, to the data's: "
                   "strands fanning out from the whorl at the top centre, against a left and a right field meeting in "
                   "a line (not in the paper; may change on --resume). [0]")
@click.option("--mean-map-weight", type=click.FloatRange(min=0),
              help="Pull the running mean of G's maps, texel by texel, to the data's mean maps, against whatever G "
                   "draws at the same place in every sample: a line down the crown, a rim along the hairline "
                   "(not in the paper; may change on --resume). [0]")
@click.option("--tone-order-weight", type=click.FloatRange(min=0),
              help="Pull the running mean of each batch's sorted per-region mean albedos, less the batch's mean, to "
                   "the data's expected order statistics: the skew of the tones (a long tail of fair skin), which the "
                   "tone term's mean and variance do not pin (not in the paper; may change on --resume). [0]")
@click.option("--detail-map-weight", type=click.FloatRange(min=0),
              help="Pull the running mean of where G's maps have fine detail, texel by texel, to the data's, against a "
                   "band without strands down the crown, whatever its sign (not in the paper; may change on --resume). [0]")
@click.option("--tone-band-weight", type=click.FloatRange(min=0),
              help="The band term's pull taken apart by skin tone: each region's band RMS of the log albedo on the darker and "
                   "on the lighter half of each batch, against mottled dark skin and smooth fair skin (uses --band-levels; "
                   "not in the paper; may change on --resume). [0]")
@click.option("--chroma-band-weight", type=click.FloatRange(min=0),
              help="The tone-band term on colour: each region's band RMS of the albedo's log chromaticity (red-green, "
                   "yellow-blue) on the darker and on the lighter half of each batch, against blotches of colour (uses "
                   "--band-levels; not in the paper; may change on --resume). [0]")
@click.option("--specular-band-weight", type=click.FloatRange(min=0),
              help="The band term on the specular albedo: each region's RMS of its finest bands to the data's, against "
                   "a specular grain too coarse (uses --band-levels; not in the paper; may change on --resume). [0]")
@click.option("--grain-weight", type=click.FloatRange(min=0),
              help="Pull each region's single-texel grain (mean |Laplacian|) of the albedo and the specular to the "
                   "data's, against grain that sits in the finest band's lower part (not in the paper; may change on "
                   "--resume). [0]")
@click.option("--lattice-weight", type=click.FloatRange(min=0),
              help="Pull each channel's texel-lattice ratios (rows and columns alternating, the border rows' and columns' "
                   "steps against the inner ones') to the data's, against an upsampling's texel pairs and a seam at the "
                   "borders (not in the paper; may change on --resume). [0]")
@click.option("--chroma-grain-weight", type=click.FloatRange(min=0),
              help="Pull each region's single-texel grain of the albedo's log chromaticity to the data's, against colour "
                   "fringes and coloured rim texels (not in the paper; may change on --resume). [0]")
@click.option("--specular-link-weight", type=click.FloatRange(min=0),
              help="Pull each region's correlation of the specular's finest band with the normals' divergence to the "
                   "data's, against a specular whose pores do not follow the normals (not in the paper; may change on "
                   "--resume). [0]")
@click.option("--specular-spectrum-weight", type=click.FloatRange(min=0),
              help="Pull the running per-region spectrum of the finest band of G's specular albedo to the data's, "
                   "against a cross-hatch where the data has sparse pore dots (not in the paper; may change on "
                   "--resume). [0]")
@click.option("--texel-tail-weight", type=click.FloatRange(min=0),
              help="Pull each region's share of single-texel pits and bumps in G's albedo and specular to the data's: "
                   "crisp dark dots (pores, moles) against detail that is as often a bright bump (not in the paper; "
                   "may change on --resume). [0]")
@click.option("--eye-ring-weight", type=click.FloatRange(min=0),
              help="Pull the profile of G's log albedo around the eye openings (each band of skin nearest them against "
                   "the skin beyond) and the openings' flatness to the data's, against a dark ring (\"eyeshadow\") and "
                   "mottled eyeballs (not in the paper; may change on --resume). [0]")
@click.option("--edge-sharpness-weight", type=click.FloatRange(min=0),
              help="Pull each region's edge sharpness in G's albedo (how much of a change across 4 texels happens in "
                   "one step) to the data's, against soft or doubled hair, brow and lip edges (not in the paper; may "
                   "change on --resume). [0]")
@click.option("--chroma-edge-weight", type=click.FloatRange(min=0),
              help="The edge-sharpness term on the albedo's log chromaticity: colour that steps in one texel at an "
                   "edge, not a fringe fading over several (not in the paper; may change on --resume). [0]")
@click.option("--specular-slope-weight", type=click.FloatRange(min=0),
              help="Pull each region's correlation of the specular's slope with the normals' tilt to the data's, "
                   "against a specular that is not its strands' and pores' height (not in the paper; may change on "
                   "--resume). [0]")
@click.option("--forehead-rows-weight", type=click.FloatRange(min=0),
              help="Pull the profile of G's albedo colour down the forehead's rows (each row against the forehead, and "
                   "its absolute value) to the data's flat one, against a coloured band across the forehead (not in the "
                   "paper; may change on --resume). [0]")
@click.option("--albedo-specular-link-weight", type=click.FloatRange(min=0),
              help="Pull each region's correlation of G's albedo grain with its specular grain, and its spread "
                   "between samples, to the data's, whose pores and speckles are one field in both maps (not in the "
                   "paper; may change on --resume). [0]")
@click.option("--hairline-edge-weight", type=click.FloatRange(min=0),
              help="Pull how smooth G's hairline outline runs (the orientation coherence of its edge), and its spread "
                   "between samples, to the data's ragged outlines (not in the paper; may change on --resume). [0]")
@click.option("--hairline-specks-weight", type=click.FloatRange(min=0),
              help="Pull how far texels along G's hairline fall below the darker of its skin and hair (dark specks) "
                   "to the data's, relative to it (not in the paper; may change on --resume). [0]")
@click.option("--beard-band-weight", type=click.FloatRange(min=0),
              help="Pull the fine texture of G's beards (the log luminance's three finest bands over the beard zone, "
                   "weighted by each face's hair share there) to the data's, each band relative to its target (not in "
                   "the paper; may change on --resume). [0]")
@click.option("--relief-band-weight", type=click.FloatRange(min=0),
              help="Pull each region's correlation of G's albedo luminance (2-8 texels), chromaticity and specular "
                   "(1-8 texels) with its normals' x and y to the data's ~0: against bumps embossed into the albedo "
                   "(not in the paper; may change on --resume). [0]")
@click.option("--nyquist-weight", type=click.FloatRange(min=0),
              help="Pull each map's energy on the Nyquist row and column over the octave below, around the diagonal "
                   "corner, and in the spectrum's top two bands over 1/4-3/8 cycle (albedo, specular, normals x and "
                   "y; over the whole map and the face), and their spreads between samples, to the data's: against a "
                   "texel checkerboard and a peak below Nyquist (not in the paper; may change on --resume). [0]")
@click.option("--normal-symmetry-weight", type=click.FloatRange(min=0),
              help="Pull each region's skewness of G's normals' x and y and their correlation, in the two finest "
                   "bands, to the data's ~0: against bumps tilted one way more than the other (not in the paper; may "
                   "change on --resume). [0]")
@click.option("--texel-neighbour-weight", type=click.FloatRange(min=0),
              help="Pull how smooth each region's finest band runs from texel to texel (its correlation with the "
                   "next texel along u and v; log luminance and chromaticity, specular, normals x and y) to the "
                   "data's (not in the paper; may change on --resume). [0]")
@click.option("--mouth-rows-weight", type=click.FloatRange(min=0),
              help="Pull each row's log luminance and chromaticity on the lips and on the skin around them, against "
                   "the whole lips' or ring's, to the data's: against bands across the lip and casts around the mouth "
                   "(not in the paper; may change on --resume). [0]")
@click.option("--screen-weight", type=click.FloatRange(min=0),
              help="Pull every per-region band statistic of the screen (variance, skewness, kurtosis, neighbour and "
                   "pair correlations, Nyquist ratio) to the data's mean, in units of the data's spread (not in the "
                   "paper; may change on --resume; ~0.5 s per step). [0]")
@click.option("--screen-levels", type=click.IntRange(1, 4),
              help="Finest Laplacian bands the screen term measures. [3]")
@click.option("--specular-quantile-weight", type=click.FloatRange(min=0),
              help="Pull each region's quantiles of G's specular (0.1 % to 99 %) to the data's, in units of the "
                   "data's spread: against a darkest specular too light or too dark (not in the paper; may change on "
                   "--resume). [0]")
@click.option("--range-map-weight", type=click.FloatRange(min=0),
              help="Pull G's mean 3x3 range of each map, texel by texel as the sheet shows it, to the data's: against "
                   "grain where the data is flat or smooth (not in the paper; may change on --resume). [0]")
@click.option("--range-quantile-weight", type=click.FloatRange(min=0),
              help="Pull each region's quantiles of that range (0.5 % to 99 %) to the data's, in units of the data's "
                   "spread: its share of flat texels and the spread of its grain (not in the paper; may change on "
                   "--resume). [0]")
@click.option("--eye-flat-weight", type=click.FloatRange(min=0),
              help="Pull each sample's eye openings' grain and colour on the sheet, each with the skin's tone around "
                   "them, to the data's in units of its spread: the data's are flat on dark skin and grainier on fair "
                   "(not in the paper; may change on --resume). [0]")
@click.option("--brow-profile-weight", type=click.FloatRange(min=0),
              help="Pull each sample's profile across the brows (lightness, colour and specular, top to bottom along "
                   "their arch) to the data's in units of its spread: the data's brows are as dark or light in the "
                   "middle as at their edges, without a stripe or a halo (not in the paper; may change on --resume). [0]")
@click.option("--lip-ring-weight", type=click.FloatRange(min=0),
              help="Pull each sample's lips and the skin around them, in bands of distance above and below, against "
                   "the skin further out, to the data's in units of its spread: the data's skin is as light next to "
                   "the lips as beyond, without a halo or a light patch above the upper lip (not in the paper; may "
                   "change on --resume). [0]")
@click.option("--grain-evenness-weight", type=click.FloatRange(min=0),
              help="Pull each sample's evenness of the fine grain (the albedo's and the specular's, per region, over "
                   "8x8-texel tiles at 256^2) to the data's in units of its spread: the data's grain is even where "
                   "G's came in patches (not in the paper; may change on --resume). [0]")
@click.option("--specular-sobel-weight", type=click.FloatRange(min=0),
              help="Pull each sample's correlation of the specular's Sobel slopes with the normals' tilt, per region, to "
                   "the data's in units of its spread: the data's hair normals are the slopes of its specular, where "
                   "G's followed it more loosely (not in the paper; may change on --resume). [0]")
@click.option("--normal-spectrum-weight", type=click.FloatRange(min=0),
              help="The spectrum term on the normals' x and y: pull each region's spectrum of their finest band to the "
                   "data's: G's sat too low in frequency, the neck's most (not in the paper; may change on "
                   "--resume). [0]")
@click.option("--normal-tilt-weight", type=click.FloatRange(min=0),
              help="Pull each sample's mean tilt of the normals per region, and its share of normals that point "
                   "straight out, to the data's in units of its spread: G's tilt varied from face to face more and "
                   "its normals leaned where the data's are flat (not in the paper; may change on --resume). [0]")
@click.option("--specular-law-weight", type=click.FloatRange(min=0),
              help="Pull how closely each sample's hair albedo (luminance and tint) follows its specular, over the "
                   "scalp and the hairline, to the data's in units of its spread: the data's dark hair follows it "
                   "exactly and G's more loosely (not in the paper; may change on --resume). [0]")
@click.option("--grain-overlap-weight", type=click.FloatRange(min=0),
              help="Pull, per region, how much the albedo's finest grain and the normals' bumps sit on the same "
                   "texels to the data's in units of its spread: G's overlapped too little on the body and too much "
                   "in the hair (not in the paper; may change on --resume). [0]")
@click.option("--normal-radial-weight", type=click.FloatRange(min=0),
              help="Pull the shape of each sample's normal spectrum, ring by ring up to Nyquist, over the whole map "
                   "and the face, to the data's in units of its spread: G's finest ring held too little energy (not "
                   "in the paper; may change on --resume). [0]")
@click.option("--sheet-radial-weight", type=click.FloatRange(min=0),
              help="The normal-radial term on all four maps as the blind test's sheet shows them (sRGB albedo, x3 "
                   "sRGB specular, clamped normals) (not in the paper; may change on --resume). [0]")
@click.option("--lattice-phase-weight", type=click.FloatRange(min=0),
              help="Pull each sample's texel lattice (the mean step between rows and columns by their index mod 4, "
                   "every channel) to the data's in units of its spread: G's parities were off both ways from sample "
                   "to sample, which the lattice term's batch mean cancels (not in the paper; may change on "
                   "--resume). [0]")
@click.option("--strip-radial-weight", type=click.FloatRange(min=0),
              help="The sheet-radial term on the top quarter (the top of the scalp) and the bottom quarter (the neck "
                   "and body) apart, each the mean of its square tiles' rings (not in the paper; may change on "
                   "--resume). [0]")
@click.option("--strip-slope-link-weight", type=click.FloatRange(min=0),
              help="On the same two strips, pull how closely the sheet's normals follow the sheet's specular's Sobel "
                   "slopes, both less a 5x5 box mean, to the data's in units of its spread (not in the paper; may "
                   "change on --resume). [0]")
@click.option("--hair-law-tail-weight", type=click.FloatRange(min=0),
              help="Pull how tightly each sample's hair albedo follows its specular (the upper edge's blur and the "
                   "spread of the luminance in bins of the specular's rank) to the data's in units of its spread (not "
                   "in the paper; may change on --resume). [0]")
@click.option("--sheet-axis-weight", type=click.FloatRange(min=0),
              help="Pull the shape of each sample's sheet normals' 1-D spectrum along u and along v, in 1/32-cycle "
                   "bands from 5/16 up to Nyquist, to the data's in units of its spread (not in the paper; may change "
                   "on --resume). [0]")
@click.option("--mottle-weight", type=click.FloatRange(min=0),
              help="Pull each region's light and dark patches (the RMS of the log albedo luminance's 8-16 and 16-32 "
                   "texel bands) to the data's in units of its spread (not in the paper; may change on --resume). [0]")
@click.option("--beard-specular-weight", type=click.FloatRange(min=0),
              help="Pull how tightly the specular follows the albedo's beard (the hair-share-weighted correlation of "
                   "their three finest bands over the beard zone) to the data's in units of its spread (not in the "
                   "paper; may change on --resume). [0]")
@click.option("--brow-hair-weight", type=click.FloatRange(min=0),
              help="Pull the colour of each face's brows less its hair's (the log chromaticity of each region's "
                   "darkest 30 % of texels) and its spread between faces to the data's in units of its spread: brows "
                   "coloured as the hair (not in the paper; may change on --resume). [0]")
@click.option("--beard-texture-weight", type=click.FloatRange(min=0),
              help="Pull the shape of each face's beard (the skewness, kurtosis and texel-to-texel correlation of "
                   "the log luminance's and log specular's three finest bands over the beard zone, times its hair "
                   "share) to the data's in units of its spread: even speckle or strands, not stains and clumps (not "
                   "in the paper; may change on --resume). [0]")
@click.option("--beard-share-weight", type=click.FloatRange(min=0),
              help="Pull the share of faces whose beard zone is more than 10, 20, 30, 50, 70 and 90 % hair to the "
                   "data's: a beard or none, not a faint haze on many faces (not in the paper; may change on "
                   "--resume). [0]")
@click.option("--gamut-weight", type=click.FloatRange(min=0),
              help="Penalise texels of G's albedo outside the data's hue gamut r >= g >= b (greenish skin, blue casts "
                   "in hair), which D did not learn (not in the paper; may change on --resume). [0]")
@click.option("--hairline-share-weight", type=click.FloatRange(min=0),
              help="Pull the running mean and mean square of each sample's hair share of the hairline and the scalp behind "
                   "it to the data's, against the same hairline on every face where the data's recedes on some (not in the "
                   "paper; may change on --resume). [0]")
@click.option("--hairline-region/--no-hairline-region", default=None,
              help="The per-region terms also measure the data's hairline as a region of its own, against a soft "
                   "hairline (not in the paper; may change on --resume). [off]")
@click.option("--side-regions/--no-side-regions", default=None,
              help="The per-region terms measure each region's left and right halves apart, against grain pulled onto one "
                   "side (not in the paper; may change on --resume). [off]")
@click.option("--eye-region/--no-eye-region", default=None,
              help="The per-region terms also measure the data's eye openings as a region of their own, against blobs "
                   "where the data paints a flat grey eyeball (not in the paper; may change on --resume). [off]")
@click.option("--brow-edge-region/--no-brow-edge-region", default=None,
              help="The per-region terms also measure a ring along the data's brow edges as a region of its own, against "
                   "soft brows (not in the paper; may change on --resume). [off]")
@click.option("--drift-on-ema/--no-drift-on-ema", default=None,
              help="The drift terms' running means follow G_ema's maps (the model that ships) instead of the training "
                   "G's; one more forward pass per step (not in the paper; may change on --resume, which then restarts "
                   "the running means; tried once, unstable: docs/brdf_gan.md). [off]")
@click.option("--patch-weight", type=click.FloatRange(min=0),
              help="A second, local D on random crops of the maps at full resolution, with more features per texel than "
                   "D's top layers, against soft hairlines, hazy skin and smeared strands; its weight in G's loss (not in "
                   "the paper; may change on --resume: a local D first turned on, or resized, starts fresh). [0]")
@click.option("--patch-size", type=click.IntRange(min=8), help="The local D's crop size (a power of two). [64]")
@click.option("--patch-count", type=click.IntRange(min=1), help="The local D's crops per map. [4]")
@click.option("--patch-channels", type=click.IntRange(1, 128), help="The local D's features per texel at the crop size. [32]")
@click.option("--patch-r1-gamma", type=click.FloatRange(min=0), help="The local D's R1 weight. [0.05]")
@click.option("--patch-focus", type=click.FloatRange(0, 1),
              help="Share of the local D's crops centred on the hairline and the beard zone, where the person test's "
                   "tells are, instead of anywhere (may change on --resume). [0]")
@click.option("--branch-noise", type=click.FloatRange(-1, 1),
              help="Set the noise strength of every per-modality layer at the start (resume included); StyleGAN2 starts "
                   "them at 0, where they stay (not in the paper; docs/brdf_gan.md). [unchanged]")
@click.option("--trunk-noise", "trunk_noise", multiple=True, callback=_res_strength, metavar="RES:S",
              help="Set the noise strength of both layers of the trunk's RES^2 block at the start (resume included), "
                   "e.g. 16:0.2; repeatable. StyleGAN2 starts them at 0, where they stay (not in the paper; "
                   "docs/brdf_gan.md). [unchanged]")
@click.option("--seed", type=int, help="[0]")
@click.option("--limit", type=int, help="Use only the first N samples of DATA_DIR.")
@click.option("--threads", type=int, help="torch CPU threads (default: all cores).")
@click.option("--bf16/--no-bf16", default=None,
              help="Run G's and D's forward passes under bfloat16 autocast (weights, Adam and losses stay float32): "
                   "1.1-1.3x faster steps on a CPU with AVX512-BF16 (measured); a CPU without bfloat16 instructions "
                   "emulates them, with a warning; may change on --resume (not in the paper). [off]")
@click.option("--compile", "compile_g", is_flag=True,
              help="torch.compile G's synthesis: ~1.3x faster training steps on CPU after a minute of "
                   "compiling; needs a C++ compiler; a compiled run does not resume bit-exactly.")
def command(data_dir: Path, run_dir: Path, config: Path | None, resume: bool, limit: int | None, threads: int | None,
            branch_noise: float | None, trunk_noise: tuple[tuple[int, float], ...], compile_g: bool,
            **flags) -> None:
    """Train BRDF-GAN on DATA_DIR (NAME_albedo/_specular/_normals maps, PNG or EXR).

    Every --snapshot-kimg it writes RUN_DIR/samples/kimgNNNN.NN.png (8 rows of A_D | A_S | N_S for fixed
    latents), appends to RUN_DIR/metrics.jsonl and saves RUN_DIR/checkpoint.safetensors, from which
    --resume continues exactly (without --compile). Ctrl-C or SIGTERM (kill) ends the current step and saves a
    checkpoint; a second Ctrl-C stops at once.

    \b
    Example:
      fitme dataset data/ -n 2000 --size 256
      fitme train data/ -o runs/brdf_gan --kimg 40
      fitme train data/ -o runs/brdf_gan --resume --kimg 60
    """
    import dataclasses

    import torch

    from ..errors import InputNotFound, OutputNotWritable
    from ..io.atomic import atomic_write_bytes
    from ..reflectance.gan.data import LAYOUT_CHANNELS, find_samples, layout_image, load_dataset, load_regions
    from ..reflectance.gan.metrics import detail_region
    from ..reflectance.gan.networks import GanSettings
    from ..reflectance.gan.train import (TrainSettings, can_bf16, can_compile, clear_running, compile_synthesis, load_checkpoint,
                                         new_state, reset_mean_image, save_checkpoint, set_branch_noise, set_layout_image,
                                         set_trunk_noise,
                                         set_learning_rates, sync_patch_discriminator, train)

    find_samples(data_dir)  # a missing or empty data folder fails before anything else
    if compile_g and not can_compile():
        raise click.UsageError("--compile needs a C++ compiler (g++ or clang++) on PATH for torch.compile's CPU "
                               "backend; train without --compile")
    if threads:
        torch.set_num_threads(threads)
    cfg: dict[str, dict] = {"gan": {}, "train": {}}
    if config is not None:
        if not config.is_file():
            raise InputNotFound("config file not found", config)
        try:
            user = json.loads(config.read_text())
        except json.JSONDecodeError as e:
            raise click.BadParameter(f"{config} is not valid JSON: {e}") from None
        for part in ("gan", "train"):
            cfg[part].update(user.get(part, {}))
    for name in _GAN_FLAGS:
        if flags.get(name) is not None:
            cfg["gan"][name] = flags[name]
    channel_noise = flags.pop("channel_noise")  # repeatable: () when not given; adds to a config file's
    if channel_noise or "channel_noise" in cfg["gan"]:
        cfg["gan"]["channel_noise"] = tuple(sorted(set(cfg["gan"].get("channel_noise", ())) | set(channel_noise)))
    if flags.get("layout") is not None:
        cfg["gan"]["layout_channels"] = len(LAYOUT_CHANNELS) if flags["layout"] else 0
    if cfg["gan"].get("layout_channels", 0) not in (0, len(LAYOUT_CHANNELS)):
        raise click.BadParameter(f"layout_channels must be 0 or {len(LAYOUT_CHANNELS)} (data.LAYOUT_CHANNELS), "
                                 f"got {cfg['gan']['layout_channels']}")
    if "resolution" in cfg["gan"] and "branch_resolution" not in cfg["gan"]:
        cfg["gan"]["branch_resolution"] = cfg["gan"]["resolution"]  # branch the top block, as by default
    for name in _TRAIN_FLAGS:
        if flags.get(name) is not None:
            cfg["train"][name] = flags[name]
    try:
        train_settings = TrainSettings(**cfg["train"])
        # on --resume --layout-gain may rest on the run's own layout inputs: widen_state checks it against the run
        gan_settings = GanSettings(**(dict(cfg["gan"], layout_gain=False) if resume else cfg["gan"]))
    except (TypeError, ValueError) as e:
        raise click.BadParameter(str(e)) from None
    if train_settings.crown_weight > 0 and gan_settings.resolution % 128:
        raise click.BadParameter(f"--crown-weight needs a resolution that is a multiple of 128 (its window's bins are "
                                 f"R / 128 texels), got {gan_settings.resolution}")
    if train_settings.patch_weight > 0 and train_settings.patch_size > gan_settings.resolution:
        raise click.BadParameter(f"--patch-size {train_settings.patch_size} exceeds the maps' resolution "
                                 f"{gan_settings.resolution}")

    ckpt = run_dir / "checkpoint.safetensors"
    if resume:
        if not ckpt.is_file():
            raise InputNotFound("nothing to resume: no checkpoint.safetensors in the run directory", run_dir)
        state = load_checkpoint(ckpt)
        # the run length, snapshot cadence, augmentation (on or off, its target, colour), learning rates and EMA
        # half-life may change on resume (turning ADA on when D starts to overfit, or lowering the rates,
        # are the usual moves); the rest is the run's own, and saying otherwise is an error
        changeable = [k for k in _TRAIN_FLAGS if k not in _FIXED_ON_RESUME]
        fixed = [k for k in _FIXED_ON_RESUME if flags.get(k) is not None and flags[k] != getattr(state.train, k)]
        if fixed:
            raise click.BadParameter(f"{', '.join('--' + k.replace('_', '-') for k in fixed)} cannot change on --resume "
                                     f"(the run has {', '.join(f'{k}={getattr(state.train, k)}' for k in fixed)})")
        # ADA comes from its flag only (a config file's "ada" keeps the run's own, as before)
        new = {k: v for k, v in cfg["train"].items() if k in changeable and k != "ada"}
        if flags.get("ada") is not None:
            new["ada"] = flags["ada"]
        if new.get("drift_on_ema", state.train.drift_on_ema) != state.train.drift_on_ema:
            clear_running(state)  # they followed the other generator: ``train`` restarts them from the one now tracked
        state.train = dataclasses.replace(state.train, **new)
        set_learning_rates(state)
        try:
            if sync_patch_discriminator(state):
                click.echo(f"a fresh local D on {state.train.patch_size}x{state.train.patch_size} crops", err=True)
        except ValueError as e:
            raise click.BadParameter(str(e)) from None
        # the architecture is the run's own, except that its channels may grow (gan/widen.py: the wider
        # networks start out computing what the trained ones did)
        _check_layout_resolution(flags, cfg["gan"].get("layout_channels", state.gan.layout_channels))
        if "channel_noise" in cfg["gan"]:  # the resolutions to add to the run's own
            cfg["gan"]["channel_noise"] = tuple(sorted(set(cfg["gan"]["channel_noise"]) | set(state.gan.channel_noise)))
        grown = {k: v for k, v in cfg["gan"].items() if getattr(state.gan, k) != v}
        if grown:
            from ..reflectance.gan.widen import widen_state

            before = state.gan
            try:
                state = widen_state(state, dataclasses.replace(state.gan, **grown))
            except ValueError as e:
                raise click.BadParameter(f"{e} (on --resume only --channel-base, --channel-max, --g-channel-min and "
                                         "--g-channel-base may grow, --d-joint-branch, --layout, --layout-gain and "
                                         "--channel-noise be added, and "
                                         "--normal-knee and --normal-knee-slope change)") from None
            grew = [f"{who}'s {r}x{r} {old(r)} -> {new(r)}" for who, old, new in
                    (("G", before.g_channels, state.gan.g_channels), ("D", before.channels, state.gan.channels))
                    for r in before.resolutions if old(r) != new(r)]
            if grew:
                click.echo(f"widened: {', '.join(grew)} channels", err=True)
            if state.gan.d_joint_branch and not before.d_joint_branch:
                click.echo("added D's joint branch (albedos and normals together)", err=True)
            if state.gan.layout_channels and not before.layout_channels:
                click.echo(f"added G's layout inputs ({state.gan.layout_channels} maps from "
                           f"{state.gan.layout_resolution}x{state.gan.layout_resolution})", err=True)
            if state.gan.layout_gain and not before.layout_gain:
                click.echo("added G's layout gain", err=True)
            if state.gan.channel_noise != before.channel_noise:
                click.echo(f"G's noise per channel at {', '.join(f'{r}x{r}' for r in state.gan.channel_noise)}", err=True)
            knee = (state.gan.normal_knee, state.gan.normal_knee_slope)
            if knee != (before.normal_knee, before.normal_knee_slope):
                click.echo(f"G's tilt knee {before.normal_knee:g} (slope {before.normal_knee_slope:g}) -> {knee[0]:g} "
                           f"(slope {knee[1]:g})", err=True)
            if not grew and (state.gan.d_joint_branch, state.gan.layout_channels, state.gan.layout_gain,
                             state.gan.channel_noise) == (before.d_joint_branch, before.layout_channels,
                                                          before.layout_gain, before.channel_noise):
                click.echo("no layer changes width", err=True)
            run_cfg = run_dir / "config.json"
            kept = json.loads(run_cfg.read_text()) if run_cfg.is_file() else {}
            # atomic: the run's only record of its settings besides the checkpoint
            atomic_write_bytes(run_cfg, json.dumps({**kept, "gan": dataclasses.asdict(state.gan)}, indent=2).encode())
        gan_settings = state.gan
        click.echo(f"resuming at {state.nimg / 1000:.2f} kimg", err=True)
    else:
        _check_layout_resolution(flags, gan_settings.layout_channels)
        if ckpt.exists():
            raise OutputNotWritable("the run directory has a checkpoint; pass --resume to continue it or choose another directory", run_dir)
        try:
            run_dir.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise OutputNotWritable(f"cannot create run directory: {e.strerror}", run_dir) from None
        state = None
        atomic_write_bytes(run_dir / "config.json", json.dumps({"gan": dataclasses.asdict(gan_settings),
                                                                "train": dataclasses.asdict(train_settings),
                                                                "data": str(data_dir.resolve())}, indent=2).encode())
    data = load_dataset(data_dir, gan_settings, limit=limit, progress=True)
    if state is None:
        state = new_state(gan_settings, train_settings, data_mean=data.float().mean(0))
    elif state.learned_mean_image:
        reset_mean_image(state, data.float().mean(0))
        click.echo("the checkpoint's mean image was trained (before it became fixed): reset to the data mean", err=True)
    if state.gan.layout_channels and not state.G.synthesis.layout_image.any():  # a new run, or the inputs just added
        set_layout_image(state, layout_image(gan_settings.resolution))
    if state.train.link_weight > 0:
        state.link_mask = detail_region(load_regions(gan_settings.resolution))  # where --link-weight measures
    if state.train.region_terms:
        # where the per-region terms measure
        state.regions = load_regions(gan_settings.resolution, hairline=state.train.hairline_region,
                                     sides=state.train.side_regions, eyes=state.train.eye_region,
                                     brows=state.train.brow_edge_region)
    if branch_noise is not None:
        set_branch_noise(state, branch_noise)
        click.echo(f"branched layers' noise strength set to {branch_noise}", err=True)
    for res, strength in trunk_noise:
        try:
            set_trunk_noise(state, res, strength)
        except ValueError as e:
            raise click.BadParameter(str(e), param_hint="--trunk-noise") from None
        click.echo(f"the trunk's {res}^2 noise strength set to {strength}", err=True)
    if state.train.bf16 and not can_bf16():
        click.echo("warning: this CPU has no bfloat16 instructions; --bf16 is emulated and likely slower than float32",
                   err=True)
    if compile_g:
        compile_synthesis(state)
        click.echo("G's synthesis is compiled on the first G and D steps (about a minute each)", err=True)
    click.echo(f"{len(data)} samples at {gan_settings.resolution}^2; G {sum(p.numel() for p in state.G.parameters()) / 1e6:.2f}M, "
               f"D {sum(p.numel() for p in state.D.parameters()) / 1e6:.2f}M parameters"
               + (f", local D {sum(p.numel() for p in state.D_patch.parameters()) / 1e6:.2f}M" if state.D_patch else ""), err=True)
    with _stop_requests() as stops:
        try:
            train(state, data, run_dir, stop=lambda: bool(stops))
        except KeyboardInterrupt:
            save_checkpoint(state, ckpt)
            click.echo(f"interrupted mid-step: checkpoint saved at {state.nimg / 1000:.2f} kimg (a resume from it is not "
                       "bit-exact)", err=True)
            raise
    if stops:
        save_checkpoint(state, ckpt)
        name = signal.Signals(stops[0]).name
        how = "from there (compiled, so not bit-exactly)" if compile_g else "exactly"
        click.echo(f"stopped by {name}: checkpoint saved at {state.nimg / 1000:.2f} kimg; --resume continues {how}",
                   err=True)
        raise SystemExit(128 + stops[0])
    click.echo(f"done: {state.nimg / 1000:.2f} kimg in {state.wall_time / 3600:.2f} h of training; {ckpt}")
