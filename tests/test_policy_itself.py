"""The policy without its safety net: the intervention cost, the PID multiplier, randomised
training starts and head profiles, and the evaluation with the safety layer removed."""

from pathlib import Path

import pytest
import torch
from torchrl.envs import Compose, TransformedEnv
from torchrl.envs.utils import check_env_specs

from mixed_traffic import make_env
from mixed_traffic.config import compose
from mixed_traffic.controllers.classic import make_classic_policy
from mixed_traffic.evaluation import evaluate
from mixed_traffic.profiles import make_profile
from transforms import InterventionCost, LagrangeMultiplier, NonNegativeReward, SafetyLayer


# ----------------------------------------------------------------------------- intervention cost
def _env(mode="both", coef=1.0, batch=4):
    return TransformedEnv(make_env("ring", batch_size=batch, seed=0),
                          Compose(NonNegativeReward(), SafetyLayer(s_min=5.0, s_max=30.0),
                                  InterventionCost(coef=coef, mode=mode)))


def test_intervention_cost_spec_and_values():
    env = _env()
    check_env_specs(env)
    assert ("safety", "intervention_cost") in env.observation_spec.keys(True)
    assert "cost" in env.full_reward_spec.keys()
    td = env.rollout(200, lambda td: td.set("action", torch.full((4, 1), 3.0)), break_when_any_done=False)
    nxt = td["next"]
    delta, clipped = nxt["safety", "delta"], nxt["safety", "clipped"].float()
    c = nxt["safety", "intervention_cost"]
    # both = mean of |delta| / (action range 6) and the clip flag
    assert torch.allclose(c, 0.5 * (delta.abs() / 6.0 + clipped), atol=1e-6)
    assert clipped.mean() > 0.3  # full throttle behind the head: the layer works
    # the env's own s_min cost is still in: cost = violation + coef * intervention
    viol = ((5.0 - nxt["cav", "gap"].clamp_min(0)).clamp_min(0) / 5.0).sum(-1, keepdim=True)
    assert torch.allclose(nxt["cost"], viol + c, atol=1e-6)


@pytest.mark.parametrize("mode", ["magnitude", "indicator"])
def test_intervention_cost_modes_and_coef(mode):
    env = _env(mode=mode, coef=2.0, batch=2)
    td = env.rollout(100, lambda td: td.set("action", torch.full((2, 1), 3.0)), break_when_any_done=False)
    nxt = td["next"]
    expect = nxt["safety", "delta"].abs() / 6.0 if mode == "magnitude" else nxt["safety", "clipped"].float()
    assert torch.allclose(nxt["safety", "intervention_cost"], expect, atol=1e-6)
    viol = ((5.0 - nxt["cav", "gap"].clamp_min(0)).clamp_min(0) / 5.0)
    assert torch.allclose(nxt["cost"], viol + 2.0 * expect, atol=1e-6)


def test_intervention_cost_is_zero_when_the_layer_is_idle():
    env = _env(batch=2)
    td = env.rollout(100, make_classic_policy("idm", env.base_env), break_when_any_done=False)
    idle = ~td["next", "safety", "clipped"]
    assert idle.any()
    assert (td["next", "safety", "intervention_cost"][idle] == 0).all()


def test_intervention_cost_direction_counts_braking_or_pushing_only():
    """``brake`` prices the layer braking for the policy and not its s_max pull-up, ``push`` the reverse."""
    def run(direction, accel):
        env = TransformedEnv(make_env("ring", batch_size=2, seed=0),
                             Compose(NonNegativeReward(), SafetyLayer(s_min=5.0, s_max=30.0),
                                     InterventionCost(mode="both", direction=direction)))
        td = env.rollout(150, lambda td: td.set("action", torch.full((2, 1), accel)), break_when_any_done=False)
        return td["next", "safety", "delta"], td["next", "safety", "intervention_cost"]

    delta, c = run("brake", 3.0)  # full throttle: the layer brakes
    assert (delta < 0).any() and torch.allclose(c, torch.where(delta < 0, 0.5 * (delta.abs() / 6.0 + 1.0), 0.0))
    delta, c = run("brake", -3.0)  # full braking from the 73.4 m start: the layer only pulls up (s_max)
    assert (delta > 0).any() and not (delta < 0).any() and (c == 0).all()
    delta, c = run("push", -3.0)
    assert torch.allclose(c, torch.where(delta > 0, 0.5 * (delta.abs() / 6.0 + 1.0), 0.0)) and (c > 0).any()


def test_intervention_cost_bad_arguments_name_the_field():
    with pytest.raises(ValueError, match="mode="):
        InterventionCost(mode="sometimes")
    with pytest.raises(ValueError, match="coef="):
        InterventionCost(coef=0.0)
    with pytest.raises(ValueError, match="direction="):
        InterventionCost(direction="down")
    with pytest.raises(ValueError, match="scale="):
        InterventionCost(scale=-1.0)


def test_jerk_penalty_prices_changes_of_the_executed_acceleration():
    from transforms import JerkPenalty

    env = TransformedEnv(make_env("ring", batch_size=2, seed=0), Compose(NonNegativeReward(), JerkPenalty(weight=2.0)))
    plain = TransformedEnv(make_env("ring", batch_size=2, seed=0), NonNegativeReward())
    acts = torch.tensor([1.0, -2.0, -2.0, 0.5]).repeat(2, 1).T.unsqueeze(-1)  # [T, B, 1]
    it = iter(acts)
    td = env.rollout(4, lambda td: td.set("action", next(it)))
    it = iter(acts)
    ref = plain.rollout(4, lambda td: td.set("action", next(it)))
    pen = (ref["next", "reward"] - td["next", "reward"])[0, :, 0]
    assert pen.tolist() == pytest.approx([2.0 * 1.0 / 6, 2.0 * 3.0 / 6, 0.0, 2.0 * 2.5 / 6], abs=1e-5)
    # weight_after prices the steps from after_seconds of the episode on (the ring steps 0.1 s: steps 3 and 4)
    late = TransformedEnv(make_env("ring", batch_size=2, seed=0),
                          Compose(NonNegativeReward(), JerkPenalty(weight=2.0, weight_after=8.0, after_seconds=0.3)))
    it = iter(acts)
    pen = (ref["next", "reward"] - late.rollout(4, lambda td: td.set("action", next(it)))["next", "reward"])[0, :, 0]
    assert pen.tolist() == pytest.approx([2.0 * 1.0 / 6, 2.0 * 3.0 / 6, 0.0, 8.0 * 2.5 / 6], abs=1e-5)
    with pytest.raises(ValueError, match="weight="):
        JerkPenalty(weight=-1.0)
    with pytest.raises(ValueError, match="weight_after=-1.0 is invalid; allowed: null or >= 0"):
        JerkPenalty(weight_after=-1.0)
    with pytest.raises(ValueError, match="after_seconds=-2.0 is invalid"):
        JerkPenalty(after_seconds=-2.0)


def test_jerk_limit_bounds_the_change_and_lets_the_layer_brake_at_once():
    from transforms import JerkLimit

    def accels(chain, acts):
        env = TransformedEnv(make_env("ring", batch_size=2, seed=0), Compose(*chain))
        check_env_specs(env)
        it = iter(acts)
        return env.rollout(len(acts), lambda td: td.set("action", next(it)))["next", "cav", "accel"][0, :, 0]

    acts = torch.tensor([3.0, 3.0, -3.0, -3.0, -3.0]).repeat(2, 1).T.unsqueeze(-1)
    a = accels([JerkLimit(max_jerk=5.0)], acts)  # 0.5 m/s^2 per 0.1 s step from the reset's 0
    assert a.tolist() == pytest.approx([0.5, 1.0, 0.5, 0.0, -0.5], abs=1e-5)
    # behind the layer: with no room ahead the layer brakes at once, whatever the limiter passed
    env = TransformedEnv(make_env("ring", batch_size=1, seed=0, init_spacing_rows=(5.5,)),
                         Compose(SafetyLayer(s_min=5.0, s_max=None), JerkLimit(max_jerk=1.0)))
    td = env.rollout(3, lambda td: td.set("action", torch.full((1, 1), 3.0)))
    assert float(td["next", "cav", "accel"][0, -1]) < -0.5
    x = torch.tensor([[2.0]], requires_grad=True)  # gradients pass inside the band
    lim = TransformedEnv(make_env("ring", batch_size=1, seed=0), JerkLimit(max_jerk=100.0))
    lim.base_env.differentiable = True
    out = lim.step(lim.reset().set("action", x * 1.0))["next", "cav", "accel"]
    out.sum().backward()
    assert x.grad is not None and float(x.grad) > 0
    for bad in ({"max_jerk": 0.0}, {"max_jerk": 1.0, "dt": -0.1}):
        with pytest.raises(ValueError, match=next(iter(k for k in bad if k != "max_jerk" or bad[k] <= 0))):
            JerkLimit(**bad)


# ----------------------------------------------------------------------------- PID multiplier
def test_pid_without_gains_is_dual_ascent():
    pid = LagrangeMultiplier(init=1.0, lr=0.3, cost_limit=0.1, method="pid")
    dual = LagrangeMultiplier(init=1.0, lr=0.3, cost_limit=0.1)
    for c in (0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.9):
        assert pid.update(c) == pytest.approx(dual.update(c))


def test_pid_proportional_term_reacts_at_once_and_releases_at_once():
    lam = LagrangeMultiplier(init=1.0, lr=0.1, cost_limit=0.1, method="pid", kp=4.0)
    # violated: integral 1 + 0.1*0.4 = 1.04, plus kp * 0.4
    assert lam.update(0.5) == pytest.approx(1.04 + 1.6)
    # met again: the proportional part goes negative at once (integral 1.04 - 0.01)
    assert lam.update(0.0) == pytest.approx(1.03 - 0.4)
    # an integral-only multiplier would still sit above 1 here
    assert float(lam) < 1.0


def test_pid_derivative_only_on_a_rising_cost_and_clipped():
    lam = LagrangeMultiplier(init=0.0, lr=0.1, cost_limit=0.0, method="pid", kd=10.0, max_value=5.0)
    assert lam.update(0.1) == pytest.approx(0.01)  # first update: no derivative
    assert lam.update(0.3) == pytest.approx(0.04 + 2.0)  # rising by 0.2
    assert lam.update(0.2) == pytest.approx(0.06)  # falling: no derivative
    assert lam.update(1.0) == pytest.approx(5.0)  # clipped at max_value


