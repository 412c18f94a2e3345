"""The ``fitme`` command line: a thin click layer. Heavy imports happen inside each command."""

from __future__ import annotations

import sys

import click

from .. import __version__
from ..errors import FitmeError

__all__ = ["main"]

_COMMANDS = {  # name -> module under fitme_cli.cli, imported only when the command runs
    "detect": "detect",
    "models": "models",
    "augment": "augment",
    "dataset": "dataset",
    "train": "train",
    "fit": "fit",
    "tune": "tune",
    "export": "export",
    "render": "render",
    "batch": "batch",
    "bench": "bench",
}


class _Group(click.Group):
    """Loads commands lazily and turns domain errors into one line and their exit code."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(_COMMANDS)

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name not in _COMMANDS:
            return None
        import importlib

        return importlib.import_module(f".{_COMMANDS[name]}", __name__).command

    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except FitmeError as e:
            click.echo(f"fitme: error: {e}", err=True)
            sys.exit(e.exit_code)
        except KeyboardInterrupt:
            click.echo("fitme: interrupted", err=True)
            sys.exit(130)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="fitme")
def main() -> None:
    """fitme: photos of a face to a relightable 3D avatar (FitMe, CVPR 2023), on the CPU."""
    from ..ops.memory import retain_freed_memory

    retain_freed_memory()  # freed buffers stay mapped: no page faults on each render's gradients
