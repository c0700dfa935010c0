"""The default's margin fade at a stop: the learned residual does not carry the CAV onto the stopping envelope."""

from __future__ import annotations

import pytest
import torch

from mixed_traffic.config import compose
from mixed_traffic.training.builders import make_transformed_env
from mixed_traffic.validation import ConfigError, validate_config, with_deploy_overrides
from transforms import ResidualAction

SLACK = "transforms.residual.envelope_fade_slack"
BELOW, BRAKE = f"{SLACK}_below", f"{SLACK}_brake"
NO_FADE, NO_GATE = [(SLACK, None), (BELOW, None), (BRAKE, None)], [(BELOW, None), (BRAKE, None)]
BRAKE_FROM_17 = dict(profile="emergency_brake", profile_kwargs={"start": 20.0, "v_cruise": 17.0, "v_low": 0.0},
                     init_spacing_range=[24.0, 24.0], episode_seconds=40.0)
SLOWING_AT_SPEED = dict(profile="sine", profile_kwargs={"v_star": 14.0, "amplitude": 4.0, "period": 30.0},
                        init_spacing_range=[20.0, 20.0], episode_seconds=60.0)


def _pushing(steps: int, overrides, env_kw):
    """The default as deployed (``overrides`` applied), without its layer, the policy pushing its largest residual on
    every step: the executed acceleration, the speed and the gap."""
    cfg = with_deploy_overrides(validate_config(compose(["experiment=ring_lagrangian_ppo_stop_margin"])), overrides)
    env = make_transformed_env(cfg, num_envs=1, seed=0, without=("safety_layer",), deploy=True, **env_kw)
    with torch.no_grad():
        td = env.rollout(steps, lambda td: td.set("action", torch.ones(1, 1)), break_when_any_done=False)
    return (td["next", "cav", k][0, :, 0] for k in ("accel", "speed", "gap"))


def _base(cfg):
    from mixed_traffic import make_env
    from mixed_traffic.training.builders import residual_base

    return residual_base(cfg.transforms.residual, make_env("ring", batch_size=1, seed=0))


def _into_the_stop(overrides):
    """Behind a head braking from 17 m/s to a standstill at 3 m/s^2: the command from its hardest braking to the
    first step at a standstill, and the smallest gap."""
    accel, speed, gap = _pushing(400, overrides, BRAKE_FROM_17)
    stop = int((speed < 1e-3).nonzero().min())
    return accel[int(accel[:stop].argmin()):stop + 1], float(gap.min())


def test_the_margin_fade_lets_go_of_the_brake_smoothly_into_the_stop():
    """With the default's margin fade the command rises steadily from its hardest braking to 0 at the standstill
    and the CAV stops short of the envelope's 5 m; without it the residual's push carries the CAV onto the
    envelope's edge, which brakes it again hard just before the stop and stops it at exactly 5 m."""
    after, min_gap = _into_the_stop([])
    assert float(after.diff().min()) > -1e-4  # no reversal: the braking only eases
    assert min_gap > 5.3
    after, min_gap = _into_the_stop(NO_FADE)
    assert float(after.diff().min()) < -0.3  # the envelope's late brake
    assert abs(min_gap - 5.0) < 0.01


def test_behind_a_leader_that_slows_gently_at_speed_the_margin_fade_changes_nothing():
    """Behind a head that slows and speeds up between 10 and 18 m/s (at most 0.84 m/s^2) the gated fade leaves every
    command as it was without the margin fade, bit for bit, while the same fade behind every leader changes them."""
    gated, *_ = _pushing(600, [], SLOWING_AT_SPEED)
    plain, *_ = _pushing(600, NO_FADE, SLOWING_AT_SPEED)
    ungated, *_ = _pushing(600, NO_GATE, SLOWING_AT_SPEED)
    torch.testing.assert_close(gated, plain, atol=0, rtol=0)
    assert float((ungated - plain).abs().max()) > 0.05


