"""Intersection controllers: NMPC (CasADi/IPOPT), barrier force transform, residual NMPC, evaluation harness."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import check_env_specs

from mixed_traffic import make_env
from mixed_traffic.envs.intersection_agents import make_test_set
from mixed_traffic.intersection.evaluate import evaluate_policy, format_table, summarise, write_gifs
from mixed_traffic.intersection.nmpc import NMPCConfig, NMPCController, make_nmpc_policy, predict_agent
from mixed_traffic.intersection.residual import BASE_KEY, ResidualNMPC
from transforms.barrier_force import BarrierForce, action_barrier_grad, state_barrier_grad


def _obs(y=-1.25, v=0.0, xa=4.0, ya=0.5, vxa=-0.8, vya=0.0, s=0.05):
    return torch.tensor([[y, v, xa, ya, vxa, vya, s, s]], dtype=torch.float32)


# ---------------------------------------------------------------- NMPC
def test_nmpc_goes_when_clear_and_yields_to_a_close_agent():
    ctrl = NMPCController()
    go = ctrl(_obs(xa=-3.0, vxa=-1.0)).item()  # agent already gone west
    assert go > 2.0
    ctrl.reset()
    # agent 1.3 m east of the ego's line, arriving in 1.3 s; the ego is rolling towards the crossing
    obs = _obs(y=-1.0, v=0.5, xa=1.8, ya=0.5, vxa=-1.0)
    a = ctrl(obs).item()
    assert a < 0  # brakes: it cannot pass in front in time
    assert ctrl.stats.n_steps == 2 and len(ctrl.stats.solve_times) == 2
    # the plan (yield, then go once the agent has passed) keeps the predicted straight agent at 2R or more
    plan = ctrl._warm[0]["Y"][1:]
    px, py, _ = predict_agent(obs[0].numpy(), ctrl.cfg)
    d = np.hypot(0.5 - px[1], plan - py[1])
    assert d.min() >= 2 * 0.3328
    assert plan[-1] > 0.5  # and it still plans to go on once the agent has passed


def test_nmpc_guard_keeps_a_waiting_ego_out_of_a_turning_agents_path():
    """Test episode 21 (a yielding left-turner): without the near-term guard the cheapest plan,
    which needs slack because the waiting ego is inside the inflated margin, drives into the
    agent; with it the ego keeps waiting and crosses afterwards."""
    ep = make_test_set(80, seed=2024).subset(torch.tensor([21]))
    guarded = make_nmpc_policy()
    res = evaluate_policy(guarded, test_set=ep)
    assert bool(res.success[0]) and not bool(res.collision[0])
    assert guarded.module.stats.n_guard > 0
    res_off = evaluate_policy(make_nmpc_policy(guard_steps=0), test_set=ep)
    assert bool(res_off.collision[0])


def test_nmpc_policy_module_batch_and_bounds():
    policy = make_nmpc_policy(horizon=30)
    obs = torch.cat([_obs(), _obs(xa=1.6, vxa=-0.5), _obs(y=0.0, v=1.5, xa=-2.0)])
    td = policy(TensorDict({"observation": obs}, batch_size=[3]))
    a = td["action"]
    assert a.shape == (3, 1) and (a.abs() <= 3.2 + 1e-6).all()
    s = policy.module.stats.summary()
    assert s["steps"] == 3 and s["solve_ms_mean"] > 0 and s["fallbacks"] == 0


def test_predict_agent_hypotheses_follow_the_map():
    cfg = NMPCConfig()
    px, py, r = predict_agent(np.array([-1.25, 0, 2.5, 0.5, -1.0, 0.0, 0.05, 0.05]), cfg)
    straight, left, right = (np.stack([px[j], py[j]], -1) for j in (1, 2, 3))
    assert np.allclose(straight[:, 1], 0.5) and straight[-1, 0] < -0.4
    assert left[-1, 1] < 0.0 and left[-1, 0] < 0.6  # curving south
    assert right[-1, 1] > 0.5  # curving north into the ego's lane
    assert np.all(np.diff(r) >= 0) and r[-1] - r[0] > 0.3 and r[0] > 2 * 0.3328  # grows along the horizon (capped)
    with pytest.raises(ValueError, match="predict"):
        NMPCConfig(predict="oracle").validate()
    with pytest.raises(ValueError, match="horizon"):
        make_nmpc_policy(horizon=1)


def test_nmpc_closed_loop_small_test_set():
    res = evaluate_policy(make_nmpc_policy(), n_per_behaviour=1, seed=5)
    assert res.table["overall"]["episodes"] == 4
    assert res.table["overall"]["collision_rate"] == 0.0
    assert res.table["overall"]["success_rate"] == 1.0
    assert res.extra["nmpc"]["fallbacks"] == 0


# ---------------------------------------------------------------- barrier force
def test_action_barrier_pushes_away_from_the_bounds():
    g = action_barrier_grad(torch.tensor([-3.0, 0.0, 3.0]), 3.2)
    assert g[0] > 0 and g[1] == 0 and g[2] < 0


def test_state_barrier_brakes_for_an_agent_ahead_and_is_silent_far_away():
    near = torch.tensor([[-0.9, 0.5, 0.9, 0.0, -0.5, 0.0, 0.05, 0.05]])  # agent ahead along the ego's line
    behind = torch.tensor([[0.9, 1.0, 0.9, 0.2, -0.5, 0.0, 0.05, 0.05]])
    far = torch.tensor([[-1.25, 0.0, 5.0, 0.5, -0.5, 0.0, 0.05, 0.05]])
    a = torch.zeros(1, 1)
    assert state_barrier_grad(near, a).item() < 0
    assert state_barrier_grad(behind, a).item() > 0
    assert state_barrier_grad(far, a).item() == 0
    bff = BarrierForce(rho=0.2, K=0.5, a_max=3.2)
    u = bff.filter(near, torch.tensor([[0.5]]))
    assert u.item() < 0.0 and abs(u.item()) <= 3.2 + 1e-6
    assert bff.filter(far, torch.tensor([[1.0]])).item() == pytest.approx(1.0 + 0.2 * action_barrier_grad(
        torch.tensor(1.0), 3.2).item(), rel=1e-5)
    with pytest.raises(ValueError, match="rho"):
        BarrierForce(rho=-1.0)


def test_barrier_force_env_specs_and_logging():
    env = TransformedEnv(make_env("intersection", batch_size=4, seed=0), BarrierForce(rho=0.2, K=0.5))
    check_env_specs(env)
    td = env.rollout(20, lambda td: td.set("action", torch.full((4, 1), 3.2)), break_when_any_done=False)
    assert td["action"].eq(3.2).all()  # the rollout keeps the policy's raw action
    force = td["next", "bff", "force"]
    assert (force <= 0).all() and (force < 0).any()  # the action barrier pulls the command off the bound


# ---------------------------------------------------------------- residual NMPC
def test_residual_nmpc_zero_residual_runs_the_nmpc():
    env = TransformedEnv(make_env("intersection", batch_size=2, seed=1), ResidualNMPC(weight=0.5))
    check_env_specs(env)
    td = env.rollout(15, lambda td: td.set("action", torch.zeros(2, 1)), break_when_any_done=False)
    assert torch.allclose(td["next", "residual", "executed"], td[BASE_KEY])
    assert not td["next", "collision"].any()
    td = env.rollout(3, lambda td: td.set("action", torch.ones(2, 1)), break_when_any_done=False)
    assert torch.allclose(td["next", "residual", "executed"], (td[BASE_KEY] + 0.5).clamp(-3.2, 3.2))


# ---------------------------------------------------------------- evaluation harness
def test_summarise_table():
    beh = np.array([0, 0, 1, 1])
    t = summarise(beh, np.array([1, 0, 1, 1], bool), np.array([0, 1, 0, 0], bool), np.zeros(4, bool),
                  np.zeros(4, bool), np.array([20, 5, 30, 10]), np.array([100.0, -50, 80, 90]), np.zeros(4))
    assert t["straight"]["success_rate"] == 0.5 and t["straight"]["collision_rate"] == 0.5
    assert t["straight"]["crossing_time_s"] == pytest.approx(2.0)
    assert t["left"]["crossing_time_s"] == pytest.approx(2.0)
    assert t["overall"]["episodes"] == 4 and t["overall"]["success_rate"] == 0.75
    assert "| straight | 2 | 50.0% |" in format_table(t)


def test_evaluate_records_and_writes_gifs(tmp_path):
    ts = make_test_set(1, seed=3)

    from tensordict.nn import TensorDictModule

    # a policy that never moves: every episode times out
    still = TensorDictModule(lambda obs: torch.zeros(obs.shape[0], 1), in_keys=["observation"], out_keys=["action"])
    res = evaluate_policy(still, test_set=ts, record=[2], max_steps=30)
    assert res.timeout.all() and not res.success.any()
    assert res.table["overall"]["timeout_rate"] == 1.0
    assert res.frames[2]["ego"].shape == (31, 2)
    paths = write_gifs(res, tmp_path, prefix="still")
    assert len(paths) == 1 and paths[0].stat().st_size > 1000
