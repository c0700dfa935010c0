"""Evaluation harness: metrics on known traces, classical controllers, reports from checkpoints, mt-eval."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

from mixed_traffic import make_env
from mixed_traffic.config import compose
from mixed_traffic.controllers.classic import make_classic_policy
from mixed_traffic.evaluation import episode_metrics, evaluate, evaluate_and_report
from mixed_traffic.training import train

SHORT_EVAL = ["eval.episodes=2", "eval.episode_seconds=30.0", "eval.warmup_seconds=5.0", "eval.settle_seconds=3.0",
              "eval.profiles=[random_steps,emergency_brake]", "eval.profile_kwargs.emergency_brake.start=10.0"]


def _trace(T=100, dt=0.1):
    """Two synthetic episodes: the second collides at step 60 and is masked afterwards."""
    t = (torch.arange(T, dtype=torch.float32) + 1) * dt
    gap = torch.full((2, T), 10.0)
    gap[0, 30:40] = 4.0  # 1 s below s_min (after the 1 s warm-up)
    gap[1, 59] = 0.0
    head_gap = gap.clone()
    head_gap[0, 50:55] = 45.0  # 0.5 s above s_max
    v = torch.full((2, T), 10.0)
    vh = torch.full((2, T), 10.0)
    v[0, 80:] = 11.0  # 1 m/s error late in the steady phase
    a_head = torch.zeros(2, T)
    a_head[:, 70] = 1.0  # one head acceleration: steady resumes after `settle`
    collision = torch.zeros(2, T, 1, dtype=torch.bool)
    collision[1, 59] = True
    done = collision.clone()
    nxt = TensorDict({
        "cav": {"gap": gap[..., None], "head_gap": head_gap[..., None], "speed": v[..., None],
                "head_speed": vh[..., None], "accel": torch.zeros(2, T, 1)},
        "traffic": {"time": t.expand(2, T)[..., None], "accel": torch.stack([a_head, a_head], -1),
                    "J": torch.ones(2, T, 1)},
        "reward": torch.ones(2, T, 1), "collision": collision, "done": done,
    }, batch_size=[2, T])
    return TensorDict({"next": nxt}, batch_size=[2, T])


def test_episode_metrics_on_a_known_trace():
    m, tr = episode_metrics(_trace(), dt=0.1, s_min=5.0, s_max=40.0, warmup=1.0, settle=0.5)
    assert m["collision"].tolist() == [0.0, 1.0]
    assert m["min_gap"].tolist() == [4.0, 0.0]
    assert m["time_outside"][0].item() == pytest.approx(1.5)  # 10 steps below s_min + 5 above s_max
    assert m["length"].tolist() == pytest.approx([10.0, 6.0])
    assert m["return"].tolist() == [100.0, 60.0]  # masked after the collision
    # steady: head still for >= 0.5 s; errors of 1 m/s on steps 80..99, steady samples from step 76 on
    n_steady = (torch.arange(100) >= 9).sum() - 5  # after warm-up, minus the 5 steps after the head's pulse
    assert m["speed_rmse_steady"][0].item() == pytest.approx((20 / n_steady.item()) ** 0.5, rel=1e-4)
    assert m["steady_seconds"][0].item() == pytest.approx(0.1 * n_steady.item())  # how long they last
    assert not tr.valid[1, 60:].any()


def test_an_episode_without_a_steady_state_says_its_steady_rmse_is_the_whole_episodes():
    """A head that never holds its speed for ``settle`` seconds (here a sine) has no steady samples: the steady
    RMSE falls back to the whole-episode RMSE, and ``steady_seconds`` = 0 says so; a head that holds gives the
    time it held, less the settling."""
    from mixed_traffic.evaluation.harness import follower_metrics

    T, dt = 400, 0.1
    t = torch.arange(T) * dt
    sine = torch.stack([torch.sin(t / 3.0), torch.zeros(T)])  # row 0: never still; row 1: held from the start
    v_head = 20.0 + torch.cumsum(sine, 1) * dt
    v = v_head + torch.tensor([[0.5], [0.3]])
    ones, after = torch.ones(2, T, dtype=torch.bool), t.expand(2, T) >= 10.0
    m = follower_metrics(gap=torch.full((2, T), 20.0), head_gap=torch.full((2, T), 20.0), speed=v, head_speed=v_head,
                         accel=sine, head_accel=sine, valid=ones, after=after, dt=dt, settle=8.0)
    assert m["steady_seconds"].tolist() == pytest.approx([0.0, 30.0])  # 10-40 s after the warm-up, settled from 8 s
    assert m["speed_rmse_steady"][0].item() == pytest.approx(m["speed_rmse"][0].item())  # the fallback
    assert m["speed_rmse_steady"][1].item() == pytest.approx(0.3, rel=1e-5)


def test_jerk_after_the_warm_up_leaves_the_start_transient_out():
    td = _trace()
    a = td["next", "cav", "accel"]
    a[0, 2] = 3.0  # a 0.1-s pulse of 3 m/s^2 at t = 0.3 s, inside the 1-s warm-up
    a[0, 50] = 1.0  # and one of 1 m/s^2 after it
    m, _ = episode_metrics(td, dt=0.1, s_min=5.0, s_max=40.0, warmup=1.0, settle=0.5)
    # |da|/dt: 30 + 30 (up, down) in the warm-up, 10 + 10 after; 99 jerk samples, 91 after the warm-up
    assert m["mean_abs_jerk"][0].item() == pytest.approx(80 / 99, rel=1e-4)
    assert m["mean_abs_jerk_after"][0].item() == pytest.approx(20 / 91, rel=1e-4)


def test_classic_controllers_follow_without_collision():
    for name in ("idm", "ovm", "soft", "cacc"):
        env = make_env("ring", batch_size=3, seed=0)
        td = env.rollout(600, make_classic_policy(name, env), break_when_any_done=False)
        assert not td["next", "collision"].any(), name
        a = td["action"]
        assert (a >= -3.0).all() and (a <= 3.0).all()
    with pytest.raises(ValueError, match="allowed"):
        make_classic_policy("idm", env, T_typo=1.0)
    with pytest.raises(ValueError, match="allowed"):
        make_classic_policy("pid", env)
    with pytest.raises(ValueError, match=r"cacc parameter h = -1.0 is invalid; allowed: >= 0"):
        make_classic_policy("cacc", env, h=-1.0)
    with pytest.raises(ValueError, match=r"reads the leader's acceleration .* which this env does not observe"):
        make_classic_policy("cacc", make_env("platoon", seed=0))  # the DeeP-LCC platoon has no leader_accel


def test_evaluate_a_classical_controller_is_deterministic():
    cfg = compose(["experiment=ring_lagrangian_ppo", "transforms=reward"] + SHORT_EVAL)
    r1, _ = evaluate(cfg, policy_factory=lambda env: make_classic_policy("idm", env))
    r2, _ = evaluate(cfg, policy_factory=lambda env: make_classic_policy("idm", env))
    assert r1["overall"] == r2["overall"]
    assert set(r1["profiles"]) == {"random_steps", "emergency_brake"}
    assert r1["overall"]["collisions"] == 0 and r1["overall"]["episodes"] == 4


def test_an_episode_does_not_depend_on_the_batch_it_runs_in():
    """Episode e of an evaluation is the same whatever else is evaluated: more episodes, other
    controllers, with or without the layer (the harness seeds rows per episode)."""
    cfg = compose(["experiment=ring_lagrangian_ppo", "transforms=reward"] + SHORT_EVAL)
    two, _ = evaluate(cfg, policy_factory=lambda env: make_classic_policy("idm", env), episodes=2)
    three, _ = evaluate(cfg, policy_factory=lambda env: make_classic_policy("idm", env), episodes=3)
    assert two["episode_seeds"] == three["episode_seeds"][:2] == [cfg.eval.seed, cfg.eval.seed + 1]
    for prof in ("random_steps", "emergency_brake"):
        for k in ("return", "mean_abs_jerk", "max_head_gap"):
            assert two["profiles"][prof]["per_episode"][k] == three["profiles"][prof]["per_episode"][k][:2]
    # the random head steps and the humans' parameters differ from episode to episode
    rs = three["profiles"]["random_steps"]["per_episode"]["return"]
    assert len(set(rs)) == 3


def test_rows_seeded_alone_run_what_a_one_row_env_runs():
    """seed_rows: row i of a batch runs the episode of a one-row env seeded seeds[i], per-step noise included."""
    kw = dict(episode_seconds=3.0, hdv_param_noise=0.2, accel_noise=0.3, init_spacing_range=(8.0, 30.0))
    batch = make_env("ring", batch_size=3, seed=0, **kw)
    batch.seed_rows([11, 12, 13])
    one = make_env("ring", batch_size=1, seed=12, **kw)
    act_b, act_1 = torch.zeros(3, 1), torch.zeros(1, 1)
    tb, t1 = batch.reset(), one.reset()
    for _ in range(20):
        tb = batch.step(tb.set("action", act_b))["next"]
        t1 = one.step(t1.set("action", act_1))["next"]
    assert torch.equal(tb["cav", "gap"][1], t1["cav", "gap"][0])
    assert torch.equal(tb["traffic", "speed"][1], t1["traffic", "speed"][0])  # the noisy humans too
    assert not torch.equal(tb["cav", "gap"][0], tb["cav", "gap"][1])  # other seeds, other episodes
    with pytest.raises(ValueError, match="seed_rows: 2 seeds is invalid; allowed: None or one seed per row"):
        batch.seed_rows([1, 2])


def test_the_metrics_rollout_is_torchrls_rollout_to_the_bit():
    """rollout_for_metrics keeps fewer keys than env.rollout, not other numbers: a PPO actor, the safety
    layer, episodes that end on the last step (no reset may write into it)."""
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from mixed_traffic.evaluation.harness import METRIC_KEYS, rollout_for_metrics
    from mixed_traffic.training.builders import make_transformed_env
    from mixed_traffic.training.on_policy import build_ppo

    cfg = compose(["experiment=ring_lagrangian_ppo", "env.episode_seconds=6.0"])
    torch.manual_seed(0)
    actor = build_ppo(cfg, make_transformed_env(cfg, num_envs=2, seed=0))[0]
    runs = []
    for lean in (False, True):
        env = make_transformed_env(cfg, num_envs=3, seed=5)
        env.base_env.seed_rows([5, 6, 7])
        steps = env.base_env.scenario.max_steps
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            runs.append(rollout_for_metrics(env, actor, steps) if lean
                        else env.rollout(steps, actor, break_when_any_done=False))
    ref, lean = runs
    assert bool(lean["next", "done"][:, -1].all())
    keys = [("next",) + (k if isinstance(k, tuple) else (k,)) for k in METRIC_KEYS]
    keys = [k for k in keys if k in ref.keys(True)]
    assert ("next", "safety", "delta") in keys and len(keys) >= 12
    for k in keys:
        assert torch.equal(ref.get(k), lean.get(k)), k
    assert set(lean.keys(True, True)) == set(keys)


def test_paired_differences_need_the_same_episodes():
    from mixed_traffic.evaluation.results import paired_differences

    def rep(seeds, values):
        return {"episode_seeds": seeds, "profiles": {"sine": {"per_episode": {"return": values}}}}

    d = paired_differences(rep([5, 6, 7], [3.0, 5.0, 4.0]), rep([5, 6, 7], [1.0, 2.0, 6.0]), "return")["sine"]
    assert d["mean"] == pytest.approx(1.0) and d["run_lower"] == 1 and d["n"] == 3
    assert d["se"] == pytest.approx(((4.0 + 1.0 + 9.0) / 2) ** 0.5 / 3 ** 0.5)  # diffs 2, 3, -2
    with pytest.raises(ValueError, match="episode_seeds .* are invalid; allowed: the same list"):
        paired_differences(rep([5, 6, 7], [1.0] * 3), rep([1000, 1001, 1002], [1.0] * 3), "return")
    with pytest.raises(ValueError, match="episode_seeds None"):
        paired_differences(rep(None, [1.0] * 3), rep([5, 6, 7], [1.0] * 3), "return")


def test_paired_table_names_a_run_however_it_is_given(tmp_path):
    """A run given as its directory, its ``eval/`` or its ``report.json`` is named by the run directory."""
    from mixed_traffic.evaluation.results import paired_table

    rep = {"episode_seeds": [5, 6], "policy": "idm", "profiles": {"sine": {"per_episode": {"return": [1.0, 2.0]}}}}
    (tmp_path / "seed3" / "eval").mkdir(parents=True)
    (tmp_path / "seed3" / "eval" / "report.json").write_text(json.dumps(rep))
    for given in ("seed3", "seed3/eval", "seed3/eval/report.json"):
        rows = paired_table([tmp_path / given], tmp_path / "seed3", metrics=("return",)).splitlines()
        assert rows[-1].startswith("| seed3 | sine | return | 1.5000 | 1.5000 | +0.0000"), (given, rows[-1])


def test_results_cli_says_what_paired_needs(capsys):
    from mixed_traffic.evaluation.results import main

    with pytest.raises(SystemExit) as e:
        main(["--paired", "outputs/some_run"])  # no --baseline: refused before any report is read
    assert e.value.code == 2 and "--paired needs --baseline DIR" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--paired", "--itself", "a", "--baseline", "b"])  # one table at a time


def _generalization_json(path, *, jerk, gap, seed=2000, v2v=None, cacc=True, layered=0.1):
    """A generalization.json of one case, as benchmarks/ring_generalization.py writes it."""
    def r(**kw):
        return {"collisions": 0, "min_gap": gap, "min_gap_after": gap, "max_head_gap": 30.0, "steady_rmse": 0.1,
                "jerk": 0.1, "return": 100.0, "intervention_rate": 0.01, **kw}

    case = {"seconds": 200.0, "policy": r(jerk=layered), "idm": r(),
            "policy_without_layer": {"standard (73.4 m)": r(jerk=jerk), "8 m": r(min_gap_after=gap + 1.0,
                                                                                 max_head_gap=36.0)}}
    if cacc:
        case["cacc"] = r(jerk=0.12)
    g = {"checkpoint": "x", "episodes": 4, "seconds": 200.0, "seed": seed, "results": {"sine_fast": case}}
    if v2v is not None:
        g["v2v"] = v2v
    path.mkdir(parents=True)
    (path / "generalization.json").write_text(json.dumps(g))
    return path


def test_a_colliding_idm_is_not_the_reference_of_the_jerk_and_return_bars(tmp_path):
    """Where IDM-as-CAV collides, its episodes end at the collision: its jerk and return cover a shorter window
    than the policy's, so the bars (and the table's columns against IDM's) compare with the first classical
    controller that completes every episode, taken from whichever run evaluated it, and the row is marked."""
    from mixed_traffic.evaluation.results import bar_reference, case_bars, clean_cases, generalization_table

    a = _generalization_json(tmp_path / "s0", jerk=0.09, gap=7.5, layered=0.09, cacc=True)
    b = _generalization_json(tmp_path / "s1", jerk=0.09, gap=7.5, layered=0.09, cacc=False)
    for d in (a, b):  # IDM-as-CAV crashes early: a high jerk over a short window, a small return
        g = json.loads((d / "generalization.json").read_text())
        g["results"]["sine_fast"]["idm"].update(collisions=4, episodes=4, jerk=0.2, **{"return": 10.0})
        (d / "generalization.json").write_text(json.dumps(g))
    x = json.loads((a / "generalization.json").read_text())["results"]["sine_fast"]
    assert bar_reference(x) == ("cacc", x["cacc"])  # cacc: jerk 0.12, return 100, no collision
    assert case_bars(x)["jerk"] is True and case_bars(x)["return"] is True
    x["cacc"]["jerk"] = 0.08  # smoother than the policy: the jerk bar is missed, whatever the crashed IDM had
    assert case_bars(x)["jerk"] is False
    x["cacc"]["collisions"] = 1  # no stand-in completes: the two bars are not judged
    assert bar_reference(x) == (None, None) and case_bars(x)["jerk"] is None and case_bars(x)["return"] is None
    # the second run has no cacc row: it is taken from the first run (the same episodes)
    xb = json.loads((b / "generalization.json").read_text())["results"]["sine_fast"]
    assert bar_reference(xb) == (None, None) and bar_reference(xb, {"cacc": x["cacc"] | {"collisions": 0}})[0] == "cacc"
    assert clean_cases([a, b]) == (1, 1)
    rows = generalization_table([a, b], bars=True).splitlines()
    assert rows[4].startswith("| sine_fast † | 0 | 7.50–36.0 | -25.0 % |")  # 0.09 against cacc's 0.12, not IDM's 0.2
    assert rows[6].startswith("† sine_fast: IDM-as-CAV collided on 4 of 4 episodes") and "against cacc" in rows[6]
    assert rows[-1].endswith("the policy (the first run) 1, idm 0, cacc 1 of the 1 cases.")  # cacc is the reference
    from mixed_traffic.evaluation.results import scorecard_margins
    (m,) = scorecard_margins([a, b])  # what the scorecard's figure draws: against the stand-in, per run
    assert m["reference"] == "cacc" and m["clean"] and m["jerk"] == pytest.approx([-25.0, -25.0])
    assert m["return"] == pytest.approx([0.0, 0.0]) and m["classical"] == {}  # IDM collided: not drawn


def test_the_bars_table_names_what_each_classical_controller_misses_beside_the_policys_misses(tmp_path):
    """A reviewer holds a policy's miss against the classical controllers on the same episodes: where IDM-as-CAV
    keeps the band and the RMSE bar it meets every bar (it is the jerk and return reference), so a policy with more
    jerk has lost to it; where IDM-as-CAV leaves the band, the table says by how much, and that no classical
    controller met every bar either. The scorecard's count reads the same judgement."""
    from mixed_traffic.evaluation.results import generalization_table, scorecard_margins

    a = _generalization_json(tmp_path / "s0", jerk=0.12, gap=7.5, layered=0.12)  # the policy: more jerk than IDM
    b = _generalization_json(tmp_path / "s1", jerk=0.11, gap=7.5, layered=0.11, cacc=False)
    rows = generalization_table([a, b], bars=True).splitlines()
    assert rows[2].endswith("| bars missed (of 2 runs) | classical controllers: bars missed |")
    assert rows[4].endswith("| jerk 2 of 2 | idm: –; cacc: jerk |"), rows[4]  # cacc 0.12 against IDM's 0.1
    assert rows[-1] == ("Where the policy misses a bar (1 of the cases), a classical controller meets every bar on the "
                        "same episodes on 1: sine_fast (idm) (the last column).")
    assert scorecard_margins([a, b])[0]["classical_clean"] == ["idm"]
    for d in (a, b):  # IDM-as-CAV drifts out of the band: it no longer meets every bar, and the cell says where
        g = json.loads((d / "generalization.json").read_text())
        g["results"]["sine_fast"]["idm"]["max_head_gap"] = 51.0
        (d / "generalization.json").write_text(json.dumps(g))
    rows = generalization_table([a, b], bars=True).splitlines()
    assert rows[4].endswith("| jerk 2 of 2 | idm: gaps 7.5–51.0 m; cacc: jerk |"), rows[4]
    assert rows[-1] == ("Where the policy misses a bar (1 of the cases), no classical controller meets every bar on "
                        "the same episodes either (the last column).")
    assert scorecard_margins([a, b])[0]["classical_clean"] == []


