"""JoinBlend: a CAV that starts far behind joins under a smooth law and hands over to the policy's command."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import Compose, TransformedEnv
from torchrl.envs.utils import check_env_specs

from mixed_traffic import make_env
from mixed_traffic.config import compose
from mixed_traffic.controllers.classic import make_classic_policy, stopping_envelope_policy
from mixed_traffic.training.builders import make_transformed_env
from mixed_traffic.validation import ConfigError, parse_deploy_overrides, validate_config, with_deploy_overrides
from transforms import JoinBlend, ResidualAction

FAR, CLOSE = dict(init_spacing_range=[73.4, 73.4]), dict(init_spacing_range=[15.0, 15.0])


def _rollout(steps: int, *, join: bool, batch: int = 1, gap: float = 35.0, fade: float = 10.0,
             seconds: float | None = None, leader_speeds=None, **env_kw):
    """IDM (s0 2.5 m) drives the CAV through a residual of weight 0; with ``join`` an IDM of s0 7 m, v0 60 m/s
    inside the stopping envelope joins first."""
    base = make_env("ring", batch_size=batch, seed=0, **env_kw)
    ts = [ResidualAction(make_classic_policy("idm", base), weight=0.0)]
    if join:
        law = stopping_envelope_policy(make_classic_policy("idm", base, s0=7.0, v0=60.0), base, 5.0)
        ts.insert(0, JoinBlend(law, gap=gap, fade=fade, seconds=seconds, leader_speeds=leader_speeds,
                               dt=base.scenario.dt))
    env = TransformedEnv(base, Compose(*ts))
    with torch.no_grad():
        return env.rollout(steps, lambda td: td.set("action", torch.zeros(batch, 1)), break_when_any_done=False)


def test_specs_hold():
    base = make_env("ring", batch_size=2, seed=0, **FAR)
    law = make_classic_policy("idm", base, s0=7.0)
    check_env_specs(TransformedEnv(base, Compose(JoinBlend(law, dt=base.scenario.dt),
                                                 ResidualAction(make_classic_policy("idm", base), weight=0.5))))


def test_the_join_law_drives_until_the_gap_reaches_the_band_then_hands_over_over_the_fade():
    td = _rollout(600, join=True, gap=35.0, fade=10.0, **FAR)
    gap, share = td["cav", "gap"][0, :, 0], td["next", "join", "share"][0, :, 0]
    executed, policy = td["next", "cav", "accel"][0, :, 0], td["next", "residual", "base_action"][0, :, 0]
    first = int((gap <= 35.0).nonzero().min())  # the first step at or below the join's gap
    assert 10 < first < 400
    assert bool((share[:first] == 0).all())
    assert float(share[first]) == pytest.approx(0.01)  # dt / fade
    assert bool((share[first + 99:] == 1).all()) and bool((share[first:first + 99] < 1).all())
    assert float((executed[:first] - policy[:first]).abs().max()) > 0.1  # the join law drove, not the policy
    torch.testing.assert_close(executed[first + 100:], policy[first + 100:], atol=1e-5, rtol=0)


def test_a_cav_that_starts_close_is_driven_by_the_policy_from_the_first_step():
    joined, plain = _rollout(200, join=True, **CLOSE), _rollout(200, join=False, **CLOSE)
    assert bool((joined["next", "join", "share"] == 1).all())
    torch.testing.assert_close(joined["next", "cav", "accel"], plain["next", "cav", "accel"], atol=0, rtol=0)


def test_seconds_start_the_handover_at_the_latest_at_that_time():
    td = _rollout(300, join=True, gap=1.0, seconds=5.0, fade=10.0, **FAR)  # a gap the CAV never reaches
    share = td["next", "join", "share"][0, :, 0]
    assert bool((share[:50] == 0).all()) and float(share[50]) > 0  # the step that starts at 5 s
    assert bool((share[149:] == 1).all()) and float(share[148]) < 1
    never = _rollout(300, join=True, gap=1.0, **FAR)["next", "join", "share"]
    assert bool((never == 0).all())


def test_leader_speeds_leave_a_join_behind_a_slow_leader_to_the_policy():
    slow = dict(FAR, profile="piecewise", profile_kwargs={"times": [0, 400], "speeds": [12, 12]})
    gated = _rollout(300, join=True, leader_speeds=(16.0, 20.0), **slow)
    plain = _rollout(300, join=False, **slow)
    assert float(gated["next", "join", "share"][0, 0, 0]) == 0.0  # joining, but the leader is below v_off
    torch.testing.assert_close(gated["next", "cav", "accel"], plain["next", "cav", "accel"], atol=0, rtol=0)
    base = make_env("ring", batch_size=1, seed=0)
    join = JoinBlend(make_classic_policy("idm", base), gap=35.0, leader_speeds=(16.0, 20.0))
    a, a_join, gap, share = (torch.tensor([0.5, 0.5, 0.5]), torch.tensor([-0.5, -0.5, -0.5]),
                             torch.full((3,), 60.0), torch.zeros(3))
    executed, _ = join.apply(a, a_join, gap, share, leader_speed=torch.tensor([12.0, 18.0, 25.0]))
    torch.testing.assert_close(executed, torch.tensor([0.5, 0.0, -0.5]))  # the policy, half and half, the law


def test_a_partial_reset_keeps_the_other_rows_state():
    base = make_env("ring", batch_size=2, seed=0, **FAR)
    join = JoinBlend(make_classic_policy("idm", base), gap=35.0)
    state = TensorDict({("join", "share"): torch.tensor([[0.5], [0.5]]), "_reset": torch.tensor([[True], [False]])},
                       batch_size=[2])
    out = join._reset(state, TensorDict({("cav", "gap"): torch.tensor([[73.4], [73.4]])}, batch_size=[2]))
    assert out["join", "share"].flatten().tolist() == [0.0, 0.5]


@pytest.mark.parametrize("kwargs, match", [
    ({"gap": 0.0}, r"JoinBlend: gap=0.0 is invalid; allowed: > 0"),
    ({"fade": -1.0}, r"JoinBlend: fade=-1.0 is invalid; allowed: > 0"),
    ({"seconds": 0.0}, r"JoinBlend: seconds=0.0 is invalid; allowed: > 0 \(s\), or None"),
    ({"leader_speeds": (20.0, 16.0)}, r"JoinBlend: leader_speeds=\(20.0, 16.0\) is invalid; allowed: \(v_off, v_on\)"),
])
def test_bad_settings_name_the_argument(kwargs, match):
    base = make_env("ring", batch_size=1, seed=0)
    with pytest.raises(ValueError, match=match):
        JoinBlend(make_classic_policy("idm", base), **kwargs)


JOIN = ["transforms.residual.join.base=idm", "+transforms.residual.join.params.s0=7.0"]


def test_the_config_puts_it_between_the_cap_and_the_residual_at_deployment_only():
    cfg = validate_config(compose(["experiment=ring_lagrangian_ppo_cap_hold", *JOIN]))
    deployed = [type(t).__name__ for t in make_transformed_env(cfg, num_envs=2, seed=0, deploy=True).transform]
    assert deployed[deployed.index("SafetyLayer"):deployed.index("ResidualAction") + 1] == \
        ["SafetyLayer", "DriveOffCap", "JoinBlend", "ResidualAction"]
    trained = [type(t).__name__ for t in make_transformed_env(cfg, num_envs=1, seed=0).transform]
    assert "JoinBlend" not in trained
    off = validate_config(compose(["experiment=ring_lagrangian_ppo_cap_hold"]))
    assert "JoinBlend" not in [type(t).__name__ for t in make_transformed_env(off, num_envs=1, seed=0, deploy=True).transform]


@pytest.mark.parametrize("override, match", [
    ("transforms.residual.join.gap=-1.0", r"transforms.residual.join.gap: -1.0 is out of range"),
    ("transforms.residual.join.when=never", r"transforms.residual.join.when"),
    ("transforms.residual.join.base=gipps", r"transforms.residual.join.base"),
    ("transforms.residual.join.leader_speeds=[20.0,16.0]", r"transforms.residual.join.leader_speeds: \[20.0, 16.0\]"),
    ("+transforms.residual.join.params.s00=7.0", r"transforms.residual.join.params.s00: is not a idm parameter"),
])
def test_bad_config_fails_at_start_up_naming_the_field(override, match):
    with pytest.raises(ConfigError, match=match):
        validate_config(compose(["experiment=ring_lagrangian_ppo_cap_hold", "transforms.residual.join.base=idm",
                                 override]))


def test_a_deployed_join_law_takes_parameters_the_run_never_set_and_refuses_typos():
    run = validate_config(compose(["experiment=ring_lagrangian_ppo_cap_hold"]))
    cfg = with_deploy_overrides(run, [("transforms.residual.join.base", "idm"),
                                      ("transforms.residual.join.params.T", 0.8)])
    assert cfg.transforms.residual.join.params.T == 0.8
    with pytest.raises(ConfigError, match=r"transforms.residual.join.params.TT: is not a idm parameter"):
        with_deploy_overrides(run, [("transforms.residual.join.base", "idm"), ("transforms.residual.join.params.TT", 1.0)])
    with pytest.raises(ConfigError, match=r"transforms.residual.join.gapp: not a setting of the run's config"):
        with_deploy_overrides(run, [("transforms.residual.join.gapp", 30.0)])
    # the fast leader's join law (fast_params) takes a parameter the run never set, as params does, and refuses typos
    fast = validate_config(compose(["experiment=ring_lagrangian_ppo_fast_band"]))
    cfg = with_deploy_overrides(fast, [("transforms.residual.join.fast_params.b", 1.0)])
    assert dict(cfg.transforms.residual.join.fast_params) == {"v0": 60.0, "gap_max": 27.0, "b": 1.0}
    with pytest.raises(ConfigError, match=r"transforms.residual.join.fast_params.bb: is not a idm parameter"):
        with_deploy_overrides(fast, [("transforms.residual.join.fast_params.bb", 1.0)])
    # mt-eval passes Hydra's "+" with a parameter the config does not list; only a law's parameter may be appended
    assert parse_deploy_overrides(["+transforms.residual.join.fast_params.b=1.5"]) == \
        [("transforms.residual.join.fast_params.b", 1.5)]
    with pytest.raises(ConfigError, match=r"^\+transforms.residual.join.gapp=30.0: not a deployed setting"):
        parse_deploy_overrides(["+transforms.residual.join.gapp=30.0"])


def test_join_is_cap_hold_with_the_deployed_join_and_nothing_else():
    """``experiment=ring_lagrangian_ppo_join`` (the previous default) is ``ring_lagrangian_ppo_cap_hold`` with the
    join of the long start (IDM s0 7 m, v0 60 m/s, T 0.8 s, b 3 m/s^2, steady gap at most 27 m; handed over at 40 m
    or 15 s, over 10 s; behind leaders above 16 m/s)."""
    from omegaconf import OmegaConf, open_dict

    d, prev = (compose([f"experiment={n}"]) for n in ("ring_lagrangian_ppo_join", "ring_lagrangian_ppo_cap_hold"))
    validate_config(d)
    j = d.transforms.residual.join
    assert (j.base, dict(j.params), j.gap, j.fade, j.seconds, list(j.leader_speeds), j.when) == \
        ("idm", {"s0": 7.0, "v0": 60.0, "T": 0.8, "b": 3.0, "gap_max": 27.0}, 40.0, 10.0, 15.0, [16.0, 20.0], "deploy")
    with open_dict(d):
        d.transforms.residual.join, d.name = prev.transforms.residual.join, prev.name
    assert OmegaConf.to_container(d) == OmegaConf.to_container(prev)

def _cav_state(env, gap, speed, leader_speed):
    """A reset tensordict of ``env`` with the CAV's gap, speed and leader speed set (``[batch, 1]`` each)."""
    td = env.reset()
    td["cav", "gap"], td["cav", "speed"], td["cav", "leader_speed"] = gap, speed, leader_speed
    return td