def test_the_gate_needs_a_margin_and_positive_thresholds():
    run = validate_config(compose(["experiment=ring_lagrangian_ppo_stop_margin"]))
    with pytest.raises(ConfigError, match=r"envelope_fade_slack_below: set with envelope_fade_slack null.*allowed: "
                                          r"null, or a leader speed \(m/s, > 0\)"):
        validate_config(compose(["experiment=ring_lagrangian_ppo_join", f"{BELOW}=2.0"]))
    with pytest.raises(ConfigError, match=r"envelope_fade_slack_brake: set with envelope_fade_slack null.*allowed: "
                                          r"null, or a leader deceleration \(m/s\^2, > 0\)"):
        validate_config(compose(["experiment=ring_lagrangian_ppo_join", f"{BRAKE}=1.0"]))
    for key in (BELOW, BRAKE):
        with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
            validate_config(compose(["experiment=ring_lagrangian_ppo_stop_margin", f"{key}=0"]))
        with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
            with_deploy_overrides(run, [(key, -1.0)])
    with pytest.raises(ValueError, match=r"slack_brake=1.0 is invalid; allowed: > 0 with a fade_slack"):
        ResidualAction(_base(run), slack_brake=1.0)


def test_stop_margin_is_join_with_the_margin_fade_at_a_stop_at_deployment_and_nothing_else():
    """``experiment=ring_lagrangian_ppo_stop_margin`` (the previous default) is ``ring_lagrangian_ppo_join`` with
    ``envelope_fade_slack: 1`` behind leaders below 2 m/s or braking harder than 1 m/s^2; it acts at deployment only, so training builds the
    join's chain and trains the same weights."""
    from omegaconf import OmegaConf, open_dict

    d, prev = (validate_config(compose([f"experiment={n}"]))
               for n in ("ring_lagrangian_ppo_stop_margin", "ring_lagrangian_ppo_join"))
    r = d.transforms.residual
    assert (r.envelope_fade_slack, r.envelope_fade_slack_below, r.envelope_fade_slack_brake, r.envelope_fade) == \
        (1.0, 2.0, 1.0, "deploy")
    trained, deployed = ([t for t in make_transformed_env(d, num_envs=1, seed=0, deploy=dep).transform
                          if isinstance(t, ResidualAction)][0] for dep in (False, True))
    assert trained.fade_slack is None and trained.room_key is None  # training: no fade at all
    assert (deployed.fade_slack, deployed.slack_below, deployed.slack_brake) == (1.0, 2.0, 1.0)
    with open_dict(d):
        r.envelope_fade_slack = r.envelope_fade_slack_below = r.envelope_fade_slack_brake = None
        d.name = prev.name
    assert OmegaConf.to_container(d) == OmegaConf.to_container(prev)


def test_mt_eval_deploys_the_margin_fade_on_a_run_of_the_default(tmp_path):
    """``mt-eval checkpoint=RUN transforms.residual.envelope_fade_slack_brake=...`` is checked against the run's own
    transforms (which have the envelope the fade needs), not against the app's defaults (which lack it), and a bad
    value is still refused naming the field."""
    from mixed_traffic.apps.evaluate import run_eval
    from mixed_traffic.apps.main_job import apply_small_budget
    from mixed_traffic.training import train

    cfg = compose(["experiment=ring_lagrangian_ppo_stop_margin", "trainer.progress=false"])
    apply_small_budget(cfg)
    train(cfg, out_dir=tmp_path / "run")
    base = [f"checkpoint={tmp_path / 'run'}", f"out_dir={tmp_path}/o", "eval.episodes=1", "eval.episode_seconds=5.0",
            "eval.warmup_seconds=1.0", "eval.settle_seconds=1.0", "eval.profiles=[random_steps]"]
    over = [f"{BRAKE}=1.5", f"{SLACK}=2.0"]
    rep = run_eval(compose(base + over), base + over)
    assert rep["deploy_overrides"] == {BRAKE: 1.5, SLACK: 2.0}
    with pytest.raises(ConfigError, match=rf"^{BRAKE}: .*allowed"):
        run_eval(compose(base + [f"{BRAKE}=-1.0"]), base + [f"{BRAKE}=-1.0"])
    bad = [f"{SLACK}=2.0", "policy.log_std_min=3.0", "policy.log_std_max=1.0"]  # the rest is still checked
    with pytest.raises(ConfigError, match=r"^policy.log_std_min: 3.0 > log_std_max 1.0"):
        run_eval(compose(base + bad), base + bad)