def test_the_scorecard_says_what_the_learned_residual_adds(tmp_path):
    """The policy beside its deployed controller with the learned residual at zero (the ``zero_residual`` baseline)
    on the same episodes: where that controller keeps every bar and the policy does not, the learned part cost a
    bar; the sentence names such cases, counts the reverse, and says where the policy's jerk is below the residual-free
    jerk on every run. Without that row there is nothing to say."""
    from mixed_traffic.evaluation.results import ZERO_RESIDUAL, residual_line, scorecard_margins

    a = _generalization_json(tmp_path / "s0", jerk=0.09, gap=7.5, layered=0.09, cacc=False)
    b = _generalization_json(tmp_path / "s1", jerk=0.095, gap=7.5, layered=0.095, cacc=False)
    assert residual_line(scorecard_margins([a, b])) == ""  # not evaluated
    g = json.loads((a / "generalization.json").read_text())
    case = g["results"]["sine_fast"]
    case[ZERO_RESIDUAL] = dict(case["idm"], jerk=0.105)  # without the residual: more jerk than IDM-as-CAV, a miss
    (a / "generalization.json").write_text(json.dumps(g))
    m = scorecard_margins([a, b])
    assert m[0]["baselines"] == ["idm", ZERO_RESIDUAL] and m[0]["classical_clean"] == ["idm"]
    assert m[0]["classical"][ZERO_RESIDUAL][0] == pytest.approx(5.0)
    head = ("Beside its learned residual at zero (zero_residual: the deployed laws, envelope, drive-off cap and join "
            "alone, on the same episodes, no layer), the policy meets every bar on every run on ")
    assert residual_line(m) == head + (
        "1 cases where that controller misses one, and that controller on 0 where the policy misses one; both meet "
        "every bar on 0. The policy's jerk is below its residual-free jerk on every run on 1 of 1 cases.")
    # the other way round: without the residual every bar is met, with it (more jerk than IDM on a run) one is not
    synthetic = [{"case": "x", "clean": False, "jerk": [-1.0, 2.0], "classical": {ZERO_RESIDUAL: (-2.0, 0.0)},
                  "classical_clean": [ZERO_RESIDUAL], "baselines": ["idm", ZERO_RESIDUAL]},
                 {"case": "y", "clean": True, "jerk": [-3.0, -4.0], "classical": {ZERO_RESIDUAL: (-5.0, 0.0)},
                  "classical_clean": ["idm", ZERO_RESIDUAL], "baselines": ["idm", ZERO_RESIDUAL]}]
    assert residual_line(synthetic) == head + (
        "0 cases where that controller misses one, and that controller on 1 where the policy misses one (x); both "
        "meet every bar on 1. The policy's jerk is below its residual-free jerk on every run on 0 of 2 cases, above "
        "it on every run on 2 (x, y).")


