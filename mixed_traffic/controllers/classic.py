"""Classical car-following models driving the CAV: IDM, OVM, a soft follower, CACC and a closing-speed law as policies.

Each is a ``TensorDictModule`` reading the env's ``("cav", "gap")``, ``("cav", "speed")``
and ``("cav", "leader_speed")`` (CACC also ``("cav", "leader_accel")``, received over V2V) and
writing ``"action"`` (m/s^2, saturated and clipped to the CAV's bounds), so the evaluation
harness runs them like any learned policy.

>>> from mixed_traffic import make_env
>>> from mixed_traffic.controllers.classic import make_classic_policy
>>> env = make_env("ring", batch_size=2, seed=0)
>>> td = env.rollout(50, make_classic_policy("idm", env))
>>> bool(td["next", "collision"].any())
False
"""

from __future__ import annotations

import dataclasses
import math

import torch
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import nn

from mixed_traffic.physics import (
    CACCParams,
    ClosingParams,
    IDMParams,
    OVMParams,
    SoftFollowerParams,
    cacc_accel,
    car_following_accel,
    closing_accel,
    soft_follower_accel,
    stop_arrival_accel,
)

CLASSIC = ("idm", "ovm", "soft", "cacc", "closing")
_PARAMS = {"idm": IDMParams, "ovm": OVMParams, "soft": SoftFollowerParams, "cacc": CACCParams, "closing": ClosingParams}
LEADER_ACCEL_KEY = ("cav", "leader_accel")  # the leader's acceleration of the last step (V2V), read by CACC


def reads_leader_accel(law) -> bool:
    """Whether ``law`` (a classical law or a wrapper of one) takes the leader's acceleration as a fourth input."""
    return bool(getattr(law, "reads_leader_accel", False))


def require_leader_accel(env, who: str) -> None:
    """Raise, naming ``who``, when ``env`` does not observe :data:`LEADER_ACCEL_KEY`."""
    if LEADER_ACCEL_KEY not in env.observation_spec.keys(True, True):
        raise ValueError(f"{who} reads the leader's acceleration {LEADER_ACCEL_KEY}, which this env does not "
                         "observe; allowed: the car-following envs (scenarios ring, ring_wave, deeplcc)")


def _reading_leader_accel(policy: TensorDictModule, env, module: nn.Module, who: str) -> TensorDictModule:
    """``module`` (a wrapper of ``policy``'s law that reads the leader's acceleration) as a policy with ``policy``'s
    keys and :data:`LEADER_ACCEL_KEY`; raises, naming ``who``, where ``env`` does not observe that key."""
    require_leader_accel(env, who)
    keys = list(policy.in_keys) + ([] if LEADER_ACCEL_KEY in policy.in_keys else [LEADER_ACCEL_KEY])
    return TensorDictModule(module, in_keys=keys, out_keys=list(policy.out_keys))


def _param_checks(model: str, p: dict) -> tuple:
    """``(name, ok, allowed)`` for each range a model's parameters must keep (none for IDM and OVM)."""
    if model == "soft":
        return (("brake_opening", 0.0 <= p["brake_opening"] <= 1.0, "[0, 1]"),
                ("v_ref", p["v_ref"] > 0.0, "> 0 (inf: no scaling)"),
                ("kv_closing_near", p["kv_closing_near"] >= 0.0, ">= 0 (0: off)"),
                ("gap_cap", p["gap_cap"] > 0.0, "> 0 (inf: no cap)"),
                ("ks_edge", p["ks_edge"] >= 0.0, ">= 0 (0: off)"),
                ("match_h_min", p["match_h_min"] >= 0.0, ">= 0 (0: a fixed floor)"),
                ("match_h_max", p["match_h_max"] >= p["match_h_min"],
                 f">= match_h_min ({p['match_h_min']}), so the band never narrows"),
                ("match_gap_max", p["match_gap_max"] > max(p["match_gap_min"], 0.0),
                 f"> match_gap_min ({p['match_gap_min']}) and > 0 (inf: off)"))
    if model == "cacc":
        return (("h", p["h"] >= 0.0, ">= 0 (s)"), ("e_max", p["e_max"] > 0.0, "> 0 (inf: no cap)"),
                *((k, p[k] >= 0.0, ">= 0") for k in ("ka", "kv", "ks")))
    if model == "closing":
        return (("target", p["target"] > 0.0, "> 0 (m)"), ("decel", p["decel"] > 0.0, "> 0 (m/s^2)"),
                ("closing_max", p["closing_max"] > 0.0, "> 0 (m/s)"), ("k", p["k"] > 0.0, "> 0 (1/s)"),
                ("a_max", p["a_max"] > 0.0, "> 0 (m/s^2)"), ("ka_brake", p["ka_brake"] >= 0.0, ">= 0"))
    return ()


