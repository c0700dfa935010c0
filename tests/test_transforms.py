"""Reward, Lagrangian, discretiser and residual transforms: specs and behaviour."""

from __future__ import annotations

import functools

import pytest
import torch
from torchrl.envs import Compose, TransformedEnv
from torchrl.envs.utils import check_env_specs

import transforms
from mixed_traffic import make_env
from transforms import LagrangeMultiplier, LagrangianPenalty, NonNegativeReward, QuadraticReward, SafetyLayer


def test_package_exports():
    for name in ("SafetyLayer", "LagrangianPenalty", "NonNegativeReward", "QuadraticReward", "LagrangeMultiplier"):
        assert name in transforms.__all__
        assert getattr(transforms, name) is not None


@pytest.mark.parametrize("scenario", ["ring", "deeplcc"])
def test_check_env_specs_all_reward_transforms(scenario):
    for t in (NonNegativeReward(), QuadraticReward(normalize=True, collision_reward=-1.0),
              LagrangianPenalty(raw_reward_key="raw_reward"),
              Compose(SafetyLayer(), NonNegativeReward(), LagrangianPenalty(raw_reward_key=("lagrangian", "raw")))):
        check_env_specs(TransformedEnv(make_env(scenario, batch_size=3, seed=0), t))


def test_non_negative_reward_formula_and_collision():
    env = TransformedEnv(make_env("ring", batch_size=4, seed=0), NonNegativeReward())
    td = env.rollout(10)
    j = td["next", "traffic", "J"]
    expected = (env.J_max - j).clamp_min(0) / env.J_max
    assert torch.allclose(td["next", "reward"], expected)
    assert ((td["next", "reward"] >= 0) & (td["next", "reward"] <= 1)).all()
    # collision -> -1 (checked on a hand-made next tensordict)
    t = NonNegativeReward(J_max=100.0)
    from tensordict import TensorDict

    nxt = TensorDict({"traffic": {"J": torch.tensor([[10.0], [500.0], [10.0]])},
                      "collision": torch.tensor([[False], [False], [True]]),
                      "reward": torch.zeros(3, 1)}, [3])
    out = t._call(nxt)
    assert out["reward"].squeeze(-1).tolist() == pytest.approx([0.9, 0.0, -1.0])
    with pytest.raises(ValueError, match="J_max"):
        NonNegativeReward(J_max=0.0)


def test_profile_normalised_reward_scales_each_profile_by_its_own_j_max():
    from mixed_traffic.envs.platoon import PROFILE_KINDS
    from transforms import ProfileNormalisedReward

    jm = {"random1": 10.0, "brake": 1000.0}
    env = make_env("platoon", batch_size=4, seed=0, profiles=["random1", "brake"], profile_rows=True)
    tenv = TransformedEnv(env, ProfileNormalisedReward(jm, kinds=PROFILE_KINDS))
    check_env_specs(tenv)
    td = tenv.rollout(5)
    j, kind = td["next", "traffic", "J"], td["next", "deeplcc", "kind"]
    j_max = torch.where(kind == PROFILE_KINDS.index("brake"), 1000.0, 10.0)
    assert torch.allclose(td["next", "reward"], ((j_max - j).clamp_min(0) / j_max).to(td["next", "reward"].dtype))
    # the same stage cost is worth 100x more reward loss on the profile with the 100x smaller J_max
    from tensordict import TensorDict

    t = ProfileNormalisedReward(jm, kinds=PROFILE_KINDS)
    k = [PROFILE_KINDS.index("random1"), PROFILE_KINDS.index("brake"), PROFILE_KINDS.index("brake")]
    nxt = TensorDict({"traffic": {"J": torch.tensor([[1.0], [1.0], [1.0]])}, "deeplcc": {"kind": torch.tensor(k)[:, None]},
                      "collision": torch.tensor([[False], [False], [True]]), "reward": torch.zeros(3, 1)}, [3])
    assert t._call(nxt)["reward"].squeeze(-1).tolist() == pytest.approx([0.9, 0.999, -1.0])
    # a row whose profile has no J_max fails and names it; bad tables name the field
    nxt["deeplcc", "kind"] = torch.full((3, 1), PROFILE_KINDS.index("sine5"))
    with pytest.raises(ValueError, match="sine5"):
        t._call(nxt)
    with pytest.raises(ValueError, match="J_max"):
        ProfileNormalisedReward({"random1": 0.0}, kinds=PROFILE_KINDS)
    with pytest.raises(ValueError, match="J_max"):
        ProfileNormalisedReward({"no_such_profile": 1.0}, kinds=PROFILE_KINDS)