def test_the_scorecard_counts_clean_cases_by_the_kind_of_head(benchmark_script):
    """The scorecard's count by the kinds of head the acceptance names: a case counts in every kind it is of, the
    policy's clean cases on every run beside each classical controller evaluated on every case, then the cases within
    the training speeds, those of no kind, and all. The kinds come from the case itself: its profile, a head faster
    than the training's top speed on an episode of its seed, its own ring length or spread of human parameters."""
    from mixed_traffic.evaluation.results import ZERO_RESIDUAL, kinds_table

    both = ["idm", ZERO_RESIDUAL]
    margins = [{"case": "stops_fast", "clean": False, "classical_clean": [], "baselines": both},
               {"case": "stops", "clean": True, "classical_clean": [ZERO_RESIDUAL], "baselines": both},
               {"case": "sine", "clean": False, "classical_clean": ["idm"], "baselines": both},
               {"case": "ring", "clean": True, "classical_clean": ["idm", ZERO_RESIDUAL], "baselines": ["idm"]}]
    kinds = {"stops_fast": ("stop-and-go", "above"), "stops": ("stop-and-go",), "sine": (), "ring": ("ring",)}
    assert kinds_table(margins, kinds, above="above").splitlines() == [
        "| kind of head | cases | the policy (every run) | idm |",  # zero_residual: not evaluated on every case
        "|---|---|---|---|",
        "| stop-and-go | 2 | 1 of 2 | 0 of 2 |",
        "| above | 1 | 0 of 1 | 0 of 1 |",
        "| ring | 1 | 1 of 1 | 1 of 1 |",
        "| within the training speeds | 3 | 2 of 3 | 2 of 3 |",
        "| other heads within the training speeds | 1 | 0 of 1 | 1 of 1 |",
        "| every case | 4 | 2 of 4 | 2 of 4 |"]
    with pytest.raises(KeyError, match="no kinds for the cases \\['ring'\\]"):
        kinds_table(margins, {k: v for k, v in kinds.items() if k != "ring"}, above="above")

    gen = benchmark_script("ring_generalization")
    every = gen.cases(200.0)

    def kinds_of(name, seed=2000):
        return gen.case_kinds(every[name], seed=seed, v_train=20.0)

    assert kinds_of("stop_and_go_10_ring_250") == ("stop-and-go", "another ring length")
    assert kinds_of("brake_from_25") == ("braking to a standstill", "above the training speeds")
    assert kinds_of("brake_22_to_8") == ("above the training speeds",)  # brakes, but not to a standstill
    assert kinds_of("stop_and_go_20") == ("stop-and-go",)  # at the training's top speed, not above it
    assert kinds_of("perturbation_10_humans_40pct", 12000) == ("other human parameters",)
    assert kinds_of("sine_10", 12000) == ()
    assert gen.case_kinds(every["sine_10"], seed=12000, v_train=12.0) == ("above the training speeds",)


