"""Evaluation harness: deterministic episodes over head profiles, report.json/.md and plots.

>>> from mixed_traffic.config import compose
>>> from mixed_traffic.evaluation import evaluate_and_report
>>> cfg = compose(["experiment=ring_lagrangian_ppo", "controller=idm", "eval.episodes=2"])  # doctest: +SKIP
>>> paths = evaluate_and_report(cfg, out_dir="outputs/eval_idm")  # doctest: +SKIP
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from mixed_traffic.evaluation.harness import METRICS, episode_metrics, evaluate
from mixed_traffic.evaluation.policies import checkpoint_config, classic_factory, policy_factory_from_state
from mixed_traffic.evaluation.report import plot_training_curves, read_scalars, write_report


def evaluate_and_report(cfg: DictConfig, out_dir: str | Path, *, checkpoint: str | Path | None = None,
                        controller: str | None = None, title: str | None = None) -> dict:
    """Evaluate a checkpoint (its own env/transform config, with ``cfg.eval``) or a classical controller.

    Returns the report dict with ``paths`` (report.json, report.md, plots).
    """
    checkpoint = checkpoint if checkpoint is not None else cfg.get("checkpoint")
    controller = controller if controller is not None else cfg.get("controller")
    if (checkpoint is None) == (controller is None):
        raise ValueError("evaluate: give exactly one of checkpoint=PATH or controller=idm|ovm")
    run_dir = None
    if checkpoint is not None:
        run_cfg, state = checkpoint_config(checkpoint)
        run_cfg.eval = cfg.eval  # evaluation settings come from the caller
        factory = policy_factory_from_state(run_cfg, state)
        label = str(checkpoint)
        p = Path(checkpoint)
        run_dir = p if p.is_dir() else (p.parent.parent if p.parent.name == "checkpoints" else p.parent)
        eval_cfg = run_cfg
    else:
        factory = classic_factory(controller)
        label = f"{controller}-as-CAV"
        eval_cfg = cfg
    if cfg.env.backend == "sumo":  # the caller's choice: a checkpoint's own config says torch
        from mixed_traffic.evaluation.sumo import evaluate_on_sumo

        report, traces = evaluate_on_sumo(eval_cfg, policy_factory=factory)
    else:
        report, traces = evaluate(eval_cfg, policy_factory=factory)
    report["policy"] = label
    report["env"] = OmegaConf.to_container(eval_cfg.env, resolve=True)
    report["transforms"] = list(eval_cfg.transforms.chain)
    paths = write_report(report, out_dir, traces, title=title or label, plot_episode=cfg.eval.plot_episode,
                         s_min=cfg.eval.s_min, s_max=cfg.eval.s_max, run_dir=run_dir)
    report["paths"] = {k: str(v) for k, v in paths.items()}
    return report


__all__ = ["evaluate", "evaluate_and_report", "episode_metrics", "write_report", "plot_training_curves",
           "read_scalars", "METRICS"]
