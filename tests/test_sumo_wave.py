"""The stop-and-go ring (``ring_wave``) in real SUMO: no head, per-episode ring lengths, the
humans' per-step acceleration noise executed by SUMO, the same episodes as the torch backend,
and the wave report on the SUMO backend. Real libsumo, no mocks."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torchrl.envs.utils import check_env_specs

libsumo = pytest.importorskip("libsumo")

from mixed_traffic import make_env  # noqa: E402
from mixed_traffic.config import compose  # noqa: E402
from mixed_traffic.controllers.dampers import make_damper  # noqa: E402


def test_ring_wave_specs_and_keys_match_torch_backend():
    su = make_env("ring_wave", backend="sumo", seed=0)
    try:
        to = make_env("ring_wave", batch_size=1, seed=0)
        assert su.observation_spec == to.observation_spec
        assert su.action_spec == to.action_spec and su.full_done_spec == to.full_done_spec
        check_env_specs(su)
        td = su.reset()
        assert ("cav", "speed_avg") in td.keys(True) and ("cav", "head_gap") not in td.keys(True)
        assert float(td["traffic", "ring_length"]) == 260.0
    finally:
        su.close()


@pytest.mark.parametrize("overrides", [dict(ring_length=260.0), dict(ring_length_range=[220.0, 270.0])])
def test_same_seed_is_the_same_noisy_episode_in_both_backends(overrides):
    """Ring length, initial wave, human parameters and the humans' noise come from the same
    draws: the two simulators follow the same trajectory for the first 15 s (float32 vs
    float64 rounding only; on a dense ring with full stops the stop at v = 0 makes the
    rounding grow after ~20 s, as any chaotic system's would)."""
    seed = 3
    to = make_env("ring_wave", batch_size=1, seed=seed, **overrides)
    su = make_env("ring_wave", backend="sumo", seed=seed, **overrides)
    try:
        rt = to.rollout(300, make_damper("idm", to), break_when_any_done=False)
        rs = su.rollout(300, make_damper("idm", su), break_when_any_done=False)
    finally:
        su.close()
    L = float(rs["traffic", "ring_length"][0, 0])
    assert L == pytest.approx(float(rt["traffic", "ring_length"][0, 0]), abs=1e-4)
    if "ring_length_range" in overrides:
        assert 220.0 <= L <= 270.0 and L != 260.0
    vt, vs = rt["next", "traffic", "speed"], rs["next", "traffic", "speed"]
    assert float(vt.std(-1).mean()) > 0.5  # a wave is there (otherwise agreement says little)
    assert float((vt - vs)[:, :150].abs().max()) < 1e-3
    gap = rs["next", "traffic", "gap"][0, -1]
    assert float(gap.sum()) + 22 * 5.0 == pytest.approx(L, abs=1e-3)


def test_timed_observation_and_relative_reward_agree_across_backends():
    """``observation="wave_ring_time"`` and ``reward="wave_relative"`` (what the CEM damper trains on)
    give the same entries in SUMO as in torch on the same seeded episode."""
    kw = dict(seed=3, ring_length_range=[220.0, 270.0], observation="wave_ring_time", reward="wave_relative")
    to = make_env("ring_wave", batch_size=1, **kw)
    su = make_env("ring_wave", backend="sumo", **kw)
    try:
        rt = to.rollout(50, make_damper("idm", to), break_when_any_done=False)
        rs = su.rollout(50, make_damper("idm", su), break_when_any_done=False)
    finally:
        su.close()
    assert torch.allclose(rt["next", "observation"], rs["next", "observation"], atol=1e-4)
    assert torch.allclose(rt["next", "reward"], rs["next", "reward"], atol=1e-4)
    assert float(rs["next", "observation"][0, -1, 6]) == pytest.approx(5.0 / 600.0, abs=1e-6)


def test_sumo_executes_the_human_noise_on_its_own_car_following_command():
    """Executed speed minus the speed SUMO's own IDM commands (``getFollowSpeed`` on the state
    before the step) is the scenario's N(0, 0.2) acceleration noise times dt."""
    env = make_env("ring_wave", backend="sumo", seed=0)
    try:
        td = env.reset()
        hdv = list(env.scenario.hdv_indices)
        res = []
        for _ in range(150):
            v, gap = env.vel.copy(), env._gaps()
            own = np.array([libsumo.vehicle.getFollowSpeed(env._ids[i], v[i], gap[i] - env.hdv_params["s0"][i],
                                                           v[i - 1], 1.5, env._ids[i - 1]) for i in hdv])
            td = env.step(td.set("action", torch.zeros(1, 1)))["next"]
            res.append((env.vel[hdv] - own) / env.dt)
        res = np.concatenate(res)
        assert abs(res.mean()) < 0.02 and res.std() == pytest.approx(0.2, abs=0.015)
    finally:
        env.close()
    # without noise SUMO's IDM drives the humans itself: their step is its command exactly
    env = make_env("ring_wave", backend="sumo", seed=0, accel_noise=0.0)
    try:
        td = env.reset()
        v, gap = env.vel.copy(), env._gaps()
        own = libsumo.vehicle.getFollowSpeed("v5", v[5], gap[5] - env.hdv_params["s0"][5], v[4], 1.5, "v4")
        env.step(td.set("action", torch.zeros(1, 1)))
        assert env.vel[5] == pytest.approx(own, abs=1e-9)
    finally:
        env.close()


def test_ring_length_drawn_per_episode_builds_a_new_ring():
    env = make_env("ring_wave", backend="sumo", seed=1, ring_length_range=[220.0, 270.0], episode_seconds=1.0)
    try:
        lengths = []
        for _ in range(3):
            td = env.reset()
            L = float(td["traffic", "ring_length"][0, 0])
            assert float(td["traffic", "gap"].sum()) + 22 * 5.0 == pytest.approx(L, abs=1e-3)
            lengths.append(L)
        assert len(set(lengths)) == 3 and all(220.0 <= x <= 270.0 for x in lengths)
    finally:
        env.close()


def test_wave_report_runs_on_the_sumo_backend(tmp_path):
    from mixed_traffic.evaluation import evaluate_and_report

    cfg = compose(["experiment=ring_wave_lppo", "controller=all", "env.backend=sumo", "eval.wave.episodes=2",
                   "eval.wave.episode_seconds=8", "eval.wave.warmup_seconds=2", "eval.wave.ring_lengths=[240]",
                   "eval.wave.controllers=[follower_stopper]"])
    rep = evaluate_and_report(cfg, tmp_path)
    assert rep["backend"] == "sumo"
    m = rep["rings"]["240"]["controllers"]["follower_stopper"]
    assert len(m["per_episode"]["mean_speed"]) == 2 and m["collisions"] == 0
    assert "Backend: sumo" in (tmp_path / "report.md").read_text()


@pytest.mark.slow
def test_all_human_sumo_ring_forms_waves_that_follower_stopper_reduces():
    from mixed_traffic.evaluation.waves import wave_metrics

    out = {}
    for name in ("human", "follower_stopper"):
        env = make_env("ring_wave", backend="sumo", seed=1000, ring_length=230.0, episode_seconds=300.0)
        try:
            with torch.no_grad():
                td = env.rollout(3000, make_damper(name, env, seed=1000), break_when_any_done=False)
        finally:
            env.close()
        m = wave_metrics(td, dt=0.1, warmup=150.0)
        assert not m["collision"].any()
        out[name] = float(m["speed_std"].mean())
    assert out["human"] >= 2.0
    assert out["follower_stopper"] < out["human"]


def test_emergency_braking_is_executed_in_sumo_as_in_torch():
    """``cav_emergency_decel``: SUMO executes the safety layer's braking below the action range, as
    the torch backend does; without it a command below the range is clipped to it."""
    for decel, expected in ((9.0, 0.8), (None, 0.3)):
        su = make_env("ring_wave", backend="sumo", seed=0, cav_emergency_decel=decel)
        try:
            assert su.action_spec.space.low.min() == -3.0
            td = su.reset()
            v0 = float(td["cav", "speed"][0, 0])
            nxt = su.step(td.set("action", torch.full((1, 1), -8.0)))["next"]
            assert float(nxt["cav", "speed"][0, 0]) == pytest.approx(max(v0 - expected, 0.0), abs=1e-6)
        finally:
            su.close()
