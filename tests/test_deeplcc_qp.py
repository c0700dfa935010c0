"""DeeP-LCC: Hankel matrices, pre-collection and the exact QP solver against cvxopt."""

import numpy as np
import pytest
import torch

from mixed_traffic.controllers.deeplcc.closed_loop import EVAL_SCENARIOS, QPController, run_closed_loop
from mixed_traffic.controllers.deeplcc.hankel import build_hankel, hankel_matrix
from mixed_traffic.controllers.deeplcc.platoon import PlatoonConfig
from mixed_traffic.controllers.deeplcc.precollect import collect_trajectories, precollect
from mixed_traffic.controllers.deeplcc.qp import DeepLCCSolver, QPParams, build_qp, solve_cvxopt


def test_hankel_matrix_columns_are_shifted_windows():
    x = np.arange(20.0).reshape(2, 10)
    H = hankel_matrix(x, 4)
    assert H.shape == (8, 7)
    for j in range(7):
        np.testing.assert_array_equal(H[:, j], x[:, j:j + 4].T.ravel())  # time-major stacking
    with pytest.raises(ValueError, match="depth"):
        hankel_matrix(x, 11)


def test_build_hankel_splits_past_and_future():
    rng = np.random.default_rng(0)
    ud, ed, yd = rng.normal(size=(2, 100)), rng.normal(size=100), rng.normal(size=(10, 100))
    h = build_hankel(ud, ed, yd, t_ini=5, n=7)
    assert (h.Up.shape, h.Uf.shape, h.Ep.shape, h.Ef.shape, h.Yp.shape, h.Yf.shape) == (
        (10, 89), (14, 89), (5, 89), (7, 89), (50, 89), (70, 89))
    np.testing.assert_array_equal(h.Uf[:, 3], ud[:, 8:15].T.ravel())
    np.testing.assert_array_equal(h.Ef[:, 0], ed[5:12])
    with pytest.raises(ValueError, match="T=100"):
        build_hankel(ud, ed, yd, t_ini=60, n=50)


def test_precollection_is_persistently_exciting_and_measured():
    cfg = PlatoonConfig()
    ud, ed, yd = collect_trajectories(cfg, 400, batch=2, generator=torch.Generator().manual_seed(1))
    assert ud.shape == (2, 2, 400) and ed.shape == (2, 1, 400) and yd.shape == (2, 10, 400)
    assert -1.0 <= ud.min() < -0.9 and 0.9 < ud.max() <= 1.0
    # the [U; E] Hankel matrix of depth t_ini + n has full row rank (persistent excitation)
    h = build_hankel(ud[0], ed[0], yd[0], 5, 10)
    assert np.linalg.matrix_rank(np.vstack([h.Up, h.Uf, h.Ep, h.Ef])) == 3 * 15
    # the trajectories are float32-exact (so float32 storage reproduces the QPs)
    for a in (ud, ed, yd):
        np.testing.assert_array_equal(a, a.astype(np.float32).astype(np.float64))
    # measurement type 3: the head speed error is e, the first outputs are follower speed errors
    assert np.abs(yd[0, :8]).max() < 10 and np.abs(yd[0, :8, 0]).max() < 1e-12


def test_presets_and_validation():
    assert (QPParams.preset("dataset").lambda_g, QPParams.preset("dataset").lambda_y) == (1.0, 1e3)
    assert (QPParams.preset("reference").lambda_g, QPParams.preset("reference").lambda_y) == (100.0, 1e4)
    with pytest.raises(ValueError, match="lambda_g"):
        QPParams(lambda_g=0.0)
    with pytest.raises(ValueError, match="spacing_min"):
        QPParams(spacing_min=25.0)
    with pytest.raises(ValueError, match="allowed"):
        QPParams.preset("fast")


@pytest.fixture(scope="module")
def small_problem():
    """A reduced-size Hankel set (T=600, t_ini=10, N=20) and closed-loop states of a hard brake."""
    cfg = PlatoonConfig()
    [h] = precollect(cfg, T=600, t_ini=10, n=20, generator=torch.Generator().manual_seed(3))
    solver = DeepLCCSolver(h, QPParams.preset("reference"))
    v = EVAL_SCENARIOS["brake"].head_speed(cfg.dt)[:, :300]
    out = run_closed_loop(QPController([solver]), v, cfg, t_ini=10, adaptive_v_star=True, record=True,
                          generator=torch.Generator().manual_seed(4))
    return h, solver, out


def test_active_set_matches_cvxopt_on_closed_loop_states(small_problem):
    h, solver, out = small_problem
    qp = build_qp(h, solver.params)
    n_active, checked = 0, 0
    for k in range(0, out["u"].shape[1], 29):
        args = out["uini"][0, k], out["yini"][0, k], out["eini"][0, k]
        res = solver.solve(*args, warm_start=False)
        ref, status = solve_cvxopt(qp, *args, reltol=1e-16)
        assert status == "optimal"
        np.testing.assert_allclose(res.u_all, ref, atol=1e-4)
        n_active += bool(res.active)
        checked += 1
    assert checked >= 8 and n_active >= 1  # some instances have binding constraints


def test_warm_start_gives_the_same_answer_with_fewer_iterations(small_problem):
    _, solver, out = small_problem
    ks = range(out["u"].shape[1])
    cold = [solver.solve(out["uini"][0, k], out["yini"][0, k], out["eini"][0, k], warm_start=False) for k in ks]
    solver.reset_warm_start()
    warm = [solver.solve(out["uini"][0, k], out["yini"][0, k], out["eini"][0, k]) for k in ks]
    np.testing.assert_allclose(np.stack([r.u for r in warm]), np.stack([r.u for r in cold]), atol=1e-9)
    assert sum(r.iterations for r in warm) <= sum(r.iterations for r in cold)
    assert max(len(r.active) for r in cold) >= 1


def test_fallbacks_are_counted_and_safe(small_problem):
    h, _, out = small_problem
    k = int(np.argmin(out["u"][0, :, 0]))  # the hardest braking instant
    args = out["uini"][0, k], out["yini"][0, k], out["eini"][0, k]
    exact = DeepLCCSolver(h, QPParams.preset("reference")).solve(*args)
    crippled = DeepLCCSolver(h, QPParams.preset("reference"), max_iter=0)  # active-set loop cannot finish
    res = crippled.solve(*args)
    assert res.status == "dual_fallback" and crippled.stats.dual_fallbacks == 1
    np.testing.assert_allclose(res.u, exact.u, atol=1e-4)
    crippled._dual_fallback = lambda a0: None  # the dual solve fails too
    res = crippled.solve(*args)
    assert res.status == "safe_action" and crippled.stats.safe_actions == 1
    assert np.all(res.u >= -5.0) and np.all(res.u <= 2.0)


def test_qp_controller_beats_no_control_on_brake(small_problem):
    _, solver, out = small_problem
    cfg = PlatoonConfig()
    v = EVAL_SCENARIOS["brake"].head_speed(cfg.dt)[:, :300]
    zero = run_closed_loop(lambda u, y, e: np.zeros((len(u), 2)), v, cfg, t_ini=10, adaptive_v_star=True,
                           generator=torch.Generator().manual_seed(4))
    assert not out["collisions"][0]
    assert out["cost"][0] < 0.5 * zero["cost"][0]
    assert out["min_gap"][0] > zero["min_gap"][0]
