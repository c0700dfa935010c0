"""Hydra callback: a sweep summary (mean ± std over seeds per configuration).

Registered in ``hydra_configs/config.yaml`` (``hydra.callbacks.sweep_summary``). At the end
of a multirun it reads every job's ``summary.json`` (written by the training loops, plus
``report.json`` when the job evaluated its policy) under the sweep directory, groups
the jobs by their overrides without ``seed``, and writes ``sweep_summary.json`` and
``sweep_summary.md`` next to them. It works the same with every launcher, because
jobs only communicate through their files.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

SKIP_KEYS = ("seed", "resume", "resume_override", "trainer.progress")


def _flatten(d: dict, prefix: str = "") -> dict[str, float]:
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flatten(v, key + "."))
        elif isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(float(v)):
            out[key] = float(v)
    return out


def _job_overrides(job_dir: Path) -> list[str]:
    f = job_dir / ".hydra" / "overrides.yaml"
    if not f.is_file():
        return []
    lines = [ln.strip()[2:].strip() for ln in f.read_text().splitlines() if ln.strip().startswith("- ")]
    return [o.strip("'\"") for o in lines]


def summarize_sweep(sweep_dir: str | Path) -> dict:
    """Group the jobs of ``sweep_dir`` by configuration (overrides without seed); mean and std per metric."""
    sweep_dir = Path(sweep_dir)
    groups: dict[str, dict[str, Any]] = {}
    for summ in sorted(sweep_dir.glob("**/summary.json")):
        job_dir = summ.parent
        hydra_dir = job_dir
        while not (hydra_dir / ".hydra").is_dir() and hydra_dir != sweep_dir:
            hydra_dir = hydra_dir.parent
        overrides = [o for o in _job_overrides(hydra_dir) if o.split("=")[0].lstrip("+~") not in SKIP_KEYS]
        key = " ".join(sorted(overrides)) or "(defaults)"
        s = json.loads(summ.read_text())
        metrics = _flatten({"train": {k: s[k] for k in ("frames", "wall_seconds") if k in s} | s.get("final", {})})
        rep = job_dir / "eval" / "report.json"
        if rep.is_file():
            r = json.loads(rep.read_text())
            metrics.update(_flatten({"eval": r.get("overall", {})}))
        g = groups.setdefault(key, {"seeds": [], "runs": []})
        g["seeds"].append(s.get("seed"))
        g["runs"].append(metrics)
    out = {}
    for key, g in groups.items():
        names = sorted(set().union(*[set(r) for r in g["runs"]]))
        stats = {}
        for n in names:
            vals = [r[n] for r in g["runs"] if n in r]
            mean = sum(vals) / len(vals)
            std = math.sqrt(sum((v - mean) ** 2 for v in vals) / len(vals)) if len(vals) > 1 else 0.0
            stats[n] = {"mean": mean, "std": std, "n": len(vals)}
        out[key] = {"seeds": g["seeds"], "metrics": stats}
    return out


FAILED = "job_failed.json"


def failed_jobs(sweep_dir: str | Path) -> list[dict]:
    """The jobs of a sweep that raised: ``{"job": dir, "overrides": [...], "error": "..."}``."""
    return [json.loads(f.read_text()) for f in sorted(Path(sweep_dir).glob(f"**/{FAILED}"))]


def _atomic_write(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.write_text(text)
    os.replace(tmp, path)


def write_sweep_summary(sweep_dir: str | Path, columns: tuple[str, ...] | None = None) -> Path:
    sweep_dir = Path(sweep_dir)
    summary = summarize_sweep(sweep_dir)
    failed = failed_jobs(sweep_dir)
    _atomic_write(sweep_dir / "sweep_summary.json", json.dumps(summary, indent=2))
    _atomic_write(sweep_dir / "sweep_failed.json", json.dumps(failed, indent=2))
    cols = columns or ("train.reward_per_step", "train.episode_return", "train.collisions", "train.lambda",
                       "train.wall_seconds", "eval.collisions", "eval.min_gap", "eval.speed_rmse_steady")
    lines = ["# Sweep summary (mean ± std over seeds)", "", f"sweep: `{sweep_dir}`", "",
             "| configuration | seeds | " + " | ".join(cols) + " |",
             "|---|---|" + "---|" * len(cols)]
    for key, g in summary.items():
        cells = []
        for c in cols:
            st = g["metrics"].get(c)
            cells.append(f"{st['mean']:.4g} ± {st['std']:.2g}" if st else "–")
        lines.append(f"| `{key}` | {g['seeds']} | " + " | ".join(cells) + " |")
    if failed:
        lines += ["", f"## Failed jobs ({len(failed)}, not in the table)", ""]
        lines += [f"- `{' '.join(f['overrides'])}`: {f['error']}" for f in failed]
    md = sweep_dir / "sweep_summary.md"
    _atomic_write(md, "\n".join(lines) + "\n")
    return md


class SweepSummary(Callback):
    """Writes ``sweep_summary.{json,md}`` in the sweep directory after every job and when a multirun ends.

    Hydra does not call ``on_multirun_end`` when a job failed, so the summary is also
    rewritten after each job (``on_job_end``); a failed job is recorded in its directory
    (``job_failed.json``) and listed in ``sweep_failed.json`` and the Markdown summary.
    """

    def on_job_end(self, config: DictConfig, job_return: Any, **kwargs: Any) -> None:
        from hydra.core.utils import JobStatus
        from hydra.types import RunMode

        if config.hydra.mode != RunMode.MULTIRUN:
            return
        sweep_dir = Path(config.hydra.sweep.dir)
        job_dir = Path(config.hydra.runtime.output_dir)
        if job_return.status == JobStatus.FAILED:
            err = job_return._return_value
            job_dir.mkdir(parents=True, exist_ok=True)
            _atomic_write(job_dir / FAILED, json.dumps({
                "job": str(job_dir), "overrides": list(config.hydra.overrides.task),
                "error": str(err) if str(err).startswith("error: ") else f"{type(err).__name__}: {err}"}, indent=2))
        if sweep_dir.is_dir():
            write_sweep_summary(sweep_dir)

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(config.hydra.sweep.dir)
        if not sweep_dir.is_dir():
            return
        md = write_sweep_summary(sweep_dir)
        print(f"sweep summary: {md}")
