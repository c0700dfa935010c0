"""SUMO ring backend (libsumo): specs, one-SUMO-per-process guard, collisions, bad input,
agreement with the torch backend. Real SUMO, no mocks."""

from __future__ import annotations

import functools
import os
import subprocess
import sys

import pytest
import torch
from torchrl.envs import ParallelEnv
from torchrl.envs.utils import check_env_specs

libsumo = pytest.importorskip("libsumo")

from mixed_traffic.envs import make_env  # noqa: E402
from mixed_traffic.envs.sumo_net import build_ring_network  # noqa: E402
from mixed_traffic.envs.sumo_ring import SumoRingEnv  # noqa: E402
from mixed_traffic.physics import idm_accel  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CONST_HEAD = dict(profile="constant", profile_kwargs={"v": 10.0})


def _drive(env, accel: float, steps: int):
    td = env.reset()
    for k in range(steps):
        td["action"] = torch.full((1, env.scenario.n_cav), accel)
        td = env.step(td)["next"]
        if bool(td["done"].any()):
            return k + 1, td
    return steps, td


def test_specs_match_torch_backend_and_check_env_specs():
    env = make_env("ring", backend="sumo", seed=0)
    try:
        check_env_specs(env)
        ref = make_env("ring", backend="torch", seed=0)
        assert env.observation_spec == ref.observation_spec
        assert env.full_action_spec == ref.full_action_spec
        assert env.full_reward_spec == ref.full_reward_spec
        assert env.full_done_spec == ref.full_done_spec
        assert env.batch_size == ref.batch_size == torch.Size([1])
        assert env.J_max == ref.J_max and env.dt == ref.dt
        td = env.rollout(20)
        assert td["next", "traffic", "time"][0, -1].item() == pytest.approx(2.0)
        # gaps and positions are consistent: every gap is the ring distance to the leader minus a length
        pos, gap = td["next", "traffic", "pos"][0], td["next", "traffic", "gap"][0]
        ring = (torch.roll(pos, 1, -1) - pos).remainder(313.65) - 5.0
        torch.testing.assert_close(gap, ring, atol=1e-3, rtol=0)
        # the leader's acceleration (what CACC reads) is the leader's row of every vehicle's accelerations
        leaders = [(i - 1) % env.scenario.n_vehicles for i in env.scenario.cav_indices]
        torch.testing.assert_close(td["next", "cav", "leader_accel"], td["next", "traffic", "accel"][..., leaders])
    finally:
        env.close()


def test_overrides_reach_sumo():
    hdv = {"v0": 25.0, "T": 1.5, "s0": 3.0, "a": 1.5, "b": 2.0, "delta": 4.0}
    env = SumoRingEnv("ring", ring_length=200.0, n_vehicles=6, cav_indices=(2, 4), episode_seconds=1.0,
                      hdv_params=hdv, v_init=12.0)
    try:
        check_env_specs(env)
        td = env.rollout(20, break_when_any_done=False)
        assert td["next", "traffic", "speed"].shape == (1, 20, 6)
        assert td["action"].shape == (1, 20, 2)
        # ring of 200 m, 6 cars of 5 m evenly spaced: gaps start at 200/6 - 5
        assert td["traffic", "gap"][0, 0] == pytest.approx(torch.full((6,), 200 / 6 - 5.0), abs=1e-3)
        # 1 s episode at dt 0.1 truncates at step 10, then auto-resets
        assert td["next", "truncated"][0, 9].item() and not td["next", "terminated"][0, 9].item()
        # the human drivers' first step is the IDM with exactly these parameters
        s0 = td[0, 0]
        gap, v = s0["traffic", "gap"], s0["traffic", "speed"]
        expected = idm_accel(gap, v, torch.roll(v, 1), **hdv)
        hdvs = [1, 3, 5]
        torch.testing.assert_close(s0["next", "traffic", "accel"][hdvs], expected[hdvs], atol=1e-4, rtol=0)
    finally:
        env.close()
    with pytest.raises(ValueError, match="v_init"):
        SumoRingEnv("ring", hdv_params={"v0": 8.0})


