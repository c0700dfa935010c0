"""``mt-eval``: evaluate a checkpoint or a classical controller; writes report.json/.md and plots.

    mt-eval checkpoint=outputs/runs/ring_lagrangian_ppo/<run>          # final.pt of a run
    mt-eval checkpoint=<run>/checkpoints/latest.pt eval.episodes=5
    mt-eval experiment=ring_lagrangian_ppo transforms=reward controller=idm
    mt-eval experiment=ring_lagrangian_ppo_band_stop controller=base     # the experiment's residual base alone
    mt-eval experiment=ring_wave_lppo controller=all                    # wave report: every classical damper
    mt-eval experiment=ring_wave_lppo checkpoint=<run>                  # learned damper vs the classical ones
"""

from __future__ import annotations

from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

from mixed_traffic.config import CONFIG_NAME, CONFIG_PATH, register_configs
from mixed_traffic.validation import ConfigError, guarded, parse_deploy_overrides, run_cli, validate_config

register_configs()


def check_eval_overrides(cfg: DictConfig, overrides: list[str]) -> None:
    """A checkpoint is evaluated on the env it was trained on: refuse ``env.*`` overrides (except the backend)."""
    if not cfg.get("checkpoint"):
        return
    for o in overrides:
        key = o.split("=", 1)[0].lstrip("+~")
        if (key == "env" or key.startswith("env.")) and key != "env.backend":
            raise ConfigError(key, "a checkpoint is evaluated on the env and transforms it was trained with "
                              "(they travel inside it)", "env.backend=torch|sumo and the eval.* settings "
                              "(e.g. eval.hdv_param_noise, eval.episode_seconds, eval.profiles)")


def run_eval(cfg: DictConfig, overrides: list[str] = ()) -> dict:
    from mixed_traffic.evaluation import evaluate_and_report
    from mixed_traffic.training.run import set_threads

    # a checkpoint deploys with its own transforms; transforms.* overrides change them for this evaluation (a
    # deployed variant, named in the report), rather than being silently dropped
    deploy = [o for o in overrides if o.split("=", 1)[0].lstrip("+~").startswith("transforms")]
    # such overrides are checked against the run's own transforms (evaluate_and_report), not against this app's
    # defaults, which may lack what the run has (e.g. the envelope a margin fade needs); the rest is checked here
    checked = OmegaConf.masked_copy(cfg, [k for k in cfg if k != "transforms"]) if cfg.get("checkpoint") and deploy else cfg
    validate_config(checked)
    check_eval_overrides(cfg, list(overrides))
    pairs = parse_deploy_overrides(deploy) if cfg.get("checkpoint") else []
    set_threads(cfg.threads)
    out = Path(cfg.out_dir) / "eval"
    rep = evaluate_and_report(cfg, out, deploy_overrides=pairs)
    if pairs:
        print("deployed with " + " ".join(deploy))
    print(f"report: {rep['paths']['md']}")
    print(f"        {rep['paths']['json']}")
    if "sets" in rep:  # the intersection: one table per test set
        print(rep["paths"]["md"].read_text())
        return rep
    if "rings" in rep:  # the stop-and-go wave report (rings without a head)
        width = max(len(label) for e in rep["rings"].values() for label in e["controllers"])
        for L, e in rep["rings"].items():
            for label, r in e["controllers"].items():
                m = r["metrics"]
                print(f"ring {L} m  {label:<{width}} mean speed {m['mean_speed']['mean']:.2f} m/s, speed std "
                      f"{m['speed_std']['mean']:.2f} m/s, collisions {r['collisions']}")
        return
    acc = rep["acceptance"]
    print(f"collisions {rep['overall']['collisions']}/{rep['overall']['episodes']} episodes, "
          f"min gap {rep['overall']['min_gap']:.2f} m, max head gap {rep['overall']['max_head_gap']:.2f} m, "
          f"steady RMSE {acc['steady_speed_rmse']:.3f} m/s, pass={acc['pass']}")
    return rep


@hydra.main(config_path=CONFIG_PATH, config_name=CONFIG_NAME, version_base="1.3")
def _hydra_main(cfg: DictConfig) -> None:
    from hydra.core.hydra_config import HydraConfig

    guarded(lambda: run_eval(cfg, list(HydraConfig.get().overrides.task)), "mt-eval")


def main(argv: list[str] | DictConfig | None = None):
    """Console entry point: bad input gives ``error: <field>: ...`` and exit status 2 (``MT_DEBUG=1``: traceback).

    Given a composed config instead of an argv (as a ``@hydra.main`` function), runs it directly.
    """
    if isinstance(argv, DictConfig):
        return run_eval(argv)
    run_cli(_hydra_main, "mt-eval", argv)


if __name__ == "__main__":
    main()
