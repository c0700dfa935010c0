"""Stop-and-go waves: the ring_wave scenario, the classical dampers, the wave metrics and report."""

import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import check_env_specs

from mixed_traffic import make_env
from mixed_traffic.config import compose
from mixed_traffic.controllers.dampers import FollowerStopper, PISaturation, make_damper
from mixed_traffic.evaluation.waves import fuel_rate, hard_brake_events, uniform_flow_speed, wave_metrics
from mixed_traffic.physics import idm_accel, idm_equilibrium_speed
from mixed_traffic.scenarios import get_scenario
from transforms import SafetyLayer
from transforms.safety_layer import scenario_leader_brake

FLOW_IDM = dict(v0=30.0, T=1.0, a=1.0, b=1.5, delta=4.0, s0=2.0)


# ----------------------------------------------------------------------------- scenario
def test_ring_wave_preset_and_specs():
    sc = get_scenario("ring_wave")
    assert (sc.n_vehicles, sc.ring_length, sc.cav_indices, sc.head) == (22, 260.0, (0,), False)
    assert sc.accel_noise == 0.2 and sc.hdv_indices == tuple(range(1, 22))
    env = make_env("ring_wave", batch_size=3, seed=0)
    check_env_specs(env)
    td = env.reset()
    assert ("cav", "head_gap") not in td.keys(True) and ("cav", "speed_avg") in td.keys(True)
    assert td["observation"].shape == (3, 5)
    assert torch.allclose(td["traffic", "ring_length"], torch.full((3, 1), 260.0))


def test_wave_ring_observation_adds_each_rows_ring_length():
    """``observation="wave_ring"``: the wave view plus the episode's ring length / 260 m, per CAV."""
    kw = dict(batch_size=3, seed=0, ring_length_range=(220.0, 270.0), cav_indices=[0, 11])
    plain = make_env("ring_wave", **kw)
    ring = make_env("ring_wave", observation="wave_ring", **kw)
    a, b = plain.reset(), ring.reset()
    feats = b["observation"].reshape(3, 2, 6)
    assert torch.equal(feats[..., :5], a["observation"].reshape(3, 2, 5))
    assert torch.allclose(feats[..., 5], (b["traffic", "ring_length"] / 260.0).expand(3, 2))
    assert len(set(b["traffic", "ring_length"].flatten().tolist())) == 3  # drawn per row
    check_env_specs(ring)


def test_wave_ring_time_observation_adds_the_saturating_time():
    kw = dict(batch_size=2, seed=0, cav_indices=[0, 11], episode_seconds=700.0)
    act = lambda td: td.set("action", torch.zeros(2, 2))  # noqa: E731
    a = make_env("ring_wave", observation="wave_ring", **kw).rollout(3, act)
    timed = make_env("ring_wave", observation="wave_ring_time", **kw)
    b = timed.rollout(3, act)
    fa, fb = a["next", "observation"].reshape(2, 3, 2, 6), b["next", "observation"].reshape(2, 3, 2, 7)
    assert torch.equal(fb[..., :6], fa)
    assert torch.allclose(fb[0, :, 0, 6], torch.tensor([0.1, 0.2, 0.3]) / 600.0)
    td = timed.reset()
    timed.step_count[:] = 6500  # past 600 s the feature stays at 1
    td = timed.step(td.set("action", torch.zeros(2, 2)))["next"]
    assert torch.equal(td["observation"].reshape(2, 2, 7)[..., 6], torch.ones(2, 2))
    check_env_specs(timed)


def test_ring_length_drawn_per_episode_and_cavs_anywhere():
    env = make_env("ring_wave", batch_size=64, seed=1, ring_length_range=[220, 270], cav_indices=[0, 11])
    check_env_specs(env)
    td = env.reset()
    L = td["traffic", "ring_length"].flatten()
    assert L.min() >= 220 and L.max() <= 270 and L.std() > 5  # drawn, not fixed
    # vehicles fill each row's own ring: the gaps plus lengths add up to L
    gaps = td["traffic", "gap"]
    assert torch.allclose(gaps.sum(-1) + 22 * 5.0, L, atol=1e-3)
    assert td["cav", "gap"].shape == (64, 2) and td["observation"].shape == (64, 10)
    # CAV 0 follows the last car of the ring
    assert torch.equal(td["cav", "leader_speed"][:, 0], td["traffic", "speed"][:, 21])


