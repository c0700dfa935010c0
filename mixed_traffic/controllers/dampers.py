"""Classical stop-and-go wave dampers for the CAV, as TorchRL policy modules.

Each controller is a ``TensorDictModule`` reading the env's ``("cav", ...)`` entries and
writing ``"action"`` (m/s^2, clipped to the CAV's bounds), so the evaluation runs them
like any learned policy. The wave report (:mod:`mixed_traffic.evaluation.waves`)
compares them on the ``ring_wave`` scenario:

* ``human``: the CAV drives like the ring's humans (IDM with their parameters and
  their per-step acceleration noise): the all-human ring;
* ``idm``: the same IDM without noise (IDM-as-CAV);
* ``follower_stopper``: FollowerStopper (Stern et al. 2018, Eq. 1-2);
* ``pi_saturation``: PI with saturation (Stern et al. 2018, Eq. 3-6);
* ``fs_then_pi``: FollowerStopper (its ramped set point, typically) until ``switch`` s,
  then PI with saturation, the acceleration blended linearly over ``switch_s`` s
  (:class:`Handover`): FollowerStopper's low set point dissolves the start's wave, PI's
  set point, its own average speed, then holds the dissolved ring at the speed it sustains.

Reference: R. E. Stern et al., "Dissipation of stop-and-go waves via control of
autonomous vehicles: Field experiments", Transportation Research Part C 89 (2018)
205-221 (arXiv:1705.01693). Both dampers compute a commanded speed ``v_cmd``; as in
Flow's implementation of them, the acceleration is ``(v_cmd - v) / dt`` clipped to the
CAV's bounds.

>>> from mixed_traffic import make_env
>>> from mixed_traffic.controllers.dampers import make_damper
>>> env = make_env("ring_wave", batch_size=2, seed=0)
>>> td = env.rollout(100, make_damper("follower_stopper", env))
>>> bool(td["next", "collision"].any())
False
"""

from __future__ import annotations

import dataclasses
import inspect

import torch
from tensordict.nn import TensorDictModule
from torch import nn

from mixed_traffic.controllers.classic import CarFollowingCAV, action_bounds
from mixed_traffic.physics import car_following_accel, idm_equilibrium_speed

Tensor = torch.Tensor
DAMPERS = ("human", "idm", "follower_stopper", "pi_saturation", "fs_then_pi")


