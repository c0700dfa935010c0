"""Behaviour cloning as a mean-squared error on the policy's deterministic action.

TorchRL's own ``torchrl.objectives.BCLoss`` does not fit this project: it maximises
the log-likelihood of the expert action under the policy's distribution. For a
``TanhNormal`` policy that log-likelihood is undefined at the action bounds (where
expert controllers often sit, e.g. braking at ``a_min``) and it also trains the scale,
while LPPO + BC regularises the *mean* action towards the expert; and a deterministic
network (the NNMPC imitating an MPC) has no distribution at all. Here the loss is
``coeff * mean((a_det(s) - a_expert)^2)`` where ``a_det`` is the distribution's
deterministic sample (``tanh`` of the location, rescaled to the bounds, for a
``TanhNormal``) or the output of a deterministic module.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.objectives import LossModule


class BCLoss(LossModule):
    """``loss_bc = coeff * MSE(deterministic action, expert action)``.

    Composes with :class:`~torchrl.objectives.ClipPPOLoss` / :class:`LagrangianPPOLoss`
    by summing the ``loss_*`` entries of both outputs (the actor is the same module,
    so its parameters receive both gradients); ``coeff`` sets the BC weight. Alone it
    trains any network by regression (e.g. an NNMPC on MPC actions).

    Args:
        actor: a probabilistic actor (anything with ``get_dist``) or a deterministic
            ``TensorDictModule`` writing ``action``.
        expert_action_key: where the expert's action is stored (default ``"expert_action"``).
        coeff: weight of the loss (>= 0, default 1.0).
        action_key: the output key of a deterministic actor (default ``"action"``).
        mask_key: optional boolean entry selecting the samples that have a valid expert action.

    Keys (``set_keys``): ``expert_action``, ``action``, ``mask``.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> from losses import BCLoss
        >>> net = TensorDictModule(torch.nn.Linear(3, 1), ["observation"], ["action"])
        >>> loss = BCLoss(net, expert_action_key="expert_action")
        >>> td = TensorDict({"observation": torch.randn(16, 3), "expert_action": torch.randn(16, 1)}, [16])
        >>> out = loss(td)
        >>> out["loss_bc"].backward()
        >>> net.module.weight.grad is not None
        True
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable keys.

        Attributes:
            expert_action: the expert's action, default ``"expert_action"``.
            action: output of a deterministic actor, default ``"action"``.
            mask: optional validity mask, default ``None`` (all samples used).
        """

        expert_action: NestedKey = "expert_action"
        action: NestedKey = "action"
        mask: NestedKey | None = None

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys

    def __init__(self, actor: TensorDictModuleBase, expert_action_key: NestedKey = "expert_action", *,
                 coeff: float = 1.0, action_key: NestedKey = "action", mask_key: NestedKey | None = None):
        if not coeff >= 0:
            raise ValueError(f"BCLoss: coeff={coeff!r} is invalid; allowed: >= 0")
        super().__init__()
        self.actor = actor
        self.register_buffer("coeff", torch.tensor(float(coeff)))
        self.set_keys(expert_action=expert_action_key, action=action_key, mask=mask_key)

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    @property
    def in_keys(self):
        keys = list(getattr(self.actor, "in_keys", [])) + [self.tensor_keys.expert_action]
        if self.tensor_keys.mask is not None:
            keys.append(self.tensor_keys.mask)
        return keys

    @property
    def out_keys(self):
        return ["loss_bc", "bc_mse"]

    def deterministic_action(self, tensordict: TensorDictBase) -> torch.Tensor:
        """The actor's deterministic action (differentiable)."""
        td = tensordict.clone(False)
        if hasattr(self.actor, "get_dist"):
            dist = self.actor.get_dist(td)
            try:
                return dist.deterministic_sample
            except (AttributeError, NotImplementedError):
                return dist.mean
        return self.actor(td).get(self.tensor_keys.action)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        pred = self.deterministic_action(tensordict)
        expert = tensordict.get(self.tensor_keys.expert_action).to(pred.dtype).detach()
        err = (pred - expert.reshape(pred.shape)).pow(2)
        if self.tensor_keys.mask is not None:
            mask = tensordict.get(self.tensor_keys.mask).to(pred.dtype)
            while mask.ndim < err.ndim:
                mask = mask.unsqueeze(-1)
            mask = mask.expand_as(err)
            mse = (err * mask).sum() / mask.sum().clamp_min(1.0)
        else:
            mse = err.mean()
        return TensorDict({"loss_bc": self.coeff * mse, "bc_mse": mse.detach()}, [])
