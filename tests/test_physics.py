import dataclasses
import math

import pytest
import torch

from mixed_traffic.physics import (
    IDMParams,
    OVMParams,
    car_following_accel,
    idm_accel,
    integrate,
    leader_gaps,
    ovm_accel,
    ovm_desired_speed,
    ovm_equilibrium_gap,
    params_as_tensors,
    saturate_accel,
)


def test_ovm_equilibrium_is_15m_at_15ms():
    p = OVMParams()
    assert ovm_equilibrium_gap(15.0) == pytest.approx(15.0)
    v = torch.tensor([15.0])
    assert ovm_desired_speed(torch.tensor([15.0]), p.v_max, p.s_st, p.s_go).item() == pytest.approx(15.0)
    acc = ovm_accel(torch.tensor([15.0]), v, v, alpha=p.alpha, beta=p.beta, v_max=p.v_max, s_st=p.s_st, s_go=p.s_go)
    assert acc.abs().item() < 1e-5


def test_ovm_homogeneous_platoon_settles_at_equilibrium_spacing():
    # head at 15 m/s, 8 OVM followers starting off-equilibrium: all gaps converge to 15 m
    n, dt = 9, 0.05
    pos = -torch.arange(n, dtype=torch.float64) * (12.0 + 5.0)
    vel = torch.full((n,), 15.0, dtype=torch.float64)
    params = params_as_tensors(OVMParams(), (n,), dtype=torch.float64)
    for _ in range(int(120 / dt)):
        gap = leader_gaps(pos, 5.0, None)
        acc = car_following_accel("ovm", gap, vel, torch.roll(vel, 1), params)
        acc[0] = 0.0
        pos, vel, _ = integrate(pos, vel, acc, dt, "euler_explicit")
    gap = leader_gaps(pos, 5.0, None)[1:]
    assert torch.allclose(gap, torch.full_like(gap, 15.0), atol=0.05)


def test_ovm_saturation_and_emergency_brake():
    # a big positive demand is clipped to +2, a fast approach brakes at -5
    acc = saturate_accel(torch.tensor([10.0, 0.5]), torch.tensor([30.0, 4.0]), torch.tensor([10.0, 20.0]),
                         torch.tensor([10.0, 5.0]), a_min=-5.0, a_max=2.0)
    assert acc.tolist() == [2.0, -5.0]


def test_idm_platoon_converges_to_analytic_equilibrium_gap():
    p = IDMParams()
    v_star = 10.0
    s_eq = (p.s0 + v_star * p.T) / math.sqrt(1 - (v_star / p.v0) ** p.delta)
    n, dt = 5, 0.1
    pos = -torch.arange(n, dtype=torch.float64) * (30.0 + 5.0)
    vel = torch.full((n,), v_star, dtype=torch.float64)
    params = params_as_tensors(p, (n,), dtype=torch.float64)
    for _ in range(3000):
        gap = leader_gaps(pos, 5.0, None)
        acc = car_following_accel("idm", gap, vel, torch.roll(vel, 1), params)
        acc[0] = 0.0
        pos, vel, _ = integrate(pos, vel, acc, dt)
    gap = leader_gaps(pos, 5.0, None)[1:]
    assert torch.allclose(gap, torch.full_like(gap, s_eq), atol=0.05), (gap, s_eq)


def test_idm_deeplcc_parameter_set():
    p = IDMParams.deeplcc()
    assert (p.v0, p.T, p.a, p.b, p.delta, p.s0) == (30.0, 1.0, 1.0, 1.5, 4.0, 5.0)
    # free road from standstill accelerates at a
    acc = idm_accel(torch.tensor([1e6]), torch.tensor([0.0]), torch.tensor([0.0]), v0=p.v0, T=p.T, a=p.a, b=p.b,
                    delta=p.delta, s0=p.s0)
    assert acc.item() == pytest.approx(1.0, abs=1e-6)


def _gap_of_no_command(accel, v: torch.Tensor, lo: float = 0.1, hi: float = 500.0) -> torch.Tensor:
    """Per speed ``v``, the gap at which ``accel(gap)`` (a law behind a leader at ``v``, whose command rises with the
    gap) is zero: where the law holds its speed (bisection)."""
    lo, hi = torch.full_like(v, lo), torch.full_like(v, hi)
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        pulls = accel(mid) > 0  # gap too large: the law speeds up
        hi, lo = torch.where(pulls, mid, hi), torch.where(pulls, lo, mid)
    return 0.5 * (lo + hi)


def _steady_gap(v: torch.Tensor, **params) -> torch.Tensor:
    """The gap at which IDM holds speed ``v`` behind a leader at ``v``."""
    return _gap_of_no_command(lambda gap: idm_accel(gap, v, v, **params), v)


def test_idm_gap_max_bounds_the_steady_gap_and_is_idm_below_it():
    p = dict(v0=40.0, T=1.0, a=2.0, b=3.0, delta=4.0, s0=7.0)
    v = torch.linspace(0.5, 38.0, 76, dtype=torch.float64)
    free = _steady_gap(v, **p)
    capped = _steady_gap(v, gap_max=34.0, **p)
    assert free.max() > 60.0  # IDM's own steady gap leaves any band as v nears v0
    assert capped.max() <= 34.0 + 1e-6
    # the steady gap is IDM's where IDM's is inside the cap, and the cap where IDM's is not
    inside = free < 33.0
    assert torch.allclose(capped[inside], free[inside], atol=1e-6)
    assert torch.allclose(capped[free > 35.0], torch.full_like(capped[free > 35.0], 34.0), atol=1e-6)
    # where the cap does not bind the command is IDM's to the bit, whatever the gap and the leader
    gap = torch.tensor([3.0, 12.0, 27.0, 80.0])
    vv, vl = torch.tensor([5.0, 10.0, 20.0, 15.0]), torch.tensor([0.0, 12.0, 18.0, 25.0])
    assert torch.equal(idm_accel(gap, vv, vl, gap_max=34.0, **p), idm_accel(gap, vv, vl, **p))


def test_idm_gap_max_is_checked_where_a_controller_is_built():
    from mixed_traffic.controllers.classic import make_classic_policy
    from mixed_traffic.evaluation.policies import classic_factory

    classic_factory("idm:s0=7.0;v0=40.0;gap_max=34.0")  # accepted from a controller string
    with pytest.raises(ValueError, match="gap_max must be above the standstill gap s0 = 7.0"):
        make_classic_policy("idm", low=-3.0, high=3.0, s0=7.0, gap_max=6.0)
    with pytest.raises(ValueError, match="allowed"):
        make_classic_policy("ovm", low=-3.0, high=3.0, gap_max=34.0)


