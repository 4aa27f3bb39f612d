"""``metrics.csv`` of a training run: one row per step, appended every few seconds, rewritten with each checkpoint."""

from __future__ import annotations

import csv
import io
import time
from pathlib import Path

from sdp_cli.data.artifacts import atomic_write_bytes

METRICS_EVERY_S = 5.0   # metrics.csv is appended to this often (and rewritten with each checkpoint)
METRIC_FIELDS = ("step", "epoch", "loss", "dp", "sobolev", "lr", "grad_norm")


class MetricsLog:
    """``metrics.csv`` of a run: one row per step (:data:`METRIC_FIELDS`), appended to the file every
    :data:`METRICS_EVERY_S` seconds and rewritten whole with each checkpoint."""

    def __init__(self, path: Path, rows: list[dict], resumed: bool):
        self.path, self.rows = path, rows
        self.flushed = len(rows) if resumed else 0
        self.last_flush = time.perf_counter()
        if resumed:   # drop rows the killed run logged after its last checkpoint
            self.rewrite()

    @staticmethod
    def read(path: Path, max_step: int) -> list[dict]:
        if not path.is_file():
            return []
        with open(path, newline="") as f:
            return [r for r in csv.DictReader(f) if int(r["step"]) <= max_step]

    def to_bytes(self) -> bytes:
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=METRIC_FIELDS, extrasaction="ignore")   # (older files: wall_time)
        w.writeheader()
        w.writerows(self.rows)
        return buf.getvalue().encode()

    def add(self, step: int, steps_per_epoch: int, loss, parts: dict, lr: float, gnorm) -> dict:
        row = {"step": step, "epoch": step // steps_per_epoch, "loss": f"{loss.item():.6g}",
               "dp": f"{parts['dp'].item():.6g}", "sobolev": f"{parts['sobolev'].item():.6g}",
               "lr": f"{lr:.6g}", "grad_norm": f"{float(gnorm):.4g}"}
        self.rows.append(row)
        if time.perf_counter() - self.last_flush >= METRICS_EVERY_S:
            self.flush()
            self.last_flush = time.perf_counter()
        return row

    def rewrite(self) -> None:
        atomic_write_bytes(self.path, lambda f: f.write(self.to_bytes()))
        self.flushed = len(self.rows)

    def flush(self) -> None:
        """Append the rows since the last write (metrics.csv follows training every few seconds)."""
        if self.flushed == 0:
            self.rewrite()
            return
        with open(self.path, "a", newline="") as f:
            csv.DictWriter(f, fieldnames=METRIC_FIELDS, extrasaction="ignore").writerows(self.rows[self.flushed:])
        self.flushed = len(self.rows)
