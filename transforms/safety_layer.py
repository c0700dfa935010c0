"""Safety layer: clip each CAV's acceleration so it never closes below ``s_min``.

Two constraints act on the commanded acceleration ``a`` of every CAV:

* ``s_max`` (gap to the head vehicle) clips ``a`` UP, so a CAV cannot fall back
  and let the head drift away;
* ``s_min`` (gap to the physical leader) clips ``a`` DOWN and wins every conflict:
  it is applied last.

Modes
-----
``mode="stopping"`` (default) guarantees no collision when the executed
acceleration is bounded (the env clips the action to ``cav_accel_bounds``, widened down to
``-cav_emergency_decel`` when the scenario sets it). It keeps
the post-step state inside the *safe set*: if from now on the leader brakes as hard
as it can (``leader_brake``) and the CAV brakes at ``b = min(ego_brake, leader_brake)``
(``ego_brake``: the action range's ``-low``, or the emergency braking the layer alone may use),
every future gap stays ``>= s_min``. The prediction uses the env's discrete update
(``v' = max(v + a dt, 0)``, ``x' = x + v' dt``), so the guarantee holds exactly in
discrete time, not only in the continuous-time limit:

* distance covered while braking at ``b`` from speed ``v`` (after the current step):
  ``D(v, b) = dt * sum_{k>=1} max(v - k b dt, 0)`` (closed form below);
* with ``b <= leader_brake`` the relative speed changes sign at most once (from
  opening to closing), so the smallest future gap is either the next gap or the gap
  once both have stopped: safe ⇔ ``s >= s_min`` and ``s + D(v_L, b_L) - D(v, b) >= s_min``;
* the largest safe acceleration ``a_hi`` solves these two conditions for the
  CAV's next speed, with the leader braking at its bound during the step
  (the worst case: any leader behaviour within its bound leaves the leader ahead of
  that trajectory at every step).

From a safe state, braking at ``b`` keeps the state safe whatever the leader does, so
``a_hi >= -b >= a_min`` and the clip is always feasible (recursive feasibility). If the
state is already outside the safe set (bad initial condition) the layer brakes as
hard as allowed.

``mode="one_step"`` reproduces the original rule (a one-step constant-acceleration
prediction ``s + v_rel dt - a dt^2 / 2``). It was safe only under a simulator that
let the car brake without limit; use it for reproduction only.

The s_max constraint assumes the head keeps its speed. In ``"stopping"`` mode it is
the mirror image of the s_min rule: the CAV, limited to its maximum acceleration,
must still be able to close its speed deficit to the head before the gap exceeds
``s_max`` (otherwise a braking CAV would notice the overshoot one step too late and
drift tens of metres beyond s_max). In ``"one_step"`` mode it is the original
``h + (v_H - v) dt - a dt^2 / 2 <= s_max``.

A state already beyond ``s_max`` (e.g. an episode that starts with a long gap) cannot
be brought back in one step. ``beyond_s_max="push"`` (default) then drives at the
maximum acceleration until the rule above is met again; ``"hold"`` only keeps the gap
from growing (the rule with ``s_max`` raised to the current gap: the CAV at least keeps
the head's speed) and leaves the closing to the command; ``"ramp"`` holds and also closes,
but raises the demanded acceleration from the CAV's current one at ``ramp_jerk`` (m/s^3) at
most, up to what ``"push"`` demands; ``"recover"`` demands that the excess ``h - s_max``
shrink with the time constant ``recover_seconds`` (the CAV closes on the head at least at
``(h - s_max) / recover_seconds``), a rule continuous in the state that meets the push rule at
``s_max`` (``"push"`` is its limit at one step, ``"hold"`` at infinity). ``s_max`` is a bound on
how far a CAV may fall back, not a safety bound, so none of them gives up a guarantee; they
remove the full-throttle burst (and the jerk that follows it) from a long start, and
``"ramp"`` and ``"recover"`` still bring back a command that does not close the gap itself.

The guarantee is exact for the ``"euler"`` integration (the default of every preset);
with ``"euler_explicit"`` / ``"ballistic"`` the same rule is a close approximation.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs.transforms import Transform

from transforms.specs import action_shaped_full, carry_to_next, entries_or_none, parent_dt

Tensor = torch.Tensor

MODES = ("stopping", "one_step")
BEYOND_S_MAX = ("push", "hold", "ramp", "recover")


# ----------------------------------------------------------------------------- pure math
def braking_distance(v: Tensor, brake: Tensor | float, dt: float) -> Tensor:
    """Distance covered after the current step when braking at ``brake`` (> 0) from speed ``v``.

    Discrete update ``v_{k+1} = max(v_k - brake dt, 0)``, ``x_{k+1} = x_k + v_{k+1} dt``:
    ``D = dt * sum_{k>=1} max(v - k h, 0)`` with ``h = brake dt``; with
    ``n = floor(v / h)``: ``D = dt (n v - h n (n + 1) / 2)``.
    """
    v = v.clamp_min(0.0)
    h = torch.as_tensor(brake, dtype=v.dtype, device=v.device) * dt
    with torch.no_grad():  # the step count is piecewise constant: its gradient is zero, so it needs no graph
        n = torch.floor(v / h)
    return dt * (n * v - h * n * (n + 1.0) / 2.0).clamp_min(0.0)


def min_future_gap(gap: Tensor, v: Tensor, v_leader: Tensor, *, dt: float,
                   brake: Tensor | float, leader_brake: Tensor | float) -> Tensor:
    """Smallest gap, now or later, when both brake (ego at ``min(brake, leader_brake)``)."""
    b = torch.minimum(torch.as_tensor(brake, dtype=v.dtype), torch.as_tensor(leader_brake, dtype=v.dtype))
    final = gap + braking_distance(v_leader, leader_brake, dt) - braking_distance(v, b, dt)
    return torch.minimum(gap, final)


_NEIGHBOURS = torch.tensor([-1.0, 0.0, 1.0])


def _max_speed_within_distance(c: Tensor, b: Tensor, dt: float) -> Tensor:
    """Largest ``u >= 0`` with ``u dt + D(u, b) <= c`` (``c >= 0``).

    ``F(u) = dt sum_{k>=0} max(u - k h, 0)`` is convex and piecewise linear with kinks
    at ``u = m h`` where ``F(m h) = dt h m (m + 1) / 2``. On segment ``m`` the solution is
    ``u = (c / dt + h m (m + 1) / 2) / (m + 1)``. Each segment's line lies below ``F``,
    so a wrong segment can only overestimate ``u``: the minimum over the segment
    computed from the square root and its two neighbours is exact despite rounding.
    """
    h = b * dt
    c = c.clamp_min(0.0)
    with torch.no_grad():  # the segment index is piecewise constant in c: its gradient is zero, so it needs no graph
        m0 = torch.floor((-1.0 + torch.sqrt(1.0 + 8.0 * c / (dt * h))) / 2.0)
        m = (m0 + _NEIGHBOURS.to(m0).view(3, *([1] * m0.dim()))).clamp_min(0.0)  # the three segments, stacked
    u = (c / dt + h * m * (m + 1.0) / 2.0) / (m + 1.0)
    return torch.minimum(torch.minimum(u[0], u[1]), u[2])


def stopping_budget(gap: Tensor, v_leader: Tensor, *, s_min: float, dt: float,
                    leader_brake: Tensor | float) -> tuple[Tensor, Tensor]:
    """The right-hand sides of the ``"stopping"`` rule: ``vl1``, the leader's speed after one step braking
    at ``leader_brake``, and ``c = gap - s_min + vl1 dt + D(vl1, leader_brake)``, the distance the car may
    cover from the next step on, ``u dt + D(u, b) <= c`` for its post-step speed ``u``, with the next gap
    itself ``gap + (vl1 - u) dt >= s_min``. Shared by :func:`safe_accel_upper`, the stopping envelope's
    margin (``StoppingEnvelope.slack``) and the jerk oracle's stopping constraint."""
    b_l = torch.as_tensor(leader_brake, dtype=v_leader.dtype, device=v_leader.device)
    vl1 = (v_leader.clamp_min(0.0) - b_l * dt).clamp_min(0.0)  # leader brakes as hard as it can
    return vl1, gap - s_min + vl1 * dt + braking_distance(vl1, b_l, dt)


