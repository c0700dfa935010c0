"""Every experiment builds what its config names; the intersection methods train through the shared loop."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import RewardSum, StepCounter
from torchrl.objectives import ClipPPOLoss, DQNLoss

from losses import LagrangianPPOLoss
from mixed_traffic.config import compose
from mixed_traffic.training import check_config, train
from mixed_traffic.training.builders import EpisodeRewardSum, make_transformed_env
from mixed_traffic.validation import ConfigError

EXPERIMENTS = sorted(p.stem for p in (Path(__file__).parent.parent / "hydra_configs" / "experiment").glob("*.yaml"))


def _transform_types() -> dict:
    from mixed_traffic.intersection.residual import ResidualNMPC
    from transforms import (
        BarrierForce,
        ConflictCost,
        ControllerBlend,
        CounterfactualReward,
        InterventionCost,
        JerkPenalty,
        NonNegativeReward,
        OnboardLeaderAccel,
        ProfileNormalisedReward,
        ResidualAction,
        SafetyLayer,
        SetPointAction,
        StateDiscretizer,
    )

    return {"non_negative_reward": NonNegativeReward, "safety_layer": SafetyLayer, "residual_damper": ResidualAction,
            "intervention_cost": InterventionCost, "residual_idm": ResidualAction, "residual_nnmpc": ResidualAction,
            "jerk_penalty": JerkPenalty,
            "state_discretizer": StateDiscretizer, "barrier_force": BarrierForce, "residual_nmpc": ResidualNMPC,
            "conflict_cost": ConflictCost, "profile_reward": ProfileNormalisedReward,
            "counterfactual_reward": CounterfactualReward, "set_point": SetPointAction,
            "blend": ControllerBlend, "onboard_accel": OnboardLeaderAccel}


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_experiment_builds_the_transforms_loss_and_policy_it_names(name, tmp_path):
    cfg = compose([f"experiment={name}", f"loss.bc.demos={tmp_path / 'demos.pt'}"]
                  if "lppo_bc" in name else [f"experiment={name}"])
    assert cfg.name == name
    if "residual_nnmpc" in cfg.transforms.chain:  # the frozen NNMPC is an artefact: a tiny one stands in
        from mixed_traffic.controllers.deeplcc.nnmpc import NNMPC

        NNMPC().save(tmp_path / "nnmpc.pt")
        cfg.transforms.residual_nnmpc.checkpoint = str(tmp_path / "nnmpc.pt")
        cfg.transforms.counterfactual_reward.checkpoint = str(tmp_path / "nnmpc.pt")
    if cfg.get("controller"):  # a classical controller: evaluated only, nothing to train
        assert cfg.controller == "nmpc" and cfg.transforms.chain == []
        return
    check_config(cfg)
    env = make_transformed_env(cfg, num_envs=2, seed=0)
    built = [type(t) for t in env.transform][:-2]
    assert built == [_transform_types()[n] for n in cfg.transforms.chain]
    assert [type(t) for t in env.transform][-2:] == [EpisodeRewardSum, StepCounter]
    assert isinstance(env.transform[-2], RewardSum)  # TorchRL's, with an unbounded episode_reward spec
    if cfg.trainer.kind == "on_policy":
        from mixed_traffic.training.on_policy import AuxiliaryLosses, build_ppo

        actor, critic, loss, gaes, penalty = build_ppo(cfg, env)
        if cfg.loss.name == "ppo":
            assert type(loss) is ClipPPOLoss and penalty is None
        else:
            assert type(loss) is LagrangianPPOLoss
            assert (loss.cost_critic_network is not None) == (cfg.loss.critics == 2) == (len(gaes) == 2)
            assert (penalty is not None) == (cfg.loss.critics == 1)
        extra = [tuple(k.split(".")) for k in cfg.policy.extra_in_keys]
        assert actor.module[0].module[0].in_keys == ["observation", *extra]
        feats = [m for m in actor.modules() if type(m).__name__ == "ObservationFeatures"]
        assert len(feats) == (cfg.policy.features == "intersection")
        assert sum(p.numel() for p in actor.parameters()) > 0
        if cfg.loss.bc.coeff > 0:  # the BC term is built from the cached demonstrations
            torch.save(TensorDict({"observation": torch.zeros(4, 8), "expert_action": torch.zeros(4, 1)}, [4]),
                       cfg.loss.bc.demos)
        aux = AuxiliaryLosses(cfg, actor, pretrain=False)
        assert (aux.bc is not None) == (cfg.loss.bc.coeff > 0)
        assert (aux.residual is not None) == (cfg.loss.residual_coeff > 0)
        td = actor(env.reset())
        assert td["action"].shape == env.action_spec.shape
    elif cfg.trainer.kind == "off_policy":
        from mixed_traffic.training.off_policy import make_qvalue

        assert cfg.loss.name == "dqn" and cfg.policy.kind == "qnet"
        qvalue, _, _ = make_qvalue(cfg, env)
        assert isinstance(DQNLoss(qvalue, action_space="one_hot"), DQNLoss)
    else:
        from mixed_traffic.training.tabular import make_table

        assert cfg.loss.name == "q_learning" and cfg.policy.kind == "q_table"
        make_table(cfg, env)


def test_hard_start_bank_and_conflict_cost():
    from mixed_traffic import make_env
    from transforms.conflict_cost import anticipation_cost

    env = make_env("intersection", batch_size=2, seed=0, agent_bank_size=64, hard_start_fraction=0.5)
    x0 = env.bank.true[:, 0, 0]
    assert ((x0[32:] >= 2.2 - 1e-6) & (x0[32:] <= 2.6 + 1e-6)).all() and (x0[:32] > 2.6).any()
    assert set(env.bank.behaviour.tolist()) <= {0, 1, 2}  # training behaviours only (zig-zag stays held out)
    # driving at 2 m/s towards an agent about to cross is charged before the distance cost sees it
    going = torch.tensor([[-0.8, 2.0, 1.8, 0.5, -1.0, 0.0, 0.05, 0.05]])
    waiting = going.clone()
    waiting[0, 1] = 0.0
    assert anticipation_cost(going).item() > 0 and anticipation_cost(waiting).item() == 0
    # a margin charges the same predicted approach more
    assert anticipation_cost(going, margin=0.3).item() > anticipation_cost(going).item()
    from transforms import ConflictCost

    with pytest.raises(ValueError, match="margin"):
        ConflictCost(margin=-0.1)


def test_bc_demonstrations_can_use_the_training_banks_agents():
    from mixed_traffic.config import compose
    from mixed_traffic.envs.intersection import agent_bank
    from mixed_traffic.envs.intersection_agents import sample_agent_trajectories
    from mixed_traffic.intersection.demos import default_path, nmpc_demonstrations
    from mixed_traffic.training.on_policy import demo_agent_mix

    # without shares the bank is the mixed-style one the demonstrations always used (same cache name)
    a, b = agent_bank(16, seed=10_000, split="train"), sample_agent_trajectories(16, seed=10_000, split="train")
    assert torch.equal(a.true, b.true) and torch.equal(a.behaviour, b.behaviour)
    assert default_path("nmpc", 0, 384).name == "nmpc_seed0_n384.pt"
    cfg = compose(["experiment=intersection_lppo_bc"])
    mix = demo_agent_mix(cfg)
    assert mix["pause_fraction"] == 0.25 and mix["reactive_fraction"] == 0.25 and mix["hard_start_fraction"] == 0.3
    assert default_path("nmpc", 0, 384, mix).name == "nmpc_seed0_n384_h0.3-r0.25-p0.25.pt"
    # another close-start range is another bank: another cache file
    assert default_path("nmpc", 0, 384, {**mix, "hard_start_x": (2.0, 2.4)}).name != default_path("nmpc", 0, 384, mix).name
    bank = agent_bank(40, seed=3, split="train", **mix)
    assert int(bank.reactive.sum()) == 10  # a quarter of the bank reacts to the ego
    demo = nmpc_demonstrations(2, seed=0, batch=2, progress=False, mix=mix)
    assert demo["expert_action"].shape[-1] == 1 and demo.shape[0] > 0
    cfg.loss.bc.agents = "everyone"
    with pytest.raises(ValueError, match="loss.bc.agents"):
        demo_agent_mix(cfg)


def test_bc_expert_overrides_name_their_cache_and_fail_clearly(tmp_path):
    from mixed_traffic.intersection.demos import default_path, load_or_make, main, nmpc_demonstrations

    # another expert is another cache file: demonstrations of the default NMPC are never loaded instead
    assert default_path("nmpc", 0, 384, None, {"margin": 0.25}).name == "nmpc_seed0_n384_margin0.25.pt"
    assert default_path("nmpc", 0, 384, None, {}).name == default_path("nmpc", 0, 384).name
    # the expert's field reaches the controller: a wider margin changes what it does near an agent
    d0 = nmpc_demonstrations(2, seed=0, batch=2, progress=False)
    d1 = nmpc_demonstrations(2, seed=0, batch=2, progress=False, expert_overrides={"margin": 0.6})
    assert not torch.equal(d0["expert_action"][: min(len(d0), len(d1))], d1["expert_action"][: min(len(d0), len(d1))])
    # bad fields fail before any episode runs, naming the config field or the CLI flag; nothing is written
    with pytest.raises(ValueError, match="loss.bc.expert_overrides.*margin"):
        load_or_make(tmp_path / "d.pt", expert="nmpc", episodes=2, seed=0, expert_overrides={"margin": -1.0})
    with pytest.raises(ValueError, match="loss.bc.expert_overrides.*margn"):
        load_or_make(tmp_path / "d.pt", expert="nmpc", episodes=2, seed=0, expert_overrides={"margn": 0.2})
    assert not (tmp_path / "d.pt").exists()
    with pytest.raises(SystemExit):
        main(["--episodes", "2", "--out", str(tmp_path / "e.pt"), "--nmpc", "horizon=x"])
    assert not (tmp_path / "e.pt").exists()


def test_dagger_labels_the_drivers_states_with_the_nmpc():
    from tensordict.nn import TensorDictModule

    from mixed_traffic.intersection.demos import nmpc_demonstrations

    brake = TensorDictModule(lambda obs: torch.full((*obs.shape[:-1], 1), -3.0), ["observation"], ["action"])
    demo = nmpc_demonstrations(2, seed=0, batch=2, progress=False, driver=brake)
    v = demo["observation"][:, 1]
    # the driver's actions were executed: the ego starts at rest and only ever backs up ...
    assert v.max() <= 1e-6 and v.min() < -0.5
    # ... while the labels are the NMPC's, which drives on across the intersection
    assert demo["expert_action"].max() > 0.5


def test_ego_caused_conflict_cost_never_charges_waiting_or_reversing():
    from torchrl.envs import TransformedEnv

    from mixed_traffic import make_env
    from transforms.conflict_cost import ConflictCost, anticipation_cost, ego_caused_anticipation_cost

    # a left turner sweeping past the waiting ego's start: the plain prediction charges waiting, this does not
    sweep = torch.tensor([[-1.25, 0.0, -0.1, -0.6, -0.8, -0.6, 0.2, 0.2]])
    assert anticipation_cost(sweep).item() > 0 and ego_caused_anticipation_cost(sweep).item() == 0
    backing = sweep.clone()
    backing[0, 1] = -1.0
    assert ego_caused_anticipation_cost(backing).item() == 0  # nothing to gain by reversing away
    # driving into an agent's predicted path is charged as before
    going = torch.tensor([[-0.8, 2.0, 1.8, 0.5, -1.0, 0.0, 0.05, 0.05]])
    assert ego_caused_anticipation_cost(going).item() == pytest.approx(anticipation_cost(going).item())
    cfg = compose(["experiment=intersection_lppo"])
    assert cfg.transforms.conflict_cost.ego_caused and cfg.env.overrides.pause_fraction > 0
    env = TransformedEnv(make_env("intersection", batch_size=2, seed=0), ConflictCost(ego_caused=True))
    assert "ego_caused=True" in repr(env.transform)


def _cfg(name, tmp_path, *extra):
    return compose([f"experiment={name}", "trainer.total_frames=2048", "trainer.num_envs=32", "trainer.rollout_len=16",
                    "trainer.epochs=1", "trainer.minibatch_size=256", "trainer.progress=false", "eval.episodes=1",
                    "trainer.checkpoint_every=1", f"out_dir={tmp_path}", *extra])


def test_lppo_trains_in_the_shared_loop_resumes_and_evaluates(tmp_path, capsys):
    """Checkpoint, early stop (said loudly), resume to the same weights, CSV logs, evaluation on the test set."""
    from mixed_traffic.apps.train import main as mt_train

    torch.set_num_threads(1)
    full = train(_cfg("intersection_lppo", tmp_path / "full"))
    assert full["summary"]["frames"] == 2048 and not full["stopped_early"]
    mt_train(_cfg("intersection_lppo", tmp_path / "cut", "trainer.max_iterations=2"))
    err = capsys.readouterr().err
    assert "STOPPED EARLY" in err and f"resume={tmp_path / 'cut'}" in err
    assert not (tmp_path / "cut" / "final.pt").exists() and (tmp_path / "cut" / "checkpoints" / "latest.pt").exists()
    rest = train(_cfg("intersection_lppo", tmp_path / "x", f"resume={tmp_path / 'cut'}"))
    a, b = full["actor"].state_dict(), rest["actor"].state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert (tmp_path / "cut" / "logs").is_dir() and any((tmp_path / "cut" / "logs").rglob("lambda.csv"))
    from mixed_traffic.evaluation import evaluate_and_report

    rep = evaluate_and_report(_cfg("intersection_lppo", tmp_path), tmp_path / "cut" / "eval",
                              checkpoint=tmp_path / "cut" / "final.pt")
    assert rep["sets"]["standard"]["table"]["overall"]["episodes"] == 4
    assert json.loads((tmp_path / "cut" / "eval" / "eval.json").read_text())["name"] == "intersection_lppo"


def test_resume_of_a_missing_path_is_an_error(tmp_path):
    with pytest.raises((ConfigError, FileNotFoundError, ValueError), match="resume|checkpoint"):
        train(_cfg("intersection_lppo", tmp_path, f"resume={tmp_path / 'nothing'}"))


def test_composed_method_from_groups_trains(tmp_path):
    """`mt-train env=intersection loss=lagrangian_ppo transforms=barrier_force` composes and trains."""
    cfg = compose(["env=intersection", "loss=lagrangian_ppo", "transforms=barrier_force", "trainer.total_frames=512",
                   "trainer.num_envs=16", "trainer.rollout_len=16", "trainer.progress=false", f"out_dir={tmp_path}"])
    out = train(cfg)
    assert out["summary"]["frames"] == 512 and (tmp_path / "final.pt").exists()
    assert "bff" in out["env"].reset().keys() or any(type(t).__name__ == "BarrierForce" for t in out["env"].transform)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["intersection_lppo_bc", "intersection_lppo_bff", "intersection_residual_mpc"])
def test_methods_run_end_to_end(name, tmp_path):
    torch.set_num_threads(1)
    extra = ["loss.bc.episodes=2", "loss.bc.pretrain_steps=5", f"loss.bc.demos={tmp_path / 'd.pt'}"] \
        if name.endswith("_bc") else []
    cfg = _cfg(name, tmp_path / "run", "trainer.total_frames=128", "trainer.num_envs=4", "trainer.minibatch_size=64",
               *extra)
    out = train(cfg)
    assert out["summary"]["frames"] >= 128


@pytest.mark.slow
def test_nmpc_experiment_evaluates_through_mt_train(tmp_path):
    from mixed_traffic.apps.train import main as mt_train

    mt_train(compose(["experiment=intersection_nmpc", "eval.episodes=1", f"out_dir={tmp_path}"]))
    out = json.loads((tmp_path / "eval" / "eval.json").read_text())
    assert out["sets"]["standard"]["table"]["overall"]["collision_rate"] == 0.0


@pytest.mark.slow
def test_nmpc_acceptance_on_the_full_test_set():
    """NMPC on 320 test episodes (80 per behaviour): 100% success with zero collisions (docs/intersection.md)."""
    from mixed_traffic.intersection.evaluate import evaluate_policy
    from mixed_traffic.intersection.nmpc import make_nmpc_policy

    res = evaluate_policy(make_nmpc_policy(), n_per_behaviour=80)
    assert int(res.collision.sum()) == 0
    assert res.table["overall"]["success_rate"] > 0.99
