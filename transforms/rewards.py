"""Rewards over the env's stage cost ``("traffic", "J")``.

The env's own reward is ``-J`` (the raw quadratic DeeP-LCC cost). A negative-only
reward invites ending the episode early (a collision stops the accumulation of
negative reward), so :class:`NonNegativeReward` maps it to ``[0, 1]`` and makes a
collision the worst outcome (-1). :class:`QuadraticReward` gives back the quadratic
form, optionally scaled, normalised by ``J_max`` or with a collision reward.
TorchRL's ``RewardScaling`` cannot express either (they read ``J`` and the collision
flag, not the reward).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Bounded, Composite, Unbounded
from torchrl.envs.transforms import Transform

from transforms.specs import per_row, profile_table


class _StageCostReward(Transform):
    """A reward computed from the step's stage cost ``J`` (subclasses: :meth:`_reward`); a step that
    ends in a collision gets ``collision_reward`` instead, unless that is None."""

    def __init__(self, J_max: float | None, j_key: NestedKey, collision_key: NestedKey, reward_key: NestedKey,
                 collision_reward: float | None = None):
        if J_max is not None and not J_max > 0:
            raise ValueError(f"{type(self).__name__}: J_max={J_max!r} is invalid; allowed: > 0 or None (read from the env)")
        super().__init__(in_keys=[j_key, collision_key], out_keys=[reward_key])
        self._J_max = J_max
        self.j_key, self.collision_key, self.reward_key = j_key, collision_key, reward_key
        self.collision_reward = None if collision_reward is None else float(collision_reward)

    @property
    def J_max(self) -> float:
        if self._J_max is None:
            j_max = getattr(self.parent, "J_max", None) if self.parent is not None else None
            if j_max is None:
                raise ValueError(f"{type(self).__name__}: J_max=None but the parent env has no `J_max`; "
                                 "pass J_max (> 0)")
            self._J_max = float(j_max)
        return self._J_max

    def _reward(self, j: torch.Tensor, next_tensordict: TensorDictBase) -> torch.Tensor:
        raise NotImplementedError

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        j = next_tensordict.get(self.j_key)
        reward = self._reward(j, next_tensordict)
        collision = next_tensordict.get(self.collision_key, None)
        if self.collision_reward is not None and collision is not None:
            reward = torch.where(collision.reshape(reward.shape), torch.full_like(reward, self.collision_reward), reward)
        old = next_tensordict.get(self.reward_key, None)
        if old is not None:
            reward = reward.to(old.dtype).reshape(old.shape)
        next_tensordict.set(self.reward_key, reward)
        return next_tensordict

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Recompute the reward of a collected batch (``"next"`` entries)."""
        if "next" in tensordict.keys():
            self._call(tensordict.get("next"))
            return tensordict
        return self._call(tensordict)


class NonNegativeReward(_StageCostReward):
    """``r = max(J_max - J, 0) / J_max`` in ``[0, 1]``, ``collision_reward`` (-1) on a collision.

    Args:
        J_max: worst-case stage cost; ``None`` reads ``env.J_max``.
        collision_reward: reward of a step that ends in a collision (default -1.0).
        j_key, collision_key, reward_key: entries read / written in ``"next"``.

    Example:
        >>> from mixed_traffic import make_env
        >>> from torchrl.envs import TransformedEnv
        >>> from transforms import NonNegativeReward
        >>> env = TransformedEnv(make_env("ring", batch_size=2, seed=0), NonNegativeReward())
        >>> r = env.rollout(5)["next", "reward"]
        >>> bool(((r >= 0) & (r <= 1)).all())
        True
    """

    def __init__(self, J_max: float | None = None, *, collision_reward: float = -1.0,
                 j_key: NestedKey = ("traffic", "J"), collision_key: NestedKey = "collision",
                 reward_key: NestedKey = "reward"):
        super().__init__(J_max, j_key, collision_key, reward_key, collision_reward=float(collision_reward))

    def _j_max(self, next_tensordict: TensorDictBase) -> torch.Tensor | float:
        return self.J_max

    def _reward(self, j, next_tensordict):
        j_max = self._j_max(next_tensordict)
        if isinstance(j_max, torch.Tensor):
            j_max = j_max.reshape(j.shape).to(j.dtype)
        return (j_max - j).clamp_min(0.0) / j_max

    def transform_reward_spec(self, reward_spec: Composite) -> Composite:
        old = reward_spec[self.reward_key]
        low = min(self.collision_reward, 0.0)
        high = max(self.collision_reward, 1.0)
        reward_spec[self.reward_key] = Bounded(low=low, high=high, shape=old.shape, dtype=old.dtype,
                                               device=old.device)
        return reward_spec


