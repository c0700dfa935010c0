"""Bad input and faults: every mistake gets a clear error before work starts, and nothing written is lost.

Each section is one failure mode a user meets; every error must name the field (or the
file) and what is allowed, and leave what was already written untouched.
"""

import errno
import json
import math
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mixed_traffic import make_env
from mixed_traffic.config import compose
from mixed_traffic.training import check_config, train
from mixed_traffic.training import checkpoint as ck
from mixed_traffic.training.builders import env_kwargs
from mixed_traffic.validation import CONFIG_RULES, ConfigError, Real, check_argv, validate_config

TINY = ["experiment=ring_ppo", "trainer.total_frames=32", "trainer.num_envs=8", "trainer.rollout_len=4",
        "trainer.epochs=1", "trainer.minibatch_size=16", "trainer.progress=false", "env.episode_seconds=1.0"]
SHORT_EVAL = ["eval.episodes=1", "eval.episode_seconds=5.0", "eval.warmup_seconds=1.0", "eval.settle_seconds=1.0",
              "eval.profiles=[random_steps]"]


def _script(name):
    exe = Path(sys.executable).parent / name
    if not exe.exists():
        pytest.skip(f"{name} console script not installed")
    return str(exe)


def _cli(name, *args, cwd, env=None):
    return subprocess.run([_script(name), *args], cwd=cwd, capture_output=True, text=True, timeout=300,
                          env=dict(os.environ, **(env or {})))


def _snapshot(d: Path) -> dict:
    return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def mid_run(tmp_path_factory):
    """A run stopped after one of two iterations: checkpoints/latest.pt, no final.pt."""
    d = tmp_path_factory.mktemp("mid") / "run"
    train(compose([*TINY, "trainer.total_frames=64", "trainer.max_iterations=1"]), out_dir=d)
    return d


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("fin") / "run"
    train(compose(TINY), out_dir=d)
    return d


# ----------------------------------------------------------------------------- 1. experiment names
def test_1_misspelt_experiment_is_refused_before_anything_starts(tmp_path):
    with pytest.raises(ConfigError, match=r"experiment: unknown name 'ring_ppoo'; allowed: \[.*'ring_ppo'"):
        check_argv(["experiment=ring_ppoo"])
    with pytest.raises(ConfigError, match="'nope'"):
        check_argv(["-m", "experiment=ring_ppo,nope"])
    out = _cli("mt-train", "experiment=ring_ppoo", cwd=tmp_path)
    assert out.returncode == 2
    assert out.stderr.startswith("error: experiment: unknown name 'ring_ppoo'; allowed:") and "ring_ppo" in out.stderr
    assert "Traceback" not in out.stderr
    assert not (tmp_path / "outputs").exists()  # no run directory: nothing started


# ----------------------------------------------------------------------------- 2. values
@pytest.mark.parametrize("field, value, allowed", [
    ("v_init", float("nan"), "finite"), ("weight_v", float("nan"), "finite"),
    ("vehicle_length", float("inf"), "finite"), ("init_spacing", float("nan"), "or null"),
    ("n_vehicles", 2.5, "an integer"), ("dt", "0.1", "a number"), ("weight_s", -1.0, ">= 0"),
])
def test_2_scenario_values_name_the_field(field, value, allowed):
    with pytest.raises(ValueError, match=rf"^{field}: .*; allowed: .*{allowed}"):
        make_env("ring", **{field: value})


def test_2_nan_hdv_params_and_seed():
    with pytest.raises(ValueError, match=r"hdv_params\.v0: nan is not finite; allowed"):
        make_env("ring", hdv_params={"v0": float("nan")})
    with pytest.raises(ValueError, match=r"seed: -1 is invalid; allowed: an integer in \[0"):
        make_env("ring", seed=-1)


def test_2_nan_action_is_refused_and_the_state_stays_finite():
    env = make_env("ring", batch_size=3, seed=0)
    td = env.reset()
    before = (env.pos.clone(), env.vel.clone())
    td["action"] = torch.tensor([[0.5], [float("nan")], [0.0]])
    with pytest.raises(ValueError, match=r"action: non-finite values in row\(s\) \[1\]; allowed: finite"):
        env.step(td)
    assert torch.equal(env.pos, before[0]) and torch.equal(env.vel, before[1])
    td["action"] = torch.zeros(3, 1)
    out = env.step(td)
    assert torch.isfinite(out["next", "traffic", "speed"]).all()


