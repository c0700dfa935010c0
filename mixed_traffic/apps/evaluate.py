"""``mt-eval``: evaluate a checkpoint or a classical controller; writes report.json/.md and plots.

    mt-eval checkpoint=outputs/runs/ring_lagrangian_ppo/<run>          # final.pt of a run
    mt-eval checkpoint=<run>/checkpoints/latest.pt eval.episodes=5
    mt-eval experiment=ring_lagrangian_ppo transforms=reward controller=idm
"""

from __future__ import annotations

from pathlib import Path

import hydra
from omegaconf import DictConfig

from mixed_traffic.config import CONFIG_NAME, CONFIG_PATH, register_configs

register_configs()


@hydra.main(config_path=CONFIG_PATH, config_name=CONFIG_NAME, version_base="1.3")
def main(cfg: DictConfig) -> None:
    from mixed_traffic.evaluation import evaluate_and_report
    from mixed_traffic.training.run import set_threads

    set_threads(cfg.threads)
    out = Path(cfg.out_dir) / "eval"
    rep = evaluate_and_report(cfg, out)
    acc = rep["acceptance"]
    print(f"report: {rep['paths']['md']}")
    print(f"        {rep['paths']['json']}")
    print(f"collisions {rep['overall']['collisions']}/{rep['overall']['episodes']} episodes, "
          f"min gap {rep['overall']['min_gap']:.2f} m, max head gap {rep['overall']['max_head_gap']:.2f} m, "
          f"steady RMSE {acc['steady_speed_rmse']:.3f} m/s, pass={acc['pass']}")


if __name__ == "__main__":
    main()
