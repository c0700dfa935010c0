"""Atomic checkpoints and the runtime state a bit-exact resume needs.

A checkpoint holds the learner (``model``), the optimiser, the Lagrange multiplier,
the counters, the RNG states (torch's global generator and the env's own) and the
environment's runtime state (the simulator tensors and the collector's carrier, so
episodes in flight continue where they were). Writing goes to a temporary file in
the same directory followed by ``os.replace``: a crash mid-write leaves the previous
checkpoint intact.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase, TransformedEnv

LATEST = "latest.pt"


def atomic_save(obj, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    torch.save(obj, tmp)
    os.replace(tmp, path)
    return path


def _base(env: EnvBase) -> EnvBase:
    while isinstance(env, TransformedEnv):
        env = env.base_env
    return env


def env_runtime_state(env: EnvBase) -> dict:
    """Tensors, dicts of tensors and generators held as attributes of the base env."""
    base = _base(env)
    out = {}
    for k, v in vars(base).items():
        if k.startswith("_modules") or k in ("_parameters", "_buffers"):
            continue
        if isinstance(v, torch.Tensor):
            out[k] = v.clone()
        elif isinstance(v, torch.Generator):
            out[k] = ("generator", v.get_state())
        elif isinstance(v, dict) and v and all(isinstance(t, torch.Tensor) for t in v.values()):
            out[k] = {kk: t.clone() for kk, t in v.items()}
    return out


def load_env_runtime_state(env: EnvBase, state: dict) -> None:
    base = _base(env)
    for k, v in state.items():
        if isinstance(v, tuple) and v and v[0] == "generator":
            getattr(base, k).set_state(v[1])
        else:
            setattr(base, k, v)


def rng_state() -> dict:
    return {"torch": torch.get_rng_state()}


def load_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])


def collector_state(collector) -> dict:
    carrier: TensorDictBase = collector._carrier
    return {"carrier": carrier.clone(), "state_dict": collector.state_dict()}


def load_collector_state(collector, state: dict) -> None:
    collector.load_state_dict(state["state_dict"])
    collector._carrier = state["carrier"].clone()


def resolve_checkpoint(path: str | Path) -> Path:
    """A checkpoint file, or a run directory (its ``checkpoints/latest.pt``)."""
    p = Path(path).expanduser()
    if p.is_dir():
        for cand in (p / "checkpoints" / LATEST, p / LATEST):
            if cand.is_file():
                return cand
        raise FileNotFoundError(f"resume={str(path)!r}: no checkpoints/{LATEST} in that directory")
    if not p.is_file():
        raise FileNotFoundError(f"resume={str(path)!r}: no such checkpoint file or run directory")
    return p


def load_checkpoint(path: str | Path) -> dict:
    return torch.load(resolve_checkpoint(path), map_location="cpu", weights_only=False)
