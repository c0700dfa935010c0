"""The stopping envelope's arrival term (``transforms.residual.arrive_gain``): the base's law hands over to a smooth
profile in the last metres before a standstill, not to the envelope's bound at full braking."""

from __future__ import annotations

import math

import pytest
import torch

from mixed_traffic.config import compose
from mixed_traffic.controllers.classic import StoppingEnvelope
from mixed_traffic.physics import integrate
from mixed_traffic.training.builders import classic_law, make_transformed_env
from mixed_traffic.validation import ConfigError, validate_config

GENTLE = "experiment=ring_lagrangian_ppo_gentle"


def _gentle_law():
    """The soft law of ``experiment=ring_lagrangian_ppo_gentle``'s base below 10 m/s, unclipped."""
    return classic_law("soft", compose([GENTLE]).transforms.residual.params, None, low=-math.inf, high=math.inf).module


def _stop(arrive_gain, gap0: float, v0: float, steps: int = 60):
    """One car at ``v0`` (m/s), ``gap0`` (m) behind a standing leader, driven by the gentle law inside the envelope
    of 5 m (braking 3 m/s^2, the ring's), its command clipped to [-3, 2]: the executed commands and the gaps."""
    envelope = StoppingEnvelope(_gentle_law(), stop_gap=5.0, dt=0.1, brake=3.0, leader_brake=3.0, low=-3.0,
                                arrive_gain=arrive_gain)
    pos, vel, accel, gaps = torch.zeros(1), torch.tensor([v0]), [], []
    for _ in range(steps):
        gap = gap0 - pos
        a = envelope(gap, vel, torch.zeros(1)).clamp(-3.0, 2.0)
        accel.append(float(a))
        gaps.append(float(gap))
        pos, vel, _ = integrate(pos, vel, a, 0.1)
    return torch.tensor(accel), torch.tensor(gaps)


@pytest.mark.parametrize("gap0,v0", [(7.1, 3.68), (7.5, 3.9), (7.0, 3.5)])
def test_with_the_arrival_the_command_eases_off_once_from_full_braking_to_the_standstill(gap0, v0):
    """From states the trained residual brought the gentle base into (brake_to_standstill, tuning seed): without the
    arrival term the law eases off in the last metres and the envelope's bound then brakes at full again, so the
    command swings more than its range (its total variation over the stop exceeds max - min by 0.5 m/s^2 or
    more); with it the command rises once, monotonically, from full braking to the standstill's. The gap stays at
    or above the envelope's 5 m either way."""
    for gain, extra in ((None, None), (1.0, 1e-4)):
        accel, gaps = _stop(gain, gap0, v0)
        swing = float((accel[1:] - accel[:-1]).abs().sum() - (accel.max() - accel.min()))
        if extra is None:
            assert swing > 0.5
        else:
            assert swing < extra
            assert bool((accel[1:] >= accel[:-1] - 1e-6).all())
        assert float(gaps.min()) >= 5.0 - 1e-3


def test_the_arrival_term_is_loose_away_from_the_edge_and_the_envelopes_braking_at_it():
    """The term is far above any command while the car has room to spare (a large gap, or a small closing speed),
    equals ``-b`` where the constant deceleration matching the leader at the stop gap reaches the envelope's
    braking ``b``, and is inf behind a leader as fast or faster; it never changes the envelope's bound."""
    env_ = StoppingEnvelope(lambda *x: torch.zeros_like(x[1]), stop_gap=5.0, dt=0.1, brake=3.0, leader_brake=3.0,
                            low=-4.0, arrive_gain=1.0)
    term = env_.arrival(torch.tensor([40.0, 12.0, 11.0, 10.0]), torch.tensor([15.0, 6.0, 6.0, 6.0]),
                        torch.tensor([12.0, 5.0, 0.0, 8.0]))
    assert float(term[0]) > 20.0 and float(term[1]) > 5.0
    assert float(term[2]) == pytest.approx(-3.0, abs=1e-5)  # d = 36 / (2 * 6) = 3 = b
    assert math.isinf(float(term[3]))
    bare = StoppingEnvelope(env_.law, stop_gap=5.0, dt=0.1, brake=3.0, leader_brake=3.0, low=-4.0)
    g = torch.Generator().manual_seed(0)
    gap, v, vl = (torch.rand(500, generator=g) * 40.0 + 1.0, torch.rand(500, generator=g) * 30.0,
                  torch.rand(500, generator=g) * 30.0)
    assert torch.equal(env_.bound(gap, v, vl), bare.bound(gap, v, vl))
    with pytest.raises(ValueError, match="arrive_gain"):
        StoppingEnvelope(env_.law, stop_gap=5.0, dt=0.1, brake=3.0, leader_brake=3.0, low=-4.0, arrive_gain=0.0)