def test_counterfactual_reward_twin_is_the_base_controllers_own_closed_loop():
    from tensordict.nn import TensorDictModule

    from mixed_traffic.envs.platoon import PROFILE_KINDS
    from transforms import CounterfactualReward

    def base_fn(uini, yini):  # a fixed feedback on the window: the twin's controller
        return (-0.3 * yini[..., -4:-2] + 0.1 * uini[..., -2:]).clamp(-5, 2)

    base = TensorDictModule(base_fn, in_keys=["uini", "yini"], out_keys=["action"])
    other = TensorDictModule(lambda o: torch.full((o.shape[0], 2), 0.4), in_keys=["observation"], out_keys=["action"])
    jr = {"random3": 2.0, "brake": 100.0}

    def env():  # humans with noise and a model mismatch: the twin must replay the same draws
        e = make_env("platoon", batch_size=4, seed=3, profiles=["random3", "brake"], profile_rows=True,
                     mismatch="idm")
        return TransformedEnv(e, CounterfactualReward(base, jr, kinds=PROFILE_KINDS, scale=2.0))

    check_env_specs(env())
    alone = env().rollout(60, base)
    assert torch.equal(alone["next", "traffic", "J_twin"], alone["next", "traffic", "J"])
    assert (alone["next", "reward"] == 1).all()
    run = env().rollout(60, other)
    # the twin of a run with another policy is, step for step, the base controller's closed loop
    assert torch.allclose(run["next", "traffic", "J_twin"], alone["next", "traffic", "J"], rtol=1e-5, atol=1e-6)
    assert not torch.allclose(run["next", "traffic", "J"], alone["next", "traffic", "J"])
    kind = run["next", "deeplcc", "kind"]
    j_ref = torch.where(kind == PROFILE_KINDS.index("brake"), 100.0, 2.0)
    expected = (1 + (run["next", "traffic", "J_twin"] - run["next", "traffic", "J"]) / (2.0 * j_ref)).clamp_min(0)
    assert torch.allclose(run["next", "reward"], expected)
    with pytest.raises(ValueError, match="J_ref"):
        CounterfactualReward(base, {"random3": -1.0}, kinds=PROFILE_KINDS)
    with pytest.raises(ValueError, match="cannot replay"):
        TransformedEnv(make_env("ring", batch_size=2, seed=0),
                       CounterfactualReward(base, jr, kinds=PROFILE_KINDS)).reset()


def test_quadratic_reward_is_minus_j():
    env = TransformedEnv(make_env("ring", batch_size=2, seed=0), QuadraticReward(scale=2.0))
    td = env.rollout(5)
    assert torch.allclose(td["next", "reward"], -2.0 * td["next", "traffic", "J"])
    with pytest.raises(ValueError, match="scale"):
        QuadraticReward(scale=-1.0)


def test_lagrangian_penalty_applies_r_minus_lambda_c():
    pen = LagrangianPenalty(lambda_init=0.7, cost_key=("traffic", "time"), raw_reward_key="raw_reward")
    env = TransformedEnv(make_env("ring", batch_size=2, seed=0), pen)
    td = env.rollout(5)
    assert torch.allclose(td["next", "reward"], td["next", "raw_reward"] - 0.7 * td["next", "traffic", "time"],
                          atol=1e-5)


def test_dual_ascent_matches_formula_step_by_step():
    lam = LagrangeMultiplier(init=1.0, lr=0.05, max_value=10.0, cost_limit=0.1)
    expected = 1.0
    g = torch.Generator().manual_seed(0)
    costs = (torch.rand(200, generator=g) * 2.0).tolist() + [0.0] * 300 + [50.0] * 100
    for c in costs:
        expected = min(max(expected + 0.05 * (c - 0.1), 0.0), 10.0)
        assert lam.update(c) == pytest.approx(expected, abs=1e-12)
    assert float(lam) == 10.0
    for _ in range(2100):  # 10 / (0.05 * 0.1) = 2000 steps down to the bound
        lam.update(0.0)
    assert float(lam) == 0.0


def test_penalty_update_uses_batch_mean_cost():
    pen = LagrangianPenalty()
    env = TransformedEnv(make_env("ring", batch_size=2, seed=0), pen)
    batch = env.rollout(4)
    batch["next", "cost"] = torch.full_like(batch["next", "cost"], 0.5)
    assert pen.update(batch) == pytest.approx(1.0 + 0.05 * 0.4)