@pytest.mark.parametrize("kw, field", [
    (dict(cav_indices=[22]), "cav_indices"),
    (dict(ring_length_range=[270, 220]), "ring_length_range"),
    (dict(ring_length_range=[100, 120]), "n_vehicles"),
    (dict(accel_noise=-0.1), "accel_noise"),
    (dict(init_wave=1.0), "init_wave"),
    (dict(reward="speed"), "reward"),
    (dict(observation="relative"), "observation"),
])
def test_ring_wave_bad_input_names_the_field(kw, field):
    with pytest.raises(ValueError, match=field):
        make_env("ring_wave", **kw)


def test_head_false_needs_a_ring_and_head_ring_keeps_cav0_forbidden():
    with pytest.raises(ValueError, match="head"):
        get_scenario("deeplcc", head=False, cav_indices=(3, 6))
    with pytest.raises(ValueError, match="cav_indices"):
        get_scenario("ring", cav_indices=(0,))


def test_human_noise_is_applied_and_seeded():
    def human_accels(seed, noise):
        env = make_env("ring_wave", batch_size=2, seed=seed, accel_noise=noise, hdv_param_noise=0.0, init_wave=0.0)
        td = env.rollout(3, lambda td: td.set("action", torch.zeros(2, 1)))
        return td["next", "traffic", "accel"][:, :, 1:]

    quiet = human_accels(0, 0.0)
    noisy = human_accels(0, 0.2)
    assert torch.allclose(quiet[0], quiet[1])  # identical rows without noise
    spread = (noisy - quiet).std()
    assert 0.1 < float(spread) < 0.3  # N(0, 0.2) per step
    assert torch.equal(noisy, human_accels(0, 0.2))  # same seed, same noise


def test_uniform_flow_speed_is_idm_equilibrium():
    for L in (220.0, 260.0, 270.0):
        gap = L / 22 - 5.0
        v = idm_equilibrium_speed(gap, **FLOW_IDM)
        a = idm_accel(torch.tensor(gap), v.float(), v.float(), **FLOW_IDM)
        assert abs(float(a)) < 1e-4
    assert uniform_flow_speed(get_scenario("ring_wave"), 260.0) == pytest.approx(4.8159, abs=1e-3)


def test_wave_reward_is_speed_minus_spread_minus_accel():
    env = make_env("ring_wave", batch_size=1, seed=0)
    td = env.rollout(2, lambda td: td.set("action", torch.full((1, 1), 1.5)))
    v = td["next", "traffic", "speed"][0, -1]
    a = td["next", "cav", "accel"][0, -1, 0]
    r = v.mean() / 10 - 0.2 * v.std(unbiased=False) / 10 - 0.3 * a.abs() / 3
    assert float(td["next", "reward"][0, -1, 0]) == pytest.approx(float(r) - 1.0, abs=1e-5)


def test_wave_relative_reward_scales_each_row_by_its_uniform_flow_speed():
    env = make_env("ring_wave", batch_size=3, seed=0, reward="wave_relative", ring_length_range=[210.0, 285.0])
    td = env.rollout(2, lambda td: td.set("action", torch.full((3, 1), 1.5)))
    L = td["next", "traffic", "ring_length"][:, -1, 0]
    assert float(L.max() - L.min()) > 5.0  # rows on different rings
    v, a = td["next", "traffic", "speed"][:, -1], td["next", "cav", "accel"][:, -1, 0]
    U = torch.tensor([uniform_flow_speed(env.scenario, float(x)) for x in L])
    r = v.mean(-1) / U - 0.2 * v.std(-1, unbiased=False) / U - 0.3 * a.abs() / 3
    assert torch.allclose(td["next", "reward"][:, -1, 0], (r - 1.0).float(), atol=1e-5)
    with pytest.raises(ValueError, match="reward"):
        make_env("ring", reward="wave_relative")  # a ring with a scripted head has no uniform flow to scale by


def test_overrides_need_no_plus():
    cfg = compose(["env=ring_wave", "env.overrides.ring_length=230", "env.overrides.cav_indices=[0,11]"])
    assert cfg.env.overrides.ring_length == 230 and list(cfg.env.overrides.cav_indices) == [0, 11]
    with pytest.raises(Exception, match="weight_vv"):
        compose(["env.weight_vv=1"])  # the named fields stay strict


