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


#: `sdp train` parameters whose TrainConfig field has another name, and how their text becomes the field's value
TRAIN_FIELD = {"horizon": "T_h", "diffusion_steps": "K"}


def _int_list_of(flag: str):
    def parse(text: str) -> list[int]:
        vals = int_list(text, flag)
        if not vals or min(vals) <= 0:
            raise SdpError(f"{flag} must be positive integers, got {text!r}")
        return list(vals)
    return parse


TRAIN_PARSE = {"down_dims": _int_list_of("--down-dims")}


def forwards_train_options(train_cmd: Callable, loop_owns: tuple[str, ...]) -> Callable:
    """Give a command every option of ``train_cmd`` (``sdp train``) that is not in ``loop_owns``: the same flags and
    help, default None (TrainConfig's default applies). The wrapped function receives the given ones as
    ``train_options={TrainConfig field: value}``: a training option is declared once, on ``sdp train``."""
    import inspect
    from copy import copy

    def decorate(fn: Callable) -> Callable:
        forwarded = []
        for p in inspect.signature(train_cmd, eval_str=True).parameters.values():
            if p.name in loop_owns:
                continue
            base, info = p.annotation.__origin__, p.annotation.__metadata__[0]
            info = copy(info)
            info.help = (info.help or "") + " (`sdp train`'s option; default: its default)"
            info.show_default = False
            forwarded.append(inspect.Parameter(p.name, inspect.Parameter.KEYWORD_ONLY, default=None,
                                               annotation=Annotated[Optional[base], info]))
        names = [p.name for p in forwarded]

        @functools.wraps(fn)
        @clean_errors
        def wrapper(**kwargs):
            opts = {}
            for name in names:
                value = kwargs.pop(name)
                if value is not None:
                    opts[TRAIN_FIELD.get(name, name)] = TRAIN_PARSE.get(name, lambda v: v)(value)
            return fn(**kwargs, train_options=opts)

        own = [p for p in inspect.signature(fn, eval_str=True).parameters.values() if p.name != "train_options"]
        wrapper.__signature__ = inspect.Signature(own + forwarded)
        wrapper.__annotations__ = {p.name: p.annotation for p in own + forwarded}
        del wrapper.__wrapped__     # typer reads __signature__, not the wrapped function's parameters
        return wrapper

    return decorate
