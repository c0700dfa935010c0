"""Intervention cost: the safety layer's work, priced as a constraint cost.

A learned policy behind a :class:`~transforms.SafetyLayer` never feels a collision: the
layer brakes for it. Its Lagrangian cost (the s_min violation) then stays at zero, the
multiplier decays, and the policy may lean on the layer for every brake. This transform
adds the layer's intervention to the per-step constraint cost, so the multiplier that
prices the cost (:class:`~transforms.LagrangianPenalty`) rises exactly when the policy
relies on the layer, and the policy learns to brake by itself.

TorchRL has no transform that turns another transform's output into a cost, hence
:class:`InterventionCost`.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Composite, Unbounded
from torchrl.envs.transforms import Transform

from transforms.specs import action_range

MODES = ("magnitude", "indicator", "both")
DIRECTIONS = ("both", "brake", "push")


class InterventionCost(Transform):
    """Adds ``coef * c_int`` to the env's cost, with ``c_int`` the safety layer's intervention.

    Per step and CAV, from the layer's ``delta`` (executed minus commanded acceleration,
    m/s^2) and ``clipped`` flag:

    * ``mode="magnitude"``: ``|delta| / scale`` (``scale`` defaults to the width of the
      action bounds, so each term is in ``[0, 1]``);
    * ``mode="indicator"``: ``1`` where the layer changed the command (its mean is the
      intervention rate);
    * ``mode="both"`` (default): the mean of the two: every clip costs at least ``1/2``,
      however small, and a large correction costs more than a small one.

    ``direction`` chooses which corrections count: ``"both"`` (default), ``"brake"`` (only
    where the layer lowered the command: it braked for the policy) or ``"push"`` (only
    where it raised it, e.g. the head-gap bound ``s_max`` pulling the CAV up). ``"brake"``
    prices the layer's safety work alone and leaves the catch-up to a far head unpriced.

    The CAV terms are summed (as the env's s_min cost), multiplied by ``coef`` and added
    to ``cost_key`` in place; the intervention cost alone is also written to
    ``out_key`` (declared as an observation entry, so it does not join the reward keys).
    Place it after the :class:`~transforms.SafetyLayer` in the chain (the layer writes
    ``delta`` during the step).

    Args:
        coef: weight of the intervention cost in the total cost (> 0, default 1.0).
        mode: ``"magnitude"``, ``"indicator"`` or ``"both"``.
        direction: ``"both"``, ``"brake"`` or ``"push"`` (which corrections count).
        scale: normalisation of ``|delta|`` (m/s^2, > 0); ``None`` reads the action bounds.
        delta_key, clipped_key: the layer's outputs (defaults: the layer's defaults).
        cost_key: the per-step constraint cost to add to (default ``"cost"``).
        out_key: where the intervention cost alone is written
            (default ``("safety", "intervention_cost")``).

    Example:
        >>> import torch
        >>> from mixed_traffic import make_env
        >>> from torchrl.envs import Compose, TransformedEnv
        >>> from transforms import InterventionCost, SafetyLayer
        >>> env = TransformedEnv(make_env("ring", batch_size=2, seed=0),
        ...                      Compose(SafetyLayer(s_min=5.0, s_max=None), InterventionCost(mode="indicator")))
        >>> td = env.rollout(50, lambda td: td.set("action", torch.full((2, 1), 3.0)))
        >>> bool((td["next", "safety", "intervention_cost"] == td["next", "safety", "clipped"].float()).all())
        True
    """

    def __init__(self, coef: float = 1.0, mode: str = "both", scale: float | None = None, *,
                 direction: str = "both", delta_key: NestedKey = ("safety", "delta"), clipped_key: NestedKey = ("safety", "clipped"),
                 cost_key: NestedKey = "cost", out_key: NestedKey = ("safety", "intervention_cost")):
        if mode not in MODES:
            raise ValueError(f"InterventionCost: mode={mode!r} is invalid; allowed: {list(MODES)}")
        if direction not in DIRECTIONS:
            raise ValueError(f"InterventionCost: direction={direction!r} is invalid; allowed: {list(DIRECTIONS)}")
        if not coef > 0:
            raise ValueError(f"InterventionCost: coef={coef!r} is invalid; allowed: > 0")
        if scale is not None and not scale > 0:
            raise ValueError(f"InterventionCost: scale={scale!r} is invalid; allowed: > 0 (m/s^2) or None")
        super().__init__(in_keys=[delta_key, clipped_key, cost_key], out_keys=[cost_key, out_key])
        self.coef, self.mode, self._scale, self.direction = float(coef), mode, scale, direction
        self.delta_key, self.clipped_key, self.cost_key, self.out_key = delta_key, clipped_key, cost_key, out_key

    @property
    def scale(self) -> float:
        if self._scale is None:
            self._scale = action_range(self.parent)
        return self._scale

    def intervention(self, delta: torch.Tensor, clipped: torch.Tensor | None) -> torch.Tensor:
        """``c_int`` summed over the CAVs, ``[..., 1]`` (before ``coef``)."""
        if clipped is None:
            clipped = delta != 0
        if self.direction != "both":
            counted = delta < 0 if self.direction == "brake" else delta > 0
            delta = torch.where(counted, delta, torch.zeros_like(delta))
            clipped = clipped & counted
        mag = delta.abs() / self.scale
        ind = clipped.to(delta.dtype)
        c = mag if self.mode == "magnitude" else ind if self.mode == "indicator" else 0.5 * (mag + ind)
        return c.sum(-1, keepdim=True)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        delta = next_tensordict.get(self.delta_key, None)
        cost = next_tensordict.get(self.cost_key)
        if delta is None:
            c = torch.zeros_like(cost)
        else:
            c = self.intervention(delta, next_tensordict.get(self.clipped_key, None)).to(cost.dtype).reshape(cost.shape)
        next_tensordict.set(self.out_key, c)
        next_tensordict.set(self.cost_key, cost + self.coef * c)
        return next_tensordict

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise RuntimeError("InterventionCost prices the layer's work during the env step; use it inside an env "
                           "(a collected batch already holds the priced cost)")

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        spec = self.parent.full_reward_spec[self.cost_key]
        tensordict_reset.set(self.out_key, spec.zero())
        return tensordict_reset

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        spec = self.parent.full_reward_spec[self.cost_key]
        observation_spec[self.out_key] = Unbounded(shape=spec.shape, dtype=spec.dtype, device=spec.device)
        return observation_spec

    def __repr__(self) -> str:
        return f"{type(self).__name__}(coef={self.coef}, mode={self.mode!r}, direction={self.direction!r})"