def _command(law, td):
    """``law``'s acceleration at ``td`` (on a copy), ``[batch, 1]``."""
    return law(td.clone())[law.out_keys[0]]


def _deployed_join_law(cfg, env):
    from mixed_traffic.training.builders import join_blend

    return join_blend(cfg.transforms.residual, env).law


def test_idm_join_joins_under_idm_cavs_own_law_where_the_capped_law_brakes_later():
    """``experiment=ring_lagrangian_ppo_idm_join`` (tried, not the default) is ``ring_lagrangian_ppo_apg60`` whose
    deployed join law is IDM_cav (s0 7 m, v0 40 m/s, b 2 m/s^2, T 1 s, no headway cap): its command equals IDM_cav's
    wherever the stopping envelope leaves it alone. In the long start's overshoot (the CAV faster than its leader,
    still far behind) the default's law (v0 60 m/s, headway capped at a 27-m steady gap) wants a smaller gap and more
    speed, so it brakes later."""
    from tests.test_config import assert_differs_only_in

    apg60, idm_join = (validate_config(compose([f"experiment=ring_lagrangian_ppo_{n}"])) for n in ("apg60", "idm_join"))
    assert_differs_only_in(idm_join, apg60, {"transforms.residual.join.params.v0": 40.0,
                                             "transforms.residual.join.params.gap_max": None})
    env = make_env("ring", batch_size=4, seed=0)
    td = _cav_state(env, torch.tensor([[60.0], [45.0], [30.0], [24.0]]), torch.tensor([[22.0], [21.0], [19.0], [17.0]]),
                    torch.tensor([[17.0], [17.0], [17.0], [16.0]]))
    joined, capped = (_command(_deployed_join_law(cfg, env), td) for cfg in (idm_join, apg60))
    torch.testing.assert_close(joined, _command(make_classic_policy("idm", env, s0=7.0, v0=40.0, b=2.0), td))
    assert bool((capped > joined + 0.05).all()), (capped, joined)


