"""SafetyLayer: property tests of the pure math, then behaviour through the env."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import check_env_specs

from mixed_traffic import make_env
from transforms import SafetyLayer
from transforms.safety_layer import (
    braking_distance,
    head_accel_lower,
    min_future_gap,
    safe_accel_upper,
    safe_action,
    scenario_leader_brake,
)

D64 = torch.float64
PROP = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def t(x):
    return torch.tensor([float(x)], dtype=D64)


def brute_min_gap(gap, v, vl, dt, b, bl):
    """Reference: simulate both braking step by step (ego at min(b, bl)), min over all gaps."""
    b = min(b, bl)
    lo = gap
    while v > 0 or vl > 0:
        v = max(v - b * dt, 0.0)
        vl = max(vl - bl * dt, 0.0)
        gap += (vl - v) * dt
        lo = min(lo, gap)
    return lo


def brute_braking_distance(v, b, dt):
    d = 0.0
    while v > 0:
        v = max(v - b * dt, 0.0)
        d += v * dt
    return d


dts = st.sampled_from([0.05, 0.1, 0.2, 0.5])
speeds = st.floats(0.0, 40.0)
brakes = st.floats(1.0, 9.0)


def test_stopping_rule_gradient_is_the_slope_of_its_segment():
    """The stopping rule's speed bound is piecewise linear in the distance budget c: ``u = (c / dt + h m (m + 1) / 2)
    / (m + 1)`` on segment m. Its segment index is piecewise constant and kept out of the graph, so the gradient
    must be the active segment's slope ``1 / (dt (m + 1))`` (what analytic policy gradients differentiate)."""
    from transforms.safety_layer import _max_speed_within_distance

    dt, b = 0.1, torch.tensor(3.0, dtype=D64)
    c = torch.linspace(0.05, 60.0, 500, dtype=D64, requires_grad=True)
    u = _max_speed_within_distance(c, b, dt)
    u.sum().backward()
    m = torch.floor(u.detach() / (b * dt))  # u lies on segment m: m h <= u < (m + 1) h
    assert torch.allclose(c.grad, 1.0 / (dt * (m + 1.0)))
    d = 1e-7  # and the slope of the function itself, by central differences
    fd = (_max_speed_within_distance(c.detach() + d, b, dt) - _max_speed_within_distance(c.detach() - d, b, dt)) / (2 * d)
    kink = (u.detach() / (b * dt) - m) < 1e-4  # at a kink the two sides' slopes differ
    assert torch.allclose(c.grad[~kink], fd[~kink], rtol=1e-5)


@PROP
@given(v=speeds, b=brakes, dt=dts)
def test_braking_distance_matches_simulation(v, b, dt):
    assert float(braking_distance(t(v), b, dt)) == pytest.approx(brute_braking_distance(v, b, dt), abs=1e-9)


@PROP
@given(gap=st.floats(-5.0, 200.0), v=speeds, vl=speeds, b=brakes, bl=brakes, dt=dts)
def test_min_future_gap_matches_simulation(gap, v, vl, b, bl, dt):
    got = float(min_future_gap(t(gap), t(v), t(vl), dt=dt, brake=b, leader_brake=bl))
    assert got == pytest.approx(brute_min_gap(gap, v, vl, dt, b, bl), abs=1e-7)


@PROP
@given(v=speeds, vl=speeds, b=brakes, bl=brakes, dt=dts, margin=st.floats(0.0, 50.0),
       a_req=st.floats(-20.0, 20.0), a_lead=st.floats(0.0, 1.0), s_min=st.floats(1.0, 10.0),
       a_max=st.floats(0.5, 4.0), head_gap_extra=st.floats(0.0, 100.0), head_speed=speeds,
       use_smax=st.booleans())
