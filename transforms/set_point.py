"""The policy chooses a speed controller's set point; the controller turns it into the acceleration.

A residual on the *acceleration* of FollowerStopper cannot move the speed it settles at:
FollowerStopper commands ``(v_cmd - v) / dt``, a gain of 10 s^-1 at ``dt = 0.1`` s, so a bounded
residual of 0.5 m/s^2 shifts its steady speed by 0.05 m/s. What decides whether one car
dissolves a ring's wave is the set point ``U`` (too high and the car follows the wave, too low
and the ring runs slower than it could), and the best ``U`` changes with the ring (measured in
``docs/wave.md``). :class:`SetPointAction` lets the policy act on that: it outputs
``a in [-1, 1]`` per CAV and the controller tracks ``U = U_ref * (ratio0 + weight * a)``.
TorchRL's action transforms map actions elementwise; this one runs a controller on the state.
"""

from __future__ import annotations

from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import Composite
from torchrl.envs.transforms import Transform

from transforms.specs import action_shaped_full, carry_to_next, with_action_shaped_entry, with_bounded_action


def linear_schedule(time, start_value: float, end_value: float, t1: float, t2: float):
    """``start_value`` until ``t1``, linear to ``end_value`` at ``t2``, ``end_value`` after it (``time`` a tensor, s)."""
    return start_value + (end_value - start_value) * ((time - t1) / (t2 - t1)).clamp(0.0, 1.0)