def test_the_arrival_term_leaves_the_gentle_bases_everyday_driving_alone():
    """On the training's random steps (2-20 m/s, no stop) the gentle base with the arrival term commands exactly
    what it does without it: the term acts only at the edge of a stop."""
    from mixed_traffic.evaluation.policies import residual_base_factory

    accel = {}
    for gain in ("null", "1.0"):
        cfg = compose([GENTLE, f"transforms.residual.arrive_gain={gain}",
                       "transforms.chain=[non_negative_reward,residual_idm]"])
        env = make_transformed_env(cfg, num_envs=4, seed=0, without=("residual_idm",), profile="random_steps")
        accel[gain] = env.rollout(600, residual_base_factory(cfg)(env), break_when_any_done=False)["next", "cav", "accel"]
    assert torch.equal(accel["null"], accel["1.0"])


def test_arrive_gain_reaches_the_envelope_from_the_config_and_bad_values_name_the_field():
    from transforms import ResidualAction

    cfg = validate_config(compose([GENTLE]))
    res = [t for t in make_transformed_env(cfg, num_envs=1, seed=0, deploy=True).transform
           if isinstance(t, ResidualAction)]
    assert res[0].base.module.envelope.arrive_gain == 1.0
    with pytest.raises(ConfigError, match=r"transforms\.residual\.arrive_gain.*> 0"):
        validate_config(compose([GENTLE, "transforms.residual.arrive_gain=0"]))
    with pytest.raises(ConfigError, match=r"transforms\.residual\.arrive_gain.*stop_gap"):
        validate_config(compose([GENTLE, "transforms.residual.stop_gap=null"]))


def test_ring_trace_shows_which_part_of_the_base_commands_each_step(benchmark_script, tmp_path):
    """``benchmarks/ring_trace.py``: per step the base's command is the least of its law, its arrival term and the
    envelope's bound (the arrival column empty where the term is off), the trace ends at the window, a CSV holds the
    same rows, and a bad case, episode or window, or a run without a residual over an enveloped base, exits naming
    what is wrong before anything runs."""
    mod = benchmark_script("ring_trace")
    common = ["--experiment", "ring_lagrangian_ppo_gentle", "--case", "brake_to_standstill", "--seconds", "60",
              "--episodes", "2"]
    rows = mod.main([*common, "--window", "50", "58", "--out", str(tmp_path / "t.csv")])
    assert rows[0]["time"] == 50.0 and rows[-1]["time"] == 58.0 and len(rows) == 81
    for r in rows:
        assert r["base"] == pytest.approx(min(r["law"], r["arrival"], r["bound"]), abs=1e-5)
    assert min(r["speed"] for r in rows) < 0.5  # the CAV stopped behind the head within the window
    assert len((tmp_path / "t.csv").read_text().splitlines()) == len(rows) + 1
    off = mod.main([*common, "--window", "50", "50.5", "--set", "transforms.residual.arrive_gain=null"])
    assert all(math.isnan(r["arrival"]) for r in off) and len(off) == 6
    for bad, said in ((["--case", "brake_from_99"], r"--case: 'brake_from_99' is not a case"),
                      (["--episode", "2"], r"--episode: 2 is invalid; allowed: 0\.\.1"),
                      (["--window", "5", "1"], r"--window: \[5\.0, 1\.0\] is invalid")):
        with pytest.raises(SystemExit, match=said):
            mod.main([*common, *bad])
    with pytest.raises(SystemExit, match=r"ring_ppo: the run has no learned residual"):
        mod.main(["--experiment", "ring_ppo", "--case", "brake_to_standstill", "--seconds", "5"])