def test_invariant_is_kept_for_any_leader_within_its_bound(v, vl, b, bl, dt, margin, a_req, a_lead, s_min,
                                                           a_max, head_gap_extra, head_speed, use_smax):
    # a state in the safe set: every future gap >= s_min if both brake
    bb = min(b, bl)
    gap = s_min + max(0.0, brute_braking_distance(v, bb, dt) - brute_braking_distance(vl, bl, dt)) + margin
    assert brute_min_gap(gap, v, vl, dt, b, bl) >= s_min - 1e-9
    a = safe_action(t(a_req), gap=t(gap), speed=t(v), leader_speed=t(vl), head_gap=t(gap + head_gap_extra),
                    head_speed=t(head_speed), low=-b, high=a_max, dt=dt, s_min=s_min,
                    s_max=s_min + 20.0 if use_smax else None, leader_brake=bl)
    a = float(a)
    assert -b - 1e-12 <= a <= a_max + 1e-12
    # the leader does anything within its bound: accel in [-bl, 3]
    a_l = -bl + a_lead * (3.0 + bl)
    v1 = max(v + a * dt, 0.0)
    vl1 = max(vl + a_l * dt, 0.0)
    gap1 = gap + (vl1 - v1) * dt
    assert gap1 >= s_min - 1e-7
    assert brute_min_gap(gap1, v1, vl1, dt, b, bl) >= s_min - 1e-7


def test_multi_step_random_leader_never_below_s_min():
    g = torch.Generator().manual_seed(0)
    n, dt, s_min, b, bl = 4096, 0.1, 5.0, 3.0, 3.0
    gap = torch.full((n,), 30.0, dtype=D64)
    v = torch.rand(n, generator=g, dtype=D64) * 5
    vl = torch.rand(n, generator=g, dtype=D64) * 30
    lowest = math.inf
    for _ in range(300):
        req = (torch.rand(n, generator=g, dtype=D64) * 6 - 3) + 3.0  # mostly max accel
        a = safe_action(req, gap=gap, speed=v, leader_speed=vl, head_gap=None, head_speed=None,
                        low=-b, high=3.0, dt=dt, s_min=s_min, s_max=None, leader_brake=bl)
        a_l = torch.where(torch.rand(n, generator=g) < 0.5, torch.full_like(vl, -bl),
                          torch.rand(n, generator=g, dtype=D64) * 5 - bl)
        v = (v + a * dt).clamp_min(0)
        vl = (vl + a_l * dt).clamp_min(0)
        gap = gap + (vl - v) * dt
        lowest = min(lowest, float(gap.min()))
    assert lowest >= s_min - 1e-9


@PROP
@given(gap=st.floats(0.0, 100.0), v=speeds, vl=speeds, head_gap=st.floats(0.0, 300.0), head_speed=speeds,
       a_req=st.floats(-10.0, 10.0), mode=st.sampled_from(["stopping", "one_step"]))
def test_s_min_wins_every_conflict(gap, v, vl, head_gap, head_speed, a_req, mode):
    kw = dict(gap=t(gap), speed=t(v), leader_speed=t(vl), head_gap=t(head_gap), head_speed=t(head_speed),
              low=-3.0, high=3.0, dt=0.1)
    a = float(safe_action(t(a_req), s_min=5.0, s_max=40.0, mode=mode, **kw))
    only_min = float(safe_action(t(a_req), s_min=5.0, s_max=None, mode=mode, **kw))
    if mode == "stopping":
        a_hi = float(safe_accel_upper(t(gap), t(v), t(vl), s_min=5.0, dt=0.1, brake=3.0, leader_brake=3.0))
    else:
        a_hi = 2.0 * (gap + (vl - v) * 0.1 - 5.0) / 0.01
    a_lo = float(head_accel_lower(t(head_gap), t(v), t(head_speed), s_max=40.0, dt=0.1, mode=mode, accel_max=3.0))
    # never above what s_min allows (unless even full braking is above it)
    assert a <= max(a_hi, -3.0) + 1e-9
    if a_lo > a_hi:  # conflict: the s_min bound (or full braking) decides
        assert a == pytest.approx(min(max(a_hi, -3.0), 3.0), abs=1e-9)
    # s_max can only raise the s_min-only action
    assert a >= only_min - 1e-9


finite = st.floats(-1e6, 1e6)


