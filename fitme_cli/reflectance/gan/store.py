"""The shipped BRDF-GAN: ``models/brdf_gan.safetensors`` (the EMA generator's weights, float32) with
``models/brdf_gan.json`` beside it (settings, training data, kimg, wall time, measured quality)."""

from __future__ import annotations

import json
from pathlib import Path

import torch

from ...errors import ModelMissing
from .networks import GanSettings, Generator

__all__ = ["MODEL_NAME", "save_generator", "load_generator"]

MODEL_NAME = "brdf_gan"


def save_generator(G: Generator, models_dir: Path, card: dict) -> Path:
    """Write NAME.safetensors (+ settings in its metadata) and NAME.json atomically; returns the weights path."""
    from dataclasses import asdict

    from safetensors.torch import save_file

    from ...io.atomic import publish_file

    models_dir = Path(models_dir)
    models_dir.mkdir(parents=True, exist_ok=True)
    path = models_dir / f"{MODEL_NAME}.safetensors"
    tmp = path.with_name(path.name + ".tmp")
    sd = {k: v.detach().float().contiguous() for k, v in G.state_dict().items()}
    save_file(sd, str(tmp), metadata={"gan": json.dumps(asdict(G.settings))})
    publish_file(tmp, path)
    card_path = models_dir / f"{MODEL_NAME}.json"
    tmp = card_path.with_name(card_path.name + ".tmp")
    tmp.write_text(json.dumps({"name": MODEL_NAME, "settings": asdict(G.settings), **card}, indent=2) + "\n")
    tmp.replace(card_path)
    return path


def load_generator(models_dir: Path, device: str | torch.device = "cpu") -> Generator:
    """The shipped generator in eval mode with gradients off (the tuning stage turns on the layers it trains),
    its 4-D weights in channels-last layout, so the synthesis' activations are too: the fit's unit, a
    synthesis forward + backward at batch 1 on 2 CPU threads, 0.136 -> 0.110 s with the 262.02 kimg G
    (docs/fitting.md, "Channels-last"). Savers write ``.contiguous()`` copies, the standard layout."""
    from safetensors import safe_open
    from safetensors.torch import load_file

    path = Path(models_dir) / f"{MODEL_NAME}.safetensors"
    if not path.is_file():
        raise ModelMissing("BRDF-GAN weights are missing (they ship in the repository's models/ folder)", path)
    with safe_open(str(path), "pt") as f:
        settings = GanSettings(**json.loads(f.metadata()["gan"]))
    G = Generator(settings)
    G.load_state_dict(load_file(str(path)))
    return G.to(device=device, memory_format=torch.channels_last).eval().requires_grad_(False)


# 2: z from latents.sample_z (version 1 drew torch seed 0's stream, whose first vectors are the mapping's
# initial first-layer rows: outlier w)
_PRIOR_VERSION = 2


def load_w_prior(models_dir: Path, G: Generator):
    """The P-space W prior of the shipped generator (``latent_prior.fit_w_prior``), cached beside the
    weights as ``brdf_gan.wprior.safetensors`` (derived data, git-ignored): 0.8 s to fit, 5 ms to load.
    The cache records the weights' size and mtime and ``_PRIOR_VERSION``, and is refitted when they change."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file, save_file

    from .latent_prior import WPrior, fit_w_prior

    weights = Path(models_dir) / f"{MODEL_NAME}.safetensors"
    cache = Path(models_dir) / f"{MODEL_NAME}.wprior.safetensors"
    st = weights.stat()
    stamp = torch.tensor([st.st_size, st.st_mtime_ns, _PRIOR_VERSION], dtype=torch.int64)
    try:
        t = load_file(str(cache))
        if torch.equal(t["stamp"], stamp):
            return WPrior(t["mean"], t["whiten"])
    except (OSError, SafetensorError, KeyError):
        pass
    prior = fit_w_prior(G.mapping, G.settings.z_dim)
    tmp = cache.with_name(f".{cache.name}.tmp")
    try:
        save_file({"mean": prior.mean.cpu(), "whiten": prior.whiten.cpu(), "stamp": stamp}, str(tmp))
        tmp.replace(cache)
    except OSError:  # a read-only install: fit every time
        tmp.unlink(missing_ok=True)
    return prior