def test_pid_state_survives_state_dict_and_old_checkpoints_load():
    lam = LagrangeMultiplier(init=1.0, lr=0.5, cost_limit=0.0, method="pid", kp=1.0)
    lam.update(0.4)
    lam.update(0.6)
    other = LagrangeMultiplier(init=0.0, lr=0.5, cost_limit=0.0, method="pid", kp=1.0)
    other.load_state_dict(lam.state_dict())
    assert other.update(0.6) == pytest.approx(lam.update(0.6))
    old = {"value": torch.tensor(2.5, dtype=torch.float64)}  # written before the PID state existed
    fresh = LagrangeMultiplier(method="pid")
    fresh.load_state_dict(old)
    assert float(fresh) == 2.5 and float(fresh.pid_integral) == 2.5
    with pytest.raises(ValueError, match="kp="):
        LagrangeMultiplier(method="pid", kp=-1.0)
    with pytest.raises(ValueError, match="method="):
        LagrangeMultiplier(method="pi")


# ----------------------------------------------------------------------------- training distribution
def test_random_start_spacing_and_fixed_rows():
    env = make_env("ring", batch_size=64, seed=0, init_spacing_range=(8.0, 40.0))
    gaps = env.reset()["cav", "gap"].squeeze(-1)
    assert gaps.min() >= 8.0 - 1e-4 and gaps.max() <= 40.0 + 1e-4 and gaps.std() > 5.0
    env = make_env("ring", batch_size=4, seed=0, init_spacing_rows=[8.0, 15.0])
    assert env.reset()["cav", "gap"].squeeze(-1).tolist() == pytest.approx([8.0, 15.0, 8.0, 15.0])
    with pytest.raises(ValueError, match="init_spacing_range"):
        make_env("ring", init_spacing_range=(80.0, 90.0))  # beyond the even spacing of the ring
    with pytest.raises(ValueError, match="init_spacing_rows"):
        make_env("ring", init_spacing_rows=[0.0])


def test_random_ramps_hold_and_ramp_within_range():
    prof = make_profile("random_ramps", v_low=2.0, v_high=20.0, rate_min=1.0, rate_max=1.0, v_init=10.0)
    p = prof.sample(8, torch.Generator().manual_seed(0))
    t = torch.arange(0, 500, 0.1)
    v = torch.stack([prof.speed(torch.full((8,), float(x)), p) for x in t], 1)
    assert (v[:, 0] == 10.0).all()
    assert v.min() >= 2.0 - 1e-4 and v.max() <= 20.0 + 1e-4
    dv = (v[:, 1:] - v[:, :-1]).abs() / 0.1
    assert dv.max() <= 1.0 + 1e-2  # the ramp rate
    assert (dv < 1e-4).float().mean() > 0.3  # holds
    assert v.std(1).min() > 1.0  # every episode moves
    with pytest.raises(ValueError, match="v_low"):
        make_profile("random_ramps", v_low=10.0, v_high=5.0)


def test_random_stop_and_go_stops_and_drives_off_within_its_ranges():
    prof = make_profile("random_stop_and_go", v_low=8.0, v_high=16.0, hold_min=6.0, hold_max=15.0, stop_min=3.0,
                        stop_max=10.0, rate_min=1.5, rate_max=2.5, horizon=200.0)
    p = prof.sample(8, torch.Generator().manual_seed(0))
    v = torch.stack([prof.speed(torch.full((8,), float(x)), p) for x in torch.arange(0, 200, 0.1)], 1)
    assert float(v.min()) == 0.0 and float(v.max()) <= 16.0 + 1e-4
    assert bool((v[:, 0] >= 8.0).all())  # it starts at a cruising speed
    rate = (v[:, 1:] - v[:, :-1]).abs() / 0.1
    assert float(rate.max()) <= 2.5 + 1e-3
    standing = v < 1e-6
    starts = standing[:, 1:] & ~standing[:, :-1]
    assert bool((starts.sum(1) >= 5).all())  # several stops in 200 s, each episode its own
    assert float(v.std(0).max()) > 3.0
    for bad, said in (({"v_low": 0.0}, "v_low=0.0, v_high=16.0 are invalid"),
                      ({"stop_min": 5.0, "stop_max": 4.0}, "stop_min=5.0, stop_max=4.0 are invalid")):
        with pytest.raises(ValueError, match=said):
            make_profile("random_stop_and_go", **bad)


# ----------------------------------------------------------------------------- evaluation without the layer
SHORT = ["eval.episodes=2", "eval.episode_seconds=30.0", "eval.warmup_seconds=5.0", "eval.settle_seconds=3.0",
         "eval.profiles=[random_steps,emergency_brake]", "eval.profile_kwargs.emergency_brake.start=10.0"]


class FullThrottle(torch.nn.Module):
    def forward(self, speed):
        return torch.full_like(speed, 3.0)


def _throttle(env):
    from tensordict.nn import TensorDictModule

    return TensorDictModule(FullThrottle(), in_keys=[("cav", "speed")], out_keys=["action"])


def test_evaluation_runs_the_policy_with_and_without_the_layer():
    cfg = compose(["experiment=ring_lagrangian_ppo_scratch"] + SHORT)
    rep, traces = evaluate(cfg, policy_factory=_throttle)
    # with the layer: safe, but the layer does all the braking
    assert rep["overall"]["collisions"] == 0
    assert rep["acceptance"]["intervention_rate_max"] > 0.3 and not rep["acceptance"]["intervention_within_bar"]
    assert rep["profiles"]["random_steps"]["metrics"]["mean_abs_delta"]["mean"] > 0.5
    # without it, the same policy collides (from every start) and the acceptance says so
    nl = rep["without_layer"]["random_steps"]
    assert list(nl) == ["standard (73.4 m)", "8 m", "15 m"]
    assert all(r["collisions"] == 2 for r in nl.values())
    assert not rep["acceptance"]["no_layer_zero_collisions"] and not rep["acceptance"]["pass"]
    # "who brakes": the command is +3 throughout, the executed acceleration is not
    tr = traces["random_steps"]
    moving = tr.valid & (tr.cav_speed > 0.5)  # away from v = 0, where the env clamps the speed
    assert ((tr.raw_accel - 3.0).abs() < 1e-3)[moving].all() and (tr.cav_accel[moving] < 0).any()
    assert "random_steps_without_layer" in traces and "random_steps_without_layer_close" in traces


def test_evaluation_leaves_the_training_only_jerk_penalty_out():
    from mixed_traffic.evaluation.harness import run_profile

    chain = "transforms.chain=[non_negative_reward,safety_layer,intervention_cost,jerk_penalty]"
    cfg = compose(["experiment=ring_lagrangian_ppo_scratch", chain] + SHORT)
    m1, _ = run_profile(cfg, None, "random_steps", episodes=2, seed=0, policy_factory=_throttle)
    cfg2 = compose(["experiment=ring_lagrangian_ppo_scratch", chain, "transforms.jerk_penalty.weight=50.0"] + SHORT)
    m2, _ = run_profile(cfg2, None, "random_steps", episodes=2, seed=0, policy_factory=_throttle)
    assert torch.equal(m1["return"], m2["return"])


def test_evaluation_without_layer_passes_for_a_safe_controller():
    cfg = compose(["experiment=ring_lagrangian_ppo_scratch"] + SHORT)
    rep, _ = evaluate(cfg, policy_factory=lambda env: make_classic_policy("idm", env, s0=6.0))
    assert rep["acceptance"]["no_layer_zero_collisions"]
    starts = rep["without_layer"]["emergency_brake"]
    assert starts["8 m"]["metrics"]["min_gap"]["min"] <= 8.0 + 1e-3  # it did start there
    assert starts["15 m"]["metrics"]["min_gap"]["min"] <= 15.0 + 1e-3
    assert rep["overall"]["collisions"] == 0


@pytest.mark.parametrize("override, field", [
    ("loss.lambda_method=pidd", "loss.lambda_method"),
    ("loss.lambda_kp=-1", "loss.lambda_kp"),
    ("transforms.intervention_cost.coef=0", "transforms.intervention_cost.coef"),
    ("transforms.intervention_cost.mode=sometimes", "transforms.intervention_cost.mode"),
    ("transforms.intervention_cost.direction=down", "transforms.intervention_cost.direction"),
    ("transforms.residual.weight=-0.5", "transforms.residual.weight"),
    ("eval.intervention_bar=2", "eval.intervention_bar"),
    ("transforms.residual.params.s9=6.0", "transforms.residual.params.s9"),
    ("transforms.residual.params.s0=abc", "transforms.residual.params.s0"),
    ("transforms.residual.catch_up.gaps=[30,20]", "transforms.residual.catch_up.gaps"),
    ("transforms.residual.catch_up.dv=0", "transforms.residual.catch_up.dv"),
    ("transforms.residual.catch_up.horizon=-1", "transforms.residual.catch_up.horizon"),
    ("transforms.residual.catch_up.when=train", "transforms.residual.catch_up.when"),
    ("transforms.residual.stand_arrival.stand_gap=0", "transforms.residual.stand_arrival.stand_gap"),
    ("transforms.residual.stand_arrival.stand_gap=5.2", "transforms.residual.stand_arrival.stand_gap"),  # no stop_gap
    ("transforms.residual.stand_arrival.speeds=[12,9]", "transforms.residual.stand_arrival.speeds"),
    ("transforms.residual.stand_arrival.slack=0", "transforms.residual.stand_arrival.slack"),
])
def test_new_config_fields_are_validated(override, field):
    from mixed_traffic.validation import validate_config

    with pytest.raises(ValueError, match=field.replace(".", r"\.")):
        validate_config(compose(["experiment=ring_lagrangian_ppo", override]))


def test_residual_base_parameters_change_the_base_controller():
    """``transforms.residual.params.s0=6``: with a zero residual the CAV drives IDM(s0=6), which
    stops farther behind a stopped leader than the humans' IDM (s0 2.5 m)."""
    from mixed_traffic.training.builders import make_transformed_env

    gaps = {}
    for over in ([], ["transforms.residual.params.s0=6.0"]):
        cfg = compose(["experiment=ring_lagrangian_ppo_no_apg", "transforms.chain=[residual_idm]", *over])
        env = make_transformed_env(cfg, num_envs=2, seed=0, profile="emergency_brake",
                                   profile_kwargs={"start": 40.0, "v_cruise": 10.0, "v_low": 0.0})
        td, low = env.reset(), []
        for _ in range(530):  # the head stands still from 43 to 53 s
            td = env.step(td.set("action", torch.zeros(env.action_spec.shape)))["next"]
            low.append(td["cav", "gap"].min())
        gaps[bool(over)] = float(min(low))
    assert gaps[False] < 3.0 and gaps[True] > 5.0, gaps  # 2.40 m and 5.05 m measured


