"""Grow a trained BRDF-GAN's channels without changing what it computes (Net2Net-style widening).

CPU training is slow, so more capacity is added to a run rather than started over: every layer keeps
its trained weights, the new output channels start from the usual random init, and the weights that
read the new channels into old ones start at zero, so the widened G draws the same maps and the
widened D gives the same logits until training moves them. Equalised learning rate scales a weight
by 1/sqrt(fan in) at run time; where that gain changes with the width, the stored weights are rescaled
so the effective weight stays. The modulated convs need no rescale: demodulation divides by the norm
over the input channels, which zero columns do not change. The same way D can gain its joint branch
(``GanSettings.d_joint_branch``): the new branch starts from its init and the last block reads its
features through zero weights. And G can gain its layout inputs (``GanSettings.layout_channels``): each conv1 and
toImage from ``layout_resolution`` up reads them through zero weights, appended after its features; the caller sets
the new ``layout_image`` (``train.set_layout_image``), and its layout gain (``GanSettings.layout_gain``), which starts at zero.
And a trunk layer's noise strength can become per channel (``GanSettings.channel_noise``), each channel at the scalar.
"""

from __future__ import annotations

import dataclasses

import torch
from torch import nn

from .networks import GanSettings

__all__ = ["widen_module", "widen_state", "carry_adam"]


def _gain(module: nn.Module) -> float:
    """The run-time factor on a module's ``weight`` (1 where demodulation makes the scale irrelevant)."""
    g = getattr(module, "gain", None)
    if isinstance(g, float):
        return g
    g = getattr(module, "w_gain", None)
    return g if isinstance(g, float) else 1.0


def widen_module(old: nn.Module, new: nn.Module) -> None:
    """Copy ``old``'s parameters and buffers into ``new`` (the same tensors, each at least as large in
    every dimension, plus possibly tensors of added submodules). ``new`` keeps its own init for added
    submodules and output channels; weights of old outputs reading added inputs are zeroed. Raises
    ValueError on tensors ``new`` lacks and on shapes that do not fit."""
    old_mods, new_mods = dict(old.named_modules()), dict(new.named_modules())
    old_state = old.state_dict()
    new_state = new.state_dict()
    if set(old_state) - set(new_state):
        raise ValueError(f"not the same architecture: tensors only in the old one {sorted(set(old_state) - set(new_state))[:3]}")
    with torch.no_grad():
        for name, t_new in new_state.items():
            if name not in old_state:
                continue  # an added submodule: its init, read through zero weights by the old outputs
            t_old = old_state[name]
            if t_old.shape == t_new.shape:
                t_new.copy_(t_old)
                continue
            if t_old.ndim == 0 and t_new.ndim == 1:  # a layer's noise strength made per channel: each starts at it
                t_new.fill_(t_old)
                continue
            if t_old.ndim != t_new.ndim or any(o > n for o, n in zip(t_old.shape, t_new.shape)):
                raise ValueError(f"{name}: cannot widen {tuple(t_old.shape)} to {tuple(t_new.shape)}")
            owner, _, leaf = name.rpartition(".")
            scale = _gain(old_mods[owner]) / _gain(new_mods[owner]) if leaf == "weight" else 1.0
            t_new[tuple(slice(0, s) for s in t_old.shape)] = t_old * scale
            if t_new.ndim >= 2 and t_new.shape[1] > t_old.shape[1]:
                t_new[: t_old.shape[0], t_old.shape[1] :] = 0  # old outputs ignore the new inputs


def carry_adam(old_opt: torch.optim.Optimizer, old: nn.Module, new_opt: torch.optim.Optimizer, new: nn.Module) -> int:
    """Copy Adam's state from ``old``'s parameters to ``new``'s of the same name (``new`` widened from ``old`` by
    ``widen_module``). A tensor of the same shape takes its state as it was; a grown one takes the old entries in
    place, rescaled as ``widen_module`` rescaled the weight, and in its new entries the second moment's mean over the
    old ones, so that their first steps are as large as the old entries' steps (a zero there would make them ~10x
    larger: Adam divides by its root). Parameters new to ``new`` start fresh. Returns how many parameters carried.

    So a widened run goes on with the optimiser it had, as a plain resume does. (It is not what jolts a widened run:
    with Adam carried, adding the layout gain at 346.68 kimg still took D's real logit from ~3 to 3.9 in 0.07 kimg;
    docs/brdf_gan.md, "The layout as a gain".)"""
    old_params, old_mods = dict(old.named_parameters()), dict(old.named_modules())
    new_mods = dict(new.named_modules())
    carried = 0
    for name, p in new.named_parameters():
        q = old_params.get(name)
        st = old_opt.state.get(q) if q is not None else None
        if not st:
            continue
        owner, _, leaf = name.rpartition(".")
        scale = _gain(old_mods[owner]) / _gain(new_mods[owner]) if leaf == "weight" else 1.0
        out = {}
        for key, v in st.items():
            if not torch.is_tensor(v) or v.shape == p.shape or key == "step":
                out[key] = v.clone() if torch.is_tensor(v) else v
                continue
            if v.ndim == 0 and p.ndim == 1:  # a scalar made per channel (``widen_module``): each channel its moments
                out[key] = v.expand_as(p).clone()
                continue
            # the stored weight grew by `scale`, so its gradient shrinks by it
            grown = v / scale if key == "exp_avg" else v / scale**2
            t = torch.full_like(p, float(grown.mean()) if key == "exp_avg_sq" else 0.0)
            t[tuple(slice(0, n) for n in v.shape)] = grown
            out[key] = t
        new_opt.state[p] = out
        carried += 1
    return carried