def test_idm_v0_leader_sets_the_desired_speed_to_a_multiple_of_the_leaders_with_v0_as_the_floor():
    """``make_classic_policy("idm", v0_leader=r)``: per row, IDM's command with the desired speed
    ``max(v0, r * v_leader)``, computed here with each row's own scalar v0; a leader slower than ``v0 / r``
    leaves IDM as it is; the setting is IDM's alone and must be positive."""
    from mixed_traffic.controllers.classic import make_classic_policy

    p = dict(s0=7.0, T=1.0, b=2.0)
    law = make_classic_policy("idm", low=-5.0, high=3.0, v0=10.0, v0_leader=1.8, gap_max=27.0, **p).module
    plain = make_classic_policy("idm", low=-5.0, high=3.0, v0=10.0, gap_max=27.0, **p).module
    gap = torch.tensor([[60.0], [40.0], [25.0], [12.0], [8.0]])
    v = torch.tensor([[10.0], [21.0], [18.0], [9.0], [0.0]])
    v_l = torch.tensor([[10.0], [16.0], [25.0], [4.0], [0.0]])
    got = law(gap, v, v_l)
    for i in range(len(gap)):
        v0 = max(10.0, 1.8 * float(v_l[i]))
        one = make_classic_policy("idm", low=-5.0, high=3.0, v0=v0, gap_max=27.0, **p).module
        assert torch.allclose(got[i], one(gap[i:i + 1], v[i:i + 1], v_l[i:i + 1])[0], atol=1e-6), i
    slow = (1.8 * v_l < 10.0).squeeze(-1)  # behind a leader slower than v0 / r: the plain law
    assert bool(slow.any()) and torch.equal(got[slow], plain(gap, v, v_l)[slow])
    # closing a long gap at 20 m/s on a 17 m/s leader: the desired speed 30.6 m/s eases off where v0 = 60 does not
    fast_v0 = make_classic_policy("idm", low=-5.0, high=3.0, v0=60.0, gap_max=27.0, **p).module
    far = (torch.tensor([[70.0]]), torch.tensor([[20.0]]), torch.tensor([[17.0]]))
    assert float(law(*far)) < float(fast_v0(*far)) - 0.2
    with pytest.raises(ValueError, match=r"v0_leader = 0.0 is invalid; allowed: > 0"):
        make_classic_policy("idm", low=-3.0, high=3.0, v0_leader=0.0)
    with pytest.raises(ValueError, match=r"ovm parameters \['v0_leader'\] are invalid; allowed: \['a_max'"):
        make_classic_policy("ovm", low=-3.0, high=3.0, v0_leader=1.8)


def test_ring_default_base_holds_its_cap_where_the_humans_idm_falls_back():
    """The default experiment's residual base, built from its config, pulls up at 38 m behind a 28 m/s head."""
    from tensordict import TensorDict

    from mixed_traffic.config import compose
    from mixed_traffic.training.builders import make_transformed_env
    from transforms import ResidualAction

    def base_command(overrides):
        env = make_transformed_env(compose(["experiment=ring_lagrangian_ppo"] + overrides), num_envs=1, seed=0)
        (res,) = [t for t in env.transform if isinstance(t, ResidualAction)]
        td = TensorDict({("cav", "gap"): torch.tensor([[38.0]]), ("cav", "speed"): torch.tensor([[28.0]]),
                         ("cav", "leader_speed"): torch.tensor([[28.0]])}, batch_size=[1])
        return float(res.base_action(td))

    assert base_command([]) > 0.0  # capped: 38 m is beyond its 34-m steady gap, it closes up
    assert base_command(["transforms.residual.params.gap_max=null"]) < 0.0  # IDM's steady gap is 40.1 m there


def test_ring_gaps_wrap():
    L = 100.0
    pos = torch.tensor([[2.0, 90.0, 60.0]])  # head at 2 m has wrapped past the ring end
    gap = leader_gaps(pos, 5.0, L)
    # 90 -> 2 is 12 m ahead, 60 -> 90 is 30 m, head's leader (60) is 58 m ahead
    assert torch.allclose(gap, torch.tensor([[58.0 - 5, 12.0 - 5, 30.0 - 5]]))


def test_integrate_never_negative_speed_and_reports_executed_accel():
    pos, vel, acc = torch.zeros(2), torch.tensor([0.2, 5.0]), torch.tensor([-3.0, -3.0])
    p2, v2, ex = integrate(pos, vel, acc, 0.1)
    assert (v2 >= 0).all()
    assert ex[0].item() == pytest.approx(-2.0)  # stopped: only 0.2 m/s could be shed
    assert ex[1].item() == pytest.approx(-3.0)
    with pytest.raises(ValueError, match="integration"):
        integrate(pos, vel, acc, 0.1, "rk4")


def test_unknown_model_is_a_clear_error():
    with pytest.raises(ValueError, match="hdv_model"):
        car_following_accel("krauss", torch.ones(1), torch.ones(1), torch.ones(1), {})


# ----------------------------------------------------------------------------- SUMO's speed mode 95
from mixed_traffic.physics import (  # noqa: E402
    KraussParams,
    sumo_brake_gap,
    sumo_safe_follow_speed,
    sumo_speed_mode_95,
)

SUMO_CAV = dict(decel=3.0, leader_decel=3.0, tau=1.0, emergency_decel=9.0, dt=0.1)


def _t(*x):
    return torch.tensor(x, dtype=torch.float64)


def test_sumo_safe_follow_speed_hand_computed():
    # v = v_leader = 10 m/s, 20 m net gap: leader's step-wise brake gap 0.1 (33 * 10 - 0.3 * 33 * 34 / 2) = 16.17 m;
    # g = 36.169 m fits n = 40 braking steps (h = 0.5 * 40 * 39 * 0.03 + 40 * 0.3 = 35.4 m);
    # v_safe = 40 * 0.3 + (36.169 - 35.4) / (40 * 0.1 + 1) = 12.1538 m/s
    assert sumo_brake_gap(_t(10.0), 3.0, 0.1).item() == pytest.approx(16.17, abs=1e-9)
    v = sumo_safe_follow_speed(_t(20.0), _t(10.0), _t(10.0), **SUMO_CAV)
    assert v.item() == pytest.approx(12.0 + 0.769 / 5.0, abs=1e-9)
    # 0.5 m at 15 m/s behind a 15 m/s leader: beyond decel, SUMO's emergency rule:
    # b1 = 0.5 * 15^2 / (0.5 + 15^2 / 6) = 2.9605 <= 3, softened 1.2 x: v_safe = 15 - 0.1 * 1.2 * b1
    v = sumo_safe_follow_speed(_t(0.5), _t(15.0), _t(15.0), **SUMO_CAV)
    assert v.item() == pytest.approx(15.0 - 0.12 * 112.5 / 38.0, abs=1e-9)
    # a negative gap: emergency braking, never below 0
    assert sumo_safe_follow_speed(_t(-1.0, -1.0), _t(15.0, 0.5), _t(15.0, 0.0), **SUMO_CAV).tolist() == \
        pytest.approx([14.1, 0.0])


