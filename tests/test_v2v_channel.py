"""The V2V link (transforms.V2VChannel and eval.v2v_*): what arrives, when, what is lost, and who reads it."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import check_env_specs

from mixed_traffic import make_env
from mixed_traffic.config import compose
from mixed_traffic.controllers.classic import make_classic_policy
from mixed_traffic.evaluation import evaluate
from mixed_traffic.validation import ConfigError, validate_config
from transforms import V2VChannel

SINE = dict(profile="sine", profile_kwargs={"v_star": 12.5, "amplitude": 5.0, "period": 10.0})
KEY = ("next", "cav", "leader_accel")


def _rollouts(channel: V2VChannel, steps: int = 60, batch: int = 3):
    act = lambda td: td.set("action", torch.zeros(batch, 1))  # noqa: E731
    got = TransformedEnv(make_env("ring", batch_size=batch, seed=0, **SINE), channel).rollout(steps, act)
    sent = make_env("ring", batch_size=batch, seed=0, **SINE).rollout(steps, act)
    return got, sent[KEY]


def test_specs_hold_with_any_link():
    for channel in (V2VChannel(), V2VChannel(delay_steps=4), V2VChannel(delay_steps=2, loss=0.5, seed=3)):
        check_env_specs(TransformedEnv(make_env("ring", batch_size=2, seed=0, **SINE), channel))


def test_a_delayed_message_is_the_one_sent_that_many_steps_before():
    got, sent = _rollouts(V2VChannel(delay_steps=5))
    late = got[KEY]
    assert sent.abs().max() > 0.5  # the leader does accelerate
    assert torch.equal(late[:, 5:], sent[:, :-5])
    assert torch.equal(late[:, :5], torch.zeros_like(late[:, :5]))  # in flight at reset: the reset value (0)
    assert not torch.equal(late, sent)
    # the measured entries stay exact
    for k in ("gap", "speed", "leader_speed"):
        assert torch.isfinite(got["next", "cav", k]).all()


def test_the_perfect_link_changes_nothing():
    got, sent = _rollouts(V2VChannel())
    assert torch.equal(got[KEY], sent)


def test_a_lost_message_holds_the_last_one_received():
    got, sent = _rollouts(V2VChannel(loss=0.5, seed=1), steps=200)
    recv = got[KEY]
    fresh = recv == sent
    assert 0.35 < fresh.float().mean() < 0.65  # about half the messages arrive (the leader's accel varies)
    # where a message was lost the receiver holds its previous value
    prev = torch.cat([torch.zeros_like(recv[:, :1]), recv[:, :-1]], 1)
    assert torch.equal(recv[~fresh], prev[~fresh])
    # nothing arrives: the reset value is held all episode
    none, _ = _rollouts(V2VChannel(loss=1.0))
    assert torch.equal(none[KEY], torch.zeros_like(none[KEY]))


def test_the_same_seed_loses_the_same_messages():
    a, _ = _rollouts(V2VChannel(delay_steps=2, loss=0.3, seed=7))
    b, _ = _rollouts(V2VChannel(delay_steps=2, loss=0.3, seed=7))
    c, _ = _rollouts(V2VChannel(delay_steps=2, loss=0.3, seed=8))
    assert torch.equal(a[KEY], b[KEY]) and not torch.equal(a[KEY], c[KEY])


def test_a_row_reset_alone_restarts_its_link_and_no_other():
    env = TransformedEnv(make_env("ring", batch_size=2, seed=0, **SINE), V2VChannel(delay_steps=3))
    td = env.reset()
    for _ in range(40):
        td = env.step(td.set("action", torch.zeros(2, 1)))["next"]
    before = td.get(("v2v", "sent")).clone()
    assert before.abs().sum() > 0
    td.set("_reset", torch.tensor([[True], [False]]))
    out = env.reset(td)
    sent = out.get(("v2v", "sent"))
    assert torch.equal(sent[1], before[1])  # row 1 keeps what it had in flight
    assert torch.equal(sent[0], out.get(("cav", "leader_accel"))[0].unsqueeze(-1).expand(-1, 3))


@pytest.mark.parametrize("kwargs, match", [({"delay_steps": -1}, "delay_steps"), ({"delay_steps": 1.5}, "delay_steps"),
                                           ({"loss": 1.2}, r"loss=1.2 is invalid; allowed: a probability in \[0, 1\]")])
def test_bad_link_settings_name_the_argument(kwargs, match):
    with pytest.raises(ValueError, match=match):
        V2VChannel(**kwargs)


def test_eval_link_settings_are_checked_at_start_up():
    with pytest.raises(ConfigError, match=r"eval.v2v_delay: 0.05 is not a whole number of steps; allowed: a "
                                          r"multiple of the env's step dt = 0.1 s"):
        validate_config(compose(["experiment=ring_lagrangian_ppo", "eval.v2v_delay=0.05"]))
    with pytest.raises(ConfigError, match=r"eval.v2v_loss: -0.1 is out of range; allowed: a number in \[0, 1\]"):
        validate_config(compose(["experiment=ring_lagrangian_ppo", "eval.v2v_loss=-0.1"]))
    validate_config(compose(["experiment=ring_lagrangian_ppo", "eval.v2v_delay=0.3", "eval.v2v_loss=0.2"]))


def test_the_evaluated_link_reaches_the_controllers_that_read_it_and_no_other():
    short = ["eval.episodes=2", "eval.episode_seconds=40.0", "eval.warmup_seconds=5.0", "eval.profiles=[sine]"]

    def jerk(controller, *link):
        cfg = compose(["experiment=ring_lagrangian_ppo", "transforms=reward", *short, *link])
        rep, _ = evaluate(cfg, policy_factory=lambda env: make_classic_policy(controller, env))
        return rep["profiles"]["sine"]["per_episode"]["mean_abs_jerk"]

    late = ["eval.v2v_delay=0.5"]
    assert jerk("idm", *late) == jerk("idm")  # IDM measures only
    assert jerk("cacc", *late) != jerk("cacc")  # CACC reads the leader's acceleration over the link


def test_the_report_names_the_link_it_was_evaluated_over(tmp_path):
    from mixed_traffic.evaluation import evaluate_and_report

    cfg = compose(["experiment=ring_lagrangian_ppo", "transforms=reward", "controller=cacc", "eval.episodes=1",
                   "eval.episode_seconds=10.0", "eval.warmup_seconds=2.0", "eval.profiles=[sine]",
                   "eval.v2v_delay=0.3", "eval.v2v_loss=0.25"])
    rep = evaluate_and_report(cfg, tmp_path)
    assert rep["v2v"] == {"delay": 0.3, "loss": 0.25}
    assert "received 0.3 s late, 25 % of the messages lost" in Path(rep["paths"]["md"]).read_text()


TRAIN_LINK = ["experiment=ring_lagrangian_ppo", "transforms.chain=[non_negative_reward,safety_layer,v2v_channel]",
              "transforms.v2v_channel.delay=0.3", "transforms.v2v_channel.loss=0.2"]


def test_a_run_trains_over_its_own_link_and_is_evaluated_over_eval_s():
    from mixed_traffic.training.builders import TRAINING_ONLY, make_transformed_env

    cfg = validate_config(compose(TRAIN_LINK))
    env = make_transformed_env(cfg, num_envs=3, seed=5)
    (link,) = [t for t in env.transform if isinstance(t, V2VChannel)]
    assert (link.delay_steps, link.loss, link.seed) == (3, 0.2, 5)  # seeded by the env: each worker its own draws
    r = env.rollout(300, lambda td: td.set("action", torch.zeros(3, 1)))
    recv, sent = r["next", "cav", "leader_accel"], r["next", "v2v", "sent"][..., -1]  # sent: this step's message
    assert sent.abs().max() > 0.1
    arrived = recv[:, 3:] == sent[:, :-3]
    held = recv[:, 3:] == recv[:, 2:-1]
    assert (arrived | held).all()  # every value received was sent 3 steps before, or is the last one held
    news = sent[:, :-3] != recv[:, 2:-1]  # where an arrival shows: the message differs from what is held
    assert 0.6 < float(arrived[news].float().mean()) < 0.95  # about 80 % of them arrive
    # the evaluation drops the training's link and runs eval.v2v_*'s (none by default)
    evaluated = make_transformed_env(cfg, num_envs=1, seed=0, without=TRAINING_ONLY, deploy=True)
    assert not any(isinstance(t, V2VChannel) for t in evaluated.transform)
    cfg = validate_config(compose([*TRAIN_LINK, "eval.v2v_delay=0.5"]))
    evaluated = make_transformed_env(cfg, num_envs=1, seed=0, without=TRAINING_ONLY, deploy=True)
    assert [t.delay_steps for t in evaluated.transform if isinstance(t, V2VChannel)] == [5]


def test_the_analytic_gradient_pre_training_runs_over_the_link():
    from mixed_traffic.training.apg import apg_pretrain
    from mixed_traffic.training.builders import make_transformed_env
    from mixed_traffic.training.on_policy import build_ppo

    chain = "transforms.chain=[non_negative_reward,safety_layer,residual_idm,intervention_cost,jerk_penalty,v2v_channel]"
    cfg = compose(["experiment=ring_lagrangian_ppo_v2v", chain, "transforms.v2v_channel.delay=0.3",
                   "transforms.v2v_channel.loss=0.2", "transforms.safety_layer.hold_seconds=0.0",
                   "policy.apg.iterations=3", "policy.apg.horizon=4", "policy.apg.num_envs=2", "policy.apg.average_last=0"])
    actor = build_ppo(cfg, make_transformed_env(cfg, num_envs=2, seed=0))[0]
    before = [p.detach().clone() for p in actor.parameters()]
    out = apg_pretrain(actor, cfg, log=None)  # windows start where the last one ended: the link's state is cut too
    assert out["iterations"] == 3 and torch.isfinite(torch.tensor([out["loss_first"], out["loss_last"]])).all()
    assert any(not torch.equal(a, b.detach()) for a, b in zip(before, actor.parameters()))


def test_training_link_settings_are_checked_at_start_up():
    base = ["experiment=ring_lagrangian_ppo", "transforms.chain=[non_negative_reward,v2v_channel]"]
    with pytest.raises(ConfigError, match=r"transforms.v2v_channel.delay: 0.05 is not a whole number of steps; "
                                          r"allowed: a multiple of the env's step dt = 0.1 s"):
        validate_config(compose([*base, "transforms.v2v_channel.delay=0.05"]))
    with pytest.raises(ConfigError, match=r"transforms.v2v_channel.loss: 1.5 is out of range; allowed: a number in "
                                          r"\[0, 1\]"):
        validate_config(compose([*base, "transforms.v2v_channel.loss=1.5"]))
