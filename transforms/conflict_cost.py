"""Training-only costs of the intersection: predicted conflicts and leaving the road.

The env's cost sees only the current separation from the perceived agent, so a policy
learns to brake late; and a cost-averse policy can escape every cost by reversing off the
road. TorchRL has no transform that adds a model-based term to a cost entry, hence
:class:`ConflictCost`. It shapes training only: the evaluation drops it, so the reported
cost is the env's. A constant-velocity
prediction also charges an ego that stands still while a turning agent's extrapolated path
sweeps past it (a left turner passes within 1 m of the ego's start); with ``ego_caused`` the
anticipation charges only the part of the predicted conflict the ego's own motion adds, so
waiting is never charged by it and reversing away from an approaching agent earns nothing.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.envs.transforms import Transform


def anticipation_cost(obs: torch.Tensor, *, horizon_s: float = 1.5, dt: float = 0.1, radius: float = 0.3328,
                      mu: float = 200.0, ego_x: float = 0.5, margin: float = 0.0) -> torch.Tensor:
    """``mu max(0, (2R + margin + |sigma|)^2 - d_min^2)``, ``d_min`` the closest approach over ``horizon_s``.

    Ego and perceived agent both keep their current velocities; ``obs`` is the intersection
    observation ``[..., 8]``; returns ``[..., 1]``.

    >>> o = torch.tensor([[-0.5, 2.0, 1.5, 0.5, -1.0, 0.0, 0.05, 0.05]])
    >>> bool(anticipation_cost(o) > 0), bool(anticipation_cost(o.index_fill(-1, torch.tensor([1]), 0.0)) == 0)
    (True, True)
    """
    tau = torch.arange(0.0, horizon_s + 1e-9, dt, dtype=obs.dtype, device=obs.device)
    y, v = obs[..., 0:1], obs[..., 1:2]
    xa, ya, vxa, vya = obs[..., 2:3], obs[..., 3:4], obs[..., 4:5], obs[..., 5:6]
    d2 = (ego_x - (xa + vxa * tau)) ** 2 + ((y + v * tau) - (ya + vya * tau)) ** 2
    sig = obs[..., 6:8].norm(dim=-1, keepdim=True)
    return mu * torch.clamp((2 * radius + margin + sig) ** 2 - d2.min(dim=-1, keepdim=True).values, min=0.0)


def ego_caused_anticipation_cost(obs: torch.Tensor, **kw) -> torch.Tensor:
    """``max(0, anticipation_cost(obs) - anticipation_cost(obs with the ego held))``: the predicted
    conflict that the ego's own velocity adds (``[..., 1]``; keywords as :func:`anticipation_cost`).

    >>> o = torch.tensor([[-1.25, 0.0, -0.1, -0.6, -0.8, -0.6, 0.2, 0.2]])  # ego waits, a turner sweeps by
    >>> bool(anticipation_cost(o) > 0), float(ego_caused_anticipation_cost(o))
    (True, 0.0)
    """
    held = obs.clone()
    held[..., 1] = 0.0
    return (anticipation_cost(obs, **kw) - anticipation_cost(held, **kw)).clamp(min=0.0)


class ConflictCost(Transform):
    """``cost <- cost + anticipation * anticipation_cost(obs') [not done] + out_of_bounds * [left the road]``.

    Args:
        anticipation: weight of :func:`anticipation_cost` on the next observation (>= 0).
        horizon_s: its prediction horizon (s).
        out_of_bounds: cost of the step that leaves the road (>= 0).
        ego_caused: charge only the part of the predicted conflict the ego's velocity adds
            (:func:`ego_caused_anticipation_cost`) instead of all of it.
        margin: extra separation (m, >= 0) the predicted approach is charged for, on top of the
            two radii and the perception error.

    Example:
        >>> from mixed_traffic import make_env
        >>> from torchrl.envs import TransformedEnv
        >>> env = TransformedEnv(make_env("intersection", batch_size=2, seed=0), ConflictCost(out_of_bounds=150.0))
        >>> env.rollout(3, break_when_any_done=False)["next", "cost"].shape
        torch.Size([2, 3, 1])
    """

    def __init__(self, anticipation: float = 1.0, horizon_s: float = 1.5, out_of_bounds: float = 150.0, *,
                 ego_caused: bool = False, margin: float = 0.0, cost_key: NestedKey = "cost"):
        for name, v in (("anticipation", anticipation), ("horizon_s", horizon_s), ("out_of_bounds", out_of_bounds),
                        ("margin", margin)):
            if not v >= 0:
                raise ValueError(f"ConflictCost: {name}={v!r} is invalid; allowed: >= 0")
        super().__init__(in_keys=["observation", cost_key], out_keys=[cost_key])
        self.anticipation, self.horizon_s, self.out_of_bounds = float(anticipation), float(horizon_s), float(out_of_bounds)
        self.cost_key, self.ego_caused, self.margin = cost_key, bool(ego_caused), float(margin)

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        cost = next_tensordict.get(self.cost_key)
        extra = torch.zeros_like(cost)
        if self.anticipation > 0:
            alive = ~next_tensordict.get("done").reshape(cost.shape)
            fn = ego_caused_anticipation_cost if self.ego_caused else anticipation_cost
            extra = extra + self.anticipation * fn(next_tensordict.get("observation"),
                                                   horizon_s=self.horizon_s, margin=self.margin).to(cost) * alive
        oob = next_tensordict.get("out_of_bounds", None)
        if self.out_of_bounds > 0 and oob is not None:
            extra = extra + self.out_of_bounds * oob.reshape(cost.shape).to(cost.dtype)
        next_tensordict.set(self.cost_key, cost + extra)
        return next_tensordict

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise RuntimeError("ConflictCost shapes the cost of env steps; use it inside an env")

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(anticipation={self.anticipation}, out_of_bounds={self.out_of_bounds}, "
                f"ego_caused={self.ego_caused}, margin={self.margin})")
