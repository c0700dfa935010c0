"""DeeP-LCC closed loop: metrics, model switch (OVM/IDM), the five evaluation scenarios."""

import numpy as np
import pytest
import torch

from mixed_traffic.controllers.deeplcc.closed_loop import (
    EVAL_SCENARIOS,
    QPController,
    evaluate,
    fuel_rate,
    head_speed_profile,
    run_closed_loop,
)
from mixed_traffic.controllers.deeplcc.platoon import PlatoonConfig, init_state, measure, step
from mixed_traffic.controllers.deeplcc.precollect import precollect
from mixed_traffic.controllers.deeplcc.qp import DeepLCCSolver, QPParams


def zero(uini, yini, eini):
    return np.zeros((len(uini), 2))


def test_fuel_model_values():
    # R = 0.333 + 0.00108 * 15^2 = 0.576; F = 0.444 + 0.09 * 0.576 * 15
    np.testing.assert_allclose(fuel_rate(np.array(15.0), np.array(0.0)), 0.444 + 0.09 * 0.576 * 15)
    assert fuel_rate(np.array(15.0), np.array(-2.0)) == 0.444  # R <= 0: idling rate
    assert fuel_rate(np.array(15.0), np.array(1.0)) > fuel_rate(np.array(15.0), np.array(0.5))


@pytest.mark.parametrize("model", ["ovm", "idm"])
def test_equilibrium_is_steady_and_cost_is_the_spacing_offset(model):
    cfg = PlatoonConfig(hdv_model=model, accel_noise=0.0)
    v = torch.full((1, 201), 15.0, dtype=torch.float64)
    out = run_closed_loop(zero, v, cfg, t_ini=20, record=True)
    np.testing.assert_allclose(out["speeds"][0, :200], 15.0, atol=1e-9)
    gap = cfg.equilibrium_gap(15.0)
    assert (model == "ovm" and abs(gap - 15.0) < 1e-9) or (model == "idm" and gap > 20.0)
    # stage cost: weight_s * sum over 2 CAVs of (gap - s*)^2, for 180 controlled steps
    np.testing.assert_allclose(out["cost"][0], 180 * 0.5 * 2 * (gap - 20.0) ** 2, rtol=1e-9)
    assert out["velocity_error"][0] < 1e-12 and not out["collisions"][0]


def test_measurement_type_3_and_emergency_override():
    cfg = PlatoonConfig(accel_noise=0.0)
    pos, vel = init_state(1, cfg)
    vel[0, 4] = 16.0
    y = measure(pos, vel, cfg)
    np.testing.assert_allclose(y[0, :8], [0, 0, 0, 1, 0, 0, 0, 0])
    np.testing.assert_allclose(y[0, 8:], [-5.0, -5.0])  # CAV gaps 15 m vs s* = 20 m
    pos[0, 3] = pos[0, 2] - 5.0 - 1.0  # CAV 3 only 1 m behind its leader and closing at 5 m/s
    vel[0, 3] = 20.0
    _, _, executed = step(pos, vel, torch.tensor([[2.0, 2.0]]), torch.tensor([15.0]), cfg)
    np.testing.assert_allclose(executed[0], [-5.0, 2.0], atol=1e-9)  # the emergency rule brakes CAV 3 only


def test_profiles_of_the_evaluation_scenarios():
    dt = 0.05
    v = EVAL_SCENARIOS["brake"].head_speed(dt)
    assert v.shape == (1, 801) and abs(float(v.min()) - 5.0) < 1e-6
    v = head_speed_profile("random_perturbation", 40.0, dt, 2, torch.Generator().manual_seed(0), amplitude=5.0)
    assert 10.0 - 1e-6 <= float(v.min()) < 12 and 18 < float(v.max()) <= 20.0 + 1e-6
    assert EVAL_SCENARIOS["nedc"].adaptive_v_star and set(EVAL_SCENARIOS) == {"random1", "random5", "brake", "sine", "nedc"}


@pytest.mark.slow
def test_qp_on_the_five_scenarios_is_collision_free_and_beats_no_control():
    cfg = PlatoonConfig()
    [h] = precollect(cfg, generator=torch.Generator().manual_seed(12345))
    qp = evaluate(QPController([DeepLCCSolver(h, QPParams.preset("dataset"))]), cfg)
    none = evaluate(zero, cfg)
    for name in EVAL_SCENARIOS:
        assert qp[name]["collisions"] == 0.0, name
    assert qp["brake"]["cost"] < 0.1 * none["brake"]["cost"]
    assert qp["random1"]["cost"] < none["random1"]["cost"]
