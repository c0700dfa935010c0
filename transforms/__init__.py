"""TorchRL transforms of the mixed-traffic pipeline (one concern per file).

>>> from transforms import SafetyLayer, LagrangianPenalty, NonNegativeReward
"""

from transforms.discretizer import StateDiscretizer
from transforms.lagrangian import LagrangeMultiplier, LagrangianPenalty
from transforms.residual import ResidualAction
from transforms.rewards import NonNegativeReward, QuadraticReward
from transforms.safety_layer import SafetyLayer

__all__ = [
    "SafetyLayer",
    "LagrangeMultiplier",
    "LagrangianPenalty",
    "NonNegativeReward",
    "QuadraticReward",
    "StateDiscretizer",
    "ResidualAction",
]

# transforms owned by other modules of the project: optional, so a missing file
# does not break the package
try:
    from transforms.deeplcc_history import DeePLCCHistory  # noqa: F401

    __all__.append("DeePLCCHistory")
except ImportError:  # pragma: no cover
    pass
try:
    from transforms.barrier_force import BarrierForce  # noqa: F401

    __all__.append("BarrierForce")
except ImportError:  # pragma: no cover
    pass
