"""Barrier force function (BFF): a physics-informed filter on the intersection ego's acceleration.

The executed acceleration is the policy's nominal action ``v`` plus two repulsive forces
from logarithmic barriers::

    u = clip(v + rho * dB_u/dv (v) + K * dB_x/da (x, v), -a_max, a_max)

* Action barrier ``B_u(v) = log(1 - z) + log(1 + z)``, ``z = v / a_max`` (clamped to
  ``|z| <= 0.99``): ``rho dB_u/dv = -2 rho z / (a_max (1 - z^2))`` pulls the command away
  from the actuator limits.
* State barrier on the predicted separation from the perceived agent: for look-ahead
  times ``tau`` (default 0.5, 1.0, 1.5 s) the ego's position ``y + v_e tau + a tau^2 / 2`` and
  the agent's constant-velocity prediction give the margin
  ``h = d(tau)^2 - (2R + |sigma|)^2``; ``B_x = sum_tau min(0, log(max(h, eps) / delta))``
  (a log barrier that is zero where ``h >= delta``, so it acts only near the agent). Its
  gradient with respect to the acceleration, ``(y(tau) - y_a(tau)) tau^2 / h`` where active,
  weighted by ``1 / tau^2`` so that imminent intrusions dominate later ones, pushes the ego
  away from the agent along its line (brake when the agent is ahead, accelerate when it is
  behind).

The policy's raw action stays in the rollout (PPO log-probs); the env runs ``u``. Each step
records ``("bff", "force")`` (``u - clip(v)``) in ``"next"``.

Reads ``observation = [y, v, x_a, y_a, vx_a, vy_a, sigma_x, sigma_y]`` of the intersection env.

>>> from mixed_traffic import make_env
>>> from torchrl.envs import TransformedEnv
>>> from transforms.barrier_force import BarrierForce
>>> env = TransformedEnv(make_env("intersection", batch_size=4, seed=0), BarrierForce(rho=0.2, K=0.5))
>>> td = env.rollout(10, break_when_any_done=False)
>>> td["next", "bff", "force"].shape
torch.Size([4, 10, 1])
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Composite
from torchrl.envs.transforms import Transform

from transforms.specs import action_shaped_full, carry_to_next, with_action_shaped_entry

Tensor = torch.Tensor


def action_barrier_grad(v: Tensor, a_max: float) -> Tensor:
    """``dB_u/dv`` of ``B_u = log(1 - v/a_max) + log(1 + v/a_max)`` (|v/a_max| clamped to 0.99)."""
    z = (v / a_max).clamp(-0.99, 0.99)
    return -2.0 * z / (a_max * (1.0 - z**2))


def state_barrier_grad(obs: Tensor, a: Tensor, *, ego_x: float = 0.5, radius: float = 0.3328,
                       taus: Sequence[float] = (0.5, 1.0, 1.5), delta: float = 1.0, eps: float = 1e-2,
                       v_min: float = 0.0) -> Tensor:
    """Weighted ``dB_x/da`` of the truncated log barrier on the predicted separation (module docstring).

    ``obs`` ``[..., 8]``, ``a`` ``[..., 1]``; returns ``[..., 1]``.
    """
    y, v = obs[..., 0:1], obs[..., 1:2]
    xa, ya, vxa, vya = obs[..., 2:3], obs[..., 3:4], obs[..., 4:5], obs[..., 5:6]
    sig = obs[..., 6:8].norm(dim=-1, keepdim=True)
    r2 = (2 * radius + sig) ** 2
    g = torch.zeros_like(a)
    for tau in taus:
        ye = y + v * tau + 0.5 * a * tau**2
        dy = ye - (ya + vya * tau)
        dx = ego_x - (xa + vxa * tau)
        h = dx**2 + dy**2 - r2
        active = h < delta
        # d/da log h = dy tau^2 / h; weighted by 1 / tau^2 so imminent intrusions dominate later ones
        g = g + torch.where(active, dy / h.clamp(min=eps), torch.zeros_like(h))
    return g


class BarrierForce(Transform):
    """Adds the barrier forces to the action before the env runs it (see the module docstring).

    Args:
        rho: gain of the action barrier (default 0.2).
        K: gain of the state barrier (default 0.5).
        a_max: action bound; ``None`` reads it from the parent's action spec.
        taus: look-ahead times of the state barrier (s).
        delta: the state barrier acts where the margin ``h < delta`` (m^2).
        eps: floor of the margin in the gradient (caps the force).
        radius: collision radius of each vehicle (m).

    >>> bff = BarrierForce(rho=0.2, K=0.5)
    >>> bff.rho, bff.K
    (0.2, 0.5)
    """

    def __init__(self, rho: float = 0.2, K: float = 0.5, *, a_max: float | None = None,
                 taus: Sequence[float] = (0.5, 1.0, 1.5), delta: float = 1.0, eps: float = 1e-2,
                 radius: float = 0.3328, action_key: NestedKey = "action", observation_key: NestedKey = "observation",
                 out_key: NestedKey = ("bff", "force")):
        for name, val in (("rho", rho), ("K", K)):
            if not (isinstance(val, (int, float)) and val >= 0):
                raise ValueError(f"BarrierForce: {name}={val!r} is invalid; allowed: >= 0")
        for name, val in (("delta", delta), ("eps", eps), ("radius", radius)):
            if not (isinstance(val, (int, float)) and val > 0):
                raise ValueError(f"BarrierForce: {name}={val!r} is invalid; allowed: > 0")
        if a_max is not None and not a_max > 0:
            raise ValueError(f"BarrierForce: a_max={a_max!r} is invalid; allowed: > 0 or None")
        if not taus or any(t <= 0 for t in taus):
            raise ValueError(f"BarrierForce: taus={taus!r} is invalid; allowed: a non-empty list of times > 0")
        super().__init__(in_keys=[], out_keys=[out_key], in_keys_inv=[action_key], out_keys_inv=[action_key])
        self.rho, self.K, self._a_max = float(rho), float(K), a_max
        self.taus, self.delta, self.eps, self.radius = tuple(float(t) for t in taus), float(delta), float(eps), float(radius)
        self.action_key, self.observation_key, self.out_key = action_key, observation_key, out_key

    @property
    def a_max(self) -> float:
        if self._a_max is None:
            spec = self.parent.full_action_spec[self.action_key]
            self._a_max = float(spec.space.high.flatten()[0])
        return self._a_max

    def filter(self, obs: Tensor, v: Tensor) -> Tensor:
        """The executed acceleration ``u`` for observations ``obs`` and nominal actions ``v``."""
        a_max = self.a_max
        v = v.clamp(-a_max, a_max)
        u = v + self.rho * action_barrier_grad(v, a_max)
        u = u + self.K * state_barrier_grad(obs, v, radius=self.radius, taus=self.taus, delta=self.delta, eps=self.eps)
        return u.clamp(-a_max, a_max)

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        v = tensordict.get(self.action_key)
        obs = tensordict.get(self.observation_key)
        u = self.filter(obs, v)
        tensordict.set(self.action_key, u)
        tensordict.set(self.out_key, u - v.clamp(-self.a_max, self.a_max))  # reaches `_step`, not the rollout
        return tensordict

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        return carry_to_next(tensordict, next_tensordict, self.out_key)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        tensordict_reset.set(self.out_key, action_shaped_full(self.parent, self.action_key, 0.0))
        return tensordict_reset

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        return with_action_shaped_entry(observation_spec, self.parent, self.action_key, self.out_key)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(rho={self.rho}, K={self.K}, taus={self.taus}, delta={self.delta})"


__all__ = ["BarrierForce", "action_barrier_grad", "state_barrier_grad"]
