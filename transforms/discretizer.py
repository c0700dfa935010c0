"""State discretiser for tabular Q-learning.

TorchRL discretises actions (``ActionDiscretizer``) but has no observation
discretiser, so :class:`StateDiscretizer` maps each observation dimension to one of
``n_bins`` bins (uniform, or quadratic "heavy-tail" spacing that puts more bins near
``low``, e.g. small normalised positions/headways) and also writes one integer state
index for table lookup.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Bounded, Composite, Unbounded
from torchrl.envs.transforms import Transform

_HASH_MOD = (1 << 61) - 1  # Mersenne prime: polynomial hash when n_bins^dim overflows int64


def bin_edges(n_bins: int, low: float = 0.0, high: float = 1.0, heavy_tail: bool = False) -> torch.Tensor:
    """The ``n_bins - 1`` interior edges: ``low + (high - low) u`` or ``... u^2`` (heavy tail), u = k / n_bins."""
    u = torch.arange(1, n_bins, dtype=torch.float64) / n_bins
    if heavy_tail:
        u = u * u
    return low + (high - low) * u


class StateDiscretizer(Transform):
    """Writes per-dimension bin indices and a flat state index.

    Args:
        n_bins: bins per dimension (default 20, >= 2).
        low, high: the range the bins cover (values outside land in the end bins);
            the seed observation is normalised to ``[0, 1]``.
        heavy_tail: ``False`` (uniform), ``True`` (quadratic spacing on the position
            half of the seed observation ``[v/30, p/L]``) or a list of dimensions.
        in_key: the observation to discretise.
        out_key: per-dimension bin indices (int64, ``[B, dim]``).
        index_key: flat index ``sum_i b_i n_bins^i`` (int64, ``[B, 1]``); a polynomial
            hash modulo ``2^61 - 1`` when ``n_bins^dim`` does not fit in int64.

    Example:
        >>> from mixed_traffic import make_env
        >>> from torchrl.envs import TransformedEnv
        >>> from transforms import StateDiscretizer
        >>> env = TransformedEnv(make_env("ring", batch_size=2, seed=0), StateDiscretizer(n_bins=20))
        >>> td = env.reset()
        >>> td["observation_discrete"].shape, td["state_index"].shape
        (torch.Size([2, 8]), torch.Size([2, 1]))
        >>> bool((td["observation_discrete"] < 20).all())
        True
    """

    def __init__(self, n_bins: int = 20, low: float = 0.0, high: float = 1.0,
                 heavy_tail: bool | Sequence[int] = False, *, in_key: NestedKey = "observation",
                 out_key: NestedKey = "observation_discrete", index_key: NestedKey | None = "state_index"):
        if not (isinstance(n_bins, int) and n_bins >= 2):
            raise ValueError(f"StateDiscretizer: n_bins={n_bins!r} is invalid; allowed: an integer >= 2")
        if not low < high:
            raise ValueError(f"StateDiscretizer: low={low!r}, high={high!r} are invalid; allowed: low < high")
        out_keys = [out_key] + ([index_key] if index_key is not None else [])
        super().__init__(in_keys=[in_key], out_keys=out_keys)
        self.n_bins, self.low, self.high, self.heavy_tail = n_bins, float(low), float(high), heavy_tail
        self.in_key, self.out_key, self.index_key = in_key, out_key, index_key
        self.register_buffer("uniform_edges", bin_edges(n_bins, low, high, False).float())
        self.register_buffer("heavy_edges", bin_edges(n_bins, low, high, True).float())
        self._dim = None

    def _heavy_mask(self, dim: int, device) -> torch.Tensor:
        mask = torch.zeros(dim, dtype=torch.bool, device=device)
        if self.heavy_tail is True:
            mask[dim // 2:] = True
        elif self.heavy_tail:
            idx = list(self.heavy_tail)
            bad = [i for i in idx if not -dim <= i < dim]
            if bad:
                raise ValueError(f"StateDiscretizer: heavy_tail dims {bad} are invalid; allowed: [0, {dim - 1}]")
            mask[idx] = True
        return mask

    def discretize(self, obs: torch.Tensor) -> torch.Tensor:
        """Bin index of every entry of ``obs`` (int64, same shape)."""
        x = obs.float().contiguous()
        uni = torch.bucketize(x, self.uniform_edges.to(x.device), right=True)
        heavy = torch.bucketize(x, self.heavy_edges.to(x.device), right=True)
        mask = self._heavy_mask(obs.shape[-1], obs.device)
        return torch.where(mask, heavy, uni).long()

    def flat_index(self, bins: torch.Tensor) -> torch.Tensor:
        """One int64 per row (exact when ``n_bins^dim < 2^62``)."""
        dim = bins.shape[-1]
        if dim * torch.log2(torch.tensor(float(self.n_bins))) < 62:
            weights = self.n_bins ** torch.arange(dim, dtype=torch.int64, device=bins.device)
            return (bins * weights).sum(-1, keepdim=True)
        h = torch.zeros(bins.shape[:-1], dtype=torch.int64, device=bins.device)
        for i in range(dim):  # Horner, kept below 2^61 * n_bins < 2^63
            h = (h * self.n_bins + bins[..., i]) % _HASH_MOD
        return h.unsqueeze(-1)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        obs = next_tensordict.get(self.in_key)
        bins = self.discretize(obs)
        next_tensordict.set(self.out_key, bins)
        if self.index_key is not None:
            next_tensordict.set(self.index_key, self.flat_index(bins))
        return next_tensordict

    forward = _call

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._call(tensordict_reset)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        spec = observation_spec[self.in_key]
        observation_spec[self.out_key] = Bounded(low=0, high=self.n_bins - 1, shape=spec.shape, dtype=torch.int64,
                                                 device=spec.device)
        if self.index_key is not None:
            observation_spec[self.index_key] = Unbounded(shape=(*spec.shape[:-1], 1), dtype=torch.int64,
                                                         device=spec.device)
        return observation_spec

    def __repr__(self) -> str:
        return f"{type(self).__name__}(n_bins={self.n_bins}, heavy_tail={self.heavy_tail})"