def safe_accel_upper(gap: Tensor, v: Tensor, v_leader: Tensor, *, s_min: float, dt: float,
                     brake: Tensor | float, leader_brake: Tensor | float) -> Tensor:
    """Largest acceleration that keeps the post-step state in the safe set (``"stopping"`` mode).

    The result may lie below ``-brake`` only when the current state is already unsafe.
    """
    dtype = v.dtype
    b_e = torch.as_tensor(brake, dtype=dtype, device=v.device)
    b_l = torch.as_tensor(leader_brake, dtype=dtype, device=v.device)
    b = torch.minimum(b_e, b_l)
    v = v.clamp_min(0.0)
    # (ii) after the step both brake: u dt + D(u, b) <= c = s - s_min + vl1 dt + D(vl1, b_l)
    vl1, c = stopping_budget(gap, v_leader, s_min=s_min, dt=dt, leader_brake=b_l)
    u2 = torch.where(c >= 0, _max_speed_within_distance(c, b, dt), c / dt)
    # (i) the next gap itself: s + (vl1 - u) dt >= s_min
    u1 = vl1 + (gap - s_min) / dt
    u = torch.minimum(u1, u2)
    return (u - v) / dt


def one_step_accel_upper(gap: Tensor, v: Tensor, v_leader: Tensor, *, s_min: float, dt: float) -> Tensor:
    """The original rule: ``s + (v_L - v) dt - a dt^2 / 2 >= s_min``."""
    return 2.0 * (gap + (v_leader - v) * dt - s_min) / dt**2