def test_optimizer_update_moves_lambda_the_right_way():
    for method in ("adam", "sgd"):
        lam = LagrangeMultiplier(init=1.0, lr=0.05, method=method)
        up = lam.update(1.0)  # cost above the limit: lambda grows
        assert up > 1.0
        for _ in range(500):
            lam.update(0.0)  # below: decreases to the projection bound 0
        assert float(lam) == pytest.approx(0.0, abs=1e-6)


def test_invalid_multiplier_arguments():
    with pytest.raises(ValueError, match="method"):
        LagrangeMultiplier(method="newton")
    with pytest.raises(ValueError, match="init"):
        LagrangeMultiplier(init=11.0, max_value=10.0)
    with pytest.raises(ValueError, match="lr"):
        LagrangeMultiplier(lr=0.0)


def test_multiplier_pickle_shares_the_value():
    import pickle

    lam = LagrangeMultiplier(init=0.5)
    twin = pickle.loads(pickle.dumps(lam))
    lam.update(10.0)
    assert float(twin) == float(lam)


def _penalised_env(penalty):
    return TransformedEnv(make_env("ring", batch_size=2, seed=0), penalty)


def test_lambda_in_workers_equals_lambda_in_main():
    from torchrl.collectors import MultiSyncCollector

    # the cost key is the episode time (> 0 every step) so the applied lambda is observable
    pen = LagrangianPenalty(lambda_init=0.5, cost_key=("traffic", "time"), raw_reward_key="raw_reward")
    fn = functools.partial(_penalised_env, pen)
    coll = MultiSyncCollector([fn, fn], policy=None, frames_per_batch=40, total_frames=80)
    try:
        for batch in coll:
            applied = (batch["next", "raw_reward"] - batch["next", "reward"]) / batch["next", "traffic", "time"]
            assert torch.allclose(applied, torch.full_like(applied, pen.lam), atol=1e-3)
            pen.multiplier.set_(pen.lam + 1.0)  # a change in main is seen by the workers' next batch
    finally:
        coll.shutdown()


# ----------------------------------------------------------------------------- discretiser
from transforms import ResidualAction, StateDiscretizer  # noqa: E402
from transforms.discretizer import bin_edges  # noqa: E402


@pytest.mark.parametrize("scenario", ["ring", "deeplcc"])
def test_check_env_specs_discretizer_and_residual(scenario):
    from mixed_traffic.controllers.classic import make_classic_policy

    base = make_env(scenario, batch_size=3, seed=0)
    check_env_specs(TransformedEnv(base, StateDiscretizer(n_bins=20, heavy_tail=True)))
    base = make_env(scenario, batch_size=3, seed=0)
    check_env_specs(TransformedEnv(base, Compose(SafetyLayer(),
                                                 ResidualAction(make_classic_policy("idm", base), weight=0.5))))


def test_discretizer_bins_uniform_and_heavy_tail():
    assert torch.allclose(bin_edges(4, 0.0, 1.0), torch.tensor([0.25, 0.5, 0.75], dtype=torch.float64))
    assert torch.allclose(bin_edges(4, 0.0, 1.0, True), torch.tensor([0.0625, 0.25, 0.5625], dtype=torch.float64))
    d = StateDiscretizer(n_bins=4, heavy_tail=[1])
    x = torch.tensor([[0.1, 0.1], [0.3, 0.3], [0.99, 0.99], [-5.0, 5.0]])
    bins = d.discretize(x)
    assert bins[:, 0].tolist() == [0, 1, 3, 0]  # uniform
    assert bins[:, 1].tolist() == [1, 2, 3, 3]  # quadratic: finer near 0
    idx = d.flat_index(bins)
    assert idx.squeeze(-1).tolist() == [0 + 4 * 1, 1 + 4 * 2, 3 + 4 * 3, 0 + 4 * 3]
    # 20 bins, 8 dims (the seed ring observation): exact flat index
    d20 = StateDiscretizer()
    b = torch.randint(0, 20, (100, 8))
    assert len(set(d20.flat_index(b).squeeze(-1).tolist())) == len({tuple(r) for r in b.tolist()})
    # too many dims for int64: hashed, still deterministic and in range
    big = StateDiscretizer(n_bins=20).flat_index(torch.randint(0, 20, (5, 30)))
    assert (big >= 0).all()
    with pytest.raises(ValueError, match="n_bins"):
        StateDiscretizer(n_bins=1)


