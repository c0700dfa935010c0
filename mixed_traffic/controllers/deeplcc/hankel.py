"""Hankel matrices of pre-collected trajectories (the data DeeP-LCC predicts with).

A trajectory ``x`` of ``m`` channels and ``T`` samples, ``x[:, t]``, gives the
Hankel matrix of depth ``L`` whose column ``j`` stacks ``x[:, j], ..., x[:, j+L-1]``
(time-major: the ``m`` channels of one instant are contiguous). Splitting the
depth into ``t_ini`` past and ``n`` future instants gives ``(Up, Uf)``, ``(Ep, Ef)``
and ``(Yp, Yf)``.

>>> import numpy as np
>>> from mixed_traffic.controllers.deeplcc.hankel import hankel_matrix
>>> hankel_matrix(np.arange(5.0)[None], 3)
array([[0., 1., 2.],
       [1., 2., 3.],
       [2., 3., 4.]])
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

HANKEL_KEYS = ("Up", "Uf", "Ep", "Ef", "Yp", "Yf")


def hankel_matrix(x: np.ndarray, depth: int) -> np.ndarray:
    """Block Hankel matrix of depth ``depth`` of ``x`` (shape ``(m, T)``) -> ``(m*depth, T-depth+1)``."""
    x = np.asarray(x)
    if x.ndim != 2:
        raise ValueError(f"hankel_matrix: x must have shape (channels, T), got {x.shape}")
    m, T = x.shape
    if not 1 <= depth <= T:
        raise ValueError(f"hankel_matrix: depth={depth} is invalid; allowed: 1 <= depth <= T ({T})")
    cols = T - depth + 1
    # row block i holds x[:, i:i+cols]
    return np.concatenate([x[:, i:i + cols] for i in range(depth)], axis=0)


@dataclass(frozen=True)
class HankelData:
    """Past/future Hankel blocks of inputs ``U``, disturbance ``E`` and outputs ``Y``.

    Shapes: ``Up (m*t_ini, M)``, ``Uf (m*n, M)``, ``Ep (t_ini, M)``, ``Ef (n, M)``,
    ``Yp (p*t_ini, M)``, ``Yf (p*n, M)`` with ``M = T - t_ini - n + 1`` columns.
    """

    Up: np.ndarray
    Uf: np.ndarray
    Ep: np.ndarray
    Ef: np.ndarray
    Yp: np.ndarray
    Yf: np.ndarray
    t_ini: int
    n: int

    @property
    def m(self) -> int:
        return self.Up.shape[0] // self.t_ini

    @property
    def p(self) -> int:
        return self.Yp.shape[0] // self.t_ini

    @property
    def columns(self) -> int:
        return self.Up.shape[1]

    def check_excitation(self) -> HankelData:
        """Refuse data DeeP-LCC cannot predict with: non-finite values, or inputs not persistently exciting.

        The behavioural model needs ``[Up; Ep; Uf; Ef]`` of full row rank ``(m + 1)(t_ini + n)``
        (Willems' fundamental lemma); without it the QP's KKT matrix is singular and every
        solve returns NaN.
        """
        for k in HANKEL_KEYS:
            if not np.all(np.isfinite(getattr(self, k))):
                raise ValueError(f"hankel data: {k} contains non-finite values; allowed: finite trajectories")
        ue = np.vstack([self.Up, self.Ep, self.Uf, self.Ef])
        rows = ue.shape[0]
        rank = int(np.linalg.matrix_rank(ue)) if ue.shape[1] >= rows else min(ue.shape)
        if rank < rows:
            raise ValueError(
                f"hankel data: [Up; Ep; Uf; Ef] has rank {rank} < {rows} rows, so the inputs are not persistently "
                f"exciting of order t_ini + n = {self.t_ini + self.n}; allowed: pre-collected CAV inputs and head "
                f"perturbations that vary (e.g. random), with at least {rows} columns (got {ue.shape[1]})")
        return self

    def as_dict(self) -> dict[str, np.ndarray]:
        return {k: getattr(self, k) for k in HANKEL_KEYS}

    @classmethod
    def from_dict(cls, d: dict, t_ini: int, n: int) -> HankelData:
        return cls(**{k: np.asarray(d[k], dtype=np.float64) for k in HANKEL_KEYS}, t_ini=t_ini, n=n)


def build_hankel(ud: np.ndarray, ed: np.ndarray, yd: np.ndarray, t_ini: int, n: int) -> HankelData:
    """Hankel blocks from trajectories ``ud (m, T)``, ``ed (1, T)`` or ``(T,)``, ``yd (p, T)``.

    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> h = build_hankel(rng.uniform(-1, 1, (2, 100)), rng.uniform(-1, 1, 100), rng.normal(size=(10, 100)), 5, 10)
    >>> h.Up.shape, h.Yf.shape, h.columns
    ((10, 86), (100, 86), 86)
    """
    if t_ini < 1 or n < 1:
        raise ValueError(f"build_hankel: t_ini={t_ini} and n={n} must both be >= 1")
    ud = np.atleast_2d(np.asarray(ud, dtype=np.float64))
    ed = np.atleast_2d(np.asarray(ed, dtype=np.float64))
    yd = np.atleast_2d(np.asarray(yd, dtype=np.float64))
    T = ud.shape[1]
    if ed.shape[1] != T or yd.shape[1] != T:
        raise ValueError(f"build_hankel: ud, ed, yd must share T; got {ud.shape}, {ed.shape}, {yd.shape}")
    L = t_ini + n
    if T < L:
        raise ValueError(f"build_hankel: T={T} is invalid; allowed: T >= t_ini + n ({L})")
    m, p = ud.shape[0], yd.shape[0]
    U, E, Y = hankel_matrix(ud, L), hankel_matrix(ed, L), hankel_matrix(yd, L)
    return HankelData(Up=U[: m * t_ini], Uf=U[m * t_ini:], Ep=E[:t_ini], Ef=E[t_ini:],
                      Yp=Y[: p * t_ini], Yf=Y[p * t_ini:], t_ini=t_ini, n=n)