def head_accel_lower(head_gap: Tensor, v: Tensor, head_speed: Tensor, *, s_max: float, dt: float,
                     mode: str = "stopping", accel_max: Tensor | float | None = None,
                     beyond: str = "push", recover_seconds: float = 5.0) -> Tensor:
    """Smallest acceleration that keeps the gap to the head ``<= s_max``.

    ``"stopping"`` mode (mirror image of the s_min rule): after this step the CAV can
    close a speed deficit ``w = v_H - v'`` only at ``accel_max``, during which the gap
    still grows by ``D(w, accel_max)``; so it requires
    ``h + w dt + D(w, accel_max) <= s_max`` with the head at constant speed. Without
    ``accel_max`` (or in ``"one_step"`` mode) only the next gap is predicted:
    ``h + (v_H - v') dt <= s_max`` (``"one_step"``: the original
    ``h + (v_H - v) dt - a dt^2 / 2 <= s_max``). With ``beyond="hold"`` a gap already
    beyond ``s_max`` is only kept from growing (no room is demanded back); with
    ``beyond="recover"`` it is demanded back at the rate ``(h - s_max) / recover_seconds``.
    """
    if mode == "one_step":
        return 2.0 * (head_gap + (head_speed - v) * dt - s_max) / dt**2
    room = s_max - head_gap
    if beyond == "hold":
        room = room.clamp_min(0.0)
    elif beyond == "recover":
        room = torch.where(room >= 0, room, room * (dt / recover_seconds))
    if accel_max is None:
        w = room / dt
    else:
        up = torch.as_tensor(accel_max, dtype=v.dtype, device=v.device).clamp_min(1e-6)
        w = torch.where(room >= 0, _max_speed_within_distance(room, up, dt), room / dt)
    return (head_speed - w - v) / dt


def worst_within_margins(gap: Tensor, speed: Tensor, leader_speed: Tensor, gap_margin: float,
                         speed_margin: float) -> tuple[Tensor, Tensor, Tensor]:
    """The state within measurement margins of the measured one that the stopping rule fears most: the gap
    shorter by ``gap_margin``, the CAV faster and its leader slower by ``speed_margin`` (not below 0)."""
    if not (gap_margin or speed_margin):
        return gap, speed, leader_speed
    return gap - gap_margin, speed + speed_margin, (leader_speed - speed_margin).clamp_min(0.0)


