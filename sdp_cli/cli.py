"""The ``sdp`` command line: a thin Typer app over the package's functions.

Every :class:`~sdp_cli.errors.SdpError` becomes one line on stderr and exit code 1.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Annotated, Optional

import typer

import sdp_cli
from sdp_cli.families import DEFAULT_TO
from sdp_cli.cli_options import (DeviceOpt, ExecutorOpt, ProgressOpt, SchedulerOpt, ThreadsOpt,  # noqa: F401
                                 ToOpt, WorkersOpt, with_loop_algorithm_options, with_loop_rollout_options, with_train_options, clean_errors, int_list,
                                 set_threads, task_help)
from sdp_cli.errors import SdpError
from sdp_cli.seeds import check_loop_options
from sdp_cli.trajopt.timeout import solve_timeout
from sdp_cli.tasks import load_task_module, task_descriptions
from sdp_cli.algorithm.collect import CollectConfig, collect, policy_fingerprint
from sdp_cli.algorithm.refine import refine
from sdp_cli.data.artifacts import artifact_writes, check_folder, check_writable, git_revision
from sdp_cli.execution.workers import die_with_parent

app = typer.Typer(name="sdp", help="Sobolev Diffusion Policy toolkit.", no_args_is_help=True,
                  pretty_exceptions_enable=False, add_completion=False)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"sdp {sdp_cli.__version__} (git {git_revision()})")
        raise typer.Exit()


@app.callback()
@clean_errors
def _root(version: Annotated[Optional[bool], typer.Option("--version", callback=_version, is_eager=True,
                                                          help="Print the package version and git revision.")] = None,
          task_module: Annotated[Optional[list[Path]], typer.Option(
              "--plugin", "--task-module", help="A Python file that registers tasks (sdp_cli.tasks.register) "
              "and/or methods (sdp_cli.policy.registry.register_method) of your own; repeatable. Worker "
              "processes inherit it through SDP_TASK_MODULES. (--task-module: its older name.)")] = None,
          ) -> None:
    """Sobolev Diffusion Policy toolkit: collect, train, rollout, refine, report."""
    solve_timeout()   # a bad SDP_SOLVE_TIMEOUT is one line now, not a silent default (or a failure in a worker)
    if task_module:
        for f in task_module:
            load_task_module(f)


@app.command("tasks")
@clean_errors
def tasks_cmd() -> None:
    """List the registered tasks."""
    for name, desc in task_descriptions().items():
        typer.echo(f"{name:24s} {desc}")


@app.command("collect")
@clean_errors
def collect_cmd(
    task: Annotated[str, typer.Option(help=task_help())],
    n_traj: Annotated[int, typer.Option("--n-traj", help="Number of converged trajectories to keep.")] = 30,
    seed: Annotated[int, typer.Option(help="Seed: xi_i is a function of (seed, i).")] = 0,
    out: Annotated[Optional[Path], typer.Option(help="Dataset artifact (.npz); default data/<task>-n<N>-s<seed>.npz.")] = None,
    workers: WorkersOpt = None,
    max_iter: Annotated[int, typer.Option("--max-iter", help="Solver iteration cap; non-converged solves are rejected.")] = 1000,
    max_attempts: Annotated[Optional[int], typer.Option("--max-attempts", help="Cap on solves tried (default 20 x n_traj).")] = None,
    policy: Annotated[Optional[Path], typer.Option(help="Warm-start TO with this policy's rollouts and keep the better of policy-guess and naive-guess solves (Algorithm 1, lines 3-8).")] = None,
    t_a: Annotated[Optional[int], typer.Option("--t-a", help="With --policy: actions played per prediction.")] = None,
    k_rollout: Annotated[Optional[int], typer.Option("--k-rollout", help="With --policy: denoising steps.")] = None,
    conversion: Annotated[Optional[str], typer.Option(help="With --policy: how its predicted chunks become "
                                                           "controls (inverse-dynamics or tracking; default: the "
                                                           "task's).")] = None,
    to: ToOpt = DEFAULT_TO,
    executor: ExecutorOpt = None,
    scheduler: SchedulerOpt = None,
    threads: ThreadsOpt = 1,
    progress: ProgressOpt = True,
) -> None:
    """Solve OCPs (from the naive guess, or warm-started by a policy) and write a dataset with feedback gains."""
    from sdp_cli.progress import collect_progress, status

    set_threads(threads)
    if workers is not None and workers <= 0:
        raise SdpError(f"--workers must be > 0, got {workers}")
    config = CollectConfig(task=task, n_traj=n_traj, seed=seed, max_iter=max_iter, max_attempts=max_attempts,
                           policy=str(policy) if policy else None,
                           policy_fingerprint=policy_fingerprint(policy) if policy else None,
                           t_a=t_a, k_rollout=k_rollout, conversion=conversion, to=to)
    out = out or Path("data") / f"{task}-n{n_traj}-s{seed}.npz"
    status(f"{task}: loading the optimizer in each worker (compiled with gcc on first use: minutes for the "
           f"larger tasks, then cached)", progress)
    with collect_progress(n_traj, progress) as on_update:
        path, stats = collect(config, out, workers=workers, progress=on_update, executor=executor,
                              scheduler=scheduler)
    typer.echo(f"wrote {path}: {stats.kept} trajectories, {stats.rejected} rejected "
               f"({stats.convergence_rate:.0%} converged), mean solve {stats.mean_solve_time:.3f} s, "
               f"wall {stats.wall_time:.1f} s")


@app.command("rollout")
@clean_errors
def rollout_cmd(
    policy: Annotated[Path, typer.Option(help="Policy checkpoint (file or run folder) from `sdp train`.")],
    out: Annotated[Path, typer.Option(help="Rollout artifact to write (.npz).")],
    task: Annotated[Optional[str], typer.Option(help="Expected task (checked against the policy's).")] = None,
    n: Annotated[int, typer.Option(help="Number of test instances.")] = 50,
    seed: Annotated[int, typer.Option(help="Test seed: instances are disjoint from every training seed.")] = 0,
    t_a: Annotated[Optional[int], typer.Option("--t-a", help="Actions played per prediction (default T_h - T_o).")] = None,
    k_rollout: Annotated[Optional[int], typer.Option("--k-rollout", help="Denoising steps at rollout (default K).")] = None,
    conversion: Annotated[Optional[str], typer.Option(help="How a predicted chunk of states becomes controls: "
                                                           "inverse-dynamics (each row alone, open loop) or tracking "
                                                           "(a time-varying LQR around the chunk); default: the "
                                                           "task's (docs/training.md).")] = None,
    device: DeviceOpt = "auto",
    threads: ThreadsOpt = 1,
    progress: ProgressOpt = True,
) -> None:
    """Roll a trained policy out on a fixed test set (Algorithm 2, batched)."""
    from sdp_cli.progress import count_progress
    from sdp_cli.algorithm.rollout import RolloutConfig, rollout
    from sdp_cli.training.train import resolve_device

    set_threads(threads)
    with count_progress("rollout (time steps)", None, progress) as on_step:
        path, s = rollout(policy, out, RolloutConfig(n=n, seed=seed, t_a=t_a, k_rollout=k_rollout,
                                                       conversion=conversion),
                          task_name=task, device=str(resolve_device(device)), on_step=on_step)
    typer.echo(f"wrote {path}: {s['method']} mean cost {s['mean_cost']:.3g} (median {s['median_cost']:.3g}), "
               f"{s['reached']}/{s['n']} reached, {s['diverged']} diverged, {s['rollout_time']:.2f} s")


@app.command("refine")
@clean_errors
def refine_cmd(
    rollouts: Annotated[Path, typer.Option(help="Rollout artifact from `sdp rollout`.")],
    out: Annotated[Path, typer.Option(help="Dataset artifact to write (.npz), same format as `sdp collect`.")],
    max_iter: Annotated[int, typer.Option("--max-iter", help="Solver iteration cap.")] = 1000,
    baseline: Annotated[bool, typer.Option("--baseline/--no-baseline", help="Also solve from the naive guess (TO alone) and keep the better (ArgminCost).")] = True,
    single_shooting: Annotated[bool, typer.Option("--single-shooting", help="Also report a second NLP baseline, single shooting solved by IPOPT, from the policy's and the naive controls (not kept in the dataset).")] = False,
    to: ToOpt = DEFAULT_TO,
    workers: WorkersOpt = None,
    executor: ExecutorOpt = None,
    scheduler: SchedulerOpt = None,
    progress: ProgressOpt = True,
) -> None:
    """Solve the OCP warm-started by the policy's trajectories (Algorithm 1, line 7)."""
    from sdp_cli.progress import count_progress

    if workers is not None and workers <= 0:
        raise SdpError(f"--workers must be > 0, got {workers}")
    with count_progress("refine (instances)", None, progress) as on_done:
        path, s = refine(rollouts, out, max_iter=max_iter, baseline=baseline, single_shooting=single_shooting,
                         workers=workers, executor=executor, scheduler=scheduler, progress=on_done, to=to)
    typer.echo(f"wrote {path}: {s.kept}/{s.n} converged, policy guess won {s.policy_wins} "
               f"(tied {s.policy_ties}); "
               f"mean iterations {s.mean_pol_iterations:.1f} (policy) vs {s.mean_base_iterations:.1f} (naive), "
               f"mean solve {s.mean_pol_time:.3f} s vs {s.mean_base_time:.3f} s")


