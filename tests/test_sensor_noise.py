"""Measurement noise (transforms.SensorNoise and eval.sensor_noise_*): what the CAV measures, what it leaves alone."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import check_env_specs

from mixed_traffic import make_env
from mixed_traffic.config import compose
from mixed_traffic.controllers.classic import make_classic_policy
from mixed_traffic.evaluation import evaluate
from mixed_traffic.training.builders import make_transformed_env
from mixed_traffic.validation import ConfigError, validate_config
from transforms import SensorNoise

RING = dict(observation="relative", profile="sine", profile_kwargs={"v_star": 12.5, "amplitude": 5.0, "period": 10.0})


def _noisy_and_true(noise: SensorNoise, steps: int = 200, batch: int = 4):
    act = lambda td: td.set("action", torch.zeros(batch, 1))  # noqa: E731
    got = TransformedEnv(make_env("ring", batch_size=batch, seed=0, **RING), noise).rollout(steps, act)
    true = make_env("ring", batch_size=batch, seed=0, **RING).rollout(steps, act)
    return got, true


def test_specs_hold():
    check_env_specs(TransformedEnv(make_env("ring", batch_size=2, seed=0, **RING), SensorNoise(0.5, 0.2, seed=1)))


def test_measurements_carry_noise_of_the_set_size_and_the_simulation_none():
    got, true = _noisy_and_true(SensorNoise(0.8, 0.3, seed=0))
    for key in (("traffic", "gap"), ("traffic", "speed"), ("traffic", "pos"), "reward", "collision"):
        assert torch.equal(got["next", key], true["next", key]), key  # the physics and the reward: the true state
    for key, std in ((("cav", "gap"), 0.8), (("cav", "head_gap"), 0.8), (("cav", "speed"), 0.3),
                     (("cav", "leader_speed"), 0.3), (("cav", "head_speed"), 0.3)):
        err = (got["next", key] - true["next", key]).flatten()
        assert abs(float(err.mean())) < 0.1 * std and abs(float(err.std()) / std - 1.0) < 0.1, key


def test_the_observation_moves_with_the_noisy_measurements():
    got, true = _noisy_and_true(SensorNoise(1.0, 0.5, seed=2), steps=30)
    n = {k: got["next", "cav", k] - true["next", "cav", k] for k in ("gap", "head_gap", "speed", "leader_speed", "head_speed")}
    shift = (got["next", "observation"] - true["next", "observation"])
    s_max = make_env("ring", batch_size=1, seed=0, **RING).scenario.s_max
    expected = torch.cat([n["speed"] / 30, (n["leader_speed"] - n["speed"]) / 10, n["gap"] / s_max,
                          n["head_gap"] / (2 * s_max), (n["head_speed"] - n["speed"]) / 10, -n["speed"] / 10,
                          torch.zeros_like(n["gap"])], -1)
    torch.testing.assert_close(shift, expected, atol=1e-5, rtol=0)


def test_correlated_errors_keep_their_size_and_drift_over_tau():
    white, true = _noisy_and_true(SensorNoise(1.0, 0.0, seed=3), steps=400, batch=8)
    slow, _ = _noisy_and_true(SensorNoise(1.0, 0.0, seed=3, tau=2.0, dt=0.1), steps=400, batch=8)
    for got, lag1 in ((white, 0.0), (slow, 0.951)):  # exp(-0.1 / 2)
        e = got["next", "cav", "gap"][..., 0] - true["next", "cav", "gap"][..., 0]
        assert abs(float(e.std()) - 1.0) < 0.15  # stationary from the reset on
        r = float(torch.corrcoef(torch.stack([e[:, 1:].flatten(), e[:, :-1].flatten()]))[0, 1])
        assert abs(r - lag1) < 0.06, (r, lag1)
        torch.testing.assert_close(got["next", "sensor_noise", "gap"], got["next", "cav", "gap"] - true["next", "cav", "gap"],
                                   atol=1e-4, rtol=0)  # the error the transform carries is the one it added


def test_the_same_seed_draws_the_same_noise():
    a, _ = _noisy_and_true(SensorNoise(0.5, 0.2, seed=7), steps=20)
    b, _ = _noisy_and_true(SensorNoise(0.5, 0.2, seed=7), steps=20)
    c, _ = _noisy_and_true(SensorNoise(0.5, 0.2, seed=8), steps=20)
    assert torch.equal(a["next", "cav", "gap"], b["next", "cav", "gap"])
    assert not torch.equal(a["next", "cav", "gap"], c["next", "cav", "gap"])


@pytest.mark.parametrize("kwargs, match", [
    ({"gap_std": -0.1}, r"gap_std=-0.1 is invalid; allowed: >= 0"),
    ({"speed_std": float("nan")}, r"speed_std=nan is invalid; allowed: >= 0"),
    ({"observation": "seed"}, r"observation='seed' is not supported; allowed: \['relative'"),
    ({"tau": -1.0}, r"tau=-1.0 is invalid; allowed: >= 0 \(s\)"),
])
def test_bad_noise_settings_name_the_argument(kwargs, match):
    with pytest.raises(ValueError, match=match):
        SensorNoise(**kwargs)


def test_noise_settings_are_checked_at_start_up():
    with pytest.raises(ConfigError, match=r"eval.sensor_noise_gap: -1.0 is out of range; allowed: a number in \[0, 10\]"):
        validate_config(compose(["experiment=ring_lagrangian_ppo", "eval.sensor_noise_gap=-1.0"]))
    with pytest.raises(ConfigError, match=r"eval.sensor_noise_speed: 6.0 is out of range; allowed: a number in \[0, 5\]"):
        validate_config(compose(["experiment=ring_lagrangian_ppo", "eval.sensor_noise_speed=6.0"]))
    with pytest.raises(ConfigError, match=r"eval.sensor_noise_tau: -2.0 is out of range; allowed: a number in \[0, 60\]"):
        validate_config(compose(["experiment=ring_lagrangian_ppo", "eval.sensor_noise_tau=-2.0"]))


def test_only_the_evaluated_chain_measures_with_noise():
    cfg = compose(["experiment=ring_lagrangian_ppo", "eval.sensor_noise_gap=0.5", "eval.sensor_noise_speed=0.1",
                   "eval.sensor_noise_tau=1.0"])
    deployed = make_transformed_env(cfg, num_envs=1, seed=0, deploy=True)
    noise = deployed.transform[0]
    assert isinstance(noise, SensorNoise) and (noise.gap_std, noise.speed_std, noise.tau) == (0.5, 0.1, 1.0)
    trained = make_transformed_env(cfg, num_envs=1, seed=0)
    assert not any(isinstance(t, SensorNoise) for t in trained.transform)
    exact = make_transformed_env(compose(["experiment=ring_lagrangian_ppo"]), num_envs=1, seed=0, deploy=True)
    assert not any(isinstance(t, SensorNoise) for t in exact.transform)


def test_the_evaluation_measures_the_true_state_not_the_noisy_one():
    """A controller that reads nothing drives the same episodes with and without noise: every metric the same."""
    from tensordict.nn import TensorDictModule

    short = ["experiment=ring_lagrangian_ppo", "transforms=reward", "eval.episodes=2", "eval.episode_seconds=30.0",
             "eval.warmup_seconds=5.0", "eval.profiles=[sine]"]

    def blind(env):
        return TensorDictModule(lambda gap: torch.zeros_like(gap), in_keys=[("cav", "gap")], out_keys=["action"])

    exact = evaluate(compose(short), policy_factory=blind)[0]["profiles"]["sine"]["per_episode"]
    noisy = evaluate(compose([*short, "eval.sensor_noise_gap=2.0", "eval.sensor_noise_speed=0.5"]),
                     policy_factory=blind)[0]["profiles"]["sine"]["per_episode"]
    for key in ("min_gap", "max_head_gap", "speed_rmse_steady", "speed_rmse", "mean_abs_jerk", "return"):
        assert noisy[key] == pytest.approx(exact[key], abs=1e-3), key


def test_the_noise_reaches_every_controller_and_the_report_names_it(tmp_path):
    from mixed_traffic.evaluation import evaluate_and_report

    short = ["experiment=ring_lagrangian_ppo", "transforms=reward", "eval.episodes=2", "eval.episode_seconds=30.0",
             "eval.warmup_seconds=5.0", "eval.profiles=[sine]"]

    def jerk(*noise):
        rep, _ = evaluate(compose([*short, *noise]), policy_factory=lambda env: make_classic_policy("idm", env))
        return rep["profiles"]["sine"]["metrics"]["mean_abs_jerk"]["mean"]

    assert jerk("eval.sensor_noise_speed=0.2") > jerk()  # IDM reacts to what it measures
    rep = evaluate_and_report(compose([*short, "controller=idm", "eval.episodes=1", "eval.sensor_noise_gap=0.3"]), tmp_path)
    assert rep["sensor_noise"] == {"gap": 0.3, "speed": 0.0, "tau": 0.0, "margin": 0.0, "filter": False}
    assert "every gap the CAV measures with a standard deviation of 0.3 m" in Path(rep["paths"]["md"]).read_text()


def test_the_layer_with_margins_acts_on_the_worst_state_within_them():
    from transforms.safety_layer import safe_action

    g = torch.linspace(4.0, 30.0, 27)[:, None]
    v, vl = torch.full_like(g, 20.0), torch.linspace(10.0, 25.0, 27)[:, None]
    kw = dict(action=torch.full_like(g, 3.0), head_gap=None, head_speed=None, low=-3.0, high=3.0, dt=0.1,
              s_min=5.0, s_max=None, leader_brake=3.0)
    worst = safe_action(gap=g - 2.0, speed=v + 0.5, leader_speed=vl - 0.5, **kw)
    margined = safe_action(gap=g, speed=v, leader_speed=vl, gap_margin=2.0, speed_margin=0.5, **kw)
    torch.testing.assert_close(margined, worst)
    assert bool((margined < safe_action(gap=g, speed=v, leader_speed=vl, **kw) - 1e-3).any())  # and it is stricter


def test_the_envelope_with_margins_bounds_the_worst_state_within_them():
    from mixed_traffic.controllers.classic import make_classic_policy, stopping_envelope_policy

    env = make_env("ring", batch_size=1, seed=0)
    plain = stopping_envelope_policy(make_classic_policy("idm", env), env, stop_gap=5.0).module
    margined = stopping_envelope_policy(make_classic_policy("idm", env), env, stop_gap=5.0, gap_margin=1.5,
                                        speed_margin=0.4).module
    g, v, vl = torch.linspace(6.0, 40.0, 18), torch.full((18,), 22.0), torch.linspace(15.0, 25.0, 18)
    torch.testing.assert_close(margined.bound(g, v, vl), plain.bound(g - 1.5, v + 0.4, vl - 0.4))
    torch.testing.assert_close(margined.slack(g, v, vl), plain.slack(g - 1.5, v + 0.4, vl - 0.4))


def test_the_noise_margin_widens_only_the_deployed_layer_and_envelope():
    from transforms import ResidualAction, SafetyLayer

    cfg = compose(["experiment=ring_lagrangian_ppo_v2v", "eval.sensor_noise_gap=1.0", "eval.sensor_noise_speed=0.3",
                   "eval.sensor_noise_margin=2.0", "transforms.safety_layer.gap_margin=0.5"])

    def margins(env):
        layer = next(t for t in env.transform if isinstance(t, SafetyLayer))
        base = next(t for t in env.transform if isinstance(t, ResidualAction)).base.module
        envelope = next(m for m in base.modules() if hasattr(m, "gap_margin"))
        return (layer.gap_margin, layer.speed_margin), (envelope.gap_margin, envelope.speed_margin)

    layer, envelope = margins(make_transformed_env(cfg, num_envs=1, seed=0, deploy=True))
    assert layer == pytest.approx((2.5, 0.6)) and envelope == pytest.approx((2.0, 0.6))  # added to its own 0.5 m
    assert margins(make_transformed_env(cfg, num_envs=1, seed=0)) == ((0.5, 0.0), (0.0, 0.0))  # training: as configured


def test_bad_margins_name_the_argument():
    from transforms import SafetyLayer

    with pytest.raises(ValueError, match=r"SafetyLayer: gap_margin=-1.0 is invalid; allowed: >= 0 \(m\)"):
        SafetyLayer(gap_margin=-1.0)
    with pytest.raises(ConfigError, match=r"eval.sensor_noise_margin: -1.0 is out of range"):
        validate_config(compose(["experiment=ring_lagrangian_ppo", "eval.sensor_noise_margin=-1.0"]))
