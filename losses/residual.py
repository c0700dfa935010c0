"""PPO on the residual of a base controller, with a penalty on the residual's size."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.objectives import ClipPPOLoss


class ResidualMPCLoss(ClipPPOLoss):
    """``ClipPPOLoss`` plus ``loss_residual = residual_coeff * mean(a_res_det^2)``.

    Use with :class:`transforms.ResidualAction`: the policy outputs the residual
    ``a_res`` (stored as ``"action"``) and the env runs ``clip(a_base + w a_res)``. The
    penalty acts on the policy's deterministic residual (the mean of its distribution),
    pulling the policy towards the base controller (zero residual) unless the reward
    says otherwise.

    Args:
        actor_network, critic_network: as for ``ClipPPOLoss``.
        residual_coeff: weight of the size penalty (>= 0, default 0.01).
        **kwargs: any ``ClipPPOLoss`` argument.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule, NormalParamExtractor
        >>> from torchrl.modules import ProbabilisticActor, TanhNormal, ValueOperator
        >>> from losses import ResidualMPCLoss
        >>> net = torch.nn.Sequential(torch.nn.Linear(3, 2), NormalParamExtractor())
        >>> actor = ProbabilisticActor(TensorDictModule(net, ["observation"], ["loc", "scale"]),
        ...     in_keys=["loc", "scale"], distribution_class=TanhNormal, return_log_prob=True)
        >>> critic = ValueOperator(torch.nn.Linear(3, 1), in_keys=["observation"])
        >>> loss = ResidualMPCLoss(actor, critic, residual_coeff=0.1)
        >>> td = actor(TensorDict({"observation": torch.randn(8, 3)}, [8]))
        >>> _ = td.update({"advantage": torch.randn(8, 1), "value_target": torch.randn(8, 1)})
        >>> "loss_residual" in loss(td.detach()).keys()
        True
    """

    def __init__(self, actor_network, critic_network=None, *, residual_coeff: float = 0.01, **kwargs):
        if not residual_coeff >= 0:
            raise ValueError(f"ResidualMPCLoss: residual_coeff={residual_coeff!r} is invalid; allowed: >= 0")
        super().__init__(actor_network, critic_network, **kwargs)
        self.register_buffer("residual_coeff", torch.tensor(float(residual_coeff)))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        out = super().forward(tensordict)
        _, dist, _ = self._get_cur_log_prob(tensordict.clone(False))
        residual = dist.deterministic_sample
        size = residual.pow(2).mean()
        out.set("loss_residual", self.residual_coeff * size)
        out.set("residual_rms", size.detach().sqrt())
        return out

    @property
    def out_keys(self):
        if self._out_keys is None:
            self._out_keys = list(super().out_keys) + ["loss_residual", "residual_rms"]
        return self._out_keys

    @out_keys.setter
    def out_keys(self, values):
        self._out_keys = values
