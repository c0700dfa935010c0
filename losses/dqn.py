"""Double DQN over discretised accelerations, built from TorchRL parts only.

Everything here is TorchRL's: ``ActionDiscretizer`` (one-hot, ``categorical=False``;
the categorical form is a ``MultiCategorical`` that ``QValueModule`` rejects),
``QValueActor``, ``DQNLoss(double_dqn=True, delay_value=True)``, ``SoftUpdate``
and ``EGreedyModule``. :func:`make_dqn` only wires them for the car-following envs.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.envs import ActionDiscretizer, EnvBase, TransformedEnv
from torchrl.modules import MLP, EGreedyModule, QValueModule
from torchrl.objectives import DQNLoss, SoftUpdate


class _BoolAction(nn.Module):
    def forward(self, action):
        return action.bool()


@dataclass
class DQNParts:
    """What :func:`make_dqn` returns: drive ``loss(batch)``, then ``updater.step()`` after each optimiser step."""

    env: TransformedEnv
    qnet: TensorDictSequential
    policy: TensorDictSequential  # qnet + epsilon-greedy exploration (call ``exploration.step(n)``)
    exploration: EGreedyModule
    loss: DQNLoss
    updater: SoftUpdate


def make_dqn(env: EnvBase, num_bins: int = 21, *, num_cells: tuple[int, ...] = (128,), gamma: float = 0.99,
             tau: float = 0.01, double_dqn: bool = True, loss_function: str = "smooth_l1", eps_init: float = 1.0,
             eps_end: float = 0.1, annealing_num_steps: int = 500_000) -> DQNParts:
    """Discretise ``env``'s action into ``num_bins`` per CAV and build a Double DQN on it.

    The Q-network outputs ``n_cav * num_bins`` values (one head of ``num_bins`` per CAV,
    the ``MultiOneHot`` layout of ``ActionDiscretizer(categorical=False)``).

    Example:
        >>> from mixed_traffic import make_env
        >>> from losses import make_dqn
        >>> parts = make_dqn(make_env("ring", batch_size=4, seed=0), num_bins=21)
        >>> batch = parts.env.rollout(8, parts.policy)
        >>> out = parts.loss(batch.reshape(-1))
        >>> out["loss"].backward(); parts.updater.step()
        >>> batch["action"].shape
        torch.Size([4, 8, 21])
    """
    if not (isinstance(num_bins, int) and num_bins >= 2):
        raise ValueError(f"make_dqn: num_bins={num_bins!r} is invalid; allowed: an integer >= 2")
    if not 0 < tau <= 1:
        raise ValueError(f"make_dqn: tau={tau!r} is invalid; allowed: (0, 1]")
    with warnings.catch_warnings():  # a TransformedEnv input is unwrapped into one Compose, as intended
        warnings.filterwarnings("ignore", message="Nested TransformedEnvs are automatically unwrapped")
        denv = TransformedEnv(env, ActionDiscretizer(num_bins, categorical=False))
    spec = denv.action_spec_unbatched
    obs_dim = denv.observation_spec["observation"].shape[-1]
    n_out = spec.shape[-1]
    mlp = TensorDictModule(MLP(in_features=obs_dim, out_features=n_out, num_cells=list(num_cells),
                               activation_class=nn.ReLU), in_keys=["observation"], out_keys=["action_value"])
    qvalue = QValueModule(spec=spec, var_nums=num_bins, action_value_key="action_value")
    qnet = TensorDictSequential(mlp, qvalue, TensorDictModule(_BoolAction(), ["action"], ["action"]))
    exploration = EGreedyModule(spec=spec, eps_init=eps_init, eps_end=eps_end,
                                annealing_num_steps=annealing_num_steps)
    policy = TensorDictSequential(qnet, exploration, TensorDictModule(_BoolAction(), ["action"], ["action"]))
    loss = DQNLoss(qnet, double_dqn=double_dqn, delay_value=True, action_space=spec, loss_function=loss_function)
    loss.make_value_estimator(gamma=gamma)
    updater = SoftUpdate(loss, tau=tau)
    return DQNParts(env=denv, qnet=qnet, policy=policy, exploration=exploration, loss=loss, updater=updater)