# ----------------------------------------------------------------------------- safety layer without a head
def test_safety_layer_without_head_bound_keeps_s_min():
    env = TransformedEnv(make_env("ring_wave", batch_size=4, seed=0, cav_indices=[0, 7]), SafetyLayer(s_min=2.0, s_max=None))
    td = env.rollout(600, lambda td: td.set("action", torch.full((4, 2), 3.0)), break_when_any_done=False)
    assert not td["next", "collision"].any()
    assert float(td["next", "cav", "gap"].min()) >= 2.0 - 1e-4
    assert td["next", "safety", "clipped"].any()  # it had work to do
    # CAV 0's leader is the last (human) car: its braking bound is the humans' a_min widened by the spread
    assert scenario_leader_brake(get_scenario("ring_wave", cav_indices=(0, 7))) == pytest.approx([9.9, 9.9])
    with pytest.raises(KeyError, match="s_max=None"):  # an s_max bound on a ring without a head
        env2 = TransformedEnv(make_env("ring_wave", batch_size=1, seed=0), SafetyLayer(s_min=2.0, s_max=40.0))
        env2.rollout(2, lambda td: td.set("action", torch.zeros(1, 1)))


# ----------------------------------------------------------------------------- dampers
def test_follower_stopper_regions_by_hand():
    fs = FollowerStopper(dt=0.1, low=-3.0, high=3.0, U=6.0)
    U = torch.tensor([6.0])

    def cmd(gap, v, vl):
        return float(fs.command(torch.tensor([gap]), torch.tensor([v]), torch.tensor([vl]), U))

    # v_lead = 4 >= v = 3: dv_- = 0, envelopes 4.5 / 5.25 / 6.0 m
    assert cmd(4.0, 3.0, 4.0) == 0.0
    assert cmd(4.875, 3.0, 4.0) == pytest.approx(4.0 * 0.375 / 0.75)  # half-way in region 2
    assert cmd(5.625, 3.0, 4.0) == pytest.approx(4.0 + (6.0 - 4.0) * 0.5)  # half-way in region 3
    assert cmd(10.0, 3.0, 4.0) == 6.0
    # closing at 2 m/s: dv_- = -2, envelopes 4.5 + 4/3, 5.25 + 2, 6 + 4
    dx1, dx2, dx3 = 4.5 + 4 / 3, 7.25, 10.0
    assert cmd(dx1 - 0.01, 5.0, 3.0) == 0.0
    g = (dx1 + dx2) / 2
    assert cmd(g, 5.0, 3.0) == pytest.approx(3.0 * (g - dx1) / (dx2 - dx1), rel=1e-5)
    assert cmd(9.0, 5.0, 3.0) == pytest.approx(3.0 + 3.0 * (9.0 - dx2) / (dx3 - dx2), rel=1e-5)
    # the leader above U: w = min(v_lead, U)
    assert cmd(5.0, 3.0, 9.0) == pytest.approx(6.0 * 0.5 / 0.75)
    # acceleration (v_cmd - v) / dt clipped to the bounds
    a = fs(torch.tensor([[4.875]]), torch.tensor([[1.9]]), torch.tensor([[4.0]]), torch.tensor([[260.0]]))
    assert float(a) == pytest.approx((2.0 - 1.9) / 0.1, abs=1e-4)
    a = fs(torch.tensor([[5.625]]), torch.tensor([[3.9]]), torch.tensor([[4.0]]), torch.tensor([[260.0]]))
    assert float(a) == pytest.approx(3.0)  # (5 - 3.9) / 0.1 clipped to the upper bound


def test_follower_stopper_ramp_moves_the_set_point_in_episode_time():
    env = make_env("ring_wave", batch_size=3, seed=0)
    ramped = make_damper("follower_stopper", env, u_ratio=0.8, ramp_to=1.0, ramp_start=100.0, ramp_end=200.0)
    assert ("traffic", "time") in ramped.in_keys
    far = torch.full((3, 1), 50.0)  # far from the leader: v_cmd = U
    speed, lead, L = torch.full((3, 1), 1.0), torch.full((3, 1), 4.0), torch.full((3, 1), 260.0)
    t = torch.tensor([[50.0], [150.0], [250.0]])
    U = uniform_flow_speed(env.scenario, 260.0)
    ratio = torch.tensor([0.8, 0.9, 1.0])
    fs = ramped.module
    fs.high = 100.0  # unclipped, to read the set point
    a = fs(far, speed, lead, L, t)[:, 0]
    assert torch.allclose(a, ((ratio * U - 1.0) / 0.1).float(), rtol=1e-4)
    with pytest.raises(ValueError, match="ramp_end"):
        make_damper("follower_stopper", env, ramp_to=1.0, ramp_start=200.0, ramp_end=100.0)


