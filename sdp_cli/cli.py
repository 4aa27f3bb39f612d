"""The ``sdp`` command line: a thin Typer app over the package's functions.

Every :class:`~sdp_cli.errors.SdpError` becomes one line on stderr and exit code 1.
"""

from __future__ import annotations

import functools
import sys
from typing import Annotated, Callable

import typer

from sdp_cli.errors import SdpError

app = typer.Typer(name="sdp", help="Sobolev Diffusion Policy toolkit.", no_args_is_help=True,
                  pretty_exceptions_enable=False, add_completion=False)


@app.callback()
def _root() -> None:
    """Sobolev Diffusion Policy toolkit: collect, train, rollout, refine, report."""


def clean_errors(fn: Callable) -> Callable:
    """Turn SdpError (and Ctrl-C) into a one-line message and exit code 1."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except SdpError as e:
            typer.echo(f"Error: {e}", err=True)
            raise typer.Exit(1) from None
        except KeyboardInterrupt:
            typer.echo("Interrupted.", err=True)
            raise typer.Exit(130) from None

    return wrapper


@app.command("tasks")
@clean_errors
def tasks_cmd() -> None:
    """List the registered tasks."""
    from sdp_cli.tasks import task_descriptions

    for name, desc in task_descriptions().items():
        typer.echo(f"{name:24s} {desc}")


def main() -> None:  # pragma: no cover - entry point
    app()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