@PROP
@given(a_req=finite, gap=finite, v=finite, vl=finite, head_gap=finite, head_speed=finite,
       mode=st.sampled_from(["stopping", "one_step"]), dtype=st.sampled_from([torch.float32, torch.float64]))
def test_no_nan_for_finite_inputs(a_req, gap, v, vl, head_gap, head_speed, mode, dtype):
    def tt(x):
        return torch.tensor([x], dtype=dtype)

    a = safe_action(tt(a_req), gap=tt(gap), speed=tt(v), leader_speed=tt(vl), head_gap=tt(head_gap),
                    head_speed=tt(head_speed), low=-3.0, high=3.0, dt=0.1, s_min=5.0, s_max=40.0, mode=mode)
    assert torch.isfinite(a).all()
    assert -3.0 <= float(a) <= 3.0


@PROP
@given(a_req=st.floats(-3.0, 3.0), v=speeds, vl=speeds, gap=st.floats(0.0, 100.0),
       head_gap=st.floats(0.0, 100.0), head_speed=speeds, mode=st.sampled_from(["stopping", "one_step"]))
def test_identity_when_no_constraint_binds(a_req, v, vl, gap, head_gap, head_speed, mode):
    kw = dict(gap=t(gap), speed=t(v), leader_speed=t(vl), head_gap=t(head_gap), head_speed=t(head_speed),
              low=-3.0, high=3.0, dt=0.1, s_min=5.0, s_max=40.0, mode=mode)
    if mode == "stopping":
        a_hi = float(safe_accel_upper(t(gap), t(v), t(vl), s_min=5.0, dt=0.1, brake=3.0, leader_brake=3.0))
    else:
        a_hi = 2.0 * (gap + (vl - v) * 0.1 - 5.0) / 0.01
    a_lo = float(head_accel_lower(t(head_gap), t(v), t(head_speed), s_max=40.0, dt=0.1, mode=mode, accel_max=3.0))
    a = float(safe_action(t(a_req), **kw))
    if a_lo <= a_req <= a_hi:
        assert a == a_req
    # and both constraints switched off: always the identity within bounds
    off = dict(kw, s_min=None, s_max=None)
    assert float(safe_action(t(a_req), **off)) == a_req


def test_one_step_mode_reproduces_the_original_rule():
    gap, v, vl, dt = t(6.0), t(10.0), t(8.0), 0.1
    a = safe_action(t(500.0), gap=gap, speed=v, leader_speed=vl, head_gap=None, head_speed=None, low=-1e9,
                    high=1e9, dt=dt, s_min=5.0, s_max=None, mode="one_step")
    predicted = 6.0 + (8.0 - 10.0) * dt - 0.5 * float(a) * dt**2
    assert predicted == pytest.approx(5.0)


def test_invalid_arguments_name_the_field():
    with pytest.raises(ValueError, match="mode"):
        SafetyLayer(mode="bogus")
    with pytest.raises(ValueError, match="s_min"):
        SafetyLayer(s_min=50.0, s_max=40.0)
    with pytest.raises(ValueError, match="leader_brake"):
        SafetyLayer(leader_brake=-1.0)
    with pytest.raises(ValueError, match="dt"):
        SafetyLayer(dt=0.0)
    with pytest.raises(ValueError, match="ego_brake"):
        SafetyLayer(ego_brake=0.0)


@PROP
@given(v=speeds, vl=speeds, e=st.floats(3.0, 9.0), bl=brakes, dt=dts, margin=st.floats(0.0, 20.0),
       a_req=st.floats(-20.0, 20.0), a_lead=st.floats(0.0, 1.0))