class CarFollowingCAV(nn.Module):
    """``a = clip(model(gap, v, v_leader), low, high)`` with the model's saturation rules; CACC also reads
    the leader's acceleration (``model(gap, v, v_leader, a_leader)``; :attr:`reads_leader_accel`)."""

    def __init__(self, model: str, params, low: float, high: float, *, gap_max: float | None = None,
                 v0_leader: float | None = None):
        super().__init__()
        if model not in CLASSIC:
            raise ValueError(f"classic controller {model!r} is invalid; allowed: {list(CLASSIC)}")
        self.model = model
        self.params = {f.name: float(getattr(params, f.name)) for f in dataclasses.fields(params)
                       if getattr(params, f.name) is not None}  # None: the law's own default (soft kv_closing)
        for name, ok, allowed in _param_checks(model, self.params):
            if not ok:
                raise ValueError(f"{model} parameter {name} = {self.params[name]} is invalid; allowed: {allowed}")
        if gap_max is not None:
            if model != "idm":
                raise ValueError(f"gap_max is an IDM controller's bound; {model!r} has none")
            if not gap_max > self.params["s0"]:
                raise ValueError(f"gap_max must be above the standstill gap s0 = {self.params['s0']} m, "
                                 f"got {gap_max}")
            self.params["gap_max"] = float(gap_max)
        if v0_leader is not None:
            if model != "idm":
                raise ValueError(f"v0_leader is an IDM controller's desired speed; {model!r} has none")
            if not float(v0_leader) > 0.0:
                raise ValueError(f"v0_leader = {v0_leader} is invalid; allowed: > 0 (the desired speed's multiple of "
                                 "the leader's speed), or None")
        self.v0_leader = None if v0_leader is None else float(v0_leader)
        self.reads_leader_accel = model == "cacc" or (model == "closing" and self.params["ka_brake"] > 0.0)
        self.low, self.high = float(low), float(high)

    def forward(self, gap: torch.Tensor, speed: torch.Tensor, leader_speed: torch.Tensor,
                leader_accel: torch.Tensor | None = None) -> torch.Tensor:
        if self.model == "cacc":
            if leader_accel is None:
                raise ValueError("cacc reads the leader's acceleration: pass leader_accel")
            a = cacc_accel(gap, speed, leader_speed, leader_accel, **self.params)
        elif self.model == "soft":
            a = soft_follower_accel(gap, speed, leader_speed, **self.params)
        elif self.model == "closing":
            a = closing_accel(gap, speed, leader_speed, leader_accel, **self.params)
        else:
            params = self.params
            if self.v0_leader is not None:  # IDM whose desired speed is v0_leader times the leader's, at least v0
                params = {**params, "v0": torch.clamp(self.v0_leader * leader_speed, min=params["v0"])}
            a = car_following_accel(self.model, gap, speed, leader_speed, params)
        return a.clamp(self.low, self.high)


class SpeedScheduledCAV(nn.Module):
    """``w(v) low(gap, v, v_lead) + (1 - w(v)) high(gap, v, v_lead)``, ``w`` falling linearly from 1 at
    ``v_low`` to 0 at ``v_high`` (m/s): one law below ``v_low``, the other above ``v_high``.

    Gain scheduling by speed, the classical way of joining two controllers that each hold only over part
    of the speed range (a follower that lets the gap float at low speed, one that keeps it short at high
    speed). A convex blend, so with both laws clipped to the same bounds the blend stays within them.
    ``on="leader_speed"`` schedules on the leader's speed instead of the car's own (a law chosen by how fast the
    traffic ahead drives, not by how fast the car happens to be going while it catches up). TorchRL has no such
    module.
    """

    def __init__(self, low: nn.Module, high: nn.Module, v_low: float, v_high: float, on: str = "speed"):
        super().__init__()
        if not 0.0 <= v_low < v_high:
            raise ValueError(f"speed schedule v_low = {v_low}, v_high = {v_high} is invalid; "
                             "allowed: 0 <= v_low < v_high (m/s)")
        if on not in ("speed", "leader_speed"):
            raise ValueError(f"speed schedule on = {on!r} is invalid; allowed: 'speed', 'leader_speed'")
        self.low, self.high = low, high
        self.v_low, self.v_high, self.on = float(v_low), float(v_high), on

    @property
    def reads_leader_accel(self) -> bool:
        return reads_leader_accel(self.low) or reads_leader_accel(self.high)

    def forward(self, gap: torch.Tensor, speed: torch.Tensor, leader_speed: torch.Tensor, *extra) -> torch.Tensor:
        v = speed if self.on == "speed" else leader_speed
        w = ((self.v_high - v) / (self.v_high - self.v_low)).clamp(0.0, 1.0)
        return w * self.low(gap, speed, leader_speed, *extra) + (1.0 - w) * self.high(gap, speed, leader_speed, *extra)


def speed_scheduled_policy(low: TensorDictModule, high: TensorDictModule, v_low: float,
                           v_high: float, on: str = "speed") -> TensorDictModule:
    """Two policies of :func:`make_classic_policy` joined by speed (:class:`SpeedScheduledCAV`): ``low``
    drives below ``v_low``, ``high`` above ``v_high``, a linear blend between; ``on="leader_speed"``: by the
    leader's speed.

    >>> from mixed_traffic import make_env
    >>> from mixed_traffic.physics import SOFT_SCALED
    >>> env = make_env("ring", batch_size=2, seed=0)
    >>> pol = speed_scheduled_policy(make_classic_policy("soft", env, **SOFT_SCALED),
    ...                              make_classic_policy("idm", env, s0=7.0, v0=60.0, gap_max=27.0), 10.0, 16.0)
    >>> bool(env.rollout(50, pol)["next", "collision"].any())
    False
    """
    in_keys = list(low.in_keys) + [k for k in high.in_keys if k not in low.in_keys]  # CACC adds leader_accel
    return TensorDictModule(SpeedScheduledCAV(low.module, high.module, v_low, v_high, on=on),
                            in_keys=in_keys, out_keys=list(low.out_keys))


