"""The Kalman filter of the noisy measurements (transforms.MeasurementFilter and eval.sensor_filter)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from torchrl.envs import Compose, TransformedEnv
from torchrl.envs.utils import check_env_specs

from mixed_traffic import make_env
from mixed_traffic.config import compose
from mixed_traffic.controllers.classic import make_classic_policy
from mixed_traffic.evaluation import evaluate
from mixed_traffic.training.builders import make_transformed_env
from transforms import MeasurementFilter, SensorNoise, V2VChannel
from transforms.measurement_filter import steady_state_gain

RING = dict(observation="relative", profile="random_steps")
KEYS = ("gap", "speed", "leader_speed", "head_gap", "head_speed")


def _filtered_rollout(gap: float, speed: float, *, tau: float = 1.0, steps: int = 2000, batch: int = 8, seed: int = 0,
                      **filter_kwargs):
    """IDM drives the CAV on what the filter estimates from noisy measurements."""
    base = make_env("ring", batch_size=batch, seed=seed, **RING)
    f = MeasurementFilter(gap, speed, tau=tau, s_max=base.scenario.s_max, **filter_kwargs)
    env = TransformedEnv(base, Compose(SensorNoise(gap, speed, seed=seed, s_max=base.scenario.s_max, tau=tau), f))
    with torch.no_grad():
        td = env.rollout(steps, make_classic_policy("idm", env), break_when_any_done=False)
    return f, td


@pytest.mark.parametrize("delay", [0, 4])
def test_specs_hold(delay):
    base = make_env("ring", batch_size=2, seed=0, **RING)
    check_env_specs(TransformedEnv(base, Compose(SensorNoise(0.5, 0.2, seed=1, tau=1.0), V2VChannel(delay_steps=delay),
                                                 MeasurementFilter(0.5, 0.2, tau=1.0, leader_accel_delay=delay))))


def test_the_gain_matches_an_independent_riccati_iteration():
    """scipy's Riccati solution against the plain recursion, run to convergence on a well-conditioned model."""
    rng = np.random.default_rng(0)
    F = np.array([[1.0, 0.1, 0.0], [0.0, 1.0, 0.1], [0.0, 0.0, 0.9]])
    G, Q = rng.normal(size=(3, 2)), np.diag([0.04, 0.01])
    H, R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), np.diag([0.25, 0.09])
    P = np.eye(3)
    for _ in range(20_000):
        prior = F @ P @ F.T + G @ Q @ G.T
        K = prior @ H.T @ np.linalg.inv(H @ prior @ H.T + R)
        P = (np.eye(3) - K @ H) @ prior
    K_got, P_got = steady_state_gain(*(torch.from_numpy(m) for m in (F, G, Q, H, R)))
    np.testing.assert_allclose(K_got.numpy(), K, atol=1e-8)
    np.testing.assert_allclose(P_got.numpy(), P, atol=1e-8)


@pytest.mark.parametrize("gap, speed, tau", [(1.0, 0.3, 1.0), (0.3, 0.1, 1.0), (1.0, 0.3, 0.0)])
def test_the_estimates_are_closer_to_the_truth_than_the_sensors_and_as_close_as_the_filter_says(gap, speed, tau):
    f, td = _filtered_rollout(gap, speed, tau=tau, steps=1000, batch=32)  # rows cost little beside steps
    post = dict(zip(KEYS, f.posterior_std[True]))
    for k in KEYS:
        est = td["next", "sensor_filter", k][:, 300:]  # after the start's transient
        raw = td["next", "sensor_noise", k][:, 300:]
        assert float(est.std()) < 0.65 * float(raw.std()), k
        assert 0.6 * post[k] < float(est.std()) < 1.25 * post[k], (k, float(est.std()), post[k])
        assert abs(float(est.mean())) < 0.5 * post[k], k