@app.command("evaluate")
@clean_errors
def evaluate_cmd(
    rollouts: Annotated[Path, typer.Option(help="Rollout artifact from `sdp rollout`.")],
    out: Annotated[Path, typer.Option(help="CSV file to write (one row).")],
    refined: Annotated[Optional[Path], typer.Option(help="Dataset from `sdp refine` of these rollouts.")] = None,
    tag: Annotated[Optional[list[str]], typer.Option(help="Extra column KEY=VALUE (repeatable), e.g. --tag experiment=small.")] = None,
    metrics: Annotated[Optional[Path], typer.Option(help="Also write the row as a JSON metrics file (DVC metrics).")] = None,
) -> None:
    """Summarize a run as one tidy CSV row (policy, refined and TO-alone metrics), with its manifest."""
    from sdp_cli.algorithm.evaluate import evaluation_artifacts, evaluation_row, write_evaluation, write_metrics

    extra = {}
    for t in tag or []:
        if "=" not in t:
            raise SdpError(f"--tag must be KEY=VALUE, got {t!r}")
        k, v = t.split("=", 1)
        extra[k] = v

    check_writable(out, metrics)   # both outputs, before writing either
    row = evaluation_row(rollouts, refined, extra)
    with artifact_writes():        # both, or (a write fails) neither
        write_evaluation([row], out, [evaluation_artifacts(rollouts, refined)])
        if metrics is not None:
            write_metrics(row, metrics)
    typer.echo(f"wrote {out}: " + ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                                            for k, v in row.items() if k in (
                                                "method", "policy_cost_mean", "refined_cost_mean",
                                                "refined_converged_rate", "argmin_cost_mean",
                                                "to_alone_cost_mean", "ss_to_alone_cost_mean",
                                                "ss_refined_cost_mean", "success_rate")))