def test_follower_stopper_default_set_point_is_uniform_flow():
    env = make_env("ring_wave", batch_size=1, seed=0, ring_length=250.0)
    fs = make_damper("follower_stopper", env).module
    assert float(fs.set_point(torch.tensor([[250.0]]))) == pytest.approx(
        float(idm_equilibrium_speed(250.0 / 22 - 5.0, **FLOW_IDM)), abs=1e-5)


def test_pi_saturation_by_hand():
    pi = PISaturation(dt=0.1, low=-3.0, high=3.0)
    # gap 18.5 m: v_target = U + 1 * (18.5 - 7) / 23 = U + 0.5; dx_s = max(2 * (5 - 4), 4) = 4; alpha = 1, beta = 0.5
    v_cmd = pi.command(torch.tensor([18.5]), torch.tensor([4.0]), torch.tensor([5.0]), torch.tensor([4.2]))
    assert float(v_cmd) == pytest.approx(0.5 * 4.7 + 0.5 * 4.0)
    # gap 5 m, leader 1 m/s slower: dx_s = 4, alpha = 0.5, beta = 0.75, v_target = U (gap < g_l)
    v_cmd = pi.command(torch.tensor([5.0]), torch.tensor([4.0]), torch.tensor([3.0]), torch.tensor([4.2]))
    assert float(v_cmd) == pytest.approx(0.75 * (0.5 * 4.2 + 0.5 * 3.0) + 0.25 * 4.0)
    # gap below dx_s: alpha = 0, beta = 1: v_cmd = v_lead
    v_cmd = pi.command(torch.tensor([3.0]), torch.tensor([4.0]), torch.tensor([2.0]), torch.tensor([4.2]))
    assert float(v_cmd) == pytest.approx(2.0)


def test_cav_speed_avg_is_the_window_mean():
    env = make_env("ring_wave", batch_size=2, seed=0, cav_speed_window=1.0)
    td = env.rollout(30, lambda td: td.set("action", torch.full((2, 1), 0.5)))
    v = torch.cat([td["cav", "speed"][:, :1], td["next", "cav", "speed"]], 1)[..., 0]  # t = 0 .. 30
    avg = td["next", "cav", "speed_avg"][:, -1, 0]
    assert torch.allclose(avg, v[:, -10:].mean(1), atol=1e-5)


def test_dampers_validate_and_run_on_the_ring():
    env = make_env("ring_wave", batch_size=2, seed=0)
    with pytest.raises(ValueError, match="damper"):
        make_damper("stopper", env)
    with pytest.raises(ValueError, match="pi_saturation"):
        make_damper("pi_saturation", make_env("ring", batch_size=1))
    for name in ("human", "idm", "follower_stopper", "pi_saturation", "fs_then_pi"):
        td = env.rollout(200, make_damper(name, env))
        assert not td["next", "collision"].any(), name


# ----------------------------------------------------------------------------- wave metrics
def _constructed(T=200, dt=0.1, n=4, L=100.0):
    """Episode 0: two cars at 2 m/s, two at 6 m/s (std 2, mean 4); car 1 brakes hard twice."""
    v = torch.tensor([2.0, 6.0, 2.0, 6.0]).expand(1, T, n).clone()
    a = torch.zeros(1, T, n)
    a[0, 150:155, 1] = -3.0
    a[0, 170:172, 1] = -2.5
    a[0, 50:60, 2] = -3.0  # inside the warm-up: not counted
    gap = torch.full((1, T, n), L / n - 5.0)
    gap[0, 10, 3] = 1.0
    t = ((torch.arange(T) + 1) * dt).reshape(1, T, 1)
    nxt = TensorDict({"traffic": TensorDict({"speed": v, "accel": a, "gap": gap, "time": t,
                                             "ring_length": torch.full((1, T, 1), L)}, [1, T]),
                      "done": torch.zeros(1, T, 1, dtype=torch.bool), "collision": torch.zeros(1, T, 1, dtype=torch.bool)},
                     [1, T])
    return TensorDict({"next": nxt}, [1, T])


