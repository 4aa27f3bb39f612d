"""What the ``sdp`` commands share: option declarations (each declared once), error handling and
small parsers. See :mod:`sdp_cli.cli`."""

from __future__ import annotations

import functools
from typing import Annotated, Callable, Optional

import typer

from sdp_cli.errors import SdpError


def _flags_without_type() -> None:
    """typer 0.29 with click 8.5 shows ``<bool>`` after every flag in ``--help`` (``--resume <bool>``,
    ``--progress/--no-progress <bool>``): a flag takes no value, so it shows no type."""
    from typer.core import TyperOption

    if getattr(TyperOption.display_type_rich, "_sdp", False):
        return
    original = TyperOption.display_type_rich

    def display_type_rich(self, ctx):
        return None if getattr(self, "is_flag", False) else original(self, ctx)

    display_type_rich._sdp = True
    TyperOption.display_type_rich = display_type_rich


_flags_without_type()


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


def task_help() -> str:
    from sdp_cli.tasks import task_names

    return "Task name, one of: " + ", ".join(task_names()) + " (see `sdp tasks`)."


ThreadsOpt = Annotated[int, typer.Option(
    help="torch CPU threads of this process (default 1: the networks are tiny, one thread is fastest on a "
         "busy or 2-core CPU, and results do not depend on the machine's core count).")]


ProgressOpt = Annotated[bool, typer.Option(
    "--progress/--no-progress", help="Progress bars on stderr (only on a terminal: never under DVC or a pipe).")]
_EXECUTOR_HELP = ("Where the solves run: local (process pool of --workers; default) or dask (dask.distributed: "
                  "a LocalCluster of --workers processes on this machine, or the cluster of --scheduler).")
_SCHEDULER_HELP = "Address of a running Dask scheduler, e.g. tcp://10.0.0.5:8786 (implies --executor dask)."
#: options shared by the commands that solve, train or roll out: declared once here
WorkersOpt = Annotated[Optional[int], typer.Option(help="Solver worker processes (default: all cores).")]
ToOpt = Annotated[str, typer.Option("--to", help="TO family: ms (multiple shooting, fatrop; ours) or ddp (box-FDDP, "
                                                 "the paper's family; tasks without state constraints).")]
ExecutorOpt = Annotated[Optional[str], typer.Option(help=_EXECUTOR_HELP)]
SchedulerOpt = Annotated[Optional[str], typer.Option(help=_SCHEDULER_HELP)]
DeviceOpt = Annotated[str, typer.Option(help="auto (CUDA when present, else CPU), cpu or cuda.")]


def set_threads(threads: int) -> None:
    """Pin torch's intra-op threads (every command that runs a network calls this first)."""
    if threads <= 0:
        raise SdpError(f"--threads must be > 0, got {threads}")
    import torch

    torch.set_num_threads(threads)


def method_help() -> str:
    from sdp_cli.policy.registry import get_method, method_names

    return "; ".join(f"{m} ({get_method(m).description})" if get_method(m).description else m
                     for m in method_names()) + "."


def int_list(value: Optional[str], name: str) -> tuple:
    if not value:
        return ()
    try:
        return tuple(int(v) for v in value.split(","))
    except ValueError:
        raise SdpError(f"{name} must be comma-separated integers, got {value!r}") from None
