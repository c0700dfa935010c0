"""Small spec and entry helpers shared by the transforms."""

from __future__ import annotations

import torch
from tensordict.utils import NestedKey
from torchrl.data import Bounded, Composite, Unbounded


def action_range(env) -> float:
    """Width ``high - low`` of the bounds of ``env``'s ``"action"`` (first element), in m/s^2.

    Transforms that normalise by the action range (``InterventionCost``, ``JerkPenalty``) read it
    from their parent env the first time it is needed.
    """
    spec = env.full_action_spec["action"]
    return float((spec.space.high - spec.space.low).flatten()[0])


def entries_or_none(transform, tensordict, *keys):
    """``[tensordict[k] for k in keys]`` for an action transform's inverse step; ``None`` when one is missing and
    the transform tolerates it (``missing_tolerance``, as TorchRL's ``Transform`` sets it), else ``KeyError``
    naming the transform and the keys."""
    values = [tensordict.get(k, None) for k in keys]
    if all(v is not None for v in values):
        return values
    if transform.missing_tolerance:
        return None
    raise KeyError(f"{type(transform).__name__}: {' or '.join(repr(k) for k in keys)} not found in the input tensordict")


def parent_dt(parent, owner: str) -> float:
    """The control step ``dt`` (s) of a transform's parent env (TransformedEnv forwards the base env's ``dt``);
    ``owner`` names the transform in the error when the env has none."""
    dt = getattr(parent, "dt", None) if parent is not None else None
    if dt is None:
        raise ValueError(f"{owner}: dt=None but the parent env has no `dt`; pass dt explicitly (> 0)")
    return float(dt)


def with_bounded_action(action_spec, key, low: float, high: float):
    """``action_spec`` (a ``Composite`` or a leaf) with the entry ``key`` replaced by ``Bounded(low, high)``
    of the same shape: the action a policy outputs when a transform maps it to the env's command."""
    spec = action_spec[key] if isinstance(action_spec, Composite) else action_spec
    new = Bounded(low=torch.full(spec.shape, float(low), dtype=spec.dtype, device=spec.device),
                  high=torch.full(spec.shape, float(high), dtype=spec.dtype, device=spec.device),
                  shape=spec.shape, dtype=spec.dtype, device=spec.device)
    if isinstance(action_spec, Composite):
        action_spec[key] = new
        return action_spec
    return new


def with_action_shaped_entry(observation_spec, parent, action_key, key):
    """``observation_spec`` with an ``Unbounded`` entry ``key`` shaped like the parent's action (a logged command)."""
    spec = parent.full_action_spec[action_key]
    observation_spec[key] = Unbounded(shape=spec.shape, dtype=spec.dtype, device=spec.device)
    return observation_spec


def action_shaped_full(parent, action_key, value, dtype=None) -> torch.Tensor:
    """A tensor shaped like the parent's action filled with ``value`` (a logged entry's reset value)."""
    spec = parent.full_action_spec[action_key]
    return torch.full(spec.shape, value, dtype=dtype or spec.dtype, device=spec.device)


def carry_to_next(tensordict, next_tensordict, *keys):
    """``next_tensordict`` with the entries ``keys`` that ``_inv_call`` wrote on the step's input
    (a transform's log of the command it executed), so they reach the rollout; absent ones are skipped."""
    for key in keys:
        val = tensordict.get(key, None)
        if val is not None:
            next_tensordict.set(key, val)
    return next_tensordict


def state_entries(owner: str, tensordict, what: str, *keys) -> list:
    """``[tensordict[k] for k in keys]``, a transform's state entries on the step's input; ``RuntimeError`` naming
    ``owner`` and its ``what`` state when one is missing (the env was stepped before a reset through the
    ``TransformedEnv``)."""
    values = [tensordict.get(k, None) for k in keys]
    if any(v is None for v in values):
        raise RuntimeError(f"{owner}: the step's input has no {what} state; reset the env through the TransformedEnv "
                           "before stepping it")
    return values


def kept_rows(tensordict, like: torch.Tensor, state_key) -> torch.Tensor | None:
    """Where a reset keeps a transform's state: ``True`` on the rows a partial reset (``"_reset"`` in
    ``tensordict``) leaves alone, broadcast to ``like``'s shape; None when every row starts afresh (a full reset,
    or no state ``state_key`` from before to keep)."""
    if tensordict is None:
        return None
    mask = tensordict.get("_reset", None)
    if mask is None or tensordict.get(state_key, None) is None:
        return None
    nb = len(tensordict.batch_size)
    return (~mask.reshape(*mask.shape[:nb], *([1] * (like.dim() - nb)))).expand_as(like)


def reset_state(tensordict, tensordict_reset, fresh: dict):
    """Sets a transform's state entries ``fresh`` (``{key: value at a fresh start}``) in ``tensordict_reset``, keeping
    the old value on the rows a partial reset leaves alone (:func:`kept_rows`); returns ``tensordict_reset``."""
    for key, value in fresh.items():
        keep = kept_rows(tensordict, value, key)
        if keep is not None:
            value = torch.where(keep, tensordict.get(key).to(value), value)
        tensordict_reset.set(key, value)
    return tensordict_reset


def with_state_spec(observation_spec: Composite, group: str, like: NestedKey, **dtypes) -> Composite:
    """Adds a transform's per-row state entries to ``observation_spec``: ``group`` holds one unbounded leaf per name
    of ``dtypes`` (``{name: dtype}``; None: the dtype of ``like``), each shaped as the entry ``like``; returns the
    spec."""
    leaf = observation_spec[like]
    observation_spec[group] = Composite(
        **{name: Unbounded(shape=leaf.shape, dtype=leaf.dtype if dtype is None else dtype, device=leaf.device)
           for name, dtype in dtypes.items()},
        shape=observation_spec.shape, device=observation_spec.device)
    return observation_spec


def profile_table(owner: str, field: str, values: dict, kinds) -> torch.Tensor:
    """One value per profile name of ``kinds`` (NaN where ``values`` has none), validated: a non-empty
    mapping from names in ``kinds`` to values > 0; ``owner`` and ``field`` name it in the error."""
    kinds = list(kinds)
    bad = {k: v for k, v in dict(values).items() if k not in kinds or not float(v) > 0}
    if not values or bad:
        raise ValueError(f"{owner}: {field}={dict(values)!r} is invalid; allowed: a non-empty mapping from profile "
                         f"names in {kinds} to values > 0 (bad: {bad})")
    return torch.tensor([float(values.get(k, float("nan"))) for k in kinds], dtype=torch.float32)


def per_row(table, kind, kinds, owner: str, field: str):
    """``table[kind]`` for a per-row profile index ``kind``; a profile without a value fails naming it."""
    kind = kind.long().cpu()
    out = table[kind]
    if torch.isnan(out).any():
        missing = sorted({list(kinds)[int(k)] for k in kind[torch.isnan(out)].flatten().tolist()})
        raise ValueError(f"{owner}: no {field} for profile(s) {missing}")
    return out