def test_discretizer_through_env_heavy_tail_positions():
    env = TransformedEnv(make_env("ring", batch_size=4, seed=0), StateDiscretizer(n_bins=20, heavy_tail=True))
    td = env.rollout(10)
    obs, bins = td["next", "observation"], td["next", "observation_discrete"]
    assert ((bins >= 0) & (bins < 20)).all()
    expected_speed_bins = torch.bucketize(obs[..., :4].contiguous(), bin_edges(20).float(), right=True)
    assert torch.equal(bins[..., :4], expected_speed_bins)
    expected_pos_bins = torch.bucketize(obs[..., 4:].contiguous(), bin_edges(20, heavy_tail=True).float(), right=True)
    assert torch.equal(bins[..., 4:], expected_pos_bins)


# ----------------------------------------------------------------------------- residual
def test_residual_action_executes_clipped_sum_and_logs_base():
    from mixed_traffic.controllers.classic import make_classic_policy

    base_env = make_env("ring", batch_size=4, seed=0)
    idm = make_classic_policy("idm", base_env)
    env = TransformedEnv(base_env, ResidualAction(idm, weight=0.5))
    res = torch.tensor([[-1.0], [0.0], [1.0], [6.0]])
    td = env.rollout(6, lambda td: td.set("action", res.clone()))
    a_base = td["next", "residual", "base_action"]
    # the IDM's own output on the same states
    with torch.no_grad():
        expected_base = idm(td.exclude("action").clone())["action"]
    assert torch.allclose(a_base, expected_base, atol=1e-5)
    executed = td["next", "cav", "accel"]
    expected = (a_base + 0.5 * res.unsqueeze(1)).clamp(-3.0, 3.0)
    assert torch.allclose(executed, expected, atol=1e-4)
    # the rollout keeps the policy's residual
    assert torch.equal(td["action"], res.unsqueeze(1).expand(4, 6, 1))
    with pytest.raises(ValueError, match="weight"):
        ResidualAction(idm, weight=-1.0)


def test_residual_engages_linearly_over_engage_seconds_and_again_after_a_reset():
    """``engage_seconds``: the base drives alone at the episode's start, the residual's weight rises
    linearly to ``weight`` at ``engage_seconds`` and stays there; a new episode engages again."""
    from mixed_traffic.controllers.classic import make_classic_policy

    base_env = make_env("ring", batch_size=2, seed=0, episode_seconds=2.0)
    env = TransformedEnv(base_env, ResidualAction(make_classic_policy("idm", base_env), weight=0.5,
                                                  engage_seconds=1.0))
    td = env.rollout(30, lambda td: td.set("action", torch.ones(2, 1)), break_when_any_done=False)
    added = td["next", "cav", "accel"] - td["next", "residual", "base_action"]  # 0.5 * w(t) * 1
    t = td["traffic", "time"]  # the time the command was given at
    assert torch.allclose(added, 0.5 * (t / 1.0).clamp(max=1.0), atol=1e-5)
    assert float(added[:, 15].min()) > 0.49  # engaged after 1 s
    assert float(added[:, 0].abs().max()) < 1e-6 and float(added[:, 20].abs().max()) < 1e-6  # each episode's start
    with pytest.raises(ValueError, match="engage_seconds"):
        ResidualAction(make_classic_policy("idm", base_env), engage_seconds=-1.0)


def test_residual_fades_out_above_the_speeds_it_trained_on():
    """``fade_speeds=(v_full, v_zero)``: the residual's weight is full at or below ``v_full``, 0 at or above
    ``v_zero`` and linear between (hand values from the car's own speed at each step); a bad pair fails,
    naming the argument."""
    from mixed_traffic.controllers.classic import make_classic_policy

    base_env = make_env("ring", batch_size=3, seed=0, profile="random_steps",
                        profile_kwargs={"v_low": 5.0, "v_high": 20.0, "period": 15.0})
    env = TransformedEnv(base_env, ResidualAction(make_classic_policy("idm", base_env), weight=0.5,
                                                  fade_speeds=(9.0, 11.0)))
    td = env.rollout(300, lambda td: td.set("action", torch.ones(3, 1)))
    added = td["next", "cav", "accel"] - td["next", "residual", "base_action"]
    v = td["cav", "speed"]  # the speed the command was given at
    expect = 0.5 * ((11.0 - v) / 2.0).clamp(0.0, 1.0)
    room = (td["next", "cav", "accel"] > -2.99) & (td["next", "cav", "accel"] < 1.99)  # not clipped
    assert torch.allclose(added[room], expect[room], atol=1e-5)
    assert bool(((v > 9.2) & (v < 10.8) & room).any()) and bool(((v < 9.0) & room).any())  # each regime seen
    assert bool(((v > 11.0) & room).any())
    with pytest.raises(ValueError, match="fade_speeds"):
        ResidualAction(make_classic_policy("idm", base_env), fade_speeds=(20.0, 18.0))