def test_generalization_table_gives_each_case_its_range_over_the_seeds(tmp_path, capsys):
    from mixed_traffic.evaluation.results import generalization_table, main

    a = _generalization_json(tmp_path / "s0", jerk=0.11, gap=7.5, layered=0.15)
    b = _generalization_json(tmp_path / "s1", jerk=0.13, gap=6.25, v2v={"delay": 0.0, "loss": 0.0}, cacc=False,
                             layered=0.12)
    rows = generalization_table([a, b]).splitlines()
    assert rows[0] == "2 run(s); 4 episodes of 200 s a case, evaluation seed 2000."
    # gaps over both starts and seeds; jerk against IDM's from the standard start, then with the layer; cacc on one
    # seed only: the same classical controller on the same episodes, so its figure stands for both
    assert rows[2].endswith("| layer's share | cacc: jerk − IDM's |")
    assert rows[-1] == "| sine_fast | 0 | 6.25–36.0 | +10.0..+30.0 % | 0.100 | +0.0 | +20.0..+50.0 % | 1.0 % | +20.0 % |"
    # a case whose head never holds its speed: the RMSE is the whole episode's, and the table says so; where some
    # episodes hold, the figure is theirs alone
    for name, k, want in (("none", 0, "| 1.500 (no steady state: whole episode) |"),
                          ("some", 2, "| 0.200 (on the episodes with a steady state, 2 of 4) |")):
        runs = []
        for i in range(2):
            g = _generalization_json(tmp_path / f"{name}{i}", jerk=0.1, gap=7.0)
            data = json.loads((g / "generalization.json").read_text())
            std = data["results"]["sine_fast"]["policy_without_layer"]["standard (73.4 m)"]
            std.update(steady_rmse=1.5 if k == 0 else 1.1, episodes=4, steady_episodes=k,
                       steady_only_rmse=0.2 if k else None)
            (g / "generalization.json").write_text(json.dumps(data))
            runs.append(g)
        assert want in generalization_table(runs).splitlines()[-1]
    c = _generalization_json(tmp_path / "s2", jerk=0.1, gap=7.0, seed=5000)
    d = _generalization_json(tmp_path / "s3", jerk=0.1, gap=7.0, v2v={"delay": 0.5, "loss": 0.0})
    for other, field in ((c, "seed 5000"), (d, "v2v")):
        with pytest.raises(SystemExit):
            main(["--generalization", str(a), str(other)])
        assert f"--generalization: {field}" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--generalization", str(tmp_path)])  # no generalization.json there
    assert "holds no generalization.json" in capsys.readouterr().err


