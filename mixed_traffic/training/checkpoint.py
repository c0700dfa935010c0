"""Atomic checkpoints and the runtime state a bit-exact resume needs.

A checkpoint holds the learner (``model``), the optimiser, the Lagrange multiplier,
the counters, the RNG states (torch's global generator and the env's own) and the
environment's runtime state (the simulator tensors and the collector's carrier, so
episodes in flight continue where they were). Writing goes to a temporary file in
the same directory followed by ``os.replace``: a crash mid-write leaves the previous
checkpoint intact.
"""

from __future__ import annotations

import errno
import os
import shutil
from pathlib import Path

import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase, TransformedEnv

LATEST = "latest.pt"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_orphans(path: str | Path) -> list[Path]:
    """Remove ``.<name>.tmp<pid>`` files next to ``path`` left by a writer that no longer runs (a kill)."""
    path = Path(path)
    removed = []
    if not path.parent.is_dir():
        return removed
    for tmp in path.parent.glob(f".{path.name}.tmp*"):
        pid = tmp.name.rsplit(".tmp", 1)[-1]
        if pid.isdigit() and int(pid) != os.getpid() and _pid_alive(int(pid)):
            continue  # another live process is writing it
        try:
            tmp.unlink()
            removed.append(tmp)
        except FileNotFoundError:
            pass
    return removed


def atomic_save(obj, path: str | Path) -> Path:
    """``torch.save`` to a temporary file in the same directory, then ``os.replace``.

    The temporary is removed when the write fails (a full disk: ``OSError`` naming the
    file, the previous version untouched); one orphaned by a kill is removed by the next
    write of the same file.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_orphans(path)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        torch.save(obj, tmp)
        os.replace(tmp, path)
    except BaseException as e:
        tmp.unlink(missing_ok=True)
        if isinstance(e, OSError) and e.errno == errno.ENOSPC:
            raise OSError(errno.ENOSPC, f"no space left on the device while writing it "
                          f"({shutil.disk_usage(path.parent).free} bytes free; the previous version is intact, "
                          "the partial file was removed)", str(path)) from None
        raise
    return path


def atomic_write_text(path: str | Path, text: str) -> Path:
    """Text file written like :func:`atomic_save` (a reader never sees half a file)."""
    path = Path(path)
    remove_orphans(path)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
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


CKPT_ALLOWED = "a checkpoint written by mt-train (<run>/final.pt, <run>/checkpoints/latest.pt) or its run directory"


def resolve_checkpoint(path: str | Path, field: str = "resume") -> Path:
    """A checkpoint file, or a run directory (its ``checkpoints/latest.pt``)."""
    from mixed_traffic.validation import ConfigError

    p = Path(path).expanduser()
    if p.is_dir():
        for cand in (p / "checkpoints" / LATEST, p / LATEST):
            if cand.is_file():
                return cand
        if (p / "final.pt").is_file() and field == "resume":
            raise FileNotFoundError(f"{field}: the run in {str(path)!r} has finished (final.pt) and keeps no "
                                    f"checkpoints/{LATEST} to continue from; allowed: a run that stopped early, "
                                    "or a new run (evaluate this one with mt-eval checkpoint=...)")
        raise FileNotFoundError(f"{field}: no checkpoints/{LATEST} in the directory {str(path)!r}; allowed: {CKPT_ALLOWED}")
    if not p.is_file():
        raise FileNotFoundError(f"{field}: no such checkpoint file or run directory {str(path)!r}; allowed: {CKPT_ALLOWED}")
    if p.stat().st_size == 0:
        raise ConfigError(field, f"{str(p)!r} is empty (0 bytes)", CKPT_ALLOWED)
    return p


def load_checkpoint(path: str | Path, field: str = "resume") -> dict:
    """Load a checkpoint; a missing, empty, truncated or foreign file is a clear error naming it."""
    from mixed_traffic.validation import ConfigError

    p = resolve_checkpoint(path, field)
    try:
        state = torch.load(p, map_location="cpu", weights_only=False)
    except Exception as e:  # truncated zip, not a torch file, unpickling errors
        raise ConfigError(field, f"{str(p)!r} cannot be read as a checkpoint ({type(e).__name__}: "
                          f"{str(e).splitlines()[0] if str(e) else ''})", CKPT_ALLOWED) from None
    if not isinstance(state, dict) or "config" not in state or not isinstance(state["config"], dict):
        raise ConfigError(field, f"{str(p)!r} is not a mixed-traffic checkpoint (no run config inside)", CKPT_ALLOWED)
    return state