@app.command("plot-dataset")
@clean_errors
def plot_dataset_cmd(
    path: Annotated[Path, typer.Argument(help="Dataset artifact (.npz) from `sdp collect` or `sdp refine`.")],
    out: Annotated[Path, typer.Option(help="Image to write (.png, .pdf, .svg, .jpg).")],
    max_traj: Annotated[int, typer.Option("--max-traj", help="Draw at most this many trajectories (the first ones).")] = 20,
    dpi: Annotated[int, typer.Option(help="Resolution of raster images.")] = 120,
) -> None:
    """Draw a dataset's end-effector / quadrotor paths in 3D with start, goal and obstacles."""
    from sdp_cli.report.figures.plot_dataset import plot_dataset

    written, n = plot_dataset(path, out, max_traj=max_traj, dpi=dpi)
    typer.echo(f"wrote {written}: {n} trajectories")


@app.command("train")
@with_train_options(required=("method",))
def train_cmd(
    data: Annotated[Path, typer.Option(help="Dataset artifact from `sdp collect` or `sdp refine`.")],
    out: Annotated[Path, typer.Option(help="Run folder: checkpoint.pt, epoch_<E>.pt, metrics.csv.")],
    device: DeviceOpt = "auto",
    resume: Annotated[bool, typer.Option("--resume", help="Continue the run in --out (after a kill).")] = False,
    init: Annotated[Optional[Path], typer.Option(help="Start from this checkpoint (weights, EMA, normalizer).")] = None,
    threads: ThreadsOpt = 1,
    progress: ProgressOpt = True,
    train=None,
) -> None:
    """Train a policy on a dataset (Algorithm 1, lines 11-23). Every training option (grouped by section below)
    is an option of `sdp loop` too, and a key of an experiment group's `train:`."""
    from sdp_cli.training.train import train as run_training

    set_threads(threads)
    path = run_training(data, out, train, device=device, resume=resume, init=init, progress=progress, log=typer.echo)
    typer.echo(f"wrote {path}")