def test_emergency_braking_keeps_the_invariant_and_goes_below_low_only_for_s_min(v, vl, e, bl, dt, margin,
                                                                                     a_req, a_lead):
    # the action range is [-3, 3]; the layer may brake at up to e (>= 3) and assumes the CAV does
    s_min, b = 2.0, min(e, bl)
    gap = s_min + max(0.0, brute_braking_distance(v, b, dt) - brute_braking_distance(vl, bl, dt)) + margin
    kw = dict(gap=t(gap), speed=t(v), leader_speed=t(vl), head_gap=None, head_speed=None, low=-3.0, high=3.0,
              dt=dt, s_min=s_min, s_max=None, leader_brake=bl)
    a = float(safe_action(t(a_req), ego_brake=e, **kw))
    assert -e - 1e-12 <= a <= 3.0 + 1e-12
    # the command within the action range, lowered to the s_min bound that assumes braking at e,
    # never below -e: the only way below -3 is that bound
    a_hi = float(safe_accel_upper(t(gap), t(v), t(vl), s_min=s_min, dt=dt, brake=e, leader_brake=bl))
    assert a == pytest.approx(max(min(max(a_req, -3.0), 3.0, a_hi), -e), abs=1e-9)
    a_l = -bl + a_lead * (3.0 + bl)
    v1, vl1 = max(v + a * dt, 0.0), max(vl + a_l * dt, 0.0)
    gap1 = gap + (vl1 - v1) * dt
    assert gap1 >= s_min - 1e-7
    assert brute_min_gap(gap1, v1, vl1, dt, e, bl) >= s_min - 1e-7


def _full_throttle(env):
    high = env.action_spec.high.clone()
    return lambda td: td.set("action", high.clone())


def test_emergency_braking_through_the_env():
    # the env executes the layer's emergency braking; the action range (and a raw command) stays [-3, 3]
    base = make_env("ring_wave", batch_size=2, seed=0, cav_emergency_decel=9.0)
    assert base.action_spec.space.low.min() == -3.0
    td = base.reset()
    v0 = td["cav", "speed"].clone()
    td = base.step(td.set("action", torch.full_like(v0, -8.0)))
    assert torch.allclose(td["next", "cav", "speed"], (v0 - 0.8).clamp_min(0.0), atol=1e-5)
    plain = make_env("ring_wave", batch_size=2, seed=0)
    td = plain.reset()
    td = plain.step(td.set("action", torch.full_like(v0, -8.0)))
    assert torch.allclose(td["next", "cav", "speed"], (v0 - 0.3).clamp_min(0.0), atol=1e-5)
    # a CAV that always asks for full throttle behind humans: the layer reads the scenario's braking,
    # lets it follow closer than with the action range's 3 m/s^2, and it never collides
    gaps = {}
    for decel in (None, 9.0):
        env = TransformedEnv(make_env("ring_wave", batch_size=8, seed=1, cav_emergency_decel=decel),
                             SafetyLayer(s_min=2.0, s_max=None))
        ro = env.rollout(1500, _full_throttle(env), break_when_any_done=False)
        assert not ro["next", "collision"].any()
        assert ro["next", "cav", "gap"].min() >= 2.0 - 1e-3
        assert ro["next", "cav", "accel"].min() >= (-9.0 if decel else -3.0) - 1e-4
        gaps[decel] = float(ro["next", "cav", "gap"][:, 500:].mean())
    assert gaps[9.0] < gaps[None] - 0.5
    # two CAVs in a row: the follower's layer assumes its CAV leader may brake as hard as that one's layer can
    sc = make_env("ring_wave", batch_size=1, seed=0, cav_indices=[0, 1], cav_emergency_decel=9.0).scenario
    assert scenario_leader_brake(sc)[1] == 9.0
    env = TransformedEnv(make_env("ring_wave", batch_size=8, seed=2, cav_indices=[0, 1], cav_emergency_decel=9.0),
                         SafetyLayer(s_min=2.0, s_max=None))
    ro = env.rollout(1500, _full_throttle(env), break_when_any_done=False)
    assert not ro["next", "collision"].any() and ro["next", "cav", "gap"].min() >= 2.0 - 1e-3


def test_emergency_braking_field_is_checked():
    from mixed_traffic.scenarios import get_scenario

    with pytest.raises(ValueError, match="cav_emergency_decel"):
        get_scenario("ring_wave", cav_emergency_decel=2.0)  # below the action range's 3 m/s^2
    assert get_scenario("ring_wave", cav_emergency_decel=9.0).cav_exec_bounds == (-9.0, 3.0)
    assert get_scenario("ring_wave").cav_exec_bounds == (-3.0, 3.0)


