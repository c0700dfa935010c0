"""Past one machine: multirun sweeps on Ray and submitit, the Ray collector in the PPO loop.

Each test starts its own local cluster (Ray with 2 CPUs on this machine, submitit's local
executor) and skips with the reason when its extra is not installed.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SWEEP_TINY = ["experiment=ring_ppo", "trainer.total_frames=32", "trainer.num_envs=8", "trainer.rollout_len=4",
              "trainer.epochs=1", "trainer.minibatch_size=16", "trainer.progress=false", "env.episode_seconds=1.0"]


def _need(module: str, extra: str):
    pytest.importorskip(module, reason=f"the {extra} extra is not installed (pip install 'mixed-traffic[{extra}]')")


def _mt_train(tmp_path, *args, timeout=600):
    exe = Path(sys.executable).parent / "mt-train"
    if not exe.exists():
        pytest.skip("mt-train console script not installed")
    env = dict(os.environ, MT_SMALL_BUDGET="1", RAY_AUTH_MODE="disabled", RAY_USAGE_STATS_ENABLED="0",
               PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    out = subprocess.run([str(exe), *args], cwd=tmp_path, capture_output=True, text=True, timeout=timeout, env=env)
    assert out.returncode == 0, (out.stdout[-2000:], out.stderr[-4000:])
    return out


def _check_summary(sweep: Path, seeds: list[int]):
    summary = json.loads((sweep / "sweep_summary.json").read_text())
    assert len(summary) == 1, summary.keys()
    (g,) = summary.values()
    assert sorted(g["seeds"]) == seeds
    assert g["metrics"]["train.frames"]["mean"] >= 32 and g["metrics"]["train.reward_per_step"]["n"] == len(seeds)
    # every job ran in its own sweep subdirectory and finished
    assert len(list(sweep.glob("*/final.pt"))) == len(seeds)


@pytest.mark.slow  # starting a local Ray takes half a minute of the 2-core machine, as submitit below
def test_sweep_on_a_local_ray_cluster(tmp_path):
    """`mt-train -m hydra/launcher=ray seed=0,1`: two jobs as Ray tasks on a 2-CPU local Ray, one sweep summary."""
    _need("ray", "ray")
    _mt_train(tmp_path, "-m", "hydra/launcher=ray", "hydra.launcher.ray.init.num_cpus=2", "seed=0,1", *SWEEP_TINY,
              f"hydra.sweep.dir={tmp_path}/sweep")
    _check_summary(tmp_path / "sweep", [0, 1])


@pytest.mark.slow
def test_sweep_with_submitit_local(tmp_path):
    """`hydra/launcher=submitit_local`: the Slurm launcher's executor, run on this machine."""
    _need("hydra_plugins.hydra_submitit_launcher", "slurm")
    _mt_train(tmp_path, "-m", "hydra/launcher=submitit_local", "hydra.launcher.timeout_min=10", "seed=0,1",
              *SWEEP_TINY, f"hydra.sweep.dir={tmp_path}/sweep")
    _check_summary(tmp_path / "sweep", [0, 1])
    assert any((tmp_path / "sweep" / ".submitit").rglob("*_log.out"))


@pytest.mark.slow
def test_ppo_with_the_ray_collector(tmp_path):
    """`trainer.collector=ray`: two Ray actors collect; the batches have the single collector's shape."""
    _need("ray", "ray")
    from mixed_traffic.config import compose
    from mixed_traffic.training import train

    cfg = compose(SWEEP_TINY + ["trainer.collector=ray", "trainer.collector_workers=2", "trainer.total_frames=96"])
    s = train(cfg, out_dir=tmp_path)["summary"]
    assert s["completed"] and s["frames"] == 96 and s["iterations"] == 3
