import pytest
import torch
from tensordict.nn import TensorDictModule
from torchrl.envs.utils import check_env_specs

from mixed_traffic import make_env
from mixed_traffic.scenarios import get_scenario


def constant(batch, n_cav, value):
    """A policy commanding the same acceleration to every CAV."""
    return TensorDictModule(lambda obs: torch.full((batch, n_cav), value), in_keys=["observation"], out_keys=["action"])


@pytest.mark.parametrize("scenario", ["ring", "deeplcc"])
@pytest.mark.parametrize("batch", [1, 16])
def test_check_env_specs(scenario, batch):
    check_env_specs(make_env(scenario, batch_size=batch, seed=0))


@pytest.mark.parametrize("observation", ["seed", "relative", "relative_accel", "relative_no_speed", "relative_time"])
def test_observation_modes(observation):
    env = make_env("ring", batch_size=4, seed=0, observation=observation)
    check_env_specs(env)
    td = env.reset()
    if observation == "seed":
        # [v/30, p/L]: all start at 10 m/s
        assert torch.allclose(td["observation"][:, :4], torch.full((4, 4), 10.0 / 30.0))


def test_relative_accel_observes_the_leaders_last_acceleration():
    """``observation="relative_accel"``: ``"relative"`` plus the leader's acceleration / a_max (V2V, as in CACC)."""
    kw = dict(batch_size=4, seed=0, profile="sine", profile_kwargs={})
    rel = make_env("ring", observation="relative", **kw)
    acc = make_env("ring", observation="relative_accel", **kw)
    act = lambda td: td.set("action", torch.full((4, 1), 0.5))  # noqa: E731
    a, b = rel.rollout(60, act), acc.rollout(60, act)
    assert torch.equal(b["next", "observation"][..., :7], a["next", "observation"])
    lead = b["next", "traffic", "accel"][..., 0] / 3.0  # the CAV (index 1) follows the head
    assert float(lead.abs().max()) > 0.1  # the sine head does accelerate
    assert torch.allclose(b["next", "observation"][..., 7], lead)
    assert torch.equal(a["next", "cav", "leader_accel"][..., 0], b["next", "traffic", "accel"][..., 0])  # in m/s^2
    with pytest.raises(ValueError, match="observation"):
        make_env("ring_wave", batch_size=1, seed=0, observation="relative_accel")  # no head to follow
    # "relative_no_speed": the same features less the CAV's own speed
    c = make_env("ring", observation="relative_no_speed", **kw).rollout(60, act)
    assert torch.equal(c["next", "observation"], a["next", "observation"][..., 1:])
    # "relative_time": the same features plus the time since engaging / 30 s, saturating at 1,
    # and back to 0 when an episode starts again
    env = make_env("ring", observation="relative_time", episode_seconds=40.0, **kw)
    d = env.rollout(500, act, break_when_any_done=False)
    assert torch.equal(d["next", "observation"][:, :60, :7], a["next", "observation"])
    t = d["next", "traffic", "time"][..., 0]
    assert torch.allclose(d["next", "observation"][..., 7], (t / 30.0).clamp(max=1.0))
    assert float(d["observation"][:, 0, 7].abs().max()) == 0.0 and float(d["observation"][:, 450, 7].max()) < 1.0


