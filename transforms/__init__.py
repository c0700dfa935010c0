"""TorchRL transforms of the mixed-traffic pipeline (one concern per file).

>>> from transforms import SafetyLayer, LagrangianPenalty, NonNegativeReward
"""

from transforms.barrier_force import BarrierForce
from transforms.blend import ControllerBlend
from transforms.committed_answer import CommittedAnswer
from transforms.conflict_cost import ConflictCost
from transforms.counterfactual_reward import CounterfactualReward
from transforms.deeplcc_history import DeePLCCHistory
from transforms.discretizer import StateDiscretizer
from transforms.drive_off import DriveOffCap
from transforms.intervention_cost import InterventionCost
from transforms.jerk_limit import JerkLimit
from transforms.jerk_penalty import JerkPenalty
from transforms.join import JoinBlend
from transforms.lagrangian import LagrangeMultiplier, LagrangianPenalty
from transforms.measurement_filter import MeasurementFilter
from transforms.onboard_accel import OnboardLeaderAccel
from transforms.residual import ResidualAction
from transforms.rewards import NonNegativeReward, ProfileNormalisedReward, QuadraticReward
from transforms.safety_layer import SafetyLayer
from transforms.sensor_noise import SensorNoise
from transforms.set_point import SetPointAction
from transforms.v2v_channel import V2VChannel

__all__ = [
    "SafetyLayer",
    "InterventionCost",
    "JerkPenalty",
    "JerkLimit",
    "LagrangeMultiplier",
    "LagrangianPenalty",
    "NonNegativeReward",
    "ProfileNormalisedReward",
    "QuadraticReward",
    "StateDiscretizer",
    "ResidualAction",
    "SetPointAction",
    "ControllerBlend",
    "DeePLCCHistory",
    "BarrierForce",
    "ConflictCost",
    "CounterfactualReward",
    "V2VChannel",
    "SensorNoise",
    "MeasurementFilter",
    "CommittedAnswer",
    "DriveOffCap",
    "JoinBlend",
    "OnboardLeaderAccel",
]
