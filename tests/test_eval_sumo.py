"""The evaluation harness on the SUMO backend: same report as torch, SafetyLayer guarantee in SUMO (speed mode 0)."""

import pytest
import torch
from tensordict.nn import TensorDictModule

pytest.importorskip("libsumo")

from mixed_traffic.config import compose  # noqa: E402
from mixed_traffic.evaluation.harness import METRICS  # noqa: E402
from mixed_traffic.evaluation.sumo import evaluate_on_sumo, evaluate_on_torch_seeds  # noqa: E402

S_MIN = 5.0  # transforms=safe: SafetyLayer(s_min=5, mode="stopping")


def _keys(d, prefix=""):
    out = set()
    for k, v in d.items():
        out.add(prefix + k)
        if isinstance(v, dict) and k not in ("profiles",):
            out |= _keys(v, prefix + k + ".")
    return out


def _full_throttle(env):
    """Always +3 m/s^2: without the SafetyLayer it drives into its leader (~7 s in)."""
    return TensorDictModule(lambda v: torch.full_like(v, 3.0), in_keys=[("cav", "speed")], out_keys=["action"])


def test_sumo_report_matches_torch_and_safety_layer_holds():
    # NonNegativeReward + SafetyLayer(s_min=5, "stopping") (no residual: the policy's command is the action);
    # SUMO speed mode 0
    cfg = compose(["experiment=ring_lagrangian_ppo", "transforms=safe", "eval.warmup_seconds=1.0",
                   "eval.settle_seconds=0.5"])
    kw = dict(policy_factory=_full_throttle, profiles=["random_steps"], episodes=1, seed=7, episode_seconds=20.0)
    sumo, traces = evaluate_on_sumo(cfg, workers=0, **kw)  # in this process: no worker spawn
    torch_rep, _ = evaluate_on_torch_seeds(cfg, **kw)

    assert sumo["backend"] == "sumo" and sumo["speed_mode"] == 0 and sumo["episode_seeds"] == [7]
    # same structure as the torch harness's report (the SUMO one adds backend details)
    assert _keys(torch_rep) <= _keys(sumo)
    pt, ps = torch_rep["profiles"]["random_steps"], sumo["profiles"]["random_steps"]
    assert set(ps) == set(pt) and set(ps["metrics"]) == set(pt["metrics"]) == set(METRICS)
    assert set(ps["per_episode"]) == set(pt["per_episode"])
    assert traces["random_steps"].gap.shape == (1, 200)
    assert ps["per_episode"]["length"] == [pytest.approx(20.0)]

    # the SafetyLayer clipped most steps, and its guarantee holds in SUMO: no collision, gap >= s_min
    assert sumo["overall"]["collisions"] == 0
    assert ps["metrics"]["safety_clip_rate"]["mean"] > 0.5
    assert sumo["overall"]["min_gap"] >= S_MIN - 1e-3
    assert sumo["overall"]["min_gap"] < S_MIN + 3.0  # the layer, not the distance, kept it apart
    # the same episode in both simulators
    assert ps["metrics"]["min_gap"]["min"] == pytest.approx(pt["metrics"]["min_gap"]["min"], abs=0.3)
    # the policy itself, without the layer, from the standard start and the close starts: it drives into its
    # leader on SUMO as on torch, and the acceptance says so
    free_s, free_t = sumo["without_layer"]["random_steps"], torch_rep["without_layer"]["random_steps"]
    assert list(free_s) == list(free_t) == ["standard (73.4 m)", "8 m", "15 m"]
    for label in free_s:
        assert free_s[label]["collisions"] == free_t[label]["collisions"] == 1, label
    assert abs(float(traces["random_steps_without_layer_close"].gap[0, 0]) - 8.0) < 1.0  # it did start 8 m back
    assert not sumo["acceptance"]["no_layer_zero_collisions"] and not sumo["acceptance"]["pass"]