def test_sumo_speed_mode_95_order_of_bounds():
    kw = dict(accel_max=3.0, decel=3.0, leader_decel=3.0, dt=0.1)
    # far behind: the command executes (no override), +3 and -3 alike
    a, over = sumo_speed_mode_95(_t(3.0, -3.0, 0.0), _t(200.0, 200.0, 200.0), _t(10.0, 10.0, 10.0),
                                 _t(10.0, 10.0, 10.0), **kw)
    assert a.tolist() == pytest.approx([3.0, -3.0, 0.0]) and not over.any()
    # 3 m bumper gap (0.5 m net of minGap) at 15 m/s: the safe speed asks 3.55 m/s^2, speed mode 95
    # brakes at most decel: -3 (SUMO measured the same), overridden
    a, over = sumo_speed_mode_95(_t(3.0), _t(3.0), _t(15.0), _t(15.0), **kw)
    assert a.item() == pytest.approx(-3.0) and over.item()
    # gap 20 m net at 10 m/s: v_safe 12.15 m/s caps +3 (v + 0.3) only when above it: not here
    a, over = sumo_speed_mode_95(_t(3.0), _t(22.5), _t(10.0), _t(10.0), **kw)
    assert a.item() == pytest.approx(3.0) and not over.item()
    # at 12.1 m/s the same gap caps +3 at the safe speed
    v_safe = sumo_safe_follow_speed(_t(20.0), _t(12.1), _t(10.0), **SUMO_CAV).item()
    a, over = sumo_speed_mode_95(_t(3.0), _t(22.5), _t(12.1), _t(10.0), **kw)
    assert a.item() == pytest.approx((v_safe - 12.1) / 0.1) and over.item() and 0 < a.item() < 3.0
    # the dtype of the command is kept; at standstill a brake command is not an override
    a, over = sumo_speed_mode_95(torch.tensor([-3.0]), torch.tensor([50.0]), torch.tensor([0.0]),
                                 torch.tensor([0.0]), **kw)
    assert a.dtype == torch.float32 and a.item() == 0.0 and not over.item()


@pytest.mark.parametrize("kw, field", [
    (dict(decel=0.0), "decel"), (dict(accel_max=float("nan")), "accel_max"), (dict(leader_decel=-3.0), "leader_decel"),
    (dict(dt=0.0), "dt"), (dict(params=KraussParams(tau=0.0)), "params.tau"),
    (dict(params=KraussParams(min_gap=-1.0)), "params.min_gap"),
])
def test_sumo_speed_mode_95_bad_input_names_the_field(kw, field):
    args = dict(accel_max=3.0, decel=3.0, leader_decel=3.0, dt=0.1)
    args.update(kw)
    with pytest.raises(ValueError, match=field.replace(".", r"\.")):
        sumo_speed_mode_95(_t(1.0), _t(10.0), _t(10.0), _t(10.0), **args)


def test_soft_follower_is_its_linear_law_in_the_band_and_idm_near_the_leader():
    from mixed_traffic.physics import SoftFollowerParams, idm_accel, soft_follower_accel

    p = dataclasses.asdict(SoftFollowerParams())
    v = torch.tensor([15.0, 15.0, 15.0])
    # at the linear law's own gap and the leader's speed it commands nothing, whatever IDM says there
    gap = torch.full((3,), p["s0"] + p["h"] * 15.0)
    assert torch.allclose(soft_follower_accel(gap, v, v, **p), torch.zeros(3), atol=1e-6)
    # a wider gap: the weak gap feedback, ks per metre, below IDM's command
    wide = gap + 10.0
    assert torch.allclose(soft_follower_accel(wide, v, v, **p), torch.full((3,), 10.0 * p["ks"]), atol=1e-6)
    # closing fast on a near leader: IDM's braking, below the linear law's
    near, slow = torch.full((3,), 12.0), torch.full((3,), 5.0)
    idm = idm_accel(near, v, slow, v0=p["v0"], T=p["T"], a=p["a"], b=p["b"], delta=4.0, s0=p["s0_idm"])
    out = soft_follower_accel(near, v, slow, **p)
    assert torch.allclose(out, idm) and bool((out < -3.0).all())


def test_soft_follower_speed_scaling_and_closing_gain_against_hand_values():
    from mixed_traffic.physics import SOFT_SCALED, SoftFollowerParams, soft_follower_accel

    p = dataclasses.asdict(SoftFollowerParams()) | {"kv_closing": 0.3, "v_ref": 10.0}
    v, lead = torch.tensor([8.0, 20.0]), torch.tensor([9.0, 21.0])  # below and above v_ref, leader faster
    far = p["s0"] + p["h"] * v + 5.0  # 5 m beyond the linear law's gap; the IDM envelope does not bind there
    lin = p["ks"] * (far - p["s0"] - p["h"] * v) + p["kv"] * (lead - v)
    assert torch.allclose(soft_follower_accel(far, v, lead, **p), lin * torch.tensor([1.0, 10.0 / 20.0]), atol=1e-6)
    # a slower leader: the closing gain, and the same scaling
    slow = v - 1.0
    lin = p["ks"] * (far - p["s0"] - p["h"] * v) - p["kv_closing"]
    assert torch.allclose(soft_follower_accel(far, v, slow, **p), lin * torch.tensor([1.0, 0.5]), atol=1e-6)
    # brake_opening 0: no braking of the linear law while the leader is faster; the envelope still brakes
    close = torch.tensor([p["s0"] + p["h"] * 8.0 - 5.0])  # IDM still accelerates here
    v8, lead8 = torch.tensor([8.0]), torch.tensor([8.3])
    assert float(soft_follower_accel(close, v8, lead8, **p)) < 0.0
    assert float(soft_follower_accel(close, v8, lead8, **(p | {"brake_opening": 0.0}))) == 0.0
    assert float(soft_follower_accel(close, v8, v8 - 0.3, **(p | {"brake_opening": 0.0}))) < 0.0  # slower: brakes
    # the defaults (kv_closing = kv, no v_ref, brake_opening 1) are the unscaled symmetric law
    d = dataclasses.asdict(SoftFollowerParams())
    assert d["kv_closing"] is None and math.isinf(d["v_ref"]) and d["brake_opening"] == 1.0
    sym = {k: v for k, v in d.items() if k != "kv_closing"}
    assert torch.allclose(soft_follower_accel(far, v, slow, **sym),
                          soft_follower_accel(far, v, slow, **(sym | {"kv_closing": d["kv"]})))
    assert set(SOFT_SCALED) <= set(d)


