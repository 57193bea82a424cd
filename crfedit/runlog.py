"""Run records of a training run, beside the model file ``NAME.safetensors``:

- ``NAME.run.json``: the resolved config and how the run was started (command, dataset,
  seed, device, threads), written when training starts; a ``--resume`` keeps that record and
  appends how it was continued to its ``resumes`` list;
- ``NAME.log.csv``: step, loss, train PSNR, rays/s, learning rate and elapsed seconds every
  ``every`` steps (appended to on ``--resume``);
- ``NAME.tb/``: the same scalars as TensorBoard events, when ``tensorboard`` is installed
  (``pip install -e '.[tensorboard]'``).
"""

from __future__ import annotations

import csv
import json
import math
import shutil
import textwrap
from pathlib import Path

from .config import Config
from .io import atomic_write_bytes, atomic_write_text, write_json

COLUMNS = ("step", "loss", "psnr", "rays_per_s", "lr", "seconds")


def record_paths(model_path: Path) -> dict[str, Path]:
    stem = Path(model_path).with_suffix("")
    return {"run": stem.with_name(stem.name + ".run.json"), "log": stem.with_name(stem.name + ".log.csv"),
            "tensorboard": stem.with_name(stem.name + ".tb")}


def config_block(cfg: Config, width: int = 100) -> str:
    """The resolved config as one block of ``key=value`` pairs, wrapped at ``width``."""
    pairs = " ".join(f"{k}={v}" for k, v in json.loads(cfg.to_json()).items())
    return "\n".join(textwrap.wrap(pairs, width, initial_indent="  ", subsequent_indent="  "))


def _tensorboard_writer(folder: Path):
    """A SummaryWriter, or None when tensorboard is not installed."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        return None
    return SummaryWriter(str(folder))


LOG_EVERY = 100
"""Steps between the CSV log's rows, unless ``--log-every`` says otherwise."""


