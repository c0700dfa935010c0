"""The DeeP-LCC platoon as pure batched torch functions (float64).

One head vehicle (index 0) and ``n_followers`` followers; CAVs at ``cav_indices``
(vehicle indices, head = 0), the others human drivers (OVM or IDM, saturated,
with the emergency-braking rule and uniform acceleration noise). The update is
the explicit Euler rule of the DeeP-LCC reference (x += v dt, then v += a dt);
the head's speed is imposed each step.

Time alignment used everywhere in this package: at instant ``t`` the state gives
the output ``y(t)`` and the disturbance ``e(t) = v_head(t) - v*``, and ``u(t)`` is
the CAV acceleration applied from ``t`` to ``t + 1``.

>>> import torch
>>> cfg = PlatoonConfig()
>>> pos, vel = init_state(2, cfg)
>>> y = measure(pos, vel, cfg)
>>> y.shape
torch.Size([2, 10])
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import torch

from mixed_traffic.physics import (
    IDMParams,
    OVMParams,
    car_following_accel,
    integrate,
    ovm_equilibrium_gap,
    saturate_accel,
)

Tensor = torch.Tensor
DTYPE = torch.float64


@dataclass(frozen=True)
class PlatoonConfig:
    """Platoon, driver model and measurement of the DeeP-LCC setting (measurement type 3)."""

    n_followers: int = 8
    cav_indices: tuple[int, ...] = (3, 6)
    dt: float = 0.05
    hdv_model: str = "ovm"  # "ovm" (OVMParams()) or "idm" (IDMParams.deeplcc())
    hdv_params: dict = field(default_factory=dict)  # overrides of the model's parameters
    accel_noise: float = 0.1  # HDV acceleration noise U[-x, x] (m/s^2)
    v_star: float = 15.0
    s_star: float = 20.0
    vehicle_length: float = 5.0
    a_min: float = -5.0
    a_max: float = 2.0

    def __post_init__(self):
        if self.hdv_model not in ("ovm", "idm"):
            raise ValueError(f"PlatoonConfig: hdv_model={self.hdv_model!r} is invalid; allowed: 'ovm', 'idm'")
        if self.n_followers < 1:
            raise ValueError(f"PlatoonConfig: n_followers={self.n_followers} is invalid; allowed: >= 1")
        for i in self.cav_indices:
            if not 1 <= i <= self.n_followers:
                raise ValueError(f"PlatoonConfig: cav_indices={self.cav_indices} is invalid; "
                                 f"allowed: distinct integers in [1, {self.n_followers}]")
        if not self.dt > 0:
            raise ValueError(f"PlatoonConfig: dt={self.dt} is invalid; allowed: > 0")
        if not self.accel_noise >= 0:
            raise ValueError(f"PlatoonConfig: accel_noise={self.accel_noise} is invalid; allowed: >= 0")
        object.__setattr__(self, "_param_dict", dataclasses.asdict(self.hdv_param_set()))

    @property
    def n_vehicles(self) -> int:
        return self.n_followers + 1

    @property
    def m(self) -> int:
        return len(self.cav_indices)

    @property
    def p(self) -> int:
        return self.n_followers + self.m

    def hdv_param_set(self):
        base = OVMParams() if self.hdv_model == "ovm" else IDMParams.deeplcc()
        return dataclasses.replace(base, **self.hdv_params)

    def equilibrium_gap(self, v: float) -> float:
        """Bumper-to-bumper gap at which an HDV holds speed ``v``."""
        p = self.hdv_param_set()
        if self.hdv_model == "ovm":
            return ovm_equilibrium_gap(v, p.v_max, p.s_st, p.s_go)
        return (p.s0 + v * p.T) / (1.0 - (v / p.v0) ** p.delta) ** 0.5


def init_state(batch: int, cfg: PlatoonConfig, v0: float | None = None) -> tuple[Tensor, Tensor]:
    """Every vehicle at speed ``v0`` (default v*) and the HDV equilibrium gap; head at x = 0."""
    v0 = cfg.v_star if v0 is None else v0
    gap = cfg.equilibrium_gap(v0)
    pos = -torch.arange(cfg.n_vehicles, dtype=DTYPE) * (gap + cfg.vehicle_length)
    return pos.expand(batch, -1).clone(), torch.full((batch, cfg.n_vehicles), float(v0), dtype=DTYPE)


def gaps(pos: Tensor, cfg: PlatoonConfig) -> Tensor:
    """Gap of each follower to its leader, ``[B, n_followers]``."""
    return pos[:, :-1] - pos[:, 1:] - cfg.vehicle_length


def measure(pos: Tensor, vel: Tensor, cfg: PlatoonConfig, v_star: Tensor | float | None = None) -> Tensor:
    """Measurement type 3: follower speed errors, then CAV spacing errors -> ``[B, p]``."""
    v_star = cfg.v_star if v_star is None else v_star
    if isinstance(v_star, Tensor) and v_star.dim() == 1:
        v_star = v_star[:, None]
    s = gaps(pos, cfg)[:, [i - 1 for i in cfg.cav_indices]]
    return torch.cat([vel[:, 1:] - v_star, s - cfg.s_star], dim=-1)


def step(pos: Tensor, vel: Tensor, u_cav: Tensor, v_head_next: Tensor, cfg: PlatoonConfig,
         generator: torch.Generator | None = None, params: dict | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """Advance one step. Returns ``(pos', vel', executed_cav_accel [B, m])``.

    HDVs: car-following model + U[-noise, noise]; CAVs: ``u_cav`` clipped to
    ``[a_min, a_max]``, overridden by the emergency-braking rule (as in the reference).
    ``params`` (optional) replaces the config's human-driver parameters, e.g. per-vehicle
    tensors ``[B, n_followers]`` for a heterogeneous platoon.
    """
    B = pos.shape[0]
    g = gaps(pos, cfg)
    v, vl = vel[:, 1:], vel[:, :-1]
    params = cfg._param_dict if params is None else params
    acc = car_following_accel(cfg.hdv_model, g, v, vl, params)
    if cfg.accel_noise > 0:
        acc = acc + cfg.accel_noise * (2.0 * torch.rand(B, cfg.n_followers, dtype=DTYPE, generator=generator) - 1.0)
    ci = [i - 1 for i in cfg.cav_indices]
    u = u_cav.to(DTYPE).clamp(cfg.a_min, cfg.a_max)
    u = saturate_accel(u, g[:, ci], v[:, ci], vl[:, ci], a_min=cfg.a_min, a_max=cfg.a_max)
    acc[:, ci] = u
    full = torch.cat([torch.zeros(B, 1, dtype=DTYPE), acc], dim=-1)
    new_pos, new_vel, executed = integrate(pos, vel, full, cfg.dt, "euler_explicit")
    new_vel[:, 0] = v_head_next.to(DTYPE)
    return new_pos, new_vel, executed[:, 1:][:, ci]