def test_soft_follower_closing_gain_near_the_leader_against_hand_values():
    """``kv_closing_near``: the closing gain grows linearly as the gap falls inside the desired gap
    ``s0 + h v`` (hand values at a quarter and at all of it), and nothing changes at or beyond it or
    while the leader is faster."""
    from mixed_traffic.physics import SoftFollowerParams, idm_accel, soft_follower_accel

    p = dataclasses.asdict(SoftFollowerParams()) | {"kv_closing": 0.5, "s0_idm": 1.0, "T": 0.1, "b": 9.0}
    v = torch.tensor([8.0, 8.0])
    desired = p["s0"] + p["h"] * 8.0
    gap = torch.tensor([0.75 * desired, desired + 3.0])  # a quarter inside the desired gap; beyond it
    slow = v - 1.0
    near = soft_follower_accel(gap, v, slow, **(p | {"kv_closing_near": 2.0}))
    expect = p["ks"] * (gap - desired) - torch.tensor([0.5 + 2.0 * 0.25, 0.5])
    envelope = idm_accel(gap, v, slow, v0=p["v0"], T=p["T"], a=p["a"], b=p["b"], delta=4.0, s0=p["s0_idm"])
    assert bool((envelope > expect).all())  # the linear law is what binds
    assert torch.allclose(near, expect, atol=1e-6)
    assert torch.allclose(near[1:], soft_follower_accel(gap, v, slow, **p)[1:])
    fast = v + 1.0  # the leader faster: kv, untouched
    assert torch.allclose(soft_follower_accel(gap, v, fast, **(p | {"kv_closing_near": 2.0})),
                          soft_follower_accel(gap, v, fast, **p))


def test_soft_follower_band_terms_against_hand_values_and_a_constant_acceleration_answer():
    """``match_gap_max`` / ``match_gap_min`` add ``dv |dv| / (2 room)`` (hand values each way), ``ks_edge``
    acts beyond the band only, and a follower driven by the term alone answers a leader's step with one
    constant acceleration that matches its speed as the gap reaches ``match_gap_max``."""
    from mixed_traffic.physics import SoftFollowerParams, soft_follower_accel

    p = dataclasses.asdict(SoftFollowerParams()) | {"T": 0.3, "s0_idm": 2.0, "b": 9.0}  # the envelope far off
    band = {"match_gap_min": 10.0, "match_gap_max": 34.0}
    gap, v = torch.tensor([20.0, 20.0]), torch.tensor([20.0, 20.0])
    lead = torch.tensor([22.0, 18.0])  # faster: room 34 - 20 = 14; slower: room 20 - 10 = 10
    off = soft_follower_accel(gap, v, lead, **p)
    on = soft_follower_accel(gap, v, lead, **(p | band))
    assert torch.allclose(on - off, torch.tensor([4.0 / 28.0, -4.0 / 20.0]), atol=1e-6)
    # ks_edge: nothing inside the band, ks_edge * (gap - 34) beyond it (the leader as fast: no match term)
    g2 = torch.tensor([20.0, 38.0])
    same = torch.tensor([20.0, 20.0])
    edge = soft_follower_accel(g2, v, same, **(p | band | {"ks_edge": 0.1}))
    assert torch.allclose(edge - soft_follower_accel(g2, v, same, **(p | band)), torch.tensor([0.0, 0.4]), atol=1e-6)
    # the term alone (no gap or speed gain) against a leader 5 m/s faster, 14 m of room: 25 / 28 m/s^2
    # until the room is down to the 1-m floor (the last sqrt(25 / 14) m/s of the step)
    q = p | band | {"ks": 0.0, "kv": 0.0, "kv_closing": 0.0}
    dt, s, vf, vl = 0.01, torch.tensor([20.0]), torch.tensor([20.0]), torch.tensor([25.0])
    accs, gaps = [], []
    while float(vl - vf) > 1.4:
        a = soft_follower_accel(s, vf, vl, **q)
        accs.append(float(a))
        s, vf = s + (vl - vf) * dt - 0.5 * a * dt * dt, vf + a * dt
        gaps.append(float(s))
    assert max(abs(x - 25.0 / 28.0) for x in accs) < 1e-3  # one constant acceleration
    assert 32.5 < gaps[-1] < 33.0 and len(accs) * dt < 4.1  # 72 % of the step matched in 4 s, 1 m short of 34
    # match_h_min / match_h_max: the edges grow with the car's speed. At 20 m/s, floor 4 + 0.3 * 20 = 10 and
    # ceiling 22 + 0.6 * 20 = 34, the band above; at 10 m/s the same law's band is [7, 28]
    grow = {"match_gap_min": 4.0, "match_h_min": 0.3, "match_gap_max": 22.0, "match_h_max": 0.6, "ks_edge": 0.1}
    assert torch.allclose(soft_follower_accel(gap, v, lead, **(p | grow)), on, atol=1e-6)
    assert torch.allclose(soft_follower_accel(g2, v, same, **(p | grow)), edge, atol=1e-6)
    v10, g10 = torch.tensor([10.0, 10.0]), torch.tensor([20.0, 20.0])
    lead10 = torch.tensor([12.0, 8.0])  # rooms 28 - 20 = 8 and 20 - 7 = 13
    fixed = soft_follower_accel(g10, v10, lead10, **p)
    assert torch.allclose(soft_follower_accel(g10, v10, lead10, **(p | grow)) - fixed,
                          torch.tensor([4.0 / 16.0, -4.0 / 26.0]), atol=1e-6)


def test_soft_follower_with_speed_gains_of_one_over_its_headway_is_a_first_order_lag():
    """``kv = kv_closing = 1 / h`` (no near-gap term, no speed scaling): whatever the leader does, the gap error
    ``e = gap - s0 - h v`` decays as ``e0 exp(-h ks t)``, and from ``e0 = 0`` the car's acceleration is the
    leader's through a lag, whose total variation (the jerk measure) is below the leader's. The gentle experiment's
    gains (stronger toward a faster leader than toward a slower one) leave the gap error metres off that curve."""
    from mixed_traffic.physics import SoftFollowerParams, soft_follower_accel

    h, ks, s0 = 1.3, 0.12, 4.0
    lag = dataclasses.asdict(SoftFollowerParams()) | {"s0": s0, "h": h, "ks": ks, "kv": 1 / h, "kv_closing": 1 / h,
                                                      "T": 0.3, "s0_idm": 2.0, "b": 9.0}  # the envelope far off
    gentle = lag | {"kv": 1.25, "kv_closing": 0.5, "kv_closing_near": 1.0}
    dt = 0.01
    t = torch.arange(0.0, 60.0, dt)
    v_lead = 10.0 + 3.0 * torch.sin(2 * math.pi * t / 20.0) + 2.0 * torch.sin(2 * math.pi * t / 7.0)

    def drive(p, e0):
        v, gap, errors, accels = v_lead[:1].clone(), torch.tensor([s0 + h * float(v_lead[0]) + e0]), [], []
        for k in range(len(t)):
            a = soft_follower_accel(gap, v, v_lead[k:k + 1], **p)
            errors.append(float(gap - s0 - h * v))
            accels.append(float(a))
            v = v + a * dt
            gap = gap + (v_lead[k] - v) * dt
        return torch.tensor(errors), torch.tensor(accels)

    errors, _ = drive(lag, 6.0)
    assert float((errors - 6.0 * torch.exp(-h * ks * t)).abs().max()) < 0.1
    errors, _ = drive(gentle, 6.0)
    assert float((errors - 6.0 * torch.exp(-h * ks * t)).abs().max()) > 1.0
    _, accels = drive(lag, 0.0)
    a_lead = torch.diff(v_lead) / dt
    assert float(torch.diff(accels).abs().sum()) < float(torch.diff(a_lead).abs().sum())