def test_classic_controller_spec_with_parameters():
    from mixed_traffic.evaluation.policies import classic_factory

    env = make_env("ring", batch_size=2, seed=0)
    pol = classic_factory("idm:s0=6;T=0.8")(env)
    assert pol.module.params["s0"] == 6.0 and pol.module.params["T"] == 0.8
    with pytest.raises(ValueError, match="controller"):
        classic_factory("idm:s0")
    with pytest.raises(ValueError, match=r"controller='idm:s9=1': .*\['T', 'a'"):
        classic_factory("idm:s9=1")
    with pytest.raises(ValueError, match=r"controller='idm:gap_max=2': gap_max must be above .* s0 = 2.5 m"):
        classic_factory("idm:gap_max=2")


# ----------------------------------------------------------------------------- one batched evaluation rollout
def test_row_profiles_give_each_row_its_part_across_resets():
    from mixed_traffic.profiles import Constant, RowProfiles, Sine

    prof = RowProfiles((Constant(10.0), Sine(v_star=20.0, amplitude=0.0), Constant(5.0)))
    env = make_env("ring", batch_size=6, seed=0)
    env.set_profile(prof)
    env.reset()
    head = env.profile.speed(torch.zeros(6), env.profile_params)
    assert head.tolist() == [10.0, 20.0, 5.0, 10.0, 20.0, 5.0]
    # a partial reset of rows 2 and 4 keeps their parts
    from tensordict import TensorDict
    env.reset(TensorDict({"_reset": torch.tensor([False, False, True, False, True, False])[:, None]}, [6]))
    assert env.profile.speed(torch.zeros(6), env.profile_params).tolist() == head.tolist()
    with pytest.raises(ValueError, match="parts"):
        RowProfiles(())


def test_safety_layer_active_rows_leave_the_other_rows_raw():
    from torchrl.envs import TransformedEnv

    from transforms import SafetyLayer

    layer = SafetyLayer(s_min=5.0, s_max=40.0)
    env = TransformedEnv(make_env("ring", batch_size=4, seed=0, init_spacing=8.0), layer)
    layer.set_active_rows(torch.tensor([True, False, True, False]))
    td = env.rollout(300, lambda td: td.set("action", torch.full((4, 1), 3.0)), break_when_any_done=False)
    hit = td["next", "collision"].any(1).squeeze(-1)
    assert hit.tolist() == [False, True, False, True]
    clipped = td["next", "safety", "clipped"].any(1).squeeze(-1)
    assert clipped.tolist() == [True, False, True, False]
    layer.set_active_rows(torch.ones(3, dtype=torch.bool))
    with pytest.raises(ValueError, match="active_rows"):
        env.rollout(2, lambda td: td.set("action", torch.zeros(4, 1)))


def test_batched_evaluation_matches_one_profile_at_a_time():
    """The one-rollout evaluation runs the same episodes as separate runs per profile and start."""
    from mixed_traffic.evaluation.harness import LAYER_FREE_WITHOUT, run_batched, run_profile

    cfg = compose(["experiment=ring_lagrangian_ppo_scratch", "eval.hdv_param_noise=0.0",
                   "eval.profiles=[emergency_brake,sine]"] + SHORT[:4] + ["eval.profile_kwargs.emergency_brake.start=10.0"])
    idm = lambda env: make_classic_policy("idm", env, s0=6.0)  # noqa: E731
    with_layer, free = run_batched(cfg, None, ["emergency_brake", "sine"], episodes=2, seed=0, policy_factory=idm,
                                   layer_free=True)
    for prof in ("emergency_brake", "sine"):
        m, _ = run_profile(cfg, None, prof, episodes=2, seed=0, policy_factory=idm)
        assert torch.allclose(with_layer[prof][0]["return"], m["return"], atol=1e-3)
        m8, _ = run_profile(cfg, None, prof, episodes=2, seed=0, policy_factory=idm, without=LAYER_FREE_WITHOUT,
                            init_spacing_rows=[8.0])
        assert torch.allclose(free[prof]["8 m"][0]["return"], m8["return"], atol=1e-3)
        assert torch.allclose(free[prof]["8 m"][0]["min_gap"], m8["min_gap"], atol=1e-4)


def test_a_one_profile_runner_reports_the_same_layer_free_runs():
    """An evaluation run one profile at a time (a ``runner``: the SUMO evaluation's path, here on torch) runs the
    policy without its layer from the same starts as the batched one, with the same figures and bars."""
    from mixed_traffic.evaluation.sumo import evaluate_on_torch_seeds

    cfg = compose(["experiment=ring_lagrangian_ppo_scratch"] + SHORT)
    kw = dict(policy_factory=_throttle, profiles=["random_steps"], episodes=2, seed=0)
    batched, _ = evaluate(cfg, **kw)
    one, traces = evaluate_on_torch_seeds(cfg, **kw)
    free, ref = one["without_layer"]["random_steps"], batched["without_layer"]["random_steps"]
    assert list(free) == list(ref) == ["standard (73.4 m)", "8 m", "15 m"]
    for label, entry in ref.items():
        assert free[label]["collisions"] == entry["collisions"] == 2  # full throttle collides without the layer
        assert free[label]["per_episode"]["min_gap"] == pytest.approx(entry["per_episode"]["min_gap"], abs=1e-4)
        assert free[label]["per_episode"]["return"] == pytest.approx(entry["per_episode"]["return"], rel=1e-5)
    assert one["overall"]["collisions"] == 0  # with the layer
    for key in ("no_layer_zero_collisions", "no_layer_min_gap_after_warmup", "no_layer_gap_within_bounds", "pass"):
        assert one["acceptance"][key] == pytest.approx(batched["acceptance"][key]), key
    assert not one["acceptance"]["no_layer_zero_collisions"] and not one["acceptance"]["pass"]
    assert "random_steps_without_layer" in traces and "random_steps_without_layer_close" in traces
    # a runner that cannot drop the layer is refused, not trusted to have done it
    from mixed_traffic.evaluation.harness import run_profile

    def swallowing(cfg_, policy_, profile, *, episodes, seed, policy_factory=None, **_):
        return run_profile(cfg_, policy_, profile, episodes=episodes, seed=seed, policy_factory=policy_factory)

    with pytest.raises(TypeError, match="runner must take the keyword arguments without= and init_spacing="):
        evaluate(cfg, runner=swallowing, **kw)
    cfg.eval.without_layer = False
    assert "without_layer" not in evaluate(cfg, runner=swallowing, **kw)[0]


def test_jerk_by_time_splits_the_reports_jerk_into_windows_that_add_up(tmp_path, benchmark_script):
    """benchmarks/ring_jerk_by_time.py: the windows' shares add up to the report's whole-episode mean |jerk|
    (first step not counted), and the mean from a time on is that of those steps alone."""
    from mixed_traffic.evaluation.harness import episode_metrics, rollout_for_metrics

    mod = benchmark_script("ring_jerk_by_time")

    env = make_env("ring", batch_size=3, seed=0, episode_seconds=8.0)
    gen = torch.Generator().manual_seed(0)
    td = rollout_for_metrics(env, lambda td: td.set("action", 6 * torch.rand(3, 1, generator=gen) - 3), 80)
    m, trace = episode_metrics(td, dt=0.1, s_min=5.0, s_max=40.0, warmup=0.0, settle=1.0)
    out = mod.jerk_shares(trace, 0.1, edges=(0.0, 2.0, 5.0, float("inf")), from_seconds=5.0)
    assert sum(out["shares"]) == pytest.approx(out["whole"], rel=1e-5)
    assert out["whole"] == pytest.approx(float(m["mean_abs_jerk"].mean()), rel=1e-5)
    a = trace.cav_accel
    late = (a[:, 1:] - a[:, :-1]).abs()[:, trace.time[0, 1:] >= 5.0] / 0.1
    assert out["after"] == pytest.approx(float(late.mean()), rel=1e-5)
    assert min(out["shares"]) > 0.0  # random commands: every window has jerk
    png = Path(tmp_path) / "start.png"
    mod.plot_starts({"random_steps": {"policy": trace, "idm": trace}}, png, seconds=5.0, engage_seconds=2.0)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _tiny_scratch_run(run):
    """A ring run trained for 32 frames (experiment=ring_lagrangian_ppo_scratch): a checkpoint the benchmark
    scripts load, in seconds."""
    from mixed_traffic.training import train

    train(compose(["experiment=ring_lagrangian_ppo_scratch", "trainer.total_frames=32", "trainer.num_envs=8",
                   "trainer.rollout_len=4", "trainer.epochs=1", "trainer.minibatch_size=16",
                   "trainer.progress=false", "env.episode_seconds=1.0"]), out_dir=run)
    return run


def test_generalization_set_evaluates_a_deployed_variant_without_retraining(tmp_path, benchmark_script):
    """benchmarks/ring_generalization.py --set transforms.KEY=VALUE: the run's deployed chain with that setting (here
    the safety layer without its s_max rule, which holds a long start's gap), recorded in generalization.json and
    named in the tables, which refuse to mix it with the run as trained; a key outside transforms, a typo and a value
    out of range fail before anything runs, naming the item."""
    import json

    from mixed_traffic.evaluation.results import generalization_table

    run = _tiny_scratch_run(tmp_path / "run")
    mod = benchmark_script("ring_generalization")
    common = ["--checkpoint", str(run), "--episodes", "1", "--seconds", "20", "--cases", "fast_steps", "--baselines", "idm"]
    plain = mod.main([*common, "--out", str(tmp_path / "plain")])["fast_steps"]
    varied = mod.main([*common, "--set", "transforms.safety_layer.deployed_s_max=false", "--out", str(tmp_path / "v")])
    assert plain["policy"]["intervention_rate"] > 0.0 == varied["fast_steps"]["policy"]["intervention_rate"]
    assert varied["fast_steps"]["idm"] == plain["idm"]  # a classical controller drives without the run's transforms
    g = json.loads((tmp_path / "v" / "generalization.json").read_text())
    assert g["set"] == ["transforms.safety_layer.deployed_s_max=false"]
    assert "deployed with transforms.safety_layer.deployed_s_max=false" in generalization_table([tmp_path / "v"])
    with pytest.raises(ValueError, match="set .* differs"):
        generalization_table([tmp_path / "plain", tmp_path / "v"])
    for bad, said in ((["env.ring_length=300"], "allowed: transforms.KEY=VALUE"),
                      (["transforms.safety_layer.s_mni=4"], "transforms.safety_layer.s_mni: not a setting"),
                      (["transforms.safety_layer.s_min=-1"], "--set transforms.safety_layer.s_min")):
        with pytest.raises(SystemExit, match=said):
            mod.main([*common, "--set", *bad, "--out", str(tmp_path / "bad")])
    assert not (tmp_path / "bad").exists()


