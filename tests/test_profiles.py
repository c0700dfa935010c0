import pytest
import torch

from mixed_traffic.profiles import make_profile


def speeds(prof, ts, params=None):
    params = prof.sample(1, torch.Generator().manual_seed(0)) if params is None else params
    return [float(prof.speed(torch.tensor([t], dtype=torch.float32), params)) for t in ts]


def test_deeplcc_brake_shape():
    v = speeds(make_profile("deeplcc_brake"), [0.0, 1.0, 2.0, 4.0, 7.0, 9.5, 12.0, 30.0])
    assert v == pytest.approx([15.0, 10.0, 5.0, 5.0, 5.0, 10.0, 15.0, 15.0])


def test_emergency_brake_shape():
    v = speeds(make_profile("emergency_brake"), [10.0, 50.0, 53.0, 60.0, 63.0, 68.0, 90.0])
    assert v == pytest.approx([15.0, 15.0, 2.0, 2.0, 2.0, 15.0, 15.0])


def test_random_steps_hold_for_period_and_stay_in_range():
    prof = make_profile("random_steps", v_init=10.0, horizon=100.0)
    p = prof.sample(64, torch.Generator().manual_seed(1))
    t = torch.full((64,), 0.0)
    assert torch.all(prof.speed(t, p) == 10.0)
    a, b = prof.speed(torch.full((64,), 15.0), p), prof.speed(torch.full((64,), 29.9), p)
    assert torch.equal(a, b)
    assert (a >= 5).all() and (a <= 20).all()
    assert a.unique().numel() > 50  # rows differ


def test_random_perturbation_amplitude_and_seed():
    prof = make_profile("random_perturbation", v_star=15.0, amplitude=3.0, horizon=50.0)
    g1, g2 = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    p1, p2 = prof.sample(8, g1), prof.sample(8, g2)
    assert torch.equal(p1, p2)
    t = torch.linspace(0, 50, 501)
    v = torch.stack([prof.speed(t, p1[i].expand(501, -1)) for i in range(8)])
    assert v.min() >= 12.0 - 1e-5 and v.max() <= 18.0 + 1e-5
    assert v.std() > 0.5


def test_sine_and_eudc_ranges():
    sine = make_profile("sine", v_star=15.0, amplitude=5.0, period=10.0)
    assert speeds(sine, [2.5])[0] == pytest.approx(20.0)
    eudc = make_profile("eudc")
    v = torch.tensor(speeds(eudc, list(range(0, 330, 2))))
    assert v.min() == pytest.approx(5.0) and v.max() == pytest.approx(20.0)


def test_bad_profile_names_and_arguments():
    with pytest.raises(ValueError, match="unknown name 'warp'"):
        make_profile("warp")
    with pytest.raises(ValueError, match="bad arguments"):
        make_profile("sine", amplitud=3.0)