# ----------------------------------------------------------------------------- through the env
@pytest.mark.parametrize("scenario", ["ring", "deeplcc"])
@pytest.mark.parametrize("mode", ["stopping", "one_step"])
def test_check_env_specs(scenario, mode):
    env = TransformedEnv(make_env(scenario, batch_size=3, seed=0), SafetyLayer(mode=mode))
    check_env_specs(env)


def test_reads_dt_and_leader_brake_from_env():
    env = TransformedEnv(make_env("deeplcc", batch_size=2, seed=0), SafetyLayer())
    env.reset()
    sl = env.transform
    assert sl.dt == pytest.approx(0.05)
    # deeplcc: CAVs 3 and 6 follow OVM human drivers (a_min = -5)
    low = torch.tensor([-5.0, -5.0])
    assert sl._leader_brake_tensor(low).tolist() == [5.0, 5.0]


def _max_accel_run(scenario, batch, steps, seed=0):
    env = TransformedEnv(make_env(scenario, batch_size=batch, seed=seed), SafetyLayer())
    high = env.action_spec.high.clone()
    return env.rollout(steps, lambda td: td.set("action", high.clone()), break_when_any_done=False)


@pytest.mark.parametrize("scenario", ["ring", "deeplcc"])
def test_max_accel_policy_never_collides_short(scenario):
    td = _max_accel_run(scenario, 32, 400)
    assert not td["next", "collision"].any()
    assert td["next", "cav", "gap"].min() >= 5.0 - 1e-3
    clip_rate = td["next", "safety", "clipped"].float().mean()
    assert 0.0 < clip_rate <= 1.0
    # the recorded delta is executed minus commanded
    delta = td["next", "safety", "delta"]
    assert (delta <= 1e-6).all()  # clipping a max-accel command can only lower it
    assert torch.equal(delta != 0, td["next", "safety", "clipped"])


@pytest.mark.slow
def test_max_accel_policy_5000_steps_256_rows_zero_collisions():
    td = _max_accel_run("ring", 256, 5000)
    assert int(td["next", "collision"].sum()) == 0
    assert td["next", "cav", "gap"].min() >= 5.0 - 1e-3


def test_braking_policy_stays_within_s_max_of_the_head():
    s_max = 40.0
    env = TransformedEnv(make_env("ring", batch_size=32, seed=1), SafetyLayer(s_min=5.0, s_max=s_max))
    low = env.action_spec.low.clone()
    td = env.rollout(1500, lambda td: td.set("action", low.clone()), break_when_any_done=False)
    head_gap = td["next", "cav", "head_gap"].squeeze(-1)  # [B, T]
    # the ring starts with the head 73 m ahead: from the first time the CAV is within
    # s_max, the layer keeps it there (bounds allow: CAV +3 m/s^2 vs head +2 m/s^2)
    inside = head_gap <= s_max
    assert inside.any(-1).all()
    first = inside.float().argmax(-1)
    for row in range(head_gap.shape[0]):
        assert head_gap[row, first[row]:].max() <= s_max + 1.0
    assert not td["next", "collision"].any()


@PROP
@given(v=speeds, vh=speeds, dt=dts, a_max=st.floats(0.5, 4.0), slack=st.floats(0.0, 30.0),
       a_req=st.floats(-10.0, 10.0), s_max=st.floats(20.0, 60.0))
def test_s_max_invariant_is_kept_when_the_head_holds_its_speed(v, vh, dt, a_max, slack, a_req, s_max):
    # a state from which full acceleration closes the speed deficit within s_max
    grow = brute_braking_distance(max(vh - v, 0.0), a_max, dt)
    h = s_max - grow - slack
    a = float(safe_action(t(a_req), gap=t(1e3), speed=t(v), leader_speed=t(vh), head_gap=t(h),
                          head_speed=t(vh), low=-3.0, high=a_max, dt=dt, s_min=None, s_max=s_max))
    v1 = max(v + a * dt, 0.0)
    h1 = h + (vh - v1) * dt
    assert h1 <= s_max + 1e-7
    assert h1 + brute_braking_distance(max(vh - v1, 0.0), a_max, dt) <= s_max + 1e-7


