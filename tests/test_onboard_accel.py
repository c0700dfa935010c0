"""The leader's acceleration from on-board measurements (transforms.OnboardLeaderAccel, transforms.onboard_accel):
what it replaces, when, what it estimates, and that a dead link then costs the deployed CAV nothing."""

from __future__ import annotations

import pytest
import torch
from torchrl.envs import Compose, TransformedEnv
from torchrl.envs.utils import check_env_specs

from mixed_traffic import make_env
from mixed_traffic.config import compose
from mixed_traffic.validation import ConfigError, parse_deploy_overrides, validate_config, with_deploy_overrides
from transforms import OnboardLeaderAccel, V2VChannel

SINE = dict(profile="sine", profile_kwargs={"v_star": 12.5, "amplitude": 5.0, "period": 10.0})
KEY = ("next", "cav", "leader_accel")


def _rollouts(*transforms, steps: int = 60, batch: int = 2):
    act = lambda td: td.set("action", torch.zeros(batch, 1))  # noqa: E731
    got = TransformedEnv(make_env("ring", batch_size=batch, seed=0, **SINE), Compose(*transforms)).rollout(steps, act)
    sent = make_env("ring", batch_size=batch, seed=0, **SINE).rollout(steps, act)
    return got, sent[KEY]


def test_specs_hold():
    for ts in ((OnboardLeaderAccel(dt=0.1),), (V2VChannel(loss=1.0), OnboardLeaderAccel(dt=0.1, after=0.3, tau=0.5)),
               (OnboardLeaderAccel(dt=0.1, after=None),)):
        check_env_specs(TransformedEnv(make_env("ring", batch_size=2, seed=0, **SINE), Compose(*ts)))


def test_over_a_dead_link_the_estimate_is_the_perfect_links_value_once_the_held_one_is_old():
    got, sent = _rollouts(V2VChannel(loss=1.0), OnboardLeaderAccel(dt=0.1, after=0.5))
    recv, used = got[KEY], got["next", "onboard_accel", "used"]
    assert sent.abs().max() > 1.0  # the leader does accelerate
    assert got["next", "v2v", "age"][0, :, 0].tolist() == list(range(1, 61))  # nothing arrives: one step older each
    assert not used[:, :5].any() and used[:, 5:].all()  # older than 0.5 s from the 6th step on
    assert torch.equal(recv[:, :5], torch.zeros_like(recv[:, :5]))  # until then the held reset value
    assert torch.allclose(recv[:, 5:], sent[:, 5:], atol=1e-4)  # then the measured speed's change: exact here
    alone, _ = _rollouts(V2VChannel(loss=1.0))
    assert torch.equal(alone[KEY], torch.zeros_like(alone[KEY]))  # without it the CAV holds 0 all episode


def test_it_replaces_nothing_over_a_live_link_and_everything_without_v2v():
    got, sent = _rollouts(OnboardLeaderAccel(dt=0.1))  # no channel: the perfect link
    assert torch.equal(got[KEY], sent) and not got["next", "onboard_accel", "used"].any()
    got, sent = _rollouts(OnboardLeaderAccel(dt=0.1, after=None))  # a CAV without V2V
    assert got["next", "onboard_accel", "used"].all() and torch.allclose(got[KEY], sent, atol=1e-4)
    # a message 1 s late is kept at after=1.0 and replaced at after=0.5
    late, sent = _rollouts(V2VChannel(delay_steps=10), OnboardLeaderAccel(dt=0.1, after=1.0))
    assert torch.equal(late[KEY][:, 10:], sent[:, :-10]) and not late["next", "onboard_accel", "used"][:, 10:].any()
    fresh, _ = _rollouts(V2VChannel(delay_steps=10), OnboardLeaderAccel(dt=0.1, after=0.5))
    assert torch.allclose(fresh[KEY][:, 10:], sent[:, 10:], atol=1e-4)


def test_a_lossy_link_falls_back_only_after_a_run_of_losses():
    got, _ = _rollouts(V2VChannel(loss=0.5, seed=2), OnboardLeaderAccel(dt=0.1, after=0.3), steps=400)
    age, used = got["next", "v2v", "age"], got["next", "onboard_accel", "used"]
    assert torch.equal(used, age > 3)
    assert 0.02 < float(used.float().mean()) < 0.2  # four losses in a row: about 1 step in 16


def test_the_low_pass_follows_its_recursion():
    tau, dt = 0.4, 0.1
    got, _ = _rollouts(OnboardLeaderAccel(dt=dt, after=None, tau=tau), steps=40, batch=1)
    raw, _ = _rollouts(OnboardLeaderAccel(dt=dt, after=None), steps=40, batch=1)
    est, expect = got[KEY][0, :, 0], torch.zeros(())
    for k, r in enumerate(raw[KEY][0, :, 0]):
        expect = expect + dt / (tau + dt) * (r - expect)
        assert torch.allclose(est[k], expect, atol=1e-4), k
    assert (est - raw[KEY][0, :, 0]).abs().max() > 0.1  # it does smooth


def test_a_row_reset_alone_keeps_the_other_rows_estimate():
    env = TransformedEnv(make_env("ring", batch_size=2, seed=0, **SINE),
                         Compose(V2VChannel(loss=1.0), OnboardLeaderAccel(dt=0.1, after=0.2, tau=0.5)))
    td = env.reset()
    for _ in range(30):
        td = env.step(td.set("action", torch.zeros(2, 1)))["next"]
    before = td.get(("onboard_accel", "estimate")).clone()
    assert before.abs().max() > 0.1
    td.set("_reset", torch.tensor([[True], [False]]))
    out = env.reset(td)
    assert torch.equal(out.get(("onboard_accel", "estimate"))[1], before[1])
    assert torch.equal(out.get(("cav", "leader_accel"))[1], before[1])  # row 1 still reads its estimate
    assert int(out.get(("v2v", "age"))[0].max()) == 0 and int(out.get(("v2v", "age"))[1].min()) == 30