def test_wave_metrics_on_a_constructed_trajectory():
    td = _constructed()
    m = wave_metrics(td, dt=0.1, warmup=10.0, hard_brake=-2.0)
    assert float(m["mean_speed"]) == pytest.approx(4.0)
    assert float(m["speed_std"]) == pytest.approx(2.0)
    steps_after = 100  # t in (10, 20]
    vkm = 4 * 4.0 * steps_after * 0.1 / 1000
    assert float(m["hard_brakes_per_vkm"]) == pytest.approx(2 / vkm)
    assert float(m["throughput"]) == pytest.approx(4 * 4.0 / 100.0 * 3600)
    assert float(m["min_gap"]) == pytest.approx(1.0) and float(m["collision"]) == 0.0
    a = td["next", "traffic", "accel"][:, 100:]
    fuel = float(fuel_rate(td["next", "traffic", "speed"][:, 100:], a).sum() * 0.1)
    assert float(m["fuel_ml_per_vkm"]) == pytest.approx(fuel / vkm, rel=1e-5)
    # the fuel model: 0.444 + 0.09 R v + 0.054 max(a, 0)^2 v with R = 0.333 + 0.00108 v^2 + 1.2 a; R <= 0: idle
    assert float(fuel_rate(torch.tensor(10.0), torch.tensor(0.5))) == pytest.approx(
        0.444 + 0.09 * (0.333 + 0.108 + 0.6) * 10 + 0.054 * 0.25 * 10)
    assert float(fuel_rate(torch.tensor(5.0), torch.tensor(-2.0))) == pytest.approx(0.444)


def test_hard_brake_events_count_crossings():
    a = torch.tensor([[0.0, -3.0, -3.0, 0.0, -3.0, -1.0]]).unsqueeze(-1)
    assert int(hard_brake_events(a, -2.0, torch.ones(1, 6, dtype=torch.bool))) == 2


def test_wave_report_from_mt_eval_pipeline(tmp_path):
    from mixed_traffic.evaluation import evaluate_and_report

    cfg = compose(["experiment=ring_wave_lppo", "controller=all", "eval.wave.episodes=2",
                   "eval.wave.episode_seconds=20", "eval.wave.warmup_seconds=5", "eval.wave.ring_lengths=[240]",
                   "eval.wave.controllers=[human,pi_saturation]"])
    rep = evaluate_and_report(cfg, tmp_path)
    ctrl = rep["rings"]["240"]["controllers"]
    assert set(ctrl) == {"human", "pi_saturation"}
    assert rep["rings"]["240"]["uniform_flow_speed"] == pytest.approx(3.908, abs=1e-3)
    assert (tmp_path / "space_time_240m.png").is_file() and (tmp_path / "report.md").is_file()
    assert "speed std vs human" in (tmp_path / "report.md").read_text()


# ----------------------------------------------------------------------------- waves form (slow)
@pytest.mark.slow
def test_all_human_ring_forms_waves_and_dampers_reduce_them():
    out = {}
    for name in ("human", "follower_stopper", "pi_saturation"):
        env = make_env("ring_wave", batch_size=4, seed=3, episode_seconds=300.0)
        with torch.no_grad():
            td = env.rollout(3000, make_damper(name, env), break_when_any_done=False)
        m = wave_metrics(td, dt=0.1, warmup=150.0)
        assert not m["collision"].any()
        out[name] = float(m["speed_std"].mean())
    assert out["human"] >= 2.0
    assert out["follower_stopper"] < 0.5 * out["human"] and out["pi_saturation"] < 0.5 * out["human"]
    assert math.isfinite(out["human"])


def test_classical_rows_drive_the_cav_themselves_not_through_the_residual():
    """With a residual_damper in the run's chain, the classical controllers' rows still
    execute their own command (the residual base is the learned policy's only)."""
    from mixed_traffic.evaluation.waves import evaluate_waves

    common = ["experiment=ring_wave_lppo", "eval.wave.episodes=1", "eval.wave.episode_seconds=6",
              "eval.wave.warmup_seconds=1", "eval.wave.ring_lengths=[240]"]
    with_res = compose(common + ["transforms.chain=[residual_damper,non_negative_reward]"])
    without = compose(common + ["transforms.chain=[non_negative_reward]"])
    a, _ = evaluate_waves(with_res, controllers=["human"])
    b, _ = evaluate_waves(without, controllers=["human"])
    ma, mb = (r["rings"]["240"]["controllers"]["human"]["per_episode"] for r in (a, b))
    assert ma["mean_speed"] == mb["mean_speed"] and ma["speed_std"] == mb["speed_std"]


