"""One episode of a trained ring policy under noisy measurements, raw and behind the Kalman filter: what the CAV
reads of its leader's speed and gap against the truth (the filtered run's), and the acceleration it commands.

    python benchmarks/ring_filter_trace.py --checkpoint outputs/results/ring_v2v_seed0 --profile random_steps \\
        --noise 1.0 0.3 --tau 1.0 --seconds 40 100 --out docs/img/ring_sensor_filter.png

The same episode (evaluation seed, episode 0) and the same noise draws three times: exact measurements, noisy
ones (``eval.sensor_noise_*``) and noisy ones filtered (``eval.sensor_filter=true``), all behind the run's
deployed chain (its safety layer included), as ``mt-eval`` runs them.
"""

from __future__ import annotations

import argparse

import torch
from omegaconf import open_dict
from torchrl.envs.utils import ExplorationType, set_exploration_type


def run(run_cfg, factory, profile: str, *, seed: int, noise=None, filtered: bool = False):
    from mixed_traffic.evaluation.harness import episode_seeds, eval_env_overrides, seed_episodes
    from mixed_traffic.training.builders import TRAINING_ONLY, make_transformed_env

    cfg = run_cfg.copy()
    with open_dict(cfg):
        cfg.eval.seed = seed
        if noise is not None:
            cfg.eval.sensor_noise_gap, cfg.eval.sensor_noise_speed, cfg.eval.sensor_noise_tau = noise
        cfg.eval.sensor_filter = filtered
    env = make_transformed_env(cfg, num_envs=1, seed=seed, without=TRAINING_ONLY, deploy=True,
                               **eval_env_overrides(cfg, profile))
    seed_episodes(env, episode_seeds(seed, 1))
    policy = factory(env)
    torch.manual_seed(seed)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        td = env.rollout(env.base_env.scenario.max_steps, policy, break_when_any_done=False)["next"]
    return td


def main(argv=None):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mixed_traffic.evaluation.policies import checkpoint_config, policy_factory_from_state

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", required=True)
    p.add_argument("--profile", default="random_steps")
    p.add_argument("--noise", type=float, nargs=2, default=(1.0, 0.3), metavar=("GAP", "SPEED"))
    p.add_argument("--tau", type=float, default=1.0)
    p.add_argument("--seed", type=int, default=1000, help="evaluation seed (episode 0 is drawn from it)")
    p.add_argument("--seconds", type=float, nargs=2, default=(40.0, 100.0), metavar=("FROM", "TO"))
    p.add_argument("--out", required=True)
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    run_cfg, state = checkpoint_config(a.checkpoint)
    factory = policy_factory_from_state(run_cfg, state)
    noise = (a.noise[0], a.noise[1], a.tau)
    exact = run(run_cfg, factory, a.profile, seed=a.seed)
    raw = run(run_cfg, factory, a.profile, seed=a.seed, noise=noise)
    kf = run(run_cfg, factory, a.profile, seed=a.seed, noise=noise, filtered=True)

    t = exact["traffic", "time"][0, :, 0]
    w = (t >= a.seconds[0]) & (t <= a.seconds[1])
    first = lambda x: x[0, :, 0][w]  # noqa: E731

    def truth(td, k):
        return first(td["cav", k] - td["sensor_filter", k])

    fig, ax = plt.subplots(3, 1, figsize=(10, 8), sharex=True)
    tw = t[w]
    measured = lambda k: truth(kf, k) + first(kf["sensor_noise", k])  # noqa: E731  (the filtered run's sensor)
    ax[0].plot(tw, measured("leader_speed"), lw=0.6, color="0.6", label="measured")
    ax[0].plot(tw, first(kf["cav", "leader_speed"]), lw=1.2, label="filtered")
    ax[0].plot(tw, truth(kf, "leader_speed"), lw=1.0, ls="--", color="k", label="true")
    ax[0].set_ylabel("leader speed (m/s)")
    ax[1].plot(tw, measured("gap"), lw=0.6, color="0.6", label="measured")
    ax[1].plot(tw, first(kf["cav", "gap"]), lw=1.2, label="filtered")
    ax[1].plot(tw, truth(kf, "gap"), lw=1.0, ls="--", color="k", label="true")
    ax[1].set_ylabel("gap (m)")
    for td, label, style in ((raw, "noisy, raw", dict(lw=0.6, color="0.6")), (kf, "noisy, filtered", dict(lw=1.2)),
                             (exact, "exact", dict(lw=1.0, ls="--", color="k"))):
        ax[2].plot(tw, first(td["cav", "accel"]), label=label, **style)
    ax[2].set_ylabel("CAV acceleration (m/s²)")
    ax[2].set_xlabel("time (s)")
    for x in ax:
        x.legend(loc="upper right", fontsize=8)
    dt = float(t[1] - t[0])
    jerks = {name: float((td["cav", "accel"][0, 1:, 0] - td["cav", "accel"][0, :-1, 0]).abs().mean() / dt)
             for name, td in (("exact", exact), ("raw", raw), ("filtered", kf))}
    fig.suptitle(f"{a.profile}, episode 0 (seed {a.seed}); noise {a.noise[0]:g} m / {a.noise[1]:g} m/s over "
                 f"{a.tau:g} s\nthe episode's mean |jerk|: " + ", ".join(f"{k} {v:.2f}" for k, v in jerks.items())
                 + " m/s³", fontsize=10)
    fig.tight_layout()
    fig.savefig(a.out, dpi=90)
    print(a.out, jerks)
    return jerks


if __name__ == "__main__":
    main()