@PROP
@given(v=speeds, vh=speeds, dt=dts, beyond=st.floats(0.1, 60.0), a_req=st.floats(-3.0, 3.0))
def test_hold_beyond_s_max_keeps_the_gap_from_growing_without_a_burst(v, vh, dt, beyond, a_req):
    # a head gap already beyond s_max: "push" demands full throttle, "hold" only that the
    # gap does not grow (the CAV keeps at least the head's speed), the command otherwise
    s_max, h = 40.0, 40.0 + beyond
    kw = dict(gap=t(1e3), speed=t(v), leader_speed=t(vh), head_gap=t(h), head_speed=t(vh), low=-3.0,
              high=3.0, dt=dt, s_min=None, s_max=s_max)
    held = float(safe_action(t(a_req), beyond_s_max="hold", **kw))
    pushed = float(safe_action(t(a_req), beyond_s_max="push", **kw))
    assert pushed >= held - 1e-12  # push demands at least as much as hold
    need = min(max((vh - v) / dt, a_req), 3.0)  # keep the head's speed, else the command
    assert held == pytest.approx(need, abs=1e-9)
    v1 = max(v + held * dt, 0.0)
    if (vh - v) / dt <= 3.0:
        assert h + (vh - v1) * dt <= h + 1e-9


def test_hold_beyond_s_max_through_the_env_leaves_a_long_start_to_the_command():
    """From the ring's 73 m start a zero command is executed as is under "hold" (the head keeps
    its speed at first), while "push" accelerates at the bound; inside s_max both act alike."""
    def first_accel(beyond):
        env = TransformedEnv(make_env("ring", batch_size=2, seed=0),
                             SafetyLayer(s_min=5.0, s_max=38.0, beyond_s_max=beyond))
        td = env.rollout(3, lambda td: td.set("action", torch.zeros_like(env.action_spec.low)))
        assert float(td["cav", "head_gap"].min()) > 38.0
        return td["next", "cav", "accel"][:, 0]

    assert torch.allclose(first_accel("push"), torch.tensor(3.0), atol=1e-4)
    assert float(first_accel("hold").abs().max()) < 1e-4
    with pytest.raises(ValueError, match="beyond_s_max='back'.*allowed"):
        SafetyLayer(beyond_s_max="back")


def test_hold_seconds_leaves_a_long_start_to_the_command_then_pushes():
    """``hold_seconds``: from the 73 m start a zero command is executed as is for the first 5 s
    (the gap is only held), then the layer pushes at the bound as ``"push"`` does from t = 0;
    s_min still wins throughout (the head brakes hard in emergency_brake)."""
    def run(hold):
        env = TransformedEnv(make_env("ring", batch_size=2, seed=0), SafetyLayer(s_min=5.0, s_max=38.0, hold_seconds=hold))
        return env.rollout(100, lambda td: td.set("action", torch.zeros_like(env.action_spec.low)))

    held, pushed = run(5.0), run(0.0)
    t, accel = held["traffic", "time"][..., 0], held["next", "cav", "accel"][..., 0]
    assert float(accel[t < 5.0 - 1e-6].abs().max()) < 1e-4  # held: the command runs
    assert torch.allclose(accel[:, 50], torch.tensor(3.0), atol=1e-4)  # then pushed at the bound
    assert torch.allclose(pushed["next", "cav", "accel"][:, 0], torch.tensor(3.0), atol=1e-4)
    ramp = TransformedEnv(make_env("ring", batch_size=2, seed=0),
                          SafetyLayer(s_min=5.0, s_max=38.0, beyond_s_max="ramp", hold_seconds=5.0))
    td = ramp.rollout(60, lambda td: td.set("action", torch.zeros_like(ramp.action_spec.low)))
    a = td["next", "cav", "accel"][..., 0]
    assert float(a[:, :50].abs().max()) < 1e-4 and float(a[:, 50:].max()) <= 1.0 * 10 * 0.1 + 1e-4  # then ramps
    assert float(a[:, 59].min()) > 0.5
    # the head's step 50-53 s braking to 2 m/s: a CAV commanded full throttle keeps s_min
    env = TransformedEnv(make_env("ring", batch_size=2, seed=0, profile="emergency_brake", profile_kwargs={}),
                         SafetyLayer(s_min=5.0, s_max=38.0, hold_seconds=1e3))
    td = env.rollout(800, lambda td: td.set("action", torch.full_like(env.action_spec.low, 3.0)))
    assert float(td["next", "cav", "gap"].min()) >= 5.0 - 1e-4 and not td["next", "collision"].any()
    with pytest.raises(ValueError, match="hold_seconds=-1.0 is invalid; allowed: >= 0"):
        SafetyLayer(hold_seconds=-1.0)