def test_reset_accel_model_starts_from_the_drivers_commands_and_leaves_the_motion_alone():
    """``reset_accel="model"``: at reset every car reports the command its model gives at the start
    state (the CAV: the humans' IDM, as if it had been driving) instead of 0, and the CAV's own
    acceleration feature of the first observation says so; positions and speeds are those of
    ``"zero"`` to the bit under the same actions."""
    from mixed_traffic.physics import IDMParams, idm_accel

    kw = dict(batch_size=3, seed=0, profile="sine", profile_kwargs={}, observation="relative",
              init_spacing_rows=(8.0, 40.0, 73.4))
    zero, model = make_env("ring", **kw), make_env("ring", reset_accel="model", **kw)
    z, m = zero.reset(), model.reset()
    assert float(z["traffic", "accel"].abs().max()) == 0.0
    p = IDMParams()
    gap, v = m["traffic", "gap"], m["traffic", "speed"]
    want = idm_accel(gap[:, 1], v[:, 1], v[:, 0], v0=p.v0, T=p.T, a=p.a, b=p.b, delta=p.delta, s0=p.s0)
    assert torch.allclose(m["cav", "accel"][:, 0], want.clamp(-3.0, 3.0))
    assert float(m["cav", "accel"][2, 0]) > 1.0 and float(m["cav", "accel"][0, 0]) < 0.0  # far: speeds up; close: brakes
    assert torch.allclose(m["observation"][:, -1], m["cav", "accel"][:, 0] / 3.0)
    assert float(m["traffic", "accel"][:, 0].min()) > 1.0  # the sine head's first command
    act = lambda td: td.set("action", torch.full((3, 1), 0.3))  # noqa: E731
    a, b = zero.rollout(50, act, tensordict=z), model.rollout(50, act, tensordict=m)
    for key in (("next", "traffic", "pos"), ("next", "traffic", "speed"), ("next", "traffic", "accel")):
        assert torch.equal(a[key], b[key])


def test_ring_preset_matches_the_seed_layout():
    env = make_env("ring", batch_size=2, seed=0)
    sc = env.scenario
    assert (sc.ring_length, sc.n_vehicles, sc.cav_indices, sc.dt, sc.max_steps) == (313.65, 4, (1,), 0.1, 5000)
    td = env.reset()
    assert torch.all(td["traffic", "speed"] == 10.0)
    gaps = td["traffic", "gap"]
    assert torch.allclose(gaps, torch.full_like(gaps, 313.65 / 4 - 5.0))


def test_same_seed_same_trajectory_and_rows_differ():
    def run(seed):
        env = make_env("ring", batch_size=4, seed=seed)
        torch.manual_seed(0)
        return env.rollout(400, break_when_any_done=False)["next", "traffic", "speed"]

    a, b, c = run(1), run(1), run(2)
    assert torch.equal(a, b)
    assert not torch.equal(a, c)
    head = a[:, -1, 0]  # after 40 s the rows' random head speeds differ
    assert head.unique().numel() == 4


def test_collision_terminates_only_that_row_and_it_restarts():
    env = make_env("ring", batch_size=3, seed=0)
    td = env.reset()
    hit = None
    for _ in range(400):
        a = torch.tensor([[3.0], [0.0], [0.0]])  # row 0 drives into its leader
        td["action"] = a
        full, td = env.step_and_maybe_reset(td)
        if full["next", "collision"].any():
            hit = full["next"]
            break
    assert hit is not None, "a CAV at +3 m/s^2 must reach its leader"
    assert hit["collision"].squeeze(-1).tolist() == [True, False, False]
    assert hit["terminated"].squeeze(-1).tolist() == [True, False, False]
    assert hit["reward"].isfinite().all()
    # the row restarted: initial spacing and speeds; the others carried on
    assert torch.allclose(td["traffic", "speed"][0], torch.full((4,), 10.0))
    assert td["traffic", "time"][0].item() == 0.0 and td["traffic", "time"][1].item() > 1.0


def test_truncation_at_episode_length():
    env = make_env("ring", batch_size=2, seed=0, episode_seconds=1.0)
    td = env.rollout(12, break_when_any_done=False)
    trunc = td["next", "truncated"][0, :, 0]
    assert trunc[9].item() and not trunc[8].item()
    assert not td["next", "terminated"].any()