def test_policy_on_sumo_set_deploys_a_variant_on_both_backends(tmp_path, benchmark_script):
    """benchmarks/ring_policy_on_sumo.py --set: the run's transforms with that setting on SUMO and on torch, recorded in
    both reports; a typo or a value out of range stops the script before SUMO starts, naming the item."""
    import json

    run = _tiny_scratch_run(tmp_path / "run")
    mod = benchmark_script("ring_policy_on_sumo")
    common = ["--checkpoint", str(run), "--episodes", "1", "--seconds", "3", "--profiles", "random_steps",
              "--workers", "0"]
    item = "transforms.safety_layer.deployed_s_max=false"
    reports = mod.main([*common, "--set", item, "--out", str(tmp_path / "v")])
    assert reports["sumo"]["set"] == reports["torch"]["set"] == [item]
    for rep in reports.values():  # the policy without its layer too, from the three starts, on both backends
        assert len(rep["without_layer"]["random_steps"]) == 3 and "no_layer_zero_collisions" in rep["acceptance"]
    only = mod.main([*common, "--with-layer-only", "--no-torch", "--out", str(tmp_path / "only")])["sumo"]
    assert "without_layer" not in only and "no_layer_zero_collisions" not in only["acceptance"]
    assert json.loads((tmp_path / "v" / "report.json").read_text())["set"] == [item]
    assert f"with {item}" in (tmp_path / "v" / "comparison.md").read_text()
    for bad, said in ((["transforms.safety_layer.s_mni=4"], "transforms.safety_layer.s_mni: not a setting"),
                      (["transforms.safety_layer.s_min=-1"], "--set transforms.safety_layer.s_min")):
        with pytest.raises(SystemExit, match=said):
            mod.main([*common, "--set", *bad, "--out", str(tmp_path / "bad")])
    assert not (tmp_path / "bad").exists()


def test_generalization_runs_the_classical_baselines_behind_the_runs_layer(tmp_path, benchmark_script):
    """benchmarks/ring_generalization.py --baselines-with-layer: each baseline runs again behind the
    trained run's safety layer on the same episodes; the layer's work shows in its row (IDM-as-CAV
    starts 73.4 m behind a 20-28 m/s head, beyond s_max) and not in the layer-free one."""
    import json

    run = _tiny_scratch_run(tmp_path / "run")
    mod = benchmark_script("ring_generalization")
    out = tmp_path / "gen"
    res = mod.main(["--checkpoint", str(run), "--episodes", "1", "--seconds", "20", "--cases", "fast_steps",
                    "--baselines", "idm", "--baselines-with-layer", "--plot", "--jerk-by-time", "5", "--out", str(out)])
    rows = res["fast_steps"]
    # --jerk-by-time: the first 5 s and the rest, adding up to each controller's whole-episode jerk
    by_time = rows["jerk_by_time"]
    assert by_time["edges"][:2] == [0.0, 5.0] and sum(by_time["idm, no layer"]) == pytest.approx(rows["idm"]["jerk"], rel=1e-4)
    assert "Mean |jerk| (m/s3) by the time" in (out / "generalization.md").read_text()
    assert rows["seconds"] == 20.0  # each case records its episode length (eudc_highway runs 330 s)
    assert rows["idm"]["intervention_rate"] == 0.0 and rows["idm + layer"]["intervention_rate"] > 0.0
    assert rows["idm + layer"]["max_head_gap"] < rows["idm"]["max_head_gap"]
    assert "idm + layer" in json.loads((out / "generalization.json").read_text())["results"]["fast_steps"]
    assert "| fast_steps | IDM, + layer |" in (out / "generalization.md").read_text()
    assert (out / "fast_steps.png").stat().st_size > 10_000  # --plot: episode 0 of the case
    with pytest.raises(SystemExit, match=r"brake_from_30.*allowed: .*brake_from_25"):  # before any rollout
        mod.main(["--checkpoint", str(run), "--cases", "brake_from_30", "--out", str(tmp_path / "bad")])
    # a baseline the run cannot have (this run trains no residual) or a misspelt one: refused before any rollout
    with pytest.raises(SystemExit, match=r"--baselines: 'zero_residual': .* lacks residual_idm"):
        mod.main(["--checkpoint", str(run), "--cases", "fast_steps", "--baselines", "idm", "zero_residual",
                  "--out", str(tmp_path / "bad")])
    with pytest.raises(SystemExit, match=r"--baselines: 'idmm'"):
        mod.main(["--checkpoint", str(run), "--cases", "fast_steps", "--baselines", "idmm", "--out", str(tmp_path / "bad")])
    assert not (tmp_path / "bad").exists()


def test_residual_base_factory_drives_the_runs_base_alone_and_refuses_a_run_without_one():
    """``--baselines base`` of benchmarks/ring_generalization.py: the run's residual base with the residual
    at zero (here the scheduled base, which the generalization table compares the policy with); a run
    whose chain has no residual fails naming the missing transform instead of driving a default IDM."""
    from mixed_traffic import make_env
    from mixed_traffic.controllers.classic import SpeedScheduledCAV
    from mixed_traffic.evaluation.policies import residual_base_factory

    env = make_env("ring", batch_size=2, seed=0)
    base = residual_base_factory(compose(["experiment=ring_lagrangian_ppo_scheduled"]))(env)
    assert isinstance(base.module, SpeedScheduledCAV)
    assert not bool(env.rollout(100, base)["next", "collision"].any())
    with pytest.raises(ValueError, match="residual_idm"):
        residual_base_factory(compose(["experiment=ring_lagrangian_ppo_scratch"]))


def test_zero_residual_drives_the_deployed_chain_with_the_learned_part_at_zero():
    """``--baselines zero_residual`` (the scorecard's yardstick of what the learned residual adds): the run's own
    deployed chain with a residual of zero, so the drive-off cap and the join act on it as on the policy. With the
    cap and the join off it is the base's laws alone (``base``) to the float; with them on it differs from the base
    just where they act, behind a head that brakes to a standstill and drives off, from the long start. A run
    without a residual fails naming the missing transform."""
    from mixed_traffic.evaluation.policies import residual_base_factory, zero_residual_factory

    over = ["experiment=ring_lagrangian_ppo_follow", "trainer.progress=false", "eval.episodes=2",
            "eval.episode_seconds=60.0", "eval.warmup_seconds=5.0", "eval.settle_seconds=3.0",
            "eval.profiles=[emergency_brake]", "eval.profile_kwargs.emergency_brake.start=25.0",
            "eval.profile_kwargs.emergency_brake.v_cruise=18.0", "eval.profile_kwargs.emergency_brake.v_low=0.0"]

    def jerks(extra):
        cfg = compose([*over, *extra])
        zero = compose([*over, *extra, "transforms.chain=[onboard_accel,non_negative_reward,residual_idm]"])
        base = compose([*over, *extra, "transforms.chain=[non_negative_reward]"])
        z, _ = evaluate(zero, policy_factory=zero_residual_factory(cfg))
        b, _ = evaluate(base, policy_factory=residual_base_factory(cfg))
        return [r["profiles"]["emergency_brake"]["per_episode"]["mean_abs_jerk"] for r in (z, b)]

    z, b = jerks(["transforms.residual.join.base=null", "transforms.residual.drive_off.gain=null"])
    assert z == pytest.approx(b, rel=1e-3)  # float32 through the chain: 6e-5 apart
    z, b = jerks([])
    assert all(abs(x / y - 1) > 0.02 for x, y in zip(z, b)), (z, b)  # the join closes the long start, the cap drives off
    with pytest.raises(ValueError, match="lacks residual_idm"):
        zero_residual_factory(compose(["experiment=ring_lagrangian_ppo_scratch"]))


def test_mt_eval_controller_zero_residual_evaluates_the_experiments_deployed_classical_part(tmp_path):
    """``mt-eval experiment=ring_lagrangian_ppo_follow controller=zero_residual``: the experiment's own chain (the
    layer, the cap, the join) with the learned residual at zero, on the episodes a checkpoint of the experiment is
    evaluated on, with and without the layer; no checkpoint is needed, the residual being zero. An experiment
    without a residual fails naming ``controller`` before any rollout."""
    from mixed_traffic.evaluation import evaluate_and_report
    from mixed_traffic.evaluation.policies import zero_residual_factory
    from mixed_traffic.validation import ConfigError

    over = ["experiment=ring_lagrangian_ppo_follow", "trainer.progress=false", *SHORT]
    rep = evaluate_and_report(compose([*over, "controller=zero_residual"]), tmp_path / "zero")
    assert rep["policy"] == "zero_residual" and "residual_idm" in rep["transforms"] and "without_layer" in rep
    ref, _ = evaluate(compose(over), policy_factory=zero_residual_factory(compose(over)))
    for prof in ("random_steps", "emergency_brake"):
        assert rep["profiles"][prof]["per_episode"]["mean_abs_jerk"] == ref["profiles"][prof]["per_episode"]["mean_abs_jerk"]
    with pytest.raises(ConfigError, match=r"controller.*lacks residual_idm"):
        evaluate_and_report(compose(["experiment=ring_lagrangian_ppo_scratch", "controller=zero_residual", *SHORT]),
                            tmp_path / "none")
    assert not (tmp_path / "none").exists()