def test_the_estimate_error_it_reports_is_the_estimate_less_the_truth():
    f, td = _filtered_rollout(1.0, 0.3, steps=50, batch=2)
    true = make_env("ring", batch_size=2, seed=0, **RING)
    # the same episodes, measured exactly, with the actions the filtered run took
    actions = td["action"]
    state = true.reset()
    for t in range(50):
        state = true.step(state.set("action", actions[:, t]))
        for k in ("gap", "speed", "leader_speed"):
            torch.testing.assert_close(td["next", "cav", k][:, t] - td["next", "sensor_filter", k][:, t],
                                       state["next", "cav", k], atol=1e-4, rtol=0)
        state = state["next"].exclude("reward", "done", "terminated", "truncated")


def test_the_observation_moves_with_the_estimates():
    _, td = _filtered_rollout(1.0, 0.5, steps=30, batch=2)
    obs, cav = td["next", "observation"], td["next", "cav"]
    s_max = make_env("ring", batch_size=1, seed=0, **RING).scenario.s_max
    torch.testing.assert_close(obs[..., 0:1] * 30.0, cav["speed"], atol=1e-4, rtol=0)
    torch.testing.assert_close(obs[..., 2:3] * s_max, cav["gap"], atol=1e-4, rtol=0)
    torch.testing.assert_close(obs[..., 1:2] * 10.0, cav["leader_speed"] - cav["speed"], atol=1e-4, rtol=0)


def test_exact_measurements_pass_through():
    _, td = _filtered_rollout(0.0, 0.0, steps=100, batch=2)
    for k in KEYS:
        assert float(td["next", "sensor_filter", k].abs().max()) < 1e-3, k


def test_the_filter_reads_the_leader_acceleration_as_received():
    """Over a link that loses every message the leader's acceleration must come from the measurements: the
    estimates then track the leader's speed more loosely than with V2V."""
    def leader_error(channel, **kw):
        base = make_env("ring", batch_size=32, seed=0, **RING)  # rows cost little beside steps
        ts = [SensorNoise(1.0, 0.3, seed=0, tau=1.0), *channel, MeasurementFilter(1.0, 0.3, tau=1.0, **kw)]
        env = TransformedEnv(base, Compose(*ts))
        with torch.no_grad():
            td = env.rollout(800, make_classic_policy("idm", env), break_when_any_done=False)
        return float(td["next", "sensor_filter", "leader_speed"][:, 300:].std())

    with_v2v = leader_error([])
    without = leader_error([V2VChannel(loss=1.0)], leader_accel_key=None, leader_accel_std=10.0)
    assert with_v2v < 0.7 * without


def _late_link_errors(**kw) -> tuple[MeasurementFilter, dict[str, float]]:
    """IDM behind noisy sensors and a leader acceleration received 1 s late: each estimate's RMS error."""
    base = make_env("ring", batch_size=8, seed=0, **RING)
    f = MeasurementFilter(1.0, 0.3, tau=1.0, **kw)
    env = TransformedEnv(base, Compose(SensorNoise(1.0, 0.3, seed=0, tau=1.0), V2VChannel(delay_steps=10), f))
    with torch.no_grad():
        td = env.rollout(1500, make_classic_policy("idm", env), break_when_any_done=False)
    return f, {k: float(td["next", "sensor_filter", k][:, 300:].pow(2).mean().sqrt()) for k in KEYS[:3]}


def test_a_late_acceleration_is_read_as_a_late_measurement():
    """Over a 1-s-late link the delayed-link model tracks the leader and the gap closer than a filter that does
    not read the link, and as closely as it says it does."""
    late, err = _late_link_errors(leader_accel_delay=10)
    _, blind = _late_link_errors(leader_accel_key=None, leader_accel_std=10.0)
    assert err["leader_speed"] < 0.85 * blind["leader_speed"] and err["gap"] < 0.85 * blind["gap"], (err, blind)
    for k, post in zip(KEYS[:3], late.posterior_std[True][:3]):
        assert 0.6 * post < err[k] < 1.25 * post, (k, err[k], post)


def test_the_delayed_link_model_reads_the_oldest_acceleration_it_carries():
    """The late message measures the acceleration ``delay`` steps back; the newest moves the leader."""
    f = MeasurementFilter(1.0, 0.3, tau=1.0, leader_accel_delay=3, leader_is_head=False)
    F, B, G, Q, H, R = f._model(False)
    assert F.shape == (14, 14) and H.shape == (6, 14)
    assert H[5].nonzero().flatten().tolist() == [13]
    assert F[2, 10] == pytest.approx(f.dt) and F[4, 10] == 0.0  # the leader moves with it, a distant head does not
    assert [F[11 + j].nonzero().flatten().tolist() for j in range(3)] == [[10], [11], [12]]  # the shift line
    assert float(B[:, 1].abs().max()) == 0.0  # the received value is no input