def widen_state(state, gan: GanSettings):
    """A TrainState whose G, G_ema and D have ``gan``'s (wider) channels, and D the joint branch if ``gan``
    asks for it, and which computes what ``state``'s did.
    Counters, ADA, train settings, Adam's state (``carry_adam``) and the drift terms' running means carry over."""
    from .train import _RUNNING_MEANS, new_state

    grows = {"channel_base", "channel_max", "g_channel_min", "g_channel_base", "d_joint_branch", "layout_channels",
             "layout_resolution", "layout_gain", "normal_knee", "normal_knee_slope",  # the knee: no weights
             "channel_noise"}
    fixed = {f.name for f in dataclasses.fields(GanSettings)} - grows
    changed = sorted(k for k in fixed if getattr(gan, k) != getattr(state.gan, k))
    if changed:
        raise ValueError(f"only the channels can grow on a trained run; {', '.join(changed)} would change")
    if state.gan.d_joint_branch and not gan.d_joint_branch:
        raise ValueError("D's joint branch cannot be removed from a run that has one (its trained weights would be lost)")
    if set(state.gan.channel_noise) - set(gan.channel_noise):
        raise ValueError(f"per-channel noise cannot be removed from a run that has it (its trained strengths would be "
                         f"lost): {list(state.gan.channel_noise)} -> {list(gan.channel_noise)}")
    if state.gan.layout_gain and not gan.layout_gain:
        raise ValueError("G's layout gain cannot be removed from a run that has it (its trained weights would be lost)")
    old_k = state.gan.layout_channels
    if old_k and (gan.layout_channels, gan.layout_resolution) != (old_k, state.gan.layout_resolution):
        raise ValueError(f"G's layout inputs cannot change once a run has them ({old_k} maps from "
                         f"{state.gan.layout_resolution}x{state.gan.layout_resolution})")
    if old_k and any(gan.g_channels(r) != state.gan.g_channels(r) for r in gan.resolutions if gan.layout_inputs(r)):
        # the layout's weights sit after the features; more features would put old ones where the layout's are
        raise ValueError("G's channels cannot grow where it reads its layout inputs")
    for r in state.gan.resolutions:
        for who, old, new in (("D", state.gan.channels(r), gan.channels(r)),
                              ("G", state.gan.g_channels(r), gan.g_channels(r))):
            if new < old:
                raise ValueError(f"channels can only grow: {who}'s {old} -> {new} at {r}x{r}")
    rng = torch.get_rng_state()
    out = new_state(gan, state.train)  # seeds torch with the run's seed for the new channels' init ...
    torch.set_rng_state(rng)  # ... then the resumed run goes on with its own random stream
    for name in ("G", "G_ema", "D"):
        widen_module(getattr(state, name), getattr(out, name))
    carry_adam(state.opt_G, state.G, out.opt_G, out.G)
    carry_adam(state.opt_D, state.D, out.opt_D, out.D)
    for name in ("step", "nimg", "ada_p", "ada_acc", "ada_n", "wall_time"):
        setattr(out, name, getattr(state, name))
    # the drift terms' running means too: the wider G draws what the trained one did. Restarted from 16 batches of
    # fakes instead (``train.warm_running``), every term's gap jumped 3-20 fold at 372.23 kimg and D won within six
    # steps (D loss 0.26 -> 0.01-0.03; docs/brdf_gan.md, "372.23 kimg")
    for name in _RUNNING_MEANS:
        setattr(out, name, getattr(state, name))
    if state.D_patch is not None:  # the local D reads the maps, not the networks' channels: kept as it is
        out.D_patch, out.opt_D_patch = state.D_patch, state.opt_D_patch
    return out