def test_report_from_a_trained_checkpoint(tmp_path):
    cfg = compose(["experiment=ring_lagrangian_ppo", "trainer.num_envs=8", "trainer.rollout_len=4",
                   "trainer.total_frames=96", "trainer.progress=false", "trainer.epochs=1",
                   "trainer.minibatch_size=16", "policy.apg.iterations=2", "policy.apg.num_envs=4",
                   "policy.apg.horizon=5"] + SHORT_EVAL)
    train(cfg, out_dir=tmp_path / "run")
    rep = evaluate_and_report(cfg, tmp_path / "eval", checkpoint=tmp_path / "run" / "final.pt")
    data = json.loads((tmp_path / "eval" / "report.json").read_text())
    assert data["overall"]["episodes"] == 4 and "acceptance" in data
    md = (tmp_path / "eval" / "report.md").read_text()
    assert "| random_steps |" in md and "steady RMSE" in md
    for name in ("random_steps.png", "emergency_brake.png", "training_curves.png"):
        assert (tmp_path / "eval" / name).stat().st_size > 1000, name
    # the safety layer of the trained config is part of the evaluated controller
    assert rep["transforms"][:4] == ["non_negative_reward", "safety_layer", "residual_idm", "intervention_cost"]
    # ... and the policy is evaluated without it too, from the standard and the close starts
    assert set(data["without_layer"]["random_steps"]) == {"standard (73.4 m)", "8 m", "15 m"}
    assert "Without the safety layer" in md and "λ over training" in md
    assert (tmp_path / "eval" / "random_steps_without_layer_close.png").stat().st_size > 1000
    assert data["overall"]["collisions"] == 0
    # the report states the layer as it was evaluated
    layer = cfg.transforms.safety_layer
    assert (data["safety_layer"]["s_min"], data["safety_layer"]["s_max"]) == (layer.s_min, layer.s_max)
    assert f"Safety layer as evaluated: s_min {layer.s_min:g} m" in md