def test_sumo_evaluates_the_deployed_chain_as_torch_does():
    """The default's chain on SUMO is the one the torch evaluation runs: deployed (the drive-off lift and the
    envelope fade of ``deploy`` on) and without the training-only jerk price, so the return, the jerk and the
    gaps of the same episode agree across the backends (the residual at zero: the classical base drives)."""
    from mixed_traffic.apps.main_job import DEFAULT_EXPERIMENT
    from mixed_traffic.evaluation.harness import eval_env_overrides
    from mixed_traffic.evaluation.sumo import make_sumo_eval_env
    from transforms import DriveOffCap, JerkPenalty, ResidualAction, SafetyLayer

    cfg = compose([f"experiment={DEFAULT_EXPERIMENT}", "eval.warmup_seconds=1.0", "eval.settle_seconds=0.5",
                   "eval.without_layer=false"])  # the layer-free runs: test_sumo_report_matches_torch_...
    assert "jerk_penalty" in cfg.transforms.chain and cfg.transforms.residual.envelope_fade == "deploy"
    env = make_sumo_eval_env(cfg, [7], in_process=True, **eval_env_overrides(cfg, "random_steps"))
    try:
        assert not any(isinstance(t, JerkPenalty) for t in env.transform)
        assert next(t for t in env.transform if isinstance(t, ResidualAction)).room_key is not None  # deployed
        assert any(isinstance(t, DriveOffCap) for t in env.transform)  # ... with the drive-off cap
        assert next(t for t in env.transform if isinstance(t, SafetyLayer)).s_max is None  # ... and the s_min rule alone
    finally:
        env.close()
    zero = TensorDictModule(lambda v: torch.zeros_like(v), in_keys=[("cav", "speed")], out_keys=["action"])
    kw = dict(policy_factory=lambda env: zero, profiles=["random_steps"], episodes=1, seed=7, episode_seconds=30.0)
    sumo, _ = evaluate_on_sumo(cfg, workers=0, **kw)
    torch_rep, _ = evaluate_on_torch_seeds(cfg, **kw)
    ps, pt = sumo["profiles"]["random_steps"]["metrics"], torch_rep["profiles"]["random_steps"]["metrics"]
    assert ps["return"]["mean"] == pytest.approx(pt["return"]["mean"], rel=1e-3)
    assert ps["mean_abs_jerk"]["mean"] == pytest.approx(pt["mean_abs_jerk"]["mean"], rel=0.02)
    assert ps["min_gap"]["min"] == pytest.approx(pt["min_gap"]["min"], abs=0.05)


def test_full_throttle_collides_without_the_safety_layer():
    """Control for the test above (torch backend, cheap): the policy is unsafe on its own."""
    cfg = compose(["experiment=ring_lagrangian_ppo", "transforms.chain=[non_negative_reward]"])
    rep, _ = evaluate_on_torch_seeds(cfg, policy_factory=_full_throttle, profiles=["random_steps"], episodes=1,
                                     seed=7, episode_seconds=20.0)
    assert rep["overall"]["collisions"] == 1


@pytest.mark.slow
def test_sumo_parallel_workers_give_the_in_process_episodes():
    """ParallelEnv(2) (3 episodes: rounds of 2 + 1) reproduces the in-process episodes, seed by seed."""
    cfg = compose(["experiment=ring_lagrangian_ppo", "transforms=safe", "eval.warmup_seconds=1.0",
                   "eval.settle_seconds=0.5", "eval.without_layer=false"])
    kw = dict(policy_factory=_full_throttle, profiles=["random_steps"], episodes=3, seed=11, episode_seconds=5.0)
    par, _ = evaluate_on_sumo(cfg, workers=2, **kw)
    seq, _ = evaluate_on_sumo(cfg, workers=0, **kw)
    assert par["workers"] == 2 and par["episode_seeds"] == [11, 12, 13]
    a, b = par["profiles"]["random_steps"]["per_episode"], seq["profiles"]["random_steps"]["per_episode"]
    for k in ("min_gap", "return", "mean_abs_accel", "speed_rmse"):
        assert a[k] == pytest.approx(b[k], rel=1e-5), k


def test_mt_eval_backend_sumo_writes_the_same_report(tmp_path):
    """`mt-eval controller=idm env.backend=sumo` goes through the SUMO evaluation."""
    from mixed_traffic.evaluation import evaluate_and_report

    cfg = compose(["experiment=ring_lagrangian_ppo", "controller=idm", "env.backend=sumo", "eval.episodes=1",
                   "eval.episode_seconds=20", "eval.warmup_seconds=5", "eval.profiles=[emergency_brake]",
                   "eval.close_starts=[8.0]"])  # one close start: each layer-free start is a SUMO run of its own
    rep = evaluate_and_report(cfg, tmp_path)
    assert rep["backend"] == "sumo" and rep["speed_mode"] == 0
    assert (tmp_path / "report.md").is_file() and (tmp_path / "report.json").is_file()
    assert rep["overall"]["collisions"] == 0
    # the layer-free bars are there, as on torch: IDM-as-CAV without the layer, from the close start too
    assert list(rep["without_layer"]["emergency_brake"]) == ["standard (73.4 m)", "8 m"]
    assert rep["acceptance"]["no_layer_zero_collisions"] is True


