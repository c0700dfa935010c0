"""Environment factory: one entry point for every scenario and backend."""

from __future__ import annotations

import torch
from torchrl.envs import EnvBase

from mixed_traffic.scenarios import PRESETS

SCENARIOS = sorted(PRESETS) + ["intersection", "platoon"]
BACKENDS = ("torch", "sumo")


def make_env(scenario: str, *, backend: str = "torch", batch_size: int = 1, seed: int | None = None,
             device: str | torch.device = "cpu", **overrides) -> EnvBase:
    """Build a TorchRL environment.

    Args:
        scenario: ``"ring"``, ``"deeplcc"``, ``"ring_wave"``, ``"intersection"`` or ``"platoon"``
            (the DeeP-LCC platoon on the physics of the DeeP-LCC closed loop, :mod:`.platoon`).
        backend: ``"torch"`` (batched pure-torch simulator) or ``"sumo"`` (ring, ring_wave and platoon,
            one libsumo simulation per process; batch through ``ParallelEnv``).
        batch_size: number of independent scenarios stepped together (torch backend).
        seed: seeds the environment's own generator (profiles, initial states).
        **overrides: any field of the scenario (see :mod:`mixed_traffic.scenarios`).

    >>> from mixed_traffic import make_env
    >>> env = make_env("ring", batch_size=8, seed=0)
    >>> env.rollout(3).shape
    torch.Size([8, 3])
    """
    if scenario not in SCENARIOS:
        raise ValueError(f"scenario: unknown {scenario!r}; allowed: {SCENARIOS}")
    if backend not in BACKENDS:
        raise ValueError(f"backend: unknown {backend!r}; allowed: {list(BACKENDS)}")
    if not (isinstance(batch_size, int) and not isinstance(batch_size, bool) and batch_size >= 1):
        raise ValueError(f"batch_size: {batch_size!r} is invalid; allowed: an integer >= 1")
    if seed is not None and not (isinstance(seed, int) and not isinstance(seed, bool) and 0 <= seed < 2**63):
        raise ValueError(f"seed: {seed!r} is invalid; allowed: an integer in [0, 2**63) or None")
    if scenario == "intersection":
        if backend != "torch":
            raise ValueError("backend: the intersection scenario has only the 'torch' backend")
        from mixed_traffic.envs.intersection import IntersectionEnv

        env = IntersectionEnv(batch_size=batch_size, device=device, **overrides)
    elif scenario == "platoon":
        if backend == "sumo":
            from mixed_traffic.envs.sumo_platoon import SumoPlatoonEnv

            env = SumoPlatoonEnv(batch_size=batch_size, device=device, **overrides)
        else:
            from mixed_traffic.envs.platoon import PlatoonEnv

            env = PlatoonEnv(batch_size=batch_size, device=device, **overrides)
    elif backend == "sumo":
        if scenario not in ("ring", "ring_wave"):
            raise ValueError(f"backend 'sumo' supports scenarios 'ring', 'ring_wave' and 'platoon' only, "
                             f"got {scenario!r}")
        if batch_size != 1:
            raise ValueError("batch_size: the SUMO backend runs one simulation per process (batch_size=1); "
                             "batch it with torchrl.envs.ParallelEnv")
        from mixed_traffic.envs.sumo_ring import SumoRingEnv

        env = SumoRingEnv(scenario, device=device, **overrides)
    else:
        from mixed_traffic.envs.traffic import TrafficEnv

        env = TrafficEnv(scenario, batch_size=batch_size, device=device, **overrides)
    if seed is not None:
        env.set_seed(seed)
    return env


__all__ = ["make_env", "SCENARIOS", "BACKENDS"]