def test_evaluate_needs_exactly_one_policy(tmp_path):
    cfg = compose(["experiment=ring_ppo"])
    with pytest.raises(ValueError, match=r"checkpoint: neither .* exactly one .*controller=idm\|ovm\|soft\|base"):
        evaluate_and_report(cfg, tmp_path)
    with pytest.raises(ValueError, match=r"checkpoint: both are set"):
        evaluate_and_report(cfg, tmp_path, checkpoint=str(tmp_path), controller="idm")


def test_mt_eval_cli_with_a_classical_controller(tmp_path):
    exe = Path(sys.executable).parent / "mt-eval"
    if not exe.exists():
        pytest.skip("mt-eval not installed")
    out = subprocess.run([str(exe), "experiment=ring_lagrangian_ppo", "transforms=reward", "controller=idm",
                          "eval.episodes=1", "eval.episode_seconds=10.0", "eval.profiles=[sine]",
                          f"hydra.run.dir={tmp_path}/run"], cwd=tmp_path, capture_output=True, text=True,
                         timeout=300, env=dict(os.environ))
    assert out.returncode == 0, out.stderr[-2000:]
    assert (tmp_path / "run" / "eval" / "report.md").is_file()
    assert "report:" in out.stdout


def test_evaluation_reports_the_speed_mode_95_override_rate(tmp_path):
    """With env.sumo_safety the report carries the share of steps SUMO's speed mode 95 changed."""
    from tensordict.nn import TensorDictModule

    from mixed_traffic.evaluation.report import write_report

    cfg = compose(["experiment=ring_ppo", "env.sumo_safety=true"] + SHORT_EVAL)
    always = TensorDictModule(lambda obs: torch.full((obs.shape[0], 1), 3.0), in_keys=["observation"],
                              out_keys=["action"])
    rep, traces = evaluate(cfg, always)
    assert rep["sumo_safety"] and rep["overall"]["collisions"] == 0
    assert rep["overall"]["override_rate"] > 0.5  # SUMO's safe speed caps "always +3" most of the time
    write_report(rep, tmp_path, traces)
    assert "speed-mode-95 override rate" in (tmp_path / "report.md").read_text()
    off, _ = evaluate(compose(["experiment=ring_ppo"] + SHORT_EVAL), always)
    assert not off["sumo_safety"] and off["overall"]["override_rate"] == 0.0