def test_paced_join_schedules_the_join_law_on_the_leaders_speed():
    """``experiment=ring_lagrangian_ppo_paced_join`` is ``ring_lagrangian_ppo_idm_join`` with ``fast_params`` and
    ``fast_leader_speeds`` [19, 21]: behind a leader at or below 19 m/s its join law commands IDM_cav's acceleration,
    behind one at or above 21 m/s the default's capped law's, and the average of the two at 20 m/s, whatever the
    CAV's own speed (it is the leader's speed that picks the law)."""
    from tests.test_config import assert_differs_only_in

    apg60, idm_join, paced = (validate_config(compose([f"experiment=ring_lagrangian_ppo_{n}"]))
                              for n in ("apg60", "idm_join", "paced_join"))
    assert_differs_only_in(paced, idm_join, {"transforms.residual.join.fast_params": {"v0": 60.0, "gap_max": 27.0},
                                             "transforms.residual.join.fast_leader_speeds": [19.0, 21.0]})
    env = make_env("ring", batch_size=3, seed=0)
    td = _cav_state(env, torch.full((3, 1), 60.0), torch.full((3, 1), 24.0), torch.tensor([[18.0], [20.0], [22.0]]))
    slow, capped, mixed = (_command(_deployed_join_law(cfg, env), td)[:, 0] for cfg in (idm_join, apg60, paced))
    assert bool((capped - slow).abs().min() > 0.05), (capped, slow)  # the two laws differ at these states
    torch.testing.assert_close(mixed[0], slow[0])
    torch.testing.assert_close(mixed[2], capped[2])
    torch.testing.assert_close(mixed[1], 0.5 * (slow[1] + capped[1]))


@pytest.mark.parametrize("overrides, match", [
    (["+transforms.residual.join.fast_params.v00=60.0", "transforms.residual.join.fast_leader_speeds=[19.0,21.0]"],
     r"transforms.residual.join.fast_params.v00: is not a idm parameter"),
    (["+transforms.residual.join.fast_params.v0=60.0"],
     r"transforms.residual.join.fast_leader_speeds: None.*set together with transforms.residual.join.fast_params"),
    (["+transforms.residual.join.fast_params.v0=60.0", "transforms.residual.join.fast_leader_speeds=[21.0,19.0]"],
     r"transforms.residual.join.fast_leader_speeds: \[21.0, 19.0\].*0 <= v1 < v2"),
])
def test_a_bad_fast_join_law_fails_at_start_up_naming_the_field(overrides, match):
    with pytest.raises(ConfigError, match=match):
        validate_config(compose(["experiment=ring_lagrangian_ppo_idm_join", *overrides]))
