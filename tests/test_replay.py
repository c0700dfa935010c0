"""The ring CAV replayed behind recorded head traces (mixed_traffic.evaluation.replay): what a base search
relies on is that the replay gives the env's own numbers."""

import pytest
import torch
from omegaconf import open_dict

from mixed_traffic import make_env
from mixed_traffic.config import compose
from mixed_traffic.controllers.classic import make_classic_policy
from mixed_traffic.evaluation.harness import evaluate
from mixed_traffic.evaluation.policies import classic_factory, residual_base_factory
from mixed_traffic.evaluation.replay import record_head_traces, replay, replay_settings, stack_traces
from mixed_traffic.training.builders import residual_base


def _cfg(profile: str, seconds: float, **kwargs):
    cfg = compose(["experiment=ring_lagrangian_ppo_band_stop", "eval.episodes=2", f"eval.episode_seconds={seconds}",
                   f"eval.profiles=[{profile}]", "eval.seed=3000"])
    with open_dict(cfg):
        cfg.eval.profile_kwargs = {profile: kwargs} if kwargs else {}
    return cfg


def _env_run(cfg, factory, profile):
    run = cfg.copy()
    with open_dict(run):
        run.transforms.chain, run.eval.without_layer = ["non_negative_reward"], False
    m, traces = evaluate(run, policy_factory=factory)
    return m["profiles"][profile]["metrics"], traces[profile]


@pytest.fixture(scope="module")
def fast_random_steps():
    """The band base's own rollout of 60 s of random steps at 20-28 m/s (two episodes)."""
    cfg = _cfg("random_steps", 60.0, v_low=20.0, v_high=28.0, period=15.0, v_init=20.0)
    m, trace = _env_run(cfg, residual_base_factory(cfg), "random_steps")
    return cfg, m, trace


def test_replaying_the_recording_law_gives_the_envs_gaps_and_jerk(fast_random_steps):
    """The base re-driven behind its own recording: the same gaps step by step and the same jerk, RMSE and
    largest gap as the env's report, from the start state the replay rebuilds before the first step."""
    cfg, m, trace = fast_random_steps
    base = residual_base(cfg.transforms.residual, make_env("ring", batch_size=1, seed=0)).module.double()
    r = replay(base, trace, **replay_settings(cfg, "random_steps"))
    assert torch.allclose(r["gap"], trace.gap.double(), atol=2e-3)
    assert float(r["mean_abs_jerk"].mean()) == pytest.approx(m["mean_abs_jerk"]["mean"], rel=1e-4)
    assert float(r["speed_rmse_steady"].mean()) == pytest.approx(m["speed_rmse_steady"]["mean"], rel=1e-3)
    assert float(r["max_head_gap"].max()) == pytest.approx(m["max_head_gap"]["max"], abs=2e-3)
    assert float(r["min_gap_after"].min()) == pytest.approx(m["min_gap_after"]["min"], abs=2e-3)


def test_another_law_replayed_behind_the_recording_matches_its_own_env_run(fast_random_steps):
    """IDM replayed behind the base's recording gives what IDM measures in the env on the same episodes
    (its own, different humans reach the head only by a few hundredths of a m/s here): a replay ranks laws
    as the env would."""
    cfg, _, trace = fast_random_steps
    m, idm_trace = _env_run(cfg, classic_factory("idm"), "random_steps")
    idm = make_classic_policy("idm", make_env("ring", batch_size=1, seed=0)).module.double()
    r = replay(idm, trace, **replay_settings(cfg, "random_steps"))
    assert torch.allclose(r["gap"], idm_trace.gap.double(), atol=0.05)
    assert float(r["mean_abs_jerk"].mean()) == pytest.approx(m["mean_abs_jerk"]["mean"], rel=2e-3)
    # and it is a different law: its gaps are not the base's
    assert float((r["gap"] - trace.gap.double()).abs().max()) > 5.0


def test_cacc_replayed_behind_its_own_recording_sees_the_heads_acceleration_as_the_env_gives_it():
    """CACC reads the leader's acceleration of the last step. Replayed behind its own rollout it gives the
    env's gaps and jerk, so the replay feeds the head's acceleration with the env's timing; fed one step
    late (the acceleration of the step before), the gaps part from the env's."""
    cfg = _cfg("sine", 60.0, v_star=24.0, amplitude=4.0, period=20.0)
    m, trace = _env_run(cfg, classic_factory("cacc:ka=0.6"), "sine")  # a strong feed-forward: timing shows
    kw = replay_settings(cfg, "sine")
    cacc = make_classic_policy("cacc", make_env("ring", batch_size=1, seed=0), ka=0.6).module.double()
    r = replay(cacc, trace, **kw)
    assert torch.allclose(r["gap"], trace.gap.double(), atol=2e-3)
    assert float(r["mean_abs_jerk"].mean()) == pytest.approx(m["mean_abs_jerk"]["mean"], rel=1e-4)

    class Late(torch.nn.Module):  # the same law, handed the head's acceleration one step late
        reads_leader_accel = True

        def __init__(self):
            super().__init__()
            self.prev = None

        def forward(self, gap, v, vl, al):
            late = torch.zeros_like(al) if self.prev is None else self.prev
            self.prev = al
            return cacc(gap, v, vl, late)

    late = replay(Late(), trace, **kw)
    assert float((late["gap"] - trace.gap.double()).abs().max()) > 0.05
    with pytest.raises(ValueError, match="cacc reads the leader's acceleration"):
        cacc(torch.ones(1), torch.ones(1), torch.ones(1))