def safe_action(action: Tensor, *, gap: Tensor, speed: Tensor, leader_speed: Tensor,
                head_gap: Tensor | None, head_speed: Tensor | None, low: Tensor | float, high: Tensor | float,
                dt: float, s_min: float | None = 5.0, s_max: float | None = 40.0, mode: str = "stopping",
                leader_brake: Tensor | float | None = None, beyond_s_max: str = "push",
                accel: Tensor | None = None, ramp_jerk: float = 1.0, recover_seconds: float = 5.0,
                hold_mask: Tensor | None = None, ego_brake: Tensor | float | None = None,
                gap_margin: float = 0.0, speed_margin: float = 0.0) -> Tensor:
    """The executed acceleration: bounds, then s_max (up), then s_min (down, wins), then bounds.

    ``gap_margin`` (m) and ``speed_margin`` (m/s), both >= 0: the s_min rule holds for the worst state within
    them of the measured one (the gap shorter, the CAV faster, the leader slower), so that measurement errors
    up to the margins do not take the true gap below ``s_min``; the s_max rule reads the measurements as they are.

    ``ego_brake`` (> 0, m/s^2, at least ``-low``) is the hardest braking the CAV can execute,
    defaulting to ``-low``: the s_min bound assumes the CAV brakes that hard from the next step
    on, and only it may take the command below ``low`` (down to ``-ego_brake``);
    ``leader_brake`` (> 0, m/s^2) defaults to the CAV's own braking bound ``-low``;
    ``beyond_s_max``: ``"push"``, ``"hold"``, ``"ramp"`` (with the CAV's current acceleration
    ``accel`` and ``ramp_jerk``) or ``"recover"`` (with ``recover_seconds``); see the module
    docstring. ``hold_mask`` (bool, broadcastable to ``action``) marks the entries where a head
    gap beyond ``s_max`` is only held whatever ``beyond_s_max`` says (:class:`SafetyLayer`'s
    ``hold_seconds``).
    """
    low = torch.as_tensor(low, dtype=action.dtype, device=action.device)
    high = torch.as_tensor(high, dtype=action.dtype, device=action.device)
    a = torch.minimum(torch.maximum(action, low), high)
    if s_max is not None:
        if beyond_s_max == "ramp":
            if accel is None:
                raise ValueError("safe_action: beyond_s_max='ramp' needs the CAV's current acceleration (accel=)")
            held = head_accel_lower(head_gap, speed, head_speed, s_max=s_max, dt=dt, mode=mode, accel_max=high,
                                    beyond="hold")
            pushed = head_accel_lower(head_gap, speed, head_speed, s_max=s_max, dt=dt, mode=mode, accel_max=high)
            # inside s_max the two bounds are the same, so this is the push rule there
            a_lo = torch.maximum(held, torch.minimum(pushed, accel + ramp_jerk * dt))
        else:
            a_lo = head_accel_lower(head_gap, speed, head_speed, s_max=s_max, dt=dt, mode=mode, accel_max=high,
                                    beyond=beyond_s_max, recover_seconds=recover_seconds)
        if hold_mask is not None and beyond_s_max != "hold":
            held_lo = head_accel_lower(head_gap, speed, head_speed, s_max=s_max, dt=dt, mode=mode, accel_max=high,
                                       beyond="hold")
            a_lo = torch.where(hold_mask, held_lo, a_lo)
        a = torch.maximum(a, torch.minimum(a_lo, high))
    brake = -low if ego_brake is None else torch.maximum(torch.as_tensor(ego_brake, dtype=low.dtype, device=low.device), -low)
    if s_min is not None:
        gap, speed, leader_speed = worst_within_margins(gap, speed, leader_speed, gap_margin, speed_margin)
        if mode == "one_step":
            a_hi = one_step_accel_upper(gap, speed, leader_speed, s_min=s_min, dt=dt)
        else:
            lb = -low if leader_brake is None else leader_brake
            a_hi = safe_accel_upper(gap, speed, leader_speed, s_min=s_min, dt=dt, brake=brake, leader_brake=lb)
        a = torch.minimum(a, a_hi)
    return torch.minimum(torch.maximum(a, -brake), high)


