"""Reward against a twin run by a base controller on the same disturbances (common random numbers).

On the DeeP-LCC platoon the stage cost of a step is set mostly by what the policy cannot
change: the head's profile and the humans' noise. A residual policy that improves the
closed loop by 10% changes ``J`` by a tenth of its size, under disturbances that change it by
orders of magnitude from one episode (and one profile) to the next, so PPO's advantage
estimates drown in the exogenous variance. :class:`CounterfactualReward` removes it: beside
the env it keeps a *twin* of every row, in the same state at reset, driven by the base
controller (e.g. the frozen NNMPC) and fed the **same** noise draws as the row, and rewards
the row by how much cheaper its step was than the twin's::

    r = max(0, offset + (J_twin - J) / (scale * J_ref[profile]))     (collision: collision_reward)

The twin's costs do not depend on the policy, so ``sum_t J_twin`` is a constant of the episode
and the undiscounted return ranks policies exactly as ``-sum_t J`` does; only the variance
goes. ``J_ref[profile]`` (the base controller's mean stage cost on that profile) puts a given
relative improvement on the same footing on every profile; an ``offset`` > 0 keeps the reward
non-negative, so ending the episode early never pays (``offset=0``: the plain difference, no
clamp, for chains whose safety layer rules collisions out; the critic then learns values near 0). TorchRL has no reward that needs a
replayed copy of the environment; the env provides the replay (``make_twin``,
``copy_rows_from``, ``replay_step``, ``window``: :class:`~mixed_traffic.envs.platoon.PlatoonEnv`).
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.data import Composite, Unbounded

from transforms.rewards import _StageCostReward
from transforms.specs import per_row, profile_table


class CounterfactualReward(_StageCostReward):
    """``r = max(0, offset + (J_twin - J) / (scale J_ref[p]))``: the step's cost against a base-controller twin's.

    Args:
        base: the twin's controller, a module reading the env's window (``uini``, ``yini``,
            ``eini``) and writing ``action_key``.
        J_ref: ``{profile name: reference stage cost per step > 0}`` for every profile the env draws.
        kinds: the profile names in the order of the env's profile index (the platoon's ``PROFILE_KINDS``).
        scale: ``J_twin - J`` is divided by ``scale * J_ref`` (> 0, default 5).
        offset: added to the scaled difference (>= 0, default 1); with ``offset > 0`` the reward is
            clamped at 0, with ``offset=0`` it is the plain difference.
        collision_reward: the reward of a step that ends in a collision (default -1).
        action_key, j_key, kind_key, collision_key, reward_key: entries read and written.

    The base env must provide the twin replay (the torch ``PlatoonEnv`` does); the twin runs
    without the chain's other transforms (no safety layer). The twin is not part of a
    checkpoint: after a resume it restarts from the rows' current state.

    Example:
        >>> from mixed_traffic import make_env
        >>> from mixed_traffic.envs.platoon import PROFILE_KINDS
        >>> from torchrl.envs import TransformedEnv
        >>> from tensordict.nn import TensorDictModule
        >>> from transforms import CounterfactualReward
        >>> zero = TensorDictModule(lambda u: u[..., -2:] * 0, in_keys=["uini"], out_keys=["action"])
        >>> env = TransformedEnv(make_env("platoon", batch_size=2, seed=0, profiles=["random1"]),
        ...                      CounterfactualReward(zero, {"random1": 1.0}, kinds=PROFILE_KINDS))
        >>> td = env.rollout(4, zero)            # the policy is the base controller: the twin's exact copy
        >>> bool((td["next", "reward"] == 1).all())
        True
    """

    def __init__(self, base: TensorDictModuleBase, J_ref: dict, *, kinds, scale: float = 5.0, offset: float = 1.0,
                 collision_reward: float = -1.0, action_key: NestedKey = "action",
                 j_key: NestedKey = ("traffic", "J"), kind_key: NestedKey = ("deeplcc", "kind"),
                 collision_key: NestedKey = "collision", reward_key: NestedKey = "reward"):
        table = profile_table("CounterfactualReward", "J_ref", J_ref, kinds)
        if not scale > 0:
            raise ValueError(f"CounterfactualReward: scale={scale!r} is invalid; allowed: > 0")
        if not offset >= 0:
            raise ValueError(f"CounterfactualReward: offset={offset!r} is invalid; allowed: >= 0")
        super().__init__(None, j_key, collision_key, reward_key, collision_reward=float(collision_reward))
        self.in_keys = [*self.in_keys, kind_key]
        self.base = base
        self.register_buffer("J_ref_table", table)
        self.kinds = list(kinds)
        self.scale, self.offset = float(scale), float(offset)
        self.action_key, self.kind_key = action_key, kind_key
        self._twin = None
        self._rng_state = None

    # ------------------------------------------------------------------ the twin
    def _sim(self):
        env = self.parent.base_env if self.parent is not None else None
        if env is None or not hasattr(env, "make_twin"):
            raise ValueError(f"CounterfactualReward: the base env {type(env).__name__} cannot replay its rows; "
                             "allowed: an env with make_twin / copy_rows_from / replay_step / window "
                             "(make_env('platoon'))")
        return env

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        env = self._sim()
        if self._twin is None:
            self._twin = env.make_twin()
        mask = tensordict.get("_reset", None) if tensordict is not None else None
        rows = None if mask is None else mask.reshape(-1).cpu().nonzero().squeeze(-1)
        self._twin.copy_rows_from(env, rows)
        tensordict_reset.set(("traffic", "J_twin"), tensordict_reset.get(self.j_key).clone())  # the same state
        return tensordict_reset

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        # the noise the env is about to draw for this step: the twin draws the same
        self._rng_state = self._sim().rng.get_state()
        return tensordict

    def _reward(self, j: torch.Tensor, next_tensordict: TensorDictBase) -> torch.Tensor:
        """Step the twin with the base controller on this step's noise; the scaled cost difference."""
        if self._rng_state is None:
            raise RuntimeError("CounterfactualReward: the step did not pass through the transform's inverse; "
                               "step the TransformedEnv, not its base env")
        if self._twin is None:  # restored without a reset (resume): the twin starts from the current state
            self._twin = self._sim().make_twin()
            self._twin.copy_rows_from(self._sim())
        twin = self._twin
        with torch.no_grad():
            td = TensorDict(twin.window(), batch_size=twin.batch_size)
            u = self.base(td).get(self.action_key)
            j_twin = twin.replay_step(u.detach().cpu(), self._rng_state)
        self._rng_state = None
        j_ref = per_row(self.J_ref_table, next_tensordict.get(self.kind_key), self.kinds, "CounterfactualReward", "J_ref")
        j_twin = j_twin.to(j.dtype).to(j.device).reshape(j.shape)
        next_tensordict.set(("traffic", "J_twin"), j_twin.to(torch.float32))
        r = self.offset + (j_twin - j) / (self.scale * j_ref.to(j.device, j.dtype).reshape(j.shape))
        return r.clamp_min(0.0) if self.offset > 0 else r

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise RuntimeError("CounterfactualReward: needs the live env (the twin replays it); it cannot "
                           "recompute the reward of a stored batch")

    # ------------------------------------------------------------------ specs
    def transform_reward_spec(self, reward_spec: Composite) -> Composite:
        old = reward_spec[self.reward_key]
        reward_spec[self.reward_key] = Unbounded(shape=old.shape, dtype=old.dtype, device=old.device)
        return reward_spec

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        traffic = observation_spec["traffic"]
        j = traffic["J"]
        traffic["J_twin"] = Unbounded(shape=j.shape, dtype=torch.float32, device=j.device)
        return observation_spec