class LeaderBrakeFloor(nn.Module):
    """``max(law(gap, v, v_leader), min(-floor, a_leader - margin))``: a law that brakes at most ``floor``
    (m/s^2) harder than needed to match its leader's braking plus ``margin``.

    In a base scheduled by speed (:class:`SpeedScheduledCAV`) two laws can want different gaps at the same
    speed: below 18 m/s the ring's base is an IDM that wants about 25 m, from 18 m/s band laws that let the
    gap float down to 10 m. A leader that slows gently takes the car from one into the other in a gap the
    second accepts, and the first brakes at up to 3 m/s^2 to open it within seconds (sine_wide,
    docs/results.md). With the leader's acceleration received over V2V (``("cav", "leader_accel")``) the law
    brakes no harder than ``max(floor, |a_leader| + margin)``, which opens the gap over a longer time behind
    a gently slowing leader and leaves a leader that brakes hard (a stop, an emergency) the full answer. It
    only ever raises the command, and the stopping envelope applied to the whole base afterwards
    (:class:`StoppingEnvelope`) still caps it, so the base stays collision-free. TorchRL has no such term.
    """

    reads_leader_accel = True

    def __init__(self, law: nn.Module, *, floor: float, margin: float):
        super().__init__()
        if not floor > 0.0:
            raise ValueError(f"brake_floor = {floor} is invalid; allowed: > 0 (m/s^2)")
        if not margin >= 0.0:
            raise ValueError(f"brake_margin = {margin} is invalid; allowed: >= 0 (m/s^2)")
        self.law, self.floor, self.margin = law, float(floor), float(margin)

    def forward(self, gap: torch.Tensor, speed: torch.Tensor, leader_speed: torch.Tensor,
                leader_accel: torch.Tensor | None = None) -> torch.Tensor:
        if leader_accel is None:
            raise ValueError("a brake floor reads the leader's acceleration: pass leader_accel")
        a = self.law(gap, speed, leader_speed, leader_accel)
        return torch.maximum(a, torch.clamp(leader_accel - self.margin, max=-self.floor))


def leader_brake_floor_policy(policy: TensorDictModule, env, *, floor: float, margin: float) -> TensorDictModule:
    """``policy`` (of :func:`make_classic_policy`) with :class:`LeaderBrakeFloor`, reading the leader's
    acceleration as well.

    >>> from mixed_traffic import make_env
    >>> env = make_env("ring", batch_size=2, seed=0)
    >>> pol = leader_brake_floor_policy(make_classic_policy("idm", env), env, floor=1.0, margin=0.3)
    >>> bool(env.rollout(50, pol)["next", "collision"].any())
    False
    """
    return _reading_leader_accel(policy, env, LeaderBrakeFloor(policy.module, floor=floor, margin=margin),
                                 "a brake floor")


class CatchUp(nn.Module):
    """``law + w (accel - law)^+``: the law lifted toward ``accel`` while its leader pulls away from a large gap.

    ``w = clip((gap - gaps[0]) / (gaps[1] - gaps[0]), 0, 1) clip((v_leader - v) / dv, 0, 1)``: nothing at
    gaps up to ``gaps[0]`` (m) or while the leader is not faster, all of it from ``gaps[1]`` with the leader
    ``dv`` (m/s) faster or more. A leader that drives off from a standstill, or climbs a long ramp, at the
    head's 2 m/s^2 outruns a follower whose free-road acceleration stays under that (the ring's bases: an
    IDM envelope's ``a`` of 1.83-2.17 m/s^2), and the gap it loses over 10 s of lag leaves the band's upper
    edge. Raising ``a`` itself answers that too, but every start and everyday step then gets the harder
    acceleration. ``horizon`` (s, >= 0) gates on the gap projected that far ahead at the present speed
    difference, ``gap + horizon (v_leader - v)^+``, instead of the gap itself, so the lift begins while the
    gap is still inside the band and a leader that drives off quickly is caught before the gap has grown.
    TorchRL has no car-following law.
    """

    def __init__(self, law: nn.Module, *, accel: float, gaps: tuple[float, float], dv: float, horizon: float = 0.0):
        super().__init__()
        g0, g1 = (float(g) for g in gaps)
        if not 0.0 <= g0 < g1:
            raise ValueError(f"catch_up.gaps = {list(gaps)} is invalid; allowed: 0 <= gaps[0] < gaps[1] (m)")
        if not dv > 0.0:
            raise ValueError(f"catch_up.dv = {dv} is invalid; allowed: > 0 (m/s)")
        if not horizon >= 0.0:
            raise ValueError(f"catch_up.horizon = {horizon} is invalid; allowed: >= 0 (s)")
        self.law, self.accel, self.gaps, self.dv, self.horizon = law, float(accel), (g0, g1), float(dv), float(horizon)

    @property
    def reads_leader_accel(self) -> bool:
        return reads_leader_accel(self.law)

    def forward(self, gap: torch.Tensor, speed: torch.Tensor, leader_speed: torch.Tensor, *extra) -> torch.Tensor:
        a = self.law(gap, speed, leader_speed, *extra)
        g0, g1 = self.gaps
        closing = leader_speed - speed
        ahead = gap + self.horizon * closing.clamp_min(0.0)
        w = ((ahead - g0) / (g1 - g0)).clamp(0.0, 1.0) * (closing / self.dv).clamp(0.0, 1.0)
        return a + w * (self.accel - a).clamp_min(0.0)