class FollowerStopper(nn.Module):
    """FollowerStopper (Stern et al. 2018, Eq. 1-2): a speed command below the leader's speed
    near three braking envelopes, the set point ``U`` far from them.

    ``dx_k = dx0_k + (dv_-)^2 / (2 d_k)`` with ``dv_- = min(v_lead - v, 0)``,
    ``dx0 = (4.5, 5.25, 6.0)`` m, ``d = (1.5, 1.0, 0.5)`` m/s^2 (the paper's values);
    ``w = min(max(v_lead, 0), U)`` and::

        v_cmd = 0                                          gap <= dx_1
                w (gap - dx_1) / (dx_2 - dx_1)             dx_1 < gap <= dx_2
                w + (U - w) (gap - dx_2) / (dx_3 - dx_2)   dx_2 < gap <= dx_3
                U                                          gap > dx_3

    ``U`` (the set point, chosen by the operator in the field test) is ``u_ratio`` times
    the uniform-flow speed of the row's ring (``("traffic", "ring_length")``) computed
    from the humans' IDM, unless a fixed ``U`` is given.

    With ``ramp_to`` the ratio follows a schedule in episode time (``("traffic", "time")``):
    ``u_ratio`` until ``ramp_start``, linear to ``ramp_to`` at ``ramp_end``, ``ramp_to`` after
    it (s): a low set point dissolves the start's wave, then the set point rises to near
    the uniform flow, which the dissolved ring holds (``docs/wave.md``).
    """

    DX0 = (4.5, 5.25, 6.0)
    D = (1.5, 1.0, 0.5)

    def __init__(self, *, dt: float, low: float, high: float, U: float | None = None, u_ratio: float = 1.0,
                 n_vehicles: int = 22, vehicle_length: float = 5.0, hdv_params: dict | None = None,
                 ramp_to: float | None = None, ramp_start: float = 150.0, ramp_end: float = 300.0):
        super().__init__()
        if ramp_to is not None and not (ramp_to > 0 and 0 <= ramp_start < ramp_end):
            raise ValueError(f"FollowerStopper: ramp_to={ramp_to!r}, ramp_start={ramp_start!r}, ramp_end={ramp_end!r} "
                             "are invalid; allowed: ramp_to > 0 and 0 <= ramp_start < ramp_end (s)")
        self.ramp = None if ramp_to is None else (float(ramp_to), float(ramp_start), float(ramp_end))
        if U is None and hdv_params is None:
            raise ValueError("FollowerStopper: give U (m/s) or hdv_params (to compute the uniform-flow speed)")
        if U is not None and not U > 0:
            raise ValueError(f"FollowerStopper: U={U!r} is invalid; allowed: > 0 (m/s) or None")
        self.dt, self.low, self.high = float(dt), float(low), float(high)
        self.U, self.u_ratio = U, float(u_ratio)
        self.n_vehicles, self.vehicle_length = int(n_vehicles), float(vehicle_length)
        self.hdv_params = dict(hdv_params or {})

    def set_point(self, ring_length: Tensor) -> Tensor:
        if self.U is not None:
            return torch.full_like(ring_length, float(self.U))
        cached = self.__dict__.get("_set_point_cache")
        if cached is not None and cached[0].shape == ring_length.shape and torch.equal(cached[0], ring_length):
            return cached[1]
        gap = ring_length.double() / self.n_vehicles - self.vehicle_length
        U = (self.u_ratio * idm_equilibrium_speed(gap, **self.hdv_params)).to(ring_length.dtype)
        self.__dict__["_set_point_cache"] = (ring_length.clone(), U)
        return U

    def command(self, gap: Tensor, speed: Tensor, leader_speed: Tensor, U: Tensor) -> Tensor:
        dv_minus = (leader_speed - speed).clamp_max(0.0)
        dx1, dx2, dx3 = (x0 + dv_minus**2 / (2.0 * d) for x0, d in zip(self.DX0, self.D, strict=True))
        w = torch.minimum(leader_speed.clamp_min(0.0), U)
        v_cmd = torch.where(gap <= dx1, torch.zeros_like(speed),
                            torch.where(gap <= dx2, w * (gap - dx1) / (dx2 - dx1),
                                        torch.where(gap <= dx3, w + (U - w) * (gap - dx2) / (dx3 - dx2), U)))
        return v_cmd

    def forward(self, gap: Tensor, speed: Tensor, leader_speed: Tensor, ring_length: Tensor,
                time: Tensor | None = None) -> Tensor:
        U = self.set_point(ring_length).expand_as(speed)
        if self.ramp is not None:
            to, t1, t2 = self.ramp
            f = ((time - t1) / (t2 - t1)).clamp(0.0, 1.0).expand_as(speed)
            U = U * (1.0 + (to / self.u_ratio - 1.0) * f)
        v_cmd = self.command(gap, speed, leader_speed, U)
        return ((v_cmd - speed) / self.dt).clamp(self.low, self.high)


