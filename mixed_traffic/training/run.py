"""Per-run bookkeeping shared by the training loops: directory, TorchRL logger, progress bar, checkpoints."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf
from tqdm.auto import tqdm

from mixed_traffic.training.checkpoint import LATEST, atomic_save, atomic_write_text


def make_logger(cfg: DictConfig, out_dir: Path):
    """TorchRL logger from ``cfg.logger``: CSVLogger (default), WandbLogger (offline), or None."""
    lc = cfg.logger
    log_dir = out_dir / lc.log_dir
    if lc.backend == "csv":
        from torchrl.record.loggers import CSVLogger

        return CSVLogger(exp_name=cfg.name, log_dir=str(log_dir))
    if lc.backend == "wandb":
        import uuid

        from torchrl.record.loggers import WandbLogger

        log_dir.mkdir(parents=True, exist_ok=True)
        # one wandb run per training run: the id is kept in the run directory, so a resume continues it
        id_file = log_dir / "wandb_run_id"
        run_id = id_file.read_text().strip() if id_file.is_file() else uuid.uuid4().hex[:12]
        id_file.write_text(run_id)
        # log_env_packages=False: TorchRL would otherwise replace the run config's `env` with package metadata
        return WandbLogger(exp_name=f"{cfg.name}_seed{cfg.seed}", offline=lc.mode == "offline", save_dir=str(log_dir),
                           project=lc.project, id=run_id, log_env_packages=False,
                           config=OmegaConf.to_container(cfg, resolve=True))
    if lc.backend == "none":
        return None
    raise ValueError(f"logger.backend={lc.backend!r} is invalid; allowed: 'csv', 'wandb', 'none'")


def scalar_dir(out_dir: str | Path, cfg: DictConfig | None = None) -> Path | None:
    """Where the CSV logger of a run wrote its scalars (``<run>/logs/<name>/scalars``)."""
    hits = sorted(Path(out_dir).glob("logs/*/scalars"))
    return hits[0] if hits else None


def trim_scalars(out_dir: str | Path, max_step: int) -> int:
    """Drop CSV scalar rows logged after step ``max_step`` (a resume logs those steps again).

    Each ``<run>/logs/<name>/scalars/<key>.csv`` holds ``step,value`` lines; the file is
    rewritten atomically. Returns the number of rows removed.
    """
    removed = 0
    for f in Path(out_dir).glob("logs/*/scalars/*.csv"):
        lines = f.read_text().splitlines(keepends=True)
        keep = [ln for ln in lines if not ln.strip() or float(ln.split(",", 1)[0]) <= max_step]
        if len(keep) != len(lines):
            removed += len(lines) - len(keep)
            tmp = f.with_name(f".{f.name}.tmp")
            tmp.write_text("".join(keep))
            tmp.replace(f)
    return removed


@dataclass
class Run:
    """Directory layout of one training run."""

    cfg: DictConfig
    out_dir: Path
    total_iters: int
    frames_per_batch: int
    logger: object = None
    bar: object = None
    t0: float = field(default_factory=time.perf_counter)
    elapsed_before: float = 0.0  # wall-clock of the interrupted part(s) of a resumed run

    @classmethod
    def start(cls, cfg: DictConfig, out_dir: str | Path, total_iters: int, frames_per_batch: int) -> Run:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        run = cls(cfg=cfg, out_dir=out, total_iters=total_iters, frames_per_batch=frames_per_batch)
        run.logger = make_logger(cfg, out)
        if not (cfg.get("resume") and (out / "config.yaml").exists()):  # a resume keeps the run's own config
            atomic_write_text(out / "config.yaml", OmegaConf.to_yaml(cfg, resolve=True))
        return run

    @property
    def ckpt_dir(self) -> Path:
        return self.out_dir / "checkpoints"

    def wall(self) -> float:
        return self.elapsed_before + time.perf_counter() - self.t0

    def open_bar(self, start_iter: int) -> None:
        if self.cfg.trainer.progress:
            self.bar = tqdm(total=self.total_iters * self.frames_per_batch, initial=start_iter * self.frames_per_batch,
                            unit="frames", unit_scale=True, dynamic_ncols=True, desc=self.cfg.name)

    def log(self, metrics: dict, frames: int, bar_fields: dict | None = None) -> None:
        if self.logger is not None:
            for k, v in metrics.items():
                if v is not None:
                    self.logger.log_scalar(k, float(v), step=frames)
        if self.bar is not None:
            self.bar.n = frames
            if bar_fields:
                self.bar.set_postfix({k: (f"{v:.3g}" if isinstance(v, float) else v) for k, v in bar_fields.items()},
                                     refresh=False)
            self.bar.refresh()

    def save_checkpoint(self, payload: dict, iteration: int) -> Path:
        payload = dict(payload, wall_seconds=self.wall(), iteration=iteration,
                       config=OmegaConf.to_container(self.cfg, resolve=True))
        return atomic_save(payload, self.ckpt_dir / LATEST)

    def end_iteration(self, done_iters: int, start_iter: int, payload) -> bool:
        """Periodic checkpoint after iteration ``done_iters``; True when the run must stop early.

        ``payload()`` builds the checkpoint. A run stops early (after checkpointing, so
        ``resume=`` continues it) when ``trainer.max_iterations`` iterations were done in
        this process or ``trainer.max_minutes`` of wall-clock have passed.
        """
        tc = self.cfg.trainer
        unfinished = done_iters < self.total_iters
        if tc.checkpoint_every and done_iters % tc.checkpoint_every == 0 and unfinished:
            self.save_checkpoint(payload(), done_iters)
        out_of_budget = (tc.max_iterations is not None and done_iters - start_iter >= tc.max_iterations) or (
            tc.max_minutes is not None and self.wall() > 60.0 * tc.max_minutes)
        if out_of_budget and unfinished:
            self.save_checkpoint(payload(), done_iters)
            return True
        return False

    def save_final(self, payload: dict, summary: dict) -> Path:
        path = atomic_save(dict(payload, config=OmegaConf.to_container(self.cfg, resolve=True)),
                           self.out_dir / "final.pt")
        atomic_write_text(self.out_dir / "summary.json", json.dumps(summary, indent=2))
        return path

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
        if self.logger is not None and hasattr(self.logger, "experiment"):
            exp = self.logger.experiment
            if hasattr(exp, "finish"):
                exp.finish()


def set_threads(n: int) -> None:
    if n and n > 0:
        torch.set_num_threads(int(n))