def catch_up_policy(policy: TensorDictModule, *, accel: float, gaps, dv: float, horizon: float = 0.0) -> TensorDictModule:
    """``policy`` (of :func:`make_classic_policy` or :func:`speed_scheduled_policy`) with :class:`CatchUp`.

    >>> from mixed_traffic import make_env
    >>> env = make_env("ring", batch_size=2, seed=0)
    >>> pol = catch_up_policy(make_classic_policy("idm", env), accel=3.0, gaps=(15.0, 25.0), dv=4.0)
    >>> bool(env.rollout(50, pol)["next", "collision"].any())
    False
    """
    return TensorDictModule(CatchUp(policy.module, accel=accel, gaps=tuple(gaps), dv=dv, horizon=horizon),
                            in_keys=list(policy.in_keys), out_keys=list(policy.out_keys))


class LeaderAccelFeed(nn.Module):
    """``law + w(v) gain clip(a_leader, -accel_max, accel_max)``: the leader's acceleration fed forward above a speed.

    ``w(v)`` rises linearly from 0 at ``speeds[0]`` to 1 at ``speeds[1]`` (m/s, the car's own speed). A law that
    answers only the speed difference lags a head whose speed swings smoothly, and the gap swings with it; with
    the leader's acceleration (``("cav", "leader_accel")``, over V2V, as CACC reads it) in the command the car
    swings in phase and the gap stays put. Clipped at ``accel_max``, a head's hard ramps and steps (1-2 m/s^2)
    pass only that much, so their jumps in acceleration are not copied whole. It is a term of the base: the
    catch-up and the stopping envelope applied to the whole base afterwards still act on it, so the base stays
    collision-free. TorchRL has no car-following law.

    >>> import torch
    >>> law = LeaderAccelFeed(lambda gap, v, vl: torch.zeros_like(v), gain=0.8, accel_max=0.25, speeds=(18.0, 20.0))
    >>> law(torch.tensor([25.0] * 3), torch.tensor([17.0, 19.0, 22.0]), torch.tensor([22.0] * 3), torch.tensor([0.2, 0.2, 1.0]))
    tensor([0.0000, 0.0800, 0.2000])
    """

    reads_leader_accel = True

    def __init__(self, law, *, gain: float, accel_max: float, speeds: tuple[float, float]):
        super().__init__()
        v0, v1 = (float(v) for v in speeds)
        if not 0.0 < gain <= 1.0:
            raise ValueError(f"feed_forward.gain = {gain} is invalid; allowed: 0 < gain <= 1")
        if not accel_max > 0.0:
            raise ValueError(f"feed_forward.accel_max = {accel_max} is invalid; allowed: > 0 (m/s^2)")
        if not 0.0 <= v0 < v1:
            raise ValueError(f"feed_forward.speeds = {list(speeds)} is invalid; allowed: [v_off, v_on] with "
                             "0 <= v_off < v_on (m/s)")
        self.law, self.gain, self.accel_max, self.speeds = law, float(gain), float(accel_max), (v0, v1)

    def forward(self, gap: torch.Tensor, speed: torch.Tensor, leader_speed: torch.Tensor,
                leader_accel: torch.Tensor | None = None) -> torch.Tensor:
        if leader_accel is None:
            raise ValueError("a feed-forward reads the leader's acceleration: pass leader_accel")
        a = self.law(gap, speed, leader_speed, *((leader_accel,) if reads_leader_accel(self.law) else ()))
        v0, v1 = self.speeds
        w = ((speed - v0) / (v1 - v0)).clamp(0.0, 1.0)
        return a + w * self.gain * leader_accel.clamp(-self.accel_max, self.accel_max)


def leader_accel_feed_policy(policy: TensorDictModule, env, *, gain: float, accel_max: float,
                             speeds=(18.0, 20.0)) -> TensorDictModule:
    """``policy`` (of :func:`make_classic_policy` or :func:`speed_scheduled_policy`) with :class:`LeaderAccelFeed`,
    reading the leader's acceleration as well.

    >>> from mixed_traffic import make_env
    >>> env = make_env("ring", batch_size=2, seed=0)
    >>> pol = leader_accel_feed_policy(make_classic_policy("idm", env), env, gain=0.8, accel_max=0.25)
    >>> bool(env.rollout(50, pol)["next", "collision"].any())
    False
    """
    return _reading_leader_accel(
        policy, env, LeaderAccelFeed(policy.module, gain=gain, accel_max=accel_max, speeds=tuple(speeds)),
        "a feed-forward")