def test_the_report_judges_the_jerk_and_return_bars_against_idm_as_cav_on_the_same_episodes(tmp_path):
    """``eval.reference: idm`` (the ring's Lagrangian PPO experiments; what ``mt-main`` prints): a checkpoint's report
    also runs IDM driving the CAV, under the task's reward alone, on the same episodes, and compares the policy's jerk
    and return with it on every profile, with the layer and without it; the acceptance's ``pass`` then needs "jerk at
    most IDM-as-CAV's" and "return at least its". The reference equals ``mt-eval controller=idm transforms=reward``
    on the same episodes. A bad reference fails naming ``eval.reference`` before anything runs or is written."""
    from mixed_traffic.evaluation import evaluate_and_report
    from mixed_traffic.evaluation.policies import checkpoint_config
    from mixed_traffic.validation import ConfigError

    run = _tiny_scratch_run(tmp_path / "run")
    assert compose(["experiment=ring_lagrangian_ppo_follow"]).eval.reference == "idm"  # mt-main's default
    assert checkpoint_config(run)[0].eval.reference == "idm"  # and the run's own, kept by mt-eval checkpoint=...
    cfg = compose(["trainer.progress=false", *SHORT, "eval.close_starts=[]"])
    rep = evaluate_and_report(cfg, tmp_path / "eval", checkpoint=run)
    ref = rep["reference"]
    assert ref["controller"] == "idm-as-CAV" and list(ref["profiles"]) == ["random_steps", "emergency_brake"]
    idm_cfg = checkpoint_config(run)[0]
    idm_cfg.eval = cfg.eval
    idm_cfg.transforms.chain = ["non_negative_reward"]
    idm = evaluate_and_report(idm_cfg, tmp_path / "idm", controller="idm")
    rows = []
    for prof, e in ref["profiles"].items():
        m = idm["profiles"][prof]["metrics"]
        assert e["reference"]["jerk"] == pytest.approx(m["mean_abs_jerk"]["mean"], rel=1e-6)
        assert e["reference"]["return"] == pytest.approx(m["return"]["mean"], rel=1e-6)
        assert set(e) == {"reference", "with the layer", "without the layer"}
        own = rep["profiles"][prof]["metrics"]
        assert e["with the layer"]["jerk_pct"] == pytest.approx(
            100 * (own["mean_abs_jerk"]["mean"] / m["mean_abs_jerk"]["mean"] - 1), abs=1e-6)
        assert e["with the layer"]["return_diff"] == pytest.approx(own["return"]["mean"] - m["return"]["mean"], abs=1e-3)
        rows += [e["with the layer"], e["without the layer"]]
    acc = rep["acceptance"]
    assert acc["jerk_within_reference"] == all(r["jerk_pct"] <= 0 for r in rows)
    assert acc["return_within_reference"] == all(r["return_diff"] >= 0 for r in rows)
    assert acc["pass"] == all(v for k, v in acc.items() if isinstance(v, bool) and k != "pass")
    assert list(acc)[-1] == "pass"
    # the reference ran in a forked second process beside the policy's rollout (eval.parallel_reference, the
    # default); run after it in this process instead, it gives the same report to the bit
    from mixed_traffic.evaluation.background import can_fork

    assert can_fork()
    seq = evaluate_and_report(compose(["trainer.progress=false", *SHORT, "eval.close_starts=[]",
                                       "eval.parallel_reference=false"]), tmp_path / "seq", checkpoint=run)
    assert seq["reference"] == ref and seq["profiles"] == rep["profiles"]
    md = (tmp_path / "eval" / "report.md").read_text()
    assert "Against idm-as-CAV on the same episodes" in md and "| without the layer: jerk − its |" in md
    for bad in ("nonsense", "idm:s0"):
        with pytest.raises(ConfigError, match=rf"eval.reference: '{bad}' is not a classical controller; allowed: idm,"):
            evaluate_and_report(compose([*SHORT, f"eval.reference={bad}"]), tmp_path / "bad", checkpoint=run)
    assert not (tmp_path / "bad").exists()


def test_mt_eval_controller_base_is_the_policy_with_a_zero_residual(tmp_path):
    """``mt-eval experiment=ring_lagrangian_ppo_band controller=base``: the experiment's scheduled base drives
    the CAV alone, on the episodes a checkpoint of the experiment is evaluated on, with and without the
    layer. It is what the learned residual is measured against: the report equals, episode by episode, the
    experiment's own chain driven by a residual of zero. An experiment without a residual fails naming
    ``controller``, before any rollout."""
    from tensordict.nn import TensorDictModule

    from mixed_traffic.evaluation import evaluate_and_report
    from mixed_traffic.validation import ConfigError

    over = ["experiment=ring_lagrangian_ppo_band", "trainer.progress=false", *SHORT]
    rep = evaluate_and_report(compose([*over, "controller=base"]), tmp_path / "base")
    assert rep["policy"] == "base-as-CAV" and "residual_idm" not in rep["transforms"]
    assert list(rep["without_layer"]["emergency_brake"]) == ["standard (73.4 m)", "8 m", "15 m"]

    def zero_residual(env):
        return TensorDictModule(lambda v: torch.zeros_like(v), in_keys=[("cav", "speed")], out_keys=["action"])

    ref, _ = evaluate(compose(over), policy_factory=zero_residual)
    for prof in ("random_steps", "emergency_brake"):
        for k in ("return", "mean_abs_jerk", "min_gap", "max_head_gap"):
            assert rep["profiles"][prof]["per_episode"][k] == pytest.approx(ref["profiles"][prof]["per_episode"][k],
                                                                             rel=1e-5), (prof, k)
    with pytest.raises(ConfigError, match=r"controller.*lacks residual_idm"):
        evaluate_and_report(compose(["experiment=ring_lagrangian_ppo_scratch", "controller=base", *SHORT]),
                            tmp_path / "none")
    assert not (tmp_path / "none").exists()


@pytest.mark.slow  # 200-s closed-loop runs of a past experiment's base; its laws' own tests: tests/test_physics.py
def test_base_probe_applies_overrides_and_the_near_closing_gain_keeps_a_stops_margin(benchmark_script):
    """benchmarks/ring_base_probe.py builds the experiment's base with the ``--set`` overrides: on a head
    braking to standstill the closing gain near the leader (``kv_closing_near``) stops the base alone
    further back than the same base without it; a case that does not exist fails naming the allowed ones."""
    mod = benchmark_script("ring_base_probe")
    args = ["--experiment", "ring_lagrangian_ppo_tight", "--cases", "brake_to_standstill", "--episodes", "1"]
    near = mod.main(args)["base"]["brake_to_standstill"]
    off = mod.main(args + ["--set", "transforms.residual.params.kv_closing_near=0.0"])["base"]["brake_to_standstill"]
    assert near["collisions"] == off["collisions"] == 0
    assert near["min_gap"] > off["min_gap"] + 0.5
    with pytest.raises(SystemExit, match="stop_and_go"):
        mod.main(["--experiment", "ring_lagrangian_ppo_tight", "--cases", "brake_to_stop"])


@pytest.mark.slow  # 200-s closed-loop runs of a past experiment's base; its laws' own tests: tests/test_physics.py
def test_band_base_answers_a_fast_heads_steps_inside_the_band_with_less_jerk_than_the_capped_idm(benchmark_script):
    """Above the training range the default's base is the band follower: on a head stepping between 20 and
    28 m/s (one episode of ``fast_steps``, the tuning seed) it keeps the gap inside [5, 40] m without a layer
    and with far less jerk than the previous default's 27-m-capped IDM on the same episode, and below
    IDM-as-CAV's; the steady tracking stays within the 0.2 m/s bar."""
    mod = benchmark_script("ring_base_probe")
    args = ["--cases", "fast_steps", "--episodes", "1"]
    band = mod.main(["--experiment", "ring_lagrangian_ppo_band", *args])
    tight = mod.main(["--experiment", "ring_lagrangian_ppo_tight", *args])["base"]["fast_steps"]
    b, idm = band["base"]["fast_steps"], band["idm_as_cav"]["fast_steps"]
    assert b["collisions"] == 0 and b["min_gap"] >= 5.0 and b["max_head_gap"] <= 40.0
    assert b["jerk"] < 0.75 * tight["jerk"] and b["jerk"] < idm["jerk"]
    assert b["steady_rmse"] <= 0.2


def _brake_from_25(stop_gap, layer: bool, *, steps: int = 300, overrides=()):
    """The band base (``stop_gap``: inside its stopping envelope; ``overrides``: more Hydra overrides) behind
    a head that cruises at 25 m/s, brakes at its bound (3 m/s^2, the CAV's own) to a standstill at 5 s, holds
    10 s and drives off again at its 2 m/s^2 back to 25 m/s, from a 22 m gap; ``steps`` of 0.1 s."""
    from mixed_traffic.evaluation.policies import residual_base_factory
    from mixed_traffic.training.builders import make_transformed_env

    chain = "[safety_layer,residual_idm]" if layer else "[non_negative_reward,residual_idm]"
    cfg = compose(["experiment=ring_lagrangian_ppo_band", f"transforms.residual.stop_gap={stop_gap}",
                   f"transforms.chain={chain}", *overrides])
    env = make_transformed_env(cfg, num_envs=2, seed=0, without=("residual_idm",), profile="emergency_brake",
                               profile_kwargs={"start": 5.0, "v_cruise": 25.0, "v_low": 0.0},
                               v_init=25.0, init_spacing=22.0)
    return env.rollout(steps, residual_base_factory(cfg)(env), break_when_any_done=False)


def test_stopping_envelope_keeps_the_band_base_off_a_head_braking_from_25_ms_to_a_standstill():
    """The guarantee a policy faded out to its base relies on without a layer: the band follower alone hits
    a head braking from 25 m/s at the CAV's own braking bound; inside the stopping envelope of 5 m it stops
    at 5 m or more. With the layer's s_min equal to the envelope's gap, the layer never brakes for it (it
    may still push a CAV that falls back beyond s_max as the head drives off again)."""
    bare = _brake_from_25("null", layer=False)
    assert bool(bare["next", "collision"].any())
    safe = _brake_from_25(5.0, layer=False)
    assert not bool(safe["next", "collision"].any())
    assert float(safe["next", "cav", "gap"].min()) >= 5.0 - 1e-3
    assert float(safe["next", "cav", "speed"].min(-2).values.max()) < 0.5  # it did stop behind the head
    layered = _brake_from_25(5.0, layer=True)
    assert float(layered["next", "safety", "delta"].min()) > -1e-4


def test_stopping_envelope_leaves_everyday_driving_alone():
    """Where no stop-safe bound binds (the training profile's speeds, no hard stop from speed) the enveloped
    base commands exactly what the bare base does: the envelope changes nothing the policy trained over."""
    from mixed_traffic.evaluation.policies import residual_base_factory
    from mixed_traffic.training.builders import make_transformed_env

    accel = {}
    for gap in ("null", "5.0"):
        cfg = compose(["experiment=ring_lagrangian_ppo_band", f"transforms.residual.stop_gap={gap}",
                       "transforms.chain=[non_negative_reward,residual_idm]"])
        env = make_transformed_env(cfg, num_envs=4, seed=0, without=("residual_idm",), profile="random_steps")
        accel[gap] = env.rollout(600, residual_base_factory(cfg)(env), break_when_any_done=False)["next", "cav", "accel"]
    assert torch.equal(accel["null"], accel["5.0"])