def test_speeds_never_negative_and_accel_within_bounds():
    env = make_env("ring", batch_size=64, seed=0)
    td = env.rollout(300, constant(64, 1, -3.0), break_when_any_done=False)
    assert (td["next", "traffic", "speed"] >= 0).all()
    acc = td["next", "cav", "accel"]
    assert (acc >= -3.0 - 1e-5).all() and (acc <= 3.0 + 1e-5).all()


def test_actions_outside_bounds_are_clipped():
    env = make_env("ring", batch_size=1, seed=0)
    td = env.reset().set("action", torch.tensor([[50.0]]))
    assert env.step(td)["next", "cav", "accel"].item() == pytest.approx(3.0)


def test_head_never_drives_into_its_leader_on_a_ring():
    # a short crowded ring: the head's profile asks for 20 m/s but the car ahead (last) brakes to a stop
    env = make_env("ring", batch_size=8, seed=0, ring_length=60.0, n_vehicles=4,
                   profile="constant", profile_kwargs={"v": 20.0})
    td = env.rollout(600, constant(8, 1, -3.0), break_when_any_done=False)
    assert not td["next", "collision"].any()


def test_reward_and_cost_terms():
    env = make_env("ring", batch_size=2, seed=0, weight_v=1.0, weight_s=0.5, weight_u=0.2)
    td = env.reset().set("action", torch.zeros(2, 1))
    nxt = env.step(td)["next"]
    sc = env.scenario
    v, gap, veq = nxt["traffic", "speed"], nxt["traffic", "gap"], nxt["traffic", "v_eq"]
    j = ((v[:, 1:] - veq) ** 2).sum(-1) + 0.5 * ((gap[:, 1] - 20).clamp(-20, 20) ** 2) + 0.2 * nxt["cav", "accel"][:, 0] ** 2
    assert torch.allclose(-nxt["reward"][:, 0], j)
    assert torch.all(nxt["cost"] == 0)
    assert env.J_max == pytest.approx(1 * 3 * 15**2 + 0.5 * 20**2 + 0.2 * 9)
    assert sc.s_min == 5.0


def test_deeplcc_preset_starts_at_equilibrium():
    env = make_env("deeplcc", batch_size=2, seed=0, profile="constant", profile_kwargs={"v": 15.0})
    td = env.rollout(200, constant(2, 2, 0.0), break_when_any_done=False)
    assert torch.allclose(td["next", "traffic", "speed"], torch.full_like(td["next", "traffic", "speed"], 15.0), atol=1e-4)
    gap = td["next", "traffic", "gap"][..., 1:]
    assert torch.allclose(gap, torch.full_like(gap, 15.0), atol=1e-3)
    assert env.scenario.cav_indices == (3, 6)


@pytest.mark.parametrize(
    "overrides, field",
    [
        (dict(ring_length=-5.0), "ring_length"),
        (dict(n_vehicles=60), "n_vehicles"),
        (dict(cav_indices=(4,)), "cav_indices"),
        (dict(dt=0.0), "dt"),
        (dict(hdv_model="krauss"), "hdv_model"),
        (dict(cav_accel_bounds=(1.0, 3.0)), "cav_accel_bounds"),
        (dict(ringlength=300.0), "unknown override"),
        (dict(reset_accel="idm"), "reset_accel"),
    ],
)
def test_bad_input_names_the_field(overrides, field):
    with pytest.raises(ValueError, match=field):
        make_env("ring", **overrides)


def test_unknown_preset_and_bad_action_shape():
    with pytest.raises(ValueError, match="unknown preset|unknown 'highway'"):
        make_env("highway")
    env = make_env("ring", batch_size=2)
    td = env.reset().set("action", torch.zeros(2, 3))
    with pytest.raises(ValueError, match=r"action: shape \(2, 3\)"):
        env.step(td)


def test_scenario_overrides_reach_the_env():
    sc = get_scenario("ring", ring_length=260.0, n_vehicles=6, cav_indices=[2, 4])
    env = make_env("ring", batch_size=2, ring_length=260.0, n_vehicles=6, cav_indices=[2, 4])
    assert env.scenario == sc
    assert env.action_spec.shape == (2, 2)
    check_env_specs(env)