class StoppingEnvelope(nn.Module):
    """``min(law(gap, v, v_lead), a_stop)``: a law that never leaves the stopping-safe set.

    ``a_stop`` is the largest acceleration after which, if from the next step on the leader brakes at
    ``leader_brake`` and this car at ``min(brake, leader_brake)``, every future gap stays at or above
    ``stop_gap`` (m): the safety layer's ``"stopping"`` rule (:func:`transforms.safety_layer.safe_accel_upper`,
    exact in the env's discrete time), here as a term of the classical law itself, as Gipps' safe speed is
    of Gipps' model. From a safe state the law is then collision-free whatever the leader does within its
    bound, so a residual over it that is faded out (``ResidualAction(fade_speeds=...)``) drives without a
    layer there. Below the bound the law is unchanged. TorchRL has no car-following envelope.

    :meth:`room` is how far the command lies below the bound (``a_stop - command``, >= 0): a residual over
    this law that adds at most that much stays inside the envelope (``ResidualAction(room_key=...)``).
    ``gap_margin`` (m) and ``speed_margin`` (m/s): the rule holds for the worst state within them of the measured
    one (the gap shorter, the car faster, the leader slower), for sensors that err by up to that much.

    ``arrive_gain`` (1/s^2, > 0, or None): while the car closes on its leader the law is also held at or below
    ``-d + arrive_gain * r (1 - d / b)``, where ``r = gap - stop_gap``, ``d = (v - v_leader)^2 / (2 r)`` is the
    constant deceleration that matches the leader's speed just at ``stop_gap`` and ``b = min(brake,
    leader_brake)`` the envelope's braking (floored at ``low``; ``low`` where ``r <= 0``). Far from the edge the
    term is large and does nothing; where ``d`` reaches ``b`` it is ``-b``, and beyond, it brakes harder still
    (down to ``low``). ``a_stop`` alone is a wall: it binds only where the car must brake at ``b`` from the next step
    on, so a law whose braking fades with the closing speed (a linear law's ``k (v_leader - v)``) eases off in
    the last metres before a standstill and the wall then takes over at full braking, a command that rises and
    falls back within half a second. The arrival term is smooth in the state, so the law hands over to it
    without that kink. The envelope's bound is unchanged; :meth:`room` is measured from the command, the arrival
    term included (default None: off).

    ``stand_gap`` (m, > 0, or None): near the envelope's edge behind a braking leader the law is also held at or
    below :meth:`stand_arrival`, the constant deceleration that brings the car to rest ``stand_gap`` behind the
    point where its leader, braking on as it brakes now (its acceleration over V2V, counted at most
    ``stand_leader_brake`` m/s^2: a leader that steps its speed down at its hardest braking is not taken to stop
    at that rate), will stand (:func:`mixed_traffic.physics.stop_arrival_accel`), blended in as ``command + w min(0, a_stand - command)``
    with ``w = w_v w_s``: ``w_v = clip((stand_speeds[1] - v) / (stand_speeds[1] - stand_speeds[0]), 0, 1)`` by the
    car's speed and ``w_s = clip(1 - slack / stand_slack, 0, 1)`` by the envelope's margin in metres
    (:meth:`slack`). A law whose braking answers a slowing leader weakly at low speeds rides the envelope's edge
    down to a stop, and on that edge the car's braking converges to the envelope's full braking ``b`` as the
    leader's speed falls to 0 (on the edge ``a = (b / b_l) a_l (v_l / v) + b (v_l - v) / v``, ``-b`` at
    ``v_l = 0``): every stop ends in a dip of about 1 m/s^2 below the braking before it. The term ends the stop on
    the constant deceleration instead, off the edge. A leader that stops braking has its stopping point recede to
    infinity (the term asks for nothing), one at rest has it where it stands, so it comes and goes without a step
    in the state. Default None: off.
    """

    def __init__(self, law: nn.Module, *, stop_gap: float, dt: float, brake: float, leader_brake, low: float,
                 gap_margin: float = 0.0, speed_margin: float = 0.0, arrive_gain: float | None = None,
                 stand_gap: float | None = None, stand_speeds: tuple[float, float] = (6.0, 9.0),
                 stand_slack: float = 3.0, stand_leader_brake: float = 1.5):
        super().__init__()
        from transforms.safety_layer import safe_accel_upper  # mixed_traffic imports the transforms package lazily

        if not stop_gap > 0.0:
            raise ValueError(f"stop_gap = {stop_gap} is invalid; allowed: > 0 (m)")
        if not (gap_margin >= 0.0 and speed_margin >= 0.0):
            raise ValueError(f"gap_margin = {gap_margin}, speed_margin = {speed_margin} are invalid; allowed: >= 0")
        if arrive_gain is not None and not arrive_gain > 0.0:
            raise ValueError(f"arrive_gain = {arrive_gain} is invalid; allowed: > 0 (1/s^2), or None")
        self.gap_margin, self.speed_margin = float(gap_margin), float(speed_margin)
        self.arrive_gain = None if arrive_gain is None else float(arrive_gain)
        if stand_gap is not None:
            v_full, v_none = (float(v) for v in stand_speeds)
            if not stand_gap > 0.0:
                raise ValueError(f"stand_gap = {stand_gap} is invalid; allowed: > 0 (m), or None")
            if not 0.0 <= v_full < v_none:
                raise ValueError(f"stand_speeds = {list(stand_speeds)} is invalid; allowed: 0 <= stand_speeds[0] < "
                                 "stand_speeds[1] (m/s)")
            if not stand_slack > 0.0:
                raise ValueError(f"stand_slack = {stand_slack} is invalid; allowed: > 0 (m)")
            if not stand_leader_brake > 0.0:
                raise ValueError(f"stand_leader_brake = {stand_leader_brake} is invalid; allowed: > 0 (m/s^2)")
        self.stand_gap = None if stand_gap is None else float(stand_gap)
        self.stand_speeds, self.stand_slack = tuple(float(v) for v in stand_speeds), float(stand_slack)
        self.stand_leader_brake = float(stand_leader_brake)
        self._upper = safe_accel_upper
        self.law, self.stop_gap, self.dt, self.brake, self.low = law, float(stop_gap), float(dt), float(brake), float(low)
        self.register_buffer("leader_brake", torch.as_tensor(leader_brake, dtype=torch.float32), persistent=False)

    def _worst(self, gap: torch.Tensor, speed: torch.Tensor, leader_speed: torch.Tensor):
        """The worst state within the measurement margins (:func:`transforms.safety_layer.worst_within_margins`)."""
        from transforms.safety_layer import worst_within_margins

        return worst_within_margins(gap, speed, leader_speed, self.gap_margin, self.speed_margin)

    def _both_brake(self, like: torch.Tensor) -> torch.Tensor:
        """``min(brake, leader_brake)``: the braking both cars are assumed to manage (m/s^2)."""
        return torch.minimum(torch.as_tensor(self.brake, dtype=like.dtype), self.leader_brake.to(like))

    def bound(self, gap: torch.Tensor, speed: torch.Tensor, leader_speed: torch.Tensor) -> torch.Tensor:
        """``a_stop`` (floored at the car's braking bound: below it only from an already unsafe state), for the
        worst state within the measurement margins."""
        gap, speed, leader_speed = self._worst(gap, speed, leader_speed)
        upper = self._upper(gap, speed, leader_speed, s_min=self.stop_gap, dt=self.dt, brake=self.brake,
                            leader_brake=self.leader_brake.to(speed))
        return upper.clamp_min(self.low)

    @property
    def reads_leader_accel(self) -> bool:
        return reads_leader_accel(self.law) or self.stand_gap is not None

    def forward(self, gap: torch.Tensor, speed: torch.Tensor, leader_speed: torch.Tensor, *extra) -> torch.Tensor:
        return self.command_and_room(gap, speed, leader_speed, *extra)[0]

    def command_and_room(self, gap: torch.Tensor, speed: torch.Tensor, leader_speed: torch.Tensor, *extra):
        """The command and :meth:`room`, from one evaluation of the law (``extra``: the leader's acceleration,
        where the law or the stand arrival reads it)."""
        return self.command_room_slack(gap, speed, leader_speed, *extra)[:2]

    def command_room_slack(self, gap: torch.Tensor, speed: torch.Tensor, leader_speed: torch.Tensor, *extra,
                           with_slack: bool = False):
        """The command, :meth:`room` and :meth:`slack` (None unless ``with_slack`` or the stand arrival needs it),
        from one evaluation of the law and of the margin."""
        upper = self.bound(gap, speed, leader_speed)
        command = self.law(gap, speed, leader_speed, *(extra if reads_leader_accel(self.law) else ()))
        if self.arrive_gain is not None:
            command = torch.minimum(command, self.arrival(gap, speed, leader_speed))
        slack = self.slack(gap, speed, leader_speed) if with_slack or self.stand_gap is not None else None
        if self.stand_gap is not None:
            if not extra:
                raise ValueError("the stand arrival (stand_gap) reads the leader's acceleration: pass leader_accel")
            a_stand = self.stand_arrival(gap, speed, leader_speed, extra[0])
            command = command + self.stand_weight(speed, slack) * (a_stand - command).clamp_max(0.0)
        command = torch.minimum(command, upper)
        return command, upper - command, slack

    def stand_arrival(self, gap: torch.Tensor, speed: torch.Tensor, leader_speed: torch.Tensor,
                      leader_accel: torch.Tensor) -> torch.Tensor:
        """The constant deceleration (m/s^2, <= 0) that brings the car to rest ``stand_gap`` behind where its leader,
        braking on as it brakes now, will stand, for the worst state within the measurement margins, at or above
        ``low``."""
        gap, speed, leader_speed = self._worst(gap, speed, leader_speed)
        a = stop_arrival_accel(gap, speed.clamp_min(0.0), leader_speed.clamp_min(0.0), leader_accel,
                               stand_gap=self.stand_gap, max_brake=self.stand_leader_brake)
        return a.clamp_min(self.low)

    def stand_weight(self, speed: torch.Tensor, slack: torch.Tensor) -> torch.Tensor:
        """How much of :meth:`stand_arrival` acts, in [0, 1], given the envelope's margin ``slack`` (:meth:`slack`):
        all of it on the edge at the car's speeds up to ``stand_speeds[0]``, none from ``stand_slack`` metres of
        margin or ``stand_speeds[1]``."""
        v_full, v_none = self.stand_speeds
        w_v = ((v_none - speed) / (v_none - v_full)).clamp(0.0, 1.0)
        return w_v * (1.0 - slack / self.stand_slack).clamp(0.0, 1.0)

    def arrival(self, gap: torch.Tensor, speed: torch.Tensor, leader_speed: torch.Tensor) -> torch.Tensor:
        """The arrival term (m/s^2; ``arrive_gain``): ``-d + arrive_gain * r (1 - d / b)`` while the car closes on
        its leader, inf otherwise, for the worst state within the measurement margins."""
        gap, speed, leader_speed = self._worst(gap, speed, leader_speed)
        closing = (speed - leader_speed).clamp_min(0.0)
        b = self._both_brake(speed)
        r = gap - self.stop_gap
        d = closing * closing / (2.0 * r.clamp_min(1e-6))
        term = (-d + self.arrive_gain * r * (1.0 - d / b)).clamp_min(self.low)
        term = torch.where(r > 0, term, torch.full_like(term, self.low))
        return torch.where(closing > 0, term, torch.full_like(term, math.inf))

    def room(self, gap: torch.Tensor, speed: torch.Tensor, leader_speed: torch.Tensor, *extra) -> torch.Tensor:
        """``a_stop`` minus the command (m/s^2, >= 0; 0 where the envelope binds)."""
        return self.command_and_room(gap, speed, leader_speed, *extra)[1]

    def slack(self, gap: torch.Tensor, speed: torch.Tensor, leader_speed: torch.Tensor) -> torch.Tensor:
        """The stopping rule's margin in metres: how much gap the car could still give up if it held its
        speed for this step and then braked, the leader braking from now on (0 on the envelope's edge).
        Unlike :meth:`room`, whose scale near a stop is ``1 / dt^2`` per metre, it shrinks smoothly."""
        from transforms.safety_layer import braking_distance, stopping_budget

        gap, speed, leader_speed = self._worst(gap, speed, leader_speed)
        b_l, b = self.leader_brake.to(speed), self._both_brake(speed)
        v = speed.clamp_min(0.0)
        vl1, c = stopping_budget(gap, leader_speed, s_min=self.stop_gap, dt=self.dt, leader_brake=b_l)
        return torch.minimum(gap - self.stop_gap + (vl1 - v) * self.dt, c - v * self.dt - braking_distance(v, b, self.dt))