class SetPointAction(Transform):
    """Executes ``controller(state, U = U_ref * (ratio0 + weight * a))``; the policy outputs ``a`` in [-1, 1].

    Args:
        controller: a set-point speed controller with ``set_point(ring_length) -> U_ref`` and
            ``command(gap, speed, leader_speed, U) -> v_cmd`` plus ``dt``, ``low``, ``high``
            (:class:`~mixed_traffic.controllers.dampers.FollowerStopper` with ``u_ratio=1``).
        ratio0: the set point's ratio to ``U_ref`` at ``a = 0`` (> 0, default 0.9).
        weight: the ratio moves by ``weight * a`` (>= 0, default 0.1).
        rate: if set (> 0), the action is the ratio's rate of change instead: each step
            ``ratio = clip(ratio + rate * a, low, high)``, from ``ratio0`` at reset. A held set
            point then needs no held action, and the policy's per-step exploration noise adds
            up to slow, persistent excursions of the set point (what shows its effect on a ring).
        low, high: the ratio's range in ``rate`` mode (default 0.8, 1.05).
        ramp_to, ramp_start, ramp_end: if ``ramp_to`` is set, the action acts around a schedule
            in episode time instead of the constant ``ratio0``: ``b(t) = ratio0`` until
            ``ramp_start``, linear to ``ramp_to`` at ``ramp_end``, ``ramp_to`` after it (s), the
            ramped FollowerStopper's schedule. ``ratio = b(t) + weight * a``, or in ``rate`` mode
            ``ratio = clip(ratio + rate * a + b(t) - b(t - dt), low, high)``: at ``a = 0`` the
            controller is the ramped FollowerStopper, and the policy learns a correction to it.
        action_key: the policy's action (replaced by the executed acceleration).
        gap_key, speed_key, leader_speed_key, ring_length_key: the state entries read.
        ratio_key: where the ratio used is logged (in ``"next"``).
        time_key: the episode time (s), read with ``ramp_to``.

    Example:
        >>> from mixed_traffic import make_env
        >>> from mixed_traffic.controllers.dampers import make_damper
        >>> from torchrl.envs import TransformedEnv
        >>> from transforms import SetPointAction
        >>> base = make_env("ring_wave", batch_size=2, seed=0, ring_length=230.0)
        >>> env = TransformedEnv(base, SetPointAction(make_damper("follower_stopper", base).module, ratio0=0.9))
        >>> td = env.rollout(3, lambda td: td.set("action", torch.ones(2, 1)))
        >>> [round(float(r), 2) for r in td["next", "set_point", "ratio"][0, :, 0]]
        [1.0, 1.0, 1.0]
    """

    def __init__(self, controller: nn.Module, *, ratio0: float = 0.9, weight: float = 0.1,
                 rate: float | None = None, low: float = 0.8, high: float = 1.05, action_key: NestedKey = "action", gap_key: NestedKey = ("cav", "gap"),
                 speed_key: NestedKey = ("cav", "speed"), leader_speed_key: NestedKey = ("cav", "leader_speed"),
                 ring_length_key: NestedKey = ("traffic", "ring_length"),
                 ratio_key: NestedKey = ("set_point", "ratio"), ramp_to: float | None = None,
                 ramp_start: float = 150.0, ramp_end: float = 300.0, time_key: NestedKey = ("traffic", "time")):
        if not ratio0 > 0:
            raise ValueError(f"SetPointAction: ratio0={ratio0!r} is invalid; allowed: > 0")
        if ramp_to is not None and not (ramp_to > 0 and 0 <= ramp_start < ramp_end):
            raise ValueError(f"SetPointAction: ramp_to={ramp_to!r}, ramp_start={ramp_start!r}, ramp_end={ramp_end!r} "
                             "are invalid; allowed: ramp_to > 0 and 0 <= ramp_start < ramp_end (s)")
        lowest = ratio0 if ramp_to is None else min(ratio0, ramp_to)
        if not 0 <= weight < lowest:
            raise ValueError(f"SetPointAction: weight={weight!r} is invalid; allowed: 0 <= weight < min(ratio0, ramp_to) "
                             f"({lowest}), so the set point stays > 0")
        ends = (ratio0,) if ramp_to is None else (ratio0, ramp_to)
        if rate is not None and not (rate > 0 and 0 < low and all(low <= r <= high for r in ends)):
            raise ValueError(f"SetPointAction: rate={rate!r}, low={low!r}, ratio0={ratio0!r}, ramp_to={ramp_to!r}, "
                             f"high={high!r} are invalid; allowed: rate > 0 and 0 < low <= ratio0, ramp_to <= high")
        for name in ("set_point", "command", "dt", "low", "high"):
            if not hasattr(controller, name):
                raise ValueError(f"SetPointAction: controller {type(controller).__name__} has no {name!r}; allowed: "
                                 "a set-point controller such as dampers.FollowerStopper")
        super().__init__(in_keys=[], out_keys=[ratio_key], in_keys_inv=[action_key], out_keys_inv=[action_key])
        self.controller, self.ratio0, self.weight = controller, float(ratio0), float(weight)
        self.rate = None if rate is None else float(rate)
        self.low, self.high = float(low), float(high)
        self.action_key, self.ratio_key = action_key, ratio_key
        self.state_keys = (gap_key, speed_key, leader_speed_key)
        self.ring_length_key = ring_length_key
        self.ramp = None if ramp_to is None else (float(ramp_to), float(ramp_start), float(ramp_end))
        self.time_key = time_key

    def base(self, time):
        """The ratio at ``a = 0``: ``ratio0``, or the schedule ``b(time)`` with ``ramp_to``."""
        if self.ramp is None:
            return self.ratio0
        return linear_schedule(time, self.ratio0, *self.ramp)

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get(self.action_key)
        gap, speed, leader = (tensordict.get(k) for k in self.state_keys)
        a = action.clamp(-1.0, 1.0).reshape(speed.shape).double()
        c = self.controller
        t = tensordict.get(self.time_key).double() if self.ramp is not None else None
        if self.rate is None:
            ratio = self.base(t) + self.weight * a
        else:  # the ratio in force (the observation's entry) moved by rate * a and by the schedule's step
            drift = 0.0 if t is None else self.base(t) - self.base(t - float(c.dt))
            ratio = (tensordict.get(self.ratio_key).reshape(speed.shape).double() + self.rate * a
                     + drift).clamp(self.low, self.high)
        U = (c.set_point(tensordict.get(self.ring_length_key).double()).expand_as(speed) * ratio).to(speed.dtype)
        v_cmd = c.command(gap, speed, leader, U)
        executed = ((v_cmd - speed) / c.dt).clamp(c.low, c.high)
        tensordict.set(self.action_key, executed.to(action.dtype).reshape(action.shape))
        tensordict.set(self.ratio_key, ratio.to(action.dtype).reshape(action.shape))
        return tensordict

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        return carry_to_next(tensordict, next_tensordict, self.ratio_key)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        tensordict_reset.set(self.ratio_key, action_shaped_full(self.parent, self.action_key, self.ratio0))
        return tensordict_reset

    def transform_action_spec(self, action_spec):
        return with_bounded_action(action_spec, self.action_key, -1.0, 1.0)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        return with_action_shaped_entry(observation_spec, self.parent, self.action_key, self.ratio_key)

    def __repr__(self) -> str:
        mode = f"rate={self.rate}, low={self.low}, high={self.high}" if self.rate else f"weight={self.weight}"
        if self.ramp is not None:
            mode += f", ramp_to={self.ramp[0]}, ramp_start={self.ramp[1]}, ramp_end={self.ramp[2]}"
        return f"{type(self).__name__}(ratio0={self.ratio0}, {mode}, controller={type(self.controller).__name__})"