class PISaturation(nn.Module):
    """PI controller with saturation (Stern et al. 2018, Eq. 3-6).

    ``U`` is the CAV's own mean speed over the last 38 s (``("cav", "speed_avg")``, window
    ``cav_speed_window``), ``v_target = U + v_catch min(max((gap - g_l) / (g_u - g_l), 0), 1)``,
    ``alpha = min(max((gap - dx_s) / gamma, 0), 1)`` with ``dx_s = max(2 (v_lead - v), 4)`` m,
    ``beta = 1 - alpha / 2`` and
    ``v_cmd = beta (alpha v_target + (1 - alpha) v_lead) + (1 - beta) v_cmd_prev``,
    with the paper's ``g_l = 7`` m, ``g_u = 30`` m, ``v_catch = 1`` m/s, ``gamma = 2`` m.

    ``v_cmd_prev`` is taken as the CAV's current speed: with the acceleration
    ``(v_cmd - v) / dt`` the previous command is reached within one step whenever it was
    not clipped, so the module stays stateless (no recurrent state to reset per row).
    """

    def __init__(self, *, dt: float, low: float, high: float, g_l: float = 7.0, g_u: float = 30.0,
                 v_catch: float = 1.0, gamma: float = 2.0):
        super().__init__()
        self.dt, self.low, self.high = float(dt), float(low), float(high)
        self.g_l, self.g_u, self.v_catch, self.gamma = float(g_l), float(g_u), float(v_catch), float(gamma)

    def command(self, gap: Tensor, speed: Tensor, leader_speed: Tensor, speed_avg: Tensor) -> Tensor:
        v_target = speed_avg + self.v_catch * ((gap - self.g_l) / (self.g_u - self.g_l)).clamp(0.0, 1.0)
        dx_s = (2.0 * (leader_speed - speed)).clamp_min(4.0)
        alpha = ((gap - dx_s) / self.gamma).clamp(0.0, 1.0)
        beta = 1.0 - 0.5 * alpha
        return beta * (alpha * v_target + (1.0 - alpha) * leader_speed) + (1.0 - beta) * speed

    def forward(self, gap: Tensor, speed: Tensor, leader_speed: Tensor, speed_avg: Tensor) -> Tensor:
        v_cmd = self.command(gap, speed, leader_speed, speed_avg)
        return ((v_cmd - speed) / self.dt).clamp(self.low, self.high)


class Handover(nn.Module):
    """``(1 - m) * first + m * second`` with ``m = clip((time - switch) / switch_s, 0, 1)``.

    ``first`` is a :class:`FollowerStopper`, ``second`` a :class:`PISaturation`; both return
    accelerations within the same bounds, so the blend does too.
    """

    def __init__(self, first: FollowerStopper, second: PISaturation, *, switch: float = 300.0, switch_s: float = 30.0):
        super().__init__()
        if not (switch >= 0 and switch_s > 0):
            raise ValueError(f"fs_then_pi: switch={switch!r}, switch_s={switch_s!r} are invalid; allowed: switch >= 0, "
                             "switch_s > 0 (s)")
        self.first, self.second = first, second
        self.switch, self.switch_s = float(switch), float(switch_s)

    def forward(self, gap: Tensor, speed: Tensor, leader_speed: Tensor, ring_length: Tensor, time: Tensor,
                speed_avg: Tensor) -> Tensor:
        m = ((time - self.switch) / self.switch_s).clamp(0.0, 1.0).expand_as(speed)
        a_first = self.first(gap, speed, leader_speed, ring_length, time)
        return (1.0 - m) * a_first + m * self.second(gap, speed, leader_speed, speed_avg)


class HumanCAV(CarFollowingCAV):
    """The humans' car-following model driving the CAV, with optional per-step noise.

    :class:`~mixed_traffic.controllers.classic.CarFollowingCAV` plus ``N(0, noise)`` added
    to the acceleration (before the clip) from the module's own generator (seeded by
    ``seed``), as the env does for its humans: the all-human ring.
    """

    def __init__(self, model: str, params, *, low: float, high: float, noise: float = 0.0, seed: int = 0):
        super().__init__(model, params, low, high)
        self.noise = float(noise)
        self.rng = torch.Generator().manual_seed(int(seed))

    def forward(self, gap: Tensor, speed: Tensor, leader_speed: Tensor) -> Tensor:
        a = car_following_accel(self.model, gap, speed, leader_speed, self.params)
        if self.noise > 0:
            a = a + self.noise * torch.randn(a.shape, generator=self.rng).to(a)
        return a.clamp(self.low, self.high)


def _scenario(env):
    sc = getattr(env, "scenario", None)
    if sc is None and hasattr(env, "base_env"):
        sc = getattr(env.base_env, "scenario", None)
    if sc is None:
        raise ValueError("make_damper: env has no `scenario` (a car-following env from make_env is needed)")
    return sc


def damper_arguments(name: str) -> list[str]:
    """The keyword arguments :func:`make_damper` accepts for damper ``name`` (its constructor's,
    less what the env supplies: bounds, ``dt``, the ring's size and the humans' parameters)."""
    from_env = {"dt", "low", "high", "n_vehicles", "vehicle_length", "hdv_params"}

    def own(cls) -> list[str]:
        return [n for n, p in inspect.signature(cls).parameters.items()
                if p.kind is inspect.Parameter.KEYWORD_ONLY and n not in from_env]

    if name == "follower_stopper":
        return own(FollowerStopper)
    if name == "pi_saturation":
        return own(PISaturation)
    if name == "fs_then_pi":
        return own(Handover) + own(FollowerStopper)
    return []


