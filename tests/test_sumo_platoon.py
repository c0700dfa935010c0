"""The DeeP-LCC platoon in SUMO (libsumo): spec parity with the torch platoon, SUMO's IDM
humans, bad backend options, Hankel data collected in SUMO. Real SUMO, no mocks."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torchrl.envs.utils import check_env_specs

pytest.importorskip("libsumo")

from mixed_traffic import make_env  # noqa: E402
from mixed_traffic.controllers.deeplcc.platoon import PlatoonConfig, gaps  # noqa: E402
from mixed_traffic.controllers.deeplcc.precollect import precollect  # noqa: E402
from mixed_traffic.envs.sumo_platoon import SumoPlatoon  # noqa: E402
from mixed_traffic.physics import IDMParams, idm_accel  # noqa: E402
from mixed_traffic.validation import ConfigError  # noqa: E402

IDM_CFG = PlatoonConfig(hdv_model="idm", accel_noise=0.0)


def _zero(td):
    return td.set("action", torch.zeros(1, 2))


def test_specs_equal_the_torch_platoon_and_pass_check_env_specs():
    sumo = make_env("platoon", backend="sumo", seed=0, episode_seconds=3.0)
    try:
        check_env_specs(sumo)
        ref = make_env("platoon", batch_size=1, seed=0, mismatch="idm", episode_seconds=3.0)
        assert sumo.observation_spec == ref.observation_spec
        assert sumo.action_spec == ref.action_spec
        assert sumo.reward_spec == ref.reward_spec
        assert sumo.done_spec == ref.done_spec
        td = sumo.rollout(sumo.scenario.max_steps + 2, _zero, break_when_any_done=False)
        assert bool(td["next", "truncated"][0, sumo.scenario.max_steps - 1])  # same episode length as torch
    finally:
        sumo.close()


def test_sumo_humans_are_the_deeplcc_idm_and_the_cavs_execute_the_command():
    sim = SumoPlatoon(IDM_CFG, seconds=2.0)
    try:
        pos, vel = sim.start(15.0, v_head=14.0)
        u = torch.tensor([[0.7, -1.3]])
        new_pos, new_vel, executed = sim.step(u, torch.tensor([13.5]))
    finally:
        sim.close()
    p = IDMParams.deeplcc()
    g = gaps(pos, IDM_CFG)
    acc = (new_vel - vel) / IDM_CFG.dt
    hdv = [i for i in range(1, 9) if i not in IDM_CFG.cav_indices]
    want = idm_accel(g[:, [i - 1 for i in hdv]], vel[:, hdv], vel[:, [i - 1 for i in hdv]], v0=p.v0, T=p.T, a=p.a,
                     b=p.b, delta=p.delta, s0=p.s0)
    assert torch.allclose(acc[:, hdv], want, atol=1e-6)  # vehicle 1 brakes behind the slower head
    assert float(acc[0, 1]) < -0.05
    assert torch.allclose(executed, u.double(), atol=1e-9)
    assert torch.allclose(acc[:, list(IDM_CFG.cav_indices)], u.double(), atol=1e-6)
    assert float(new_vel[0, 0]) == pytest.approx(13.5)
    # SUMO's Euler update: x' = x + v' dt
    assert torch.allclose(new_pos - pos, new_vel * IDM_CFG.dt, atol=1e-6)


def test_same_episode_as_the_torch_idm_platoon():
    """Same seed, same head profile; all-HDV-like zero CAV input: SUMO tracks the torch IDM platoon closely,
    and far more closely than the torch OVM platoon (the humans SUMO cannot run)."""

    def speeds(backend, mismatch):
        env = make_env("platoon", backend=backend, seed=2, mismatch=mismatch, accel_noise=0.0, profiles=["random5"],
                       episode_seconds=6.0)
        td = env.rollout(env.scenario.max_steps, _zero, break_when_any_done=False)
        env.close()
        return td["next", "traffic", "speed"][0]

    s_sumo, s_idm, s_ovm = speeds("sumo", "idm"), speeds("torch", "idm"), speeds("torch", "none")
    assert torch.equal(s_sumo[:, 0], s_idm[:, 0])  # the same head profile draw
    d_idm = (s_sumo - s_idm).abs().max()
    assert d_idm < 0.05
    assert (s_sumo - s_ovm).abs().max() > 10 * d_idm


@pytest.mark.parametrize("kw,field", [(dict(mismatch="none"), "mismatch"), (dict(mismatch="hetero_ovm"), "mismatch"),
                                      (dict(accel_noise=0.1), "accel_noise"), (dict(batch_size=2), "batch_size")])
def test_bad_backend_options_name_the_field(kw, field):
    with pytest.raises(ValueError, match=field):
        make_env("platoon", backend="sumo", **kw)


def test_sumo_errors_and_one_simulation_per_process():
    with pytest.raises(RuntimeError, match="no-such-option"):
        make_env("platoon", backend="sumo", sumo_args=["--no-such-option", "1"])
    with pytest.raises(ValueError, match="hdv_model"):
        SumoPlatoon(PlatoonConfig(), seconds=2.0)  # OVM humans
    env = make_env("platoon", backend="sumo", episode_seconds=3.0)
    try:
        with pytest.raises(RuntimeError, match="one per process"):
            SumoPlatoon(IDM_CFG, seconds=2.0)
    finally:
        env.close()
    sim = SumoPlatoon(IDM_CFG, seconds=2.0)  # free again after close
    sim.close()


def test_hankel_data_collected_in_sumo():
    gen = lambda: torch.Generator().manual_seed(4)  # noqa: E731
    sim = SumoPlatoon(IDM_CFG, seconds=300 * IDM_CFG.dt)
    try:
        [h] = precollect(IDM_CFG, T=300, t_ini=5, n=10, generator=gen(), simulator=sim)
    finally:
        sim.close()
    assert h.Up.shape == (10, 286) and h.Yp.shape == (50, 286) and h.Ef.shape == (10, 286)
    # persistently exciting: [U; E] of depth t_ini + n has full row rank
    assert np.linalg.matrix_rank(np.vstack([h.Up, h.Uf, h.Ep, h.Ef])) == 3 * 15
    # the same excitation in the torch IDM platoon gives close but not identical outputs
    [t] = precollect(IDM_CFG, T=300, t_ini=5, n=10, generator=gen())
    np.testing.assert_array_equal(h.Up, t.Up)
    np.testing.assert_array_equal(h.Ep, t.Ep)
    diff = np.abs(h.Yp - t.Yp).max()
    assert 0 < diff < 0.5


def test_mt_dataset_on_the_sumo_backend(tmp_path):
    from mixed_traffic.apps.dataset import run
    from mixed_traffic.controllers.deeplcc.dataset import DatasetConfig, load_dataset

    with pytest.raises(ConfigError, match="hdv_model"):
        DatasetConfig(backend="sumo").validate()
    with pytest.raises(ConfigError, match="accel_noise"):
        DatasetConfig(backend="sumo", hdv_model="idm").validate()
    with pytest.raises(ConfigError, match="backend"):
        DatasetConfig(backend="gazebo").validate()
    out = tmp_path / "sumo.npz"
    run(dict(backend="sumo", hdv_model="idm", accel_noise=0.0, episodes=1, episode_seconds=2.0, T=200, t_ini=5, n=10,
             workers=1, mix={"brake": 1.0}, brake_start=[0.5, 0.5], output=str(out), progress=False))
    d = load_dataset(out)
    assert d["uini"].shape == (35, 10) and d["Up"].shape == (1, 10, 186)
    info = __import__("json").loads(str(d["config"]))
    assert info["backend"] == "sumo" and not info["episodes_info"][0]["collision"]


def test_rlmpc_chain_runs_on_the_sumo_platoon_through_hydra(tmp_path):
    """``env.backend=sumo`` composes with the RLMPC experiment: the residual over the NNMPC drives SUMO's CAVs."""
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from mixed_traffic.config import compose
    from mixed_traffic.controllers.deeplcc.nnmpc import NNMPC
    from mixed_traffic.training.builders import check_collector_config, make_actor_critic, make_transformed_env

    torch.manual_seed(0)
    NNMPC().eval().save(tmp_path / "nnmpc.pt")
    over = ["experiment=deeplcc_rlmpc", f"transforms.residual_nnmpc.checkpoint={tmp_path / 'nnmpc.pt'}",
            "env.backend=sumo", "env.episode_seconds=2.0"]
    with pytest.raises(ConfigError, match="trainer.num_envs"):
        check_collector_config(compose(over))  # 64 rows would be 64 SUMO simulations in one process
    cfg = compose([*over, "trainer.num_envs=1"])
    check_collector_config(cfg)
    env = make_transformed_env(cfg, num_envs=1, seed=0)
    try:
        assert type(env.base_env).__name__ == "SumoPlatoonEnv"
        actor, _ = make_actor_critic(cfg, env)
        with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
            td = env.rollout(10, actor)
        res = td["next", "cav", "accel"] - td["next", "residual", "base_action"]
        clipped = td["next", "safety", "clipped"]
        assert float(res.abs().max()) <= 1.0 + 1e-5 and float(res[~clipped].abs().max()) > 0
    finally:
        env.close()


@pytest.mark.slow
def test_qp_on_sumo_data_is_no_worse_in_sumo_than_the_ovm_data_qp():
    from mixed_traffic.controllers.deeplcc.compare import build, rollout_metrics

    out, cache = {}, {}
    for c in ("qp", "qp_sumo"):
        env, pol = build(c, scenarios=("brake",), mismatch="idm", episodes=1, seed=10_000, safety=True, runs={},
                         nnmpc="", cache=cache, backend="sumo")
        try:
            out[c] = rollout_metrics(env, pol, ("brake",), 1)["brake"]
        finally:
            env.close()
    assert out["qp"]["collisions"] == 0 and out["qp_sumo"]["collisions"] == 0
    assert out["qp_sumo"]["cost"] <= out["qp"]["cost"]
