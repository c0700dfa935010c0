"""RL on the DeeP-LCC platoon: RLMPC residual over the NNMPC, warm start, experiments, comparison."""

import pytest
import torch
from torchrl.envs import Compose, TransformedEnv
from torchrl.envs.utils import ExplorationType, check_env_specs, set_exploration_type

from mixed_traffic.config import compose
from mixed_traffic.controllers.deeplcc.nnmpc import NNMPC
from mixed_traffic.training import train
from mixed_traffic.training.builders import TRANSFORMS, make_actor_critic, make_transformed_env

TINY = ["trainer.num_envs=4", "trainer.rollout_len=8", "trainer.total_frames=64", "trainer.epochs=1",
        "trainer.minibatch_size=16", "trainer.progress=false", "env.episode_seconds=2.0"]


@pytest.fixture
def nnmpc_path(tmp_path):
    torch.manual_seed(0)
    net = NNMPC().eval()
    p = tmp_path / "nnmpc.pt"
    net.save(p)
    return str(p)


def test_rlmpc_env_starts_as_the_nnmpc(nnmpc_path):
    cfg = compose(["experiment=deeplcc_rlmpc", f"transforms.residual_nnmpc.checkpoint={nnmpc_path}", *TINY])
    env = make_transformed_env(cfg, num_envs=3, seed=0)
    # the chain itself (RewardSum's running sum leaves its own bounded spec, as on every env)
    base = env.base_env
    check_env_specs(TransformedEnv(base, Compose(*[TRANSFORMS[n](cfg.transforms, base) for n in cfg.transforms.chain])))
    assert float(env.action_spec.space.low.min()) == -1.0 and float(env.action_spec.space.high.max()) == 1.0
    actor, _ = make_actor_critic(cfg, env)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        td = env.rollout(10, actor)
    base = td["next", "residual", "base_action"]
    executed = td["next", "cav", "accel"]
    # a fresh actor's mean residual is ~0: the executed command is the NNMPC's (the layer rarely acts)
    clipped = td["next", "safety", "clipped"]
    diff = (executed - base).abs()[~clipped]
    assert diff.numel() > 0 and float(diff.max()) < 0.1
    # the residual is bounded by the weight (1 m/s^2)
    with set_exploration_type(ExplorationType.RANDOM):
        td = env.rollout(10, actor)
    assert float((td["next", "cav", "accel"] - td["next", "residual", "base_action"]).abs().max()) <= 1.0 + 1e-5


def test_missing_nnmpc_names_the_field_and_the_command(tmp_path):
    cfg = compose(["experiment=deeplcc_rlmpc", f"transforms.residual_nnmpc.checkpoint={tmp_path / 'none.pt'}", *TINY])
    with pytest.raises(FileNotFoundError, match="transforms.residual_nnmpc.checkpoint.*mt-dataset"):
        make_transformed_env(cfg, num_envs=2, seed=0)


@pytest.mark.parametrize("experiment", ["deeplcc_rlmpc", "deeplcc_lppo", "deeplcc_warmstart"])
def test_experiments_train_through_mt_train_loop(experiment, nnmpc_path, tmp_path):
    cfg = compose([f"experiment={experiment}", f"transforms.residual_nnmpc.checkpoint={nnmpc_path}",
                   f"policy.warm_start.nnmpc={nnmpc_path}" if experiment == "deeplcc_warmstart" else "seed=0",
                   "policy.warm_start.frames=64", "policy.warm_start.epochs=2", *TINY])
    assert cfg.env.overrides.mismatch == "idm"  # the RL learns on the mismatched platoon
    res = train(cfg, out_dir=tmp_path)
    assert res["summary"]["completed"] and (tmp_path / "final.pt").is_file()
    assert "lambda" in res["summary"]["final"]


