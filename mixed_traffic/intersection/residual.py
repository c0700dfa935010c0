"""Residual action around the intersection NMPC: ``a = clip(a_mpc + w * a_res, -a_max, a_max)``.

The transform runs the NMPC on every new observation and publishes its action as
``("residual", "base_action")`` (an observation entry, so the residual policy can read it);
on the way back it adds ``w`` times the policy's residual. The policy's raw residual stays in
the rollout (PPO log-probs); ``("residual", "executed")`` in ``"next"`` holds what the env ran.

>>> from mixed_traffic import make_env
>>> from torchrl.envs import TransformedEnv
>>> from mixed_traffic.intersection.residual import ResidualNMPC
>>> env = TransformedEnv(make_env("intersection", batch_size=2, seed=0), ResidualNMPC(weight=0.5))
>>> td = env.rollout(3, break_when_any_done=False)
>>> td["residual", "base_action"].shape
torch.Size([2, 3, 1])
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.data import Composite, Unbounded
from torchrl.envs.transforms import Transform

from mixed_traffic.intersection.nmpc import NMPCConfig, NMPCController

BASE_KEY = ("residual", "base_action")
EXEC_KEY = ("residual", "executed")


class ResidualNMPC(Transform):
    """Residual action around an :class:`NMPCController` (see the module docstring).

    Args:
        weight: ``w``, the scale of the residual (> 0).
        nmpc: the controller (default: ``NMPCController(NMPCConfig())``).
        a_max: action bound (default: the parent's action spec).
    """

    def __init__(self, weight: float = 0.5, nmpc: NMPCController | None = None, a_max: float | None = None):
        if not (isinstance(weight, (int, float)) and weight > 0):
            raise ValueError(f"ResidualNMPC: weight={weight!r} is invalid; allowed: > 0")
        super().__init__(in_keys=[], out_keys=[BASE_KEY], in_keys_inv=["action"], out_keys_inv=["action"])
        self.weight = float(weight)
        self.nmpc = nmpc or NMPCController(NMPCConfig())
        self._a_max = a_max

    @property
    def a_max(self) -> float:
        if self._a_max is None:
            self._a_max = float(self.parent.full_action_spec["action"].space.high.flatten()[0])
        return self._a_max

    def _base(self, obs: torch.Tensor, rows: torch.Tensor | None = None) -> torch.Tensor:
        """NMPC action for the given rows (all rows when ``rows`` is None); others get 0."""
        out = torch.zeros(*obs.shape[:-1], 1, dtype=obs.dtype, device=obs.device)
        flat = obs.reshape(-1, obs.shape[-1])
        idx = torch.arange(flat.shape[0]) if rows is None else rows.reshape(-1).nonzero().squeeze(-1).cpu()
        if len(idx):
            self.nmpc.set_rows(idx.tolist())
            a = self.nmpc(flat[idx])
            self.nmpc.set_rows(None)
            out.reshape(-1, 1)[idx] = a.to(out)
        return out

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        res = tensordict.get("action")
        base = tensordict.get(BASE_KEY)
        a = (base + self.weight * res).clamp(-self.a_max, self.a_max)
        tensordict.set("action", a)
        tensordict.set(EXEC_KEY, a)
        return tensordict

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        done = next_tensordict.get("done", None)
        alive = None if done is None else ~done.reshape(-1)
        next_tensordict.set(BASE_KEY, self._base(next_tensordict.get("observation"), alive))
        ex = tensordict.get(EXEC_KEY, None)
        if ex is not None:
            next_tensordict.set(EXEC_KEY, ex)
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        obs = tensordict_reset.get("observation")
        mask = None
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict.get("_reset").reshape(-1)
        base = self._base(obs, mask)
        if mask is not None and tensordict.get(BASE_KEY, None) is not None:
            keep = ~mask.reshape(base.shape[:-1])
            base[keep] = tensordict.get(BASE_KEY)[keep].to(base)
        tensordict_reset.set(BASE_KEY, base)
        tensordict_reset.set(EXEC_KEY, torch.zeros_like(base))
        return tensordict_reset

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        spec = self.parent.full_action_spec["action"]
        observation_spec[BASE_KEY] = Unbounded(shape=spec.shape, dtype=spec.dtype, device=spec.device)
        observation_spec[EXEC_KEY] = Unbounded(shape=spec.shape, dtype=spec.dtype, device=spec.device)
        return observation_spec


__all__ = ["ResidualNMPC", "BASE_KEY", "EXEC_KEY"]