def test_report_names_the_profiles_whose_steady_rmse_is_the_whole_episodes():
    """report.md says which profiles' steady RMSE fell back to the whole episode's (no steady samples), and on
    how many episodes; a profile steady in every episode is not named."""
    from mixed_traffic.evaluation.report import markdown

    def prof(secs):
        return {"collisions": 0, "metrics": {}, "per_episode": {"steady_seconds": secs}}

    rep = {"episodes_per_profile": 2, "eval_seed": 1000,
           "profiles": {"random_steps": prof([12.0, 30.5]), "sine": prof([0.0, 0.0]), "stops": prof([0.0, 1.5])}}
    md = markdown(rep, "t")
    assert ("Steady RMSE where the head never held its speed long enough to settle: sine, every episode; stops, 1 of "
            "2 episodes.") in md
    assert "random_steps, " not in md
    rep["profiles"] = {"random_steps": prof([12.0, 30.5])}
    assert "never held" not in markdown(rep, "t")


def test_report_gives_the_steady_rmse_of_the_episodes_that_settle():
    """report.json's entry of a profile carries the steady RMSE over the episodes that settle
    (``steady_only_rmse``) beside ``metrics.speed_rmse_steady``, which averages in the others' whole-episode
    fallback; report.md's table gives that figure, marked, and marks a whole-episode one."""
    from mixed_traffic.evaluation.harness import METRICS, profile_entry
    from mixed_traffic.evaluation.report import markdown

    def entry(rmse, secs):
        m = {k: torch.zeros(len(rmse)) for k in METRICS}
        m["speed_rmse_steady"], m["steady_seconds"] = torch.tensor(rmse), torch.tensor(secs)
        return profile_entry(m)

    part, none, full = entry([1.9, 0.1, 0.3], [0.0, 4.0, 2.0]), entry([1.9, 1.7], [0.0, 0.0]), entry([0.1, 0.2], [3.0, 4.0])
    assert part["metrics"]["speed_rmse_steady"]["mean"] == pytest.approx(2.3 / 3)  # the mixed mean, as before
    assert part["steady_episodes"] == 2 and part["steady_only_rmse"] == pytest.approx(0.2)
    assert none["steady_episodes"] == 0 and none["steady_only_rmse"] is None
    assert full["steady_only_rmse"] == pytest.approx(full["metrics"]["speed_rmse_steady"]["mean"])
    md = markdown({"episodes_per_profile": 3, "eval_seed": 1000, "profiles": {"stops": part, "sine": none,
                                                                               "steps": full}}, "t")
    rows = {line.split(" | ")[0]: line for line in md.splitlines() if line.startswith("| ")}
    assert "| 0.200 (steady in 2 of 3 episodes, on those) |" in rows["| stops"]
    assert "| 1.800 (no steady state: whole episode) |" in rows["| sine"]
    assert "| 0.150 ± 0.050 |" in rows["| steps"]


def test_the_rmse_bar_judges_only_profiles_with_a_steady_state():
    """The acceptance's steady speed RMSE is taken over the profiles whose head held its speed long enough to settle
    in some episode: a stop-and-go head whose holds are shorter than ``settle_seconds`` (its steady RMSE is the
    whole episode's) is left out, as the sine is, and the same head with long holds counts."""
    from mixed_traffic.evaluation.harness import evaluate
    from mixed_traffic.evaluation.policies import classic_factory

    def acceptance(hold):
        times, speeds, t = [0.0], [10.0], 0.0
        for dt, v in ((hold, 10.0), (5.0, 0.0), (3.0, 0.0), (5.0, 10.0), (hold, 10.0)):
            t += dt
            times.append(t)
            speeds.append(v)
        cfg = compose(["experiment=ring_lagrangian_ppo", "transforms=reward", "eval.episodes=1",
                       f"eval.episode_seconds={t}", "eval.warmup_seconds=0.0", "eval.settle_seconds=6.0",
                       "eval.without_layer=false", "eval.profiles=[piecewise,random_steps]",
                       f"+eval.profile_kwargs.piecewise={{times:{times},speeds:{speeds}}}"])
        rep, _ = evaluate(cfg, policy_factory=classic_factory("idm"))
        secs = rep["profiles"]["piecewise"]["per_episode"]["steady_seconds"][0]
        return secs, rep["acceptance"]["steady_speed_rmse"], rep["profiles"]

    secs, rmse, prof = acceptance(hold=4.0)  # never 6 s at one speed
    assert secs == 0.0 and rmse == pytest.approx(prof["random_steps"]["metrics"]["speed_rmse_steady"]["mean"])
    secs, rmse, prof = acceptance(hold=12.0)
    assert secs > 0.0 and rmse == pytest.approx(max(p["metrics"]["speed_rmse_steady"]["mean"] for p in prof.values()))