@pytest.mark.parametrize("kwargs, match", [
    ({"gap_std": -0.1}, r"MeasurementFilter: gap_std=-0.1 is invalid; allowed: >= 0"),
    ({"leader_accel_delay": -1}, r"MeasurementFilter: leader_accel_delay=-1 is invalid; allowed: an integer >= 0"),
    ({"leader_accel_delay": 1.5}, r"MeasurementFilter: leader_accel_delay=1.5 is invalid"),
    ({"leader_accel_delay": 2, "leader_accel_key": None}, r"leader_accel_delay > 0 needs a leader_accel_key"),
    ({"leader_jerk_std": 0.0}, r"MeasurementFilter: leader_jerk_std=0.0 is invalid; allowed: > 0"),
    ({"tau": float("nan")}, r"MeasurementFilter: tau=nan is invalid; allowed: >= 0"),
    ({"leader_accel_std": 0.0}, r"MeasurementFilter: leader_accel_std=0.0 is invalid; allowed: > 0"),
    ({"observation": "seed"}, r"MeasurementFilter: observation='seed' is not supported"),
])
def test_bad_filter_settings_name_the_argument(kwargs, match):
    with pytest.raises(ValueError, match=match):
        MeasurementFilter(**kwargs)


def test_a_flag_per_cav_or_one_for_all():
    base = make_env("ring", batch_size=1, seed=0, **RING)
    env = TransformedEnv(base, MeasurementFilter(0.5, 0.1, leader_is_head=(True, False)))
    with pytest.raises(RuntimeError, match="leader_is_head has 2 flags for 1 CAVs"):
        env.rollout(2, lambda td: td.set("action", torch.zeros(1, 1)))


def test_the_evaluation_puts_the_filter_after_the_noise_and_the_link_and_sizes_the_margin_on_it():
    from transforms import SafetyLayer

    cfg_overrides = ["experiment=ring_lagrangian_ppo_v2v", "eval.sensor_noise_gap=1.0", "eval.sensor_noise_speed=0.3",
                     "eval.sensor_noise_tau=1.0", "eval.sensor_filter=true", "eval.sensor_noise_margin=2.0",
                     "eval.v2v_delay=0.5"]
    cfg = compose(cfg_overrides)
    env = make_transformed_env(cfg, num_envs=1, seed=0, deploy=True)
    kinds = [type(t) for t in env.transform]
    assert kinds[:3] == [SensorNoise, V2VChannel, MeasurementFilter]
    f = env.transform[2]
    assert f.leader_accel_key == ("cav", "leader_accel") and f.delay == 5  # a late link: a late measurement
    lossy = make_transformed_env(compose([*cfg_overrides[:-2], "eval.v2v_loss=0.3"]), num_envs=1, seed=0, deploy=True)
    assert lossy.transform[2].leader_accel_key == ("cav", "leader_accel") and lossy.transform[2].accel_std[1] == 0.5
    assert lossy.transform[2].delay == 0
    late_lossy = make_transformed_env(compose([*cfg_overrides, "eval.v2v_loss=0.3"]), num_envs=1, seed=0, deploy=True)
    assert late_lossy.transform[2].leader_accel_key is None and late_lossy.transform[2].accel_std[1] == 10.0
    layer = next(t for t in env.transform if isinstance(t, SafetyLayer))
    post = f.posterior_std[True]
    assert layer.gap_margin == pytest.approx(2.0 * post[0]) and layer.speed_margin == pytest.approx(2.0 * max(post[1:3]))
    assert layer.gap_margin < 2.0 * 1.0  # tighter than the sensor's own margin
    trained = make_transformed_env(cfg, num_envs=1, seed=0)
    assert not any(isinstance(t, MeasurementFilter) for t in trained.transform)
    exact = compose(["experiment=ring_lagrangian_ppo_v2v", "eval.sensor_filter=true"])  # nothing to filter
    assert not any(isinstance(t, MeasurementFilter) for t in make_transformed_env(exact, num_envs=1, seed=0, deploy=True).transform)


