"""The backlash's release (``transforms.residual.drive_off.residual_play_release``): when the drive-off cap releases,
the learned residual's held term reaches the policy's over seconds instead of in one step."""

from __future__ import annotations

import torch

from mixed_traffic.config import compose
from mixed_traffic.training.builders import make_transformed_env
from mixed_traffic.validation import validate_config
from transforms import ResidualAction

# a head that stops, drives off at 31 s and then cruises: the cap engages at the stop and releases 40 s after the CAV
# has matched it
STOP_THEN_CRUISE = dict(profile="piecewise", init_spacing_range=[20.0, 20.0], episode_seconds=140.0,
                        profile_kwargs={"times": [0, 10, 17.5, 23.5, 31, 400], "speeds": [15, 15, 0, 0, 15, 15]})


def _drifting(experiment: str):
    """``experiment`` as deployed, without its layer, behind the head above; the policy's output drifts down by
    0.01 per second, so the backlash holds the residual's term 0.1 m/s^2 above the policy's while the cap is engaged."""
    cfg = validate_config(compose([f"experiment={experiment}"]))
    env = make_transformed_env(cfg, num_envs=1, seed=0, without=("safety_layer",), deploy=True, **STOP_THEN_CRUISE)
    k = iter(range(10 ** 6))
    with torch.no_grad():
        td = env.rollout(1300, lambda td: td.set("action", torch.full((1, 1), 0.5 - 0.001 * next(k))),
                         break_when_any_done=False)
    return td["next", "cav", "accel"][0, :, 0], td["next", "drive_off", "engaged"][0, :, 0]


def test_the_release_fade_removes_the_step_where_the_cap_releases():
    """Under ``ring_lagrangian_ppo_stop_margin`` the executed command steps by 0.1 m/s^2 where the cap releases;
    under ``ring_lagrangian_ppo_release_fade`` no step in the 12 s around it exceeds 0.002 m/s^2, and every step
    before it is the same."""
    held, engaged = _drifting("ring_lagrangian_ppo_stop_margin")
    faded, engaged_faded = _drifting("ring_lagrangian_ppo_release_fade")
    assert torch.equal(engaged, engaged_faded)
    on = engaged.nonzero()
    assert int(on.min()) < 300 and int(on.max()) < 1200  # the cap engaged at the stop and released in the episode
    release = int(on.max()) + 1  # the first step executed with the cap released
    assert torch.equal(held[:release], faded[:release])
    window = slice(release - 20, release + 100)
    assert float(held[window].diff().abs().max()) > 0.09
    assert float(faded[window].diff().abs().max()) < 0.002


def test_release_fade_is_stop_margin_with_a_10_s_release_at_deployment_and_nothing_else():
    """``experiment=ring_lagrangian_ppo_release_fade`` (which the default extends) is ``ring_lagrangian_ppo_stop_margin``
    with the backlash released over 10 s; it acts at deployment only, so training builds the same chain and trains
    the same weights."""
    from omegaconf import OmegaConf, open_dict

    d, prev = (validate_config(compose([f"experiment={n}"]))
               for n in ("ring_lagrangian_ppo_release_fade", "ring_lagrangian_ppo_stop_margin"))
    assert d.transforms.residual.drive_off.residual_play_release == 10.0
    trained, deployed = ([t for t in make_transformed_env(d, num_envs=1, seed=0, deploy=dep).transform
                          if isinstance(t, ResidualAction)][0] for dep in (False, True))
    assert trained.play is None and trained.play_release is None  # training: no cap, no backlash
    assert (deployed.play, deployed.play_release) == (0.1, 10.0)
    with open_dict(d):
        d.transforms.residual.drive_off.residual_play_release, d.name = None, prev.name
    assert OmegaConf.to_container(d) == OmegaConf.to_container(prev)