def check_damper_arguments(name: str, kwargs) -> None:
    """Raise ``ValueError`` naming the arguments in ``kwargs`` that damper ``name`` does not take and
    listing the ones it does (:func:`damper_arguments`)."""
    allowed = damper_arguments(name)
    unknown = sorted(set(kwargs) - set(allowed))
    if unknown:
        raise ValueError(f"{name}: arguments {unknown} are invalid; allowed: {allowed or 'none'}")


def make_damper(name: str, env, *, seed: int = 0, **kwargs) -> TensorDictModule:
    """A wave damper (or the human/IDM baselines) driving every CAV of ``env``.

    Args:
        name: one of :data:`DAMPERS`.
        env: a car-following env (bounds from its action spec, humans' model and ``dt``
            from its scenario).
        seed: generator seed of the ``human`` controller's noise.
        **kwargs: controller arguments (``U``, ``u_ratio``, ``ramp_to``, ``ramp_start``, ``ramp_end`` for
            ``follower_stopper``;
            ``g_l``, ``g_u``, ``v_catch``, ``gamma`` for ``pi_saturation``; for ``fs_then_pi``
            ``switch`` and ``switch_s`` and FollowerStopper's, defaults ``u_ratio=0.87``,
            ``ramp_to=1.0``, ``switch=300``, ``switch_s=30``; none for ``human`` and ``idm``).
            Any other name raises ``ValueError`` listing the allowed ones (:func:`damper_arguments`).
    """
    if name not in DAMPERS:
        raise ValueError(f"damper {name!r} is invalid; allowed: {list(DAMPERS)}")
    check_damper_arguments(name, kwargs)
    sc = _scenario(env)
    low, high = action_bounds(env)
    params = dataclasses.asdict(sc.hdv_defaults())
    base = [("cav", "gap"), ("cav", "speed"), ("cav", "leader_speed")]
    if name in ("human", "idm"):
        noise = sc.accel_noise if name == "human" else 0.0
        module = HumanCAV(sc.hdv_model, sc.hdv_defaults(), low=low, high=high, noise=noise, seed=seed)
        return TensorDictModule(module, in_keys=base, out_keys=["action"])

    def follower_stopper(**fs_kwargs) -> FollowerStopper:
        if sc.hdv_model != "idm" and fs_kwargs.get("U") is None:
            raise ValueError(f"{name}: give U (m/s); the uniform-flow set point needs IDM humans")
        return FollowerStopper(dt=sc.dt, low=low, high=high, n_vehicles=sc.n_vehicles,
                               vehicle_length=sc.vehicle_length, hdv_params=params, **fs_kwargs)

    if name == "follower_stopper":
        module = follower_stopper(**kwargs)
        keys = [*base, ("traffic", "ring_length")] + ([("traffic", "time")] if module.ramp is not None else [])
        return TensorDictModule(module, in_keys=keys, out_keys=["action"])
    if sc.head:
        raise ValueError(f"{name}: needs ('cav', 'speed_avg'), which rings without a head provide "
                         "(head=False, e.g. 'ring_wave')")
    if name == "fs_then_pi":
        switch = {k: kwargs.pop(k) for k in ("switch", "switch_s") if k in kwargs}
        first = follower_stopper(**{"u_ratio": 0.87, "ramp_to": 1.0, **kwargs})
        module = Handover(first, PISaturation(dt=sc.dt, low=low, high=high), **switch)
        return TensorDictModule(module, in_keys=[*base, ("traffic", "ring_length"), ("traffic", "time"),
                                                 ("cav", "speed_avg")], out_keys=["action"])
    module = PISaturation(dt=sc.dt, low=low, high=high, **kwargs)
    return TensorDictModule(module, in_keys=[*base, ("cav", "speed_avg")], out_keys=["action"])


__all__ = ["make_damper", "damper_arguments", "check_damper_arguments", "FollowerStopper", "PISaturation", "Handover", "HumanCAV", "DAMPERS"]