def test_warm_start_fits_the_actor_to_the_nnmpc(nnmpc_path):
    from mixed_traffic.controllers.deeplcc.rlmpc import load_nnmpc, warm_start_actor

    cfg = compose(["experiment=deeplcc_lppo", *TINY])
    env = make_transformed_env(cfg, num_envs=8, seed=0)
    actor, _ = make_actor_critic(cfg, env)
    net = load_nnmpc(nnmpc_path)

    def gap_to_nnmpc():
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            td = env.rollout(20, actor, break_when_any_done=False)
            return float((td["action"] - net(td["uini"], td["yini"], td["eini"])).pow(2).mean())

    before = gap_to_nnmpc()
    out = warm_start_actor(actor, env, nnmpc_path, frames=640, epochs=40, lr=3e-3, log=None)
    after = gap_to_nnmpc()
    assert out["bc_mse"] < 0.5 * before and after < 0.5 * before


def test_comparison_metrics_split_by_scenario(nnmpc_path):
    from torchrl.envs import Compose, TransformedEnv

    from mixed_traffic import make_env
    from mixed_traffic.controllers.deeplcc import compare
    from transforms import SafetyLayer

    base = make_env("platoon", batch_size=4, seed=10_000, profiles=["random1", "brake"], profile_rows=True,
                    randomize=False, mismatch="idm", episode_seconds=4.0)
    env = TransformedEnv(base, Compose(SafetyLayer(s_min=5.0, s_max=None)))
    pol = compare.build("nnmpc", scenarios=("brake",), mismatch="idm", episodes=1, seed=0, safety=True, runs={},
                        nnmpc=nnmpc_path)[1]
    m = compare.rollout_metrics(env, pol, ("random1", "brake"))
    assert set(m) == {"random1", "brake"} and m["brake"]["episodes"] == 2
    assert m["brake"]["cost"] > m["random1"]["cost"] > 0 and m["brake"]["fuel"] > 0
    assert m["random1"]["collisions"] == 0 and 0 <= m["random1"]["clip_rate"] <= 1
    hdv_env, hdv = compare.build("hdv", scenarios=("brake",), mismatch="idm", episodes=1, seed=0, safety=False,
                                 runs={}, nnmpc=nnmpc_path)
    td = hdv_env.reset()
    a = hdv(td)["action"]
    assert a.shape == (1, 2) and float(a.abs().max()) < 0.5  # at equilibrium a human barely accelerates


def test_per_step_compute_times_the_network_and_the_module(nnmpc_path):
    from mixed_traffic.controllers.deeplcc import compare

    t = compare.per_step_compute("nnmpc", {}, nnmpc_path, repeats=5)
    assert set(t) == {"module", "network"} and 0 < t["network"] < 1.0 and 0 < t["module"] < 1.0


@pytest.mark.parametrize("experiment", ["deeplcc_rlmpc_apg", "ring_lagrangian_ppo"])
def test_apg_gradient_is_the_closed_loops_own(experiment, nnmpc_path):
    """The analytic gradient of a window's cost equals a finite difference of the same seeded closed loop."""
    from mixed_traffic.training.apg import _j_ref, window_loss

    platoon = experiment.startswith("deeplcc")
    cfg = compose([f"experiment={experiment}", *([f"transforms.residual_nnmpc.checkpoint={nnmpc_path}", *TINY,
                                                    "env.episode_seconds=20.0"] if platoon else [])])
    torch.manual_seed(0)
    actor, _ = make_actor_critic(cfg, make_transformed_env(cfg, num_envs=2, seed=0))
    j_ref = _j_ref(cfg.policy.apg.J_ref, "policy.apg.J_ref") if platoon else None
    names, params = zip(*[(n, p) for n, p in actor.named_parameters() if p.requires_grad], strict=True)
    direction = [torch.randn_like(p) for p in params]

    def loss_at(eps: float, grad: bool):
        env = make_transformed_env(cfg, num_envs=3, seed=5)  # same seed: same profiles and noise draws
        env.base_env.differentiable = grad
        shifted = [p + eps * d for p, d in zip(params, direction, strict=True)] if eps else params
        with torch.nn.utils.stateless._reparametrize_module(actor, dict(zip(names, shifted, strict=True))), \
                torch.set_grad_enabled(grad), set_exploration_type(ExplorationType.DETERMINISTIC):
            loss, _, _ = window_loss(env, actor, env.reset(), 30, j_ref, 10.0)
        return loss

    loss = loss_at(0.0, True)
    grads = torch.autograd.grad(loss, params, allow_unused=True)  # the log-std is unused by the deterministic action
    analytic = sum(float((g * d).sum()) for g, d in zip(grads, direction, strict=True) if g is not None)
    eps = 1e-4
    numeric = (float(loss_at(eps, False)) - float(loss_at(-eps, False))) / (2 * eps)
    assert abs(analytic) > 1e-6  # the residual moves the platoon's cost ...
    assert analytic == pytest.approx(numeric, rel=0.05)  # ... and the gradient is the closed loop's
    if not platoon:
        return
    # without the flag the platoon cuts the graph at the action (what PPO's collection gets)
    env = make_transformed_env(cfg, num_envs=3, seed=5)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        td = env.step(actor(env.reset()))["next"]
    assert not td["traffic", "J"].requires_grad and not td["observation"].requires_grad


