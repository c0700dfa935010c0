"""DeePLCCHistory: the DeeP-LCC past-data window ``uini``, ``yini``, ``eini`` from the env's keys.

At every step the window holds the last ``t_ini`` instants of (time-major, flat):

- ``uini`` [B, n_cav * t_ini]: the CAV accelerations executed from each instant;
- ``yini`` [B, (n_followers + n_cav) * t_ini]: measurement type 3, the followers'
  speed errors ``v_i - v*`` then the CAV spacing errors ``s - s*``;
- ``eini`` [B, t_ini]: the head's speed error ``v_head - v*``.

The instant ``t`` enters the window once its action is known, so at step ``t`` the
window covers ``t - t_ini .. t - 1`` (the alignment of the Hankel data). At reset the
platoon is taken as having rested in its current state: ``yini``/``eini`` repeat the
current measurement, ``uini`` is zero.

``v*`` is fixed, or with ``adaptive_v_star=True`` the mean head speed over the last
``t_ini`` instants up to the current one; the whole window is then re-expressed
around the current ``v*`` (needed when the head leaves v* for long, e.g. a hard
brake). The raw window is kept in ``deeplcc_window`` [B, (n_followers + n_cav + 1) * t_ini].

>>> from torchrl.envs import TransformedEnv
>>> from mixed_traffic import make_env
>>> env = TransformedEnv(make_env("deeplcc", batch_size=2, seed=0), DeePLCCHistory())
>>> td = env.rollout(3)
>>> td["next", "yini"].shape
torch.Size([2, 3, 200])
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.data import Composite, Unbounded
from torchrl.envs.transforms import Transform

SPEED, GAP, ACCEL = ("traffic", "speed"), ("traffic", "gap"), ("cav", "accel")
RAW = "deeplcc_window"


class DeePLCCHistory(Transform):
    """Emit the DeeP-LCC past-data window (see the module docstring).

    Args:
        cav_indices: vehicle indices of the CAVs (head = 0), as in the scenario.
        t_ini: window length in steps (default 20).
        v_star: equilibrium speed the errors are taken around (m/s), when not adaptive.
        s_star: CAV spacing reference (m).
        adaptive_v_star: use the mean head speed of the last ``t_ini`` instants as v*.
    """

    def __init__(self, cav_indices=(3, 6), t_ini: int = 20, v_star: float = 15.0, s_star: float = 20.0,
                 adaptive_v_star: bool = False):
        if not (isinstance(t_ini, int) and t_ini >= 1):
            raise ValueError(f"DeePLCCHistory: t_ini={t_ini!r} is invalid; allowed: an integer >= 1")
        cav_indices = tuple(int(i) for i in cav_indices)
        if not cav_indices or min(cav_indices) < 1:
            raise ValueError(f"DeePLCCHistory: cav_indices={cav_indices} is invalid; allowed: vehicle indices >= 1")
        super().__init__(in_keys=[SPEED, GAP, ACCEL], out_keys=["uini", "yini", "eini", RAW])
        self.cav_indices, self.t_ini, self.v_star, self.s_star = cav_indices, t_ini, float(v_star), float(s_star)
        self.adaptive_v_star = bool(adaptive_v_star)

    # ----------------------------------------------------------------- helpers
    def _raw(self, td: TensorDictBase) -> torch.Tensor:
        """One instant, raw: follower speeds, CAV gaps, head speed -> [..., p + 1]."""
        speed, gap = td.get(SPEED), td.get(GAP)
        return torch.cat([speed[..., 1:], gap[..., list(self.cav_indices)], speed[..., :1]], dim=-1)

    def _emit(self, out: TensorDictBase, raw_window: torch.Tensor, head_now: torch.Tensor) -> None:
        """Write yini/eini (re-expressed around the current v*) and the raw window."""
        w = raw_window.unflatten(-1, (self.t_ini, -1))  # [..., t_ini, p + 1]
        m = len(self.cav_indices)
        n_f = w.shape[-1] - 1 - m
        if self.adaptive_v_star:
            heads = torch.cat([w[..., 1:, -1], head_now], -1)  # instants t-t_ini+1 .. t
            v_star = heads.mean(-1, keepdim=True).unsqueeze(-1)
        else:
            v_star = self.v_star
        y = torch.cat([w[..., :n_f] - v_star, w[..., n_f:n_f + m] - self.s_star], -1)
        out.set("yini", y.flatten(-2))
        out.set("eini", (w[..., -1:] - v_star).flatten(-2))
        out.set(RAW, raw_window)

    # ---------------------------------------------------------- transform API
    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        raw = self._raw(tensordict_reset)
        m = len(self.cav_indices)
        tensordict_reset.set("uini", torch.zeros(*raw.shape[:-1], m * self.t_ini, dtype=raw.dtype, device=raw.device))
        self._emit(tensordict_reset, raw.tile(self.t_ini), raw[..., -1:])
        return tensordict_reset

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        raw = self._raw(tensordict)  # instant t (before the action)
        u = next_tensordict.get(ACCEL).to(raw.dtype)  # executed from t to t+1
        m, q = u.shape[-1], raw.shape[-1]
        next_tensordict.set("uini", torch.cat([tensordict.get("uini")[..., m:], u], -1))
        window = torch.cat([tensordict.get(RAW)[..., q:], raw], -1)
        self._emit(next_tensordict, window, next_tensordict.get(SPEED)[..., :1])
        return next_tensordict

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        return next_tensordict  # everything happens in _step/_reset (needs the previous window)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        n = observation_spec[SPEED].shape[-1]
        m = len(self.cav_indices)
        p = n - 1 + m
        batch, dev, dtype = observation_spec.shape, observation_spec.device, observation_spec[SPEED].dtype
        for key, width in (("uini", m * self.t_ini), ("yini", p * self.t_ini), ("eini", self.t_ini),
                           (RAW, (p + 1) * self.t_ini)):
            observation_spec[key] = Unbounded(shape=(*batch, width), dtype=dtype, device=dev)
        return observation_spec