def scenario_leader_brake(scenario) -> list[float]:
    """Braking bound (> 0) of each CAV's leader in a :class:`TrafficScenario`.

    Vehicles are ordered head first, so CAV ``i`` follows vehicle ``i - 1`` (on a ring,
    CAV 0 follows the last vehicle): the head (``head_accel_bounds``), another CAV (``cav_accel_bounds``, widened to
    ``-cav_emergency_decel`` when set) or a human driver (the
    car-following model's ``a_min``, widened by ``hdv_param_noise``).
    """
    out = []
    head = getattr(scenario, "head", True)
    for i in scenario.cav_indices:
        lead = (i - 1) % scenario.n_vehicles
        if lead == 0 and head:
            out.append(-float(scenario.head_accel_bounds[0]))
        elif lead in scenario.cav_indices:  # its own layer may brake it down to the emergency bound
            out.append(-float(getattr(scenario, "cav_exec_bounds", scenario.cav_accel_bounds)[0]))
        else:
            a_min = float(scenario.hdv_defaults().a_min)
            out.append(-a_min * (1.0 + float(scenario.hdv_param_noise)))
    return out


# ----------------------------------------------------------------------------- transform
class SafetyLayer(Transform):
    """Clips the CAV acceleration command so gaps stay within ``[s_min, s_max]``.

    The policy's raw action stays in the rollout (right for PPO log-probs); the env runs
    the clipped one. Per step the layer records, in ``"next"``:

    * ``("safety", "clipped")`` (bool ``[B, n_cav]``): the layer changed the command;
    * ``("safety", "delta")`` (``[B, n_cav]``, m/s^2): executed minus commanded
      (commanded clipped to the action bounds first), so ``safety_clip_rate`` is
      ``batch["next", "safety", "clipped"].float().mean()``.

    Args:
        s_min: minimum gap to the leader (m); ``None`` switches the constraint off.
        s_max: maximum gap to the head vehicle (m); ``None`` switches it off (required on
            rings without a head, which have no ``("cav", "head_gap")``).
        dt: step length (s); ``None`` reads ``dt`` from the parent env.
        mode: ``"stopping"`` (default, collision-free under bounded braking, see the
            module docstring) or ``"one_step"`` (the original rule, for reproduction).
        beyond_s_max: ``"push"`` (default: a head gap beyond ``s_max`` is closed at the
            maximum acceleration), ``"hold"`` (it is only kept from growing; the command
            closes it), ``"ramp"`` (held, and closed with a demand that rises from the
            current acceleration at ``ramp_jerk``) or ``"recover"`` (closed at a rate of at least
            the excess over ``recover_seconds``); ``"stopping"`` mode only.
        ramp_jerk: the ``"ramp"`` demand's rate of rise (m/s^3, > 0).
        recover_seconds: the ``"recover"`` rule's time constant (s, > 0).
        hold_seconds: during the first ``hold_seconds`` of an episode (``time_key`` below that)
            a head gap beyond ``s_max`` is only held, whatever ``beyond_s_max`` says: a CAV
            that engages far behind the head closes the gap at its own pace, and the layer
            pushes only a CAV that has not closed it by then (s, >= 0; 0: from the start).
        gap_margin, speed_margin: measurement margins of the s_min rule (m, m/s, >= 0; default 0): it holds
            for the worst state within them of the measured one (the gap shorter by ``gap_margin``, the CAV
            faster and its leader slower by ``speed_margin``), for a CAV whose sensors err by up to that much
            (``transforms.SensorNoise``).
        time_key: the episode time entry ``hold_seconds`` reads (default ``("traffic", "time")``).
        leader_brake: braking bound (> 0, m/s^2) of each CAV's leader, a float or one
            value per CAV; ``None`` reads it from the parent's ``scenario``
            (:func:`scenario_leader_brake`), else uses the CAV's own bound.
        ego_brake: the hardest braking (> 0, m/s^2) the CAV can execute, at least the action
            range's ``-low``: the s_min bound assumes the CAV brakes that hard, and only it may
            take the executed command below ``low``. ``None`` reads the parent scenario's
            ``cav_emergency_decel`` and falls back to ``-low`` (the action range is all the
            layer may use).
        action_key: the action entry (default ``"action"``).
        cav_keys: where to read the CAV state (defaults follow the env key contract).
        out_keys: the two keys written into ``"next"`` (clipped flag, delta).

    Example:
        >>> from mixed_traffic import make_env
        >>> from torchrl.envs import TransformedEnv
        >>> from transforms import SafetyLayer
        >>> env = TransformedEnv(make_env("ring", batch_size=4, seed=0), SafetyLayer(s_min=5.0, s_max=40.0))
        >>> td = env.rollout(20, lambda td: td.set("action", env.action_spec.high.clone()))
        >>> bool(td["next", "collision"].any())
        False
        >>> td["next", "safety", "clipped"].shape
        torch.Size([4, 20, 1])
    """

    DEFAULT_CAV_KEYS = {
        "gap": ("cav", "gap"),
        "speed": ("cav", "speed"),
        "leader_speed": ("cav", "leader_speed"),
        "head_gap": ("cav", "head_gap"),
        "head_speed": ("cav", "head_speed"),
        "accel": ("cav", "accel"),
    }

    def __init__(self, s_min: float | None = 5.0, s_max: float | None = 40.0, dt: float | None = None, *,
                 mode: str = "stopping", leader_brake: float | Sequence[float] | None = None,
                 ego_brake: float | None = None, beyond_s_max: str = "push", ramp_jerk: float = 1.0, recover_seconds: float = 5.0,
                 hold_seconds: float = 0.0, gap_margin: float = 0.0, speed_margin: float = 0.0,
                 time_key: NestedKey = ("traffic", "time"), action_key: NestedKey = "action",
                 cav_keys: dict[str, NestedKey] | None = None,
                 out_keys: Sequence[NestedKey] = (("safety", "clipped"), ("safety", "delta"))):
        if mode not in MODES:
            raise ValueError(f"SafetyLayer: mode={mode!r} is invalid; allowed: {list(MODES)}")
        if beyond_s_max not in BEYOND_S_MAX:
            raise ValueError(f"SafetyLayer: beyond_s_max={beyond_s_max!r} is invalid; allowed: {list(BEYOND_S_MAX)}")
        if not ramp_jerk > 0:
            raise ValueError(f"SafetyLayer: ramp_jerk={ramp_jerk!r} is invalid; allowed: > 0 (m/s^3)")
        if not recover_seconds > 0:
            raise ValueError(f"SafetyLayer: recover_seconds={recover_seconds!r} is invalid; allowed: > 0 (s)")
        if not hold_seconds >= 0:
            raise ValueError(f"SafetyLayer: hold_seconds={hold_seconds!r} is invalid; allowed: >= 0 (s)")
        for name, value in (("gap_margin", gap_margin), ("speed_margin", speed_margin)):
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"SafetyLayer: {name}={value!r} is invalid; allowed: >= 0 ({'m' if name[0] == 'g' else 'm/s'})")
        if s_min is not None and not s_min > 0:
            raise ValueError(f"SafetyLayer: s_min={s_min!r} is invalid; allowed: > 0 or None")
        if s_max is not None and not s_max > 0:
            raise ValueError(f"SafetyLayer: s_max={s_max!r} is invalid; allowed: > 0 or None")
        if s_min is not None and s_max is not None and not s_min < s_max:
            raise ValueError(f"SafetyLayer: s_min={s_min} and s_max={s_max} are invalid; allowed: s_min < s_max")
        if dt is not None and not dt > 0:
            raise ValueError(f"SafetyLayer: dt={dt!r} is invalid; allowed: > 0 or None (read from the env)")
        if leader_brake is not None:
            lb = torch.as_tensor(leader_brake, dtype=torch.float64)
            if not bool((lb > 0).all()):
                raise ValueError(f"SafetyLayer: leader_brake={leader_brake!r} is invalid; allowed: > 0 (m/s^2) or None")
        if ego_brake is not None and not (math.isfinite(ego_brake) and ego_brake > 0):
            raise ValueError(f"SafetyLayer: ego_brake={ego_brake!r} is invalid; allowed: > 0 (m/s^2) or None")
        keys = dict(self.DEFAULT_CAV_KEYS)
        if cav_keys:
            unknown = set(cav_keys) - set(keys)
            if unknown:
                raise ValueError(f"SafetyLayer: cav_keys {sorted(unknown)} are invalid; allowed: {sorted(keys)}")
            keys.update(cav_keys)
        if len(out_keys) != 2:
            raise ValueError(f"SafetyLayer: out_keys={out_keys!r} is invalid; allowed: two keys (clipped, delta)")
        super().__init__(in_keys=[], out_keys=list(out_keys), in_keys_inv=[action_key], out_keys_inv=[action_key])
        self.s_min, self.s_max, self.mode, self.beyond_s_max = s_min, s_max, mode, beyond_s_max
        self.ramp_jerk, self.hold_seconds, self.time_key = float(ramp_jerk), float(hold_seconds), time_key
        self.recover_seconds = float(recover_seconds)
        self.gap_margin, self.speed_margin = float(gap_margin), float(speed_margin)
        self._dt = dt
        self._leader_brake = leader_brake
        self._ego_brake = None if ego_brake is None else float(ego_brake)
        self.action_key = action_key
        self.cav_keys = keys
        self.clipped_key, self.delta_key = out_keys
        self.active_rows: Tensor | None = None

    def set_active_rows(self, mask: Tensor | None) -> None:
        """Apply the layer only on the batch rows where ``mask`` (bool ``[B]``) is True.

        The other rows execute the command unchanged (bounded to the action box), as if the
        layer were not in the chain: one batch then evaluates a policy with and without its
        safety net side by side. ``None`` (the default) applies the layer on every row.
        """
        if mask is not None:
            mask = torch.as_tensor(mask, dtype=torch.bool).reshape(-1)
        self.active_rows = mask

    # -------------------------------------------------------------- env lookups
    @property
    def dt(self) -> float:
        if self._dt is None:
            self._dt = parent_dt(self.parent, "SafetyLayer")
        return self._dt

    def _bounds(self, like: Tensor) -> tuple[Tensor, Tensor]:
        cached = self.__dict__.get("_bounds_cache")
        if cached is None:
            spec = self.parent.full_action_spec[self.action_key]
            low, high = spec.space.low, spec.space.high
            # one value per CAV (bounds do not vary along the batch)
            while low.ndim > 1:
                low, high = low[0], high[0]
            cached = (low, high)
            self.__dict__["_bounds_cache"] = cached
        low, high = cached
        return low.to(like), high.to(like)

    def _leader_brake_tensor(self, low: Tensor) -> Tensor:
        lb = self.__dict__.get("_lb_cache")
        if lb is None:
            if self._leader_brake is not None:
                lb = torch.as_tensor(self._leader_brake, dtype=low.dtype)
            else:
                scenario = getattr(self.parent, "scenario", None) if self.parent is not None else None
                if scenario is not None and hasattr(scenario, "cav_indices"):
                    lb = torch.tensor(scenario_leader_brake(scenario), dtype=low.dtype)
                else:
                    lb = -low
            self.__dict__["_lb_cache"] = lb
        return lb.to(low)

    def _ego_brake_value(self, low: Tensor) -> Tensor:
        """``ego_brake``, else the scenario's ``cav_emergency_decel``, else ``-low``; never below ``-low``
        (looked up once, like the leader's bound)."""
        eb = self.__dict__.get("_eb_cache")
        if eb is None:
            value = self._ego_brake
            if value is None:
                scenario = getattr(self.parent, "scenario", None) if self.parent is not None else None
                value = getattr(scenario, "cav_emergency_decel", None)
            eb = -low if value is None else torch.full_like(low, float(value)).maximum(-low)
            self.__dict__["_eb_cache"] = eb
        return eb.to(low)

    # -------------------------------------------------------------- transform API
    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        got = entries_or_none(self, tensordict, self.action_key)
        if got is None:
            return tensordict
        (action,) = got
        k = self.cav_keys
        low, high = self._bounds(action)
        need_head = self.s_max is not None
        if need_head and k["head_gap"] not in tensordict.keys(True):
            raise KeyError(f"SafetyLayer: s_max={self.s_max} bounds the gap to the head, but {k['head_gap']!r} is "
                           "not in the tensordict (a ring without a head); use s_max=None there")
        executed = safe_action(
            action, gap=tensordict.get(k["gap"]), speed=tensordict.get(k["speed"]),
            leader_speed=tensordict.get(k["leader_speed"]),
            head_gap=tensordict.get(k["head_gap"]) if need_head else None,
            head_speed=tensordict.get(k["head_speed"]) if need_head else None,
            low=low, high=high, dt=self.dt, s_min=self.s_min, s_max=self.s_max, mode=self.mode,
            leader_brake=self._leader_brake_tensor(low) if self.mode == "stopping" else None,
            beyond_s_max=self.beyond_s_max, ramp_jerk=self.ramp_jerk, recover_seconds=self.recover_seconds,
            accel=tensordict.get(k["accel"]) if need_head and self.beyond_s_max == "ramp" else None,
            hold_mask=self._hold_mask(tensordict) if need_head else None, ego_brake=self._ego_brake_value(low),
            gap_margin=self.gap_margin, speed_margin=self.speed_margin,
        )
        commanded = torch.minimum(torch.maximum(action, low), high)
        if self.active_rows is not None:
            if self.active_rows.numel() != action.shape[0]:
                raise ValueError(f"SafetyLayer: active_rows has {self.active_rows.numel()} rows; allowed: the batch "
                                 f"size {action.shape[0]}")
            executed = torch.where(self.active_rows.to(action.device).unsqueeze(-1), executed, commanded)
        delta = executed - commanded
        tensordict.set(self.action_key, executed)
        # the input is a shallow clone: these entries reach `_step`, not the rollout
        tensordict.set(self.delta_key, delta)
        tensordict.set(self.clipped_key, delta != 0)
        return tensordict

    def _hold_mask(self, tensordict: TensorDictBase) -> Tensor | None:
        """Rows (``[*batch, 1]``, e.g. ``[B, 1]``, or ``[workers, 1, 1]`` behind a ``ParallelEnv``) still inside
        ``hold_seconds``; ``None`` when it is 0, ``beyond_s_max`` holds anyway or no row is inside any more
        (past the first seconds: ``safe_action`` then skips the held bound, which it would compute for nothing)."""
        if self.hold_seconds == 0 or self.beyond_s_max == "hold":
            return None
        time = tensordict.get(self.time_key, None)
        if time is None:
            raise KeyError(f"SafetyLayer: hold_seconds={self.hold_seconds} reads the episode time, but "
                           f"{self.time_key!r} is not in the tensordict; allowed: an env that reports it, or "
                           "hold_seconds=0")
        batch = tensordict.batch_size
        mask = time.reshape(*batch, -1)[..., :1] < self.hold_seconds
        return mask if bool(mask.any()) else None

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        return carry_to_next(tensordict, next_tensordict, self.clipped_key, self.delta_key)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        tensordict_reset.set(self.clipped_key, action_shaped_full(self.parent, self.action_key, False, torch.bool))
        tensordict_reset.set(self.delta_key, action_shaped_full(self.parent, self.action_key, 0.0))
        return tensordict_reset

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        spec = self.parent.full_action_spec[self.action_key]
        observation_spec[self.clipped_key] = Categorical(2, shape=spec.shape, dtype=torch.bool, device=spec.device)
        observation_spec[self.delta_key] = Unbounded(shape=spec.shape, dtype=spec.dtype, device=spec.device)
        return observation_spec

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(s_min={self.s_min}, s_max={self.s_max}, mode={self.mode!r}, "
                f"beyond_s_max={self.beyond_s_max!r}, dt={self._dt})")