def test_apg_refuses_bad_settings_naming_the_field(nnmpc_path):
    from mixed_traffic.training.apg import apg_pretrain

    cfg = compose(["experiment=deeplcc_rlmpc_apg", f"transforms.residual_nnmpc.checkpoint={nnmpc_path}", *TINY])
    actor, _ = make_actor_critic(cfg, make_transformed_env(cfg, num_envs=2, seed=0))
    cfg.policy.apg.J_ref = {"brakes": 1.0}
    with pytest.raises(ValueError, match="policy.apg.J_ref.*brakes"):
        apg_pretrain(actor, cfg, log=None)
    cfg.policy.apg.J_ref = {}
    cfg.policy.apg.horizon = 0
    with pytest.raises(ValueError, match="policy.apg.horizon"):
        apg_pretrain(actor, cfg, log=None)
    # the intersection env is not differentiable (nor are the SUMO backends): refused by name
    cross = compose(["experiment=intersection_lppo", "policy.apg.iterations=1", "policy.apg.num_envs=2"])
    cross_actor, _ = make_actor_critic(cross, make_transformed_env(cross, num_envs=2, seed=0))
    with pytest.raises(ValueError, match="policy.apg needs a differentiable torch env.*IntersectionEnv"):
        apg_pretrain(cross_actor, cross, log=None)
    # per-profile references are the platoon's: on the ring they are an error, not ignored
    ring = compose(["experiment=ring_lagrangian_ppo", "policy.apg.iterations=1", "policy.apg.num_envs=2",
                    "+policy.apg.J_ref.brake=1.0"])
    ring_actor, _ = make_actor_critic(ring, make_transformed_env(ring, num_envs=2, seed=0))
    with pytest.raises(ValueError, match="policy.apg.J_ref.*TrafficEnv"):
        apg_pretrain(ring_actor, ring, log=None)
    ring.policy.apg.J_ref = {}
    ring.policy.apg.head_gap_max = 0.0
    with pytest.raises(ValueError, match=r"policy.apg.head_gap_max=0.0 is invalid; allowed: null or > 0"):
        apg_pretrain(ring_actor, ring, log=None)
    cfg.policy.apg.horizon = 2
    cfg.policy.apg.head_gap_max = 36.0  # the platoon has no head gap: refused, not ignored
    with pytest.raises(ValueError, match="policy.apg.head_gap_max.*PlatoonEnv"):
        apg_pretrain(actor, cfg, log=None)


def test_apg_prices_a_head_gap_above_head_gap_max():
    """``policy.apg.head_gap_max``: the window's loss grows by cost_coeff * (head gap - max) / max,
    from ``head_gap_after`` seconds into the episode on."""
    from mixed_traffic.training.apg import window_loss

    cfg = compose(["experiment=ring_lagrangian_ppo"])
    actor, _ = make_actor_critic(cfg, make_transformed_env(cfg, num_envs=2, seed=0))
    losses = []
    for head_max, after in ((None, 0.0), (10.0, 0.0), (10.0, 5.0)):
        env = make_transformed_env(cfg, num_envs=3, seed=5)
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            loss, td, _ = window_loss(env, actor, env.reset(), 1, None, 30.0, head_gap_max=head_max,
                                      head_gap_after=after)
        losses.append(float(loss))
    assert losses[2] == losses[0]  # one 0.1-s step: still before head_gap_after
    excess = (td["cav", "head_gap"].double() - 10.0).clamp_min(0.0) / 10.0
    assert float(excess.min()) > 0  # the ring's starts lie beyond 10 m
    assert losses[1] - losses[0] == pytest.approx(30.0 * float(excess.mean()), rel=1e-6)


