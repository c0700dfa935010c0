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
              b: Num, delta: Num, s0: Num, **_) -> Tensor:
    """Unsaturated IDM acceleration a [1 - (v/v0)^delta - (s*/s)^2]."""
    dv = v - v_leader
    s_star = s0 + (v * T + v * dv / (2.0 * torch.sqrt(torch.as_tensor(a * b)))).clamp_min(0.0)
    return a * (1.0 - (v / v0) ** delta - (s_star / gap.clamp_min(1e-3)) ** 2)


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
