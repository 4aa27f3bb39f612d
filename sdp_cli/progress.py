"""Rich progress bars for the long loops of the CLI (stderr, quiet when not a terminal)."""

from __future__ import annotations

import contextlib
import sys
from typing import Iterator

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn


def _console() -> Console:
    return Console(stderr=True)


@contextlib.contextmanager
def collect_progress(n_traj: int) -> Iterator:
    """Yield a callback ``on_update(stats)`` that drives a kept/rejected/solve-time bar."""
    progress = Progress(TextColumn("[bold]collect"), BarColumn(), MofNCompleteColumn(),
                        TextColumn("rejected {task.fields[rejected]}"),
                        TextColumn("mean solve {task.fields[solve]:.3f} s"), TimeElapsedColumn(),
                        console=_console(), disable=not sys.stderr.isatty())
    with progress:
        bar = progress.add_task("collect", total=n_traj, rejected=0, solve=0.0)

        def on_update(stats) -> None:
            progress.update(bar, completed=stats.kept, rejected=stats.rejected, solve=stats.mean_solve_time)

        yield on_update
