"""DeeP-LCC as a TorchRL policy: a TensorDictModule reading ``uini``/``yini``/``eini``, writing ``action``.

The window keys come from :class:`transforms.deeplcc_history.DeePLCCHistory` (or any
producer of the same layout). Each batch row keeps its own warm-start active set.

>>> import torch
>>> from torchrl.envs import TransformedEnv
>>> from mixed_traffic import make_env
>>> from transforms.deeplcc_history import DeePLCCHistory
>>> from mixed_traffic.controllers.deeplcc.platoon import PlatoonConfig
>>> from mixed_traffic.controllers.deeplcc.precollect import precollect
>>> [h] = precollect(PlatoonConfig(), T=600, generator=torch.Generator().manual_seed(0))
>>> policy = deeplcc_policy(DeepLCCSolver(h, QPParams.preset("dataset")))
>>> env = TransformedEnv(make_env("deeplcc", batch_size=2, seed=0), DeePLCCHistory())
>>> env.rollout(3, policy)["action"].shape
torch.Size([2, 3, 2])
"""

from __future__ import annotations

import numpy as np
import torch
from tensordict.nn import TensorDictModule

from mixed_traffic.controllers.deeplcc.qp import DeepLCCSolver, QPParams

WINDOW_KEYS = ["uini", "yini", "eini"]


class QPPolicyNet(torch.nn.Module):
    """``forward(uini, yini, eini) -> action``: the exact QP, one row at a time.

    ``solvers`` is one :class:`DeepLCCSolver` shared by every row or a list with
    one per row. ``statuses`` counts the solve outcomes (optimal / dual_fallback /
    safe_action / invalid_input) so a fallback is never silent.
    """

    def __init__(self, solvers):
        super().__init__()
        self.solvers = solvers if isinstance(solvers, (list, tuple)) else [solvers]
        self._warm: dict[int, tuple] = {}
        self.statuses: dict[str, int] = {}

    def reset(self) -> None:
        self._warm.clear()

    def forward(self, uini: torch.Tensor, yini: torch.Tensor, eini: torch.Tensor) -> torch.Tensor:
        shape = uini.shape[:-1]
        u2, y2, e2 = (x.reshape(-1, x.shape[-1]).detach().cpu().double().numpy() for x in (uini, yini, eini))
        out = np.empty((u2.shape[0], self.solvers[0].m))
        for b in range(u2.shape[0]):
            s = self.solvers[b % len(self.solvers)]
            res = s.solve(u2[b], y2[b], e2[b], warm=self._warm.get(b, ()))
            self._warm[b] = res.active
            self.statuses[res.status] = self.statuses.get(res.status, 0) + 1
            out[b] = res.u
        return torch.as_tensor(out, dtype=uini.dtype, device=uini.device).reshape(*shape, -1)


def deeplcc_policy(solvers) -> TensorDictModule:
    """The exact DeeP-LCC QP as a policy module (``uini, yini, eini -> action``)."""
    return TensorDictModule(QPPolicyNet(solvers), in_keys=list(WINDOW_KEYS), out_keys=["action"])


__all__ = ["QPPolicyNet", "deeplcc_policy", "DeepLCCSolver", "QPParams", "WINDOW_KEYS"]
