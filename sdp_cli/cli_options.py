"""What the ``sdp`` commands share: option declarations (each declared once), error handling and
small parsers. See :mod:`sdp_cli.cli`."""

from __future__ import annotations

import functools
from typing import Annotated, Callable, Optional
import inspect
from dataclasses import fields

import typer
from typer.core import TyperOption

from sdp_cli.errors import SdpError
from sdp_cli.tasks import task_names
from sdp_cli.policy.registry import get_method, method_names
from sdp_cli.policy.config import TrainConfig, option_field, option_type, options
from sdp_cli.algorithm.loop_options import LoopAlgorithmOptions, LoopRolloutConfig, _default, option_kind


def _flags_without_type() -> None:
    """typer 0.29 with click 8.5 shows ``<bool>`` after every flag in ``--help`` (``--resume <bool>``,
    ``--progress/--no-progress <bool>``): a flag takes no value, so it shows no type."""
    if getattr(TyperOption.display_type_rich, "_sdp", False):
        return
    original = TyperOption.display_type_rich

    def display_type_rich(self, ctx):
        return None if getattr(self, "is_flag", False) else original(self, ctx)

    display_type_rich._sdp = True
    TyperOption.display_type_rich = display_type_rich


_flags_without_type()


def clean_errors(fn: Callable) -> Callable:
    """Turn SdpError and OS errors (a full disk, a path under a file, permissions: one line naming the path)
    into a one-line message and exit code 1, Ctrl-C into "Interrupted." and exit code 130."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except SdpError as e:
            typer.echo(f"Error: {e}", err=True)
            raise typer.Exit(1) from None
        except OSError as e:
            typer.echo(f"Error: {os_error_text(e)}", err=True)
            raise typer.Exit(1) from None
        except KeyboardInterrupt:
            typer.echo("Interrupted.", err=True)
            raise typer.Exit(130) from None

    return wrapper


def os_error_text(e: OSError) -> str:
    """One line for an OS error: what failed on which path (``cannot write x/y: Not a directory``)."""
    where = " -> ".join(str(f) for f in (e.filename, e.filename2) if f is not None)
    what = e.strerror or str(e) or type(e).__name__
    return f"{where}: {what}" if where else what


def task_help() -> str:
    return "Task name, one of: " + ", ".join(task_names()) + " (see `sdp tasks`)."


ThreadsOpt = Annotated[int, typer.Option(
    help="torch CPU threads of this process (default 1: the networks are tiny, one thread is fastest on a "
         "busy or 2-core CPU, and results do not depend on the machine's core count).")]


ProgressOpt = Annotated[bool, typer.Option(
    "--progress/--no-progress", help="Progress bars on stderr (only on a terminal, `dvc repro` in a terminal included; never into a pipe or a file).")]
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
    return "; ".join(f"{m} ({get_method(m).description})" if get_method(m).description else m
                     for m in method_names()) + "."


def int_list(value: Optional[str], name: str) -> tuple:
    if not value:
        return ()
    try:
        return tuple(int(v) for v in value.split(","))
    except ValueError:
        raise SdpError(f"{name} must be comma-separated integers, got {value!r}") from None


def _list_parser(flag: str, kind: type):
    def parse(text: str) -> list:
        try:
            return [kind(v) for v in text.split(",") if v.strip()]
        except ValueError:
            raise SdpError(f"{flag} must be comma-separated {'integers' if kind is int else 'numbers'}, "
                           f"got {text!r}") from None
    return parse


def _option_param(name: str, required: tuple[str, ...]):
    """``(inspect.Parameter, parse)`` of training option ``name`` (:func:`sdp_cli.policy.config.options`)."""
    _, default, help_ = option_field(name)
    base, item, _ = option_type(name)
    flag = "--" + name.replace("_", "-")
    parse = None
    if item is not None:
        parse, base = _list_parser(flag, item), str
        shown = ",".join(str(v) for v in default)
    else:
        shown = str(default)
    section = options()[name][0]
    panel = f"Training options ({section})" if section else "Training options"
    if name == "method":
        help_ = method_help()
    decls = [f"{flag}/--no-{flag[2:]}"] if base is bool else [flag]
    if name in required:
        info = typer.Option(*decls, help=help_, rich_help_panel=panel)
        return inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, annotation=Annotated[base, info]), parse
    info = typer.Option(*decls, help=help_, rich_help_panel=panel,
                        show_default=shown if default is not None else False)
    return inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=None,
                             annotation=Annotated[Optional[base], info]), parse


def _with_params(wrapper: Callable, fn: Callable, injected: str, params: list) -> Callable:
    """Give ``wrapper`` (which calls ``fn`` with ``injected=...``) the signature typer reads: ``fn``'s own
    parameters but ``injected``, with the generated ``params``; required ones first, each group in order."""
    own = [p for p in inspect.signature(fn, eval_str=True).parameters.values() if p.name != injected]
    req = lambda ps: [p for p in ps if p.default is inspect.Parameter.empty]          # noqa: E731
    opt_ = lambda ps: [p for p in ps if p.default is not inspect.Parameter.empty]     # noqa: E731
    ordered = req(own) + req(params) + opt_(own) + opt_(params)
    wrapper.__signature__ = inspect.Signature([p.replace(kind=inspect.Parameter.KEYWORD_ONLY) for p in ordered])
    wrapper.__annotations__ = {p.name: p.annotation for p in ordered}
    del wrapper.__wrapped__
    return wrapper


def with_train_options(required: tuple[str, ...] = ("method",), check: Callable[[dict], None] | None = None) -> Callable:
    """Give a command every training option of :class:`~sdp_cli.policy.config.TrainConfig` as a flag (one name
    each: ``--horizon``, ``--sobolev-alpha``, ...; grouped by section in ``--help``), so that ``sdp train`` and
    ``sdp loop`` declare none by hand. The wrapped function receives ``train=TrainConfig.of(given options)``
    (the others at the config's defaults); an invalid value is one line and exit code 1. ``check(given)`` runs
    the command's own rules first (``sdp loop``'s seed range)."""
    def decorate(fn: Callable) -> Callable:
        params, parsers = [], {}
        for name in options():
            param, parse = _option_param(name, required)
            params.append(param)
            if parse is not None:
                parsers[name] = parse

        @functools.wraps(fn)
        @clean_errors
        def wrapper(**kwargs):
            given = {}
            for name in options():
                value = kwargs.pop(name)
                if value is not None:
                    given[name] = parsers[name](value) if name in parsers else value
            if check is not None:
                check(given)
            return fn(**kwargs, train=TrainConfig.of(**given))

        return _with_params(wrapper, fn, "train", params)

    return decorate


def with_loop_options(cls, injected: str) -> Callable:
    """Give ``sdp loop`` every option of a :mod:`sdp_cli.algorithm.loop_options` class as a flag (``--n-algo``, ``--t-a``,
    ``--eval-t-a 1,4,8``, ``--eval-refine/--no-eval-refine``, ...), generated from its fields as the experiment
    keys are; the wrapped function receives ``<injected>=`` the options given: an instance of ``cls``, or, for
    :class:`~sdp_cli.algorithm.loop_options.LoopAlgorithmOptions` (``LoopConfig``'s own fields), a ``{field: value}`` dict
    (the defaults are the fields')."""
    def param(f):
        base, item, optional = option_kind(f, cls)
        flag = f.metadata.get("flag") or "--" + f.name.replace("_", "-")
        default = _default(f)
        if base is bool:
            switch = flag if "/" in flag else f"{flag}/--no-{flag[2:]}"
            info = typer.Option(switch, help=f.metadata["help"], rich_help_panel="Loop options")
            return inspect.Parameter(f.name, inspect.Parameter.KEYWORD_ONLY, default=default,
                                     annotation=Annotated[bool, info])
        kind = str if item is not None else base
        shown = ",".join(map(str, default)) if item is not None else default
        info = typer.Option(flag, help=f.metadata["help"], rich_help_panel="Loop options",
                            show_default=shown if default not in (None, ()) else False)
        return inspect.Parameter(f.name, inspect.Parameter.KEYWORD_ONLY, default=None,
                                 annotation=Annotated[Optional[kind], info])

    opts = list(fields(cls))
    as_dict = issubclass(cls, LoopAlgorithmOptions)

    def decorate(fn: Callable) -> Callable:
        params = [param(f) for f in opts]

        @functools.wraps(fn)
        @clean_errors
        def wrapper(**kwargs):
            given = {}
            for f in opts:
                value = kwargs.pop(f.name)
                if value is None:
                    continue
                given[f.name] = (int_list(value, "--" + f.name.replace("_", "-"))
                                 if option_kind(f, cls)[1] is not None else value)
            return fn(**kwargs, **{injected: given if as_dict else cls(**given)})

        return _with_params(wrapper, fn, injected, params)

    return decorate


def with_loop_rollout_options(cls=None) -> Callable:
    """:func:`with_loop_options` of :class:`~sdp_cli.algorithm.loop_options.LoopRolloutConfig` (or a subclass with more
    options): ``rollout=LoopRolloutConfig(given options)``."""
    return with_loop_options(cls or LoopRolloutConfig, "rollout")


def with_loop_algorithm_options(cls=None) -> Callable:
    """:func:`with_loop_options` of :class:`~sdp_cli.algorithm.loop_options.LoopAlgorithmOptions` (or a subclass):
    ``algorithm={given options}``, the keyword arguments of ``LoopConfig``."""
    return with_loop_options(cls or LoopAlgorithmOptions, "algorithm")
