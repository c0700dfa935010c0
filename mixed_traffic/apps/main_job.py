"""``mt-main`` (``make run``): train Lagrangian PPO on the ring, evaluate it, write the report.

    mt-main                       # experiment=ring_lagrangian_ppo_fast_band (DEFAULT_EXPERIMENT), seed 0
    mt-main seed=1                # any Hydra override works as for mt-train
    MT_SMALL_BUDGET=1 mt-main     # a quick pass through the whole pipeline (minutes -> seconds)

Prints where the run directory, the report and the plots are.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig, open_dict

from mixed_traffic.config import CONFIG_NAME, CONFIG_PATH, register_configs
from mixed_traffic.validation import guarded, run_cli

register_configs()
DEFAULT_EXPERIMENT = "ring_lagrangian_ppo_fast_band"  # docs/results.md, "One band law above 18 m/s"


def small_budget() -> bool:
    return os.environ.get("MT_SMALL_BUDGET", "0") not in ("", "0", "false", "False")


def apply_small_budget(cfg: DictConfig) -> None:
    """Shrink training and evaluation so the pipeline runs end to end in well under a minute."""
    with open_dict(cfg):
        cfg.trainer.total_frames = min(int(cfg.trainer.total_frames), 4 * cfg.trainer.num_envs * cfg.trainer.rollout_len)
        cfg.eval.episodes = min(int(cfg.eval.episodes), 2)
        cfg.eval.episode_seconds = 60.0
        cfg.eval.warmup_seconds = 10.0
        if cfg.policy.get("apg") is not None and cfg.policy.apg.iterations:
            cfg.policy.apg.iterations = min(int(cfg.policy.apg.iterations), 3)
            cfg.policy.apg.num_envs = min(int(cfg.policy.apg.num_envs), 8)
            cfg.policy.apg.horizon = min(int(cfg.policy.apg.horizon), 10)
            if cfg.policy.apg.get("average_last"):
                cfg.policy.apg.average_last = min(int(cfg.policy.apg.average_last), cfg.policy.apg.iterations)


def run_main(cfg: DictConfig) -> dict:
    from mixed_traffic.evaluation import evaluate_and_report
    from mixed_traffic.training import train

    if small_budget():
        apply_small_budget(cfg)
    result = train(cfg)
    run_dir = Path(result["out_dir"])
    if result["stopped_early"]:
        print(f"training stopped early; continue with: mt-main resume={run_dir}")
        return {"run_dir": run_dir, "report": None}
    rep = evaluate_and_report(cfg, run_dir / "eval", checkpoint=run_dir / "final.pt", title=f"{cfg.name} seed {cfg.seed}")
    s = result["summary"]
    acc = rep["acceptance"]
    print("")
    apg = s.get("apg")  # the analytic-gradient phase before the frames, where the experiment has one
    first = (f"{apg['iterations']} analytic-gradient steps in {apg['seconds']:.0f} s ({apg['seconds'] / apg['iterations']:.2f} s "
             "a step; mt-bench apg times one), then " if apg else "")
    print(f"trained {cfg.name} (seed {cfg.seed}): {first}{s['frames']} frames in {s['wall_seconds']:.0f} s")
    print(f"run directory : {run_dir}")
    print(f"final policy  : {run_dir / 'final.pt'}")
    print(f"report        : {rep['paths']['md']}")
    print(f"plots         : {run_dir / 'eval'}/*.png (training_curves.png, one per head profile)")
    print(f"evaluation    : {rep['overall']['collisions']} collisions in {rep['overall']['episodes']} episodes, "
          f"min gap {rep['overall']['min_gap']:.2f} m, max head gap {rep['overall']['max_head_gap']:.2f} m, "
          f"steady-state speed RMSE {acc['steady_speed_rmse']:.3f} m/s")
    if "intervention_rate_max" in acc:
        print(f"safety layer  : intervention rate <= {acc['intervention_rate_max']:.3f} per profile")
    if "no_layer_zero_collisions" in acc:
        nl = sum(r["collisions"] for starts in rep["without_layer"].values() for r in starts.values())
        print(f"without layer : {nl} collisions (standard and close starts), min gap after warm-up "
              f"{acc['no_layer_min_gap_after_warmup']:.2f} m, max head gap {acc['no_layer_max_head_gap']:.2f} m")
    ref = rep.get("reference")
    if ref:
        from mixed_traffic.evaluation import policy_rows

        rows = policy_rows(ref["profiles"])
        jerk, ret = [r["jerk_pct"] for r in rows], [r["return_diff"] for r in rows]
        print(f"against {ref['controller']}: jerk {min(jerk):+.2f}..{max(jerk):+.2f} % of its (at most its: "
              f"{acc['jerk_within_reference']}), return {min(ret):+.1f}..{max(ret):+.1f} (at least its: "
              f"{acc['return_within_reference']}); every profile, with and without the layer")
    print(f"acceptance    : pass={acc['pass']}")
    return {"run_dir": run_dir, "report": rep, "summary": s}


@hydra.main(config_path=CONFIG_PATH, config_name=CONFIG_NAME, version_base="1.3")
def _hydra_main(cfg: DictConfig) -> None:
    guarded(lambda: run_main(cfg), "mt-main")


def main(argv: list[str] | DictConfig | None = None):
    """Console entry point: bad input gives ``error: <field>: ...`` and exit status 2 (``MT_DEBUG=1``: traceback).

    Given a composed config instead of an argv (as a ``@hydra.main`` function), runs it directly.
    """
    if isinstance(argv, DictConfig):
        return run_main(argv)
    argv = with_default_experiment(sys.argv[1:] if argv is None else argv)
    run_cli(_hydra_main, "mt-main", argv)


def with_default_experiment(overrides) -> list[str]:
    """``overrides`` with ``experiment=DEFAULT_EXPERIMENT`` first unless they name an experiment (``mt-main``'s rule)."""
    overrides = list(overrides)
    if not any(o.startswith(("experiment=", "+experiment=")) for o in overrides):
        overrides.insert(0, f"experiment={DEFAULT_EXPERIMENT}")
    return overrides


if __name__ == "__main__":
    main()
