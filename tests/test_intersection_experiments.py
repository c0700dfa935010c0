"""Intersection experiments: Hydra configs compose, every method runs end to end, NMPC meets its bar."""

from __future__ import annotations

import pytest
import torch

from mixed_traffic.config import compose
from mixed_traffic.intersection.train_lppo import METHODS, TrainConfig, from_hydra, load_actor, main, train

EXPERIMENTS = ["intersection_lppo", "intersection_lppo_bc", "intersection_lppo_bff", "intersection_residual_mpc",
               "intersection_nmpc"]


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_experiment_configs_compose(name):
    cfg = compose([f"experiment={name}"])
    assert cfg.name == name and cfg.env.scenario == "intersection"
    assert cfg.eval.episodes * 4 >= 300  # the acceptance test set: >= 300 episodes across behaviours
    if name != "intersection_nmpc":
        tc = from_hydra(cfg)
        assert tc.method == name.removeprefix("intersection_") and tc.method in METHODS
        assert tc.env_overrides["agent_split"] == "train"


def test_unknown_method_and_knob_are_rejected():
    with pytest.raises(ValueError, match="method"):
        TrainConfig(method="sac").validate()
    with pytest.raises(ValueError, match="bff_rho"):
        TrainConfig(method="lppo", knobs={"bff_rho": 0.1}).validate()


def test_hard_start_bank_and_anticipation_cost():
    from mixed_traffic.intersection.train_lppo import anticipation_cost, hard_start_bank

    assert hard_start_bank(TrainConfig(method="lppo", knobs={"hard_fraction": 0.0})) is None
    bank = hard_start_bank(TrainConfig(method="lppo", knobs={"hard_fraction": 0.5, "hard_start_x": (2.2, 2.6)}),
                           bank_size=64)
    x0 = bank.true[:, 0, 0]
    assert len(bank) == 64 and (x0[32:] <= 2.6 + 1e-6).all() and (x0[32:] >= 2.2 - 1e-6).all()
    assert set(bank.behaviour.tolist()) <= {0, 1, 2}  # training behaviours only (zig-zag stays held out)
    # driving at 2 m/s towards an agent about to cross is charged before the distance cost sees it
    going = torch.tensor([[-0.8, 2.0, 1.8, 0.5, -1.0, 0.0, 0.05, 0.05]])
    waiting = going.clone()
    waiting[0, 1] = 0.0
    assert anticipation_cost(going).item() > 0 and anticipation_cost(waiting).item() == 0


def test_lppo_tiny_run_and_reload(tmp_path):
    torch.set_num_threads(1)
    out = train(TrainConfig(method="lppo", total_frames=1024, num_envs=32, rollout_len=16, epochs=1,
                            minibatch_size=256, eval_per_behaviour=1, out_dir=str(tmp_path)))
    assert out["history"][-1]["frames"] == 1024
    assert out["eval"]["overall"]["episodes"] == 4
    actor, transform, cfg = load_actor(tmp_path / "final.pt")
    assert transform is None and cfg.method == "lppo"
    obs = torch.zeros(3, 8)
    from tensordict import TensorDict

    a = actor(TensorDict({"observation": obs}, [3]))["action"]
    assert a.shape == (3, 1) and (a.abs() <= 3.2).all()


@pytest.mark.slow
@pytest.mark.parametrize("method", ["lppo_bc", "lppo_bff", "residual_mpc"])
def test_methods_run_end_to_end(method, tmp_path):
    torch.set_num_threads(1)
    knobs = {"bc_episodes": 4, "bc_pretrain_steps": 20} if method == "lppo_bc" else {}
    out = train(TrainConfig(method=method, total_frames=256, num_envs=8, rollout_len=32, epochs=1,
                            minibatch_size=128, eval_per_behaviour=1, knobs=knobs, demo_cache=None))
    assert out["eval"]["overall"]["episodes"] == 4


@pytest.mark.slow
def test_hydra_entry_point_nmpc(tmp_path):
    out = main(["experiment=intersection_nmpc", "eval.episodes=1", f"out_dir={tmp_path}"])
    assert out["eval"]["overall"]["collision_rate"] == 0.0
    assert (tmp_path / "eval.json").exists()


@pytest.mark.slow
def test_nmpc_acceptance_on_the_full_test_set():
    """NMPC on 320 test episodes (80 per behaviour).

    The issue's bar is > 90% success with zero collisions; the measured result is 100% with
    zero collisions (see docs/intersection.md), so this test guards that level.
    """
    from mixed_traffic.intersection.evaluate import evaluate_policy
    from mixed_traffic.intersection.nmpc import make_nmpc_policy

    res = evaluate_policy(make_nmpc_policy(), n_per_behaviour=80)
    assert int(res.collision.sum()) == 0
    assert res.table["overall"]["success_rate"] > 0.99


def test_mt_train_dispatches_intersection_experiments(tmp_path):
    """`mt-train experiment=intersection_nmpc` runs the intersection loop and writes its evaluation."""
    import json

    from mixed_traffic.apps.train import main as mt_train

    cfg = compose(["experiment=intersection_nmpc", "eval.episodes=1", f"out_dir={tmp_path}"])
    success = mt_train(cfg)
    out = json.loads((tmp_path / "eval.json").read_text())
    assert set(out["eval"]) >= {"straight", "left", "right", "overall"}
    assert 0.0 <= success <= 1.0
