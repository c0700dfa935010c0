"""The floor from the leader's drive-off (experiment=ring_lagrangian_ppo_follow, and the default that extends it): it is
ring_lagrangian_ppo_onboard_accel plus ``drive_off.follow: 0.9`` at deployment, it keeps up with the leader's drive-off, and it does so over a dead V2V
link as over a perfect one (the leader's acceleration read on board)."""

from __future__ import annotations

import torch
from omegaconf import OmegaConf, open_dict

from mixed_traffic.config import compose
from mixed_traffic.training.builders import make_transformed_env
from mixed_traffic.validation import validate_config
from transforms import DriveOffCap

# the head cruises at 15 m/s, stops at 17.5 s, stands 6 s and drives off to 15 m/s within 7.5 s (2 m/s^2)
STOP = dict(profile="piecewise", profile_kwargs={"times": [0, 10, 17.5, 23.5, 31, 400], "speeds": [15, 15, 0, 0, 15, 15]})


def _drive(experiment: str, *overrides: str, steps: int = 600):
    """The experiment's deployed chain driven by its base alone (the policy's action 0) behind STOP."""
    cfg = validate_config(compose([f"experiment={experiment}", *overrides]))
    env = make_transformed_env(cfg, num_envs=1, seed=0, deploy=True, **STOP)
    with torch.no_grad():
        return env.rollout(steps, lambda td: td.set("action", torch.zeros(1, 1)), break_when_any_done=False)


def test_the_follow_floor_keeps_up_with_the_leaders_drive_off_over_any_link():
    follow, plain = _drive("ring_lagrangian_ppo_follow"), _drive("ring_lagrangian_ppo_onboard_accel")
    a, a_plain = follow["next", "cav", "accel"][0, :, 0], plain["next", "cav", "accel"][0, :, 0]
    a_l = follow["cav", "leader_accel"][0, :, 0]
    engaged = follow["drive_off", "engaged"][0, :, 0]
    assert torch.equal(a[:170], a_plain[:170])  # identical until the standstill
    on = engaged & (a_l > 0.3) & (follow["cav", "speed"][0, :, 0] > 0.05)
    assert on.sum() > 20  # the floor acts through the leader's drive-off
    assert (a[on] - a_plain[on]).max() > 0.3  # it lifts the command while the leader drives off
    # (the floor itself, min(0.9 a_leader, cap) inside the stopping rule: tests/test_drive_off.py)
    gap, gap_plain = (r["next", "cav", "gap"][0, 235:600, 0].max() for r in (follow, plain))
    assert gap < gap_plain - 2.0  # so the gap opens less behind the drive-off
    # over a dead link the on-board estimate feeds the floor: the same commands, step for step
    dead = _drive("ring_lagrangian_ppo_follow", "eval.v2v_loss=1.0")["next", "cav", "accel"][0, :, 0]
    torch.testing.assert_close(dead, a, atol=1e-4, rtol=0)


def test_the_follow_experiment_is_onboard_accel_with_the_follow_floor_at_deployment_and_nothing_else():
    d, prev = (validate_config(compose([f"experiment={n}"]))
               for n in ("ring_lagrangian_ppo_follow", "ring_lagrangian_ppo_onboard_accel"))
    assert d.transforms.residual.drive_off.follow == 0.9
    trained, deployed = ([t for t in make_transformed_env(d, num_envs=1, seed=0, deploy=dep).transform
                          if isinstance(t, DriveOffCap)] for dep in (False, True))
    assert trained == [] and deployed[0].follow == 0.9  # training has no cap, so the same weights
    with open_dict(d):
        d.transforms.residual.drive_off.follow, d.name = None, prev.name
    assert OmegaConf.to_container(d) == OmegaConf.to_container(prev)