def test_v_eq_is_the_rolling_mean_of_head_speed():
    env = make_env("ring", batch_size=1, seed=0, profile="constant", profile_kwargs={"v": 10.0}, v_eq_window=2.0)
    td = env.rollout(60, constant(1, 1, 0.0), break_when_any_done=False)
    head = torch.cat([td["traffic", "speed"][0, :1, 0], td["next", "traffic", "speed"][0, :, 0]])
    v_eq = td["next", "traffic", "v_eq"][0, :, 0]
    for k in (0, 5, 19, 20, 21, 59):  # window of 20 steps, including the reset speed at first
        lo = max(0, k + 1 - 19)
        assert v_eq[k].item() == pytest.approx(head[lo : k + 2].mean().item(), abs=1e-5), k
    assert v_eq[-1].item() == pytest.approx(10.0, abs=1e-5)


# ----------------------------------------------------------------------------- SUMO's speed mode 95 (sumo_safety)
CONST_HEAD = dict(profile="constant", profile_kwargs={"v": 10.0})


def _drive(env, accel, steps):
    td = env.reset()
    tds = []
    for _ in range(steps):
        td["action"] = torch.full((env.batch_size[0], env.scenario.n_cav), accel)
        out = env.step(td)
        tds.append(out["next"].clone())
        td = out["next"]
        if bool(td["done"].any()):
            break
    return torch.stack(tds, 1)


def test_sumo_safety_caps_an_always_accelerating_cav_and_counts_the_overrides():
    # speed mode 0 (default): +3 m/s^2 into a 10 m/s head collides (step 70)
    raw = _drive(make_env("ring", seed=0, **CONST_HEAD), 3.0, 600)
    assert raw["collision"][0, -1].item() and raw.shape[1] == 70
    env = make_env("ring", batch_size=2, seed=0, sumo_safety=True, **CONST_HEAD)
    check_env_specs(env)
    td = _drive(env, 3.0, 600)
    assert td.shape[1] == 600 and not td["collision"].any()
    assert td["cav", "gap"].min() > 2.5  # Krauss keeps the vType's minGap
    over = td["cav", "override"]
    assert over.dtype == torch.float32 and set(over.unique().tolist()) <= {0.0, 1.0}
    # overridden exactly where the executed acceleration is below the command
    assert torch.equal(over.bool(), td["cav", "accel"] < 3.0 - 1e-3)
    assert env.override_steps == int(over.sum()) == env.override_count and env.override_steps > 0.9 * 1200
    # a command below the safe speed runs unchanged
    td = _drive(make_env("ring", seed=0, sumo_safety=True, **CONST_HEAD), -1.0, 30)
    assert torch.allclose(td["cav", "accel"], torch.full_like(td["cav", "accel"], -1.0), atol=1e-4)
    assert not td["cav", "override"].any()


def test_sumo_safety_off_has_no_override_key_and_bad_integration_is_refused():
    assert ("cav", "override") not in make_env("ring", seed=0).observation_spec.keys(True)
    with pytest.raises(ValueError, match="integration"):
        make_env("ring", seed=0, sumo_safety=True, integration="ballistic")
    with pytest.raises(ValueError, match="sumo_safety"):
        make_env("ring", seed=0, sumo_safety="yes")


def test_sumo_safety_from_the_hydra_config():
    from mixed_traffic.config import compose
    from mixed_traffic.training.builders import make_transformed_env

    for override in ("env.sumo_safety=true", "env.overrides.sumo_safety=true"):
        cfg = compose(["experiment=ring_dqn", override, "trainer.num_envs=2"])
        env = make_transformed_env(cfg, num_envs=2, seed=0)
        assert env.base_env.scenario.sumo_safety
        assert ("cav", "override") in env.rollout(3)["next"].keys(True)
