"""Lagrangian PPO: clipped PPO on a reward/cost-combined advantage.

TorchRL's :class:`~torchrl.objectives.ClipPPOLoss` does the clipped surrogate, the
entropy bonus and the (optionally clipped) reward critic; this subclass only adds
what it lacks: a cost critic, the combined advantage and the multiplier.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.utils import distance_loss
from torchrl.objectives.value import GAE

from transforms.lagrangian import LagrangeMultiplier, _mean_cost


class LagrangianPPOLoss(ClipPPOLoss):
    """Clipped PPO on ``A = (A_R - lambda A_C) / (1 + lambda)`` (or ``A_R - lambda A_C``).

    Two ways to use it:

    * *intersection style* (pass ``cost_critic_network``): the loss holds the
      multiplier, a cost critic (trained by ``loss_cost_critic``) and combines the
      reward advantage with the cost advantage. Call :meth:`update_lambda` once per
      collected batch.
    * *ring style* (``cost_critic_network=None``): the reward is already penalised by
      :class:`transforms.LagrangianPenalty`, so the loss is plain ``ClipPPOLoss``; pass
      ``multiplier=penalty.multiplier`` to log that multiplier with the losses.

    Advantages are read from the input (``"advantage"`` / ``"cost_advantage"``, e.g.
    from ``GAE(...)`` and a second ``GAE`` with ``set_keys(reward="cost", value="cost_value",
    advantage="cost_advantage", value_target="cost_value_target")``) or computed here
    with GAE when missing (``make_value_estimator(gamma=..., lmbda=...)`` sets both).

    Args:
        actor_network: the stochastic policy (as for ``ClipPPOLoss``).
        critic_network: reward critic writing ``"state_value"``.
        cost_critic_network: cost critic writing ``"cost_value"`` (or ``None``).
        lambda_init, lambda_lr, lambda_max, cost_limit, lambda_method: the multiplier,
            see :class:`transforms.LagrangeMultiplier` (defaults 1.0, 0.05, 10.0, 0.1,
            ``"dual_ascent"``; ``"adam"`` / ``"sgd"`` update lambda with that optimiser).
        multiplier: share an existing :class:`~transforms.LagrangeMultiplier` instead.
        normalize_lagrangian: divide the combined advantage by ``1 + lambda`` (default True).
        cost_critic_coeff: weight of ``loss_cost_critic`` (default 1.0).
        **kwargs: any ``ClipPPOLoss`` argument (``clip_epsilon``, ``entropy_coeff``,
            ``critic_coeff``, ``clip_value``, ``normalize_advantage``, ...).

    Output keys (besides ``ClipPPOLoss``'s): ``loss_cost_critic``,
    ``lagrange_multiplier``, ``cost_advantage_share`` (``lambda |A_C|`` over
    ``|A_R| + lambda |A_C|``, batch means: how much of the combined advantage comes from cost).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule, NormalParamExtractor
        >>> from torchrl.modules import ProbabilisticActor, TanhNormal, ValueOperator
        >>> from losses import LagrangianPPOLoss
        >>> net = torch.nn.Sequential(torch.nn.Linear(3, 2), NormalParamExtractor())
        >>> actor = ProbabilisticActor(TensorDictModule(net, ["observation"], ["loc", "scale"]),
        ...     in_keys=["loc", "scale"], distribution_class=TanhNormal, return_log_prob=True)
        >>> critic = ValueOperator(torch.nn.Linear(3, 1), in_keys=["observation"])
        >>> cost_critic = ValueOperator(torch.nn.Linear(3, 1), in_keys=["observation"], out_keys=["cost_value"])
        >>> loss = LagrangianPPOLoss(actor, critic, cost_critic, lambda_init=2.0)
        >>> td = actor(TensorDict({"observation": torch.randn(8, 3)}, [8]))
        >>> _ = td.update({"advantage": torch.randn(8, 1), "value_target": torch.randn(8, 1),
        ...            "cost_advantage": torch.randn(8, 1), "cost_value_target": torch.rand(8, 1)})
        >>> out = loss(td.detach())
        >>> sorted(k for k in out.keys() if k.startswith("loss_"))
        ['loss_cost_critic', 'loss_critic', 'loss_entropy', 'loss_objective']
        >>> float(out["lagrange_multiplier"])
        2.0
    """

    @dataclass
    class _AcceptedKeys(ClipPPOLoss._AcceptedKeys):
        """Keys of :class:`ClipPPOLoss` plus the cost ones.

        Attributes:
            cost: per-step cost (read under ``"next"``), default ``"cost"``.
            cost_value: cost critic output, default ``"cost_value"``.
            cost_advantage: default ``"cost_advantage"``.
            cost_value_target: default ``"cost_value_target"``.
        """

        cost: NestedKey = "cost"
        cost_value: NestedKey = "cost_value"
        cost_advantage: NestedKey = "cost_advantage"
        cost_value_target: NestedKey = "cost_value_target"

    default_keys = _AcceptedKeys

    def __init__(self, actor_network, critic_network=None, cost_critic_network: TensorDictModule | None = None, *,
                 lambda_init: float = 1.0, lambda_lr: float = 0.05, lambda_max: float = 10.0,
                 cost_limit: float = 0.1, lambda_method: str = "dual_ascent",
                 multiplier: LagrangeMultiplier | None = None, normalize_lagrangian: bool = True,
                 cost_critic_coeff: float = 1.0, **kwargs):
        if cost_critic_coeff < 0:
            raise ValueError(f"LagrangianPPOLoss: cost_critic_coeff={cost_critic_coeff!r} is invalid; allowed: >= 0")
        super().__init__(actor_network, critic_network, **kwargs)
        self.multiplier = multiplier if multiplier is not None else LagrangeMultiplier(
            init=lambda_init, lr=lambda_lr, max_value=lambda_max, cost_limit=cost_limit, method=lambda_method)
        self.cost_critic_network = cost_critic_network
        self.normalize_lagrangian = bool(normalize_lagrangian)
        self.cost_critic_coeff = float(cost_critic_coeff)
        self._cost_estimator = None
        self._cost_gae_kwargs = {"gamma": 0.99, "lmbda": 0.95}

    # ------------------------------------------------------------------ lambda
    @property
    def lagrange_multiplier(self) -> torch.Tensor:
        return self.multiplier.get()

    def update_lambda(self, batch_or_mean_cost) -> float:
        """One multiplier update from a collected batch (mean of ``("next", cost)``) or a mean cost."""
        return self.multiplier.update(_mean_cost(batch_or_mean_cost, self.tensor_keys.cost))

    # ------------------------------------------------------------- estimators
    def make_value_estimator(self, value_type=None, **hyperparams):
        """Builds the reward estimator (``ClipPPOLoss``) and a GAE on the cost with the same gamma / lmbda."""
        out = super().make_value_estimator(value_type, **hyperparams)
        for k in ("gamma", "lmbda"):
            if k in hyperparams:
                self._cost_gae_kwargs[k] = float(hyperparams[k])
        self._cost_estimator = None
        return out

    @property
    def cost_value_estimator(self) -> GAE:
        if self._cost_estimator is None:
            if self.cost_critic_network is None:
                raise RuntimeError("LagrangianPPOLoss: no cost critic; pass `cost_advantage` in the input")
            est = GAE(value_network=self.cost_critic_network, **self._cost_gae_kwargs)
            k = self.tensor_keys
            est.set_keys(reward=k.cost, value=k.cost_value, advantage=k.cost_advantage,
                         value_target=k.cost_value_target, done=k.done, terminated=k.terminated)
            self.__dict__["_cost_estimator"] = est
        return self._cost_estimator

    # ------------------------------------------------------------------ forward
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        lam = self.lagrange_multiplier
        if self.cost_critic_network is None:
            out = super().forward(tensordict)
            out.set("lagrange_multiplier", lam.clone())
            return out
        k = self.tensor_keys
        td = tensordict.clone(False)
        adv_r = td.get(k.advantage, None)
        if adv_r is None:
            self.value_estimator(td, params=self._cached_critic_network_params_detached,
                                 target_params=self.target_critic_network_params)
            adv_r = td.get(k.advantage)
        adv_c = td.get(k.cost_advantage, None)
        if adv_c is None:
            with torch.no_grad():
                self.cost_value_estimator(td)
            adv_c = td.get(k.cost_advantage)
        adv_c = adv_c.to(adv_r.dtype)
        lam_t = lam.to(adv_r)
        combined = adv_r - lam_t * adv_c
        if self.normalize_lagrangian:
            combined = combined / (1.0 + lam_t)
        td.set(k.advantage, combined)
        out = super().forward(td)
        if self.cost_critic_coeff > 0:
            out.set("loss_cost_critic", self.loss_cost_critic(td))
        with torch.no_grad():
            a_r = adv_r.abs().mean()
            a_c = lam_t * adv_c.abs().mean()
            out.set("cost_advantage_share", a_c / (a_r + a_c).clamp_min(1e-12))
        out.set("lagrange_multiplier", lam.clone())
        return out

    def loss_cost_critic(self, tensordict: TensorDictBase) -> torch.Tensor:
        """``cost_critic_coeff * distance(cost_value, cost_value_target)`` (``loss_critic_type``)."""
        k = self.tensor_keys
        target = tensordict.get(k.cost_value_target).detach()
        inp = tensordict.select(*self.cost_critic_network.in_keys, strict=False).clone(False)
        pred = self.cost_critic_network(inp).get(k.cost_value)
        loss = distance_loss(pred, target.to(pred.dtype), loss_function=self.loss_critic_type)
        return self.cost_critic_coeff * loss.mean()

    @property
    def out_keys(self):
        if self._out_keys is None:
            keys = list(super().out_keys)
            if self.cost_critic_network is not None:
                keys += ["loss_cost_critic", "cost_advantage_share"]
            self._out_keys = keys + ["lagrange_multiplier"]
        return self._out_keys

    @out_keys.setter
    def out_keys(self, values):
        self._out_keys = values


__all__ = ["LagrangianPPOLoss"]