@app.command("loop")
@with_train_options(required=("method",), check=check_loop_options)
@with_loop_rollout_options()
@with_loop_algorithm_options()
def loop_cmd(
    task: Annotated[str, typer.Option(help=task_help())],
    out: Annotated[Path, typer.Option(help="Run folder (it<k>/data.npz, policy/, eval/; summary.csv).")],
    n_traj: Annotated[str, typer.Option("--n-traj", help="Trajectories per iteration, e.g. 30 or 30,30,60 (last repeats).")] = "30",
    workers: WorkersOpt = None,
    device: DeviceOpt = "auto",
    executor: ExecutorOpt = None,
    scheduler: SchedulerOpt = None,
    threads: ThreadsOpt = 1,
    progress: ProgressOpt = True,
    train=None,
    rollout=None,
    algorithm=None,
) -> None:
    """Run Algorithm 1 (collect, train, evaluate, repeat); resumable. The training options are `sdp train`'s
    (--epochs per iteration; --seed also seeds collection, 1000 * seed + k; the --save-at checkpoints are
    evaluated too)."""
    from sdp_cli.algorithm.loop import LoopConfig, run_loop
    from sdp_cli.training.train import resolve_device

    set_threads(threads)
    cfg = LoopConfig(task=task, train=train, rollout=rollout, **algorithm, n_traj=int_list(n_traj, "--n-traj"),
                     workers=workers, device=str(resolve_device(device)), executor=executor, scheduler=scheduler)
    summary = run_loop(cfg, out, log=typer.echo, progress=progress)
    cols = [c for c in ("iteration", "t_a", "policy_cost_mean", "refined_cost_mean", "argmin_cost_mean",
                        "to_alone_cost_mean", "success_rate") if c in summary]
    typer.echo(summary[cols].to_string(index=False))


