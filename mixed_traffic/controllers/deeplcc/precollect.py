"""Pre-collection: persistently exciting trajectories -> Hankel data.

CAV accelerations ``u ~ U[-u_amp, u_amp]`` and head speed deviations
``e ~ U[-e_amp, e_amp]`` are drawn i.i.d. every step for ``T`` steps while the
human drivers follow their model with small noise; outputs are measured with
measurement type 3. Trajectories are rounded to float32 so that Hankel data
stored in float32 reproduce the same QPs exactly.

>>> import torch
>>> from mixed_traffic.controllers.deeplcc.platoon import PlatoonConfig
>>> [h] = precollect(PlatoonConfig(), T=200, t_ini=5, n=10, generator=torch.Generator().manual_seed(0))
>>> h.Up.shape, h.Yp.shape
((10, 186), (50, 186))
"""

from __future__ import annotations

import numpy as np
import torch

from mixed_traffic.controllers.deeplcc.hankel import HankelData, build_hankel
from mixed_traffic.controllers.deeplcc.platoon import DTYPE, PlatoonConfig, init_state, measure, step


def collect_trajectories(cfg: PlatoonConfig, T: int, batch: int = 1, u_amp: float = 1.0, e_amp: float = 1.0,
                         generator: torch.Generator | None = None,
                         simulator=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Simulate ``batch`` excitation runs of ``T`` steps -> ``ud (B, m, T)``, ``ed (B, 1, T)``, ``yd (B, p, T)``.

    ``simulator``: ``None`` (the torch platoon, :func:`.platoon.step`) or a started-on-demand
    :class:`mixed_traffic.envs.sumo_platoon.SumoPlatoon` (batch 1): the data then come from SUMO.
    """
    if T < 2:
        raise ValueError(f"collect_trajectories: T={T} is invalid; allowed: >= 2")
    if simulator is not None and batch != 1:
        raise ValueError(f"collect_trajectories: batch={batch} is invalid with a simulator; allowed: 1")
    ud = (2.0 * torch.rand(batch, cfg.m, T, dtype=DTYPE, generator=generator) - 1.0) * u_amp
    ed = (2.0 * torch.rand(batch, 1, T, dtype=DTYPE, generator=generator) - 1.0) * e_amp
    ud, ed = ud.float().double(), ed.float().double()
    if simulator is None:
        pos, vel = init_state(batch, cfg)
        vel[:, 0] = cfg.v_star + ed[:, 0, 0]
    else:
        pos, vel = simulator.start(cfg.v_star, cfg.v_star + float(ed[0, 0, 0]))
    yd = torch.empty(batch, cfg.p, T, dtype=DTYPE)
    for t in range(T):
        yd[:, :, t] = measure(pos, vel, cfg)
        if t + 1 < T:
            if simulator is None:
                pos, vel, executed = step(pos, vel, ud[:, :, t], cfg.v_star + ed[:, 0, t + 1], cfg, generator)
            else:
                pos, vel, executed = simulator.step(ud[:, :, t], cfg.v_star + ed[:, 0, t + 1])
            ud[:, :, t] = executed.float().double()  # the emergency rule may override the excitation
    return ud.numpy(), ed.numpy(), yd.float().double().numpy()


def precollect(cfg: PlatoonConfig, T: int = 2000, t_ini: int = 20, n: int = 50, batch: int = 1,
               u_amp: float = 1.0, e_amp: float = 1.0, generator: torch.Generator | None = None,
               simulator=None) -> list[HankelData]:
    """``batch`` independent Hankel data sets (one per episode); ``simulator``: see :func:`collect_trajectories`."""
    if T < t_ini + n + 1:
        raise ValueError(f"precollect: T={T} is invalid; allowed: >= t_ini + n + 1 ({t_ini + n + 1})")
    ud, ed, yd = collect_trajectories(cfg, T, batch, u_amp, e_amp, generator, simulator)
    return [build_hankel(ud[b], ed[b], yd[b], t_ini, n) for b in range(batch)]
