"""``sdp loop``: Algorithm 1 end to end, resumable.

For iteration ``k = 0 .. n_algo-1`` in ``OUT/it<k>/``:

1. ``data.npz``   — collect ``n_traj[k]`` trajectories: naive-guess TO at ``k = 0``, then TO
   warm-started by the previous policy with ArgminCost (``sdp collect --policy``); the
   collection seed of iteration ``k`` is ``1000 * seed + k`` (disjoint from the test seed);
2. ``buffer.npz`` — only with ``reset_buffer=False``: the union of all collections so far;
3. ``policy/``    — ``sdp train`` for ``epochs`` epochs, from the previous iteration's
   weights, EMA and normalizer (``--init``) when ``k > 0``;
4. ``eval/``      — ``sdp rollout`` on the fixed test set (``n_test`` instances of the test
   seed), ``sdp refine`` of those rollouts (policy guess vs naive guess) and ``sdp evaluate``,
   for the final policy (``rollout_ta<T_a>.npz``) and for the checkpoints kept at the
   ``save_at`` epochs (``rollout_e<E>-ta<T_a>.npz``; Fig. 1's two budgets from one training).

Every stage writes its artifact atomically, so "the artifact exists" means "the stage is
done": re-running the same command after a kill continues from the last finished stage
(training itself resumes from its last checkpoint). ``OUT/loop_config.json`` records the
settings; resuming with other settings (other than ``RESUMABLE_FIELDS``: more iterations,
more evaluated T_a, where the work runs) is refused rather than mixed into one folder.
Solves run on the executor of ``executor``/``workers``/``scheduler`` (local pool or Dask).
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Callable
import json
import time

import numpy as np
import pandas as pd

from sdp_cli.algorithm.loop_options import LoopAlgorithmOptions, LoopRolloutConfig  # (re-exported: sdp_cli.algorithm.loop.*)
from sdp_cli.data.artifacts import atomic_write_bytes, ensure_dir, load_npz, save_npz
from sdp_cli.errors import SdpError
from sdp_cli.rules import rule
from sdp_cli.policy.config import TrainConfig, flat_options
from sdp_cli.seeds import check_loop_seed
from sdp_cli.execution.executor import check_executor_options
from sdp_cli.tasks import get_task
from sdp_cli.trajopt import check_to
from sdp_cli import RESULTS_VERSION
from sdp_cli.data.artifacts import code_revision
from sdp_cli.algorithm.refine import refine
from sdp_cli.data.artifacts import load_timing
from sdp_cli.algorithm.collect import CollectConfig, collect, policy_fingerprint


@dataclass(frozen=True)
class LoopConfig(LoopAlgorithmOptions):
    """One run of Algorithm 1: its task, the typed training config (:class:`TrainConfig`: method, epochs,
    seed, architecture, ...), Algorithm 1's own options (:class:`~sdp_cli.algorithm.loop_options.LoopAlgorithmOptions`:
    ``n_algo``, ``reset_buffer``, ``max_iter``, ``to``, keyword-only), the rollout settings
    (:class:`LoopRolloutConfig`) and where the work runs."""

    task: str
    train: TrainConfig
    rollout: LoopRolloutConfig = field(default_factory=LoopRolloutConfig)
    n_traj: tuple = field(default=(30,), metadata=rule(ge=1))  # per iteration; the last value repeats
    workers: int | None = None
    device: str = "cpu"
    executor: str | None = None    # where collect/refine solves run: local or dask (sdp_cli.execution.executor)
    scheduler: str | None = None   # address of a running Dask scheduler

    def __post_init__(self):
        object.__setattr__(self, "n_traj", tuple(int(n) for n in self.n_traj))
        LoopAlgorithmOptions.__post_init__(self)
        check_loop_seed(self.seed, "seed", self.n_algo)
        if not self.n_traj:
            raise SdpError("n_traj must be positive integers, got []")

        check_executor_options(self.executor, self.workers, self.scheduler)
        self.validate()

    # the training settings the loop itself reads (one name each: TrainConfig's)
    @property
    def method(self) -> str:
        return self.train.method

    @property
    def seed(self) -> int:
        return self.train.seed

    @property
    def epochs(self) -> int:
        return self.train.data.epochs

    @property
    def horizon(self) -> int:
        return self.train.policy.horizon

    @property
    def save_at(self) -> list[int]:
        return self.train.save_at

    def validate(self) -> None:
        """Everything checkable before any file is written: task, TO family, T_a, k_rollout."""
        task = get_task(self.task)
        check_to(self.to)
        if self.max_iter <= 0:
            raise SdpError(f"max_iter must be > 0, got {self.max_iter}")
        tcfg, r = self.train, self.rollout
        if tcfg.chunked and self.horizon > task.T + 1:
            raise SdpError(f"horizon {self.horizon} is longer than the task's T + 1 = {task.T + 1}")
        # the policies' own rules (Policy.max_t_a, Policy.sampler_options), from the config before any policy
        hi, what = (tcfg.policy.max_t_a, "T_h - T_o") if tcfg.chunked else (1, "one control per state")
        for name, values in (("t_a", () if r.t_a is None else (r.t_a,)), ("eval_t_a", r.eval_t_a),
                             ("eval_t_a_last", r.eval_t_a_last)):
            bad = [v for v in values if not 1 <= v <= hi]
            if bad:
                raise SdpError(f"{name} {bad} outside [1, {what}] = [1, {hi}] for method {tcfg.method!r}")
        if r.k_rollout is not None:
            K = tcfg.policy_class.sampler_steps(tcfg) if tcfg.chunked else None
            if K is None:
                raise SdpError(f"k_rollout (denoising steps at rollout) applies to chunked diffusion policies; "
                               f"{tcfg.method!r} has no sampler")
            if not 1 <= r.k_rollout <= K:
                raise SdpError(f"k_rollout must be in [1, K] = [1, {K}], got {r.k_rollout}")

    def n_traj_at(self, k: int) -> int:
        return int(self.n_traj[min(k, len(self.n_traj) - 1)])

    def collect_seed(self, k: int) -> int:
        return 1000 * self.seed + k

    def to_dict(self) -> dict:
        """Plain types, nested like the config (``loop_config.json``, the runner's jobs)."""
        d = asdict(self)
        d["train"] = self.train.to_dict()
        return d

    @classmethod
    def from_dict(cls, d: dict, **override) -> "LoopConfig":
        """From :meth:`to_dict`, or the flat layout of loop folders before the sections (migrated)."""
        d = migrate_loop_dict(d)
        d = {**{k: v for k, v in d.items() if k in {f.name for f in fields(cls)}}, **override}
        return cls(**{**d, "train": TrainConfig.from_dict(d["train"]),
                      "rollout": LoopRolloutConfig(**d.get("rollout", {}))})


#: loop settings of the flat layout (before results version 3's sections) that moved into ``rollout``
_ROLLOUT_KEYS = tuple(f.name for f in fields(LoopRolloutConfig))


def migrate_loop_dict(d: dict) -> dict:
    """A ``loop_config.json`` dict in the current layout: older ones were flat, with the training options
    ``method, epochs, seed, horizon, save_at`` and ``train_options`` (older names) at the top."""
    if isinstance(d.get("train"), dict):
        return d
    d = dict(d)
    opts = {"method": d.pop("method"), "epochs": d.pop("epochs", 1000), "seed": d.pop("seed", 0),
            "horizon": d.pop("horizon", 32), "save_at": list(d.pop("save_at", ())),
            **flat_options(d.pop("train_options", None) or {})}
    d["rollout"] = {k: d.pop(k) for k in _ROLLOUT_KEYS if k in d}
    d["train"] = TrainConfig.of(**opts).to_dict()
    return d


# settings that may change when a loop is resumed (where it runs, how much is evaluated), as dotted keys
RESUMABLE_FIELDS = ("n_algo", "rollout.eval_t_a", "rollout.eval_t_a_last", "workers", "device", "executor",
                    "scheduler", "rollout.single_shooting", "rollout.eval_refine", "train.checkpoint_every_s",
                    "code_rev", "results_version")


def _config_json(cfg: LoopConfig) -> str:
    return json.dumps({**cfg.to_dict(), "code_rev": code_revision(), "results_version": RESULTS_VERSION},
                      indent=2)


def _dotted(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_dotted(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = list(v) if isinstance(v, tuple) else v
    return out


def check_resume(cfg: LoopConfig, out: Path, same_results: bool = False) -> None:
    """Refuse to resume ``out`` with settings that would mix two experiments in one folder.

    ``loop_config.json`` also records the code revision (:func:`sdp_cli.data.artifacts.code_revision`)
    and the results version (:data:`sdp_cli.RESULTS_VERSION`) of the last (re)start: ``sdp loop``
    resumes across both (the artifacts record their revision); with ``same_results`` (the DVC stage)
    another results version (none recorded: version 1) counts as other settings. A code revision alone
    never does: a comment edit must not restart 70 hours of runs. Folders of the older flat layout are
    compared after :func:`migrate_loop_dict`."""
    path = out / "loop_config.json"
    if not path.exists():
        if out.is_dir() and any(out.iterdir()):
            raise SdpError(f"{out} holds files but no loop_config.json (not an `sdp loop` folder, or one of "
                           "unknown settings); use another --out")
        return
    try:
        raw = json.loads(path.read_text())
        old = _dotted({**migrate_loop_dict(raw), "results_version": raw.get("results_version", 1)})
    except (OSError, ValueError, KeyError, TypeError, SdpError) as e:
        raise SdpError(f"corrupt loop config {path}: {e}") from None
    old.setdefault("rollout.conversion", None)   # folders made before the setting: the task's default
    new = _dotted(json.loads(_config_json(cfg)))
    bad = [k for k in new if k not in RESUMABLE_FIELDS and k in old and old[k] != new[k]]
    if same_results and old["results_version"] != new["results_version"]:
        bad.append("results_version")
    if bad:
        diffs = ", ".join(f"{k}={old[k]!r} (now {new[k]!r})" for k in bad)
        raise SdpError(f"{out} holds a loop run with other settings: {diffs}; use another --out")


def merge_datasets(paths: list[Path], out: Path) -> Path:
    """Union of dataset artifacts of one task (the non-reset buffer of Algorithm 1)."""
    parts = [load_npz(p, kind="dataset") for p in paths]
    tasks = {m["task"] for _, m in parts}
    if len(tasks) != 1:
        raise SdpError(f"cannot merge datasets of different tasks: {sorted(tasks)}")
    keys = [k for k in parts[0][0] if not k.startswith("inst_") and all(k in a for a, _ in parts)]
    arrays = {k: np.concatenate([a[k] for a, _ in parts]) for k in keys}
    meta = dict(parts[-1][1])
    extra = {k: meta[k] for k in ("task", "task_options", "task_params", "dims") if k in meta}
    return save_npz(out, arrays, kind="dataset", config={"merged": [str(p) for p in paths]}, **extra)


def train_done(policy_dir: Path) -> bool:
    ck = policy_dir / "checkpoint.pt"
    if not ck.exists():
        return False
    from sdp_cli.policy.checkpoint import load_checkpoint

    return bool(load_checkpoint(ck).get("finished"))


def run_iteration_eval(policy_dir: Path, eval_dir: Path, cfg: LoopConfig, extra: dict,
                       log: Callable[[str], None], last: bool = False, progress: bool = False) -> pd.DataFrame:
    """Rollout + refine + evaluate the policy on the fixed test set, for each eval T_a
    (without refine when ``cfg.rollout.eval_refine`` is off: the policy's own metrics only)."""
    from sdp_cli.algorithm.evaluate import evaluation_artifacts, evaluation_row, write_evaluation
    from sdp_cli.progress import count_progress
    from sdp_cli.algorithm.rollout import RolloutConfig, rollout


    t0 = time.perf_counter()
    new_work = reused = 0      # artifacts made by this call / found made by an earlier one
    rows, artifacts = [], []
    r = cfg.rollout
    t_as = list(r.eval_t_a or (r.t_a,))
    if last:
        t_as += [t for t in r.eval_t_a_last if t not in t_as]
    # the final policy, then the checkpoints kept at the save_at epochs (Fig. 1's two budgets)
    ckpts = [(policy_dir, "")] + [(policy_dir / f"epoch_{e}.pt", f"e{e}-") for e in sorted(cfg.save_at)]
    for (ckpt, prefix), t_a in ((c, t) for c in ckpts for t in t_as):
        tag = prefix + (f"ta{t_a}" if t_a is not None else "ta-default")
        ro, rf = eval_dir / f"rollout_{tag}.npz", eval_dir / f"refined_{tag}.npz"
        if ro.exists():
            reused += 1
        else:
            new_work += 1
            with count_progress(f"rollout {tag} (time steps)", None, progress) as on_step:
                _, s = rollout(ckpt, ro, RolloutConfig(n=r.n_test, seed=r.test_seed, t_a=t_a,
                                                             k_rollout=r.k_rollout, conversion=r.conversion),
                               device=cfg.device,
                               on_step=on_step)
            log(f"  rollout {tag}: mean cost {s['mean_cost']:.3g}, {s['reached']}/{s['n']} reached")
        if r.eval_refine and rf.exists():
            reused += 1
        elif r.eval_refine:
            new_work += 1
            with count_progress(f"refine {tag} (instances)", None, progress) as on_done:
                refine(ro, rf, max_iter=cfg.max_iter, single_shooting=r.single_shooting, workers=cfg.workers,
                       executor=cfg.executor or "local", scheduler=cfg.scheduler, progress=on_done, to=cfg.to)
        rows.append(evaluation_row(ro, rf if r.eval_refine else None, extra))
        artifacts.append(evaluation_artifacts(ro, rf if r.eval_refine else None))
    df = pd.DataFrame(rows)
    # the measured wall time of the evaluation (rollouts, refinement with every baseline, evaluation), not a sum
    # of parts. A resume that found every artifact made keeps the recorded one; one that found some made records
    # its own time and says the measurement is partial.

    before = load_timing(eval_dir / "eval.csv")
    wall, partial = time.perf_counter() - t0, bool(reused)
    if not new_work and "wall_time" in before:
        wall, partial = before["wall_time"], bool(before.get("wall_partial", False))
    write_evaluation(rows, eval_dir / "eval.csv", artifacts, wall_time=wall, wall_partial=partial)
    return df


def begin_loop(cfg: LoopConfig, out: str | os.PathLike) -> Path:
    """The loop folder, checked against the settings it holds (:func:`check_resume`), with this start's
    ``loop_config.json``."""
    out = Path(out)
    ensure_dir(out, "loop folder")
    check_resume(cfg, out)
    atomic_write_bytes(out / "loop_config.json", lambda f: f.write(_config_json(cfg).encode()))
    return out


def collect_iteration(cfg: LoopConfig, out: Path, k: int, prev_policy: Path | None,
                      log: Callable[[str], None] = print, progress: bool = False) -> Path:
    """Iteration ``k``'s dataset ``out/it<k>/data.npz`` (collected unless it exists): the naive-guess TO at
    ``k = 0``, then TO warm-started by ``prev_policy``'s rollouts with ArgminCost."""
    data = out / f"it{k}" / "data.npz"
    if not data.exists():
        log(f"[it{k}] collect {cfg.n_traj_at(k)} trajectories" + (" (policy warm start)" if prev_policy else ""))
        ccfg = CollectConfig(task=cfg.task, n_traj=cfg.n_traj_at(k), seed=cfg.collect_seed(k),
                             max_iter=cfg.max_iter,
                             policy=str(prev_policy) if prev_policy else None,
                             policy_fingerprint=policy_fingerprint(prev_policy) if prev_policy else None,
                             t_a=cfg.rollout.t_a if prev_policy else None,
                             k_rollout=cfg.rollout.k_rollout if prev_policy else None,
                             conversion=cfg.rollout.conversion if prev_policy else None, to=cfg.to)
        from sdp_cli.progress import collect_progress

        with collect_progress(ccfg.n_traj, progress) as on_update:
            collect(ccfg, data, workers=cfg.workers, executor=cfg.executor or "local", scheduler=cfg.scheduler,
                    progress=on_update)
    return data


def iteration_data(cfg: LoopConfig, out: Path, k: int, prev_policy: Path | None,
                   log: Callable[[str], None] = print, progress: bool = False) -> Path:
    """What iteration ``k`` trains on: its dataset (:func:`collect_iteration`), or, without ``reset_buffer``,
    the union of every dataset so far (``it<k>/buffer.npz``, Algorithm 1's buffer)."""
    data = collect_iteration(cfg, out, k, prev_policy, log, progress)
    if cfg.reset_buffer or k == 0:
        return data
    buffer = out / f"it{k}" / "buffer.npz"
    if not buffer.exists():
        merge_datasets([out / f"it{j}" / "data.npz" for j in range(k + 1)], buffer)
    return buffer


def run_loop(cfg: LoopConfig, out: str | os.PathLike, log: Callable[[str], None] = print,
             progress: bool = False) -> pd.DataFrame:
    """Run (or resume) Algorithm 1 in ``out``; returns the per-iteration evaluation table.
    ``progress``: bars on stderr for every phase (on a terminal only, :func:`sdp_cli.progress.enabled`)."""
    from sdp_cli.algorithm.evaluate import is_timing_column
    from sdp_cli.training.train import train

    out = begin_loop(cfg, out)
    tables, prev_policy = [], None
    for k in range(cfg.n_algo):
        d = out / f"it{k}"
        train_data = iteration_data(cfg, out, k, prev_policy, log, progress)
        policy_dir = d / "policy"
        if not train_done(policy_dir):
            log(f"[it{k}] train {cfg.method} for {cfg.epochs} epochs" + (" (init from previous)" if prev_policy else ""))
            train(train_data, policy_dir, cfg.train, device=cfg.device, resume=(policy_dir / "checkpoint.pt").exists(),
                  init=(prev_policy / "checkpoint.pt") if prev_policy else None, progress=progress,
                  log=lambda s: None)
        log(f"[it{k}] evaluate on {cfg.rollout.n_test} test instances")
        df = run_iteration_eval(policy_dir, d / "eval", cfg, {"run": out.name, "iteration": k, "loop_seed": cfg.seed,
                                                                   "n_algo": cfg.n_algo,
                                                                   "results_version": RESULTS_VERSION},
                                log,
                                last=k == cfg.n_algo - 1, progress=progress)
        tables.append(df)
        prev_policy = policy_dir
    summary = pd.concat(tables, ignore_index=True)
    # summary.csv is hashed (a DVC output): no clock readings, which live in each eval's timing sidecar
    stored = summary.drop(columns=[c for c in summary.columns if is_timing_column(c)])
    atomic_write_bytes(out / "summary.csv", lambda f: f.write(stored.to_csv(index=False).encode()))
    return summary
