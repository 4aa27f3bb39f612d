"""Rich progress bars for the long loops of the CLI (stderr, quiet when not a terminal)."""

from __future__ import annotations

import contextlib
import os
import sys
from typing import Iterator

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn


def _console() -> Console:
    return Console(stderr=True)


def enabled(flag: bool = True) -> bool:
    """Bars are drawn when asked for, on a terminal (also under `dvc repro` in a terminal; not into a pipe or
    a file), unless SDP_NO_PROGRESS=1."""
    return bool(flag) and sys.stderr.isatty() and os.environ.get("SDP_NO_PROGRESS") != "1"


def status(message: str, flag: bool = True) -> None:
    """A one-line note on stderr (what a long silent phase is doing), shown when bars are."""
    if enabled(flag):
        _console().print(f"[dim]{message}[/dim]")


@contextlib.contextmanager
def count_progress(description: str, total: int | None = None, flag: bool = True) -> Iterator:
    """Yield ``on_done(completed, total=None)`` for a bar of ``total`` items (instances, time steps);
    the total may be given with the first update instead."""
    progress = Progress(TextColumn(f"[bold]{description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                        console=_console(), disable=not enabled(flag))
    with progress:
        bar = progress.add_task(description, total=total)

        def on_done(completed: int, total: int | None = None) -> None:
            progress.update(bar, completed=completed, **({"total": total} if total is not None else {}))

        yield on_done


@contextlib.contextmanager
def collect_progress(n_traj: int, flag: bool = True) -> Iterator:
    """Yield a callback ``on_update(stats)`` that drives a kept/rejected/solve-time bar."""
    progress = Progress(TextColumn("[bold]collect"), BarColumn(), MofNCompleteColumn(),
                        TextColumn("rejected {task.fields[rejected]}"),
                        TextColumn("mean solve {task.fields[solve]:.3f} s"), TimeElapsedColumn(),
                        console=_console(), disable=not enabled(flag))
    with progress:
        bar = progress.add_task("collect", total=n_traj, rejected=0, solve=0.0)

        def on_update(stats) -> None:
            progress.update(bar, completed=stats.kept, rejected=stats.rejected, solve=stats.mean_solve_time)

        yield on_update