def test_stacked_profiles_replay_as_each_alone(fast_random_steps):
    """Traces of different lengths stacked into one batch (the shorter padded with invalid steps) give each
    profile's metrics as replaying it alone does."""
    cfg, _, trace = fast_random_steps
    short = record_head_traces(_cfg("sine", 30.0))["sine"]
    both, rows = stack_traces([trace, short])
    assert both.valid.shape == (4, trace.valid.shape[1]) and not bool(both.valid[2:, short.valid.shape[1]:].any())
    idm = make_classic_policy("idm", make_env("ring", batch_size=1, seed=0)).module.double()
    kw = replay_settings(cfg, "random_steps")
    together = replay(idm, both, **kw)
    for tr, r in zip((trace, short), rows):
        alone = replay(idm, tr, **kw)
        for key in ("mean_abs_jerk", "min_gap_after", "max_head_gap", "speed_rmse_steady"):
            assert torch.allclose(together[key][r], alone[key]), key


def test_a_recording_cut_short_by_a_collision_is_refused():
    """IDM without an envelope hits a head braking from 25 m/s at 3 m/s^2: the episode ends there, and the
    head's speeds after it are unknown, so the recording is refused with the profile named."""
    cfg = _cfg("emergency_brake", 60.0, start=30.0, v_cruise=25.0, v_low=0.0)
    with pytest.raises(ValueError, match="emergency_brake: an episode ended before the profile's end"):
        record_head_traces(cfg, policy_factory=classic_factory("idm"))
    assert bool(record_head_traces(cfg)["emergency_brake"].valid.all())  # the default recorder stops in time


def test_the_replay_benchmark_ranks_a_grid_against_its_reference(tmp_path):
    """``benchmarks/ring_base_replay.py`` as a user runs it: the reference first (its jerk against itself
    0), one setting per combination of the grid (a list value kept whole), results written; a bad range
    names its flag before anything runs."""
    import json
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent.parent / "benchmarks"))
    from ring_base_replay import main

    out = main(["--experiment", "ring_lagrangian_ppo_band_stop", "--cases", "sine_fast", "--episodes", "2",
                "--grid", "transforms.residual.catch_up.accel=3.0",
                "transforms.residual.catch_up.gaps=[15,25],[20,30]", "--out", str(tmp_path)])
    settings = out["settings"]
    assert [s["overrides"] for s in settings] == [
        [], ["transforms.residual.catch_up.accel=3.0", "transforms.residual.catch_up.gaps=[15,25]"],
        ["transforms.residual.catch_up.accel=3.0", "transforms.residual.catch_up.gaps=[20,30]"]]
    assert settings[0]["cases"]["sine_fast"]["jerk_vs_reference"] == 0.0
    assert len((tmp_path / "replay.jsonl").read_text().splitlines()) == 3
    assert json.loads((tmp_path / "replay.json").read_text())["cases"] == ["sine_fast"]
    with pytest.raises(SystemExit, match="--vary"):
        main(["--experiment", "ring_lagrangian_ppo_band_stop", "--vary", "transforms.residual.weight=2:1"])
    # the fresh cases are accepted by name (to look into them) but are not searched on by default
    with pytest.raises(SystemExit, match=r"\['sine_slowest'\] are not cases; allowed: .*'sine_wide'"):
        main(["--experiment", "ring_lagrangian_ppo_band_stop", "--cases", "sine_slowest"])
    import ring_base_replay
    assert "sine_wide" in ring_base_replay.NAMES and "sine_wide" not in ring_base_replay.PROBED
    assert {"sine_slow_wide", "sine_cross"} <= set(ring_base_replay.NAMES)


def test_the_replay_benchmark_searches_a_classical_controller_by_its_own_parameters(tmp_path):
    """``--classic cacc``: settings name CACC's parameters (not Hydra keys), the reference is CACC's
    defaults, and CACC is replayed with the head's acceleration it reads; unknown names fail before
    anything is recorded."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent.parent / "benchmarks"))
    from ring_base_replay import main

    out = main(["--experiment", "ring_lagrangian_ppo_band_stop", "--classic", "cacc", "--cases", "sine_fast",
                "--episodes", "2", "--set", "h=1.2", "--grid", "ka=0.0,0.6", "--out", str(tmp_path)])
    assert out["classic"] == "cacc" and [s["overrides"] for s in out["settings"]] == [[], ["ka=0.0"], ["ka=0.6"]]
    jerk = [s["cases"]["sine_fast"]["jerk"] for s in out["settings"]]
    assert len(set(jerk)) == 3  # the fed-forward share changes the command behind a sine
    with pytest.raises(SystemExit, match=r"\['kz'\] are not cacc parameters; allowed: \['e_max', 'h', 'ka'"):
        main(["--experiment", "ring_lagrangian_ppo_band_stop", "--classic", "cacc", "--vary", "kz=0:1"])
    with pytest.raises(SystemExit, match="--classic: classic controller 'pid' is invalid"):
        main(["--experiment", "ring_lagrangian_ppo_band_stop", "--classic", "pid"])