@pytest.mark.parametrize("sensor_filter", [False, True])
def test_sumo_measures_the_true_state_under_sensor_noise(sensor_filter):
    """A controller that reads nothing drives the same SUMO episode with and without noise: the same metrics
    (the evaluation subtracts the errors SensorNoise added, or those of MeasurementFilter's estimates), while
    the noise did reach the chain."""
    cfg = compose(["experiment=ring_lagrangian_ppo", "transforms=reward", "eval.warmup_seconds=1.0",
                   "eval.settle_seconds=0.5"])
    noisy = compose(["experiment=ring_lagrangian_ppo", "transforms=reward", "eval.warmup_seconds=1.0",
                     "eval.settle_seconds=0.5", "eval.sensor_noise_gap=2.0", "eval.sensor_noise_speed=0.5",
                     f"eval.sensor_filter={str(sensor_filter).lower()}"])
    blind = lambda env: TensorDictModule(lambda v: torch.zeros_like(v), in_keys=[("cav", "speed")],  # noqa: E731
                                         out_keys=["action"])
    kw = dict(policy_factory=blind, profiles=["random_steps"], episodes=1, seed=7, episode_seconds=15.0)
    exact, _ = evaluate_on_sumo(cfg, workers=0, **kw)
    rep, _ = evaluate_on_sumo(noisy, workers=0, **kw)
    assert rep["sensor_noise"]["gap"] == 2.0 and rep["sensor_noise"]["filter"] is sensor_filter
    for key in ("min_gap", "max_head_gap", "speed_rmse", "mean_abs_jerk"):
        assert rep["profiles"]["random_steps"]["per_episode"][key] == pytest.approx(
            exact["profiles"]["random_steps"]["per_episode"][key], abs=1e-3), key


def test_the_drive_off_cap_acts_in_sumo_as_on_torch():
    """Behind a head that stops and drives off, the deployed cap keeps the CAV from passing the head's speed to
    close the gap, in SUMO as on torch: once the head holds its speed, the CAV stays within the overspeed of it,
    where the base alone passes it by about a metre per second."""
    from omegaconf import OmegaConf, open_dict

    stop = {"times": [0.0, 10.0, 17.5, 23.5, 31.0, 70.0], "speeds": [15.0, 15.0, 0.0, 0.0, 15.0, 15.0]}
    zero = TensorDictModule(lambda v: torch.zeros_like(v), in_keys=[("cav", "speed")], out_keys=["action"])
    over = {}
    for name in ("ring_lagrangian_ppo_v2v", "ring_lagrangian_ppo_drive_off"):
        cfg = compose([f"experiment={name}", "eval.profiles=[piecewise]", "eval.without_layer=false"])
        with open_dict(cfg):
            cfg.eval.profile_kwargs = OmegaConf.create({"piecewise": stop})
        kw = dict(policy_factory=lambda env: zero, profiles=["piecewise"], episodes=1, seed=7, episode_seconds=70.0)
        for backend in ("sumo", "torch"):
            run = evaluate_on_sumo(cfg, workers=0, **kw) if backend == "sumo" else evaluate_on_torch_seeds(cfg, **kw)
            tr = run[1]["piecewise"]
            held = tr.time >= 33.0  # the head holds 15 m/s from 31 s
            over[name, backend] = float((tr.cav_speed - tr.head_speed)[held].max())
    for backend in ("sumo", "torch"):
        assert over["ring_lagrangian_ppo_v2v", backend] > 0.8, over  # the base passes the head's speed
        assert over["ring_lagrangian_ppo_drive_off", backend] < 0.16, over  # under the cap: the overspeed, 0.15 m/s


def test_generalization_runs_a_case_on_sumo_as_on_torch(tmp_path, benchmark_script):
    """benchmarks/ring_generalization.py --backend sumo: a held-out case (random steps on a 250-m ring) in SUMO, on
    the same episodes and in the same table as on torch: the policy with its layer, without it from the three starts,
    and IDM-as-CAV, each within what the two simulators differ by; the backend is recorded, and a bad --workers
    fails before anything runs."""
    import json

    from tests.test_policy_itself import _tiny_scratch_run

    run = _tiny_scratch_run(tmp_path / "run")
    mod = benchmark_script("ring_generalization")
    common = ["--checkpoint", str(run), "--episodes", "1", "--seconds", "15", "--cases", "ring_250", "--baselines", "idm"]
    on_torch = mod.main([*common, "--out", str(tmp_path / "torch")])["ring_250"]
    on_sumo = mod.main([*common, "--backend", "sumo", "--workers", "0", "--out", str(tmp_path / "sumo")])["ring_250"]
    starts = list(on_torch["policy_without_layer"])
    assert list(on_sumo["policy_without_layer"]) == starts and len(starts) == 3
    pairs = [(on_sumo[k], on_torch[k]) for k in ("policy", "idm")]
    pairs += [(on_sumo["policy_without_layer"][k], on_torch["policy_without_layer"][k]) for k in starts]
    for s, t in pairs:
        assert s["collisions"] == t["collisions"]
        assert s["return"] == pytest.approx(t["return"], rel=0.01)
        assert s["min_gap"] == pytest.approx(t["min_gap"], abs=0.3)
    assert json.loads((tmp_path / "sumo" / "generalization.json").read_text())["backend"] == "sumo"
    with pytest.raises(SystemExit, match="--workers: -1 is invalid"):
        mod.main([*common, "--backend", "sumo", "--workers", "-1", "--out", str(tmp_path / "bad")])
    assert not (tmp_path / "bad").exists()