@pytest.mark.parametrize("override, field, allowed", [
    ("env.weight_v=nan", "env.weight_v", ">= 0"),
    ("trainer.minibatch_size=0", "trainer.minibatch_size", ">= 1"),
    ("loss.gamma=1.5", "loss.gamma", r"\(0, 1\]"),
    ("trainer.epochs=0", "trainer.epochs", ">= 1"),
    ("trainer.max_minutes=-1", "trainer.max_minutes", "> 0 or null"),
    ("trainer.checkpoint_every=-1", "trainer.checkpoint_every", ">= 0"),
    ("seed=-1", "seed", r"\[0, "),
    ("++env.overrides.n_vehicles=2.5", "env.overrides.n_vehicles", "an integer"),
    ("++env.overrides.dt='0.1'", "env.overrides.dt", "a number"),
    ("++env.overrides.v_init=nan", "env.overrides.v_init", "finite"),
    ("transforms.safety_layer.beyond_s_max=back", "transforms.safety_layer.beyond_s_max", "push"),
    ("transforms.safety_layer.hold_seconds=-5", "transforms.safety_layer.hold_seconds", ">= 0"),
    ("transforms.safety_layer.recover_seconds=0", "transforms.safety_layer.recover_seconds", "> 0"),
])
def test_2_config_values_fail_before_any_work(tmp_path, override, field, allowed):
    cfg = compose([*TINY, override])
    with pytest.raises(ValueError, match=rf"^{field}: .*; allowed: .*{allowed}"):
        train(cfg, out_dir=tmp_path / "run")
    assert not (tmp_path / "run").exists()


# ----------------------------------------------------------------------------- 3. mt-dataset output
def test_3_dataset_refuses_an_unwritable_output_before_generating(tmp_path):
    from mixed_traffic.apps.dataset import run

    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    keep = tmp_path / "keep.npz"
    keep.write_bytes(b"precious")
    t0 = time.perf_counter()
    with pytest.raises(ConfigError, match=r"^output: cannot write in .*; allowed: a writable directory"):
        run({"output": str(blocker / "sub" / "d.npz"), "progress": False})  # default: 100 episodes
    with pytest.raises(ConfigError, match=r"^output: .* exists and overwrite=false; allowed"):
        run({"output": str(keep), "overwrite": False, "progress": False})
    with pytest.raises(ConfigError, match=r"^output: the dataset needs about .* MB free; allowed: .*enough free space"):
        run({"output": str(tmp_path / "huge.npz"), "episodes": 10**9, "progress": False})
    assert time.perf_counter() - t0 < 5.0
    assert keep.read_bytes() == b"precious" and sorted(p.name for p in tmp_path.iterdir()) == ["file", "keep.npz"]


def test_3_dataset_cli_exit_code_and_time(tmp_path):
    (tmp_path / "file").write_text("x")
    out = _cli("mt-dataset", f"output={tmp_path}/file/d.npz", cwd=tmp_path)
    assert out.returncode == 2 and out.stderr.startswith("error: output: cannot write in"), out.stderr
    # refused before generating: no progress bar, no QP solve (the wall time is in docs/benchmarks.md)
    assert "%|" not in out.stderr and "%|" not in out.stdout