def test_the_evaluation_measures_the_true_state_behind_the_filter(tmp_path):
    """A controller that reads nothing drives the same episodes with and without noise and filter."""
    from tensordict.nn import TensorDictModule

    from mixed_traffic.evaluation import evaluate_and_report

    short = ["experiment=ring_lagrangian_ppo", "transforms=reward", "eval.episodes=2", "eval.episode_seconds=30.0",
             "eval.warmup_seconds=5.0", "eval.profiles=[sine]"]

    def blind(env):
        return TensorDictModule(lambda gap: torch.zeros_like(gap), in_keys=[("cav", "gap")], out_keys=["action"])

    noisy = [*short, "eval.sensor_noise_gap=2.0", "eval.sensor_noise_speed=0.5", "eval.sensor_filter=true"]
    exact = evaluate(compose(short), policy_factory=blind)[0]["profiles"]["sine"]["per_episode"]
    filtered = evaluate(compose(noisy), policy_factory=blind)[0]["profiles"]["sine"]["per_episode"]
    for key in ("min_gap", "max_head_gap", "speed_rmse_steady", "mean_abs_jerk", "return"):
        assert filtered[key] == pytest.approx(exact[key], abs=1e-3), key
    rep = evaluate_and_report(compose([*noisy, "controller=idm", "eval.episodes=1"]), tmp_path)
    assert rep["sensor_noise"]["filter"] is True
    assert "a Kalman filter tracks the measurements" in Path(rep["paths"]["md"]).read_text()


def test_the_filter_takes_the_noise_out_of_a_controllers_jerk():
    short = ["experiment=ring_lagrangian_ppo", "transforms=reward", "eval.episodes=2", "eval.episode_seconds=60.0",
             "eval.warmup_seconds=5.0", "eval.profiles=[random_steps]", "eval.sensor_noise_gap=1.0",
             "eval.sensor_noise_speed=0.3", "eval.sensor_noise_tau=1.0"]

    def jerk(*extra):
        rep, _ = evaluate(compose([*short, *extra]), policy_factory=lambda env: make_classic_policy("idm", env))
        return rep["profiles"]["random_steps"]["metrics"]["mean_abs_jerk"]["mean"]

    assert jerk("eval.sensor_filter=true") < 0.5 * jerk()


TRAIN_NOISE = ["experiment=ring_lagrangian_ppo", "transforms.chain=[sensor_noise,non_negative_reward,safety_layer]",
               "transforms.sensor_noise.gap=0.3", "transforms.sensor_noise.speed=0.1", "transforms.sensor_noise.tau=1.0"]


def test_training_under_noise_puts_it_in_the_trained_chain_only():
    from torchrl.envs import Compose as ComposeT

    cfg = compose([*TRAIN_NOISE, "transforms.sensor_noise.filter=true"])
    trained = make_transformed_env(cfg, num_envs=2, seed=3)
    first = trained.transform[0]
    assert isinstance(first, ComposeT) and [type(t) for t in first] == [SensorNoise, MeasurementFilter]
    assert first[0].seed == 3 + 0  # the env's seed plus transforms.sensor_noise.seed: each worker its own draws
    check_env_specs(trained)
    evaluated = make_transformed_env(cfg, num_envs=2, seed=3, without=("sensor_noise",), deploy=True)
    assert not any(isinstance(t, (SensorNoise, MeasurementFilter, ComposeT)) for t in list(evaluated.transform)[:-2])
    plain = make_transformed_env(compose(TRAIN_NOISE), num_envs=2, seed=3).transform[0]
    assert isinstance(plain, SensorNoise) and (plain.gap_std, plain.speed_std, plain.tau) == (0.3, 0.1, 1.0)