def test_apg_average_last_keeps_the_mean_of_the_last_steps_parameters():
    """``policy.apg.average_last: N``: the actor ends on the mean of its parameters after each of the
    last N steps. APG is deterministic under the seed, so the runs of 1 and 2 steps are the 2-step
    run's own trajectory; a count above the steps is refused naming the field."""
    from mixed_traffic.training.apg import apg_pretrain

    def params_after(iterations: int, average_last: int = 0) -> list[torch.Tensor]:
        cfg = compose(["experiment=ring_lagrangian_ppo", f"policy.apg.iterations={iterations}",
                       f"policy.apg.average_last={average_last}", "policy.apg.num_envs=2", "policy.apg.horizon=3",
                       "trainer.progress=false"])
        torch.manual_seed(0)
        actor, _ = make_actor_critic(cfg, make_transformed_env(cfg, num_envs=2, seed=0))
        apg_pretrain(actor, cfg, log=None)
        return [p.detach().clone() for p in actor.parameters() if p.requires_grad]

    one, two, mean = params_after(1), params_after(2), params_after(2, average_last=2)
    assert any(not torch.equal(a, b) for a, b in zip(one, two))  # the second step moved the policy
    for a, b, m in zip(one, two, mean):
        torch.testing.assert_close(m, (a + b) / 2, rtol=1e-6, atol=1e-7)
    assert all(torch.equal(a, b) for a, b in zip(params_after(2, average_last=1), two))
    with pytest.raises(ValueError, match=r"policy.apg.average_last=3 is invalid; allowed: an integer in \[0, "
                                         r"policy.apg.iterations=2\]"):
        params_after(2, average_last=3)


def test_apg_alone_trains_and_saves_a_policy(tmp_path):
    """``trainer.total_frames=0`` with ``policy.apg``: the APG-trained actor is the run's final policy."""
    from mixed_traffic.evaluation.policies import checkpoint_config
    from mixed_traffic.validation import ConfigError

    over = ["experiment=ring_lagrangian_ppo", "policy.apg.num_envs=4", "policy.apg.horizon=5",
            "trainer.total_frames=0", "trainer.progress=false", "eval.after_train=false"]
    with pytest.raises(ConfigError, match="trainer.total_frames.*policy.apg.iterations"):
        train(compose([*over, "policy.apg.iterations=0"]), out_dir=tmp_path / "none")  # no PPO, no APG: nothing trains
    torch.manual_seed(0)
    res = train(compose([*over, "policy.apg.iterations=3"]), out_dir=tmp_path / "apg")
    assert res["summary"]["frames"] == 0 and (tmp_path / "apg" / "final.pt").is_file()
    _, state = checkpoint_config(tmp_path / "apg" / "final.pt")
    # the run's own initialisation (as train_on_policy builds it under the run's seed) ...
    from mixed_traffic.training.on_policy import build_ppo, collector_rows

    cfg = compose([*over, "policy.apg.iterations=3"])
    torch.manual_seed(cfg.seed)
    init = build_ppo(cfg, make_transformed_env(cfg, num_envs=collector_rows(cfg), seed=cfg.seed))[0].state_dict()
    assert set(init) == set(state["actor"])
    # ... is not what was saved: the APG steps moved the mean head
    assert any(not torch.equal(v, state["actor"][k]) for k, v in init.items())


def test_apg_fast_action_is_the_actors_deterministic_action():
    """APG steps with ``deterministic_action(actor)``: the action ``actor`` gives deterministically, still
    differentiable (the gradient itself: ``test_apg_gradient_is_the_closed_loops_own``)."""
    from mixed_traffic.training.apg import deterministic_action

    cfg = compose(["experiment=ring_lagrangian_ppo"])
    env = make_transformed_env(cfg, num_envs=4, seed=0)
    actor, _ = make_actor_critic(cfg, env)
    td = env.reset()
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        slow = actor(td.clone())["action"]
        fast = deterministic_action(actor)(td.clone())["action"]
    assert torch.equal(slow, fast) and fast.requires_grad