@app.command("pipeline")
@clean_errors
def pipeline_cmd(
    experiment: Annotated[str, typer.Argument(help="Experiment name: a file pipelines/<name>.yaml (" + ", ".join(
        sorted(p.stem for p in Path("pipelines").glob("*.yaml"))) + " here).")],
    params: Annotated[Path, typer.Option(help="DVC params file to write the stage lists into.")] = Path("params.yaml"),
    estimate: Annotated[bool, typer.Option("--estimate", help="Print each run's training steps, samples and estimated hours (training calibrated here: <= 60 s of timed steps, plus each compiled network's compile, minutes with a cold cache), and the totals; writes nothing.")] = False,
    run: Annotated[bool, typer.Option("--run", help="Run every run of the experiment now (each an `sdp loop` in OUT/<run>/), in parallel on the executor; resumable. This is what the DVC stage `group` runs.")] = False,
    status: Annotated[bool, typer.Option("--status", help="Print where each run stands in OUT (iterations evaluated, done / in progress / not started); reads only.")] = False,
    out: Annotated[Optional[Path], typer.Option(help="--run, --status: folder of the runs (default runs/<experiment>).")] = None,
    only: Annotated[Optional[str], typer.Option(help="--run, --estimate: comma-separated run names to run or estimate (default all).")] = None,
    restart_changed: Annotated[bool, typer.Option("--restart-changed", help="--run: start over a run whose folder holds other settings (the experiment file changed) instead of refusing; what the DVC stage does.")] = False,
    workers: Annotated[Optional[int], typer.Option(help="--run: worker processes (default $SDP_WORKERS, else all cores); --estimate: parallel workers for the total (default 2).")] = None,
    executor: Annotated[Optional[str], typer.Option(help="--run: local (process pool; default $SDP_EXECUTOR, else local) or dask.")] = None,
    scheduler: Annotated[Optional[str], typer.Option(help="--run: address of a running Dask scheduler (default $SDP_SCHEDULER).")] = None,
    stack: Annotated[Optional[int], typer.Option(help="--run, --estimate: runs trained together as one stacked network (compatible runs: fig1's, or loops of as many iterations and dataset sizes, trained in lockstep; default 8, fixed so that a seed gives the same bytes on any machine; 1: every run alone).")] = None,
) -> None:
    """Select the experiment that `dvc repro` runs (pipelines/<name>.yaml, written into params.yaml), or run it (--run)."""
    from sdp_cli.experiments.pipeline import select_experiment

    if estimate + run + status > 1:
        raise SdpError("--estimate, --run and --status exclude each other")
    if status:
        from sdp_cli.experiments.runner import status_text

        typer.echo(status_text(experiment, out or Path("runs") / experiment))
        return
    if estimate:
        from sdp_cli.experiments.estimate import estimate as run_estimate, format_estimate

        df, totals = run_estimate(experiment, workers or 2, log=lambda s: typer.echo(s, err=True), stack=stack,
                                  only=[s for s in (only or "").split(",") if s] or None)
        typer.echo(format_estimate(experiment, df, totals))
        return
    if run:
        from sdp_cli.experiments.runner import run_group, summary_text

        check_folder(out, "runs folder")
        if os.environ.get("DVC_STAGE"):   # run by `dvc repro`: a kill -9 of dvc takes this runner (and so its workers)
            die_with_parent(os.getppid())

        names = [s for s in (only or "").split(",") if s] or None
        summary = run_group(experiment, out or Path("runs") / experiment, executor=executor, workers=workers,
                            scheduler=scheduler, only=names, restart_changed=restart_changed,
                            log=lambda s: typer.echo(s, err=True), stack=stack)
        typer.echo(summary_text(summary))
        return

    counts = select_experiment(experiment, params)
    typer.echo(f"selected {experiment!r} in {params}: " + ", ".join(f"{v} {k}" for k, v in counts.items())
               + "; run `dvc repro`")


@app.command("check-task")
@clean_errors
def check_task_cmd(
    task: Annotated[str, typer.Argument(help=task_help())],
    n_traj: Annotated[int, typer.Option("--n-traj", help="TO optima (from the naive guess) for the oracle replay, the memorizer and the timing.")] = 2,
    cases: Annotated[Optional[str], typer.Option(help="(T_h, T_a) pairs for the memorizer, e.g. 32:31,64:63 (default: those pipelines/*.yaml use for this task, and 32:31).")] = None,
    solve: Annotated[bool, typer.Option("--solve/--no-solve", help="Also run the checks that need TO optima (oracle replay, memorizer, timing).")] = True,
) -> None:
    """Check a task's contract before training on it: dynamics, derivatives vs finite differences, oracle
    replay, the memorizer (a perfect learner must score TO's cost) and the timing of its optimum."""
    from sdp_cli.checks.contract import check_task

    n = check_task(task, n_traj, cases, solve, echo=typer.echo)
    typer.echo(f"task {task!r} passes all {n} checks")