def test_residual_room_key_fades_an_accelerating_residual_to_the_room_the_base_leaves():
    """``room_key``: a residual that accelerates is scaled by ``room / r_max`` (``r_max = weight * max|policy
    bound|``), and never adds more than the room (an action outside the policy's bounds included); a
    braking residual and one with room to spare are left as they are; with ``slack_key`` / ``fade_slack`` the
    smaller of that fade and ``slack / fade_slack`` applies (hand values)."""
    from tensordict.nn import TensorDictModule

    room = torch.tensor([[1.0], [0.25], [0.0], [0.1]])
    base = TensorDictModule(lambda v: (torch.zeros_like(v), room.expand_as(v)), in_keys=[("cav", "speed")],
                            out_keys=["action", ("residual", "envelope_room")])
    env = TransformedEnv(make_env("ring", batch_size=4, seed=0),
                         ResidualAction(base, weight=0.5, policy_bounds=(-1.0, 1.0),
                                        room_key=("residual", "envelope_room")))
    res = torch.tensor([[1.0], [1.0], [-1.0], [2.0]])
    td = env.rollout(3, lambda td: td.set("action", res.clone()))
    expect = torch.tensor([0.5, 0.25, -0.5, 0.1]).view(4, 1, 1).expand(4, 3, 1)
    assert torch.allclose(td["next", "cav", "accel"], expect, atol=1e-5)
    # with a margin (m) and fade_slack 2: the smaller of the two fades
    slack = torch.tensor([[1.0], [2.0], [0.0], [-1.0]])
    base = TensorDictModule(lambda v: (torch.zeros_like(v), room.expand_as(v), slack.expand_as(v)),
                            in_keys=[("cav", "speed")],
                            out_keys=["action", ("residual", "envelope_room"), ("residual", "envelope_slack")])
    env = TransformedEnv(make_env("ring", batch_size=4, seed=0),
                         ResidualAction(base, weight=0.5, policy_bounds=(-1.0, 1.0),
                                        room_key=("residual", "envelope_room"),
                                        slack_key=("residual", "envelope_slack"), fade_slack=2.0))
    td = env.rollout(3, lambda td: td.set("action", res.clone()))
    expect = torch.tensor([0.25, 0.25, -0.5, 0.0]).view(4, 1, 1).expand(4, 3, 1)
    assert torch.allclose(td["next", "cav", "accel"], expect, atol=1e-5)
    with pytest.raises(ValueError, match="fade_slack"):
        ResidualAction(base, room_key=("residual", "envelope_room"), slack_key=("residual", "envelope_slack"),
                       fade_slack=0.0)


# ----------------------------------------------------------------------------- docstrings
@pytest.mark.parametrize("module", [
    "transforms.safety_layer", "transforms.lagrangian", "transforms.rewards", "transforms.discretizer",
    "transforms.residual", "transforms.counterfactual_reward", "transforms.intervention_cost", "transforms.jerk_penalty", "losses.lagrangian_ppo", "losses.bc", "losses.residual", "losses.qlearning",
    "losses.dqn", "mixed_traffic.profiles", "mixed_traffic.evaluation", "transforms.committed_answer",
    "mixed_traffic.evaluation.replay",
])
def test_docstring_examples_run(module):
    import doctest
    import importlib

    mod = importlib.import_module(module)
    result = doctest.testmod(mod, optionflags=doctest.ELLIPSIS)
    assert result.attempted > 0
    assert result.failed == 0


def test_safety_layer_clips_the_final_residual_action():
    from mixed_traffic.controllers.classic import make_classic_policy

    base_env = make_env("ring", batch_size=16, seed=0)
    env = TransformedEnv(base_env, Compose(SafetyLayer(), ResidualAction(make_classic_policy("idm", base_env))))
    td = env.rollout(300, lambda td: td.set("action", torch.full((16, 1), 3.0)), break_when_any_done=False)
    nxt = td["next"]
    assert not nxt["collision"].any()
    assert nxt["cav", "gap"].min() >= 5.0 - 1e-3
    # the layer saw base + residual: delta = executed - clip(base + 3)
    commanded = (nxt["residual", "base_action"] + 3.0).clamp(-3.0, 3.0)
    moving = nxt["cav", "speed"] > 0.5  # away from the stop at v = 0
    diff = (nxt["cav", "accel"] - commanded - nxt["safety", "delta"])[moving]
    assert diff.abs().max() < 1e-3
    assert nxt["safety", "clipped"].any()