def test_soft_follower_gradient_is_finite_with_its_defaults():
    """The defaults (no speed scaling, ``v_ref`` inf; no band) give a finite gradient: the analytic policy
    gradient of a residual over this law would otherwise turn the policy's weights into NaN."""
    from mixed_traffic.physics import SoftFollowerParams, soft_follower_accel

    p = dataclasses.asdict(SoftFollowerParams())
    gap = torch.tensor([20.0, 40.0, 6.0], requires_grad=True)
    v = torch.tensor([20.0, 20.0, 25.0], requires_grad=True)
    soft_follower_accel(gap, v, torch.tensor([22.0, 19.0, 25.0]), **p).sum().backward()
    assert bool(torch.isfinite(gap.grad).all()) and bool(torch.isfinite(v.grad).all())


@pytest.mark.parametrize("settings", [
    {},                                                         # every optional term off
    {"ks": 0.0, "kv_closing": 0.5},                             # no gap term: the desired gap is not needed
    {"match_gap_min": 10.0, "match_gap_max": 32.0, "ks": 0.0},  # a band with fixed edges, no edge gain
    {"match_gap_max": 32.0, "ks_edge": 0.06},                   # one edge only
])
def test_soft_follower_terms_left_out_at_their_off_settings_change_no_bit(settings):
    """A term whose setting is its off value given as a plain number is left out of the computation; the same
    settings given as tensors take every term. Command and gradient must agree to the bit, or analytic policy
    gradients would train other weights than the full law does."""
    from mixed_traffic.physics import SoftFollowerParams, soft_follower_accel

    p = dataclasses.asdict(SoftFollowerParams()) | {"v_ref": math.inf, "brake_opening": 1.0, "kv_closing_near": 0.0,
                                                     "match_gap_max": math.inf, "match_gap_min": -math.inf,
                                                     "ks_edge": 0.0, "match_h_min": 0.0, "match_h_max": 0.0} | settings
    full = {k: torch.tensor(float(x)) for k, x in p.items()
            if x is not None and k not in ("s0", "h", "T", "s0_idm", "a", "b", "v0")}
    g = torch.Generator().manual_seed(0)
    gap0, v0 = 4.0 + 40.0 * torch.rand(256, generator=g), 25.0 * torch.rand(256, generator=g)
    lead0 = (v0 + 6.0 * torch.randn(256, generator=g)).clamp_min(0.0)
    out = []
    for kw in (p, p | full):
        gap, v, lead = (x.clone().requires_grad_() for x in (gap0, v0, lead0))
        a = soft_follower_accel(gap, v, lead, **kw)
        (a * torch.linspace(-1.0, 2.0, 256)).sum().backward()
        out.append((a.detach(), gap.grad, v.grad, lead.grad))
    for left_out, every_term in zip(*out):
        assert torch.equal(left_out, every_term)


def test_speed_scaled_soft_follower_drives_the_ring_without_a_layer():
    from mixed_traffic import make_env
    from mixed_traffic.controllers.classic import make_classic_policy
    from mixed_traffic.physics import SOFT_SCALED

    env = make_env("ring", batch_size=4, seed=0, profile="random_steps",
                   profile_kwargs={"v_low": 5.0, "v_high": 20.0, "period": 15.0})
    td = env.rollout(1500, make_classic_policy("soft", env, **SOFT_SCALED))
    assert not bool(td["next", "collision"].any())
    gap = td["next", "cav", "gap"][:, 200:]  # after a 20-s warm-up: inside the evaluation band
    assert float(gap.min()) > 5.0 and float(gap.max()) < 40.0


@pytest.mark.parametrize("name, value", [("brake_opening", 1.5), ("v_ref", 0.0), ("gap_cap", -1.0),
                                         ("kv_closing_near", -0.5), ("ks_edge", -0.1),
                                         ("match_gap_max", 8.0), ("match_h_min", -0.1), ("match_h_max", 0.1)])
def test_soft_controller_rejects_out_of_range_parameters(name, value):
    from mixed_traffic.controllers.classic import make_classic_policy

    band = {"match_gap_min": 10.0, "match_gap_max": 34.0, "match_h_min": 0.2, "match_h_max": 0.2}
    # match_gap_max 8: below match_gap_min; match_h_max 0.1: a ceiling growing slower than the floor
    with pytest.raises(ValueError, match=name):
        make_classic_policy("soft", low=-3.0, high=2.0, **(band | {name: value}))


def test_speed_scheduled_base_is_each_law_outside_its_band_and_their_blend_inside():
    """``SpeedScheduledCAV``: the low-speed law below ``v_low``, the high-speed law above ``v_high``, the
    linear blend between (hand values at 13 m/s: weights 1/2 and 1/2), each law clipped first."""
    from mixed_traffic.controllers.classic import make_classic_policy, speed_scheduled_policy
    from mixed_traffic.physics import SOFT_SCALED

    soft = make_classic_policy("soft", low=-3.0, high=2.0, **SOFT_SCALED)
    idm = make_classic_policy("idm", low=-3.0, high=2.0, s0=7.0, v0=60.0, gap_max=27.0)
    sched = speed_scheduled_policy(soft, idm, 10.0, 16.0).module
    v = torch.tensor([4.0, 9.9, 13.0, 16.0, 25.0])
    gap, lead = torch.tensor([12.0, 20.0, 30.0, 18.0, 45.0]), v + torch.tensor([0.5, -1.0, 0.0, 2.0, -3.0])
    a_soft, a_idm = soft.module(gap, v, lead), idm.module(gap, v, lead)
    assert not torch.allclose(a_soft, a_idm, atol=1e-3)  # the two laws differ at every test state
    want = torch.cat([a_soft[:2], 0.5 * (a_soft[2:3] + a_idm[2:3]), a_idm[3:]])
    assert torch.allclose(sched(gap, v, lead), want, atol=1e-6)
    with pytest.raises(ValueError, match="v_low"):
        speed_scheduled_policy(soft, idm, 16.0, 10.0)
    # on the leader's speed: the same weights, read from the leader (13 m/s ahead of every car: the blend for all)
    on_lead = speed_scheduled_policy(soft, idm, 10.0, 16.0, on="leader_speed").module
    lead13 = torch.full_like(v, 13.0)
    assert torch.allclose(on_lead(gap, v, lead13), 0.5 * (soft.module(gap, v, lead13) + idm.module(gap, v, lead13)),
                          atol=1e-6)
    with pytest.raises(ValueError, match=r"on = 'gap' is invalid; allowed: 'speed', 'leader_speed'"):
        speed_scheduled_policy(soft, idm, 10.0, 16.0, on="gap")