def _full_throttle_residual_behind_a_stop(fade: str, deploy: bool = True):
    """``ring_lagrangian_ppo_band_stop`` (``envelope_fade``: ``fade``) without a layer, as deployed (or, with
    ``deploy`` False, as trained), driven by a residual that always asks for its largest acceleration (an
    adversarial policy), behind the head of :func:`_brake_from_25` braking from 18 m/s (inside the residual's
    speeds) to a standstill; 30 s."""
    from mixed_traffic.training.builders import make_transformed_env

    cfg = compose(["experiment=ring_lagrangian_ppo_band_stop", f"transforms.residual.envelope_fade={fade}",
                   "transforms.chain=[non_negative_reward,residual_idm]", "transforms.residual.engage_seconds=0"])
    env = make_transformed_env(cfg, num_envs=2, seed=0, deploy=deploy, profile="emergency_brake",
                               profile_kwargs={"start": 5.0, "v_cruise": 18.0, "v_low": 0.0},
                               v_init=18.0, init_spacing=22.0)
    high = env.action_spec.space.high

    def throttle(td):
        return td.set("action", high.expand(td.batch_size + high.shape[-1:]).clone())

    return env.rollout(300, throttle, break_when_any_done=False)


def test_envelope_fade_keeps_base_plus_residual_inside_the_stopping_envelope_whatever_the_residual():
    """``transforms.residual.envelope_fade`` (``deploy``, the default's; ``always``): the policy itself (base
    plus learned residual, no layer) keeps every gap at or above ``stop_gap`` when the head brakes to a stop,
    even with a residual that always pushes its hardest; without the fade (``off``, or ``deploy`` in the
    training env) that residual takes the gap under it. Away from the envelope the
    residual acts in full (a first command is the base's plus the residual's largest value, 1.5 m/s^2), and
    it is only ever faded, never turned into braking."""
    faded = _full_throttle_residual_behind_a_stop("deploy")
    assert not bool(faded["next", "collision"].any())
    assert float(faded["next", "cav", "gap"].min()) >= 5.0 - 1e-3
    base = faded["next", "residual", "base_action"]
    added = faded["next", "cav", "accel"] - base
    assert float(added[:, 0].max()) == pytest.approx(1.5, abs=1e-4) and float(added.min()) >= -1e-4
    always = _full_throttle_residual_behind_a_stop("always", deploy=False)
    assert torch.equal(always["next", "cav", "accel"], faded["next", "cav", "accel"])
    for bare in (_full_throttle_residual_behind_a_stop("off"), _full_throttle_residual_behind_a_stop("deploy", False)):
        assert float(bare["next", "cav", "gap"].min()) < 4.0


def test_envelope_slack_is_nonnegative_exactly_where_holding_speed_stays_inside_the_layers_rule():
    """``StoppingEnvelope.slack`` (m) is >= 0 exactly where the safety layer's own stopping rule
    (``safe_accel_upper``) allows holding the speed for a step (its bound >= 0), on random states; the base
    with a slack key reports it only while closing on the leader (inf otherwise), beside command and room."""
    from mixed_traffic.controllers.classic import StoppingEnvelope, _EnvelopeRoom
    from transforms.safety_layer import safe_accel_upper

    g = torch.Generator().manual_seed(0)
    gap, v, vl = (torch.rand(4000, generator=g) * 40.0 + 1.0, torch.rand(4000, generator=g) * 30.0,
                  torch.rand(4000, generator=g) * 30.0)
    env_ = StoppingEnvelope(lambda *x: torch.zeros_like(x[1]), stop_gap=5.0, dt=0.1, brake=3.0, leader_brake=3.0,
                            low=-3.0)
    slack = env_.slack(gap, v, vl)
    upper = safe_accel_upper(gap, v, vl, s_min=5.0, dt=0.1, brake=3.0, leader_brake=3.0)
    clear = (slack.abs() > 1e-3) & (upper.abs() > 1e-3)
    assert bool(clear.float().mean() > 0.95) and bool(((slack > 0) == (upper > 0))[clear].all())
    assert bool((slack > 0).any()) and bool((slack < 0).any())
    command, room, closing = _EnvelopeRoom(env_, slack=True)(gap, v, vl)
    assert torch.equal(command, env_(gap, v, vl)) and torch.equal(room, env_.room(gap, v, vl))
    assert torch.equal(closing[v > vl], slack[v > vl]) and bool(torch.isinf(closing[v <= vl]).all())


def test_catch_up_lifts_the_law_only_behind_a_leader_pulling_away_from_a_large_gap():
    """``CatchUp``: the law's command where the gap is at most ``gaps[0]`` or the leader is not faster; lifted
    all the way to ``accel`` from ``gaps[1]`` with the leader ``dv`` faster; halfway at half of both; never
    below the law (a law already above ``accel`` keeps its command). Bad settings name the field."""
    from mixed_traffic.controllers.classic import CatchUp

    law = lambda gap, v, vl: torch.full_like(v, 1.0)  # noqa: E731
    cu = CatchUp(law, accel=3.0, gaps=(20.0, 30.0), dv=4.0)
    gap = torch.tensor([15.0, 35.0, 35.0, 25.0, 35.0])
    v = torch.tensor([10.0, 10.0, 10.0, 10.0, 10.0])
    vl = torch.tensor([16.0, 10.0, 8.0, 12.0, 20.0])
    assert cu(gap, v, vl).tolist() == pytest.approx([1.0, 1.0, 1.0, 1.0 + 0.25 * 2.0, 3.0])
    high = CatchUp(lambda gap, v, vl: torch.full_like(v, 3.5), accel=3.0, gaps=(20.0, 30.0), dv=4.0)
    assert high(gap, v, vl).tolist() == pytest.approx([3.5] * 5)
    with pytest.raises(ValueError, match=r"catch_up\.gaps"):
        CatchUp(law, accel=3.0, gaps=(30.0, 20.0), dv=4.0)
    with pytest.raises(ValueError, match=r"catch_up\.dv"):
        CatchUp(law, accel=3.0, gaps=(20.0, 30.0), dv=0.0)
    with pytest.raises(ValueError, match=r"catch_up\.horizon"):
        CatchUp(law, accel=3.0, gaps=(20.0, 30.0), dv=4.0, horizon=-1.0)


def test_catch_up_horizon_gates_on_the_gap_projected_ahead_at_the_speed_difference():
    """``horizon``: the gate reads ``gap + horizon (v_leader - v)^+``. A 22-m gap with the leader 4 m/s faster
    reads as 30 m two seconds ahead (fully lifted), as 22 m with no horizon (lifted a fifth of the way); a
    closing leader projects nothing (the gap itself, and the speed gate is shut anyway)."""
    from mixed_traffic.controllers.classic import CatchUp

    law = lambda gap, v, vl: torch.zeros_like(v)  # noqa: E731
    gap, v = torch.tensor([22.0, 22.0, 35.0]), torch.tensor([10.0, 10.0, 10.0])
    vl = torch.tensor([14.0, 12.0, 8.0])
    ahead = CatchUp(law, accel=3.0, gaps=(20.0, 30.0), dv=4.0, horizon=2.0)
    now = CatchUp(law, accel=3.0, gaps=(20.0, 30.0), dv=4.0)
    assert ahead(gap, v, vl).tolist() == pytest.approx([3.0, 3.0 * 0.6 * 0.5, 0.0])
    assert now(gap, v, vl).tolist() == pytest.approx([3.0 * 0.2, 3.0 * 0.2 * 0.5, 0.0])


def _drive_off(catch_up: list[str]):
    """The default's base (stop_gap 5 m) behind the head of :func:`_brake_from_25` through its stop and its
    drive-off; 50 s, no layer. Returns the gaps after the first 10 s."""
    return _brake_from_25(5.0, layer=False, steps=500, overrides=catch_up)["next", "cav", "gap"][:, 100:]


def test_catch_up_keeps_the_gap_under_the_bands_edge_as_the_head_drives_off_from_a_standstill():
    """What ``transforms.residual.catch_up`` is for: the default's base falls more than 40 m behind a head
    that drives off from a standstill at 2 m/s^2 (its free-road acceleration stays under the head's); lifted
    toward 3 m/s^2 from 15 m with the leader 4 m/s faster, it stays inside the band, still stopping at 5 m."""
    assert float(_drive_off([]).max()) > 45.0
    lifted = _drive_off(["transforms.residual.catch_up.accel=3.0", "transforms.residual.catch_up.gaps=[15,25]",
                         "transforms.residual.catch_up.dv=4"])
    assert float(lifted.max()) < 40.0
    assert float(lifted.min()) >= 5.0 - 1e-3


def test_catch_up_when_deploy_lifts_the_base_only_where_the_policy_is_evaluated():
    """``catch_up.when: deploy``: the policy trains on the base without the lift (so its weights are those of a
    run without it) and is evaluated and deployed with it, as ``envelope_fade: deploy``; ``always``: both.
    The base driving alone (``residual_base_factory``, the replay benchmark) is the deployed one."""
    from mixed_traffic import make_env
    from mixed_traffic.controllers.classic import CatchUp
    from mixed_traffic.training.builders import make_transformed_env, residual_base
    from mixed_traffic.validation import validate_config
    from transforms import ResidualAction

    def law(when: str, deploy: bool):
        cfg = validate_config(compose(["experiment=ring_lagrangian_ppo_band_stop", "transforms.residual.catch_up.accel=3.0",
                                       f"transforms.residual.catch_up.when={when}"]))
        res = [t for t in make_transformed_env(cfg, num_envs=1, seed=0, deploy=deploy).transform
               if isinstance(t, ResidualAction)][0]
        module = res.base.module
        return getattr(module, "envelope", module).law, cfg

    assert not isinstance(law("deploy", False)[0], CatchUp)
    lifted, cfg = law("deploy", True)
    assert isinstance(lifted, CatchUp)
    assert isinstance(law("always", False)[0], CatchUp) and isinstance(law("always", True)[0], CatchUp)
    alone = residual_base(cfg.transforms.residual, make_env("ring", batch_size=1, seed=0)).module
    assert isinstance(alone.law, CatchUp)