def test_hold_seconds_behind_a_batch_of_one_row_envs():
    """Behind a ``SerialEnv`` / ``ParallelEnv`` of one-row rings (batch ``[workers, 1]``, as the SUMO evaluation
    builds it) the held start executes each worker's command with the action's shape, as the one-row env does."""
    from functools import partial

    from torchrl.envs import SerialEnv

    def layer():
        return SafetyLayer(s_min=5.0, s_max=38.0, hold_seconds=5.0)

    base = SerialEnv(2, [partial(make_env, "ring", batch_size=1, seed=s) for s in (0, 1)])
    sc = make_env("ring", batch_size=1, seed=0).scenario
    base.scenario, base.dt = sc, sc.dt
    env = TransformedEnv(base, layer())
    td = env.rollout(60, lambda td: td.set("action", torch.zeros_like(env.action_spec.low)))
    assert td["action"].shape == (2, 1, 60, 1)  # [workers, 1, time, CAVs]
    a = td["next", "cav", "accel"][:, 0, :, 0]
    assert float(a[:, :50].abs().max()) < 1e-4 and torch.allclose(a[:, 55], torch.tensor(3.0), atol=1e-4)
    one = TransformedEnv(make_env("ring", batch_size=1, seed=1), layer())
    alone = one.rollout(60, lambda td: td.set("action", torch.zeros_like(one.action_spec.low)))
    assert torch.allclose(a[1], alone["next", "cav", "accel"][0, :, 0], atol=1e-5)


def test_ramp_beyond_s_max_closes_a_long_start_with_bounded_jerk():
    """``beyond_s_max="ramp"``: from the 73 m start a zero command is pushed with an acceleration that
    rises by ramp_jerk * dt per step (no full-throttle step), and the gap is brought inside s_max."""
    env = TransformedEnv(make_env("ring", batch_size=2, seed=0),
                         SafetyLayer(s_min=5.0, s_max=38.0, beyond_s_max="ramp", ramp_jerk=0.5))
    td = env.rollout(400, lambda td: td.set("action", torch.zeros_like(env.action_spec.low)))
    accel, head_gap = td["next", "cav", "accel"][..., 0], td["next", "cav", "head_gap"][..., 0]
    outside = td["cav", "head_gap"][..., 0] > 38.0  # the state the layer acted on
    rise = accel[:, 1:] - accel[:, :-1]
    assert float(rise[outside[:, 1:]].max()) <= 0.5 * 0.1 + 1e-5  # the demand rises at ramp_jerk
    assert float(accel[:, 0].max()) == pytest.approx(0.05, abs=1e-5)  # not 3 m/s^2 at once
    assert bool((head_gap[:, :150] <= 38.0 + 1e-3).any(-1).all())  # and the 73 m gap is closed in 15 s
    assert not td["next", "collision"].any()
    with pytest.raises(ValueError, match="ramp_jerk=0.0 is invalid; allowed: > 0"):
        SafetyLayer(beyond_s_max="ramp", ramp_jerk=0.0)