def test_speed_scheduled_base_drives_the_ring_without_a_layer_across_its_blend():
    """The scheduled base of ``experiment=ring_lagrangian_ppo_scheduled`` alone (the learned residual at
    zero) on the evaluation's random steps (5-20 m/s), which cross its 10-16 m/s blend: no collision, gaps in the
    band after the warm-up."""
    from mixed_traffic import make_env
    from mixed_traffic.config import compose
    from mixed_traffic.training.builders import residual_base

    env = make_env("ring", batch_size=4, seed=1, profile="random_steps",
                   profile_kwargs={"v_low": 5.0, "v_high": 20.0, "period": 15.0})
    td = env.rollout(1500, residual_base(compose(["experiment=ring_lagrangian_ppo_scheduled"]).transforms.residual, env))
    speed = td["next", "cav", "speed"][:, 200:]
    assert float(speed.min()) < 10.0 and float(speed.max()) > 16.0  # both laws and the blend drove
    assert not bool(td["next", "collision"].any())
    gap = td["next", "cav", "gap"][:, 200:]
    assert float(gap.min()) > 5.0 and float(gap.max()) < 40.0


def test_unsaturated_base_keeps_braking_beyond_the_bound_when_a_residual_softens_it():
    """``transforms.residual.saturate_base=false``: closing at 12 m/s on a standing leader 12 m ahead the base
    asks for more than the 3 m/s^2 of braking the CAV has; a residual of +0.5 m/s^2 then still executes
    -3, where with the base clipped first it executes -2.5 (it takes back braking the CAV needs)."""
    from tensordict import TensorDict

    from mixed_traffic.config import compose
    from mixed_traffic.training.builders import make_transformed_env
    from transforms import ResidualAction

    def executed(saturate: bool):
        cfg = compose(["experiment=ring_lagrangian_ppo_scheduled", f"transforms.residual.saturate_base={saturate}"])
        env = make_transformed_env(cfg, num_envs=1, seed=0)
        (res,) = [t for t in env.transform if isinstance(t, ResidualAction)]
        res.engage_seconds = 0.0
        td = TensorDict({("cav", "gap"): torch.tensor([[12.0]]), ("cav", "speed"): torch.tensor([[12.0]]),
                         ("cav", "leader_speed"): torch.tensor([[0.0]]), "action": torch.tensor([[1.0]])},
                        batch_size=[1])
        out = res._inv_call(td)
        return float(out["residual", "base_action"]), float(out["action"])

    raw, a_free = executed(False)
    clipped, a_sat = executed(True)
    assert raw < -3.5 and clipped == pytest.approx(-3.0)
    assert a_free == pytest.approx(-3.0) and a_sat == pytest.approx(-2.5)


def test_a_residual_base_over_cacc_reads_the_leaders_acceleration_through_its_envelope():
    """``experiment=ring_lagrangian_ppo_cacc``: the base is CACC inside the stopping envelope. It reads
    ``("cav", "leader_accel")`` through the envelope (a braking head changes its command before the gap and
    the speeds do), drives the ring without collision, and the envelope still caps it."""
    from tensordict import TensorDict

    from mixed_traffic import make_env
    from mixed_traffic.config import compose
    from mixed_traffic.controllers.classic import LEADER_ACCEL_KEY, reads_leader_accel
    from mixed_traffic.training.builders import residual_base

    env = make_env("ring", batch_size=4, seed=1, profile="random_steps",
                   profile_kwargs={"v_low": 5.0, "v_high": 20.0, "period": 15.0})
    base = residual_base(compose(["experiment=ring_lagrangian_ppo_cacc"]).transforms.residual, env)
    assert LEADER_ACCEL_KEY in base.in_keys and reads_leader_accel(base.module)
    td = env.rollout(1500, base)
    assert not bool(td["next", "collision"].any())

    def command(gap, leader_accel):
        state = {("cav", "gap"): gap, ("cav", "speed"): 15.0, ("cav", "leader_speed"): 15.0,
                 LEADER_ACCEL_KEY: leader_accel}
        return float(base(TensorDict({k: torch.tensor([[v]]) for k, v in state.items()}, [1]))["action"])

    assert command(30.0, -2.0) < command(30.0, 0.0) - 0.1  # the head's braking is fed forward
    assert command(6.0, 2.0) == pytest.approx(command(6.0, 0.0))  # close behind, the envelope binds either way


def test_a_brake_floor_softens_a_law_only_behind_a_leader_that_slows_gently():
    """``LeaderBrakeFloor`` (``transforms.residual.high_speed.brake_floor``): an IDM 14 m behind a leader at
    17.5 m/s, itself at 18 m/s, brakes at its limit; with a floor of 1 m/s^2 and a margin of 0.3 it brakes
    at 1.0 behind a leader slowing at 0.5 m/s^2, at 2.3 behind one braking at 2, and a command above the floor
    is left as it is. Bad settings name the field."""
    from mixed_traffic.controllers.classic import LeaderBrakeFloor, make_classic_policy

    idm = make_classic_policy("idm", low=-3.0, high=3.0, s0=7.0, v0=60.0, gap_max=27.0).module
    floor = LeaderBrakeFloor(idm, floor=1.0, margin=0.3)
    g, v, vl = torch.tensor([14.0]), torch.tensor([18.0]), torch.tensor([17.5])
    assert float(idm(g, v, vl)) == pytest.approx(-3.0)
    assert float(floor(g, v, vl, torch.tensor([-0.5]))) == pytest.approx(-1.0)
    assert float(floor(g, v, vl, torch.tensor([-2.0]))) == pytest.approx(-2.3)
    far = torch.tensor([40.0])
    assert float(floor(far, v, vl, torch.tensor([-0.5]))) == pytest.approx(float(idm(far, v, vl)))
    with pytest.raises(ValueError, match=r"brake_floor = 0.0 is invalid; allowed: > 0"):
        LeaderBrakeFloor(idm, floor=0.0, margin=0.3)
    with pytest.raises(ValueError, match="reads the leader's acceleration"):
        floor(g, v, vl)


def test_the_brake_floor_experiment_reads_the_leaders_acceleration_and_drives_the_ring_alone():
    """``experiment=ring_lagrangian_ppo_brake_floor``: the default's base with the floor on its IDM slot,
    reading ``("cav", "leader_accel")``; alone (the residual at zero) behind a slow sine that crosses the
    10-20 m/s handovers it keeps the gap in the band, without collision; a bad floor names the field."""
    from mixed_traffic import make_env
    from mixed_traffic.config import compose
    from mixed_traffic.controllers.classic import LEADER_ACCEL_KEY
    from mixed_traffic.training.builders import residual_base
    from mixed_traffic.validation import ConfigError, validate_config

    cfg = validate_config(compose(["experiment=ring_lagrangian_ppo_brake_floor"]))
    env = make_env("ring", batch_size=2, seed=3, profile="sine",
                   profile_kwargs={"v_star": 18.0, "amplitude": 5.0, "period": 45.0})
    base = residual_base(cfg.transforms.residual, env)
    assert LEADER_ACCEL_KEY in base.in_keys
    td = env.rollout(2000, base)
    assert not bool(td["next", "collision"].any())
    gap = td["next", "cav", "gap"][:, 200:]
    assert float(gap.min()) > 5.0 and float(gap.max()) < 40.0
    for bad, field in (("transforms.residual.high_speed.brake_floor=-1", "brake_floor"),
                       ("transforms.residual.high_speed.brake_margin=-0.1", "brake_margin")):
        with pytest.raises(ConfigError, match=rf"transforms\.residual\.high_speed\.{field}"):
            validate_config(compose(["experiment=ring_lagrangian_ppo_brake_floor", bad]))