def test_set_point_action_is_follower_stopper_at_the_chosen_ratio():
    from torchrl.envs import TransformedEnv

    from mixed_traffic.controllers.dampers import make_damper
    from transforms import SetPointAction

    def run(ratio0, a, policy_of_env):
        base = make_env("ring_wave", batch_size=3, seed=5, ring_length_range=[220.0, 270.0])
        if policy_of_env is None:
            env = TransformedEnv(base, SetPointAction(make_damper("follower_stopper", base).module, ratio0=ratio0,
                                                      weight=0.05))
            return env.rollout(200, lambda td: td.set("action", torch.full((3, 1), a)))
        return base.rollout(200, policy_of_env(base))

    for ratio0, a, ratio in ((0.9, 0.0, 0.9), (0.9, 1.0, 0.95), (0.95, -1.0, 0.9)):
        ours = run(ratio0, a, None)
        fs = run(None, None, lambda e, r=ratio: make_damper("follower_stopper", e, u_ratio=r))
        assert torch.allclose(ours["next", "traffic", "speed"], fs["next", "traffic", "speed"], atol=1e-5)
        assert torch.allclose(ours["next", "set_point", "ratio"], torch.tensor(ratio))
    base = make_env("ring_wave", batch_size=2, seed=0)
    env = TransformedEnv(base, SetPointAction(make_damper("follower_stopper", base).module))
    assert env.action_spec.space.low.min() == -1 and env.action_spec.space.high.max() == 1
    check_env_specs(env)
    with pytest.raises(ValueError, match="weight"):
        SetPointAction(make_damper("follower_stopper", base).module, ratio0=0.5, weight=0.6)
    with pytest.raises(ValueError, match="set_point"):
        SetPointAction(torch.nn.Linear(1, 1))
    # rate mode: the action moves the ratio in force, which stays in [low, high]
    env = TransformedEnv(base, SetPointAction(make_damper("follower_stopper", base).module, ratio0=0.9, rate=0.04,
                                              low=0.8, high=1.0))
    up = env.rollout(5, lambda td: td.set("action", torch.ones(2, 1)))["next", "set_point", "ratio"][0, :, 0]
    assert up.tolist() == pytest.approx([0.94, 0.98, 1.0, 1.0, 1.0])
    down = env.rollout(4, lambda td: td.set("action", -torch.ones(2, 1)))["next", "set_point", "ratio"][0, :, 0]
    assert down.tolist() == pytest.approx([0.86, 0.82, 0.8, 0.8])
    with pytest.raises(ValueError, match="rate"):
        SetPointAction(make_damper("follower_stopper", base).module, ratio0=0.9, rate=0.01, low=0.95)


def test_set_point_action_with_a_ramp_is_the_ramped_follower_stopper_at_zero_action():
    """ramp_to: a = 0 follows FollowerStopper's ramped schedule; the rate-mode action adds its correction."""
    from torchrl.envs import TransformedEnv

    from mixed_traffic.controllers.dampers import make_damper
    from transforms import SetPointAction

    ramp = dict(ramp_to=1.0, ramp_start=1.0, ramp_end=3.0)

    def run(a, rate=0.001):
        base = make_env("ring_wave", batch_size=2, seed=5, ring_length=230.0)
        if a is None:
            return base.rollout(40, make_damper("follower_stopper", base, u_ratio=0.87, **ramp))
        sp = SetPointAction(make_damper("follower_stopper", base).module, ratio0=0.87, rate=rate, **ramp)
        return TransformedEnv(base, sp).rollout(40, lambda td: td.set("action", torch.full((2, 1), a)))

    fs, zero, up = run(None), run(0.0), run(1.0)
    assert torch.allclose(zero["next", "traffic", "speed"], fs["next", "traffic", "speed"], atol=1e-4)
    ratio = zero["next", "set_point", "ratio"][0, :, 0]
    assert ratio[:11].tolist() == pytest.approx([0.87] * 11) and float(ratio[-1]) == pytest.approx(1.0)
    assert float(ratio[20]) == pytest.approx(0.87 + 0.13 * 0.5)  # t = 2 s: half-way
    # rate mode: the correction integrates on top of the schedule (40 steps of +0.001)
    assert (up["next", "set_point", "ratio"][0, :, 0] - ratio)[-1] == pytest.approx(0.04, abs=1e-6)
    with pytest.raises(ValueError, match="ramp_to"):
        SetPointAction(make_damper("follower_stopper", make_env("ring_wave", batch_size=1, seed=0)).module,
                       ratio0=0.9, rate=0.01, ramp_to=1.2, high=1.05)