def test_generalization_bars_name_what_each_case_misses_and_on_how_many_runs(tmp_path, capsys):
    """``--generalization --bars``: per case, the acceptance bars some run misses and on how many runs, a steady
    RMSE bar that does not apply (no steady state) not counted as a miss, and the count of clean cases."""
    from mixed_traffic.evaluation.results import case_bars, main

    a = _generalization_json(tmp_path / "s0", jerk=0.09, gap=7.5, layered=0.09)  # meets every bar
    b = _generalization_json(tmp_path / "s1", jerk=0.13, gap=4.0, layered=0.13)  # more jerk than IDM; a gap under 5 m
    x = json.loads((b / "generalization.json").read_text())["results"]["sine_fast"]
    assert case_bars(x) == {"collisions": True, "gaps": False, "jerk": False, "steady RMSE": True, "return": True,
                            "layer's share": True}
    x["policy_without_layer"]["standard (73.4 m)"].update(steady_rmse=1.9, episodes=4, steady_episodes=0)
    assert case_bars(x)["steady RMSE"] is None  # no steady state: not judged
    for v in x["policy_without_layer"].values():
        v["min_gap_after"] = 4.99995  # 5 m held by the envelope, in the env's float32: met
    assert case_bars(x)["gaps"] is True
    x["policy_without_layer"]["8 m"]["min_gap_after"] = 4.99
    assert case_bars(x)["gaps"] is False
    x["policy_without_layer"]["standard (73.4 m)"].update(steady_episodes=1, steady_only_rmse=0.25)
    assert case_bars(x)["steady RMSE"] is False and case_bars(x, rmse_bar=0.3)["steady RMSE"] is True
    x["policy"]["intervention_rate"] = 0.06
    assert case_bars(x)["layer's share"] is False
    out = main(["--generalization", str(a), str(b), "--bars"]).splitlines()
    assert out[2].endswith("| bars missed (of 2 runs) | classical controllers: bars missed |")
    assert out[4].endswith("| gaps 1 of 2; jerk 1 of 2 | idm: –; cacc: jerk |")
    assert out[-3].startswith("0 of 1 cases meet every bar on every run")
    # and what each controller meets from the standard start: the first run's policy, IDM-as-CAV (the reference of
    # the jerk and return bars), and cacc (evaluated in one run: the same on every run's episodes)
    assert out[-2] == ("From the standard start, without a layer, on the same episodes, the controllers meet every bar "
                       "on: the policy (the first run) 1, idm 1, cacc 0 of the 1 cases.")
    assert out[-1].startswith("Where the policy misses a bar (1 of the cases), a classical controller meets every bar")
    assert main(["--generalization", str(a), "--bars"]).splitlines()[4].endswith("| – | idm: –; cacc: jerk |")
    from mixed_traffic.evaluation.results import clean_cases
    assert clean_cases([a, b]) == (0, 1) and clean_cases([a]) == (1, 1)  # the count the table ends with
    assert "bars missed" not in main(["--generalization", str(a)])
    for bad, said in ((["--bars", str(a)], "--bars needs --generalization"),
                      (["--generalization", str(a), "--bars", "--rmse-bar", "0"], "--rmse-bar 0.0 is invalid")):
        with pytest.raises(SystemExit):
            main(bad)
        assert said in capsys.readouterr().err


def test_the_acceptance_judges_a_partly_steady_profile_on_its_steady_episodes():
    """A profile whose head settles in some episodes only: its steady RMSE for the acceptance is the mean over
    those episodes, not over figures of which some are whole-episode RMSEs; all steady: the report's mean; none:
    not judged."""
    from mixed_traffic.evaluation.harness import steady_rmse_mean

    def prof(rmse, secs):
        return {"metrics": {"speed_rmse_steady": {"mean": sum(rmse) / len(rmse)}},
                "per_episode": {"speed_rmse_steady": rmse, "steady_seconds": secs}}

    assert steady_rmse_mean(prof([0.1, 1.9, 0.3], [4.0, 0.0, 2.0])) == pytest.approx(0.2)
    assert steady_rmse_mean(prof([0.1, 0.3], [4.0, 2.0])) == pytest.approx(0.2)
    assert steady_rmse_mean(prof([1.9, 1.7], [0.0, 0.0])) is None


def test_a_classical_controller_beside_a_policy_runs_under_the_runs_reward_alone():
    """The reference of mt-main's acceptance and the scorecard's baselines share one rule: the run's reward
    transforms, in its order, the safety layer only where asked; never the residual, the constraint cost or the
    training-only shaping."""
    from mixed_traffic.config import compose
    from mixed_traffic.evaluation import classical_chain

    chain = list(compose(["experiment=ring_lagrangian_ppo_follow"]).transforms.chain)
    assert classical_chain(chain) == ["non_negative_reward"]
    assert classical_chain(chain, layer=True) == ["non_negative_reward", "safety_layer"]
    other = ["profile_reward", "safety_layer", "residual_nnmpc", "intervention_cost", "jerk_penalty"]
    assert classical_chain(other) == ["profile_reward"]
    assert classical_chain(["safety_layer", "residual_idm"]) == []