def test_second_env_in_process_raises_and_close_releases():
    env = make_env("ring", backend="sumo", seed=0)
    try:
        with pytest.raises(RuntimeError, match="already running in this process"):
            make_env("ring", backend="sumo")
    finally:
        env.close()
    assert not libsumo.isLoaded()
    env2 = make_env("ring", backend="sumo", seed=0)  # the guard was released
    env2.close()


def test_speed_mode_0_collides_and_terminates_speed_mode_95_does_not():
    raw = make_env("ring", backend="sumo", seed=0, sumo_safety=False, **CONST_HEAD)
    try:
        k_sumo, td = _drive(raw, 3.0, 600)
        assert td["collision"].item() and td["terminated"].item() and td["done"].item()
        assert not td["truncated"].item()
        assert raw.override_steps == 0  # speed mode 0 executes the command
    finally:
        raw.close()
    ref = make_env("ring", backend="torch", seed=0, **CONST_HEAD)
    k_torch, td_t = _drive(ref, 3.0, 600)
    assert td_t["collision"].item() and k_torch == k_sumo  # same step in both simulators

    safe = make_env("ring", backend="sumo", seed=0, sumo_safety=True, **CONST_HEAD)
    try:
        k, td = _drive(safe, 3.0, 400)
        assert k == 400 and not td["collision"].item()
        assert td["cav", "gap"].item() > 0
        assert safe.override_steps > 300  # SUMO capped almost every command
    finally:
        safe.close()


def test_torch_speed_mode_95_equals_sumos(benchmark_script):
    """The torch backend's sumo_safety against SUMO's speed mode 95 (tolerances: docs/sumo.md, measured)."""
    mod = benchmark_script("sumo_speed_mode_agreement")
    # from SUMO's own state, the function predicts every step SUMO executes (measured: 1e-13 m/s^2
    # before the SUMO ring was reworked for ring_wave, ~1e-6 m/s^2 since; cause not isolated)
    for pol in ("+2", "idm_T0.5"):
        r = mod.one_step(pol, seconds=20.0, seed=0)
        assert r["decision_agreement"] == 1.0 and r["sumo_overridden"] > 150, r
        assert r["max_abs_accel_error"] < 1e-5, r
    # both backends, same episode and commands: same override decisions, executed speeds within
    # 0.05 m/s (measured at most 9.1e-3 m/s over 100 s, 3 seeds)
    for pol in ("+3", "random"):
        r = mod.both_backends(pol, seconds=20.0, seed=1)
        assert r["decision_agreement"] >= 0.99, r
        assert r["speed_max"] < 0.05 and r["accel_rms"] < 0.05, r
        assert not r["collision_torch"] and not r["collision_sumo"]
    # both backends emit the same keys with sumo_safety
    env = make_env("ring", backend="sumo", seed=0, sumo_safety=True)
    try:
        ref = make_env("ring", backend="torch", seed=0, sumo_safety=True)
        assert env.observation_spec == ref.observation_spec
        assert ("cav", "override") in env.observation_spec.keys(True)
    finally:
        env.close()


def test_reset_restarts_with_seeded_profiles():
    def zero(td):
        return td.set("action", torch.zeros(1, 1))

    env = make_env("ring", backend="sumo", seed=3)
    try:
        a = env.rollout(160, zero)["next", "traffic", "speed"][0, :, 0]
        b = env.rollout(160, zero)["next", "traffic", "speed"][0, :, 0]  # a new episode, new profile
        env.set_seed(3)
        c = env.rollout(160, zero)["next", "traffic", "speed"][0, :, 0]
    finally:
        env.close()
    assert not torch.allclose(a, b)
    torch.testing.assert_close(a, c)
    # same seed and episode count as the torch backend: the same head trajectory
    ref = make_env("ring", backend="torch", seed=3)
    t = ref.rollout(160, zero)["next", "traffic", "speed"][0, :, 0]
    torch.testing.assert_close(a, t, atol=0.05, rtol=0)


