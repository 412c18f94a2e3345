"""G's layout inputs (``GanSettings.layout_channels``): the split modulated conv against its concatenated reference,
the networks that read the layout, widening a trained run to them, the layout maps, and the train command."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from click.testing import CliRunner

from fitme_cli.reflectance.gan import ops
from fitme_cli.reflectance.gan.networks import GanSettings, Generator
from fitme_cli.reflectance.gan.train import TrainSettings, load_checkpoint, new_state, save_checkpoint, set_layout_image

TINY = GanSettings(resolution=16, branch_resolution=8, channel_base=64, channel_max=16, z_dim=32, w_dim=32)
K = 3
LAYOUT = dataclasses.replace(TINY, layout_channels=K, layout_resolution=8)


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)


def _perturbed(state):
    """Every weight matters: trained-looking biases, noise, colours, and non-zero layout weights."""
    with torch.no_grad():
        for p in state.G.parameters():
            p.add_(0.1 * torch.randn_like(p))
        state.G_ema.load_state_dict(state.G.state_dict())
    return state


# --- the op ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("demodulate", [True, False])
@pytest.mark.parametrize("extra_batch", [1, 3])
def test_split_modulated_conv_is_the_conv_of_the_concatenation(demodulate, extra_batch):
    x = torch.randn(3, 4, 8, 8, dtype=torch.float64)
    extra = torch.randn(extra_batch, 2, 8, 8, dtype=torch.float64)
    for k in (3, 1):
        w = torch.randn(5, 6, k, k, dtype=torch.float64)
        s = torch.randn(3, 6, dtype=torch.float64)
        fast = ops.modulated_conv2d_extra(x, extra, w, s, demodulate)
        assert fast.shape == (3, 5, 8, 8)
        torch.testing.assert_close(fast, ops._modulated_conv2d_extra_ref(x, extra, w, s, demodulate), rtol=1e-10, atol=1e-10)
    # known values: a zero extra's weights change nothing but, demodulated, the norm; zero weights on it change nothing
    w = torch.randn(5, 6, 3, 3, dtype=torch.float64)
    s = torch.randn(3, 6, dtype=torch.float64)
    w0 = w.clone()
    w0[:, 4:] = 0
    torch.testing.assert_close(ops.modulated_conv2d_extra(x, extra, w0, s, demodulate),
                               ops.modulated_conv2d(x, w[:, :4], s[:, :4], demodulate), rtol=1e-10, atol=1e-10)


def test_split_modulated_conv_gradients_match_the_reference_and_check():
    x = torch.randn(2, 3, 4, 4, dtype=torch.float64, requires_grad=True)
    w = torch.randn(2, 5, 3, 3, dtype=torch.float64, requires_grad=True)
    s = torch.randn(2, 5, dtype=torch.float64, requires_grad=True)
    extra = torch.randn(1, 2, 4, 4, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda *a: ops.modulated_conv2d_extra(a[0], extra, *a[1:]), (x, w, s))
    g_fast = torch.autograd.grad(ops.modulated_conv2d_extra(x, extra, w, s).square().sum(), (x, w, s))
    g_ref = torch.autograd.grad(ops._modulated_conv2d_extra_ref(x, extra, w, s).square().sum(), (x, w, s))
    for a, b in zip(g_fast, g_ref):
        torch.testing.assert_close(a, b)


def test_split_modulated_conv_refuses_mismatched_inputs():
    x, w, s = torch.randn(2, 3, 4, 4), torch.randn(2, 5, 3, 3), torch.randn(2, 5)
    with pytest.raises(ValueError, match=r"extra \(2, 2, 8, 8\)"):
        ops.modulated_conv2d_extra(x, torch.randn(2, 2, 8, 8), w, s)
    with pytest.raises(ValueError, match=r"extra \(3, 2, 4, 4\)"):
        ops.modulated_conv2d_extra(x, torch.randn(3, 2, 4, 4), w, s)
    with pytest.raises(ValueError, match=r"weight \(2, 5, 3, 3\), styles \(2, 4\)"):
        ops.modulated_conv2d_extra(x, torch.randn(1, 2, 4, 4), w, torch.randn(2, 4))
    with pytest.raises(ValueError, match=r"weight \(2, 6, 3, 3\)"):
        ops.modulated_conv2d_extra(x, torch.randn(1, 2, 4, 4), torch.randn(2, 6, 3, 3), torch.randn(2, 6))


def test_spatial_gain_scales_each_channel_by_its_mix_of_the_maps():
    x = torch.randn(3, 4, 5, 6, dtype=torch.float64)
    for b in (1, 3):
        layout = torch.randn(b, 2, 5, 6, dtype=torch.float64)
        w = torch.randn(4, 2, dtype=torch.float64)
        out = ops.spatial_gain(x, layout, w)
        assert out.shape == x.shape and out.dtype == x.dtype
        torch.testing.assert_close(out, ops._spatial_gain_ref(x, layout, w), rtol=1e-12, atol=1e-12)
    # known values: zero weights change nothing; a weight of -1 on a mask of ones silences that channel inside it
    layout = torch.zeros(1, 2, 5, 6, dtype=torch.float64)
    layout[0, 1, 1:3, 2:4] = 1
    assert torch.equal(ops.spatial_gain(x, layout, torch.zeros(4, 2, dtype=torch.float64)), x)
    w = torch.zeros(4, 2, dtype=torch.float64)
    w[2, 1] = -1
    out = ops.spatial_gain(x, layout, w)
    assert (out[:, 2, 1:3, 2:4] == 0).all()
    inside = torch.zeros(5, 6, dtype=torch.bool)
    inside[1:3, 2:4] = True
    assert torch.equal(out[:, 2][:, ~inside], x[:, 2][:, ~inside]) and torch.equal(out[:, [0, 1, 3]], x[:, [0, 1, 3]])
    # gradients: float64 gradcheck, and the same as the reference's
    x = torch.randn(2, 3, 4, 4, dtype=torch.float64, requires_grad=True)
    layout = torch.randn(1, 2, 4, 4, dtype=torch.float64)
    w = torch.randn(3, 2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: ops.spatial_gain(a, layout, b), (x, w))
    g_fast = torch.autograd.grad(ops.spatial_gain(x, layout, w).square().sum(), (x, w))
    g_ref = torch.autograd.grad(ops._spatial_gain_ref(x, layout, w).square().sum(), (x, w))
    for a, b in zip(g_fast, g_ref):
        torch.testing.assert_close(a, b)


def test_spatial_gain_refuses_mismatched_inputs():
    x = torch.randn(2, 3, 4, 4)
    for layout, w, shown in ((torch.randn(1, 2, 8, 8), torch.randn(3, 2), r"layout \(1, 2, 8, 8\)"),
                             (torch.randn(3, 2, 4, 4), torch.randn(3, 2), r"layout \(3, 2, 4, 4\)"),
                             (torch.randn(1, 2, 4, 4), torch.randn(2, 3), r"weight \(2, 3\)")):
        with pytest.raises(ValueError, match=r"spatial_gain: expected x \(B, C, H, W\).*got x \(2, 3, 4, 4\), .*" + shown):
            ops.spatial_gain(x, layout, w)


# --- the networks ----------------------------------------------------------------------------------------


def test_layout_settings_are_checked():
    assert [LAYOUT.layout_inputs(r) for r in LAYOUT.resolutions] == [0, K, K]
    assert [TINY.layout_inputs(r) for r in TINY.resolutions] == [0, 0, 0]
    with pytest.raises(ValueError, match="layout_channels must be >= 0, got -1"):
        dataclasses.replace(TINY, layout_channels=-1)
    for bad in (12, 2, 32):
        with pytest.raises(ValueError, match=rf"layout_resolution must be a power of two in \[4, 16\], got {bad}"):
            dataclasses.replace(LAYOUT, layout_resolution=bad)
    assert TINY.layout_resolution == 64 > TINY.resolution  # unread without layout channels


def test_g_reads_its_layout_where_the_settings_say_and_nowhere_else():
    G = Generator(LAYOUT)
    assert "synthesis.layout_image" not in Generator(TINY).state_dict()  # checkpoints of G without it load unchanged
    syn = G.synthesis
    assert syn.layout_image.shape == (K, 16, 16)
    c4, c8, c16 = (LAYOUT.g_channels(r) for r in (4, 8, 16))
    assert syn.trunk["b4"].conv1.weight.shape[1] == c4 and syn.trunk["b4"].to_image.weight.shape[1] == c4
    for name in ("albedo", "specular", "normals"):  # TINY branches at 8x8
        for res, c_in, c in ((8, c4, c8), (16, c8, c16)):
            block = syn.branches[name][f"b{res}"]
            assert block.conv0.weight.shape[1] == c_in  # conv0 reads the features only
            assert block.conv1.weight.shape[1] == c + K and block.to_image.weight.shape[1] == c + K
    # a change of one layout map moves the maps, and most where it changed
    ws = G.ws(torch.randn(2, LAYOUT.z_dim))
    with torch.no_grad():
        syn.layout_image.normal_()
        before = syn(ws, noise_mode="const").cat()
        syn.layout_image[1, 2:6, 9:13] += 3.0
        moved = (syn(ws, noise_mode="const").cat() - before).abs().mean(dim=(0, 1))
    assert moved.max() > 0 and moved[2:6, 9:13].mean() > 3 * moved[12:, :6].mean()
    # every layout weight learns
    syn(ws, noise_mode="const").cat().square().mean().backward()
    for w in (syn.branches["specular"]["b8"].conv1.weight, syn.branches["normals"]["b16"].to_image.weight):
        assert w.grad[:, -K:].abs().sum() > 0
    # the coarse stage stops before the layout blocks without touching them, or reads the layout area-averaged
    assert syn(ws, max_resolution=4).albedo.shape == (2, 3, 4, 4)
    with torch.no_grad():
        coarse = syn(ws, noise_mode="const", max_resolution=8).cat()
        syn.layout_image[1, 2:6, 9:13] += 3.0  # at 8x8: rows 1-2, columns 4-6
        moved = (syn(ws, noise_mode="const", max_resolution=8).cat() - coarse).abs().mean(dim=(0, 1))
    assert coarse.shape == (2, 7, 8, 8) and moved[1:3, 4:7].mean() > 3 * moved[6:, :2].mean()


def test_layout_gain_scales_g_s_features_where_the_settings_say():
    gain = dataclasses.replace(LAYOUT, layout_gain=True)
    with pytest.raises(ValueError, match=r"layout_gain needs layout inputs \(layout_channels > 0\)"):
        dataclasses.replace(TINY, layout_gain=True)
    G = Generator(gain)
    syn = G.synthesis
    assert syn.trunk["b4"].conv1.layout_gain is None and syn.trunk["b4"].to_image.layout_gain is None
    c8, c16 = gain.g_channels(8), gain.g_channels(16)
    for name in ("albedo", "specular", "normals"):
        for res, c in ((8, c8), (16, c16)):
            block = syn.branches[name][f"b{res}"]
            assert block.conv0.layout_gain is None  # conv0 reads no layout
            for layer in (block.conv1, block.to_image):
                assert layer.layout_gain.shape == (c, K) and not layer.layout_gain.any()  # zero: no gain at start
    assert Generator(LAYOUT).synthesis.branches["albedo"]["b16"].conv1.layout_gain is None
    # at zero it computes what the G without it does; set, it moves the maps most where the layout is
    plain = Generator(LAYOUT)
    plain.load_state_dict({k: v for k, v in G.state_dict().items() if "layout_gain" not in k})
    with torch.no_grad():
        syn.layout_image.zero_()
        syn.layout_image[1, 2:6, 9:13] = 1.0
        plain.synthesis.layout_image.copy_(syn.layout_image)
    ws = G.ws(torch.randn(2, LAYOUT.z_dim))
    with torch.no_grad():
        before = syn(ws, noise_mode="const").cat()
        torch.testing.assert_close(before, plain.synthesis(ws, noise_mode="const").cat(), rtol=0, atol=0)
        syn.branches["albedo"]["b16"].to_image.layout_gain[:, 1] = -1.0
        moved = (syn(ws, noise_mode="const").cat() - before).abs()
    assert moved[:, :3, 2:6, 9:13].min() > 0 and moved[:, :3, 10:, :6].max() == 0 and moved[:, 3:].max() == 0
    # every gain weight learns
    syn(ws, noise_mode="const").cat().square().mean().backward()
    for layer in (syn.branches["specular"]["b8"].conv1, syn.branches["normals"]["b16"].to_image):
        assert layer.layout_gain.grad.abs().sum() > 0


def test_layout_and_gain_under_bfloat16_autocast_follow_float32():
    # (under autocast only the convolutions run in bfloat16: each layer's bias, a float32 parameter, lifts its output
    # back to float32, so spatial_gain's 1 + g is float32 there; checked with a gain of 0.003, below bfloat16's step)
    G = Generator(dataclasses.replace(LAYOUT, layout_gain=True))
    syn = G.synthesis
    with torch.no_grad():
        for p in G.parameters():
            p.add_(0.1 * torch.randn_like(p))
        syn.layout_image.uniform_(0, 1)
    ws = G.ws(torch.randn(4, LAYOUT.z_dim))
    with torch.no_grad():
        f32 = syn(ws, noise_mode="const").cat()
        with torch.autocast("cpu", dtype=torch.bfloat16):
            b16 = syn(ws, noise_mode="const").cat()
    assert b16.dtype == torch.float32 and 0 < (b16 - f32).abs().max() < 0.05 * f32.std()


def test_set_layout_image_sets_both_generators_and_refuses_what_does_not_fit():
    state = new_state(LAYOUT, TrainSettings(batch=4, kimg=1))
    layout = torch.rand(K, 16, 16)
    set_layout_image(state, layout)
    assert torch.equal(state.G.synthesis.layout_image, layout) and torch.equal(state.G_ema.synthesis.layout_image, layout)
    with pytest.raises(ValueError, match=r"expected a layout of shape \(3, 16, 16\), got \(3, 8, 8\)"):
        set_layout_image(state, torch.rand(K, 8, 8))
    with pytest.raises(ValueError, match="no layout inputs"):
        set_layout_image(new_state(TINY, TrainSettings(batch=4, kimg=1)), layout)


def test_checkpoint_and_shipped_generator_round_trip_the_layout_exactly(tmp_path):
    from fitme_cli.reflectance.gan.store import load_generator, save_generator

    state = _perturbed(new_state(LAYOUT, TrainSettings(batch=4, kimg=1)))
    set_layout_image(state, torch.rand(K, 16, 16))
    save_checkpoint(state, tmp_path / "ckpt.safetensors")
    back = load_checkpoint(tmp_path / "ckpt.safetensors")
    assert back.gan == LAYOUT
    for a, b in ((state.G, back.G), (state.G_ema, back.G_ema)):
        sa, sb = a.state_dict(), b.state_dict()
        assert sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)
    save_generator(state.G_ema, tmp_path / "models", {"kimg": 0})
    G = load_generator(tmp_path / "models")
    sa, sb = state.G_ema.state_dict(), G.state_dict()
    assert sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)
    z = torch.randn(2, LAYOUT.z_dim)
    with torch.no_grad():  # the loaded G runs channels-last: another order of the same sums
        torch.testing.assert_close(G(z, noise_mode="const").cat(), state.G_ema(z, noise_mode="const").cat(), rtol=1e-5, atol=1e-6)


# --- widening a trained run to its layout ----------------------------------------------------------------


def test_adding_the_layout_keeps_what_g_computes_and_trains_the_new_weights():
    from fitme_cli.reflectance.gan.widen import widen_state

    state = _perturbed(new_state(TINY, TrainSettings(batch=4, kimg=1, channels_last=False)))
    state.step, state.nimg = 5, 20
    wide = widen_state(state, LAYOUT)
    assert (wide.step, wide.nimg, wide.gan) == (5, 20, LAYOUT)
    set_layout_image(wide, torch.rand(K, 16, 16) * 2 - 1)
    z = torch.randn(3, TINY.z_dim)
    with torch.no_grad():
        for old, new in ((state.G, wide.G), (state.G_ema, wide.G_ema)):
            torch.testing.assert_close(new(z, noise_mode="const").cat(), old(z, noise_mode="const").cat(), rtol=1e-5, atol=1e-5)
        x = torch.randn(4, 7, 16, 16)
        torch.testing.assert_close(wide.D(x), state.D(x), rtol=0, atol=0)
    wide.G(z, noise_mode="const").cat().square().sum().backward()
    w = wide.G.synthesis.branches["albedo"]["b16"].conv1.weight
    assert torch.count_nonzero(w[:, -K:]) == 0 and w.grad[:, -K:].abs().sum() > 0


def test_a_run_s_layout_cannot_change_nor_its_features_grow_where_it_is_read():
    from fitme_cli.reflectance.gan.widen import widen_state

    state = new_state(LAYOUT, TrainSettings(batch=4, kimg=1))
    for other in (dataclasses.replace(LAYOUT, layout_channels=K + 1), dataclasses.replace(LAYOUT, layout_resolution=16), TINY):
        with pytest.raises(ValueError, match=r"layout inputs cannot change once a run has them \(3 maps from 8x8\)"):
            widen_state(state, other)
    with pytest.raises(ValueError, match="channels cannot grow where it reads its layout inputs"):
        widen_state(state, dataclasses.replace(LAYOUT, g_channel_min=8))
    # D's may: it reads no layout
    wide = widen_state(state, dataclasses.replace(LAYOUT, d_joint_branch=True))
    assert wide.D.joint_branch is not None and wide.gan.layout_channels == K


def test_adding_the_layout_gain_keeps_what_g_computes_and_adam_s_state():
    from fitme_cli.reflectance.gan.train import train_step
    from fitme_cli.reflectance.gan.widen import widen_state

    state = _perturbed(new_state(LAYOUT, TrainSettings(batch=4, kimg=1, channels_last=False)))
    set_layout_image(state, torch.rand(K, 16, 16) * 2 - 1)
    reals = torch.randn(8, 7, 16, 16)
    for i in range(2):  # Adam's state for every parameter
        train_step(state, reals[4 * (i % 2) : 4 * (i % 2) + 4])
    gained = widen_state(state, dataclasses.replace(LAYOUT, layout_gain=True))
    z = torch.randn(3, LAYOUT.z_dim)
    with torch.no_grad():
        torch.testing.assert_close(gained.G_ema(z, noise_mode="const").cat(), state.G_ema(z, noise_mode="const").cat(),
                                   rtol=1e-5, atol=1e-5)
    # Adam goes on as it was: every old parameter's state by name, none for the new gains (fresh)
    old = dict(state.G.named_parameters())
    for name, p in gained.G.named_parameters():
        if "layout_gain" in name:
            assert p not in gained.opt_G.state
            continue
        a, b = state.opt_G.state[old[name]], gained.opt_G.state[p]
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a), name
    d_old = dict(state.D.named_parameters())
    for name, p in gained.D.named_parameters():
        assert torch.equal(gained.opt_D.state[p]["exp_avg_sq"], state.opt_D.state[d_old[name]]["exp_avg_sq"])
    train_step(gained, reals[:4])  # and trains on
    assert gained.G.synthesis.branches["normals"]["b16"].to_image.layout_gain.abs().sum() > 0
    with pytest.raises(ValueError, match="layout gain cannot be removed"):
        widen_state(gained, LAYOUT)


def test_widening_carries_adam_s_second_moment_into_the_grown_tensors():
    from fitme_cli.reflectance.gan.train import train_step
    from fitme_cli.reflectance.gan.widen import carry_adam, widen_state

    state = _perturbed(new_state(TINY, TrainSettings(batch=4, kimg=1, channels_last=False)))
    train_step(state, torch.randn(4, 7, 16, 16))
    wide = widen_state(state, dataclasses.replace(TINY, channel_base=128))  # G's and D's 8x8 and 16x16 twice as wide
    # the second moment is of the stored weight's gradient, which the widening rescaled: measure that rescale
    z = torch.randn(2, TINY.z_dim)
    old = dict(state.G.named_parameters())
    new = dict(wide.G.named_parameters())
    for p in (*old.values(), *new.values()):
        p.requires_grad_(True)  # the last D step left G's off
    grads = [dict(zip(ps, torch.autograd.grad(G(z, noise_mode="const").cat().square().sum(), list(ps.values()))))
             for G, ps in ((state.G, old), (wide.G, new))]
    grown = 0
    for name, p in new.items():
        v_old, v_new = state.opt_G.state[old[name]]["exp_avg_sq"], wide.opt_G.state[p]["exp_avg_sq"]
        assert v_new.shape == p.shape
        if v_old.shape == p.shape:
            torch.testing.assert_close(v_new, v_old, rtol=0, atol=0)
            continue
        grown += 1
        part = tuple(slice(0, n) for n in v_old.shape)
        g_old, g_new = grads[0][name], grads[1][name][part]
        used = g_old.abs() > 1e-6 * g_old.abs().max()
        ratio = (g_new[used] / g_old[used]).abs()
        torch.testing.assert_close(ratio, torch.full_like(ratio, float(ratio.median())), rtol=1e-3, atol=0)
        torch.testing.assert_close(v_new[part], v_old * float(ratio.median()) ** 2, rtol=1e-3, atol=0)
        rest = torch.ones_like(v_new, dtype=torch.bool)
        rest[part] = False
        torch.testing.assert_close(v_new[rest], torch.full_like(v_new[rest], float(v_new[part].mean())))
    assert grown > 5
    # a module with no state (never stepped) carries nothing
    fresh = new_state(TINY, TrainSettings(batch=4, kimg=1))
    assert carry_adam(fresh.opt_G, fresh.G, wide.opt_G, wide.G) == 0


# --- the layout maps and the command line ----------------------------------------------------------------


def test_layout_image_is_the_data_s_anatomy_in_its_channels(models_root):
    from fitme_cli.reflectance.gan.data import LAYOUT_CHANNELS, beard_zone, eye_openings, layout_image, load_regions
    from fitme_cli.shape.regions import REGIONS

    for r in (16, 64, 256):
        L = layout_image(r)
        assert L.shape == (len(LAYOUT_CHANNELS), r, r) and L.dtype == torch.float32 and torch.isfinite(L).all()
    L = layout_image(256)
    # each map at unit RMS, or scaled by 10 where that is less: the small masks, whose inside is then 10
    rms = L.square().mean(dim=(1, 2)).sqrt()
    small = ["lips", "mouth_line", "lips_zone", "brows", "eye_inside", "lash", "eyes"]
    for i, n in enumerate(LAYOUT_CHANNELS):
        if n in small:
            assert rms[i] < 1 and 8 < L[i].max() <= 10 + 1e-4, n  # the eyes mask peaks at 0.88
        else:
            assert rms[i] == pytest.approx(1, rel=1e-4), n
    ch = {n: L[i] / L[i].abs().max() for i, n in enumerate(LAYOUT_CHANNELS)}  # back to the natural units
    for n in ("lips", "brows", "eye_inside", "beard", "face"):
        assert 0 <= ch[n].min(), n
    regions = load_regions(256)
    lips = regions == REGIONS.index("lips")
    # the data's lips are FaceMesh's lip contour, most of it on the shape model's lips region (232 of 344 texels)
    assert ((ch["lips"] > 0.5) & lips).sum() > 0.6 * (ch["lips"] > 0.5).sum()
    assert ((ch["brows"] > 0.5) <= (regions == REGIONS.index("brows"))).all()
    assert ch["eye_inside"][eye_openings(256)].min() > 0.5 and torch.equal(ch["beard"] > 0.5, beard_zone(256))
    # the hairline's distance: in the scalp's interior the largest, on the face the most negative, a ramp between
    assert ch["hair_distance"][regions == REGIONS.index("scalp")].max() == 1
    assert ch["hair_distance"][lips].max() == -1
    coords = (torch.arange(256) + 0.5) / 256 * 2 - 1
    coords = coords / coords.square().mean().sqrt()
    torch.testing.assert_close(L[LAYOUT_CHANNELS.index("column")], coords[None].expand(256, 256))
    torch.testing.assert_close(L[LAYOUT_CHANNELS.index("row")], coords[:, None].expand(256, 256))
    # the flow's cosine and sine, each reaching +-1 somewhere: a unit vector at every texel
    torch.testing.assert_close(ch["hair_flow_cos"] ** 2 + ch["hair_flow_sin"] ** 2, torch.ones(256, 256), rtol=0, atol=0.03)
    # below 64^2 the 64^2 maps area-averaged: the mean of each channel kept
    torch.testing.assert_close(layout_image(16).mean(dim=(1, 2)), layout_image(64).mean(dim=(1, 2)), rtol=1e-4, atol=1e-4)
    with pytest.raises(ValueError, match="expected a resolution >= 1, got 0"):
        layout_image(0)


def test_train_command_adds_the_layout_to_a_new_run_and_on_resume(tmp_path, models_root):
    from fitme_cli.cli import main
    from fitme_cli.reflectance.gan.data import LAYOUT_CHANNELS, layout_image

    data = tmp_path / "skin"
    r = CliRunner().invoke(main, ["dataset", str(data), "-n", "4", "--size", "64", "--seed", "3"])
    assert r.exit_code == 0, r.output
    base = ["train", str(data), "--resolution", "16", "--branch-resolution", "8", "--channel-base", "64",
            "--channel-max", "16", "--batch", "4", "--snapshot-kimg", "0.004", "--threads", "1"]
    r = CliRunner().invoke(main, [*base, "-o", str(tmp_path / "new"), "--kimg", "0.004", "--layout", "--layout-resolution", "8"])
    assert r.exit_code == 0, r.output
    state = load_checkpoint(tmp_path / "new" / "checkpoint.safetensors")
    assert (state.gan.layout_channels, state.gan.layout_resolution) == (len(LAYOUT_CHANNELS), 8)
    torch.testing.assert_close(state.G_ema.synthesis.layout_image, layout_image(16))
    # a run without it gains it on resume, computing what it did
    run = tmp_path / "old"
    r = CliRunner().invoke(main, [*base, "-o", str(run), "--kimg", "0.004"])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(main, [*base, "-o", str(run), "--kimg", "0.008", "--resume", "--layout"])
    assert r.exit_code == 2 and "layout_resolution must be a power of two in [4, 16], got 64" in r.output
    r = CliRunner().invoke(main, [*base, "-o", str(run), "--kimg", "0.008", "--resume", "--layout", "--layout-resolution", "16"])
    assert r.exit_code == 0, r.output
    assert "added G's layout inputs (15 maps from 16x16)" in r.output
    state = load_checkpoint(run / "checkpoint.safetensors")
    assert state.gan.layout_channels == len(LAYOUT_CHANNELS) and state.nimg == 8
    torch.testing.assert_close(state.G.synthesis.layout_image, layout_image(16))
    r = CliRunner().invoke(main, [*base, "-o", str(run), "--kimg", "0.012", "--resume", "--no-layout"])
    assert r.exit_code == 2 and "layout inputs cannot change once a run has them" in r.output
    # the gain, on resume (to a run with the layout) and on a new run, never without the layout
    r = CliRunner().invoke(main, [*base, "-o", str(run), "--kimg", "0.012", "--resume", "--layout-gain"])
    assert r.exit_code == 0, r.output
    assert "added G's layout gain" in r.output and load_checkpoint(run / "checkpoint.safetensors").gan.layout_gain
    r = CliRunner().invoke(main, [*base, "-o", str(tmp_path / "gain"), "--kimg", "0.004", "--layout", "--layout-resolution",
                                  "8", "--layout-gain"])
    assert r.exit_code == 0, r.output
    assert load_checkpoint(tmp_path / "gain" / "checkpoint.safetensors").gan.layout_gain
    r = CliRunner().invoke(main, [*base, "-o", str(tmp_path / "nogain"), "--kimg", "0.004", "--layout-gain"])
    assert r.exit_code == 2 and "layout_gain needs layout inputs" in r.output, r.output
    # a layout resolution without a layout is refused, not silently ignored (new run) or rebuilt for (resume)
    plain = tmp_path / "plain"
    r = CliRunner().invoke(main, [*base, "-o", str(plain), "--kimg", "0.004", "--layout-resolution", "8"])
    assert r.exit_code == 2 and "--layout-resolution is read only with --layout" in r.output, r.output
    assert not (plain / "config.json").exists()
    r = CliRunner().invoke(main, [*base, "-o", str(plain), "--kimg", "0.004"])
    assert r.exit_code == 0, r.output
    before = (plain / "config.json").read_text()
    r = CliRunner().invoke(main, [*base, "-o", str(plain), "--kimg", "0.008", "--resume", "--layout-resolution", "8"])
    assert r.exit_code == 2 and "--layout-resolution is read only with --layout" in r.output, r.output
    assert (plain / "config.json").read_text() == before
    cfg = tmp_path / "cfg.json"
    cfg.write_text('{"gan": {"layout_channels": 4}}')
    r = CliRunner().invoke(main, [*base, "-o", str(tmp_path / "bad"), "--kimg", "0.004", "--config", str(cfg)])
    assert r.exit_code == 2 and "layout_channels must be 0 or 15" in r.output
