"""Jerk penalty: a smoothness term on the executed acceleration.

The DeeP-LCC reward penalises ``a^2`` but not how fast ``a`` changes, so a learned policy
may chatter where a car-following model is smooth. TorchRL has no transform that reads
an entry before and after the step to shape the reward, hence :class:`JerkPenalty`.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.envs.transforms import Transform

from transforms.specs import action_range


class JerkPenalty(Transform):
    """``r <- r - weight * sum_cav |a_t - a_{t-1}| / scale`` on the executed acceleration.

    ``a_{t-1}`` is ``accel_key`` of the step's input, ``a_t`` the same entry after the
    step (the env key contract's ``("cav", "accel")``); on the first step of an episode
    ``a_{t-1}`` is the reset value (0). ``scale`` (m/s^2) defaults to the width of the
    action bounds, so each term is in ``[0, 1]``. The absolute value (not the square)
    prices persistent chatter without making a necessary hard brake expensive. Place it
    after the reward shaping (e.g. after :class:`NonNegativeReward`, which overwrites the
    reward). It shapes training only: the evaluation drops it, so returns stay the task's.

    Args:
        weight: penalty weight (>= 0).
        weight_after: the weight from ``after_seconds`` of the episode on (``None``: ``weight`` throughout); the
            episode's time is ``time_key`` of the step's result. A start transient's large changes of command then
            need not dominate what the price teaches about following.
        after_seconds: when ``weight_after`` takes over (s, >= 0).
        scale: normalisation of the acceleration change (m/s^2, > 0); ``None`` reads the
            action bounds.
        accel_key: executed acceleration entry (default ``("cav", "accel")``).
        reward_key: reward entry (default ``"reward"``).

    Example:
        >>> import torch
        >>> from mixed_traffic import make_env
        >>> from torchrl.envs import TransformedEnv
        >>> from transforms import JerkPenalty
        >>> env = TransformedEnv(make_env("ring", batch_size=1, seed=0), JerkPenalty(weight=1.0))
        >>> plain = make_env("ring", batch_size=1, seed=0)
        >>> act = lambda td: td.set("action", torch.full((1, 1), 3.0))
        >>> r = env.rollout(2, act)["next", "reward"] - plain.rollout(2, act)["next", "reward"]
        >>> [round(float(x), 4) for x in r.flatten()]  # 0 -> 3 m/s^2 on the first step, then constant
        [-0.5, 0.0]
    """

    def __init__(self, weight: float = 0.1, scale: float | None = None, *, weight_after: float | None = None,
                 after_seconds: float = 0.0, accel_key: NestedKey = ("cav", "accel"), reward_key: NestedKey = "reward",
                 time_key: NestedKey = ("traffic", "time")):
        if not weight >= 0:
            raise ValueError(f"JerkPenalty: weight={weight!r} is invalid; allowed: >= 0")
        if scale is not None and not scale > 0:
            raise ValueError(f"JerkPenalty: scale={scale!r} is invalid; allowed: > 0 (m/s^2) or None")
        if weight_after is not None and not weight_after >= 0:
            raise ValueError(f"JerkPenalty: weight_after={weight_after!r} is invalid; allowed: null or >= 0")
        if not after_seconds >= 0:
            raise ValueError(f"JerkPenalty: after_seconds={after_seconds!r} is invalid; allowed: >= 0 (s)")
        super().__init__(in_keys=[accel_key, reward_key], out_keys=[reward_key])
        self.weight, self._scale = float(weight), scale
        self.weight_after = None if weight_after is None else float(weight_after)
        self.after_seconds = float(after_seconds)
        self.accel_key, self.reward_key, self.time_key = accel_key, reward_key, time_key

    @property
    def scale(self) -> float:
        if self._scale is None:
            self._scale = action_range(self.parent)
        return self._scale

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        prev = tensordict.get(self.accel_key, None)
        now = next_tensordict.get(self.accel_key)
        reward = next_tensordict.get(self.reward_key)
        if prev is None:
            prev = torch.zeros_like(now)
        pen = ((now - prev).abs() / self.scale).sum(-1, keepdim=True).to(reward.dtype).reshape(reward.shape)
        weight = self.weight
        if self.weight_after is not None:  # the episode's time decides which weight prices the step
            late = next_tensordict.get(self.time_key).reshape(reward.shape) >= self.after_seconds
            weight = torch.where(late, torch.full_like(pen, self.weight_after), torch.full_like(pen, self.weight))
        next_tensordict.set(self.reward_key, reward - weight * pen)
        return next_tensordict

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise RuntimeError("JerkPenalty reads the state before and after a step; use it inside an env")

    def __repr__(self) -> str:
        after = "" if self.weight_after is None else f", weight_after={self.weight_after}, after_seconds={self.after_seconds}"
        return f"{type(self).__name__}(weight={self.weight}{after})"