class _EnvelopeRoom(nn.Module):
    """The command, its :meth:`StoppingEnvelope.room` and (``slack``) its :meth:`StoppingEnvelope.slack`
    while the car closes on its leader (inf while the leader is as fast or faster: the margin then grows by
    itself, and the room alone guards the bound), one evaluation of the law."""

    def __init__(self, envelope: StoppingEnvelope, slack: bool):
        super().__init__()
        self.envelope, self.with_slack = envelope, slack

    def forward(self, gap: torch.Tensor, speed: torch.Tensor, leader_speed: torch.Tensor, *extra):
        command, room, slack = self.envelope.command_room_slack(gap, speed, leader_speed, *extra,
                                                                with_slack=self.with_slack)
        if not self.with_slack:
            return command, room
        return command, room, torch.where(speed > leader_speed, slack, torch.full_like(slack, math.inf))


def stopping_envelope_policy(policy: TensorDictModule, env, stop_gap: float, room_key: NestedKey | None = None,
                             slack_key: NestedKey | None = None, *, gap_margin: float = 0.0,
                             speed_margin: float = 0.0, arrive_gain: float | None = None,
                             stand_gap: float | None = None, stand_speeds=(6.0, 9.0),
                             stand_slack: float = 3.0, stand_leader_brake: float = 1.5) -> TensorDictModule:
    """``policy`` (of :func:`make_classic_policy` or :func:`speed_scheduled_policy`) inside the
    :class:`StoppingEnvelope` of ``env``'s braking bounds: its own (the action spec's low) and its leader's
    (the head's, a human's or a CAV's; as the safety layer reads them). With ``room_key`` the module also
    writes the envelope's :meth:`~StoppingEnvelope.room` there, and with ``slack_key`` (with ``room_key``)
    its :meth:`~StoppingEnvelope.slack`. ``gap_margin`` / ``speed_margin``: the envelope's measurement margins
    (m, m/s; :class:`StoppingEnvelope`); ``arrive_gain``: its arrival term (1/s^2; :class:`StoppingEnvelope`);
    ``stand_gap`` / ``stand_speeds`` / ``stand_slack`` / ``stand_leader_brake``: its arrival behind where a braking leader will stand
    (:class:`StoppingEnvelope`; the module then also reads the leader's acceleration).

    >>> from mixed_traffic import make_env
    >>> env = make_env("ring", batch_size=2, seed=0)
    >>> pol = stopping_envelope_policy(make_classic_policy("idm", env), env, stop_gap=5.0)
    >>> bool(env.rollout(50, pol)["next", "collision"].any())
    False
    """
    from transforms.safety_layer import scenario_leader_brake

    scenario = env.scenario
    low, _ = action_bounds(env)
    envelope = StoppingEnvelope(policy.module, stop_gap=stop_gap, dt=scenario.dt, brake=-low,
                                leader_brake=scenario_leader_brake(scenario), low=low, gap_margin=gap_margin,
                                speed_margin=speed_margin, arrive_gain=arrive_gain, stand_gap=stand_gap,
                                stand_speeds=tuple(stand_speeds), stand_slack=stand_slack,
                                stand_leader_brake=stand_leader_brake)
    in_keys = list(policy.in_keys)
    if stand_gap is not None and LEADER_ACCEL_KEY not in in_keys:
        require_leader_accel(env, "the stand arrival (stand_gap)")
        in_keys.append(LEADER_ACCEL_KEY)
    if room_key is None:
        if slack_key is not None:
            raise ValueError("stopping_envelope_policy: slack_key needs a room_key")
        return TensorDictModule(envelope, in_keys=in_keys, out_keys=list(policy.out_keys))
    extra = [room_key] if slack_key is None else [room_key, slack_key]
    return TensorDictModule(_EnvelopeRoom(envelope, slack=slack_key is not None), in_keys=in_keys,
                            out_keys=[*policy.out_keys, *extra])


