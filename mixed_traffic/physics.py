"""Car-following physics as pure, batched torch functions.

Every function takes tensors of any (broadcastable) shape and returns new tensors;
nothing here holds state. Parameters can be per vehicle (tensors) or shared
(floats), so heterogeneous platoons and per-episode randomisation need no extra code.

Conventions: ``gap`` is the bumper-to-bumper distance to the leader (m), ``v`` the
follower's speed, ``v_leader`` the leader's speed (m/s); accelerations are m/s^2.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch

Tensor = torch.Tensor
Num = float | Tensor


@dataclass(frozen=True)
class OVMParams:
    """Optimal Velocity Model parameters (DeeP-LCC reference, homogeneous set)."""

    alpha: float = 0.6
    beta: float = 0.9
    v_max: float = 30.0
    s_st: float = 5.0
    s_go: float = 25.0
    a_min: float = -5.0
    a_max: float = 2.0


@dataclass(frozen=True)
class IDMParams:
    """Intelligent Driver Model parameters.

    Defaults are SUMO's IDM as the ring scenario uses it (accel 2.0, decel 3.0,
    tau 1.0, minGap 2.5). ``IDMParams.deeplcc()`` is the DeeP-LCC reference's set.
    """

    v0: float = 30.0
    T: float = 1.0
    a: float = 2.0
    b: float = 3.0
    delta: float = 4.0
    s0: float = 2.5
    a_min: float = -9.0
    a_max: float = 2.0

    @classmethod
    def deeplcc(cls) -> IDMParams:
        return cls(v0=30.0, T=1.0, a=1.0, b=1.5, delta=4.0, s0=5.0, a_min=-5.0, a_max=2.0)


@dataclass(frozen=True)
class SoftFollowerParams:
    """A linear follower with weak gap feedback under an IDM envelope (:func:`soft_follower_accel`).

    The defaults are the setting of ``benchmarks/ring_classical_frontier.py --family soft`` (100 random
    settings) that met the most of the ring's bars without a layer (docs/results.md); with them the law is
    symmetric (``kv_closing`` None: ``kv``), unscaled (``v_ref`` inf), uncapped and brakes wherever its
    command is negative. :data:`SOFT_SCALED` is a setting with the speed scaling and a closing gain.
    """

    ks: float = 0.074  # gap gain (1/s^2)
    kv: float = 0.65  # speed-difference gain while the leader is faster (1/s)
    s0: float = 8.45  # the linear law's standstill gap (m)
    h: float = 0.86  # the linear law's time headway (s)
    T: float = 0.7  # the envelope's IDM headway (s)
    s0_idm: float = 4.53  # the envelope's IDM standstill gap (m)
    a: float = 2.17  # the envelope's IDM acceleration (m/s^2)
    b: float = 3.02  # the envelope's IDM comfortable deceleration (m/s^2)
    v0: float = 60.0  # the envelope's IDM desired speed (m/s)
    kv_closing: float | None = None  # speed-difference gain while the leader is slower (1/s; None: kv)
    v_ref: float = math.inf  # above this speed (m/s) both gains fall as v_ref / v
    gap_cap: float = math.inf  # the linear law's desired gap s0 + h v is capped here (m)
    brake_opening: float = 1.0  # share of the linear law's braking kept while the leader is faster (0-1)
    kv_closing_near: float = 0.0  # closing gain added at gap 0, falling linearly to 0 at the desired gap (1/s)
    match_gap_max: float = math.inf  # match a faster leader's speed at constant acceleration before this gap (m)
    match_gap_min: float = -math.inf  # match a slower leader's speed at constant deceleration above this gap (m)
    ks_edge: float = 0.0  # gap gain added beyond match_gap_max and below match_gap_min (1/s^2)
    match_h_min: float = 0.0  # the band's floor grows by this time headway: match_gap_min + match_h_min v (s)
    match_h_max: float = 0.0  # ... and its ceiling by this one: match_gap_max + match_h_max v (s)


@dataclass(frozen=True)
class CACCParams:
    """Cooperative adaptive cruise control: a constant-time-gap follower with the leader's acceleration
    fed forward (:func:`cacc_accel`), what a CAV that receives its leader's acceleration over V2V runs.

    The defaults are the ring's best CACC: of 600 settings replayed at the tuning seed 3000 on 14 cases
    (``benchmarks/ring_base_replay.py --classic cacc``), the one with the least worst-case jerk against
    IDM-as-CAV's among those that keep every gap in the 5-40 m band after the warm-up (docs/results.md,
    "Against cooperative adaptive cruise control").
    """

    ka: float = 0.086  # share of the leader's acceleration fed forward
    kv: float = 0.662  # speed-difference gain (1/s)
    ks: float = 0.204  # gap-error gain (1/s^2)
    s0: float = 9.357  # standstill gap of the spacing policy (m)
    h: float = 0.941  # time gap of the spacing policy (s)
    e_max: float = 32.95  # the gap error counts up to this much (m): a long gap is closed at a capped rate


@dataclass(frozen=True)
class ClosingParams:
    """A closing-speed law (:func:`closing_accel`): the car closes on (or opens to) a target gap with its closing
    speed on a constant-deceleration arrival profile, a join law for a car that starts far behind its leader.

    The defaults are the join of ``experiment=ring_lagrangian_ppo_closing_join`` (tried, not kept): picked at the
    tuning seed 3000 among decelerations of 0.2, 0.25 and 0.3 m/s^2 (docs/results.md, "A join on a closing-speed
    profile").
    """

    target: float = 25.0  # the gap the law arrives at (m)
    decel: float = 0.25  # the arrival's constant deceleration (m/s^2)
    closing_max: float = 6.0  # the largest closing speed asked for (m/s)
    k: float = 0.5  # gain on the closing speed's error (1/s)
    a_max: float = 2.0  # the law's largest acceleration (m/s^2)
    ka_brake: float = 0.0  # share of the leader's braking (its acceleration where negative, over V2V) fed forward


# The soft follower with gains that fall as 1/v above 11 m/s and a weaker answer to a slower leader: the
# setting of a local search (benchmarks/ring_soft_search.py, on the frontier's five cases with a tuning seed,
# 3000, that no report uses) over the family with brake_opening 0, kept with the linear law's braking
# (brake_opening 1), over which the learned residual did better (docs/results.md).
SOFT_SCALED = dict(ks=0.127, kv=0.805, kv_closing=0.71, s0=10.322, h=0.86, T=0.497, s0_idm=4.571, a=1.834,
                   b=5.0, v_ref=11.038)


def soft_follower_accel(gap: Tensor, v: Tensor, v_leader: Tensor, *, ks: Num, kv: Num, s0: Num, h: Num, T: Num,
                        s0_idm: Num, a: Num, b: Num, v0: Num, kv_closing: Num | None = None,
                        v_ref: Num = math.inf, gap_cap: Num = math.inf, brake_opening: Num = 1.0,
                        kv_closing_near: Num = 0.0, match_gap_max: Num = math.inf,
                        match_gap_min: Num = -math.inf, ks_edge: Num = 0.0, match_h_min: Num = 0.0,
                        match_h_max: Num = 0.0, **_) -> Tensor:
    """``min(g(v) [ks (gap - min(s0 + h v, gap_cap)) + k (v_leader - v)], IDM(gap, v, v_leader))``.

    The linear law lets the gap float inside a band (weak gap feedback); the IDM envelope (delta 4) brakes
    where IDM would.

    ``k`` is ``kv`` while the leader is faster and ``kv_closing`` (default ``kv``) while it is slower;
    ``g(v) = min(1, v_ref / v)``: above ``v_ref`` the same gap and speed errors get a gentler answer (a
    time headway's room grows with speed), which lowers the jerk of answering a fast head's steps.
    While the leader is faster the gap is already opening: ``brake_opening`` (1: all, 0: none) is the
    share of the linear law's braking kept there; the envelope still brakes where IDM would.
    ``kv_closing_near`` strengthens the answer to a slower leader only inside the desired gap
    ``s* = min(s0 + h v, gap_cap)``: the closing gain is ``kv_closing + kv_closing_near (1 - gap / s*)``
    there (``kv_closing`` alone at or beyond ``s*``). A head braking hard pulls the gap inside ``s*`` early
    and gets the stronger answer; the everyday small oscillations around ``s*`` get little of it.

    With ``kv = kv_closing = 1 / h`` (``kv_closing_near`` 0, below ``v_ref`` and ``gap_cap``) the linear law is a
    first-order lag: the gap error ``e = gap - (s0 + h v)`` obeys ``de/dt = -h ks e`` whatever the leader does, and
    the car's speed is the leader's through a lag of time constant ``h``. Its acceleration is then the leader's
    through a non-negative kernel, so its total variation (the jerk measure) is at most the leader's; the other
    gains leave a slow mode that answers each of the leader's speed changes with an overshoot.

    ``match_gap_max`` / ``match_gap_min`` (m; off by default) keep the gap inside a band with the least
    constant acceleration: the law adds ``dv |dv| / (2 room)``, ``dv = v_leader - v``, the acceleration
    that matches the leader's speed just as the gap reaches ``match_gap_max`` (leader faster; ``room =
    match_gap_max - gap``) or falls to ``match_gap_min`` (leader slower; ``room = gap - match_gap_min``),
    room floored at 1 m. Followed exactly it is constant through the answer (``dv^2 / room`` does not
    change), so a step of the leader costs one rise and one fall of the command, and a small step a small
    one. ``ks_edge`` (1/s^2) adds a gap gain beyond the two gaps only, which brings a gap back inside
    them; with ``ks`` 0 the gap floats freely between them. ``match_h_min`` / ``match_h_max`` (s, default 0)
    let the two edges grow with the car's speed, ``match_gap_min + match_h_min v`` and ``match_gap_max +
    match_h_max v``, so that one law keeps a band that suits every speed (a time headway's room grows with it).
    """
    # A term whose setting is its "off" value (a plain number) adds exactly zero to the command and to its gradient,
    # so it is left out: the same numbers with fewer operations (the law runs three times in every step of the ring's
    # base, and analytic policy gradients differentiate through each).
    kv = torch.as_tensor(kv, dtype=v.dtype)
    desired = None if _is(ks, 0.0) and _is(kv_closing_near, 0.0) else torch.clamp(s0 + h * v, max=gap_cap)
    k_close = kv if kv_closing is None else kv_closing
    if not _is(kv_closing_near, 0.0):
        inside = (1.0 - gap / desired.clamp_min(1e-6)).clamp(0.0, 1.0)  # 0 at or beyond the desired gap, 1 at 0
        k_close = k_close + kv_closing_near * inside
    dv = v_leader - v
    k = torch.where(dv < 0, k_close, kv)
    linear = k * dv if _is(ks, 0.0) else ks * (gap - desired) + k * dv
    if not _is(v_ref, math.inf):
        linear = linear / (v / v_ref).clamp_min(1.0)  # g(v) = min(1, v_ref / v)
    if not _is(brake_opening, 1.0):
        linear = torch.where((dv > 0) & (linear < 0), linear * brake_opening, linear)
    no_band = (_is(match_gap_max, math.inf) and _is(match_gap_min, -math.inf) and _is(match_h_min, 0.0)
               and _is(match_h_max, 0.0))
    if not no_band:
        ceil = match_gap_max if _is(match_h_max, 0.0) else match_gap_max + match_h_max * v  # +-inf (one side off)
        floor = match_gap_min if _is(match_h_min, 0.0) else match_gap_min + match_h_min * v  # stay so
        linear = linear + band_match(gap, dv, floor, ceil)  # an edge at +-inf (that side off): no term
        if not _is(ks_edge, 0.0):
            linear = linear + ks_edge * band_beyond(gap, floor, ceil)
    return torch.minimum(linear, idm_accel(gap, v, v_leader, v0=v0, T=T, a=a, b=b, delta=4.0, s0=s0_idm))


def band_match(gap: Tensor, dv: Tensor, floor: Num, ceil: Num) -> Tensor:
    """``dv |dv| / (2 room)``: the constant acceleration that matches the leader's speed (``dv = v_leader - v``) just
    as the gap reaches the band's edge ahead, ``ceil`` while the leader is faster (``room = ceil - gap``), ``floor``
    while it is slower (``room = gap - floor``); room floored at 1 m (m)."""
    room = torch.where(dv > 0, ceil - gap, gap - floor).clamp_min(1.0)
    return dv * dv.abs() / (2.0 * room)


def band_beyond(gap: Tensor, floor: Num, ceil: Num) -> Tensor:
    """How far the gap lies beyond the band ``[floor, ceil]`` (m): positive above ``ceil``, negative below ``floor``,
    0 inside."""
    return (gap - ceil).clamp_min(0.0) - (floor - gap).clamp_min(0.0)


def _is(setting: Num, value: float) -> bool:
    """Whether ``setting`` is the plain number ``value`` (a tensor setting is never treated as off)."""
    return isinstance(setting, (int, float)) and setting == value


def committed_answer_accel(gap: Tensor, v: Tensor, v_leader: Tensor, tau: Tensor, sign: Tensor, *, horizon: float,
                           horizon_min: float, start: float, done: float, gaps: tuple[float, float], ks_edge: float,
                           dt: float) -> tuple[Tensor, Tensor, Tensor]:
    """One step of the committed answer: ``(accel, tau, sign)`` from the state ``(tau, sign)`` before it.

    The answer to a change of the leader's speed is one acceleration, held while a time to go runs. Once the speed
    difference ``dv = v_leader - v`` exceeds ``start`` (m/s) while no answer runs (``sign`` 0), an answer starts:
    ``sign`` takes ``dv``'s sign and the time to go ``tau`` is set to ``horizon`` (s), then counts down by ``dt``
    each step. The command is ``dv / max(tau, horizon_min)``: behind a step of the leader ``dv`` and ``tau`` fall in
    proportion, so the command holds ``dv0 / horizon`` for ``horizon - horizon_min`` seconds (it would match the
    speeds in ``horizon`` seconds), and then eases off with a gain of ``1 / horizon_min`` on what is left of
    ``dv``; behind a leader that keeps changing its speed the gain firms up to ``1 / horizon_min``. The answer ends
    (``sign`` 0, command 0) once ``dv`` has closed to ``done`` or changed sign. Where keeping the gap inside
    ``gaps = (low, high)`` (m) asks for more, the command is the constant acceleration that matches the leader's
    speed just at the edge ahead, ``dv |dv| / (2 room)`` (:func:`band_match`, :func:`soft_follower_accel`'s band
    term), and beyond the edges ``ks_edge`` (1/s^2) pulls the gap back.

    The causal least-jerk bound (:func:`mixed_traffic.evaluation.oracle.causal_least_jerk`) drives behind steps of
    the head this way; a law of the present state alone cannot, since holding an acceleration until the speeds
    match needs to remember when the answer began.
    """
    dv = v_leader - v
    begin = (sign == 0) & (dv.abs() > start)
    tau = torch.where(begin, torch.full_like(tau, horizon), tau)
    sign = torch.where(begin, torch.sign(dv), sign)
    sign = torch.where((sign != 0) & (dv * sign < done), torch.zeros_like(sign), sign)
    running = sign != 0
    a = torch.where(running, dv / tau.clamp_min(horizon_min), torch.zeros_like(dv))
    tau = torch.where(running, tau - dt, tau)
    low, high = gaps
    match = band_match(gap, dv, low, high)
    a = torch.where(match.abs() > a.abs(), match, a)
    return a + ks_edge * band_beyond(gap, low, high), tau, sign


def stop_arrival_accel(gap: Tensor, v: Tensor, v_leader: Tensor, a_leader: Tensor, *, stand_gap: Num,
                       max_brake: Num = math.inf, min_brake: float = 1e-3) -> Tensor:
    """``-v^2 / (2 R)``, ``R = gap + v_leader^2 / (2 b_l) - stand_gap``, ``b_l = clip(-a_leader, min_brake,
    max_brake)``: the constant deceleration that brings the car to rest ``stand_gap`` (m) behind the point where its
    leader, braking on as it brakes now (counted at most ``max_brake``, m/s^2), will stand.

    A leader that does not brake stands ``v_leader^2 / (2 min_brake)`` ahead, far enough that the term asks for
    almost nothing; a standing leader stands where it is. The term is continuous in the state through both: as
    the leader's braking fades to 0 its stopping point recedes and the term goes to 0, and as the leader comes to
    rest its stopping point reaches it. ``R`` is floored at 0.05 m (the term is then the car's hardest braking or
    more; the caller bounds it).
    """
    b_l = (-a_leader).clamp(min_brake, max_brake)
    room = (gap + v_leader * v_leader / (2.0 * b_l) - stand_gap).clamp_min(0.05)
    return -(v * v) / (2.0 * room)


def closing_accel(gap: Tensor, v: Tensor, v_leader: Tensor, a_leader: Tensor | None = None, *, target: Num, decel: Num,
                  closing_max: Num, k: Num, a_max: Num, ka_brake: Num = 0.0, **_) -> Tensor:
    """``min(ka_brake min(a_leader, 0) + k (u*(gap - target) - (v - v_leader)), a_max)``,
    ``u*(e) = sign(e) min(closing_max, sqrt(2 decel |e|))``.

    ``u*`` is the closing speed from which braking at ``decel`` matches the leader's speed just at ``target``:
    followed, the car arrives with one constant gentle deceleration instead of IDM's late, harder one, and
    from far behind it closes at up to ``closing_max``. Inside the target the same profile opens the gap. With
    ``ka_brake`` the leader's braking (its acceleration where negative, received over V2V) is fed forward, so the
    car does not close on a slowing leader faster than its profile asks (``a_leader`` is needed then); its
    speeding up is not, so the command carries none of a head's steps up. In the last metres the
    profile's slope grows without bound, so a car behind it brakes harder there (up to about 2.7 ``decel`` at ``k``
    0.5) and settles with a small decaying swing; as a join law it has usually handed over before.

    >>> round(float(closing_accel(torch.tensor(45.0), torch.tensor(22.0), torch.tensor(20.0), target=25.0,
    ...                           decel=0.25, closing_max=6.0, k=0.5, a_max=2.0)), 3)
    0.581
    """
    e = gap - target
    u_star = torch.sign(e) * torch.sqrt(2.0 * decel * e.abs()).clamp(max=closing_max)
    a = k * (u_star - (v - v_leader))
    if ka_brake:
        if a_leader is None:
            raise ValueError("closing_accel: ka_brake > 0 feeds the leader's braking forward; pass a_leader")
        a = a + ka_brake * a_leader.clamp(max=0.0)
    return a.clamp(max=a_max)


def cacc_accel(gap: Tensor, v: Tensor, v_leader: Tensor, a_leader: Tensor, *, ka: Num, kv: Num, ks: Num, s0: Num,
               h: Num, e_max: Num = math.inf, **_) -> Tensor:
    """``ka a_leader + kv (v_leader - v) + ks min(gap - (s0 + h v), e_max)``: the linear CACC law.

    The spacing policy ``s0 + h v`` keeps a constant time gap; the leader's acceleration of the last step
    (received over V2V) is fed forward, so the follower starts to answer a change of its leader's speed
    before the gap and the speed difference show it. ``e_max`` caps the gap error, so that a follower
    far behind (a long start) closes the gap at a bounded rate instead of at its top acceleration.

    >>> round(float(cacc_accel(torch.tensor(25.0), torch.tensor(20.0), torch.tensor(20.0), torch.tensor(0.5),
    ...                        ka=0.5, kv=0.58, ks=0.1, s0=5.0, h=1.0)), 3)
    0.25
    """
    error = torch.clamp(gap - (s0 + h * v), max=e_max)
    return ka * a_leader + kv * (v_leader - v) + ks * error


def params_as_tensors(params, shape, *, dtype=torch.float32, device=None) -> dict[str, Tensor]:
    """Expand a parameter dataclass to a dict of tensors of ``shape`` (per vehicle)."""
    return {
        f.name: torch.full(shape, float(getattr(params, f.name)), dtype=dtype, device=device)
        for f in fields(params)
    }


def ovm_desired_speed(gap: Tensor, v_max: Num, s_st: Num, s_go: Num) -> Tensor:
    """OVM spacing policy V_d(s): 0 below s_st, v_max above s_go, cosine between."""
    frac = ((gap - s_st) / (s_go - s_st)).clamp(0.0, 1.0)
    return 0.5 * v_max * (1.0 - torch.cos(math.pi * frac))


def ovm_equilibrium_gap(v: float, v_max: float = 30.0, s_st: float = 5.0, s_go: float = 25.0) -> float:
    """Spacing at which V_d(s) = v (15 m at 15 m/s for the DeeP-LCC parameters)."""
    return math.acos(1.0 - 2.0 * v / v_max) / math.pi * (s_go - s_st) + s_st


def ovm_accel(gap: Tensor, v: Tensor, v_leader: Tensor, *, alpha: Num, beta: Num,
              v_max: Num, s_st: Num, s_go: Num, **_) -> Tensor:
    """Unsaturated OVM acceleration alpha (V_d(s) - v) + beta (v_leader - v)."""
    return alpha * (ovm_desired_speed(gap, v_max, s_st, s_go) - v) + beta * (v_leader - v)


def idm_accel(gap: Tensor, v: Tensor, v_leader: Tensor, *, v0: Num, T: Num, a: Num,
              b: Num, delta: Num, s0: Num, gap_max: Num | None = None, **_) -> Tensor:
    """Unsaturated IDM acceleration a [1 - (v/v0)^delta - (s*/s)^2].

    ``gap_max`` (optional, a controller's design bound; humans have none) caps the desired
    gap's steady part ``s0 + v T`` at ``gap_max sqrt(1 - (v/v0)^delta)``, so that the
    steady gap ``s*/sqrt(1 - (v/v0)^delta)`` stays at or below ``gap_max`` at every speed
    (IDM's own steady gap grows without bound as ``v`` nears ``v0``). Where the cap does
    not bind, the result is IDM's to the bit.
    """
    dv = v - v_leader
    speed_term = (v / v0) ** delta
    headway = v * T
    if gap_max is not None:
        headway = torch.minimum(headway, gap_max * torch.sqrt((1.0 - speed_term).clamp_min(0.0)) - s0)
    s_star = s0 + (headway + v * dv / (2.0 * torch.sqrt(torch.as_tensor(a * b)))).clamp_min(0.0)
    return a * (1.0 - speed_term - (s_star / gap.clamp_min(1e-3)) ** 2)


def saturate_accel(acc: Tensor, gap: Tensor, v: Tensor, v_leader: Tensor, *,
                   a_min: Num, a_max: Num, emergency_brake: bool = True) -> Tensor:
    """Clip to [a_min, a_max] and apply the DeeP-LCC emergency-braking rule.

    When the deceleration needed to match the leader's speed within the gap,
    (v^2 - v_leader^2) / (2 s), exceeds |a_min|, the vehicle brakes at a_min.
    """
    acc = torch.minimum(torch.maximum(acc, torch.as_tensor(a_min, dtype=acc.dtype)),
                        torch.as_tensor(a_max, dtype=acc.dtype))
    if emergency_brake:
        need = (v * v - v_leader * v_leader) / (2.0 * gap.clamp_min(1e-3))
        a_min_t = torch.as_tensor(a_min, dtype=acc.dtype)
        acc = torch.where(need > a_min_t.abs(), a_min_t.expand_as(acc), acc)
    return acc


def car_following_accel(model: str, gap: Tensor, v: Tensor, v_leader: Tensor,
                        params: dict[str, Num]) -> Tensor:
    """Saturated acceleration of a human driver under ``model`` ("ovm" or "idm")."""
    if model == "ovm":
        acc = ovm_accel(gap, v, v_leader, **params)
    elif model == "idm":
        acc = idm_accel(gap, v, v_leader, **params)
    else:
        raise ValueError(f"hdv_model must be 'ovm' or 'idm', got {model!r}")
    return saturate_accel(acc, gap, v, v_leader, a_min=params["a_min"], a_max=params["a_max"])


def integrate(pos: Tensor, vel: Tensor, acc: Tensor, dt: float, method: str = "euler") -> tuple[Tensor, Tensor, Tensor]:
    """Advance positions and speeds one step; speeds never go negative.

    Methods:
      - ``"euler"``: v' = v + a dt, x' = x + v' dt (SUMO's default update rule);
      - ``"euler_explicit"``: x' = x + v dt, v' = v + a dt (the DeeP-LCC reference);
      - ``"ballistic"``: x' = x + (v + v') dt / 2 (SUMO's ballistic option).

    Returns ``(pos', vel', executed_acc)``, where the executed acceleration accounts
    for the stop at v = 0.
    """
    new_vel = (vel + acc * dt).clamp_min(0.0)
    executed = (new_vel - vel) / dt
    if method == "euler":
        new_pos = pos + new_vel * dt
    elif method == "euler_explicit":
        new_pos = pos + vel * dt
    elif method == "ballistic":
        new_pos = pos + 0.5 * (vel + new_vel) * dt
    else:
        raise ValueError(f"integration must be 'euler', 'euler_explicit' or 'ballistic', got {method!r}")
    return new_pos, new_vel, executed


def leader_gaps(pos: Tensor, vehicle_length: float, ring_length: float | None) -> Tensor:
    """Bumper-to-bumper gap of every vehicle to the one ahead (index i-1).

    Vehicles are ordered head first (index 0) along the direction of travel. On a
    ring (``ring_length`` given) the head's leader is the last vehicle, one lap
    ahead, and gaps wrap modulo the ring length; on an open road the head has no
    leader and gets ``+inf``.
    """
    ahead = torch.roll(pos, shifts=1, dims=-1)
    if ring_length is not None:
        return torch.remainder(ahead - pos, ring_length) - vehicle_length
    gap = ahead - pos - vehicle_length
    gap[..., 0] = float("inf")
    return gap


def idm_equilibrium_speed(gap: Tensor | float, *, v0: Num, T: Num, s0: Num, delta: Num, iters: int = 60,
                          **_) -> Tensor:
    """Speed at which IDM drives steadily at bumper gap ``gap``: the root of ``a(gap, v, v) = 0``.

    ``(s0 + v T) / sqrt(1 - (v / v0)^delta) = gap``, solved by bisection on ``[0, v0]``
    (the left side grows with ``v``); 0 when ``gap <= s0``. On a ring of length ``L``
    with ``n`` identical cars of length ``l`` the uniform flow has ``gap = L / n - l``.
    """
    gap = torch.as_tensor(gap, dtype=torch.float64)
    lo = torch.zeros_like(gap)
    hi = torch.full_like(gap, float(v0))
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        need = (s0 + mid * T) / torch.sqrt((1.0 - (mid / v0) ** delta).clamp_min(1e-12))
        too_fast = need > gap
        hi = torch.where(too_fast, mid, hi)
        lo = torch.where(too_fast, lo, mid)
    return 0.5 * (lo + hi)


# ----------------------------------------------------------------------------- SUMO's speed mode 95
NUMERICAL_EPS = 0.001  # m; SUMO's NUMERICAL_EPS (the stop-speed gap margin)
EMERGENCY_DECEL_AMPLIFIER = 1.2  # SUMO's factor on the emergency deceleration it computes


@dataclass(frozen=True)
class KraussParams:
    """The CAV's SUMO vType (``carFollowModel="Krauss"``, ``sigma=0``) that the ring's SUMO backend uses.

    ``accel`` / ``decel`` are the scenario's ``cav_accel_bounds`` (``(-decel, accel)``);
    ``emergency_decel`` is ``max(decel, 9)``.
    """

    tau: float = 1.0
    min_gap: float = 2.5
    emergency_decel: float = 9.0


def sumo_brake_gap(speed: Tensor, decel: Num, dt: float) -> Tensor:
    """Distance covered braking from ``speed`` at ``decel`` to a stop, step by step (SUMO's Euler ``brakeGap``, no headway).

    With ``k = floor(speed / (decel dt))`` full braking steps the distance is
    ``dt (k speed - decel dt k (k + 1) / 2)``.
    """
    red = decel * dt
    k = torch.floor(speed / red)
    return dt * (k * speed - red * k * (k + 1.0) / 2.0)


def sumo_safe_stop_speed(gap: Tensor, decel: Num, tau: float, dt: float) -> Tensor:
    """Largest speed from which the vehicle stops within ``gap`` braking ``decel`` after a reaction time ``tau``.

    SUMO's ``maximumSafeStopSpeedEuler``: the number ``n`` of whole braking steps that fit in
    ``g = gap - NUMERICAL_EPS`` (distance ``h = b dt n (n - 1) / 2 + n b tau`` with ``b = decel dt``),
    plus the speed ``(g - h) / (n dt + tau)`` that uses up the rest; 0 when ``g < 0``.
    """
    g = gap - NUMERICAL_EPS
    b = decel * dt
    s, t = dt, tau
    n = torch.floor(0.5 - (t - 0.5 * torch.sqrt((s * s + 4.0 * (s * (2.0 * g.clamp_min(0.0) / b - t) + t * t))
                                                .clamp_min(0.0))) / s).clamp_min(0.0)
    h = 0.5 * n * (n - 1.0) * b * s + n * b * t
    x = n * b + (g - h) / (n * s + t)
    return torch.where(g < 0, torch.zeros_like(x), x)


def sumo_emergency_decel(gap: Tensor, v: Tensor, v_leader: Tensor, leader_decel: Num, emergency_decel: Num) -> Tensor:
    """SUMO's ``calculateEmergencyDeceleration``: the braking that still avoids the leader when it brakes at most ``leader_decel``.

    ``b1 = v^2 / (2 (gap + v_leader^2 / (2 leader_decel)))`` if that is at most ``leader_decel``,
    else ``b2 = (v^2 - v_leader^2) / (2 gap)``; ``emergency_decel`` when ``gap <= 0``.
    """
    b1 = 0.5 * v * v / (gap + 0.5 * v_leader * v_leader / leader_decel)
    b2 = 0.5 * (v * v - v_leader * v_leader) / gap.clamp_min(1e-12)
    out = torch.where(b1 <= leader_decel, b1, b2)
    return torch.where(gap <= 0, torch.full_like(out, float(emergency_decel)), out)


def sumo_safe_follow_speed(gap: Tensor, v: Tensor, v_leader: Tensor, *, decel: Num, leader_decel: Num, tau: float,
                           emergency_decel: Num, dt: float) -> Tensor:
    """SUMO's Krauss safe speed (``MSCFModel::maximumSafeFollowSpeed``, Euler update), ``sigma = 0``.

    ``gap`` is net of the follower's ``minGap`` (SUMO's gap: leader's back minus own front
    minus ``minGap``). The safe speed stops the follower, reacting after ``tau`` and braking
    ``decel``, within the gap plus the leader's own braking distance at ``max(decel,
    leader_decel)`` (:func:`sumo_safe_stop_speed`, :func:`sumo_brake_gap`). If that needs
    harder braking than ``decel`` (and ``emergency_decel != decel``) SUMO softens it to
    ``1.2 x`` :func:`sumo_emergency_decel`, at least ``decel``, at most the first answer's.
    A negative gap gives ``v - emergency_decel dt``. Never below 0.
    """
    f = dict(dtype=v.dtype, device=v.device)
    decel, leader_decel, emergency_decel = (torch.as_tensor(x, **f) for x in (decel, leader_decel, emergency_decel))
    x = sumo_safe_stop_speed(gap + sumo_brake_gap(v_leader, torch.maximum(decel, leader_decel), dt), decel, tau, dt)
    x = torch.where(gap >= 0, x, (v - emergency_decel * dt).clamp_min(0.0))
    orig = (v - x) / dt
    soft = EMERGENCY_DECEL_AMPLIFIER * sumo_emergency_decel(gap, v, v_leader, leader_decel, emergency_decel)
    soft = torch.minimum(torch.maximum(soft, decel), orig)
    harder = (orig > decel + NUMERICAL_EPS) & (decel != emergency_decel)
    x = torch.where(harder, (v - soft * dt).clamp_min(0.0), x)
    return x


def sumo_speed_mode_95(accel: Tensor, gap: Tensor, v: Tensor, v_leader: Tensor, *, accel_max: Num, decel: Num,
                       leader_decel: Num, dt: float, params: KraussParams = KraussParams()) -> tuple[Tensor, Tensor]:
    """The acceleration SUMO executes for a ``setSpeed(max(0, v + accel dt))`` command under speed mode 95.

    Args:
        accel: commanded acceleration (m/s^2).
        gap: bumper-to-bumper gap to the leader (m), before ``minGap``.
        v, v_leader: the vehicle's and its leader's speed (m/s).
        accel_max, decel: the vehicle's vType accel / decel (> 0; the scenario's ``cav_accel_bounds``).
        leader_decel: the leader vType's ``decel`` (> 0; SUMO uses its apparent decel, = decel).
        dt: step length (s).
        params: the vehicle's Krauss ``tau``, ``minGap`` and ``emergencyDecel``.

    SUMO's Influencer bounds the commanded speed in this order (bits 0-2 of the mode): at
    most the Krauss safe speed (:func:`sumo_safe_follow_speed` on the gap net of
    ``minGap``), at most ``v + accel_max dt``, at least ``max(0, v - decel dt)``. The
    last bound wins: under speed mode 95 SUMO never brakes harder than ``decel`` (its
    emergency braking needs bit 2 off), so a command can still end in a collision when
    the safe speed asks for more. Computed in float64 (SUMO's precision), returned in
    ``accel``'s dtype. Measured against libsumo 1.28 step by step: equal to 1e-13 m/s^2
    (``benchmarks/sumo_speed_mode_agreement.py``).

    Returns ``(executed_accel, overridden)``: the executed acceleration and a bool tensor,
    True where the executed speed differs from ``max(0, v + accel dt)`` by more than
    1e-6 m/s (the SUMO env's ``override_steps`` rule).

    >>> a, over = sumo_speed_mode_95(torch.tensor([3.0, 1.0]), torch.tensor([10.0, 80.0]), torch.tensor([15.0, 15.0]),
    ...                              torch.tensor([10.0, 15.0]), accel_max=3.0, decel=3.0, leader_decel=3.0, dt=0.1)
    >>> over.tolist(), [round(x, 3) for x in a.tolist()]
    ([True, False], [-3.0, 1.0])
    """
    for name, x in (("accel_max", accel_max), ("decel", decel), ("leader_decel", leader_decel), ("dt", dt),
                    ("params.tau", params.tau), ("params.emergency_decel", params.emergency_decel)):
        t = torch.as_tensor(x)
        if not (bool(torch.isfinite(t).all()) and bool((t > 0).all())):
            raise ValueError(f"sumo_speed_mode_95: {name}={x!r} is invalid; allowed: finite values > 0")
    if not (math.isfinite(params.min_gap) and params.min_gap >= 0):
        raise ValueError(f"sumo_speed_mode_95: params.min_gap={params.min_gap!r} is invalid; allowed: finite, >= 0 (m)")
    d = dict(dtype=torch.float64)
    a, g, v64, vl, dec, ldec, amax, emerg = (torch.as_tensor(x).to(**d) for x in (
        accel, gap, v, v_leader, decel, leader_decel, accel_max, params.emergency_decel))
    v_cmd = (v64 + a * dt).clamp_min(0.0)
    v_safe = sumo_safe_follow_speed(g - params.min_gap, v64, vl, decel=dec, leader_decel=ldec, tau=params.tau,
                                    emergency_decel=emerg, dt=dt)
    v_next = torch.minimum(v_cmd, v_safe)  # bit 0: the safe speed
    v_next = torch.minimum(v_next, v64 + amax * dt)  # bit 1: max acceleration
    v_next = torch.maximum(v_next, (v64 - dec * dt).clamp_min(0.0))  # bit 2: max deceleration
    overridden = (v_next - v_cmd).abs() > 1e-6
    return ((v_next - v64) / dt).to(torch.as_tensor(accel).dtype), overridden