def _base_steady_gap(base, speeds) -> list[float]:
    """Per speed, the gap at which ``base`` (a ring base module reading the leader's acceleration, here 0) holds it
    behind a leader at that speed."""
    v = torch.tensor(speeds, dtype=torch.float32)
    return _gap_of_no_command(lambda gap: base(gap, v, v, torch.zeros_like(v)), v, lo=5.0, hi=40.0).tolist()


def test_near_gap_base_parks_near_the_rewards_gap_at_16_m_s_and_its_laws_agree_where_they_hand_over():
    """``experiment=ring_lagrangian_ppo_near_gap``: the paced join's experiment with the high-speed IDM's standstill
    gap at 3.5 m and the humans' desired speed (uncapped), and the soft law's standstill gap at 5 m. Its base, as it
    trains, holds a leader at 16 m/s at 20.3 m (the capped IDM of before: 23 m; the reward prices the distance
    from 20 m), the steady gap grows by more than 1 m every 2 m/s through the handover at 10-16 m/s, and at 10 m/s the soft law
    below and the IDM above want the same gap within 0.3 m."""
    from mixed_traffic import make_env
    from mixed_traffic.config import compose
    from mixed_traffic.training.builders import classic_law, residual_base
    from mixed_traffic.validation import validate_config
    from tests.test_config import assert_differs_only_in

    near, paced = (validate_config(compose([f"experiment=ring_lagrangian_ppo_{n}"])) for n in ("near_gap", "paced_join"))
    assert_differs_only_in(near, paced, {"transforms.residual.params.s0": 5.0,
                                         "transforms.residual.high_speed.params.s0": 3.5,
                                         "transforms.residual.high_speed.params.v0": 30.0,
                                         "transforms.residual.high_speed.params.gap_max": None})
    env = make_env("ring", batch_size=1, seed=0)
    new, old = (residual_base(c.transforms.residual, env, deploy=False).module for c in (near, paced))
    assert _base_steady_gap(new, [16.0])[0] == pytest.approx(20.3, abs=0.2)
    assert _base_steady_gap(old, [16.0])[0] > 22.5
    gaps = _base_steady_gap(new, [6.0, 8.0, 10.0, 12.0, 14.0, 16.0, 17.0])
    assert all(b > a + 1.0 for a, b in zip(gaps, gaps[1:])), gaps  # no flat stretch (the old base: +0.7 m at 10-12)
    r = near.transforms.residual
    soft = classic_law(r.base, r.params, env).module
    idm = classic_law(r.high_speed.base, r.high_speed.params, env).module
    assert _base_steady_gap(lambda g, s, lv, a: soft(g, s, lv), [10.0])[0] == pytest.approx(
        _base_steady_gap(lambda g, s, lv, a: idm(g, s, lv), [10.0])[0], abs=0.3)


def test_stop_arrival_accel_is_the_constant_deceleration_to_rest_behind_the_leaders_stopping_point():
    """``stop_arrival_accel``: behind a standing leader, braking at it from 10 m/s with 30 m of gap covers exactly the
    25 m to a 5-m stand (``v^2 / (2 d)``); behind one braking at 2 m/s^2 from 8 m/s the stopping point lies 16 m
    further; a leader that does not brake puts it so far ahead that the term asks for almost nothing."""
    from mixed_traffic.physics import stop_arrival_accel

    v = torch.tensor([10.0])
    d = -stop_arrival_accel(torch.tensor([30.0]), v, torch.tensor([0.0]), torch.tensor([0.0]), stand_gap=5.0)
    assert (v * v / (2 * d)).item() == pytest.approx(25.0)
    d = -stop_arrival_accel(torch.tensor([30.0]), v, torch.tensor([8.0]), torch.tensor([-2.0]), stand_gap=5.0)
    assert (v * v / (2 * d)).item() == pytest.approx(25.0 + 16.0)
    coasting = stop_arrival_accel(torch.tensor([30.0]), v, torch.tensor([8.0]), torch.tensor([0.0]), stand_gap=5.0)
    assert -0.01 < coasting.item() <= 0.0
    # max_brake: a leader braking at 3 m/s^2 counts as one braking at 1.5 (its stop 21.3 m ahead, not 10.7 m)
    hard, counted = (stop_arrival_accel(torch.tensor([30.0]), v, torch.tensor([8.0]), torch.tensor([a]), stand_gap=5.0,
                                        max_brake=1.5) for a in (-3.0, -1.5))
    assert hard.item() == counted.item() > stop_arrival_accel(torch.tensor([30.0]), v, torch.tensor([8.0]),
                                                               torch.tensor([-3.0]), stand_gap=5.0).item()


def _behind_a_leader(base, gap: float, v0: float, head, seconds: float, dt: float = 0.1):
    """The base alone ``gap`` m behind a leader, both at ``v0``, the leader commanded ``head(t)`` (m/s^2), both moved
    by the env's :func:`integrate` (V2V reports the leader's executed acceleration of the last step) for ``seconds``:
    per step the car's executed acceleration, speed and gap, and the leader's executed acceleration."""
    from mixed_traffic.physics import integrate

    pos, vel = torch.tensor([gap, 0.0]), torch.tensor([v0, v0])  # [leader, car]; no length
    leader_accel, rows = torch.zeros(1), []
    for k in range(int(seconds / dt)):
        a = base(pos[:1] - pos[1:], vel[1:], vel[:1], leader_accel).reshape(1)
        pos, vel, executed = integrate(pos, vel, torch.cat([torch.tensor([head(k * dt)]), a]), dt)
        leader_accel = executed[:1]
        rows.append((float(executed[1]), float(vel[1]), float(pos[0] - pos[1]), float(executed[0])))
    return rows


def _stop_behind_a_braking_leader(base, v0: float, rate: float):
    """:func:`_behind_a_leader` for 40 s, 7 m beyond the soft law's desired gap behind a leader that cruises at
    ``v0`` for 5 s and brakes at ``rate`` to a standstill."""
    return _behind_a_leader(base, 5.0 + 0.86 * v0 + 2.0, v0, lambda t: 0.0 if t < 5.0 else -rate, 40.0)


