"""The safety layer where the policy is deployed: its rule beyond s_max (transforms.safety_layer.deployed_beyond_s_max),
or no s_max at all, the s_min rule alone (transforms.safety_layer.deployed_s_max: false)."""

from __future__ import annotations

import pytest
import torch
from omegaconf import OmegaConf, open_dict

from mixed_traffic.config import compose
from mixed_traffic.training.builders import make_transformed_env
from mixed_traffic.validation import ConfigError, validate_config

# the head cruises at 25 m/s; the CAV starts 73.4 m behind it, the ring's spread start
FAST_FAR = dict(profile="piecewise", profile_kwargs={"times": [0, 400], "speeds": [25, 25]},
                init_spacing_range=(73.4, 73.4))


def _layer(cfg, *, deploy: bool):
    env = make_transformed_env(cfg, num_envs=1, seed=0, deploy=deploy)
    return next(t for t in env.transform if type(t).__name__ == "SafetyLayer")


def test_the_deployed_rule_replaces_the_trained_one_only_where_the_chain_is_deployed():
    cfg = validate_config(compose(["experiment=ring_lagrangian_ppo_layer_recover"]))
    assert _layer(cfg, deploy=True).beyond_s_max == "recover"
    assert _layer(cfg, deploy=False).beyond_s_max == "push"  # the training's rule, so the weights do not move
    unset = validate_config(compose(["experiment=ring_lagrangian_ppo_drive_off"]))
    assert _layer(unset, deploy=True).beyond_s_max == _layer(unset, deploy=False).beyond_s_max == "push"


def test_the_safety_net_deploys_the_s_min_rule_alone_and_trains_the_whole_layer():
    cfg = validate_config(compose(["experiment=ring_lagrangian_ppo_safety_net"]))
    deployed, trained = _layer(cfg, deploy=True), _layer(cfg, deploy=False)
    assert deployed.s_max is None and trained.s_max == 38.0
    assert (deployed.s_min, deployed.mode) == (trained.s_min, trained.mode) == (5.0, "stopping")


@pytest.mark.parametrize("name", ["ring_lagrangian_ppo_layer_recover", "ring_lagrangian_ppo_safety_net"])
def test_the_deployed_layer_keeps_its_guarantee(name):
    """Full throttle behind a head that brakes to a standstill, through the experiment's layer as deployed and
    nothing else: the layer alone keeps the 5-m gap, under either deployed form."""
    from torchrl.envs import Compose, TransformedEnv

    from mixed_traffic import make_env
    from mixed_traffic.training.builders import safety_layer_settings
    from transforms import SafetyLayer

    cfg = validate_config(compose([f"experiment={name}"]))
    base = make_env("ring", batch_size=4, seed=0, profile="emergency_brake",
                    profile_kwargs={"start": 20.0, "v_cruise": 25.0, "v_low": 0.0}, init_spacing_range=(8.0, 30.0))
    layer = SafetyLayer(**safety_layer_settings(cfg.transforms.safety_layer, deploy=True))
    env = TransformedEnv(base, Compose(layer))
    with torch.no_grad():
        td = env.rollout(600, lambda td: td.set("action", torch.full((4, 1), 3.0)), break_when_any_done=False)
    assert not bool(td["next", "collision"].any())
    assert float(td["next", "cav", "gap"].min()) >= 5.0 - 1e-3


def test_the_deployed_layer_does_not_throw_the_car_forward_after_the_hold():
    """The base alone (residual 0) behind a 25 m/s head from the 73.4-m start: when the layer's 15-s hold ends the
    gap is still beyond s_max (38 m). ``push`` then commands +3 m/s^2 and the car brakes right after; ``recover``
    leaves the base's own closing alone, and the gap is back in the band all the same; without a deployed s_max
    the layer does not act at all and the base's closing is the same as under ``recover``."""
    out = {}
    for name in ("ring_lagrangian_ppo_drive_off", "ring_lagrangian_ppo_layer_recover", "ring_lagrangian_ppo_safety_net"):
        cfg = validate_config(compose([f"experiment={name}"]))
        env = make_transformed_env(cfg, num_envs=1, seed=0, deploy=True, **FAST_FAR)
        with torch.no_grad():
            td = env.rollout(300, lambda td: td.set("action", torch.zeros(1, 1)), break_when_any_done=False)
        a, gap = td["next", "cav", "accel"].flatten(), td["next", "cav", "head_gap"].flatten()
        out[name] = dict(clipped=int(td["next", "safety", "clipped"].sum()), top=float(a[140:200].max()),
                         variation=float((a[1:] - a[:-1]).abs().sum()), gap_at_hold_end=float(gap[149]),
                         late_gap=float(gap[200:].max()), collision=bool(td["next", "collision"].any()))
    push, recover = out["ring_lagrangian_ppo_drive_off"], out["ring_lagrangian_ppo_layer_recover"]
    assert push["gap_at_hold_end"] > 38.0 and recover["gap_at_hold_end"] == pytest.approx(push["gap_at_hold_end"])
    assert push["clipped"] > 0 and push["top"] > 2.9
    assert recover["clipped"] == 0 and recover["top"] < 0.0
    assert recover["variation"] < 0.5 * push["variation"]
    assert recover["late_gap"] < 38.0 and not recover["collision"] and not push["collision"]
    net = out["ring_lagrangian_ppo_safety_net"]
    assert net["clipped"] == 0 and net["variation"] == pytest.approx(recover["variation"]) and not net["collision"]