def action_bounds(env) -> tuple[float, float]:
    """``(low, high)`` of the CAV acceleration command of ``env`` (first element of its action spec)."""
    spec = env.action_spec
    return float(spec.space.low.flatten()[0]), float(spec.space.high.flatten()[0])


def classic_parameters(model: str) -> list[str]:
    """Names ``make_classic_policy(model, ...)`` accepts: the model's parameters (IDM: and ``gap_max``,
    ``v0_leader``)."""
    if model not in CLASSIC:
        raise ValueError(f"classic controller {model!r} is invalid; allowed: {list(CLASSIC)}")
    names = {f.name for f in dataclasses.fields(_PARAMS[model])}
    return sorted(names | ({"gap_max", "v0_leader"} if model == "idm" else set()))


def make_classic_policy(model: str, env=None, *, low: float | None = None, high: float | None = None,
                        **param_overrides) -> TensorDictModule:
    """IDM (SUMO's defaults, as the ring's humans), OVM (DeeP-LCC's set), the soft follower
    (:class:`~mixed_traffic.physics.SoftFollowerParams`) or CACC (:class:`~mixed_traffic.physics.CACCParams`,
    reading the leader's acceleration) driving every CAV.

    Bounds come from ``env.action_spec`` unless given; ``param_overrides`` replace model
    parameters (``make_classic_policy("idm", env, T=1.5)``); unknown names raise ValueError.
    IDM also takes ``gap_max`` (m): the steady gap stays at or below it at every speed
    (``mixed_traffic.physics.idm_accel``), a bound the humans' IDM does not have; and ``v0_leader``: the
    desired speed is ``max(v0, v0_leader * v_leader)``, so the free-road term eases off at the same multiple of
    the leader's speed behind any leader (a CAV closing a long gap overshoots a slow leader less, and still
    catches a fast one).
    """
    allowed = classic_parameters(model)  # an unknown model fails here
    base = _PARAMS[model]()
    unknown = set(param_overrides) - set(allowed)
    if unknown:
        raise ValueError(f"{model} parameters {sorted(unknown)} are invalid; allowed: {allowed}")
    param_overrides = dict(param_overrides)
    gap_max = param_overrides.pop("gap_max", None)
    v0_leader = param_overrides.pop("v0_leader", None)
    params = dataclasses.replace(base, **param_overrides)
    if low is None or high is None:
        if env is None:
            raise ValueError("make_classic_policy: pass env (for the action bounds) or low and high")
        env_low, env_high = action_bounds(env)
        low = env_low if low is None else low
        high = env_high if high is None else high
    law = CarFollowingCAV(model, params, low, high, gap_max=gap_max, v0_leader=v0_leader)
    in_keys = [("cav", "gap"), ("cav", "speed"), ("cav", "leader_speed")]
    if law.reads_leader_accel:
        if env is not None:
            require_leader_accel(env, model)
        in_keys.append(LEADER_ACCEL_KEY)
    return TensorDictModule(law, in_keys=in_keys, out_keys=["action"])


__all__ = ["make_classic_policy", "classic_parameters", "action_bounds", "speed_scheduled_policy", "CarFollowingCAV",
           "SpeedScheduledCAV", "StoppingEnvelope", "stopping_envelope_policy", "CLASSIC", "LEADER_ACCEL_KEY",
           "LeaderBrakeFloor", "leader_brake_floor_policy", "LeaderAccelFeed", "leader_accel_feed_policy", "reads_leader_accel", "require_leader_accel"]