def test_a_trained_filter_reads_the_trained_link_and_must_stand_after_it():
    from torchrl.envs import Compose as ComposeT

    from mixed_traffic.validation import ConfigError, validate_config

    link = ["transforms.v2v_channel.delay=1.0", "transforms.sensor_noise.filter=true"]
    chain = "transforms.chain=[v2v_channel,sensor_noise,non_negative_reward,safety_layer,residual_idm,intervention_cost,jerk_penalty]"
    cfg = validate_config(compose([*TRAIN_NOISE, *link, chain]))
    trained = make_transformed_env(cfg, num_envs=2, seed=3)
    assert isinstance(trained.transform[0], V2VChannel) and isinstance(trained.transform[1], ComposeT)
    assert trained.transform[1][1].delay == 10 and trained.transform[1][1].leader_accel_key == ("cav", "leader_accel")
    lossy = validate_config(compose([*TRAIN_NOISE, *link, chain, "transforms.v2v_channel.loss=0.2"]))
    assert make_transformed_env(lossy, num_envs=2, seed=3).transform[1][1].leader_accel_key is None
    after = chain.replace("v2v_channel,sensor_noise", "sensor_noise,v2v_channel")
    with pytest.raises(ConfigError, match=r"transforms.chain: .*sensor_noise \(with transforms.sensor_noise.filter\) "
                                          r"before v2v_channel; allowed: v2v_channel before sensor_noise"):
        validate_config(compose([*TRAIN_NOISE, *link, after]))
    validate_config(compose([*TRAIN_NOISE, link[0], after]))  # no filter: the order is the user's


def test_training_noise_settings_are_checked_at_start_up():
    from mixed_traffic.validation import ConfigError, validate_config

    with pytest.raises(ConfigError, match=r"transforms.sensor_noise.gap: -1.0 is out of range; allowed: a number in \[0, 10\]"):
        validate_config(compose([*TRAIN_NOISE, "transforms.sensor_noise.gap=-1.0"]))
    with pytest.raises(ConfigError, match=r"transforms.sensor_noise.tau: 100.0 is out of range"):
        validate_config(compose([*TRAIN_NOISE, "transforms.sensor_noise.tau=100.0"]))


def test_the_filter_can_assume_another_noise_than_the_one_drawn(tmp_path):
    from mixed_traffic.evaluation import evaluate_and_report
    from mixed_traffic.validation import ConfigError, validate_config

    noisy = ["experiment=ring_lagrangian_ppo", "eval.sensor_noise_gap=1.0", "eval.sensor_noise_speed=0.3",
             "eval.sensor_noise_tau=1.0", "eval.sensor_filter=true"]
    f = make_transformed_env(compose([*noisy, "eval.sensor_filter_gap=0.3"]), num_envs=1, seed=0, deploy=True).transform[1]
    assert isinstance(f, MeasurementFilter) and (f.gap_std, f.speed_std, f.tau) == (0.3, 0.3, 1.0)  # the rest: drawn
    short = [*noisy, "transforms=reward", "controller=idm", "eval.episodes=1", "eval.episode_seconds=20.0",
             "eval.warmup_seconds=5.0", "eval.profiles=[sine]", "eval.sensor_filter_tau=0.0"]
    rep = evaluate_and_report(compose(short), tmp_path)
    assert rep["sensor_noise"]["filter_model"] == {"gap": 1.0, "speed": 0.3, "tau": 0.0}
    assert "it assumes errors of 1 m and 0.3 m/s over 0 s" in Path(rep["paths"]["md"]).read_text()
    with pytest.raises(ConfigError, match=r"eval.sensor_filter_speed: -0.1 is out of range; allowed: a number in \[0, 5\] or null"):
        validate_config(compose([*noisy, "eval.sensor_filter_speed=-0.1"]))


def test_a_filter_told_the_wrong_layout_says_so():
    base = make_env("ring", batch_size=1, seed=0, **RING)  # observation="relative": 7 features a CAV
    env = TransformedEnv(base, Compose(SensorNoise(0.5, 0.1), MeasurementFilter(0.5, 0.1, observation="relative_accel")))
    with pytest.raises(RuntimeError, match="MeasurementFilter: the observation has 7 features, the 'relative_accel' layout 8"):
        env.rollout(2, lambda td: td.set("action", torch.zeros(1, 1)))
