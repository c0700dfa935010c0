"""A comfort bound on the command's rate of change: ``|a_t - a_{t-1}| <= max_jerk * dt``.

TorchRL's action transforms rescale or discretise an action one step at a time; none bounds
its change against the vehicle's current acceleration, hence :class:`JerkLimit`.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.envs.transforms import Transform

from transforms.specs import entries_or_none, parent_dt


class JerkLimit(Transform):
    """Moves the command at most ``max_jerk * dt`` away from the CAV's current acceleration.

    ``a_exec = clip(a, a_now - max_jerk dt, a_now + max_jerk dt)`` with ``a_now`` the entry
    ``accel_key`` of the step's input (the env key contract's ``("cav", "accel")``: what the
    CAV executed on the last step). It is part of the controller, like an ACC's jerk bound:
    place it between the safety layer and the policy's command (``[..., safety_layer,
    jerk_limit, residual_idm, ...]``: the residual's sum is limited, the layer still brakes at
    once when it must) and it stays in the layer-free evaluation. Gradients pass where the
    command is inside the band (analytic policy gradients).

    Args:
        max_jerk: the bound (m/s^3, > 0).
        dt: the step (s); ``None`` reads the parent env's ``dt``.
        action_key: the command entry (default ``"action"``).
        accel_key: the current acceleration entry (default ``("cav", "accel")``).

    Example:
        >>> import torch
        >>> from mixed_traffic import make_env
        >>> from torchrl.envs import TransformedEnv
        >>> from transforms import JerkLimit
        >>> env = TransformedEnv(make_env("ring", batch_size=1, seed=0), JerkLimit(max_jerk=2.0))
        >>> td = env.rollout(3, lambda td: td.set("action", torch.full((1, 1), 3.0)))
        >>> [round(float(a), 2) for a in td["next", "cav", "accel"].flatten()]  # 0.2 m/s^2 more per 0.1 s step
        [0.2, 0.4, 0.6]
    """

    def __init__(self, max_jerk: float, dt: float | None = None, *, action_key: NestedKey = "action",
                 accel_key: NestedKey = ("cav", "accel")):
        if not max_jerk > 0:
            raise ValueError(f"JerkLimit: max_jerk={max_jerk!r} is invalid; allowed: > 0 (m/s^3)")
        if dt is not None and not dt > 0:
            raise ValueError(f"JerkLimit: dt={dt!r} is invalid; allowed: > 0 (s) or None")
        super().__init__(in_keys=[], out_keys=[], in_keys_inv=[action_key], out_keys_inv=[action_key])
        self.max_jerk, self._dt = float(max_jerk), dt
        self.action_key, self.accel_key = action_key, accel_key

    @property
    def dt(self) -> float:
        if self._dt is None:
            self._dt = parent_dt(self.parent, "JerkLimit")
        return self._dt

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        got = entries_or_none(self, tensordict, self.action_key, self.accel_key)
        if got is None:
            return tensordict
        a, now = got
        step = self.max_jerk * self.dt
        now = now.to(a.dtype).reshape(a.shape)
        tensordict.set(self.action_key, torch.minimum(torch.maximum(a, now - step), now + step))
        return tensordict

    def __repr__(self) -> str:
        return f"{type(self).__name__}(max_jerk={self.max_jerk})"