def test_beyond_speed_law_drives_only_above_its_speeds():
    """``transforms.residual.beyond_speed`` takes the base over above its ``v_high`` and leaves it as it was
    below its ``v_low``: the default's band law with the wider band acts above 21 m/s, and below 20 m/s, where
    the policy trains, the base commands exactly what the base without it commands."""
    from mixed_traffic.controllers.classic import make_classic_policy
    from mixed_traffic.training.builders import residual_base
    from mixed_traffic.validation import validate_config

    env = make_env("ring", batch_size=1, seed=0)
    wide_cfg = validate_config(compose(["experiment=ring_lagrangian_ppo_wide_band"]))
    wide = residual_base(wide_cfg.transforms.residual, env, deploy=False).module
    lift = residual_base(validate_config(compose(["experiment=ring_lagrangian_ppo_band_stop_lift"])).transforms.residual,
                         env, deploy=False).module
    beyond = wide_cfg.transforms.residual.beyond_speed
    law = make_classic_policy(beyond.base, env, **beyond.params).module
    gap = torch.linspace(8.0, 38.0, 31).repeat(3)
    dv = torch.linspace(-3.0, 3.0, 3).repeat_interleave(31)
    for v, same_as in ((torch.full_like(gap, 12.0), "lift"), (torch.full_like(gap, 19.9), "lift"),
                       (torch.full_like(gap, 24.0), "beyond")):
        a = wide(gap, v, v + dv)
        if same_as == "lift":
            torch.testing.assert_close(a, lift(gap, v, v + dv), rtol=0, atol=0)
        else:  # inside the stopping envelope, which binds only where the gap is short for the closing speed
            torch.testing.assert_close(a, torch.minimum(law(gap, v, v + dv), wide.bound(gap, v, v + dv)))
    assert not torch.equal(wide(gap, torch.full_like(gap, 24.0), 24.0 + dv),
                           lift(gap, torch.full_like(gap, 24.0), 24.0 + dv))


def test_generalization_fresh_cases_drive_above_the_training_range_and_groups_expand(benchmark_script):
    """``--cases fresh`` / ``fresh_2`` of benchmarks/ring_generalization.py run the cases added after a base was
    searched: each head profile (as the evaluation samples it, 4 episodes) stays at or above 0 m/s and
    reaches above the training profile's 20 m/s (stop_and_go_20 reaches it), within the CAV's reach (28 m/s);
    the tuning cases cross 16-20 m/s; the groups are disjoint and cover every case, expand in order and once,
    and an unknown name exits naming the allowed groups."""
    mod = benchmark_script("ring_generalization")
    all_cases = mod.cases(200.0)
    assert mod.case_names(["fresh"], all_cases) == list(mod.GROUPS["fresh"])
    assert mod.case_names(["sine_fast", "held_out"], all_cases)[:2] == ["sine_fast", "stop_and_go"]
    assert len(mod.case_names(["sine_fast", "held_out"], all_cases)) == 12
    with pytest.raises(SystemExit, match=r"sine_fastest.*a group: \['held_out', 'fresh', 'fresh_2', 'tuning', 'fresh_3', "
                                         r"'fresh_4', 'random_stops', 'fresh_5', 'fresh_6', 'fresh_7', "
                                         r"'fresh_8', 'fresh_9', 'fresh_10', 'fresh_11', 'fresh_12', 'fresh_13', 'fresh_14', "
                                         r"'fresh_15', 'fresh_16', 'fresh_17', 'fresh_17_fast', 'fresh_18', 'fresh_18_fast', "
                                         r"'fresh_19', 'fresh_19_fast', 'fresh_20', 'fresh_20_fast', 'fresh_21', "
                                         r"'fresh_21_fast', 'fresh_22', 'fresh_22_fast', 'fresh_23', 'fresh_23_fast', "
                                         r"'training'\]"):
        mod.case_names(["sine_fastest"], all_cases)
    groups = [set(g) for g in mod.GROUPS.values()]
    assert sum(map(len, groups)) == len(set().union(*groups)) == len(all_cases)  # disjoint, covering every case
    assert len(mod.GROUPS["held_out"]) == 12 and len(mod.GROUPS["fresh_2"]) == 6 and len(mod.GROUPS["fresh_3"]) == 5
    assert len(mod.GROUPS["fresh_4"]) == 5 and len(mod.GROUPS["fresh_5"]) == 9 and len(mod.GROUPS["fresh_6"]) == 9
    assert len(mod.GROUPS["fresh_7"]) == len(mod.GROUPS["fresh_8"]) == len(mod.GROUPS["fresh_9"]) == 9
    assert len(mod.GROUPS["fresh_10"]) == len(mod.GROUPS["fresh_11"]) == len(mod.GROUPS["fresh_12"]) == 9
    assert len(mod.GROUPS["fresh_13"]) == len(mod.GROUPS["fresh_14"]) == len(mod.GROUPS["fresh_15"]) == 9
    assert len(mod.GROUPS["fresh_16"]) == len(mod.GROUPS["fresh_17"]) == len(mod.GROUPS["fresh_18"]) == 9
    assert len(mod.GROUPS["fresh_19"]) == len(mod.GROUPS["fresh_20"]) == len(mod.GROUPS["fresh_21"]) == 9
    assert len(mod.GROUPS["fresh_17_fast"]) == len(mod.GROUPS["fresh_18_fast"]) == len(mod.GROUPS["fresh_19_fast"]) == 4
    assert len(mod.GROUPS["fresh_20_fast"]) == len(mod.GROUPS["fresh_21_fast"]) == len(mod.GROUPS["fresh_22_fast"]) == 4
    assert len(mod.GROUPS["fresh_22"]) == len(mod.GROUPS["fresh_23"]) == 9
    assert len(mod.GROUPS["fresh_23_fast"]) == 4
    with pytest.raises(SystemExit, match=r"--jerk-by-speed: \[20.0, 16.0\] is invalid; allowed: increasing"):
        mod.main(["--checkpoint", "none", "--jerk-by-speed", "20", "16", "--out", "none"])  # before any loading
    with pytest.raises(SystemExit, match=r"--jerk-by-time: \[0.0\] is invalid; allowed: increasing times > 0"):
        mod.main(["--checkpoint", "none", "--jerk-by-time", "0", "--out", "none"])

    def head_speeds(name: str, seed: int) -> torch.Tensor:  # [time, 4 episodes], every 0.1 s of the episode
        case = all_cases[name]
        seconds = case.get("eval", {}).get("episode_seconds", 200.0)
        prof = make_profile(case["profile"], **case["kwargs"])
        params = prof.sample(4, torch.Generator().manual_seed(seed))
        return torch.stack([prof.speed(torch.full((4,), t), params) for t in torch.arange(0.0, seconds, 0.1).tolist()])

    for name in mod.GROUPS["fresh"] + mod.GROUPS["fresh_2"]:
        v = head_speeds(name, 5000)
        assert float(v.min()) >= 0.0 and float(v.max()) <= 28.0 + 1e-4, name
        assert float(v.max()) > (19.99 if name == "stop_and_go_20" else 20.5), name
    for name in mod.GROUPS["tuning"]:  # the tuning cases cross the laws' handover speeds (16-20 m/s) both ways
        v = head_speeds(name, 3000)
        assert float(v.min()) < 16.0 and float(v.max()) > 20.0, name
    for name in mod.GROUPS["fresh_4"]:  # stop cases: the head stands still, and drives off again (but a hard brake)
        v = head_speeds(name, 9000)
        assert float(v.min()) == 0.0 and float(v.max()) <= 20.0, name
        assert name == "brake_from_17" or float(v[-300:].max()) > 10.0, name
    # random_stops: the head stops and drives off several times in every episode, and another seed draws other stops
    # (a fixed stop case gives the same head at every seed: a tuning seed would tune on the scored episodes)
    for name in mod.GROUPS["random_stops"]:
        v, w = head_speeds(name, 10000), head_speeds(name, 3000)
        stops = ((v[1:] < 1e-6) & (v[:-1] >= 1e-6)).sum(0)
        assert bool((stops >= 3).all()) and float(v.max()) <= 24.0 + 1e-4, name
        assert float((v - w).abs().max()) > 5.0, name
    # fresh_5: each kind of head the acceptance names, inside the CAV's reach; three drive above the training range
    above = {"brake_from_23", "steps_21_27", "sine_23"}
    for name in mod.GROUPS["fresh_5"]:
        v = head_speeds(name, 12000)
        assert float(v.min()) >= 0.0 and float(v.max()) <= 28.0 + 1e-4, name
        assert (float(v.max()) > 20.5) == (name in above), name
    assert float(head_speeds("random_stops_slow_long", 12000).min()) == 0.0
    # fresh_6 to fresh_23: each within the CAV's reach, one case above the training speeds, two that stand still
    for group, seed, above, stand in (("fresh_6", 13000, "sine_22_p35", ("random_stops_mid", "brake_from_15_late")),
                                      ("fresh_7", 14000, "steps_20_26", ("random_stops_short", "brake_from_11")),
                                      ("fresh_8", 15000, "sine_21_p40", ("random_stops_long", "brake_from_14")),
                                      ("fresh_9", 16000, "ramps_19_24", ("random_stops_gentle", "brake_from_16_late")),
                                      ("fresh_10", 17000, "steps_19_23", ("random_stops_brisk", "brake_from_12_late")),
                                      ("fresh_11", 18000, "sine_22_p50", ("random_stops_mixed", "brake_from_18_late")),
                                      ("fresh_12", 19000, "sine_23_p60",
                                       ("random_stops_long_holds", "brake_from_17_late_ring_330")),
                                      ("fresh_13", 20000, "steps_20_25",
                                       ("random_stops_quick", "brake_from_16_late_ring_270")),
                                      ("fresh_14", 21000, "ramps_20_25", ("random_stops_slow_quick", "brake_from_19_late")),
                                      ("fresh_15", 22000, "sine_21_p45",
                                       ("random_stops_long_quick", "brake_from_18_late_ring_280")),
                                      ("fresh_16", 23000, "steps_20_24",
                                       ("random_stops_short_brisk", "brake_from_15_late_ring_290")),
                                      ("fresh_17", 24000, "ramps_21_25",
                                       ("random_stops_varied", "brake_from_13_late_ring_320")),
                                      ("fresh_18", 26000, "ramps_19_23",
                                       ("random_stops_short_stands", "brake_from_14_mid_ring_300")),
                                      ("fresh_19", 28000, "steps_18_22",
                                       ("random_stops_mid_holds", "brake_from_12_ring_280")),
                                      ("fresh_20", 30000, "ramps_20_24_ring_280",
                                       ("random_stops_long_stands", "brake_from_16_ring_320")),
                                      ("fresh_21", 32000, "steps_20_24_ring_300",
                                       ("random_stops_slow_short_holds", "brake_from_18_ring_300")),
                                      ("fresh_22", 34000, "sine_22_p45_ring_280",
                                       ("random_stops_mid_short_stands", "brake_from_17_ring_270")),
                                      ("fresh_23", 36000, "ramps_20_26_ring_270",
                                       ("random_stops_brisk_short_stands", "brake_from_15_ring_290"))):
        for name in mod.GROUPS[group]:
            v = head_speeds(name, seed)
            assert float(v.min()) >= 0.0 and float(v.max()) <= 28.0 + 1e-4, name
            assert (float(v.max()) > 20.5) == (name == above), name
            assert (float(v.min()) == 0.0) == (name in stand), name
    # the fast groups: every case above the training speeds, none standing still
    for group, seed in (("fresh_17_fast", 25000), ("fresh_18_fast", 27000), ("fresh_19_fast", 29000),
                        ("fresh_20_fast", 31000), ("fresh_21_fast", 33000), ("fresh_22_fast", 35000),
                        ("fresh_23_fast", 37000)):
        for name in mod.GROUPS[group]:
            v = head_speeds(name, seed)
            assert float(v.min()) > 0.0 and float(v.max()) > 20.5 and float(v.max()) <= 28.0 + 1e-4, name
    fixed = head_speeds("stop_and_go_15", 3000)
    assert torch.equal(fixed, head_speeds("stop_and_go_15", 2000))


