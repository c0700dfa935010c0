"""DeeP-LCC: data-driven predictive control of CAVs, its (state, solution) dataset and the NNMPC surrogate.

>>> from mixed_traffic.controllers.deeplcc import DeepLCCSolver, QPParams, precollect, PlatoonConfig
>>> QPParams.preset("reference").lambda_y
10000.0

See ``docs/deeplcc.md`` for the formulation, commands and measured figures.
"""

from mixed_traffic.controllers.deeplcc.closed_loop import EVAL_SCENARIOS, QPController, evaluate, run_closed_loop
from mixed_traffic.controllers.deeplcc.controller import QPPolicyNet, deeplcc_policy
from mixed_traffic.controllers.deeplcc.dataset import DatasetConfig, generate_dataset, load_dataset, write_dataset
from mixed_traffic.controllers.deeplcc.hankel import HankelData, build_hankel, hankel_matrix
from mixed_traffic.controllers.deeplcc.nnmpc import NNMPC, TrainConfig, nnmpc_policy, qp_gain, train_nnmpc
from mixed_traffic.controllers.deeplcc.platoon import PlatoonConfig
from mixed_traffic.controllers.deeplcc.precollect import precollect
from mixed_traffic.controllers.deeplcc.qp import DeepLCCSolver, QPParams, build_qp, solve_cvxopt

__all__ = [
    "EVAL_SCENARIOS", "QPController", "evaluate", "run_closed_loop", "QPPolicyNet", "deeplcc_policy",
    "DatasetConfig", "generate_dataset", "load_dataset", "write_dataset", "HankelData", "build_hankel",
    "hankel_matrix", "NNMPC", "TrainConfig", "nnmpc_policy", "qp_gain", "train_nnmpc", "PlatoonConfig",
    "precollect", "DeepLCCSolver", "QPParams", "build_qp", "solve_cvxopt",
]