# ----------------------------------------------------------------------------- 4. mt-eval
def test_4_eval_names_missing_empty_truncated_and_foreign_checkpoints(tmp_path, finished_run):
    from mixed_traffic.evaluation.policies import checkpoint_config

    with pytest.raises(FileNotFoundError, match=r"^checkpoint: no such checkpoint .*nope.pt.*; allowed: a checkpoint"):
        checkpoint_config(tmp_path / "nope.pt")
    (tmp_path / "empty.pt").write_bytes(b"")
    with pytest.raises(ConfigError, match=r"^checkpoint: .*empty.pt' is empty \(0 bytes\); allowed: a checkpoint"):
        checkpoint_config(tmp_path / "empty.pt")
    data = (finished_run / "final.pt").read_bytes()
    (tmp_path / "cut.pt").write_bytes(data[: len(data) // 2])
    with pytest.raises(ConfigError, match=r"^checkpoint: .*cut.pt' cannot be read as a checkpoint"):
        checkpoint_config(tmp_path / "cut.pt")
    torch.save({"weights": torch.zeros(3)}, tmp_path / "foreign.pt")
    with pytest.raises(ConfigError, match=r"^checkpoint: .*foreign.pt' is not a mixed-traffic checkpoint"):
        checkpoint_config(tmp_path / "foreign.pt")
    assert (finished_run / "final.pt").read_bytes() == data


def test_4_eval_says_when_it_evaluates_a_mid_run_checkpoint(mid_run, capsys):
    from mixed_traffic.evaluation.policies import checkpoint_config

    checkpoint_config(mid_run)
    err = capsys.readouterr().err
    assert "mid-run checkpoint (iteration 1, 32 of 64 frames)" in err and "no final.pt" in err


def test_4_eval_refuses_env_overrides_of_a_checkpoint(finished_run):
    from mixed_traffic.apps.evaluate import check_eval_overrides

    cfg = compose([f"checkpoint={finished_run}", "env.weight_v=3.0"])
    with pytest.raises(ConfigError, match=r"^env.weight_v: a checkpoint is evaluated on .*; allowed: env.backend"):
        check_eval_overrides(cfg, ["env.weight_v=3.0"])
    check_eval_overrides(cfg, ["env.backend=torch", "eval.episodes=2"])  # allowed
    check_eval_overrides(compose(["controller=idm", "env.weight_v=3.0"]), ["env.weight_v=3.0"])  # no checkpoint


def test_4_eval_deploys_a_checkpoint_with_its_transforms_overridden_not_silently_dropped(finished_run, tmp_path):
    """``mt-eval checkpoint=RUN transforms.KEY=VALUE``: a checkpoint deploys with its own transforms, so such an
    override used to be dropped without a word; it now changes them for this evaluation, and the report names it.
    A key the run's config does not have, or a transforms group, is refused naming it."""
    from mixed_traffic.apps.evaluate import run_eval

    base = [f"checkpoint={finished_run}", f"out_dir={tmp_path}/o", *SHORT_EVAL]
    over = ["transforms.safety_layer.s_min=6.0"]
    rep = run_eval(compose(base + over), base + over)
    assert rep["deploy_overrides"] == {"transforms.safety_layer.s_min": 6.0}
    assert rep["policy"].endswith("deployed with transforms.safety_layer.s_min=6.0")
    if "safety_layer" in rep:
        assert rep["safety_layer"]["s_min"] == 6.0
    plain = run_eval(compose(base), base)
    assert "deploy_overrides" not in plain and not plain["policy"].endswith("6.0")
    with pytest.raises(ConfigError, match=r"^transforms.safety_layer.s_mni: not a setting of the run's config"):
        run_eval(compose(base), base + ["transforms.safety_layer.s_mni=6.0"])
    with pytest.raises(ConfigError, match=r"^transforms=reward: not a deployed setting of the run's transforms"):
        run_eval(compose(base), base + ["transforms=reward"])
    from mixed_traffic.evaluation import evaluate_and_report
    with pytest.raises(ConfigError, match=r"^transforms: deploy-time overrides apply to a checkpoint"):
        evaluate_and_report(compose(["experiment=ring_ppo", "controller=idm"]), tmp_path / "c",
                            deploy_overrides=[("transforms.safety_layer.s_min", 6.0)])


def test_4_eval_cli_missing_checkpoint_exit_2_and_debug_traceback(tmp_path):
    out = _cli("mt-eval", f"checkpoint={tmp_path}/nope.pt", f"hydra.run.dir={tmp_path}/o", cwd=tmp_path)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert out.stderr.startswith("error: checkpoint: no such checkpoint file or run directory"), out.stderr
    out = _cli("mt-eval", f"checkpoint={tmp_path}/nope.pt", f"hydra.run.dir={tmp_path}/o", cwd=tmp_path,
               env={"MT_DEBUG": "1"})
    assert out.returncode != 0 and "Traceback" in out.stderr


# ----------------------------------------------------------------------------- 5. resume compatibility
def test_5_resume_with_a_conflicting_config_is_refused_with_the_keys(tmp_path):
    run = tmp_path / "run"
    train(compose([*TINY, "trainer.total_frames=96", "trainer.max_iterations=1"]), out_dir=run)
    before = _snapshot(run)
    with pytest.raises(ConfigError, match=r"^resume: the command line differs .* trainer\.total_frames \(96 -> 128\)"
                                          r".*; allowed: .*resume_override=true"):
        train(compose([*TINY, "trainer.total_frames=128"]), resume=run)
    for bad in ("trainer.num_envs=4", "experiment=ring_lagrangian_ppo", "env.weight_v=2.0"):
        with pytest.raises(ConfigError, match=r"^resume: .* which its saved state depends on; allowed"):
            train(compose([*TINY, "trainer.total_frames=96", bad, "resume_override=true"]), resume=run)
    assert _snapshot(run) == before  # nothing written by a refused resume
    res = train(compose([*TINY, "trainer.total_frames=128", "resume_override=true"]), resume=run)
    assert res["summary"]["completed"] and res["summary"]["frames"] == 128
    assert (run / "config.yaml").read_bytes() == before["config.yaml"]  # the run's own config is kept
    assert "total_frames: 128" in (run / "config.resumed_1.yaml").read_text()


def test_5_a_finished_run_cannot_be_resumed(finished_run):
    with pytest.raises(FileNotFoundError, match=r"^resume: the run in .* has finished \(final.pt\).*; allowed:"):
        train(compose(TINY), resume=finished_run)


# ----------------------------------------------------------------------------- 6. files
def test_6_orphaned_temporaries_are_removed_and_a_full_disk_keeps_the_previous_file(tmp_path, monkeypatch):
    path = tmp_path / "checkpoints" / "latest.pt"
    ck.atomic_save({"config": {}, "v": 1}, path)
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    orphan = path.with_name(f".latest.pt.tmp{int(dead.stdout)}")
    orphan.write_bytes(b"x" * 100)
    ck.atomic_save({"config": {}, "v": 2}, path)
    assert not orphan.exists() and torch.load(path, weights_only=False)["v"] == 2
    good = path.read_bytes()

    def full_disk(obj, f):
        Path(f).write_bytes(b"partial")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(ck.torch, "save", full_disk)
    with pytest.raises(OSError, match="no space left on the device while writing it") as e:
        ck.atomic_save({"config": {}, "v": 3}, path)
    assert e.value.filename == str(path)
    assert path.read_bytes() == good and sorted(p.name for p in path.parent.iterdir()) == ["latest.pt"]


def test_6_a_new_run_never_writes_into_an_existing_run(finished_run):
    before = _snapshot(finished_run)
    with pytest.raises(ConfigError, match=r"^out_dir: .* already holds a run \(final.pt.*; allowed: a new directory, or resume="):
        train(compose(TINY), out_dir=finished_run)
    assert _snapshot(finished_run) == before


def test_6_resume_after_a_kill_does_not_duplicate_csv_rows(tmp_path):
    run = tmp_path / "run"
    base = [*TINY, "trainer.total_frames=160", "trainer.checkpoint_every=1"]
    train(compose([*base, "trainer.max_iterations=2"]), out_dir=run)
    saved = (run / "checkpoints" / "latest.pt").read_bytes()  # iteration 2
    train(compose([*base, "trainer.max_iterations=1"]), resume=run)  # logs iteration 3 ...
    (run / "checkpoints" / "latest.pt").write_bytes(saved)  # ... then "killed" before its checkpoint survived
    train(compose(base), resume=run)
    for f in (run / "logs").glob("*/scalars/*.csv"):
        steps = [float(ln.split(",")[0]) for ln in f.read_text().splitlines() if ln]
        assert steps == sorted(set(steps)), f.name
    steps = [float(ln.split(",")[0]) for ln in (next((run / "logs").glob("*/scalars/reward_per_step.csv")))
             .read_text().splitlines()]
    assert steps == [32.0, 64.0, 96.0, 128.0, 160.0]


# ----------------------------------------------------------------------------- 7. wandb
def test_7_wandb_keeps_the_run_config_and_resumes_the_same_run(tmp_path, monkeypatch):
    pytest.importorskip("wandb")
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    run = tmp_path / "run"
    base = [*TINY, "logger=wandb", "trainer.total_frames=64"]
    train(compose([*base, "trainer.max_iterations=1"]), out_dir=run)
    run_id = (run / "logs" / "wandb_run_id").read_text()
    train(compose(base), resume=run)
    assert (run / "logs" / "wandb_run_id").read_text() == run_id
    # offline-run-<YYYYmmdd_HHMMSS>-<id>, with "-<n>" added when a resume starts in the same second
    names = [p.name for p in (run / "logs" / "wandb").glob("offline-run-*")]
    dirs = {m.group(1) for m in (re.fullmatch(r"offline-run-\d{8}_\d{6}-([0-9a-z]+)(?:-\d+)?", n) for n in names) if m}
    assert len(names) == 2 and dirs == {run_id}  # one wandb run, continued
    from mixed_traffic.training.run import make_logger

    cfg = compose(base)
    cfg.out_dir = str(run)
    logger = make_logger(cfg, run)  # what a third resume would log to
    try:
        assert logger.experiment.id == run_id
        assert dict(logger.experiment.config["env"])["scenario"] == "ring"  # the run's env, not package metadata
        assert dict(logger.experiment.config["trainer"])["total_frames"] == 64
    finally:
        logger.experiment.finish()


# ----------------------------------------------------------------------------- 8. sweeps
def test_8_a_failing_job_still_gets_a_sweep_summary(tmp_path, monkeypatch, capsys):
    from mixed_traffic.apps.train import main

    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as e:
        main(["-m", *TINY, "trainer.epochs=1,0", f"hydra.sweep.dir={tmp_path}/sweep"])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "error: trainer.epochs: 0 is out of range; allowed: an integer >= 1" in err and "Traceback" not in err
    summary = json.loads((tmp_path / "sweep" / "sweep_summary.json").read_text())
    assert len(summary) == 1 and "trainer.epochs=1" in next(iter(summary))
    failed = json.loads((tmp_path / "sweep" / "sweep_failed.json").read_text())
    assert len(failed) == 1 and "trainer.epochs=0" in failed[0]["overrides"]
    assert "trainer.epochs: 0 is out of range; allowed: an integer >= 1" in failed[0]["error"]
    assert "Failed jobs (1" in (tmp_path / "sweep" / "sweep_summary.md").read_text()


# ----------------------------------------------------------------------------- 9. DeeP-LCC
@pytest.fixture(scope="module")
def hankel():
    from mixed_traffic.controllers.deeplcc.platoon import PlatoonConfig
    from mixed_traffic.controllers.deeplcc.precollect import precollect

    [h] = precollect(PlatoonConfig(), T=400, t_ini=5, n=10, generator=torch.Generator().manual_seed(0))
    return h


def test_9_qp_non_finite_input_gives_the_counted_safe_action(hankel):
    from mixed_traffic.controllers.deeplcc.qp import DeepLCCSolver, QPParams

    s = DeepLCCSolver(hankel, QPParams.preset("dataset"))
    for bad in (np.nan, np.inf):
        u = np.zeros(10)
        u[3] = bad
        r = s.solve(u, np.zeros(50), np.zeros(5))
        assert r.status == "invalid_input" and np.array_equal(r.u, [0.0, 0.0])
    assert s.stats.invalid_inputs == 2 and s.stats.safe_actions == 2
    assert s.solve(np.zeros(10), np.zeros(50), np.zeros(5)).status == "optimal"  # the solver still works


def test_9_unexcited_hankel_data_is_refused(hankel):
    from mixed_traffic.controllers.deeplcc.hankel import build_hankel
    from mixed_traffic.controllers.deeplcc.qp import DeepLCCSolver, QPParams

    flat = build_hankel(np.zeros((2, 400)), np.zeros(400), np.ones((10, 400)), 5, 10)
    with pytest.raises(ValueError, match=r"^hankel data: \[Up; Ep; Uf; Ef\] has rank 0 < 45 rows.*; allowed:"):
        DeepLCCSolver(flat, QPParams.preset("dataset"))


def test_9_infeasible_state_is_flagged_and_counted(hankel):
    from mixed_traffic.controllers.deeplcc.qp import DeepLCCSolver, QPParams

    s = DeepLCCSolver(hankel, QPParams.preset("dataset"))
    y = np.zeros(50)
    y[-2:] = -18.0  # both CAVs 2 m behind their leaders (spacing_min 5 m)
    r = s.solve(np.zeros(10), y, np.zeros(5))
    assert r.infeasible_state and s.stats.infeasible_states == 1
    assert not s.solve(np.zeros(10), np.zeros(50), np.zeros(5)).infeasible_state


@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory):
    from mixed_traffic.controllers.deeplcc.dataset import DatasetConfig, generate_dataset, write_dataset

    cfg = DatasetConfig(episodes=1, episode_seconds=1.5, T=300, t_ini=5, n=10, workers=1, mix={"random1": 1.0})
    path = tmp_path_factory.mktemp("ds") / "d.npz"
    write_dataset(path, generate_dataset(cfg, progress=False))
    return path


def test_9_corrupt_and_inconsistent_datasets_name_the_file_and_key(small_dataset, tmp_path):
    from mixed_traffic.controllers.deeplcc.dataset import load_dataset, validate_dataset

    raw = small_dataset.read_bytes()
    (tmp_path / "cut.npz").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(ValueError, match=r"^dataset: '.*cut.npz' cannot be read .*; allowed: a complete .npz"):
        load_dataset(tmp_path / "cut.npz")
    d = dict(np.load(small_dataset))
    bad = dict(d, u_opt=np.full_like(d["u_opt"], 50.0))
    with pytest.raises(ValueError, match=r"'u_opt' holds values in \[50, 50\]; expected .* \[-5, 2\]"):
        validate_dataset(bad)
    md = d["metadata"].copy()
    md[5] = 1.0
    with pytest.raises(ValueError, match=r"'metadata' holds lambda_y=1.0 but key 'qp' says 1000"):
        validate_dataset(dict(d, metadata=md))
    np.savez(tmp_path / "bad.npz", **dict(d, metadata=md))
    with pytest.raises(ValueError, match=r"bad.npz: dataset: key 'metadata'"):
        load_dataset(tmp_path / "bad.npz")
    assert small_dataset.read_bytes() == raw


# ----------------------------------------------------------------------------- 10. one error style
def test_10_hydra_errors_exit_2_and_overrides_need_no_plus(tmp_path):
    assert check_argv(["env.overrides.v_init=3.0", "+env.overrides.x=1"]) == [
        "++env.overrides.v_init=3.0", "+env.overrides.x=1"]
    cfg = compose([*TINY, *check_argv(["env.overrides.v_init=3.0"])])
    assert cfg.env.overrides.v_init == 3.0
    # a profile's argument the experiment does not set (random_mix's weights) needs no "+" either; a misspelt one
    # fails when the env is built, naming it
    cfg = compose(["experiment=ring_lagrangian_ppo_mix", *check_argv(["env.profile_kwargs.weights=[1.0,3.0]"])])
    assert make_env("ring", **env_kwargs(cfg.env)).profile.weights == [1.0, 3.0]
    cfg = compose(["experiment=ring_lagrangian_ppo_mix", *check_argv(["env.profile_kwargs.weigths=[1.0,3.0]"])])
    with pytest.raises(ValueError, match=r"unknown arguments \['weigths'\]"):
        make_env("ring", **env_kwargs(cfg.env))
    out = _cli("mt-train", "loss.clip_epsilom=0.2", cwd=tmp_path)
    assert out.returncode == 2 and "clip_epsilom" in out.stderr


def test_10_sumo_args_replace_the_defaults():
    pytest.importorskip("libsumo")
    env = make_env("ring", backend="sumo", seed=0, sumo_args=["--seed", "3"])
    try:
        cmd = env._sumo_cmd()
        assert cmd.count("--seed") == 1 and cmd[cmd.index("--seed") + 1] == "3"
        assert env.rollout(3).shape == (1, 3)
    finally:
        env.close()


# ----------------------------------------------------------------------------- property
SCENARIO_NUMBERS = ["ring_length", "vehicle_length", "dt", "episode_seconds", "v_init", "weight_v", "weight_s",
                    "weight_u", "s_star", "spacing_clip", "v_eq_window", "v_dev_max", "v_star", "s_min", "s_max",
                    "hdv_param_noise", "n_vehicles"]
NON_NUMBERS = st.sampled_from([float("nan"), float("inf"), float("-inf"), "x", "1.0", True, [1.0], {"a": 1}])


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(field=st.sampled_from(SCENARIO_NUMBERS + ["cav_accel_bounds", "head_accel_bounds", "cav_indices",
                                                 "init_spacing", "hdv_params", "profile_kwargs", "road",
                                                 "hdv_model", "integration", "observation", "profile"]),
       value=NON_NUMBERS)
def test_property_make_env_refuses_invalid_values_with_a_value_error_naming_the_field(field, value):
    if field in ("road", "hdv_model", "integration", "observation", "profile") and value in ("x", "1.0"):
        value = 3.0  # strings are these fields' type: a number is the wrong one
    if field in ("hdv_params", "profile_kwargs"):
        value = {"v0" if field == "hdv_params" else "v_low": value}
    try:
        make_env("ring", **{field: value})
    except ValueError as e:
        assert str(e).startswith(field) and "; allowed: " in str(e), str(e)
    else:
        pytest.fail(f"make_env accepted {field}={value!r}")


def _invalid_for(rule):
    out = [float("nan"), float("inf")]
    if isinstance(rule, Real):
        if math.isfinite(rule.lo):
            out.append(rule.lo - 1 if not rule.integer else int(rule.lo) - 1)
        if math.isfinite(rule.hi):
            out.append(rule.hi + 1 if not rule.integer else int(min(rule.hi, 2**62)) + 1 if rule.hi < 2**62 else None)
        if rule.integer:
            out.append(2.5)
    return [v for v in out if v is not None]


PAIRS = [(path, v) for path, rule in CONFIG_RULES.items() if isinstance(rule, Real) for v in _invalid_for(rule)]


@pytest.fixture(scope="module")
def base_configs():
    return {e: compose([f"experiment={e}"]) for e in ("ring_ppo", "ring_dqn", "ring_q_learning")}


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(pair=st.sampled_from(PAIRS), experiment=st.sampled_from(["ring_ppo", "ring_dqn", "ring_q_learning"]))
def test_property_config_refuses_invalid_values_naming_the_field(base_configs, pair, experiment):
    from omegaconf import OmegaConf, open_dict
    from omegaconf.errors import ValidationError

    path, value = pair
    cfg = base_configs[experiment].copy()
    if OmegaConf.select(cfg, path, default="<absent>") == "<absent>":
        return  # a key of another loss / trainer
    try:
        with open_dict(cfg):
            OmegaConf.update(cfg, path, value, merge=False)
    except ValidationError:  # the typed schema refuses it already (Hydra: exit 2 at start-up)
        return
    with pytest.raises(ValueError) as e:
        check_config(cfg)
    assert str(e.value).startswith(path + ":") and "; allowed: " in str(e.value)


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(pair=st.sampled_from(PAIRS))
def test_property_apps_exit_2_on_invalid_values(tmp_path, capsys, pair):
    from mixed_traffic.apps.train import main

    path, value = pair
    text = {math.inf: "inf"}.get(value, "nan" if value != value else repr(value))
    with pytest.raises(SystemExit) as e:
        main([*TINY, f"{path}={text}", f"hydra.run.dir={tmp_path}/o"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and path.split(".")[-1] in err, err  # ours or Hydra's (schema type) message
    assert "Traceback" not in err
    assert not (tmp_path / "o" / "logs").exists()  # nothing started


def test_validate_config_accepts_every_shipped_experiment():
    from mixed_traffic.validation import known_experiments

    for e in known_experiments():
        validate_config(compose([f"experiment={e}"]))


def test_a_checkpoint_saved_before_a_schema_field_existed_still_builds():
    """Old run configs lack fields added later; they load with the field's default."""
    from omegaconf import OmegaConf

    from mixed_traffic.config import compose
    from mixed_traffic.evaluation.policies import with_schema_defaults
    from mixed_traffic.training.builders import make_transformed_env

    stored = OmegaConf.to_container(compose(["experiment=ring_lagrangian_ppo"]), resolve=False)
    del stored["transforms"]["intervention_cost"]["direction"]  # a field added after the run was saved
    stored["transforms"]["safety_layer"]["s_min"] = 6.0  # stored values are kept
    with pytest.raises(Exception, match="direction"):
        make_transformed_env(OmegaConf.create(stored), num_envs=1, seed=0)
    cfg = with_schema_defaults(stored)
    assert cfg.transforms.intervention_cost.direction == "both" and cfg.transforms.safety_layer.s_min == 6.0
    env = make_transformed_env(cfg, num_envs=1, seed=0)
    assert env.rollout(3)["next", "cost"].shape == (1, 3, 1)