@pytest.mark.parametrize("v0, rate", [(14.0, 1.5), (8.0, 1.3), (10.0, 1.5)])
def test_smooth_stop_base_ends_a_stop_on_a_constant_deceleration_not_on_the_envelopes_full_braking(v0, rate):
    """``experiment=ring_lagrangian_ppo_smooth_stop`` (``transforms.residual.stand_arrival``): the near-gap base rides
    its stopping envelope's edge down to a stop and ends it at the car's full braking (3 m/s^2), a dip of about
    1 m/s^2 below the braking before it; the smooth-stop base ends the stop no harder than it braked before the last
    second, comes down to a crawl (0.1 m/s) still more than 5.1 m back (the soft law then creeps to its 5 m), never
    closer than the envelope's 5 m, and the total variation of its acceleration is at least 1 m/s^2 (one dip) less.
    (Its leader's braking counts at most 1.5 m/s^2, so behind a leader that brakes harder to a stop it may still end
    on the edge.)"""
    from mixed_traffic import make_env
    from mixed_traffic.config import compose
    from mixed_traffic.training.builders import residual_base
    from mixed_traffic.validation import validate_config
    from tests.test_config import assert_differs_only_in

    near, smooth = (validate_config(compose([f"experiment=ring_lagrangian_ppo_{n}"])) for n in ("near_gap", "smooth_stop"))
    assert_differs_only_in(smooth, near, {"transforms.residual.params.kv": 0.8,
                                          "transforms.residual.stand_arrival.stand_gap": 5.2})
    assert list(smooth.transforms.residual.stand_arrival.speeds) == [6.0, 9.0]  # the config's defaults
    assert smooth.transforms.residual.stand_arrival.leader_brake == 1.5
    env = make_env("ring", batch_size=1, seed=0)
    runs = {name: _stop_behind_a_braking_leader(residual_base(c.transforms.residual, env, deploy=False).module, v0, rate)
            for name, c in (("near", near), ("smooth", smooth))}
    for name, rows in runs.items():
        stood = next(k for k, r in enumerate(rows) if k > 50 and r[1] < 0.1)
        before, last = [r[0] for r in rows[:stood - 10]], [r[0] for r in rows[stood - 10:stood + 1]]
        tv = sum(abs(b[0] - a[0]) for a, b in zip(rows, rows[1:]))
        if name == "near":
            assert min(last) < -2.9 and min(last) < min(before) - 0.5, (min(last), min(before))
            tv_without = tv
        else:
            assert min(last) >= min(before) - 0.3 and min(last) > -2.7, (min(last), min(before))
            assert rows[stood][2] > 5.1 and min(r[2] for r in rows) > 5.0 - 1e-3, (rows[stood][2], min(r[2] for r in rows))
            assert tv < tv_without - 1.0, (tv, tv_without)


@pytest.mark.parametrize("v_mid, amplitude, period", [(21.5, 2.0, 45.0), (20.5, 1.5, 35.0), (19.5, 2.0, 40.0)])
def test_fast_band_base_follows_a_sine_above_the_training_speeds_with_less_jerk(v_mid, amplitude, period):
    """``experiment=ring_lagrangian_ppo_fast_band``: one band law from 18 m/s up (the 20 m/s law's band, gain 0.2
    1/s) and an IDM of 10-18 m/s that brakes at most 0.3 m/s^2 beyond its leader's braking plus 0.2. Behind sines at
    17.5-23.5 m/s (the residual fades out from 18 m/s, so the base drives there alone) the total variation of its
    acceleration is at least 5 % below ``smooth_stop``'s base (whose sine through 18-20 m/s meets IDM's braking at
    each trough), below the leader's own where the sine stays at or above 19 m/s, with the gap inside [5, 40] m."""
    from mixed_traffic import make_env
    from mixed_traffic.config import compose
    from mixed_traffic.training.builders import residual_base
    from mixed_traffic.validation import validate_config
    from tests.test_config import assert_differs_only_in

    smooth, fast = (validate_config(compose([f"experiment=ring_lagrangian_ppo_{n}"])) for n in ("smooth_stop", "fast_band"))
    r = "transforms.residual."
    assert_differs_only_in(fast, smooth, {r + "high_speed.brake_floor": 0.3, r + "high_speed.brake_margin": 0.2,
                                          r + "top_speed.params.kv": 0.2, r + "top_speed.params.match_gap_min": 6.1,
                                          r + "top_speed.params.match_gap_max": 35.0,
                                          r + "top_speed.params.ks_edge": 0.077, r + "beyond_speed.params.kv": 0.2,
                                          r + "drive_off.follow": 0.8})  # the drive-off: deploy-only, not the base
    env = make_env("ring", batch_size=1, seed=0)
    tv = {}
    def head(t: float) -> float:  # the leader's speed v_mid + amplitude sin(2 pi t / period)
        return amplitude * 2.0 * math.pi / period * math.cos(2.0 * math.pi * t / period)

    for name, c in (("smooth", smooth), ("fast", fast)):
        base = residual_base(c.transforms.residual, env, deploy=False).module
        rows = _behind_a_leader(base, 25.0, v_mid, head, 200.0)[600:]  # the last 140 s
        tv[name] = sum(abs(b[0] - a[0]) for a, b in zip(rows, rows[1:]))
        tv_leader = sum(abs(b[3] - a[3]) for a, b in zip(rows, rows[1:]))
        assert 5.0 < min(r[2] for r in rows) and max(r[2] for r in rows) < 40.0, name
    assert tv["fast"] < 0.95 * tv["smooth"], tv
    if v_mid - amplitude >= 19.0:
        assert tv["fast"] < tv_leader, (tv, tv_leader)


def test_stand_arrival_lowers_the_command_only_near_the_envelopes_edge_at_low_speed_behind_a_braking_leader():
    """``StoppingEnvelope(stand_gap=...)``: the command is the plain envelope's above ``stand_speeds[1]``, with
    ``stand_slack`` metres of margin or more, and behind a leader that does not brake (the term asks for almost
    nothing); on the edge at low speed behind a braking leader it is lower; never higher anywhere."""
    from mixed_traffic import make_env
    from mixed_traffic.controllers.classic import make_classic_policy, stopping_envelope_policy

    env = make_env("ring", batch_size=1, seed=0)
    law = make_classic_policy("idm", env, s0=4.0)
    plain = stopping_envelope_policy(law, env, stop_gap=5.0).module
    stand = stopping_envelope_policy(law, env, stop_gap=5.0, stand_gap=5.5, stand_speeds=(9.0, 12.0),
                                     stand_slack=3.0).module
    g = torch.linspace(5.0, 60.0, 56)
    for v, vl, al in ((15.0, 10.0, -1.5), (6.0, 4.0, -1.5), (6.0, 6.0, 0.0), (3.0, 1.0, -1.0)):
        v_, vl_, al_ = (torch.full_like(g, x) for x in (v, vl, al))
        a0, a1 = plain(g, v_, vl_, al_), stand(g, v_, vl_, al_)
        assert bool((a1 <= a0 + 1e-6).all())
        far = stand.slack(g, v_, vl_) >= 3.0
        assert bool(far.any()) and torch.equal(a1[far], a0[far]), (v, vl)
        if v > 12.0:
            assert torch.equal(a1, a0)
        if al == 0.0:
            assert float((a0 - a1).max()) < 0.02
        if v < 9.0 and al < 0.0:
            assert bool((a1 < a0 - 0.05).any()), (v, vl)