def test_the_s_min_rule_is_the_same_whichever_rule_beyond_s_max():
    """The guarantee does not depend on the deployed rule: the same command is clipped the same way near s_min."""
    cfg = validate_config(compose(["experiment=ring_lagrangian_ppo_layer_recover"]))
    deployed, trained = _layer(cfg, deploy=True), _layer(cfg, deploy=False)
    assert (deployed.s_min, deployed.mode, deployed.s_max) == (trained.s_min, trained.mode, trained.s_max)


@pytest.mark.parametrize("overrides, match", [
    (["transforms.safety_layer.deployed_beyond_s_max=shove"],
     r"transforms.safety_layer.deployed_beyond_s_max: unknown value 'shove'; allowed: \[None, 'push'"),
    (["transforms.safety_layer.deployed_s_max=false", "transforms.safety_layer.deployed_beyond_s_max=recover"],
     r"transforms.safety_layer.deployed_beyond_s_max: 'recover' has no effect with deployed_s_max: false"),
])
def test_a_bad_deployed_layer_fails_at_start_up_naming_the_field(overrides, match):
    with pytest.raises(ConfigError, match=match):
        validate_config(compose(["experiment=ring_lagrangian_ppo_drive_off", *overrides]))


def test_a_deployed_s_max_that_is_not_a_bool_fails_at_composition_naming_the_field():
    from hydra.errors import ConfigCompositionException

    with pytest.raises(ConfigCompositionException) as e:
        compose(["experiment=ring_lagrangian_ppo_drive_off", "transforms.safety_layer.deployed_s_max=maybe"])
    assert "transforms.safety_layer.deployed_s_max" in str(e.value)
    assert "not a valid bool" in str(e.value.__cause__)


@pytest.mark.parametrize("name, says", [
    ("ring_lagrangian_ppo_safety_net", "s_min 5 m (stopping rule); no s_max: its s_min rule alone."),
    ("ring_lagrangian_ppo_layer_recover", "s_min 5 m (stopping rule); s_max 38 m (recover beyond it, after a 15-s hold)."),
    ("ring_lagrangian_ppo_drive_off", "s_min 5 m (stopping rule); s_max 38 m (push beyond it, after a 15-s hold)."),
])
def test_the_report_states_the_layer_as_it_was_deployed(name, says):
    from mixed_traffic.evaluation.report import markdown
    from mixed_traffic.training.builders import safety_layer_settings

    cfg = compose([f"experiment={name}"])
    report = {"episodes_per_profile": 1, "eval_seed": 0, "profiles": {},
              "safety_layer": safety_layer_settings(cfg.transforms.safety_layer, deploy=True)}
    assert f"Safety layer as evaluated: {says}" in markdown(report, "t")


def test_a_checkpoint_saved_before_the_field_existed_deploys_its_own_rule():
    """An old run's stored config lacks the field: it loads at null, so the layer deploys as it trained."""
    from mixed_traffic.evaluation.policies import with_schema_defaults

    cfg = compose(["experiment=ring_lagrangian_ppo_drive_off"])
    stored = OmegaConf.to_container(cfg)
    del stored["transforms"]["safety_layer"]["deployed_beyond_s_max"]
    loaded = with_schema_defaults(stored)
    assert loaded.transforms.safety_layer.deployed_beyond_s_max is None
    assert loaded.transforms.safety_layer.deployed_s_max is True
    with open_dict(loaded):
        loaded.transforms.safety_layer.beyond_s_max = "hold"
    assert _layer(validate_config(loaded), deploy=True).beyond_s_max == "hold"
