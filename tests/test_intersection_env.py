"""Intersection environment and agent model: geometry, events, reward/cost, agent statistics."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from mixed_traffic import make_env
from mixed_traffic.envs.intersection import EGO_X, IntersectionEnv
from mixed_traffic.envs.intersection_agents import (
    BEHAVIOURS,
    AgentTrajectories,
    load_recorded_trajectories,
    make_test_set,
    sample_agent_trajectories,
)

R = 0.3328


def _static_bank(x: float, y: float, sigma: float = 0.0, horizon: int = 500, n: int = 1) -> AgentTrajectories:
    """An agent parked at (x, y) with a constant perceived sigma."""
    true = torch.zeros(n, horizon + 1, 4)
    true[..., 0], true[..., 1] = x, y
    obs = torch.zeros(n, horizon + 1, 6)
    obs[..., :4] = true
    obs[..., 4:] = sigma
    z = torch.zeros(n, dtype=torch.bool)
    return AgentTrajectories(true, obs, torch.zeros(n, dtype=torch.long), z, z.clone())


def _step(env, a):
    td = env.reset()
    td["action"] = torch.full((env.batch_size[0], 1), float(a))
    return env.step(td)["next"]


def test_check_env_specs_and_reward_keys():
    env = make_env("intersection", batch_size=3, seed=1, start_noise=0.15)
    check_env_specs(env)
    assert env.reward_keys == ["cost", "reward"]
    td = env.reset()
    assert td["observation"].shape == (3, 8)
    assert ((td["observation"][:, 0] + 1.25).abs() <= 0.15 + 1e-6).all()


@pytest.mark.parametrize("gap,expect", [(2 * R - 0.01, True), (2 * R + 0.01, False)])
def test_collision_geometry(gap, expect):
    # agent parked on the ego's line, `gap` ahead of the ego's position after one step from rest
    env = IntersectionEnv(batch_size=1, agent_trajectories=_static_bank(EGO_X, -1.25 + gap))
    nxt = _step(env, 0.0)
    assert bool(nxt["collision"]) is expect
    assert bool(nxt["terminated"]) is expect
    if expect:
        assert nxt["reward"].item() == pytest.approx(-0.5 * 0.1 - 150.0)
        assert nxt["cost"].item() >= 150.0


def test_collision_uses_true_not_perceived_position():
    bank = _static_bank(EGO_X, -1.25 + 2 * R - 0.05)
    bank.observed[..., 0] = 3.0  # perceived far away, truly touching
    env = IntersectionEnv(batch_size=1, agent_trajectories=bank)
    assert bool(_step(env, 0.0)["collision"])


def test_success_and_goal_reward():
    env = IntersectionEnv(batch_size=1, agent_trajectories=_static_bank(-5.0, 10.0), v_max=3.0)
    td = env.reset()
    done_at, total = None, 0.0
    for k in range(40):
        td["action"] = torch.full((1, 1), 3.2 if td["observation"][0, 1] < 1.5 else 0.0)
        td = env.step(td)
        total += td["next", "reward"].item()
        if td["next", "done"].item():
            done_at = k
            break
        td = td["next"]
    assert done_at is not None
    assert bool(td["next", "success"]) and bool(td["next", "terminated"]) and not bool(td["next", "collision"])
    assert td["next", "observation"][0, 0] >= 1.25
    assert total > 200.0  # goal bonus plus progress, minus small penalties


def test_out_of_bounds_and_step_cap():
    env = IntersectionEnv(batch_size=1, agent_trajectories=_static_bank(-5.0, 10.0), v_min=-3.0)
    td = env.reset()
    for _ in range(60):
        td["action"] = torch.full((1, 1), -3.2)
        td = env.step(td)
        if td["next", "done"].item():
            break
        td = td["next"]
    assert bool(td["next", "out_of_bounds"]) and bool(td["next", "terminated"])
    assert td["next", "observation"][0, 0] < -6.0
    env = IntersectionEnv(batch_size=2, agent_trajectories=_static_bank(-5.0, 10.0, horizon=10), max_steps=10)
    td = env.rollout(10, break_when_any_done=False)
    assert td["next", "truncated"][:, -1].all() and not td["next", "terminated"].any()
    assert not td["next", "truncated"][:, :-1].any()


def test_cost_formula():
    y_agent, sigma = -1.0, 0.1
    env = IntersectionEnv(batch_size=1, agent_trajectories=_static_bank(EGO_X + 0.7, y_agent, sigma=sigma))
    nxt = _step(env, 1.0)
    y = nxt["observation"][0, 0].item()
    d2 = 0.7**2 + (y - y_agent) ** 2
    expect = 200.0 * max(0.0, (2 * R + math.sqrt(2) * sigma) ** 2 - d2)
    assert expect > 0
    assert nxt["cost"].item() == pytest.approx(expect, rel=1e-4)
    assert not bool(nxt["collision"])
    far = IntersectionEnv(batch_size=1, agent_trajectories=_static_bank(4.0, 0.5, sigma=sigma))
    assert _step(far, 1.0)["cost"].item() == 0.0


def test_reward_shaping_terms():
    env = IntersectionEnv(batch_size=1, agent_trajectories=_static_bank(-5.0, 10.0))
    nxt = _step(env, 2.0)  # v goes 0 -> 0.2
    expect = 25 * 0.2 * 0.1 - 0.5 * 0.1 - 0.697 * 2.0**2
    assert nxt["reward"].item() == pytest.approx(expect, rel=1e-5)
    # over-speed: start at 1.9 m/s
    env._state["v"][:] = 1.9
    td = TensorDict({"action": torch.zeros(1, 1)}, batch_size=[1])
    r = env.step(td)["next", "reward"].item()
    assert r == pytest.approx(25 * 1.9 * 0.1 - 0.05 - 90 * 0.4**2, rel=1e-5)
    # reversing: only a training config's w_reverse charges it beyond the lost progress
    for w in (0.0, 50.0):
        env = IntersectionEnv(batch_size=1, agent_trajectories=_static_bank(-5.0, 10.0), w_reverse=w)
        assert _step(env, -2.0)["reward"].item() == pytest.approx(
            25 * -0.2 * 0.1 - 0.05 - 0.697 * 4.0 - w * 0.2 * 0.1, rel=1e-5)
    with pytest.raises(ValueError, match="w_reverse"):
        IntersectionEnv(w_reverse=-1.0)


def test_rows_reset_independently_and_seeding():
    env = make_env("intersection", batch_size=16, seed=3)
    td = env.rollout(80, break_when_any_done=False, policy=lambda td: td.set("action", torch.full((16, 1), 1.2)))
    done = td["next", "done"].squeeze(-1)
    assert done.any()
    steps = td["step_count"].squeeze(-1)
    # after a done the row restarts at step 0 with the start position
    b, k = torch.nonzero(done[:, :-1], as_tuple=True)
    assert (steps[b, k + 1] == 0).all()
    assert torch.allclose(td["observation"][b, k + 1, 0], torch.tensor(-1.25))
    env2 = make_env("intersection", batch_size=16, seed=3)
    td2 = env2.rollout(20, break_when_any_done=False, policy=lambda td: td.set("action", torch.full((16, 1), 1.2)))
    assert torch.equal(td["observation"][:, :20], td2["observation"])


def test_sequential_sampling_assigns_rows_in_order():
    bank = make_test_set(2, horizon=500)
    env = IntersectionEnv(batch_size=8, agent_trajectories=bank, agent_sampling="sequential")
    td = env.reset()
    assert td["agent", "episode"].squeeze(-1).tolist() == list(range(8))
    assert td["agent", "behaviour"].squeeze(-1).tolist() == [0, 1, 2, 3] * 2


def test_invalid_arguments_name_the_field():
    with pytest.raises(ValueError, match="start_noise"):
        IntersectionEnv(start_noise=0.5)
    with pytest.raises(ValueError, match="agent_sampling"):
        IntersectionEnv(agent_sampling="shuffled")
    with pytest.raises(ValueError, match="behaviours"):
        sample_agent_trajectories(4, seed=0, behaviours=["reverse"])


# ---------------------------------------------------------------- agent model statistics
@pytest.fixture(scope="module")
def test_bank():
    return make_test_set(40, seed=7)


def test_agent_routes_go_where_they_should(test_bank):
    end = test_bank.true[:, -1, :2]
    beh = test_bank.behaviour
    straight, left, right, zz = (end[beh == i] for i in range(4))
    # straight and zigzag leave to the west on the lane y ~ 0.5
    assert (straight[:, 0] < -3).all() and ((straight[:, 1] - 0.5).abs() < 0.25).all()
    assert (zz[:, 0] < -3).all()
    # left turns end southbound on x ~ -0.5, right turns northbound on x ~ +0.5
    assert (left[:, 1] < -3).all() and ((left[:, 0] + 0.5).abs() < 0.25).all()
    assert (right[:, 1] > 3).all() and ((right[:, 0] - 0.5).abs() < 0.25).all()
    # all start east of the box on the westbound lane
    start = test_bank.true[:, 0, :2]
    assert (start[:, 0] > 1.5).all() and ((start[:, 1] - 0.5).abs() < 0.25).all()
    # every route passes within the collision distance of the ego's line inside the crossing
    traj = test_bank.true[..., :2]
    near = ((traj[..., 0] - EGO_X).abs() < 2 * R) & (traj[..., 1] > -1.25) & (traj[..., 1] < 1.8)
    assert near.any(dim=1).all()


def test_zigzag_weaves_and_straight_does_not(test_bank):
    beh = test_bank.behaviour
    inside = lambda tr: tr[(tr[:, 0] < 1.5) & (tr[:, 0] > -1.5)]  # noqa: E731
    zz_spread = [inside(t)[:, 1].std().item() for t in test_bank.true[beh == 3]]
    st_spread = [inside(t)[:, 1].std().item() for t in test_bank.true[beh == 0]]
    assert min(zz_spread) > 0.1 and max(st_spread) < 0.02


def test_agent_sigma_in_range_and_time_varying(test_bank):
    sig = test_bank.observed[..., 4:]
    assert sig.min() >= 0.02 - 1e-6 and sig.max() <= 0.35 + 1e-6
    assert (sig.std(dim=1) > 0).all()  # varies over time in every trajectory
    err = (test_bank.observed[..., :2] - test_bank.true[..., :2]).abs()
    # perception error is of the order of sigma: within 4 sigma almost always
    assert (err <= 4 * sig + 1e-6).float().mean() > 0.99


def test_agent_speeds_and_styles(test_bank):
    speed = test_bank.true[:, 5:60, 2:4].norm(dim=-1)
    plain = test_bank.behaviour != 3
    assert speed[plain].max() < 1.8  # human-like mobile-robot speeds
    assert speed[~plain].max() < 3.0  # weaving adds lateral speed
    assert test_bank.hesitate.any() and test_bank.yields.any() and not test_bank.yields.all()
    # a yielding agent comes to a full stop at some point
    y_idx = torch.nonzero(test_bank.yields).squeeze(-1)
    stops = [(test_bank.true[i, :150, 2:4].norm(dim=-1) < 0.02).any().item() for i in y_idx.tolist()]
    assert np.mean(stops) > 0.7


def test_splits_and_seeds():
    a = sample_agent_trajectories(16, seed=0, split="train")
    b = sample_agent_trajectories(16, seed=0, split="train")
    c = sample_agent_trajectories(16, seed=0, split="test", behaviours=["straight", "left", "right"])
    assert torch.equal(a.observed, b.observed)
    assert not torch.allclose(a.true[:, 0], c.true[:, 0])
    assert set(a.behaviour.tolist()) == {0, 1, 2}  # zig-zag is held out of training by default
    assert set(sample_agent_trajectories(8, seed=0, split="test").behaviour.tolist()) == set(range(len(BEHAVIOURS)))


def test_recorded_trajectories_roundtrip_and_errors(tmp_path):
    rows = np.zeros((40, 6))
    rows[:, 0] = np.linspace(3.0, -0.9, 40)
    rows[:, 1] = 0.5
    rows[:, 2] = -1.0
    rows[:, 4:] = 0.05
    p = tmp_path / "agent.npy"
    np.save(p, np.stack([rows, rows]))
    bank = load_recorded_trajectories(str(p), horizon=100)
    assert bank.true.shape == (2, 101, 4) and (bank.behaviour == 4).all()
    # continues at the last velocity after the recording ends
    assert bank.true[0, 100, 0].item() == pytest.approx(-0.9 - 61 * 0.1, abs=1e-4)
    env = IntersectionEnv(batch_size=2, agent_trajectories=str(p), max_steps=100)
    check_env_specs(env)
    bad = rows.copy()
    bad[3, 5] = -0.1
    with pytest.raises(ValueError, match="row 3 sigma_y"):
        load_recorded_trajectories(bad)
    bad = rows.copy()
    bad[7, 1] = np.nan
    with pytest.raises(ValueError, match="row 7 column y is not finite"):
        load_recorded_trajectories(bad)
    with pytest.raises(ValueError, match=r"shape \(40, 5\)"):
        load_recorded_trajectories([rows[:, :5]])
    with pytest.raises(FileNotFoundError, match="no file"):
        load_recorded_trajectories(str(tmp_path / "missing.npy"))
    with pytest.raises(ValueError, match="horizon"):
        IntersectionEnv(agent_trajectories=load_recorded_trajectories(rows, horizon=50), max_steps=100)


def test_recorded_trajectories_carry_perception_error_and_route_labels(tmp_path):
    rows = np.zeros((40, 8))
    rows[:, 0] = np.linspace(3.0, -0.9, 40)
    rows[:, 1] = 0.5
    rows[:, 2] = -1.0
    rows[:, 4:6] = 0.05
    rows[:, 6] = 0.2  # perceived 0.2 m east of where the agent is
    p = tmp_path / "agents.npy"
    np.save(p, {"trajectories": np.stack([rows, rows]), "routes": ["straight", "left"]}, allow_pickle=True)
    bank = load_recorded_trajectories(str(p), horizon=60)
    assert bank.behaviour.tolist() == [0, 1]  # per-route tables keep the labels
    assert torch.allclose(bank.observed[:, :40, 0] - bank.true[:, :40, 0], torch.tensor(0.2))
    with pytest.raises(ValueError, match="routes"):
        load_recorded_trajectories(rows, routes=["diagonal"])


def _drive(bank, accel: float, steps: int = 60):
    """Run every agent of ``bank`` against an ego holding ``accel`` (0: waits at the start); true x per step."""
    env = IntersectionEnv(batch_size=len(bank), agent_trajectories=bank, agent_sampling="sequential")
    td, xs = env.reset(), []
    for _ in range(steps):
        td["action"] = torch.full((len(bank), 1), accel)
        td = env.step(td)["next"]
        xs.append(td["agent", "true_pos"][:, 0].clone())
    return torch.stack(xs, 1)


def test_reactive_agents_answer_the_egos_motion():
    from mixed_traffic.envs.intersection_agents import REACTIVE_PARAMS

    bank = sample_agent_trajectories(3, seed=3, split="test", behaviours=["straight"], style="reactive")
    assert bank.reactive.all()
    a = REACTIVE_PARAMS.index("assertiveness")
    bank.params[:, a] = torch.tensor([0.1, 0.55, 0.95])  # yields, hesitates, speeds up
    bank.params[:, 0] = 3.5  # all start 3.5 m east
    bank.params[:, 1] = 1.0  # nominal 1 m/s
    bank.params[:, -1] = 1.0
    waits, goes = _drive(bank, 0.0), _drive(bank, 0.5)
    # with the ego waiting, every agent drives on alike
    assert torch.allclose(waits[0], waits[1]) and torch.allclose(waits[1], waits[2])
    # while the moving ego crosses: the yielder holds at its stop line, the hesitant one lags, the assertive
    # one is ahead of where it would be had the ego waited
    assert goes[0, 25] > waits[0, 25] + 0.5 and goes[1, 25] > waits[1, 25] + 0.5
    assert goes[2, 25] < waits[2, 25] - 0.1
    assert goes[0, -1] < 1.0  # the yielder goes on once the ego has crossed


def test_stop_in_zone_agents_stop_on_the_egos_line_then_go_on():
    bank = make_test_set(5, seed=11, behaviours=("straight", "left"), style="stop_in_zone")
    x = bank.true[:, :, 0]
    v = bank.true[:, :, 2:].norm(dim=-1)
    stopped = v < 1e-3
    first = stopped.float().argmax(1)
    x_stop = x[torch.arange(len(bank)), first]
    assert stopped.any(1).all() and ((x_stop > 0.1) & (x_stop < 0.5)).all()  # centre just past the ego's line
    assert (x[:, -1] < x_stop - 0.5).all()  # and it leaves later
    with pytest.raises(ValueError, match="behaviours"):
        make_test_set(1, behaviours=("right",), style="stop_in_zone")


def test_held_out_test_sets_have_200_episodes_each():
    from omegaconf import OmegaConf

    from mixed_traffic.intersection.evaluate import test_sets

    sets = test_sets(OmegaConf.create({"episodes": 80, "seed": 2024}))
    assert len(sets["standard"]) == 320 and len(sets["reactive"]) >= 200 and len(sets["stop_in_zone"]) >= 200
    assert sets["reactive"].reactive.all() and not sets["stop_in_zone"].reactive.any()
    train_env = IntersectionEnv(batch_size=1, agent_bank_size=64, reactive_fraction=0.25)
    assert int(train_env.bank.reactive.sum()) == 16  # reactive agents also drive in training


def test_pause_agents_stop_once_anywhere_from_the_stop_line_to_past_the_crossing():
    """The training style ``pause``: one stop of 0.5-10 s on the approach, inside the crossing or beyond it."""
    from mixed_traffic.envs.intersection_agents import STOP_LINE_X

    bank = sample_agent_trajectories(300, seed=5, split="train", style="pause")
    assert set(bank.behaviour.tolist()) == {0, 1, 2} and not bank.reactive.any()
    x = bank.true[:, :, 0]
    stopped = bank.true[:, :, 2:].norm(dim=-1) < 1e-3
    assert stopped.any(1).all()  # every agent pauses
    first = stopped.float().argmax(1)
    x_stop = x[torch.arange(len(bank)), first]
    assert (x_stop <= STOP_LINE_X + 1e-3).all()  # from its stop line on ...
    dur = stopped.sum(1) * 0.1
    assert dur.min() >= 0.4 and dur.max() <= 10.2
    # ... through the crossing: a share pause with the centre on the ego's line (west of it by < 0.45 m),
    # others on the approach or past the line
    on_line = (x_stop > 0.05) & (x_stop < 0.5) & (bank.behaviour < 2)
    assert 0.03 < on_line.float().mean() < 0.3 and (x_stop > 1.0).any() and (x_stop < -0.3).any()


def test_training_bank_is_drawn_from_the_train_split_and_shares_no_episode_with_the_test_sets():
    from omegaconf import OmegaConf

    from mixed_traffic.intersection.evaluate import test_sets

    env = IntersectionEnv(batch_size=1, agent_bank_size=400, hard_start_fraction=0.3, reactive_fraction=0.25,
                          pause_fraction=0.25, seed=0)
    assert env.agent_split == "train" and set(env.bank.behaviour.tolist()) == {0, 1, 2}
    assert int(env.bank.reactive.sum()) == 100
    again = sample_agent_trajectories(100, seed=130_363, split="train", style="pause")
    assert torch.equal(env.bank.observed[-100:], again.observed)  # the last quarter: pause agents, train stream
    starts = env.bank.true[:, 0, :2]
    for name, ts in test_sets(OmegaConf.create({"episodes": 80, "seed": 2024})).items():
        d = torch.cdist(ts.true[:, 0, :2].double(), starts.double())
        assert d.min() > 1e-6, name  # no test episode starts where a training agent does
    with pytest.raises(ValueError, match="pause_fraction"):
        IntersectionEnv(pause_fraction=1.5)
    with pytest.raises(ValueError, match="pause_fraction"):
        IntersectionEnv(hard_start_fraction=0.5, reactive_fraction=0.25, pause_fraction=0.5)


def test_exploring_starts_put_a_share_of_resets_along_the_path_moving():
    env = IntersectionEnv(batch_size=400, random_start_fraction=0.5, random_start_y=(-1.0, 0.5),
                          random_start_v=(0.5, 1.5), seed=3)
    y, v = env.reset()["observation"][:, :2].unbind(-1)
    moved = v > 0
    assert 0.4 < moved.float().mean() < 0.6
    assert ((y[moved] >= -1.0) & (y[moved] <= 0.5) & (v[moved] >= 0.5) & (v[moved] <= 1.5)).all()
    assert (y[~moved] == -1.25).all()  # the others start at rest on the start line (no start noise here)
    assert IntersectionEnv(batch_size=4).reset()["observation"][:, 1].abs().max() == 0  # off by default
    with pytest.raises(ValueError, match="random_start_v"):
        IntersectionEnv(random_start_fraction=0.2, random_start_v=(0.0, 5.0))
    with pytest.raises(ValueError, match="random_start_fraction"):
        IntersectionEnv(random_start_fraction=-0.1)