class QuadraticReward(_StageCostReward):
    """The raw quadratic reward ``r = -scale * J`` (``-J / J_max`` with ``normalize=True``).

    Args:
        scale: multiplies ``-J`` (> 0, default 1.0).
        normalize: divide by ``J_max`` (read from the env unless given).
        collision_reward: if set, the reward of a step that ends in a collision.
        J_max, j_key, collision_key, reward_key: as in :class:`NonNegativeReward`.

    Example:
        >>> from mixed_traffic import make_env
        >>> from torchrl.envs import TransformedEnv
        >>> from transforms import QuadraticReward
        >>> env = TransformedEnv(make_env("ring", batch_size=2, seed=0), QuadraticReward(normalize=True))
        >>> td = env.rollout(5)
        >>> bool(((td["next", "reward"] + td["next", "traffic", "J"] / env.J_max).abs() < 1e-6).all())
        True
    """

    def __init__(self, scale: float = 1.0, *, normalize: bool = False, collision_reward: float | None = None,
                 J_max: float | None = None, j_key: NestedKey = ("traffic", "J"),
                 collision_key: NestedKey = "collision", reward_key: NestedKey = "reward"):
        if not scale > 0:
            raise ValueError(f"QuadraticReward: scale={scale!r} is invalid; allowed: > 0")
        super().__init__(J_max, j_key, collision_key, reward_key, collision_reward=collision_reward)
        self.scale, self.normalize = float(scale), bool(normalize)

    def _reward(self, j, next_tensordict):
        r = -self.scale * j
        return r / self.J_max if self.normalize else r

    def transform_reward_spec(self, reward_spec: Composite) -> Composite:
        old = reward_spec[self.reward_key]
        reward_spec[self.reward_key] = Unbounded(shape=old.shape, dtype=old.dtype, device=old.device)
        return reward_spec


class ProfileNormalisedReward(NonNegativeReward):
    """:class:`NonNegativeReward` with one ``J_max`` per head profile: ``r = max(J_max[p] - J, 0) / J_max[p]``.

    Written because on the DeeP-LCC platoon the stage cost of one head profile is orders of
    magnitude above another's (under the NNMPC, mean ``J`` per step 0.23 on random +-1 against
    ~150 in the brake scenario): with one ``J_max`` a 10% cut on the small profiles is worth
    ~1e-4 of the reward PPO sees and the return is the brake scenario's alone. With ``J_max[p]``
    a fixed multiple of profile ``p``'s reference cost, a given *relative* cut is worth the same
    reward on every profile. TorchRL's ``RewardScaling`` has one scale for all rows.

    Args:
        J_max: ``{profile name: J_max}``, one entry (> 0) for every name in ``kinds`` the env draws.
        kinds: the profile names in the order of the env's profile index (the platoon's
            ``PROFILE_KINDS``).
        kind_key: the per-row profile index in ``"next"`` (``("deeplcc", "kind")``).
        collision_reward, j_key, collision_key, reward_key: as in :class:`NonNegativeReward`.

    Example:
        >>> from mixed_traffic import make_env
        >>> from mixed_traffic.envs.platoon import PROFILE_KINDS
        >>> from torchrl.envs import TransformedEnv
        >>> from transforms import ProfileNormalisedReward
        >>> env = make_env("platoon", batch_size=2, seed=0, profiles=["random1", "brake"], profile_rows=True)
        >>> t = ProfileNormalisedReward({"random1": 5.0, "brake": 3000.0}, kinds=PROFILE_KINDS)
        >>> td = TransformedEnv(env, t).rollout(3)
        >>> bool(((td["next", "reward"] >= 0) & (td["next", "reward"] <= 1)).all())
        True
    """

    def __init__(self, J_max: dict, *, kinds, kind_key: NestedKey = ("deeplcc", "kind"),
                 collision_reward: float = -1.0, j_key: NestedKey = ("traffic", "J"),
                 collision_key: NestedKey = "collision", reward_key: NestedKey = "reward"):
        table = profile_table("ProfileNormalisedReward", "J_max", J_max, kinds)  # NaN: a profile without J_max
        super().__init__(1.0, collision_reward=collision_reward, j_key=j_key, collision_key=collision_key,
                         reward_key=reward_key)
        self.register_buffer("J_max_table", table)
        self.kinds, self.kind_key = list(kinds), kind_key
        self.in_keys = [*self.in_keys, kind_key]

    def _j_max(self, next_tensordict: TensorDictBase) -> torch.Tensor:
        return per_row(self.J_max_table, next_tensordict.get(self.kind_key), self.kinds, "ProfileNormalisedReward",
                       "J_max")