def started_with(model_path: Path, key: str) -> list[int]:
    """The positive whole numbers ``key`` (``log_every``, ``threads``) that the run's start and
    resumes recorded, in order (its ``run.json``); [] when the record does not say."""
    try:
        first = json.loads(record_paths(model_path)["run"].read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return []
    if not isinstance(first, dict):
        return []
    resumes = first.get("resumes")
    starts = [first, *(r for r in resumes if isinstance(r, dict))] if isinstance(resumes, list) else [first]
    return [n for n in (r.get(key) for r in starts) if isinstance(n, int) and not isinstance(n, bool) and n >= 1]


def stored_log_every(model_path: Path) -> int:
    """The ``--log-every`` a run was last started or resumed with, so that ``--resume`` keeps
    the log's cadence (it fell back to 100: rows at 20, 40, … 100, then 200); :data:`LOG_EVERY`
    when the record does not say."""
    said = started_with(model_path, "log_every")
    return said[-1] if said else LOG_EVERY


def run_record(path: Path, run: dict, cfg: Config, resume: bool) -> dict:
    """What ``NAME.run.json`` holds after this start: a fresh run's record, or on ``resume`` the
    first start's record (when it reads as one) with this start appended to ``resumes``, so the
    command that began the run is never lost."""
    record = {**run, "config": json.loads(cfg.to_json())}
    if not resume or not path.is_file():
        return record
    try:
        first = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return record
    if not isinstance(first, dict) or "command" not in first:
        return record
    resumes = first.get("resumes") if isinstance(first.get("resumes"), list) else []
    keys = ("command", "device", "threads", "minutes", "resumed_at", "world_size", "log_every")
    return {**first, "resumes": [*resumes, {k: run.get(k) for k in keys}]}


def _drop_rows_after(path: Path, step: int) -> None:
    """Rewrite the log ``path`` without its rows past ``step``: a run interrupted (or killed)
    after its last checkpoint logged steps that ``--resume`` trains again, and their rows would
    appear twice.  Rows whose step does not read as a number stay."""
    lines = path.read_text().splitlines(keepends=True)
    kept = [line for i, line in enumerate(lines) if i == 0 or not line.split(",", 1)[0].strip().isdigit()
            or int(line.split(",", 1)[0]) <= step]
    if len(kept) != len(lines):
        atomic_write_text(path, "".join(kept))


class RunLog:
    """Writes the run records; ``on_step`` has :func:`crfedit.train.train`'s callback signature."""

    def __init__(self, model_path: Path, cfg: Config, every: int, minutes: float | None, resume: bool, run: dict):
        from .train import learning_rate

        self.paths, self.cfg, self.every = record_paths(model_path), cfg, max(1, every)
        self.budget = None if minutes is None else 60.0 * minutes
        self._lr = learning_rate
        # the records as they were, for take_back()
        self._before = {p: p.read_bytes() if p.is_file() else None for p in (self.paths["run"], self.paths["log"])}
        tb = self.paths["tensorboard"]
        self._tb_before = set(tb.rglob("*")) if tb.is_dir() else None
        write_json(self.paths["run"], run_record(self.paths["run"], run, cfg, resume))
        # an empty log (a run killed before its header reached the disk) starts again with its header
        fresh = not (resume and self.paths["log"].is_file() and self.paths["log"].stat().st_size > 0)
        if not fresh and isinstance(run.get("resumed_at"), int):
            _drop_rows_after(self.paths["log"], run["resumed_at"])  # steps past the checkpoint are trained again
        self.file = open(self.paths["log"], "w" if fresh else "a", newline="")
        self.csv = csv.writer(self.file)
        if fresh:
            self.csv.writerow(COLUMNS)
            self.file.flush()  # on disk now: a run killed before its first row leaves a log with its header
        self.tb = _tensorboard_writer(self.paths["tensorboard"])
        self._last: tuple | None = None  # the last read-out: (its step, loss, PSNR, rays/s), and the last step written
        self._rate = 0.0  # the last rays/s reported
        self._logged: int | None = None

    def on_step(self, step: int, loss: float, psnr: float, rays_per_s: float) -> None:
        # train() reports the last read-out's loss at every step: a new value is a read-out, at this step
        # (a final row stamped with the current step held a read-out steps older)
        if math.isfinite(loss) and (self._last is None or (loss, psnr) != self._last[1:3]):
            self._last = (step, loss, psnr, rays_per_s)
        self._rate = rays_per_s
        if step % self.every:
            return
        self._logged = step
        seconds = self.cfg.rays * step / rays_per_s if rays_per_s > 0 else 0.0
        progress = None if self.budget is None else max(step / self.cfg.steps, seconds / self.budget)
        lr = self._lr(self.cfg, self.cfg.lr, step, progress)
        self.csv.writerow([step, f"{loss:.6g}", f"{psnr:.4f}", f"{rays_per_s:.1f}", f"{lr:.6g}", f"{seconds:.2f}"])
        self.file.flush()
        if self.tb is not None:
            for name, value in zip(COLUMNS[1:], (loss, psnr, rays_per_s, lr, seconds)):
                self.tb.add_scalar(f"train/{name}", value, step)

    def end(self, final: tuple[int, float, float] | None = None) -> None:
        """A finished (or stopped, with its checkpoint) run's last read-out as a row too, when
        ``every`` did not land on it (a run shorter than ``--log-every`` would otherwise leave
        the header alone): ``final`` (step, loss, PSNR: a finished run's own last step, which its
        last checkpoint read), else the last step whose loss was read, a few steps before."""
        last = self._last
        if final is not None and math.isfinite(final[1]):
            last = (*final, self._rate)
        if last is not None and self._logged != last[0]:
            every, self.every = self.every, 1
            try:
                self.on_step(*last)
            finally:
                self.every = every

    def close(self) -> None:
        self.file.close()
        if self.tb is not None:
            self.tb.close()

    def take_back(self) -> None:
        """Put the records back as they were before this run (after :meth:`close`): for a run
        that failed before its first checkpoint, whose records would describe a run the model
        file does not hold.  TensorBoard's events of this run go too."""
        for path, data in self._before.items():
            if data is None:
                path.unlink(missing_ok=True)
            else:
                atomic_write_bytes(path, data)
        tb = self.paths["tensorboard"]
        if self._tb_before is None:
            shutil.rmtree(tb, ignore_errors=True)
        elif tb.is_dir():
            for path in sorted(set(tb.rglob("*")) - self._tb_before, reverse=True):  # a new folder's files first
                (shutil.rmtree if path.is_dir() else Path.unlink)(path)
