"""Lagrange multiplier and the reward-penalty transform ``r - lambda * c``.

TorchRL has no transform that subtracts a learned multiple of a cost from the reward
(``RewardScaling`` is affine with fixed coefficients), hence :class:`LagrangianPenalty`.
"""

from __future__ import annotations

import os
import tempfile
import uuid
import weakref

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import Composite, Unbounded
from torchrl.envs.transforms import Transform

METHODS = ("dual_ascent", "adam", "sgd", "pid")


class LagrangeMultiplier(nn.Module):
    """A scalar multiplier ``lambda >= 0`` updated once per batch from the mean cost.

    ``method="dual_ascent"`` (default) applies the projected dual step
    ``lambda <- clip(lambda + lr (c_mean - cost_limit), 0, max_value)``.
    ``method="adam"`` / ``"sgd"`` instead minimise ``-lambda (c_mean - cost_limit)``
    with that torch optimiser (learning rate ``lr``) and project onto
    ``[0, max_value]`` after each step.
    ``method="pid"`` is the PID Lagrangian of Stooke, Achiam & Abbeel (2020, "Responsive
    Safety in RL by PID Lagrangian Methods"): with ``e = c_mean - cost_limit``,

    * ``I <- clip(I + lr e, 0, max_value)`` (the integral term: dual ascent, ``lr`` = K_I),
    * ``lambda <- clip(kp e + I + kd max(0, c_mean - c_prev), 0, max_value)``,

    where ``I`` starts at ``init``. The proportional term raises lambda as soon as the cost
    exceeds the limit and drops it as soon as it is met (less overshoot and oscillation
    than the pure integral); the derivative term reacts to a rising cost only.

    The value lives in shared memory backed by a file (``/dev/shm`` where available)
    and is only ever updated in place. Pickling the module (or a transform holding it)
    carries the file name, not the number, so every copy maps the same value: the
    workers of ``MultiSyncCollector`` / ``ParallelEnv`` built from a factory that
    captures it read the current value, whatever pickler ships the factory
    (TorchRL wraps env factories in cloudpickle, which would copy an ordinary
    ``share_memory_()`` tensor). A ``copy.deepcopy`` shares it too. The file is removed
    when the module that created it is garbage-collected.

    Args:
        init: initial value (``lambda_0``, default 1.0), in ``[0, max_value]``.
        lr: step size (``alpha``, default 0.05), > 0.
        max_value: upper bound (default 10.0), > 0.
        cost_limit: the tolerated mean cost ``d`` (default 0.1), >= 0.
        method: ``"dual_ascent"``, ``"adam"``, ``"sgd"`` or ``"pid"``.
        kp, kd: proportional and derivative gains of ``method="pid"`` (>= 0, default 0:
            with both 0 the PID method is dual ascent).

    Example:
        >>> lam = LagrangeMultiplier(init=1.0, lr=0.05, max_value=10.0, cost_limit=0.1)
        >>> lam.update(0.5)
        1.02
        >>> round(lam.update(0.0), 4)
        1.015
    """

    def __init__(self, init: float = 1.0, lr: float = 0.05, max_value: float = 10.0, cost_limit: float = 0.1,
                 method: str = "dual_ascent", kp: float = 0.0, kd: float = 0.0):
        super().__init__()
        if method not in METHODS:
            raise ValueError(f"LagrangeMultiplier: method={method!r} is invalid; allowed: {list(METHODS)}")
        if not max_value > 0:
            raise ValueError(f"LagrangeMultiplier: max_value={max_value!r} is invalid; allowed: > 0")
        if not 0 <= init <= max_value:
            raise ValueError(f"LagrangeMultiplier: init={init!r} is invalid; allowed: [0, max_value={max_value}]")
        if not lr > 0:
            raise ValueError(f"LagrangeMultiplier: lr={lr!r} is invalid; allowed: > 0")
        if not cost_limit >= 0:
            raise ValueError(f"LagrangeMultiplier: cost_limit={cost_limit!r} is invalid; allowed: >= 0")
        if not kp >= 0 or not kd >= 0:
            raise ValueError(f"LagrangeMultiplier: kp={kp!r}, kd={kd!r} are invalid; allowed: >= 0")
        self.lr, self.max_value, self.cost_limit, self.method = float(lr), float(max_value), float(cost_limit), method
        self.kp, self.kd = float(kp), float(kd)
        # PID state (main process only; saved with state_dict for resuming)
        self.register_buffer("pid_integral", torch.tensor(float(init), dtype=torch.float64))
        self.register_buffer("pid_prev_cost", torch.tensor(float("nan"), dtype=torch.float64))
        self._shm_path = self._new_shm_path()
        value = torch.from_file(self._shm_path, shared=True, size=1, dtype=torch.float64)
        value.fill_(float(init))
        self._finalizer = weakref.finalize(self, _unlink, self._shm_path)
        self.register_buffer("value", value.view(()))
        if method in ("adam", "sgd"):
            self.raw = nn.Parameter(torch.tensor(float(init)))
            opt = torch.optim.Adam if method == "adam" else torch.optim.SGD
            self._optim = opt([self.raw], lr=self.lr)

    @staticmethod
    def _new_shm_path() -> str:
        base = "/dev/shm" if os.path.isdir("/dev/shm") and os.access("/dev/shm", os.W_OK) else tempfile.gettempdir()
        return os.path.join(base, f"mixed_traffic_lambda_{os.getpid()}_{uuid.uuid4().hex}")

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_buffers"] = {k: v for k, v in self._buffers.items() if k != "value"}
        state.pop("_finalizer", None)
        state["_optim"] = None
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        value = torch.from_file(self._shm_path, shared=True, size=1, dtype=torch.float64)
        self._buffers["value"] = value.view(())
        if self.method in ("adam", "sgd"):
            opt = torch.optim.Adam if self.method == "adam" else torch.optim.SGD
            self._optim = opt([self.raw], lr=self.lr)

    def __deepcopy__(self, memo):
        import pickle

        return pickle.loads(pickle.dumps(self))

    def _load_from_state_dict(self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys,
                              error_msgs):
        # checkpoints written before the PID state existed: keep the defaults (integral = value)
        if prefix + "value" in state_dict and prefix + "pid_integral" not in state_dict:
            state_dict[prefix + "pid_integral"] = state_dict[prefix + "value"].detach().clone().double().reshape(())
            state_dict[prefix + "pid_prev_cost"] = torch.tensor(float("nan"), dtype=torch.float64)
        super()._load_from_state_dict(state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys,
                                      error_msgs)

    def __float__(self) -> float:
        return float(self.value)

    def get(self) -> torch.Tensor:
        """The current value (a detached 0-d tensor)."""
        return self.value.detach()

    def set_(self, value: float) -> LagrangeMultiplier:
        """Overwrite the value in place (clipped to ``[0, max_value]``)."""
        v = min(max(float(value), 0.0), self.max_value)
        self.value.fill_(v)
        self.pid_integral.fill_(v)
        if self.method in ("adam", "sgd"):
            with torch.no_grad():
                self.raw.fill_(v)
        return self

    @torch.no_grad()
    def _dual(self, violation: float) -> None:
        self.value.copy_((self.value + self.lr * violation).clamp(0.0, self.max_value))

    @torch.no_grad()
    def _pid(self, c: float, violation: float) -> None:
        self.pid_integral.copy_((self.pid_integral + self.lr * violation).clamp(0.0, self.max_value))
        prev = float(self.pid_prev_cost)
        d = 0.0 if prev != prev else max(0.0, c - prev)  # nan: first update
        self.pid_prev_cost.fill_(c)
        lam = self.kp * violation + float(self.pid_integral) + self.kd * d
        self.value.fill_(min(max(lam, 0.0), self.max_value))

    def update(self, mean_cost: float | torch.Tensor) -> float:
        """One update from the batch's mean cost; returns the new value."""
        c = float(torch.as_tensor(mean_cost, dtype=torch.float64).mean())
        violation = c - self.cost_limit
        if self.method == "dual_ascent":
            self._dual(violation)
        elif self.method == "pid":
            self._pid(c, violation)
        else:
            with torch.enable_grad():
                self._optim.zero_grad(set_to_none=True)
                loss = -self.raw * violation
                loss.backward()
                self._optim.step()
            with torch.no_grad():
                self.raw.clamp_(0.0, self.max_value)
                self.value.copy_(self.raw.detach())
        return float(self.value)

    def extra_repr(self) -> str:
        return (f"value={float(self.value):.4g}, lr={self.lr}, max_value={self.max_value}, "
                f"cost_limit={self.cost_limit}, method={self.method!r}"
                + (f", kp={self.kp}, kd={self.kd}" if self.method == "pid" else ""))


