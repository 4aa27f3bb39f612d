"""The ``sdp`` command line: a thin Typer app over the package's functions.

Every :class:`~sdp_cli.errors.SdpError` becomes one line on stderr and exit code 1.
"""

from __future__ import annotations

import functools
import sys
from pathlib import Path
from typing import Annotated, Callable, Optional

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


def _task_help() -> str:
    from sdp_cli.tasks import task_names

    return "Task name, one of: " + ", ".join(task_names()) + " (see `sdp tasks`)."


@app.command("collect")
@clean_errors
def collect_cmd(
    task: Annotated[str, typer.Option(help=_task_help())],
    n_traj: Annotated[int, typer.Option("--n-traj", help="Number of converged trajectories to keep.")] = 30,
    seed: Annotated[int, typer.Option(help="Seed: xi_i is a function of (seed, i).")] = 0,
    out: Annotated[Optional[Path], typer.Option(help="Dataset artifact (.npz); default data/<task>-n<N>-s<seed>.npz.")] = None,
    workers: Annotated[Optional[int], typer.Option(help="Worker processes (default: all cores).")] = None,
    max_iter: Annotated[int, typer.Option("--max-iter", help="Solver iteration cap; non-converged solves are rejected.")] = 1000,
    max_attempts: Annotated[Optional[int], typer.Option("--max-attempts", help="Cap on solves tried (default 20 x n_traj).")] = None,
) -> None:
    """Solve OCPs from the naive guess and write a dataset with feedback gains."""
    from sdp_cli.data.collect import CollectConfig, collect
    from sdp_cli.progress import collect_progress

    if workers is not None and workers <= 0:
        raise SdpError(f"--workers must be > 0, got {workers}")
    config = CollectConfig(task=task, n_traj=n_traj, seed=seed, max_iter=max_iter, max_attempts=max_attempts)
    out = out or Path("data") / f"{task}-n{n_traj}-s{seed}.npz"
    with collect_progress(n_traj) as on_update:
        path, stats = collect(config, out, workers=workers, progress=on_update)
    typer.echo(f"wrote {path}: {stats.kept} trajectories, {stats.rejected} rejected "
               f"({stats.convergence_rate:.0%} converged), mean solve {stats.mean_solve_time:.3f} s, "
               f"wall {stats.wall_time:.1f} s")


def main() -> None:  # pragma: no cover - entry point
    app()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
