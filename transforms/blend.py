"""The policy schedules the hand-over between two classical controllers.

Two classical wave dampers each do one job well: FollowerStopper with a low, ramped set point
dissolves a ring's stop-and-go wave; PI with saturation, whose set point is its own average
speed, holds a dissolved ring at the speed it sustains (``docs/wave.md``). When to hand over,
and how far, depends on the ring and on the wave. :class:`ControllerBlend` lets a policy decide:
it executes ``(1 - m) * first + m * second`` and the policy's action moves the weight ``m``.
TorchRL's action transforms map actions elementwise; this one runs two controllers on the state.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Composite
from torchrl.envs.transforms import Transform

from transforms.set_point import linear_schedule
from transforms.specs import action_shaped_full, carry_to_next, with_action_shaped_entry, with_bounded_action


class ControllerBlend(Transform):
    """Executes ``(1 - m) * first(state) + m * second(state)``; the policy's ``a`` in [-1, 1] moves ``m``.

    ``m = b(t) + c``: ``b(t)`` is the hand-over schedule (``weight0`` until ``start``, linear to
    ``weight1`` at ``end``, s) and ``c`` the policy's correction, integrated each step,
    ``c = clip(c + rate * a, -b(t), 1 - b(t))`` (so ``m`` stays in [0, 1] and ``c`` does not
    wind up), 0 at reset. At ``a = 0`` the executed command is exactly the classical hand-over
    (e.g. the ``fs_then_pi`` damper); the policy learns to hand over earlier, later or partly.

    Args:
        first, second: controllers as ``TensorDictModule``s writing the acceleration to their
            first out key (:func:`mixed_traffic.controllers.dampers.make_damper`); each runs on
            a shallow copy of the step's input, within the env's bounds, so the blend is too.
        rate: the correction's change per step at ``|a| = 1`` (> 0).
        weight0, weight1, start, end: the schedule ``b(t)`` (weights in [0, 1], ``0 <= start < end``).
        action_key: the policy's action (replaced by the executed acceleration).
        weight_key: where the weight ``m`` in force is logged (in ``"next"``; an observation).
        correction_key: the correction ``c`` (state carried between steps; an observation).
        time_key: the episode time (s).

    Example:
        >>> from mixed_traffic import make_env
        >>> from mixed_traffic.controllers.dampers import make_damper
        >>> from torchrl.envs import TransformedEnv
        >>> base = make_env("ring_wave", batch_size=2, seed=0)
        >>> fs = make_damper("follower_stopper", base, u_ratio=0.87, ramp_to=1.0)
        >>> env = TransformedEnv(base, ControllerBlend(fs, make_damper("pi_saturation", base), rate=0.001))
        >>> td = env.rollout(5)
        >>> td["next", "blend", "weight"].shape
        torch.Size([2, 5, 1])
    """

    def __init__(self, first, second, *, rate: float, weight0: float = 0.0, weight1: float = 1.0,
                 start: float = 300.0, end: float = 330.0, action_key: NestedKey = "action",
                 weight_key: NestedKey = ("blend", "weight"), correction_key: NestedKey = ("blend", "correction"),
                 time_key: NestedKey = ("traffic", "time")):
        if not rate > 0:
            raise ValueError(f"ControllerBlend: rate={rate!r} is invalid; allowed: > 0 (weight per step)")
        if not (0 <= weight0 <= 1 and 0 <= weight1 <= 1 and 0 <= start < end):
            raise ValueError(f"ControllerBlend: weight0={weight0!r}, weight1={weight1!r}, start={start!r}, end={end!r} "
                             "are invalid; allowed: weights in [0, 1], 0 <= start < end (s)")
        for name, c in (("first", first), ("second", second)):
            if not (callable(c) and getattr(c, "out_keys", None)):
                raise ValueError(f"ControllerBlend: {name}={type(c).__name__} is invalid; allowed: a TensorDictModule "
                                 "that writes the acceleration (make_damper)")
        super().__init__(in_keys_inv=[action_key], out_keys_inv=[action_key])
        self.first, self.second = first, second
        self.rate, self.schedule = float(rate), (float(weight0), float(weight1), float(start), float(end))
        self.action_key, self.weight_key, self.correction_key = action_key, weight_key, correction_key
        self.time_key = time_key

    def base(self, time):
        """The weight at ``a = 0``: the schedule ``b(time)``."""
        return linear_schedule(time, *self.schedule)

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get(self.action_key)
        a = action.clamp(-1.0, 1.0)
        # in the action's dtype, as the classical hand-over computes it: a = 0 gives its command exactly
        b = self.base(tensordict.get(self.time_key).to(a.dtype)).reshape(-1, *([1] * (a.dim() - 1))).expand_as(a)
        c = tensordict.get(self.correction_key).to(a.dtype) + self.rate * a
        c = torch.minimum(torch.maximum(c, -b), 1.0 - b)
        m = b + c
        a1 = self.first(tensordict.copy()).get(self.first.out_keys[0]).reshape(m.shape)
        a2 = self.second(tensordict.copy()).get(self.second.out_keys[0]).reshape(m.shape)
        tensordict.set(self.action_key, (1.0 - m) * a1 + m * a2)
        tensordict.set(self.weight_key, m)
        tensordict.set(self.correction_key, c)
        return tensordict

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        return carry_to_next(tensordict, next_tensordict, self.weight_key, self.correction_key)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        w0 = float(self.base(torch.zeros(())))
        tensordict_reset.set(self.weight_key, action_shaped_full(self.parent, self.action_key, w0))
        tensordict_reset.set(self.correction_key, action_shaped_full(self.parent, self.action_key, 0.0))
        return tensordict_reset

    def transform_action_spec(self, action_spec):
        return with_bounded_action(action_spec, self.action_key, -1.0, 1.0)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        observation_spec = with_action_shaped_entry(observation_spec, self.parent, self.action_key, self.weight_key)
        return with_action_shaped_entry(observation_spec, self.parent, self.action_key, self.correction_key)

    def __repr__(self) -> str:
        w0, w1, t1, t2 = self.schedule
        return (f"{type(self).__name__}(rate={self.rate}, schedule={w0}->{w1} over [{t1}, {t2}] s, "
                f"first={type(self.first.module).__name__}, second={type(self.second.module).__name__})")