def test_fs_then_pi_is_follower_stopper_then_pi_blended_over_the_switch():
    """``fs_then_pi``: FollowerStopper's ramp until ``switch``, PI-saturation after ``switch + switch_s``,
    the two commands mixed linearly between."""
    env = make_env("ring_wave", batch_size=2, seed=3, ring_length=230.0)
    hand = make_damper("fs_then_pi", env, switch=2.0, switch_s=1.0)
    fs = make_damper("follower_stopper", env, u_ratio=0.87, ramp_to=1.0)
    pi = make_damper("pi_saturation", env)
    td = env.rollout(40, hand)
    for k, t in ((5, 0.5), (15, 1.5), (25, 2.5), (35, 3.5)):  # state k: time k * dt
        state = td[:, k]
        a1, a2 = fs(state.clone())["action"], pi(state.clone())["action"]
        m = min(max((t - 2.0) / 1.0, 0.0), 1.0)
        assert torch.allclose(state["action"], (1 - m) * a1 + m * a2, atol=1e-6), t
    assert not torch.allclose(fs(td[:, 35].clone())["action"], pi(td[:, 35].clone())["action"])  # a real hand-over
    with pytest.raises(ValueError, match="switch_s"):
        make_damper("fs_then_pi", env, switch_s=0.0)


def test_controller_blend_is_the_hand_over_at_zero_action_and_the_policy_moves_it():
    """``ControllerBlend``: at a = 0 exactly the ``fs_then_pi`` damper; a = +1 hands over earlier; specs hold."""
    from transforms import ControllerBlend

    base = make_env("ring_wave", batch_size=2, seed=4, ring_length=230.0)
    fs = make_damper("follower_stopper", base, u_ratio=0.87, ramp_to=1.0)
    pi = make_damper("pi_saturation", base)
    env = TransformedEnv(base, ControllerBlend(fs, pi, rate=0.01, start=2.0, end=3.0))
    zero = env.rollout(50, lambda td: td.set("action", torch.zeros(2, 1)))
    ref_env = make_env("ring_wave", batch_size=2, seed=4, ring_length=230.0)
    ref = ref_env.rollout(50, make_damper("fs_then_pi", ref_env, switch=2.0, switch_s=1.0))
    assert torch.equal(zero["next", "traffic", "speed"], ref["next", "traffic", "speed"])
    w = zero["next", "blend", "weight"][0, :, 0]
    assert float(w[19]) == 0.0 and float(w[25]) == pytest.approx(0.5) and float(w[-1]) == 1.0
    up = env.rollout(50, lambda td: td.set("action", torch.ones(2, 1)))
    wu = up["next", "blend", "weight"][0, :, 0]
    assert float(wu[9]) == pytest.approx(0.1) and float(wu[-1]) == 1.0  # 0.01 per step before the switch, capped at 1
    assert float(up["next", "blend", "correction"][0, -1, 0]) == 0.0  # no wind-up: the schedule took over
    check_env_specs(env)
    with pytest.raises(ValueError, match="rate"):
        ControllerBlend(fs, pi, rate=0.0)
    with pytest.raises(ValueError, match="start"):
        ControllerBlend(fs, pi, rate=0.01, start=5.0, end=3.0)
    with pytest.raises(ValueError, match="first"):
        ControllerBlend(lambda td: td, pi, rate=0.01)
    from mixed_traffic.training.builders import make_transformed_env

    for field, bad, allowed in (("first", "no_such_damper", "follower_stopper"),
                                ("first", "follower_stopper:speed=3", "'U', 'u_ratio'"),
                                ("second", "pi_saturation:g_x=1", "'g_l', 'g_u', 'v_catch', 'gamma'")):
        cfg = compose(["experiment=ring_wave_blend", f"transforms.blend.{field}='{bad}'"])
        with pytest.raises(ValueError, match=f"transforms.blend.{field}=.*allowed: .*{allowed}"):
            make_transformed_env(cfg, num_envs=1, seed=0)


def test_wave_experiments_pass_check_env_specs():
    """The training chain's ``episode_reward`` is unbounded (TorchRL's ``RewardSum`` would copy the wave
    reward's [-1, 1] bounds, which the episode's sum leaves after two steps)."""
    from mixed_traffic.training.builders import make_transformed_env

    for exp in ("ring_wave_cem", "ring_wave_blend"):
        check_env_specs(make_transformed_env(compose([f"experiment={exp}"]), num_envs=2, seed=0))