def test_agreement_with_torch_backend_short(benchmark_script):
    mod = benchmark_script("sumo_agreement")
    _, tr, su = mod.run_pair(seconds=20.0, seed=0)
    res = mod.compare(tr, su)
    assert len(tr["speed"]) == 201
    assert res["speed_rms"] < 0.05, res
    assert res["gap_rms"] < 0.1, res
    # dense ring: every leader is inside SUMO's look-ahead, the two simulators coincide
    _, tr, su = mod.run_pair(seconds=5.0, seed=0, ring_length=200.0, n_vehicles=12)
    assert mod.compare(tr, su)["speed_rms"] < 1e-3


def test_bad_input_shows_sumo_message_and_leaves_nothing_running(tmp_path):
    with pytest.raises(RuntimeError, match="No option with the name 'no-such-option'"):
        make_env("ring", backend="sumo", sumo_args=["--no-such-option"])
    assert not libsumo.isLoaded()
    with pytest.raises(RuntimeError, match="netconvert"):
        make_env("ring", backend="sumo", netconvert=str(tmp_path / "no-netconvert"))
    bad = tmp_path / "bad.net.xml"
    bad.write_text("<net><edge id='e0'")
    with pytest.raises(ValueError, match="net_file"):
        make_env("ring", backend="sumo", net_file=str(bad))
    with pytest.raises(ValueError, match="hdv_model"):
        make_env("ring", backend="sumo", hdv_model="ovm")
    with pytest.raises(ValueError, match="integration"):
        make_env("ring", backend="sumo", integration="euler_explicit")
    with pytest.raises(ValueError, match="sigma"):
        make_env("ring", backend="sumo", sigma=2.0)
    with pytest.raises(ValueError, match="reset_accel"):
        make_env("ring", backend="sumo", reset_accel="model")
    assert not libsumo.isLoaded()
    # a prebuilt network of the wrong length is refused; the right one works
    net = build_ring_network(313.65, str(tmp_path))
    with pytest.raises(ValueError, match="ring_length"):
        make_env("ring", backend="sumo", net_file=net.net_file, ring_length=300.0)
    env = make_env("ring", backend="sumo", net_file=net.net_file)
    try:
        with pytest.raises(ValueError, match="action"):
            env.step(env.reset().set("action", torch.zeros(1, 2)))
    finally:
        env.close()


@pytest.mark.slow
def test_interpreter_exit_closes_sumo():
    code = ("from mixed_traffic.envs import make_env\n"
            "env = make_env('ring', backend='sumo', seed=0)\n"
            "env.rollout(5)\n"
            "import mixed_traffic.envs.sumo_ring as m; assert m._OWNER is env\n"
            "print('ok')\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert res.returncode == 0, res.stderr
    assert "ok" in res.stdout


def test_parallel_env_two_workers():
    penv = ParallelEnv(2, functools.partial(make_env, "ring", backend="sumo"))
    try:
        penv.set_seed(0)
        check_env_specs(penv)
        td = penv.rollout(160, break_when_any_done=False)
        assert td.shape == (2, 1, 160)
        head = td["next", "traffic", "speed"][:, 0, :, 0]
        assert not torch.allclose(head[0, 150:], head[1, 150:])  # workers are seeded differently
    finally:
        penv.close()


@pytest.mark.slow
def test_agreement_120s(benchmark_script):
    mod = benchmark_script("sumo_agreement")
    for seed in (0, 1, 2):
        _, tr, su = mod.run_pair(seconds=120.0, seed=seed)
        res = mod.compare(tr, su)
        assert res["speed_rms"] < 0.5, (seed, res)
        assert not tr["collision"].any() and not su["collision"].any()


@pytest.mark.slow
def test_override_rate_speed_mode_95(benchmark_script):
    mod = benchmark_script("sumo_override_rate")
    assert mod.override_rate("random", 100.0, 0)["rate"] < 0.05
    r = mod.override_rate("+3", 100.0, 0)
    assert r["rate"] > 0.9 and not r["collision"]
    r = mod.override_rate("+3", 100.0, 0, sumo_safety=False)
    assert r["rate"] == 0.0 and r["collision"]