def test_jerk_shares_by_speed_add_up_to_the_reports_mean_jerk():
    """``harness.jerk_shares_by`` (``ring_generalization.py --jerk-by-speed``): the report's mean |jerk| split by
    the CAV's speed; the bins add up to the whole-episode mean, each step's jerk lands in its speed's bin, and
    the first step (its previous acceleration unknown) and invalid steps count nowhere."""
    from mixed_traffic.evaluation.harness import abs_jerk, jerk_shares_by

    accel = torch.tensor([[0.0, 1.0, 1.0, -1.0, -1.0, 0.0], [2.0, 0.0, 0.0, 0.0, 1.0, 1.0]])
    speed = torch.tensor([[10.0, 15.0, 17.0, 19.0, 22.0, 25.0], [30.0, 30.0, 18.0, 18.0, 18.0, 5.0]])
    valid = torch.ones_like(accel, dtype=torch.bool)
    valid[1, 5] = False
    edges = [0.0, 16.0, 20.0, float("inf")]
    shares = jerk_shares_by(accel, valid, 0.1, speed, edges)
    jerk, jvalid = abs_jerk(accel, valid, 0.1)
    whole = float(((jerk * jvalid).sum(1) / jvalid.sum(1)).mean())
    assert sum(shares) == pytest.approx(whole)
    # episode 0: jerk 10 at 15 m/s, 20 at 19 m/s, 10 at 25 m/s over 5 steps; episode 1: 20 at 30 m/s, 10 at
    # 18 m/s over 4 steps (the 5-m/s step is invalid)
    assert shares == pytest.approx([(10 / 5 + 0) / 2, (20 / 5 + 10 / 4) / 2, (10 / 5 + 20 / 4) / 2])


def test_generalization_marks_a_steady_rmse_that_is_the_whole_episodes(benchmark_script):
    """benchmarks/ring_generalization.py: a case whose head holds its speed in no episode (stop_and_go_25's holds
    are shorter than the settling time) reports the whole-episode RMSE as its steady RMSE; its rows say so, and a
    case steady in some episodes gives the figure of those alone."""
    from mixed_traffic.evaluation.harness import steadiness

    mod = benchmark_script("ring_generalization")
    per = {"speed_rmse_steady": [1.9, 1.8, 0.1, 0.3], "steady_seconds": [0.0, 0.0, 2.0, 3.0]}
    s = steadiness(per)
    assert s["steady_episodes"] == 2 and s["steady_only_rmse"] == pytest.approx(0.2)
    assert s["steady_seconds"] == pytest.approx(1.25)
    row = {"steady_rmse": 1.025, "episodes": 4, **s}
    assert mod.rmse_cell(row) == "0.200 (steady in 2 of 4 episodes, on those)"
    none = {"steady_rmse": 1.85, "episodes": 4, **steadiness({"speed_rmse_steady": [1.85] * 4,
                                                                 "steady_seconds": [0.0] * 4})}
    assert mod.rmse_cell(none) == "1.850 (no steady state: whole episode)"
    assert mod.rmse_cell({"steady_rmse": 0.15, "episodes": 4, **steadiness(
        {"speed_rmse_steady": [0.15] * 4, "steady_seconds": [7.0] * 4})}) == "0.150"
    assert steadiness({"speed_rmse_steady": [0.1]}) == {}  # a report from before the metric: unmarked
    assert mod.rmse_cell({"steady_rmse": 0.1}) == "0.100"


def test_scorecard_runs_every_group_once_and_counts_the_clean_cases(tmp_path, benchmark_script):
    """benchmarks/ring_scorecard.py: ring_generalization.py per run and group (the classical controllers beside the
    first run only), the bars table of each group and the count of clean cases; a group already evaluated is not
    run again, and bad groups or runs fail before anything runs."""
    run = _tiny_scratch_run(tmp_path / "run")
    mod = benchmark_script("ring_scorecard")
    out = tmp_path / "sc"
    args = ["--runs", str(run), str(run), "--groups", "fresh_3", "--episodes", "1", "--seconds", "10",
            "--classical", "cacc", "--out", str(out)]
    md = mod.main(args)
    assert (out / "scorecard.md").read_text() == md
    assert (out / "scorecard.png").stat().st_size > 10_000  # the figure: per case, jerk and return against the reference
    assert md.startswith("# Scorecard: 2 run(s), 1 episodes of 10 s a case")
    assert "## fresh_3 (evaluation seed 8000)" in md and "| bars missed (of 2 runs) |" in md
    import re
    head = md.splitlines()[2]  # the count, and where the policy misses, whether a classical controller did better
    clean, total = (int(x) for x in re.match(r"(\d+) of (\d+) cases meet every bar on every run\.", head).groups())
    assert (clean < total) == (f"Where the policy misses a bar ({total - clean} of the cases)" in head), head
    assert "| classical controllers: bars missed |" in md
    assert "cacc: jerk − IDM's" in md  # beside the first run only, and still in the table
    # the count by kind of head: four of fresh_3's five stop and drive off, one brakes to a standstill, one each has
    # its own ring length and its own human parameters; none drives above the training's 20 m/s
    assert "| kind of head | cases | the policy (every run) | idm | cacc |" in md
    for row in ("| stop-and-go | 4 |", "| braking to a standstill | 1 |", "| another ring length | 1 |",
                "| other human parameters | 1 |", "| within the training speeds | 5 |", "| every case | 5 |"):
        assert row in md, row
    assert "| above the training speeds |" not in md
    from mixed_traffic.evaluation.results import REFERENCE_FALLBACK, ZERO_RESIDUAL
    # by default the scorecard runs the stand-ins for a colliding IDM, and the policy with its learned residual at zero
    assert mod.CLASSICAL == (*REFERENCE_FALLBACK, ZERO_RESIDUAL)
    import json
    assert "cacc" in json.loads((out / "run0" / "fresh_3" / "generalization.json").read_text())["results"]["brake_from_20"]
    assert "cacc" not in json.loads((out / "run1" / "fresh_3" / "generalization.json").read_text())["results"]["brake_from_20"]
    stamp = (out / "run0" / "fresh_3" / "generalization.json").stat().st_mtime_ns
    md = mod.main(args)  # already there: not run again
    assert (out / "run0" / "fresh_3" / "generalization.json").stat().st_mtime_ns == stamp
    assert "Beside its learned residual at zero" not in md  # not asked for
    stamp1 = (out / "run1" / "fresh_3" / "generalization.json").stat().st_mtime_ns
    md = mod.main([*args[:-4], "--classical", "cacc", "idm:s0=6", "--out", str(out)])  # a controller asked for later:
    # the first run's group is evaluated again with it, the second run's is not
    assert (out / "run0" / "fresh_3" / "generalization.json").stat().st_mtime_ns != stamp
    assert (out / "run1" / "fresh_3" / "generalization.json").stat().st_mtime_ns == stamp1
    assert "idm:s0=6: jerk − IDM's" in md
    stamp = (out / "run0" / "fresh_3" / "generalization.json").stat().st_mtime_ns
    # this run drives alone (no learned residual): zero_residual is left out by default, and asked for it fails
    # before anything runs
    assert mod.classical_for(str(run), None) == list(REFERENCE_FALLBACK)
    with pytest.raises(SystemExit, match=r"--classical: \['zero_residual'\] drive the run's classical base without"):
        mod.main([*args[:-4], "--classical", "cacc", "zero_residual", "--out", str(out)])
    assert (out / "run0" / "fresh_3" / "generalization.json").stat().st_mtime_ns == stamp
    with pytest.raises(SystemExit, match=r"--set: .* was evaluated with --set \[\], not"):  # another variant: a new --out
        mod.main([*args, "--set", "transforms.safety_layer.deployed_s_max=false"])
    with pytest.raises(SystemExit, match=r"--backend: .* was evaluated on torch, not sumo"):  # another simulator too
        mod.main([*args, "--backend", "sumo"])
    assert (out / "run0" / "fresh_3" / "generalization.json").stat().st_mtime_ns == stamp
    # in SUMO: every job runs ring_generalization.py --backend sumo with the workers asked for
    sumo_jobs = mod.jobs([str(run)], ["fresh_3"], out, episodes=1, seconds=10.0, classical=[], backend="sumo", workers=3)
    assert sumo_jobs[0][1][-4:] == ["--backend", "sumo", "--workers", "3"]
    assert "--backend" not in mod.jobs([str(run)], ["fresh_3"], out, episodes=1, seconds=10.0, classical=[])[0][1]
    with pytest.raises(SystemExit, match=r"--groups: \['fresh_99'\] are not groups"):
        mod.main(["--runs", str(run), "--groups", "fresh_99", "--out", str(tmp_path / "bad")])
    with pytest.raises(SystemExit, match=r"--runs: .* do not exist"):
        mod.main(["--runs", str(tmp_path / "none"), "--out", str(tmp_path / "bad")])
    assert not (tmp_path / "bad").exists()