@pytest.mark.parametrize("kwargs, match", [({"dt": 0.0}, r"dt=0.0 is invalid; allowed: > 0"),
                                           ({"dt": 0.1, "after": -1.0}, r"after=-1.0 is invalid; allowed: >= 0"),
                                           ({"dt": 0.1, "tau": -0.5}, r"tau=-0.5 is invalid; allowed: >= 0")])
def test_bad_settings_name_the_argument(kwargs, match):
    with pytest.raises(ValueError, match=match):
        OnboardLeaderAccel(**kwargs)


def test_config_settings_are_checked_at_start_up():
    base = "experiment=ring_lagrangian_ppo_onboard_accel"
    with pytest.raises(ConfigError, match=r"transforms.onboard_accel.tau: -1.0 is out of range; allowed: a number in "
                                          r"\[0, 60\]"):
        validate_config(compose([base, "transforms.onboard_accel.tau=-1.0"]))
    with pytest.raises(ConfigError, match=r"onboard_accel before v2v_channel; allowed: v2v_channel before onboard_accel"):
        validate_config(compose([base, "transforms.chain=[non_negative_reward,onboard_accel,v2v_channel]"]))
    validate_config(compose([base, "transforms.onboard_accel.after=null"]))


def test_a_run_trained_before_the_setting_existed_can_deploy_it():
    from omegaconf import OmegaConf

    cfg = OmegaConf.create(OmegaConf.to_container(compose(["experiment=ring_lagrangian_ppo_release_fade"])))
    del cfg.transforms["onboard_accel"]  # as an older run's config.yaml
    chain = "transforms.chain=[onboard_accel,non_negative_reward,safety_layer,residual_idm,intervention_cost,jerk_penalty]"
    out = with_deploy_overrides(cfg, parse_deploy_overrides([chain, "transforms.onboard_accel.tau=0.2"]))
    assert out.transforms.onboard_accel == {"after": 1.0, "tau": 0.2}
    out = with_deploy_overrides(cfg, parse_deploy_overrides([chain]))  # put in the chain alone: the defaults
    assert out.transforms.onboard_accel == {"after": 1.0, "tau": 0.0}
    from mixed_traffic.training.builders import make_transformed_env

    env = make_transformed_env(out, num_envs=1, seed=0, deploy=True)
    assert [t.after for t in env.transform if isinstance(t, OnboardLeaderAccel)] == [1.0]
    with pytest.raises(ConfigError, match="transforms.onboard_acel.tau: not a setting of the run's config"):
        with_deploy_overrides(cfg, parse_deploy_overrides(["transforms.onboard_acel.tau=0.2"]))


def test_the_default_drives_over_a_dead_link_as_over_a_perfect_one():
    """Behind a head that brakes hard the residual's brake floor and margin gate read the leader's acceleration:
    with the estimate, a dead link leaves the executed commands as the perfect link's; without it they differ."""
    from mixed_traffic.evaluation import evaluate
    from mixed_traffic.training.builders import make_transformed_env
    from mixed_traffic.training.on_policy import build_ppo

    short = ["eval.episodes=1", "eval.episode_seconds=40.0", "eval.warmup_seconds=5.0", "eval.profiles=[emergency_brake]",
             "eval.without_layer=false", "eval.profile_kwargs.emergency_brake.start=20.0"]
    torch.manual_seed(0)
    cfg0 = compose(["experiment=ring_lagrangian_ppo_onboard_accel", *short])
    actor = build_ppo(cfg0, make_transformed_env(cfg0, num_envs=1, seed=0))[0]  # an untrained residual: the base drives

    def jerk(exp, *link):
        cfg = compose([f"experiment={exp}", *short, *link])
        rep, _ = evaluate(cfg, policy_factory=lambda env: actor)
        return rep["profiles"]["emergency_brake"]["per_episode"]["mean_abs_jerk"][0]

    perfect = jerk("ring_lagrangian_ppo_onboard_accel")
    assert jerk("ring_lagrangian_ppo_release_fade") == perfect  # over the perfect link the two are one
    dead_with, dead_without = (jerk(e, "eval.v2v_loss=1.0") for e in ("ring_lagrangian_ppo_onboard_accel",
                                                                       "ring_lagrangian_ppo_release_fade"))
    assert dead_with == perfect and abs(dead_without - perfect) > 1e-4


def test_onboard_accel_is_release_fade_with_the_onboard_estimate_and_nothing_else():
    """``experiment=ring_lagrangian_ppo_onboard_accel`` (which the default extends) is
    ``ring_lagrangian_ppo_release_fade`` with ``onboard_accel`` first in the chain, after 1 s, unfiltered. It trains the
    same weights: without a link nothing ages, so nothing is replaced (the perfect-link rollouts above are the env's to
    the bit)."""
    from omegaconf import OmegaConf, open_dict

    d, prev = (validate_config(compose([f"experiment={n}"]))
               for n in ("ring_lagrangian_ppo_onboard_accel", "ring_lagrangian_ppo_release_fade"))
    assert list(d.transforms.chain) == ["onboard_accel", *prev.transforms.chain]
    assert (d.transforms.onboard_accel.after, d.transforms.onboard_accel.tau) == (1.0, 0.0)
    with open_dict(d):
        d.transforms.chain, d.name = prev.transforms.chain, prev.name
    assert OmegaConf.to_container(d) == OmegaConf.to_container(prev)