def _unlink(path: str) -> None:
    try:
        os.unlink(path)
    except OSError:
        pass


def _mean_cost(batch_or_mean, cost_key: NestedKey) -> torch.Tensor:
    if isinstance(batch_or_mean, TensorDictBase):
        key = ("next", *((cost_key,) if isinstance(cost_key, str) else cost_key))
        cost = batch_or_mean.get(key, None)
        if cost is None:
            cost = batch_or_mean.get(cost_key)
        return cost.float().mean()
    return torch.as_tensor(batch_or_mean, dtype=torch.float32).mean()


class LagrangianPenalty(Transform):
    """Penalised reward ``r - lambda * c`` with ``lambda`` held by the transform.

    Apply it after the reward shaping (e.g. after :class:`NonNegativeReward`). After
    each collected batch call :meth:`update` with the batch (the mean of
    ``("next", cost_key)`` is used) or with a mean cost. The multiplier sits in shared
    memory: pass the transform into the env factory of a multi-process collector
    (e.g. through ``functools.partial``) and every worker applies the current value.

    Args:
        lambda_init, lambda_lr, lambda_max, cost_limit, method, kp, kd: see
            :class:`LagrangeMultiplier` (defaults 1.0, 0.05, 10.0, 0.1, ``"dual_ascent"``, 0, 0).
        reward_key: reward entry to penalise (in place).
        cost_key: the per-step cost entry (the env's ``"cost"``).
        raw_reward_key: if set, the unpenalised reward is also written there (declared
            as an observation, so it does not join ``env.reward_keys``).
        multiplier: an existing :class:`LagrangeMultiplier` to share (overrides the
            ``lambda_*`` arguments).

    Example:
        >>> from mixed_traffic import make_env
        >>> from torchrl.envs import TransformedEnv
        >>> from transforms import LagrangianPenalty
        >>> penalty = LagrangianPenalty(lambda_init=1.0)
        >>> env = TransformedEnv(make_env("ring", batch_size=2, seed=0), penalty)
        >>> batch = env.rollout(5)
        >>> abs(penalty.update(batch) - min(max(1.0 + 0.05 * (batch["next", "cost"].mean().item() - 0.1), 0), 10)) < 1e-9
        True
    """

    def __init__(self, lambda_init: float = 1.0, lambda_lr: float = 0.05, lambda_max: float = 10.0,
                 cost_limit: float = 0.1, method: str = "dual_ascent", kp: float = 0.0, kd: float = 0.0, *,
                 reward_key: NestedKey = "reward",
                 cost_key: NestedKey = "cost", raw_reward_key: NestedKey | None = None,
                 multiplier: LagrangeMultiplier | None = None):
        super().__init__(in_keys=[reward_key, cost_key], out_keys=[reward_key])
        self.reward_key, self.cost_key, self.raw_reward_key = reward_key, cost_key, raw_reward_key
        self.multiplier = multiplier if multiplier is not None else LagrangeMultiplier(
            init=lambda_init, lr=lambda_lr, max_value=lambda_max, cost_limit=cost_limit, method=method, kp=kp, kd=kd)

    @property
    def lam(self) -> float:
        """The current multiplier (float)."""
        return float(self.multiplier.value)

    @property
    def lagrange_multiplier(self) -> torch.Tensor:
        return self.multiplier.get()

    def update(self, batch_or_mean_cost) -> float:
        """Dual update from a collected batch (``("next", cost_key)``) or a mean cost."""
        return self.multiplier.update(_mean_cost(batch_or_mean_cost, self.cost_key))

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        reward = next_tensordict.get(self.reward_key)
        cost = next_tensordict.get(self.cost_key)
        if self.raw_reward_key is not None:
            next_tensordict.set(self.raw_reward_key, reward)
        lam = self.multiplier.value.to(reward)
        next_tensordict.set(self.reward_key, reward - lam * cost)
        return next_tensordict

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Penalise a collected batch (reads ``("next", reward_key)`` if present)."""
        if "next" in tensordict.keys():
            self._call(tensordict.get("next"))
            return tensordict
        return self._call(tensordict)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        if self.raw_reward_key is not None:
            spec = self.parent.full_reward_spec[self.reward_key]
            tensordict_reset.set(self.raw_reward_key, spec.zero())
        return tensordict_reset

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        if self.raw_reward_key is not None:
            spec = self.parent.full_reward_spec[self.reward_key]
            observation_spec[self.raw_reward_key] = Unbounded(shape=spec.shape, dtype=spec.dtype, device=spec.device)
        return observation_spec

    def __repr__(self) -> str:
        return f"{type(self).__name__}(lambda={self.lam:.4g}, cost_key={self.cost_key!r})"