def test_recover_beyond_s_max_closes_the_excess_at_its_time_constant():
    """``beyond_s_max="recover"``: beyond s_max the CAV must close on the head at least at
    ``(gap - s_max) / recover_seconds``, a demand continuous in the state and met with the CAV's
    bounded acceleration. A CAV 3 m beyond s_max already closing faster than that is left alone
    (``"push"`` drives it at full throttle); from the 73 m start the gap is brought back inside
    s_max, later than by "push" and sooner than by "hold" (only the head's own slowing down brings that
    back); a short time constant is the push rule, a long one the hold rule."""
    state = dict(gap=torch.tensor([[30.0]]), speed=torch.tensor([[22.54]]), leader_speed=torch.tensor([[20.21]]),
                 head_gap=torch.tensor([[41.0]]), head_speed=torch.tensor([[20.21]]), low=-3.0, high=3.0, dt=0.1,
                 s_min=5.0, s_max=38.0)
    command = torch.tensor([[-0.3]])
    assert float(safe_action(command, beyond_s_max="recover", recover_seconds=5.0, **state)) == pytest.approx(-0.3)
    assert float(safe_action(command, beyond_s_max="push", **state)) == pytest.approx(3.0)
    slow = dict(state, speed=torch.tensor([[20.6]]))  # closing at 0.39 m/s, the rule asks 3 / 5 = 0.6
    assert float(safe_action(command, beyond_s_max="recover", recover_seconds=5.0, **slow)) == pytest.approx(
        (0.6 - 0.39) / 0.1, abs=1e-3)

    def rollout(**kw):
        env = TransformedEnv(make_env("ring", batch_size=2, seed=0), SafetyLayer(s_min=5.0, s_max=38.0, **kw))
        return env.rollout(400, lambda td: td.set("action", torch.zeros_like(env.action_spec.low)))

    def first_inside(td):
        inside = td["next", "cav", "head_gap"][..., 0] <= 38.0 + 1e-3
        return [int(row.nonzero()[0]) if row.any() else None for row in inside]

    td, push, hold = rollout(beyond_s_max="recover", recover_seconds=5.0), rollout(), rollout(beyond_s_max="hold")
    assert all(p < r for p, r in zip(first_inside(push), first_inside(td), strict=True))
    assert all(h is None or h > r for h, r in zip(first_inside(hold), first_inside(td), strict=True))
    h, vh = td["cav", "head_gap"][..., 0], td["cav", "head_speed"][..., 0]
    v_next, accel = td["next", "cav", "speed"][..., 0], td["next", "cav", "accel"][..., 0]
    met = (h > 38.0 + 1e-3) & (accel < 3.0 - 1e-3)  # beyond s_max, the demand within the CAV's bound
    assert bool(met.any())
    assert float((v_next - vh - (h - 38.0) / 5.0)[met].min()) >= -1e-3
    assert not td["next", "collision"].any()
    fast, slow = rollout(beyond_s_max="recover", recover_seconds=0.1), rollout(beyond_s_max="recover", recover_seconds=1e6)
    assert torch.allclose(fast["next", "cav", "accel"], push["next", "cav", "accel"], atol=1e-4)
    assert torch.allclose(slow["next", "cav", "accel"][:, :50], hold["next", "cav", "accel"][:, :50], atol=1e-3)
    with pytest.raises(ValueError, match="recover_seconds=0.0 is invalid; allowed: > 0"):
        SafetyLayer(beyond_s_max="recover", recover_seconds=0.0)


def test_one_step_rule_is_not_enough_when_braking_is_bounded():
    """Why "stopping" is the default: the one-step rule reacts too late at -3 m/s^2."""
    def collisions(mode):
        env = TransformedEnv(make_env("ring", batch_size=16, seed=1), SafetyLayer(mode=mode))
        high = env.action_spec.high.clone()
        td = env.rollout(400, lambda td: td.set("action", high.clone()), break_when_any_done=False)
        return int(td["next", "collision"].sum())

    assert collisions("stopping") == 0
    assert collisions("one_step") > 0