@app.command("report")
@clean_errors
def report_cmd(
    runs: Annotated[Optional[Path], typer.Option(help="Folder of runs (a DVC experiment under runs/, or `sdp loop` folders; symlinked folders are followed).")] = None,
    out: Annotated[Optional[Path], typer.Option(help="Output folder for tables (CSV, markdown) and figures (PNG), e.g. results/fig2 (required with --runs).")] = None,
    experiment: Annotated[Optional[str], typer.Option(help="Experiment name for the index (default: the runs folder's name).")] = None,
    metrics: Annotated[Optional[Path], typer.Option(help="Also write the last iteration's mean costs and success per task and method as JSON (DVC metrics).")] = None,
    ledger: Annotated[Optional[Path], typer.Option(help="Then (re)write the claims ledger, e.g. results/PAPER.md, from the reports in its folder (*/all_runs.csv, bench/*.csv) and its claims.yaml.")] = None,
    keep_missing: Annotated[bool, typer.Option("--keep-missing", help="Extend the report already in --out: keep its rows (and per-run tables) of runs that have no evaluation under --runs, e.g. run folders made on another machine; --runs may then hold no evaluation yet.")] = False,
) -> None:
    """Write the paper's tables and figures from whatever runs exist, and the claims ledger."""
    if runs is None and ledger is None:
        raise SdpError("nothing to do: give --runs (a report) and/or --ledger (the claims ledger)")

    check_folder(out, "report folder")
    check_writable(metrics, ledger)   # every output, before any work
    if runs is not None:
        from sdp_cli.report.make import make_report

        if out is None:   # no default: results/ holds every committed report and the index
            raise SdpError("--runs needs --out, the report's folder, e.g. --out results/" + Path(runs).name)
        files = make_report(runs, out, experiment, log=lambda s: typer.echo(s, err=True), metrics=metrics,
                            keep_missing=keep_missing)
        typer.echo(f"wrote {len(files)} files to {out}")
    if ledger is not None:
        from sdp_cli.report.ledger import write_ledger

        typer.echo(f"wrote {write_ledger(ledger)}")


@app.command("migrate")
@clean_errors
def migrate_cmd(
    runs: Annotated[Path, typer.Argument(help="Folder of runs whose evaluations were written by older code.")],
) -> None:
    """Bring evaluations written by older code to this code's layout, once (the old files stay as *.v1)."""
    from sdp_cli.migrate import migrate_runs

    done, current = migrate_runs(runs, log=lambda s: typer.echo(s, err=True))
    typer.echo(f"migrated {done} evaluation(s) under {runs}; {current} already current")


def main(argv: list[str] | None = None) -> int:
    """The ``sdp`` entry point: a usage error (unknown option, bad value, missing argument) is one line on
    stderr and exit code 2 (click's code for usage errors; errors of the work itself exit with 1)."""
    try:
        from typer._click import exceptions as click_exc   # typer vendors its click
    except ImportError:  # pragma: no cover - typer releases that use click itself
        from click import exceptions as click_exc

    try:
        rv = app(args=argv, standalone_mode=False, prog_name="sdp")
    except getattr(click_exc, "NoArgsIsHelpError", ()):   # `sdp` alone: the help was printed
        return 0
    except click_exc.UsageError as e:
        cmd = e.ctx.command_path if e.ctx is not None else "sdp"
        typer.echo(f"Error: {e.format_message()} (see `{cmd} --help`)", err=True)
        return 2
    except getattr(click_exc, "Abort", ()):
        typer.echo("Interrupted.", err=True)
        return 130
    return rv if isinstance(rv, int) else 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