def test_wave_blend_layer_brakes_as_hard_as_a_human_and_commands_stay_in_range():
    """ring_wave_blend: the scenario's emergency braking reaches the safety layer (its worst case and its
    floor), the action range the policy and the dampers command in is unchanged."""
    from mixed_traffic.training.builders import make_transformed_env

    env = make_transformed_env(compose(["experiment=ring_wave_blend"]), num_envs=2, seed=0)
    sc = env.base_env.scenario
    assert sc.cav_emergency_decel == 9.0 and sc.cav_exec_bounds == (-9.0, 3.0)
    assert env.base_env.action_spec.space.low.min() == -3.0
    layer = next(t for t in env.transform if type(t).__name__ == "SafetyLayer")
    assert layer._ego_brake_value(torch.tensor([-3.0])).tolist() == [9.0]
    plain = make_transformed_env(compose(["experiment=ring_wave_cem"]), num_envs=2, seed=0)
    layer = next(t for t in plain.transform if type(t).__name__ == "SafetyLayer")
    assert layer._ego_brake_value(torch.tensor([-3.0])).tolist() == [3.0]


def test_classical_with_layer_adds_each_damper_behind_the_safety_layer():
    """eval.wave.classical_with_layer: every damper (not the all-human ring) again, behind the
    run's safety layer; a set point far above the ring's speed is clipped there, not without it."""
    from mixed_traffic.evaluation.waves import evaluate_waves

    cfg = compose(["experiment=ring_wave_blend", "env.overrides.cav_emergency_decel=null", "eval.wave.episodes=2",
                   "eval.wave.episode_seconds=30",
                   "eval.wave.warmup_seconds=1", "eval.wave.ring_lengths=[240]", "eval.wave.classical_with_layer=true"])
    rep, _ = evaluate_waves(cfg, controllers=["human", "follower_stopper:U=15"])
    ctrl = rep["rings"]["240"]["controllers"]
    assert set(ctrl) == {"human", "follower_stopper:U=15", "follower_stopper:U=15 (layer)"}
    layer, bare = ctrl["follower_stopper:U=15 (layer)"], ctrl["follower_stopper:U=15"]
    assert layer["metrics"]["intervention"]["min"] > 0 and bare["metrics"]["intervention"]["max"] == 0
    assert layer["collisions"] == 0 and layer["metrics"]["cav_min_gap"]["min"] >= 2.0 - 1e-4  # the layer's s_min


def test_wave_controllers_take_arguments_and_name_bad_ones():
    from mixed_traffic.evaluation.waves import controller_factories, parse_controller

    assert parse_controller("follower_stopper:u_ratio=0.93") == ("follower_stopper", {"u_ratio": 0.93})
    assert parse_controller("pi_saturation") == ("pi_saturation", {})
    cfg = compose(["experiment=ring_wave_lppo"])
    env = make_env("ring_wave", batch_size=2, seed=0, ring_length=230.0)
    fac = controller_factories(cfg, ["follower_stopper:u_ratio=0.9"])
    assert fac["follower_stopper:u_ratio=0.9"][0](env).module.u_ratio == 0.9
    for bad in ("follower_stopper:u_ratio", "follower_stopper:u_ratio=fast", "no_such_damper:u_ratio=1"):
        with pytest.raises(ValueError, match="eval.wave.controllers"):
            controller_factories(cfg, [bad])
    # an unknown argument fails when the list is read, before any controller runs, naming the allowed ones
    with pytest.raises(ValueError, match=r"eval.wave.controllers: 'pi_saturation:gl=3'.*\['gl'\].*'g_l'"):
        controller_factories(cfg, ["follower_stopper", "pi_saturation:gl=3"])


def test_damper_arguments_are_checked_by_name():
    """``make_damper`` accepts its damper's own arguments and refuses any other by name, listing the allowed
    ones (the human and IDM baselines take none: an argument there is not silently ignored)."""
    from mixed_traffic.controllers.dampers import damper_arguments

    env = make_env("ring_wave", batch_size=1, seed=0)
    assert damper_arguments("pi_saturation") == ["g_l", "g_u", "v_catch", "gamma"]
    assert {"switch", "switch_s", "u_ratio", "ramp_to"} <= set(damper_arguments("fs_then_pi"))
    assert make_damper("fs_then_pi", env, switch=100.0, u_ratio=0.9).module.first.u_ratio == 0.9
    for name, kwargs, allowed in (("human", {"noise": 0.0}, "none"), ("idm", {"T": 1.5}, "none"),
                                  ("fs_then_pi", {"g_l": 3.0}, "'switch', 'switch_s', 'U'"),
                                  ("follower_stopper", {"dt": 0.2}, "'U', 'u_ratio'")):
        with pytest.raises(ValueError, match=f"{name}: arguments .* are invalid; allowed: .*{allowed}"):
            make_damper(name, env, **kwargs)
