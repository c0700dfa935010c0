"""Training loops: a few iterations of each algorithm, resume equivalence, sweeps, logging."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from mixed_traffic.config import compose
from mixed_traffic.training import train

TINY = ["trainer.num_envs=8", "trainer.rollout_len=4", "trainer.progress=false", "env.episode_seconds=1.0"]
ALGOS = {
    "ppo": ["experiment=ring_ppo", "trainer.total_frames=128", "trainer.epochs=2", "trainer.minibatch_size=16"],
    "lagrangian_ppo": ["experiment=ring_lagrangian_ppo", "trainer.total_frames=128", "trainer.epochs=2",
                       "trainer.minibatch_size=16", "policy.apg.iterations=2", "policy.apg.num_envs=4",
                       "policy.apg.horizon=5"],
    "dqn": ["experiment=ring_dqn", "trainer.total_frames=256", "trainer.start_learning_after=64",
            "trainer.batch_size=16", "trainer.updates_per_batch=2"],
    "q_learning": ["experiment=ring_q_learning", "trainer.total_frames=256"],
}


def _cfg(algo, *extra):
    return compose(ALGOS[algo] + TINY + list(extra))


@pytest.mark.parametrize("algo", list(ALGOS))
def test_few_iterations_of_each_algorithm(algo, tmp_path):
    res = train(_cfg(algo), out_dir=tmp_path)
    s = res["summary"]
    assert s["completed"] and s["frames"] >= int(_cfg(algo).trainer.total_frames)
    assert (tmp_path / "final.pt").is_file() and (tmp_path / "summary.json").is_file()
    scalars = tmp_path / "logs" / _cfg(algo).name / "scalars"
    assert (scalars / "reward_per_step.csv").is_file()
    # 1 s (10-step) episodes in 4-step rollouts: episodes end within the run and their return is logged
    assert (scalars / "episode_return.csv").is_file()
    fin = s["final"]
    assert all(torch.isfinite(torch.tensor(v)) for v in fin.values())
    if algo in ("ppo", "lagrangian_ppo"):
        assert {"loss_objective", "loss_critic", "entropy", "clip_fraction"} <= set(fin)
    if algo == "lagrangian_ppo":
        assert "lambda" in fin and "safety_clip_rate" in fin
        # the multiplier moves with (mean cost - tolerance) every batch
        assert 0.0 <= fin["lambda_next"] <= 10.0 and fin["lambda_next"] != fin["lambda"]
    if algo == "dqn":
        assert fin["updates"] > 0 and fin["epsilon"] < 1.0


def test_lagrangian_multiplier_follows_dual_ascent(tmp_path):
    cfg = _cfg("lagrangian_ppo", "loss.lambda_init=2.0", "loss.lambda_lr=0.5", "loss.lambda_method=dual_ascent",
               "loss.violation_tolerance=0.1")
    res = train(cfg, out_dir=tmp_path)
    rows = [ln.split(",") for ln in (tmp_path / "logs" / cfg.name / "scalars" / "lambda.csv").read_text().split()]
    viol = [ln.split(",") for ln in
            (tmp_path / "logs" / cfg.name / "scalars" / "mean_violation.csv").read_text().split()]
    lam = [float(r[1]) for r in rows]
    c = [float(r[1]) for r in viol]
    assert lam[0] == pytest.approx(2.0)
    for i in range(1, len(lam)):
        assert lam[i] == pytest.approx(min(max(lam[i - 1] + 0.5 * (c[i - 1] - 0.1), 0.0), 10.0), abs=1e-5)
    assert res["summary"]["final"]["lambda_next"] == pytest.approx(
        min(max(lam[-1] + 0.5 * (c[-1] - 0.1), 0.0), 10.0), abs=1e-5)


def _final_tensors(path):
    state = torch.load(path, weights_only=False)
    for key in ("model", "qvalue", "table"):
        if key in state:
            return state[key]
    raise AssertionError(f"no model in {path}")


@pytest.mark.parametrize("algo", ["lagrangian_ppo", "dqn", "q_learning"])
def test_resume_reaches_the_same_result(algo, tmp_path):
    """Stop after 2 iterations (checkpoint), resume, finish: same weights as one uninterrupted run."""
    extra = ["trainer.checkpoint_every=1", "env.episode_seconds=1.0"]
    ref = train(_cfg(algo, *extra), out_dir=tmp_path / "ref")
    part = train(_cfg(algo, *extra, "trainer.max_iterations=2"), out_dir=tmp_path / "cut")
    assert part["stopped_early"] and not (tmp_path / "cut" / "final.pt").exists()
    ckpt = tmp_path / "cut" / "checkpoints" / "latest.pt"
    assert torch.load(ckpt, weights_only=False)["iteration"] == 2
    res = train(_cfg(algo, *extra), resume=tmp_path / "cut")
    assert res["out_dir"] == tmp_path / "cut" and res["summary"]["completed"]
    a, b = _final_tensors(tmp_path / "ref" / "final.pt"), _final_tensors(tmp_path / "cut" / "final.pt")
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k
    assert res["summary"]["frames"] == ref["summary"]["frames"]


def test_checkpoint_is_written_atomically_and_holds_the_state(tmp_path):
    cfg = _cfg("lagrangian_ppo", "trainer.checkpoint_every=1", "trainer.max_iterations=1")
    train(cfg, out_dir=tmp_path)
    files = sorted(p.name for p in (tmp_path / "checkpoints").iterdir())
    assert files == ["latest.pt"]  # no temporary left behind
    st = torch.load(tmp_path / "checkpoints" / "latest.pt", weights_only=False)
    assert {"model", "optim", "lagrange", "env", "collector", "rng", "frames", "iteration", "config"} <= set(st)
    assert st["lagrange"]["value"].item() >= 0.0


def test_resume_of_a_missing_path_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="no such checkpoint"):
        train(_cfg("ppo"), resume=tmp_path / "nope")


def test_wandb_logger_offline(tmp_path, monkeypatch):
    pytest.importorskip("wandb")
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    cfg = _cfg("ppo", "logger=wandb", "trainer.total_frames=32")
    train(cfg, out_dir=tmp_path)
    assert any((tmp_path / "logs").rglob("*.wandb"))


def _script(name):
    exe = Path(sys.executable).parent / name
    if not exe.exists():
        pytest.skip(f"{name} console script not installed")
    return str(exe)


SWEEP_TINY = ["experiment=ring_ppo", "trainer.total_frames=32", "trainer.num_envs=8", "trainer.rollout_len=4",
              "trainer.epochs=1", "trainer.minibatch_size=16", "trainer.progress=false", "env.episode_seconds=1.0"]


def _sweep(tmp_path, *extra):
    out = subprocess.run([_script("mt-train"), "-m", "seed=0,1", "loss=ppo,lagrangian_ppo", *SWEEP_TINY,
                          f"hydra.sweep.dir={tmp_path}/sweep", *extra], cwd=tmp_path, capture_output=True, text=True,
                         timeout=600, env=dict(os.environ, MT_SMALL_BUDGET="1"))
    assert out.returncode == 0, out.stderr[-3000:]
    summary = json.loads((tmp_path / "sweep" / "sweep_summary.json").read_text())
    assert len(summary) == 2  # loss=ppo and loss=lagrangian_ppo
    for key, g in summary.items():
        assert sorted(g["seeds"]) == [0, 1], key
        st = g["metrics"]["train.reward_per_step"]
        assert st["n"] == 2 and st["std"] >= 0.0
    md = (tmp_path / "sweep" / "sweep_summary.md").read_text()
    assert "loss=lagrangian_ppo" in md and "±" in md


def test_sweep_with_the_basic_launcher(tmp_path):
    _sweep(tmp_path)


@pytest.mark.slow
def test_sweep_with_the_joblib_launcher(tmp_path):
    pytest.importorskip("hydra_plugins.hydra_joblib_launcher")
    _sweep(tmp_path, "hydra/launcher=joblib_local")
