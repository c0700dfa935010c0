"""DeeP-LCC in TorchRL: the history transform, the QP policy module and the NNMPC network."""

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import check_env_specs

from mixed_traffic import make_env
from mixed_traffic.controllers.deeplcc.controller import deeplcc_policy
from mixed_traffic.controllers.deeplcc.nnmpc import NNMPC, TrainConfig, nnmpc_policy, offline_metrics, train_nnmpc
from mixed_traffic.controllers.deeplcc.platoon import PlatoonConfig
from mixed_traffic.controllers.deeplcc.precollect import precollect
from mixed_traffic.controllers.deeplcc.qp import DeepLCCSolver, QPParams
from transforms.deeplcc_history import DeePLCCHistory


def _env(batch=2, **kw):
    return TransformedEnv(make_env("deeplcc", batch_size=batch, seed=0, **kw), DeePLCCHistory())


def test_history_specs_and_window_alignment():
    env = _env()
    check_env_specs(env)
    td = env.rollout(25, break_when_any_done=False)
    speed, gap = td["traffic", "speed"], td["traffic", "gap"]
    y = torch.cat([speed[..., 1:] - 15.0, gap[..., [3, 6]] - 20.0], -1)  # measurement type 3
    k = 23  # after step k the window holds instants k-19 .. k
    np.testing.assert_allclose(td["next", "yini"][:, k].reshape(2, 20, 10), y[:, k - 19:k + 1], atol=1e-6)
    np.testing.assert_allclose(td["next", "uini"][:, k].reshape(2, 20, 2), td["next", "cav", "accel"][:, k - 19:k + 1])
    np.testing.assert_allclose(td["next", "eini"][:, k], speed[:, k - 19:k + 1, 0] - 15.0, atol=1e-6)
    # at reset: no past input, the current measurement repeated
    assert td["uini"][:, 0].abs().max() == 0
    np.testing.assert_allclose(td["yini"][:, 0].reshape(2, 20, 10), y[:, :1].expand(2, 20, 10), atol=1e-6)


def test_history_adaptive_v_star_reexpresses_the_window():
    env = TransformedEnv(make_env("deeplcc", batch_size=1, seed=0, profile="deeplcc_brake", profile_kwargs={"start": 0.5}),
                         DeePLCCHistory(adaptive_v_star=True))
    check_env_specs(env)
    td = env.rollout(40, break_when_any_done=False)
    speed, gap = td["traffic", "speed"][0], td["traffic", "gap"][0]
    k = 35  # after step k: window k-19 .. k, v* = mean head speed over k-18 .. k+1
    v_star = td["next", "traffic", "speed"][0, k - 19:k + 1, 0].mean()
    assert v_star < 14.0  # the head is braking
    y = torch.cat([speed[k - 19:k + 1, 1:] - v_star, gap[k - 19:k + 1][:, [3, 6]] - 20.0], -1)
    np.testing.assert_allclose(td["next", "yini"][0, k].reshape(20, 10), y, atol=1e-5)
    np.testing.assert_allclose(td["next", "eini"][0, k], speed[k - 19:k + 1, 0] - v_star, atol=1e-5)


def test_history_partial_reset_keeps_other_rows():
    env = _env()
    td = env.reset()
    for _ in range(5):
        td = env.step(td.set("action", torch.full((2, 2), 0.5)))["next"]
    before = td["uini"].clone()
    td.set("_reset", torch.tensor([[True], [False]]))
    out = env.reset(td)
    assert out["uini"][0].abs().max() == 0
    torch.testing.assert_close(out["uini"][1], before[1])


def test_history_validates_arguments():
    with pytest.raises(ValueError, match="t_ini"):
        DeePLCCHistory(t_ini=0)


@pytest.fixture(scope="module")
def solver():
    [h] = precollect(PlatoonConfig(), T=600, generator=torch.Generator().manual_seed(0))
    return DeepLCCSolver(h, QPParams.preset("dataset"))


def test_qp_policy_drives_the_env_without_collision(solver):
    env = _env(batch=2, episode_seconds=6.0, integration="euler_explicit")
    policy = deeplcc_policy(solver)
    td = env.rollout(100, policy, break_when_any_done=False)
    assert not td["next", "collision"].any()
    assert td["action"].min() >= -5.0 and td["action"].max() <= 2.0
    # the CAVs open their gap from the HDV equilibrium (15 m) toward s* = 20 m
    g = td["next", "cav", "gap"]
    assert (g[:, -1] > g[:, 0] + 1.0).all()
    assert sum(policy.module.statuses.values()) == 200 and policy.module.statuses.get("safe_action", 0) == 0


def test_nnmpc_bounds_checkpoint_and_policy(tmp_path):
    net = NNMPC()
    x = torch.randn(64, 260) * 10
    net.set_normalization(x)
    a = net.forward_flat(x * 100)
    assert a.min() >= -5.0 and a.max() <= 2.0
    assert sum(p.numel() for p in net.parameters()) == 260 * 256 + 256 + 256 * 128 + 128 + 128 * 2 + 2
    net.save(tmp_path / "n.pt", note="x")
    back = NNMPC.load(tmp_path / "n.pt")
    torch.testing.assert_close(back.x_std, net.x_std)
    torch.testing.assert_close(back.forward_flat(x), net.forward_flat(x))
    td = nnmpc_policy(back)(TensorDict({"uini": x[:, :40], "yini": x[:, 40:240], "eini": x[:, 240:]}, [64]))
    assert td["action"].shape == (64, 2)


def test_bc_training_learns_a_bounded_linear_map():
    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    x = rng.normal(size=(3000, 260)).astype(np.float32)
    W = rng.normal(size=(260, 2)) * 0.05
    y = np.clip(x @ W - 1.0, -5, 2).astype(np.float32)
    untrained = NNMPC()
    untrained.set_normalization(x)
    net, hist = train_nnmpc(x, y, TrainConfig(max_epochs=25, patience=5, batch_size=128))
    before, after = offline_metrics(untrained, x, y), offline_metrics(net, x, y)
    assert after["mse"] < 0.1 * before["mse"]
    assert hist["val"][-1] < hist["val"][0] and hist["epochs"] <= 25


def test_qp_gain_is_the_unconstrained_qp_and_seeds_the_residual_network(solver):
    from mixed_traffic.controllers.deeplcc.closed_loop import EVAL_SCENARIOS, QPController, run_closed_loop
    from mixed_traffic.controllers.deeplcc.nnmpc import qp_gain

    cfg = PlatoonConfig()
    v = EVAL_SCENARIOS["random5"].head_speed(cfg.dt, 1, torch.Generator().manual_seed(0))[:, :200]
    out = run_closed_loop(QPController([solver]), v, cfg, record=True, generator=torch.Generator().manual_seed(1))
    x = np.concatenate([out["uini"][0], out["yini"][0], out["eini"][0]], -1)
    K = qp_gain(solver)
    solver.reset_warm_start()
    free = [k for k in range(len(x)) if not solver.solve(x[k, :40], x[k, 40:240], x[k, 240:], warm_start=False).active]
    assert len(free) > 100
    np.testing.assert_allclose(x[free] @ K.T, out["u"][0][free], atol=1e-8)
    net = NNMPC(gain=K, residual=True)
    net.set_normalization(x)
    with torch.no_grad():
        a = net.forward_flat(torch.as_tensor(x, dtype=torch.float32)).numpy()
    np.testing.assert_allclose(a[free], out["u"][0][free], atol=2e-3)  # float32 network, exact map
