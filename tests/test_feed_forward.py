"""LeaderAccelFeed: the leader's acceleration fed forward into the base above a speed (transforms.residual.feed_forward)."""

from __future__ import annotations

import math

import pytest
import torch

from mixed_traffic import make_env
from mixed_traffic.config import compose
from mixed_traffic.controllers.classic import CatchUp, LeaderAccelFeed, StoppingEnvelope, make_classic_policy
from mixed_traffic.training.builders import residual_base
from mixed_traffic.validation import ConfigError, validate_config

FAST_BAND = "experiment=ring_lagrangian_ppo_fast_band"


def _band_law(gap, v, vl):
    """The fast band law's shape above 18 m/s: a gain of 0.2 1/s on the speed difference, no gap feedback."""
    return 0.2 * (vl - v)


def _behind_a_sine(law, *, v_mid=22.0, amp=2.0, period=45.0, seconds=200.0, dt=0.1):
    """The car behind a head whose speed is ``v_mid + amp sin(2 pi t / period)``, exact leader acceleration of the
    last step as V2V gives it: the gaps and commands after the first period."""
    w = 2 * math.pi / period
    v, gap, a_prev = torch.tensor([v_mid], dtype=torch.float64), torch.tensor([25.0], dtype=torch.float64), 0.0
    gaps, cmds = [], []
    for k in range(int(round(seconds / dt))):
        t = k * dt
        vl = torch.tensor([v_mid + amp * math.sin(w * t)], dtype=torch.float64)
        a = law(gap, v, vl, torch.tensor([a_prev], dtype=torch.float64))
        a_head = amp * w * math.cos(w * t)
        gap = gap + (vl - v) * dt + 0.5 * (a_head - a) * dt * dt
        v = v + a * dt
        a_prev = a_head
        if t >= period:
            gaps.append(float(gap)), cmds.append(float(a))
    return torch.tensor(gaps), torch.tensor(cmds)


def test_a_smooth_head_is_followed_in_phase_and_the_gap_stays_put():
    without, _ = _behind_a_sine(lambda g, v, vl, al: _band_law(g, v, vl))
    fed = LeaderAccelFeed(_band_law, gain=0.9, accel_max=0.3, speeds=(18.0, 20.0))
    with_ff, cmds = _behind_a_sine(fed)
    spread = lambda g: float(g.max() - g.min())  # noqa: E731
    # a lag of 1/0.2 s lets the gap swing with the head; fed forward, a tenth of the head's swing is left
    assert spread(without) > 15.0
    assert spread(with_ff) < 0.15 * spread(without)
    # and the command's swing stays under the head's own (2 * amp * w): no more jerk than the head has
    assert float(cmds.max() - cmds.min()) < 2 * 2.0 * (2 * math.pi / 45.0)


def test_the_fed_acceleration_is_clipped_and_faded_in_by_speed():
    fed = LeaderAccelFeed(lambda g, v, vl: torch.zeros_like(v), gain=0.6, accel_max=0.25, speeds=(18.0, 20.0))
    gap = torch.full((5,), 30.0)
    v = torch.tensor([17.0, 18.0, 19.0, 20.0, 25.0])
    out = fed(gap, v, v, torch.full((5,), 2.0))  # a hard ramp of the head: only accel_max passes
    torch.testing.assert_close(out, torch.tensor([0.0, 0.0, 0.075, 0.15, 0.15]))
    out = fed(gap, v, v, torch.full((5,), -0.1))  # a gentle swing passes whole (times the gain)
    torch.testing.assert_close(out, torch.tensor([0.0, 0.0, -0.03, -0.06, -0.06]))
    with pytest.raises(ValueError, match="leader_accel"):
        fed(gap, v, v)


def test_the_stopping_envelope_over_the_base_still_bounds_it():
    env = make_env("ring", batch_size=1, seed=0)
    fed = LeaderAccelFeed(make_classic_policy("idm", env).module, gain=1.0, accel_max=3.0, speeds=(0.0, 1.0))
    envelope = StoppingEnvelope(fed, stop_gap=5.0, brake=3.0, leader_brake=3.0, dt=env.scenario.dt, low=-3.0)
    bare = StoppingEnvelope(make_classic_policy("idm", env).module, stop_gap=5.0, brake=3.0, leader_brake=3.0,
                            dt=env.scenario.dt, low=-3.0)
    g = torch.Generator().manual_seed(0)
    n = 4000
    gap = 3.0 + 60.0 * torch.rand(n, generator=g)
    v = 30.0 * torch.rand(n, generator=g)
    vl = 30.0 * torch.rand(n, generator=g)
    al = 4.0 * torch.rand(n, generator=g) - 2.0
    bound = bare.bound(gap, v, vl)
    out = envelope(gap, v, vl, al)
    assert bool((out <= bound + 1e-5).all())
    assert bool((out > bare(gap, v, vl) + 1e-3).any())  # and the feed does act where there is room


def test_deploy_only_by_default_off_in_the_default_and_bad_settings_name_the_field():
    env = make_env("ring", batch_size=2, seed=0)
    default = validate_config(compose([FAST_BAND]))
    assert default.transforms.residual.feed_forward.gain is None
    def fed(cfg, deploy):
        return any(isinstance(m, LeaderAccelFeed) for m in residual_base(cfg.transforms.residual, env, deploy=deploy).modules())

    assert not fed(default, True)
    on = validate_config(compose([FAST_BAND, "transforms.residual.feed_forward.gain=0.6"]))
    assert fed(on, True) and not fed(on, False)
    deployed = residual_base(on.transforms.residual, env, deploy=True).module  # inside the envelope and the catch-up
    assert isinstance(deployed, StoppingEnvelope) and isinstance(deployed.law, CatchUp)
    assert isinstance(deployed.law.law, LeaderAccelFeed)
    always = validate_config(compose([FAST_BAND, "transforms.residual.feed_forward.gain=0.6",
                                      "transforms.residual.feed_forward.when=always"]))
    assert fed(always, False)
    for override, field in (("transforms.residual.feed_forward.gain=1.5", "feed_forward.gain"),
                            ("transforms.residual.feed_forward.accel_max=0", "feed_forward.accel_max"),
                            ("transforms.residual.feed_forward.speeds=[20,18]", "feed_forward.speeds"),
                            ("transforms.residual.feed_forward.when=sometimes", "feed_forward.when")):
        with pytest.raises(ConfigError, match=field):
            validate_config(compose([FAST_BAND, "transforms.residual.feed_forward.gain=0.6", override]))
