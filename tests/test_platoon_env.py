"""The DeeP-LCC platoon training environment (``make_env("platoon")``)."""

import pytest
import torch
from torchrl.envs.utils import check_env_specs

from mixed_traffic import make_env
from mixed_traffic.controllers.deeplcc.closed_loop import run_closed_loop
from mixed_traffic.controllers.deeplcc.nnmpc import NNMPC, nnmpc_policy, numpy_controller
from mixed_traffic.controllers.deeplcc.platoon import PlatoonConfig
from mixed_traffic.validation import ConfigError


@pytest.mark.parametrize("mismatch", ["none", "idm", "hetero_ovm"])
def test_specs_and_window_shapes(mismatch):
    env = make_env("platoon", batch_size=3, seed=0, mismatch=mismatch, episode_seconds=3.0)
    check_env_specs(env)
    td = env.rollout(5)
    assert td["next", "uini"].shape == (3, 5, 40)
    assert td["next", "yini"].shape == (3, 5, 200)
    assert td["next", "eini"].shape == (3, 5, 20)
    assert td["next", "observation"].shape == (3, 5, 271)


def test_seeding_is_deterministic():
    def roll(seed):
        env = make_env("platoon", batch_size=4, seed=seed, episode_seconds=3.0)
        torch.manual_seed(0)  # the random policy
        return env.rollout(30, break_when_any_done=False)

    a, b, c = roll(5), roll(5), roll(6)
    assert torch.equal(a["next", "traffic", "speed"], b["next", "traffic", "speed"])
    assert torch.equal(a["next", "deeplcc", "kind"], b["next", "deeplcc", "kind"])
    assert not torch.equal(a["next", "traffic", "speed"], c["next", "traffic", "speed"])


def test_profiles_drawn_per_episode_and_rows_reset_alone():
    env = make_env("platoon", batch_size=64, seed=0, episode_seconds=2.0)
    td = env.rollout(env.scenario.max_steps + 3, lambda td: td.set("action", torch.zeros(64, 2)),
                     break_when_any_done=False)
    kinds = td["next", "deeplcc", "kind"][:, 0, 0]
    assert len(kinds.unique()) == 7  # every profile of the mix appears
    assert bool(td["next", "truncated"][:, env.scenario.max_steps - 1].all())
    # after the auto-reset each row has drawn a new episode (a new head profile)
    assert not torch.equal(td["deeplcc", "kind"][:, 0], td["deeplcc", "kind"][:, -1])


@pytest.mark.parametrize("kind,adaptive", [("brake", True), ("random5", False)])
def test_episode_is_the_closed_loop_of_the_deeplcc_package(kind, adaptive):
    """Rolled in the env, a controller meets the windows and costs of run_closed_loop."""
    torch.manual_seed(0)
    net = NNMPC().eval()
    env = make_env("platoon", batch_size=1, seed=3, profiles=[kind], randomize=False, accel_noise=0.0,
                   episode_seconds=8.0)
    with torch.no_grad():
        td = env.rollout(env.scenario.max_steps, nnmpc_policy(net), break_when_any_done=False)
    assert bool(td["next", "truncated"][0, -1])
    out = run_closed_loop(numpy_controller(net), env.head_v[:1].clone(), PlatoonConfig(accel_noise=0.0), 20,
                          adaptive_v_star=adaptive)
    assert float(td["next", "traffic", "J"].sum()) == pytest.approx(out["cost"][0], rel=1e-5)


def test_mismatch_changes_the_humans_not_the_head():
    def speeds(mismatch):
        env = make_env("platoon", batch_size=2, seed=1, mismatch=mismatch, profiles=["random5"], accel_noise=0.0,
                       episode_seconds=4.0)
        td = env.rollout(40, lambda td: td.set("action", torch.zeros(2, 2)))
        return td["next", "traffic", "speed"], env

    s_ovm, _ = speeds("none")
    s_idm, _ = speeds("idm")
    s_het, env = speeds("hetero_ovm")
    assert torch.equal(s_ovm[..., 0], s_idm[..., 0])  # same head
    assert (s_ovm[..., 1:] - s_idm[..., 1:]).abs().max() > 0.05
    assert (s_ovm[..., 1:] - s_het[..., 1:]).abs().max() > 0.01
    alpha = env.hdv["alpha"]
    assert alpha.std() > 0 and bool(((alpha - 0.6).abs() <= 0.2 * 0.6 + 1e-9).all())


def test_cost_is_the_spacing_violation():
    env = make_env("platoon", batch_size=1, seed=0, profiles=["brake"], randomize=False, accel_noise=0.0,
                   episode_seconds=15.0)
    td = env.rollout(env.scenario.max_steps, lambda td: td.set("action", torch.full((1, 2), 2.0)))
    gap = td["next", "cav", "gap"]
    expected = ((5.0 - gap.clamp_min(0)).clamp_min(0) / 5.0 + (gap - 40.0).clamp_min(0) / 40.0).sum(-1, keepdim=True)
    assert torch.allclose(td["next", "cost"], expected)
    assert float(td["next", "cost"].max()) > 0  # full throttle into a braking head violates s_min


@pytest.mark.parametrize("field,value", [("profiles", ["cruise"]), ("mismatch", "sumo"), ("hetero_spread", 1.5),
                                         ("episode_seconds", 0.5), ("profile_weights", [1.0])])
def test_bad_settings_name_the_field(field, value):
    with pytest.raises(ConfigError, match=field):
        make_env("platoon", batch_size=1, **{field: value})
