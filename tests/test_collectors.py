"""`trainer.collector=`: TorchRL's single-process, multi-process and Ray collectors in the PPO loop."""

import pytest
import torch

from mixed_traffic.config import compose
from mixed_traffic.training import check_config, train
from mixed_traffic.training.builders import (
    DesyncStart,
    collector_rows,
    make_collector,
    make_transformed_env,
    worker_seed,
)
from mixed_traffic.training.on_policy import build_ppo
from mixed_traffic.validation import ConfigError

PPO = ["experiment=ring_ppo", "trainer.progress=false", "trainer.epochs=1", "trainer.minibatch_size=32"]


def test_collector_choice_is_validated():
    with pytest.raises(ConfigError, match=r"trainer.collector: unknown value 'pool'; allowed: \['single', 'multi_sync'"):
        check_config(compose(PPO + ["trainer.collector=pool"]))
    with pytest.raises(ConfigError, match="trainer.collector_workers: 0 is out of range; allowed: an integer >= 1"):
        check_config(compose(PPO + ["trainer.collector=multi_sync", "trainer.collector_workers=0"]))
    with pytest.raises(ConfigError, match="trainer.num_envs: 9 rows do not split over trainer.collector_workers=2"):
        check_config(compose(PPO + ["trainer.collector=multi_sync", "trainer.collector_workers=2",
                                    "trainer.num_envs=9"]))
    check_config(compose(PPO + ["trainer.collector=multi_async", "trainer.collector_workers=2", "trainer.num_envs=8"]))


def test_sumo_with_several_rows_points_to_the_multi_process_collector():
    with pytest.raises(ConfigError, match=r"trainer.num_envs: 4 with env.backend=sumo .* libsumo runs one per process; "
                                          r"allowed: .*trainer.collector=multi_sync trainer.collector_workers=4"):
        check_config(compose(PPO + ["env.backend=sumo", "trainer.num_envs=4"]))
    with pytest.raises(ConfigError, match="asks for 2 SUMO simulations in one process"):
        check_config(compose(PPO + ["env.backend=sumo", "trainer.num_envs=4", "trainer.collector=multi_sync",
                                    "trainer.collector_workers=2"]))
    cfg = compose(PPO + ["env.backend=sumo", "trainer.num_envs=4", "trainer.collector=multi_sync",
                         "trainer.collector_workers=4"])
    check_config(cfg)
    assert collector_rows(cfg) == 1


def test_worker_seeds_are_distinct_and_worker_zero_keeps_the_run_seed():
    seeds = {worker_seed(3, i, it) for i in range(8) for it in (0, 40)}
    assert len(seeds) == 16 and worker_seed(3, 0) == 3


def test_desync_start_moves_the_sumo_clock():
    """`desync_start` on SUMO: the first episode starts at a random point of the head profile's clock."""
    pytest.importorskip("libsumo")
    from torchrl.envs import TransformedEnv

    from mixed_traffic import make_env

    env = TransformedEnv(make_env("ring", backend="sumo", seed=0, episode_seconds=20.0), DesyncStart(seed=5))
    try:
        td = env.reset()
        start = env.base_env.step_count
        assert 0 < start < env.base_env.scenario.max_steps
        out = env.rollout(3, auto_reset=False, tensordict=td, break_when_any_done=False)
        assert torch.allclose(out["next", "traffic", "time"].flatten(),
                              torch.tensor([start + 1, start + 2, start + 3]) * env.base_env.dt)
        # the episode still ends at the time limit: the first one is shorter
        steps_left = env.base_env.scenario.max_steps - env.base_env.step_count
        out = env.rollout(steps_left, auto_reset=False, tensordict=out[..., -1]["next"].clone(),
                          break_when_any_done=False)
        assert bool(out["next", "truncated"][..., -1, :].all())
    finally:
        env.close()


def _policy_loc(actor, obs):
    with torch.no_grad():
        return actor(obs.clone())["loc"]


@pytest.mark.slow
def test_multi_sync_workers_collect_with_the_updated_weights(tmp_path):
    """Two worker processes: batches stack both, per-worker seeds and desync, the workers act with the new weights."""
    cfg = compose(PPO + ["trainer.collector=multi_sync", "trainer.collector_workers=2", "trainer.num_envs=4",
                         "trainer.rollout_len=3", "threads=1"])
    env = make_transformed_env(cfg, num_envs=collector_rows(cfg), seed=0)
    actor, *_ = build_ppo(cfg, env)
    collector, fpb, _ = make_collector(cfg, env, actor)
    try:
        data = iter(collector)
        b = next(data)
        assert fpb == 12 and b.shape == (2, 2, 3)  # [workers, rows per worker, rollout_len]
        # each worker seeded on its own and desynchronised: the rows' clocks all differ
        t = b["next", "traffic", "time"][..., 0, 0].flatten()
        assert len(set(t.tolist())) == 4, t
        old = _policy_loc(actor, b.select("observation"))
        assert torch.allclose(old, b["loc"], atol=1e-5)
        with torch.no_grad():
            actor.module[0][1].module.mean.bias.add_(0.5)  # an optimiser step, in effect
        collector.update_policy_weights_(actor)
        b = next(data)
        new = _policy_loc(actor, b.select("observation"))
        assert torch.allclose(new, b["loc"], atol=1e-5) and (b["loc"] - old.mean()).abs().min() > 0.3
    finally:
        collector.shutdown()


SUMO_2 = PPO + ["env.backend=sumo", "trainer.collector=multi_sync", "trainer.collector_workers=2", "trainer.num_envs=2",
                "trainer.rollout_len=20", "trainer.total_frames=120", "env.episode_seconds=3.0"]


def test_sumo_training_with_one_simulation_per_worker_process(tmp_path):
    """`env.backend=sumo trainer.collector=multi_sync`: two SUMO processes, one simulation each, train PPO."""
    pytest.importorskip("libsumo")
    s = train(compose(SUMO_2), out_dir=tmp_path)["summary"]
    assert s["completed"] and s["frames"] == 120 and s["iterations"] == 3
    # 3 s episodes in 20-step rollouts over 2 rows: episodes ended and were logged
    assert s["final"]["reward_per_step"] > 0 and (tmp_path / "final.pt").is_file()


@pytest.mark.slow
def test_sumo_multi_process_resume_says_what_it_cannot_restore(tmp_path, capsys):
    pytest.importorskip("libsumo")
    res = train(compose(SUMO_2 + ["trainer.max_iterations=2"]), out_dir=tmp_path)
    assert res["stopped_early"] and res["summary"]["frames"] == 80
    res = train(compose(SUMO_2 + ["trainer.max_iterations=2"]), resume=tmp_path)
    assert "a SUMO simulation's state (vehicles, SUMO's clock) cannot be saved" in capsys.readouterr().out
    s = res["summary"]
    assert s["completed"] and s["frames"] == 120 and s["iterations"] == 3


@pytest.mark.slow
def test_multi_async_batches_are_one_workers_rollout(tmp_path):
    """`multi_async`: each batch is one worker's rows; the run still reaches its frame budget."""
    cfg = compose(PPO + ["trainer.collector=multi_async", "trainer.collector_workers=2", "trainer.num_envs=4",
                         "trainer.rollout_len=10", "trainer.total_frames=80", "env.episode_seconds=1.0"])
    s = train(cfg, out_dir=tmp_path)["summary"]
    assert s["completed"] and s["frames"] == 80 and s["iterations"] == 4  # 2 rows x 10 steps a batch
