"""``mt-train``: train one configuration (or a sweep with ``-m``).

    mt-train experiment=ring_lagrangian_ppo seed=1
    mt-train experiment=ring_ppo loss=lagrangian_ppo transforms=safe
    mt-train -m experiment=ring_ppo seed=0,1,2 loss=ppo,lagrangian_ppo hydra/launcher=joblib
    mt-train -m experiment=ring_ppo seed=0,1,2 hydra/launcher=ray          # Ray tasks (docs/scaling.md)
    mt-train experiment=ring_ppo env.backend=sumo trainer.num_envs=2 trainer.collector=multi_sync trainer.collector_workers=2
    mt-train experiment=ring_lagrangian_ppo resume=outputs/runs/ring_lagrangian_ppo/<run>
    mt-train experiment=intersection_lppo_bff
    mt-train env=intersection loss=lagrangian_ppo transforms=barrier_force
"""

from __future__ import annotations

import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

from mixed_traffic.config import CONFIG_NAME, CONFIG_PATH, register_configs
from mixed_traffic.validation import guarded, run_cli

register_configs()


@hydra.main(config_path=CONFIG_PATH, config_name=CONFIG_NAME, version_base="1.3")
def _hydra_main(cfg: DictConfig) -> float:
    return guarded(lambda: run_train(cfg), "mt-train")


def main(argv: list[str] | DictConfig | None = None):
    """Console entry point: bad input gives ``error: <field>: ...`` and exit status 2 (``MT_DEBUG=1``: traceback).

    Given a composed config instead of an argv (as a ``@hydra.main`` function), runs it directly.
    """
    if isinstance(argv, DictConfig):
        return run_train(argv)
    run_cli(_hydra_main, "mt-train", argv)


def run_train(cfg: DictConfig) -> float:
    from mixed_traffic.validation import validate_config

    validate_config(cfg)
    if cfg.get("controller"):  # a classical-controller experiment (e.g. intersection_nmpc): nothing to train
        from mixed_traffic.evaluation import evaluate_and_report

        rep = evaluate_and_report(cfg, Path(cfg.out_dir) / "eval")
        print(f"{cfg.name} names controller={cfg.controller}: nothing to train; evaluated it. report: {rep['paths']['md']}")
        return float("nan")
    from mixed_traffic.training import train

    result = train(cfg)
    s = result["summary"]
    if cfg.eval.after_train and not result["stopped_early"]:
        from mixed_traffic.evaluation import evaluate_and_report

        rep = evaluate_and_report(cfg, result["out_dir"] / "eval", checkpoint=result["out_dir"] / "final.pt")
        print(f"report: {rep['paths']['md']}")
    print(f"run directory: {result['out_dir']}")
    if result["stopped_early"]:
        tc = cfg.trainer
        why = (f"trainer.max_minutes={tc.max_minutes}" if tc.max_minutes is not None and
               s["wall_seconds"] > 60 * tc.max_minutes else f"trainer.max_iterations={tc.max_iterations}")
        print(f"\nWARNING: training STOPPED EARLY by {why} at {s['frames']} of {tc.total_frames} frames: "
              f"no final policy yet (no final.pt, no evaluation).\n         continue it with: "
              f"mt-train resume={result['out_dir']}", file=sys.stderr, flush=True)
    else:
        print(f"final policy: {result['out_dir'] / 'final.pt'}  ({s['frames']} frames, {s['wall_seconds']:.0f} s)")
    return float(s["final"].get("reward_per_step", float("nan")))


if __name__ == "__main__":
    main()
