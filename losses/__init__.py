"""TorchRL LossModules of the mixed-traffic pipeline.

PPO is TorchRL's ``ClipPPOLoss`` (re-exported, not rewritten); DQN is TorchRL's
``DQNLoss`` wired by :func:`make_dqn`. The rest add what TorchRL lacks.

>>> from losses import ClipPPOLoss, LagrangianPPOLoss, BCLoss, ResidualMPCLoss, TabularQLearning, make_dqn
"""

from torchrl.objectives import ClipPPOLoss, DQNLoss, SoftUpdate

from losses.bc import BCLoss
from losses.dqn import DQNParts, make_dqn
from losses.lagrangian_ppo import LagrangianPPOLoss
from losses.qlearning import EpsilonGreedyTablePolicy, QTable, TabularQLearning, action_levels
from losses.residual import ResidualMPCLoss
from transforms.lagrangian import LagrangeMultiplier

__all__ = [
    "ClipPPOLoss",
    "DQNLoss",
    "SoftUpdate",
    "LagrangianPPOLoss",
    "LagrangeMultiplier",
    "BCLoss",
    "ResidualMPCLoss",
    "TabularQLearning",
    "QTable",
    "EpsilonGreedyTablePolicy",
    "action_levels",
    "make_dqn",
    "DQNParts",
]
