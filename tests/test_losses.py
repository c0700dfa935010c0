"""Loss modules: each gradient moves the right parameters the right way."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torchrl.envs import TransformedEnv
from torchrl.modules import MLP, ProbabilisticActor, TanhNormal, ValueOperator

from losses import BCLoss, ClipPPOLoss, LagrangianPPOLoss
from mixed_traffic import make_env

OBS = 4


def make_actor(seed=0, low=-3.0, high=3.0):
    torch.manual_seed(seed)
    net = torch.nn.Sequential(MLP(in_features=OBS, out_features=2, num_cells=[32]), NormalParamExtractor())
    return ProbabilisticActor(TensorDictModule(net, ["observation"], ["loc", "scale"]), in_keys=["loc", "scale"],
                              distribution_class=TanhNormal, distribution_kwargs={"low": low, "high": high},
                              return_log_prob=True)


def make_critic(out="state_value"):
    return ValueOperator(MLP(in_features=OBS, out_features=1, num_cells=[32]), in_keys=["observation"],
                         out_keys=[out])


def make_batch(actor, n=512, seed=1):
    g = torch.Generator().manual_seed(seed)
    td = TensorDict({"observation": torch.randn(n, OBS, generator=g)}, [n])
    with torch.no_grad():
        actor(td)
    td["advantage"] = torch.randn(n, 1, generator=g)
    td["cost_advantage"] = torch.randn(n, 1, generator=g)
    td["value_target"] = torch.randn(n, 1, generator=g)
    td["cost_value_target"] = torch.rand(n, 1, generator=g)
    return td.detach()


def logprob_change(lam, steps=5):
    actor = make_actor()
    loss = LagrangianPPOLoss(actor, make_critic(), make_critic("cost_value"), lambda_init=lam, lambda_max=1e4,
                             entropy_coeff=0.0)
    td = make_batch(actor)
    before = td["action_log_prob"].clone()
    opt = torch.optim.SGD(actor.parameters(), lr=0.05)
    for _ in range(steps):
        out = loss(td)
        opt.zero_grad()
        out["loss_objective"].backward()
        opt.step()
    with torch.no_grad():
        after = actor.get_dist(td.clone(False)).log_prob(td["action"])
    return (after.reshape(-1) - before.reshape(-1)), td, out.detach()


def corr(a, b):
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / (a.norm() * b.norm()))


def test_lppo_huge_lambda_follows_the_cost_advantage():
    d0, td, out0 = logprob_change(0.0)
    d_big, _, out_big = logprob_change(1e3)
    a_r, a_c = td["advantage"].reshape(-1), td["cost_advantage"].reshape(-1)
    # the surrogate each update improves: sum_i A_i * (change of log pi(a_i | s_i))
    # lambda = 0: plain PPO, raises the reward surrogate
    assert float((a_r * d0).sum()) > 0
    # huge lambda: lowers the cost surrogate (and does so far more than lambda = 0)
    assert float((a_c * d_big).sum()) < 0
    assert float((a_c * d_big).sum()) < float((a_c * d0).sum())
    assert corr(d_big, a_c) < corr(d0, a_c)
    assert corr(d0, a_r) > corr(d_big, a_r)
    assert float(out_big["cost_advantage_share"]) > 0.99 > float(out0["cost_advantage_share"])
    assert float(out_big["lagrange_multiplier"]) == pytest.approx(1e3)


def test_lppo_combined_advantage_formula():
    actor = make_actor()
    td = make_batch(actor, n=64)
    seen = {}

    class Spy(LagrangianPPOLoss):
        def _log_weight(self, tensordict, adv_shape):
            seen["adv"] = tensordict["advantage"].clone()
            return super()._log_weight(tensordict, adv_shape)

    for normalize, expect in ((True, (td["advantage"] - 2.0 * td["cost_advantage"]) / 3.0),
                              (False, td["advantage"] - 2.0 * td["cost_advantage"])):
        loss = Spy(actor, make_critic(), make_critic("cost_value"), lambda_init=2.0,
                   normalize_lagrangian=normalize)
        loss(td)
        assert torch.allclose(seen["adv"], expect)


def test_lppo_cost_critic_loss_trains_the_cost_critic_only():
    actor, critic, cost_critic = make_actor(), make_critic(), make_critic("cost_value")
    loss = LagrangianPPOLoss(actor, critic, cost_critic)
    td = make_batch(actor)
    opt = torch.optim.Adam(cost_critic.parameters(), lr=1e-2)
    first = None
    for _ in range(60):
        out = loss(td)
        opt.zero_grad()
        out["loss_cost_critic"].backward()
        opt.step()
        first = float(out["loss_cost_critic"].detach()) if first is None else first
    assert float(loss(td)["loss_cost_critic"].detach()) < 0.5 * first
    # the cost critic loss does not touch the actor or the reward critic
    actor.zero_grad()
    critic.zero_grad()
    loss(td)["loss_cost_critic"].backward()
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in actor.parameters())
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in critic.parameters())


def test_lppo_update_lambda_matches_dual_ascent():
    actor = make_actor()
    loss = LagrangianPPOLoss(actor, make_critic(), make_critic("cost_value"))
    batch = TensorDict({"next": {"cost": torch.full((10, 1), 0.6)}}, [10])
    lam = 1.0
    for _ in range(5):
        lam = min(max(lam + 0.05 * (0.6 - 0.1), 0.0), 10.0)
        assert loss.update_lambda(batch) == pytest.approx(lam)
    assert float(loss.lagrange_multiplier) == pytest.approx(lam)


def test_lppo_ring_style_is_plain_clip_ppo():
    actor, critic = make_actor(), make_critic()
    td = make_batch(actor, n=64)
    ours = LagrangianPPOLoss(actor, critic, None, entropy_coeff=0.0)
    ref = ClipPPOLoss(actor, critic, entropy_coeff=0.0)
    assert torch.allclose(ours(td)["loss_objective"], ref(td)["loss_objective"])


def test_lppo_computes_both_advantages_from_a_rollout():
    env = make_env("ring", batch_size=4, seed=0)
    obs_dim = env.observation_spec["observation"].shape[-1]
    torch.manual_seed(0)
    net = torch.nn.Sequential(MLP(in_features=obs_dim, out_features=2, num_cells=[16]), NormalParamExtractor())
    spec = env.action_spec_unbatched
    actor = ProbabilisticActor(TensorDictModule(net, ["observation"], ["loc", "scale"]), in_keys=["loc", "scale"],
                               distribution_class=TanhNormal,
                               distribution_kwargs={"low": spec.space.low, "high": spec.space.high},
                               return_log_prob=True, spec=spec)
    critic = ValueOperator(MLP(in_features=obs_dim, out_features=1, num_cells=[16]), in_keys=["observation"])
    cost_critic = ValueOperator(MLP(in_features=obs_dim, out_features=1, num_cells=[16]), in_keys=["observation"],
                                out_keys=["cost_value"])
    loss = LagrangianPPOLoss(actor, critic, cost_critic)
    loss.make_value_estimator(gamma=0.98, lmbda=0.9)
    with torch.no_grad():
        batch = env.rollout(16, actor)
    out = loss(batch)
    for k in ("loss_objective", "loss_critic", "loss_cost_critic", "loss_entropy"):
        assert torch.isfinite(out[k]).all(), k
    total = sum(v for k, v in out.items() if k.startswith("loss_"))
    total.backward()


def test_bc_trains_a_deterministic_network_alone():
    torch.manual_seed(0)
    net = TensorDictModule(MLP(in_features=OBS, out_features=1, num_cells=[32]), ["observation"], ["action"])
    loss = BCLoss(net, expert_action_key="mpc_action")
    obs = torch.randn(256, OBS)
    td = TensorDict({"observation": obs, "mpc_action": torch.tanh(obs[:, :1] - obs[:, 1:2])}, [256])
    opt = torch.optim.Adam(net.parameters(), lr=1e-2)
    first = float(loss(td)["bc_mse"])
    for _ in range(150):
        out = loss(td)
        opt.zero_grad()
        out["loss_bc"].backward()
        opt.step()
    assert float(loss(td)["bc_mse"]) < 0.1 * first


def test_bc_moves_the_tanh_normal_mean_towards_the_expert():
    actor = make_actor()
    td = make_batch(actor, n=256)
    td["expert_action"] = torch.full((256, 1), 2.0)
    loss = BCLoss(actor, coeff=1.0)
    opt = torch.optim.Adam(actor.parameters(), lr=1e-2)
    first = float(loss(td)["bc_mse"])
    for _ in range(100):
        out = loss(td)
        opt.zero_grad()
        out["loss_bc"].backward()
        opt.step()
    with torch.no_grad():
        mean_action = actor.get_dist(td.clone(False)).deterministic_sample
    assert float(loss(td)["bc_mse"]) < 0.1 * first
    assert (mean_action - 2.0).abs().mean() < 0.3


def test_bc_composes_with_lppo_by_a_coefficient():
    actor = make_actor()
    td = make_batch(actor, n=128)
    td["expert_action"] = torch.zeros(128, 1)
    lppo = LagrangianPPOLoss(actor, make_critic(), make_critic("cost_value"), entropy_coeff=0.0)

    def grad_of(coeff):
        actor.zero_grad()
        out = lppo(td)
        bc = BCLoss(actor, coeff=coeff)(td)
        (out["loss_objective"] + bc["loss_bc"]).backward()
        return torch.cat([p.grad.reshape(-1) for p in actor.parameters()])

    g0, g1, g2 = grad_of(0.0), grad_of(1.0), grad_of(2.0)
    # the BC part is linear in its coefficient
    assert torch.allclose(g2 - g0, 2.0 * (g1 - g0), atol=1e-5)
    assert (g1 - g0).abs().sum() > 0


def test_bc_mask_and_validation():
    net = TensorDictModule(torch.nn.Linear(OBS, 1), ["observation"], ["action"])
    td = TensorDict({"observation": torch.randn(4, OBS), "expert_action": torch.zeros(4, 1),
                     "valid": torch.tensor([True, False, False, False])}, [4])
    masked = BCLoss(net, mask_key="valid")(td)["bc_mse"]
    with torch.no_grad():
        first = net(td.clone())["action"][0].pow(2).mean()
    assert torch.allclose(masked, first)
    with pytest.raises(ValueError, match="coeff"):
        BCLoss(net, coeff=-1.0)


# ----------------------------------------------------------------------------- residual PPO
def test_residual_loss_shrinks_the_residual():
    from losses import ResidualMPCLoss

    actor = make_actor()
    td = make_batch(actor, n=256)
    with torch.no_grad():  # start from a clearly non-zero mean residual
        actor.module[0].module[0][-1].bias[0] += 1.5
    loss = ResidualMPCLoss(actor, make_critic(), residual_coeff=1.0)
    first = float(loss(td)["residual_rms"])
    opt = torch.optim.Adam(actor.parameters(), lr=1e-2)
    for _ in range(60):
        out = loss(td)
        opt.zero_grad()
        out["loss_residual"].backward()
        opt.step()
    assert float(loss(td)["residual_rms"]) < 0.5 * first
    with pytest.raises(ValueError, match="residual_coeff"):
        ResidualMPCLoss(actor, make_critic(), residual_coeff=-1.0)


# ----------------------------------------------------------------------------- tabular Q
def _transition(s, a, r, s2, term):
    return TensorDict({"state_index": torch.tensor([[s]]), "action_index": torch.tensor([[a]]),
                       "next": {"state_index": torch.tensor([[s2]]), "reward": torch.tensor([[float(r)]]),
                                "terminated": torch.tensor([[term]])}}, [1])


def test_tabular_q_matches_td0_step_by_step():
    from losses import TabularQLearning

    q = TabularQLearning(n_actions=3, alpha=0.2, gamma=0.98)
    ref: dict[int, list[float]] = {}
    g = torch.Generator().manual_seed(0)
    for _ in range(300):
        s, s2 = int(torch.randint(5, (1,), generator=g)), int(torch.randint(5, (1,), generator=g))
        a = int(torch.randint(3, (1,), generator=g))
        r = float(torch.randn(1, generator=g))
        term = bool(torch.rand(1, generator=g) < 0.1)
        row, row2 = ref.setdefault(s, [0.0] * 3), ref.setdefault(s2, [0.0] * 3)
        target = r + (0.0 if term else 0.98 * max(row2))
        row[a] = (1 - 0.2) * row[a] + 0.2 * target
        q(_transition(s, a, r, s2, term))
    for s, row in ref.items():
        assert q.table.q(torch.tensor([s]))[0].tolist() == pytest.approx(row, abs=1e-5)


def test_tabular_q_learns_the_rewarding_action_and_policy_decodes():
    from losses import TabularQLearning, action_levels

    q = TabularQLearning(n_actions=4)
    for _ in range(50):
        for a in range(4):
            q(_transition(0, a, 1.0 if a == 2 else 0.0, 0, True))
    pol = q.policy(action_levels(-3.0, 3.0, 2), n_cav=2)
    pol.greedy = True
    out = pol(TensorDict({"state_index": torch.tensor([[0]])}, [1]))
    assert out["action_index"].item() == 2
    # joint index 2 = digits (0, 1) -> (-3, +3)
    assert out["action"].tolist() == [[-3.0, 3.0]]
    pol.greedy = False
    for _ in range(10):
        pol.step(10_000)
    assert pol.eps == pytest.approx(0.05)


def test_tabular_q_through_the_env():
    from losses import TabularQLearning, action_levels
    from transforms import StateDiscretizer

    env = TransformedEnv(make_env("ring", batch_size=8, seed=0), StateDiscretizer(n_bins=20, heavy_tail=True))
    q = TabularQLearning(n_actions=20)
    pol = q.policy(action_levels(-3.0, 3.0, 20))
    batch = env.rollout(20, pol)
    out = q(batch)
    assert float(out["table_size"]) > 0
    assert torch.isfinite(out["loss_td"])
    with pytest.raises(ValueError, match="alpha"):
        TabularQLearning(n_actions=3, alpha=0.0)


# ----------------------------------------------------------------------------- DQN
@pytest.mark.parametrize("scenario", ["ring", "deeplcc"])
def test_make_dqn_reduces_td_loss_and_soft_updates(scenario):
    from losses import make_dqn

    torch.manual_seed(0)
    parts = make_dqn(make_env(scenario, batch_size=8, seed=0), num_bins=21, tau=0.01)
    with torch.no_grad():
        batch = parts.env.rollout(16, parts.policy).reshape(-1)
    online = parts.loss.value_network_params.clone()
    target_before = parts.loss.target_value_network_params.clone()
    opt = torch.optim.Adam(parts.loss.parameters(), lr=1e-3)
    first = float(parts.loss(batch)["loss"].detach())
    opt.zero_grad()
    parts.loss(batch)["loss"].backward()
    opt.step()
    parts.updater.step()
    # soft update: target <- (1 - tau) target + tau online (online after the step)
    new_online = parts.loss.value_network_params
    expected = target_before.apply(lambda t, o: 0.99 * t + 0.01 * o, new_online)
    got = parts.loss.target_value_network_params
    for k, v in expected.items(True, True):
        assert torch.allclose(got[k], v, atol=1e-6)
    for _ in range(100):
        opt.zero_grad()
        parts.loss(batch)["loss"].backward()
        opt.step()
    assert float(parts.loss(batch)["loss"].detach()) < first
    assert online is not None


def test_make_dqn_behind_the_safety_layer():
    from torchrl.envs import Compose
    from torchrl.envs.utils import check_env_specs

    from losses import make_dqn
    from transforms import NonNegativeReward, SafetyLayer

    parts = make_dqn(TransformedEnv(make_env("ring", batch_size=8, seed=0), Compose(SafetyLayer(), NonNegativeReward())))
    check_env_specs(parts.env)
    td = parts.env.rollout(30, parts.policy)
    assert not td["next", "collision"].any()
    assert torch.isfinite(parts.loss(td.reshape(-1))["loss"])
