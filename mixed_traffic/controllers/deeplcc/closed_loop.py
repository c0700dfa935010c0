"""Closed-loop simulation of the DeeP-LCC platoon and its evaluation metrics.

:func:`run_closed_loop` drives a batch of platoons with a controller
``controller(uini, yini, eini) -> u`` (flat, time-major numpy arrays ``(B, m*t_ini)``,
``(B, p*t_ini)``, ``(B, t_ini)`` -> ``(B, m)``). The first ``t_ini`` steps run
with zero CAV input to fill the past-data window; the equilibrium speed is fixed
(``v*``) or adaptive (mean head speed over the last ``t_ini`` steps, for
scenarios far from v*), and past outputs are re-expressed around the current v*
as in the reference. Five evaluation scenarios are in :data:`EVAL_SCENARIOS`.

Metrics (per episode, over the controlled steps):
  - ``cost``: sum of the stage cost ``weight_v |v - v*|^2 + weight_s |s_cav - s*|^2 + weight_u |u|^2``;
  - ``fuel`` (mL): the reference's fuel model summed over the vehicles from the
    first CAV to the tail, ``0.444 + 0.09 R v + 0.054 max(a,0)^2 v`` with
    ``R = 0.333 + 0.00108 v^2 + 1.2 a`` (0.444 when ``R <= 0``), times dt;
  - ``velocity_error``: ``sum |v_i - v_head| / v_head`` over the same vehicles,
    divided by the number of followers and the number of steps (the reference's normalisation);
  - ``collisions`` (any gap <= 0) and ``min_gap``.

>>> import numpy as np, torch
>>> cfg = PlatoonConfig(accel_noise=0.0)
>>> v = head_speed_profile("sine", 4.0, cfg.dt, batch=1)
>>> out = run_closed_loop(lambda u, y, e: np.zeros((u.shape[0], 2)), v, cfg, t_ini=20)
>>> out["cost"].shape, bool(out["collisions"][0])
((1,), False)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from mixed_traffic.controllers.deeplcc.platoon import DTYPE, PlatoonConfig, gaps, init_state, step
from mixed_traffic.controllers.deeplcc.qp import QPParams
from mixed_traffic.profiles import make_profile


@dataclass(frozen=True)
class ScenarioSpec:
    """A head-speed scenario: profile name and arguments, length, equilibrium mode."""

    name: str
    profile: str
    kwargs: tuple = ()
    seconds: float = 40.0
    adaptive_v_star: bool = False

    def head_speed(self, dt: float, batch: int = 1, generator: torch.Generator | None = None) -> torch.Tensor:
        return head_speed_profile(self.profile, self.seconds, dt, batch, generator, **dict(self.kwargs))


EVAL_SCENARIOS = {
    "random1": ScenarioSpec("random1", "random_perturbation", (("amplitude", 1.0), ("period", 1.0))),
    "random5": ScenarioSpec("random5", "random_perturbation", (("amplitude", 5.0), ("period", 1.0))),
    "brake": ScenarioSpec("brake", "deeplcc_brake", (("start", 1.0),), adaptive_v_star=True),
    "sine": ScenarioSpec("sine", "sine", (("amplitude", 5.0), ("period", 10.0))),
    "nedc": ScenarioSpec("nedc", "nedc", (("start", 5.0),), seconds=330.0, adaptive_v_star=True),
}


def head_speed_profile(name: str, seconds: float, dt: float, batch: int = 1,
                       generator: torch.Generator | None = None, **kwargs) -> torch.Tensor:
    """Head speed ``[batch, steps + 1]`` of a named profile sampled every ``dt``."""
    if name == "random_perturbation":
        kwargs.setdefault("horizon", seconds)
    prof = make_profile(name, **kwargs)
    params = prof.sample(batch, generator)
    steps = int(round(seconds / dt))
    t = torch.arange(steps + 1, dtype=torch.float32) * dt
    return torch.stack([prof.speed(t, params[b].expand(len(t), -1)) for b in range(batch)]).to(DTYPE)


def fuel_rate(v: np.ndarray, a: np.ndarray) -> np.ndarray:
    """The reference's instantaneous fuel model (mL/s)."""
    R = 0.333 + 0.00108 * v**2 + 1.2 * a
    F = 0.444 + 0.09 * R * v + 0.054 * np.maximum(a, 0.0) ** 2 * v
    return np.where(R <= 0, 0.444, F)


def run_closed_loop(controller, head_speed: torch.Tensor, cfg: PlatoonConfig, t_ini: int = 20,
                    qp_params: QPParams | None = None, adaptive_v_star=False,
                    generator: torch.Generator | None = None, record: bool = False, simulator=None) -> dict:
    """Simulate ``head_speed.shape[0]`` platoons for ``head_speed.shape[1] - 1`` steps.

    ``simulator``: ``None`` (the torch platoon, :func:`.platoon.step`) or a
    :class:`mixed_traffic.envs.sumo_platoon.SumoPlatoon` (one platoon: SUMO moves the cars).

    Returns numpy metrics (``cost``, ``fuel``, ``velocity_error``, ``collisions``,
    ``min_gap``: ``(B,)``) and, with ``record=True``, the samples the controller
    saw (``uini``, ``yini``, ``eini``, ``u``: ``(B, K, ·)``) and trajectories.
    """
    qp_params = qp_params or QPParams()
    B, K1 = head_speed.shape
    K = K1 - 1
    if K <= t_ini:
        raise ValueError(f"run_closed_loop: {K} steps is too short; allowed: > t_ini ({t_ini})")
    m, nf = cfg.m, cfg.n_followers
    ci = [i - 1 for i in cfg.cav_indices]
    adaptive = torch.as_tensor(adaptive_v_star, dtype=torch.bool).expand(B)
    if simulator is not None and B != 1:
        raise ValueError(f"run_closed_loop: {B} platoons is invalid with a simulator; allowed: 1")
    if simulator is None:
        pos, vel = init_state(B, cfg, v0=float(head_speed[0, 0]))
    else:
        pos, vel = simulator.start(float(head_speed[0, 0]))
    vel[:, 0] = head_speed[:, 0]
    # raw histories of the window (head speed, follower speeds, CAV gaps, executed u)
    h_vh = torch.zeros(B, K + 1, dtype=DTYPE)
    h_v = torch.zeros(B, K + 1, nf, dtype=DTYPE)
    h_s = torch.zeros(B, K + 1, m, dtype=DTYPE)
    h_u = torch.zeros(B, K + 1, m, dtype=DTYPE)
    h_acc = torch.zeros(B, K + 1, nf, dtype=DTYPE)
    cost = np.zeros(B)
    min_gap = np.full(B, np.inf)
    collided = np.zeros(B, dtype=bool)
    rec = {k: [] for k in ("uini", "yini", "eini", "u")} if record else None
    for k in range(K):
        h_vh[:, k], h_v[:, k], h_s[:, k] = vel[:, 0], vel[:, 1:], gaps(pos, cfg)[:, ci]
        g = gaps(pos, cfg)
        min_gap = np.minimum(min_gap, g.min(-1).values.numpy())
        collided |= (g <= 0).any(-1).numpy()
        lo = max(0, k - t_ini + 1)
        v_star = torch.where(adaptive, h_vh[:, lo:k + 1].mean(-1), torch.full((B,), cfg.v_star, dtype=DTYPE))
        if k >= t_ini:
            w = slice(k - t_ini, k)
            uini = h_u[:, w].reshape(B, -1)
            yini = torch.cat([h_v[:, w] - v_star[:, None, None], h_s[:, w] - cfg.s_star], -1).reshape(B, -1)
            eini = h_vh[:, w] - v_star[:, None]
            u = torch.as_tensor(np.asarray(controller(uini.numpy(), yini.numpy(), eini.numpy())), dtype=DTYPE)
            if record:
                for key, val in (("uini", uini), ("yini", yini), ("eini", eini), ("u", u)):
                    rec[key].append(val.numpy().copy())
        else:
            u = torch.zeros(B, m, dtype=DTYPE)
        if simulator is None:
            pos, vel, executed = step(pos, vel, u, head_speed[:, k + 1], cfg, generator)
        else:
            pos, vel, executed = simulator.step(u, head_speed[:, k + 1])
        h_u[:, k] = executed
        h_acc[:, k] = (vel[:, 1:] - h_v[:, k]) / cfg.dt
        if k >= t_ini:
            J = (qp_params.weight_v * ((h_v[:, k] - v_star[:, None]) ** 2).sum(-1)
                 + qp_params.weight_s * ((h_s[:, k] - cfg.s_star) ** 2).sum(-1)
                 + qp_params.weight_u * (executed**2).sum(-1))
            cost += J.numpy()
    ctrl = slice(t_ini, K)
    first = min(cfg.cav_indices) - 1
    v_tail, a_tail = h_v[:, ctrl, first:].numpy(), h_acc[:, ctrl, first:].numpy()
    fuel = fuel_rate(v_tail, a_tail).sum((1, 2)) * cfg.dt
    vh = h_vh[:, ctrl].numpy()[..., None]
    vel_err = (np.abs(v_tail - vh) / np.maximum(vh, 1e-6)).sum((1, 2)) / nf / (K - t_ini)
    out = {"cost": cost, "fuel": fuel, "velocity_error": vel_err, "collisions": collided, "min_gap": min_gap}
    if record:
        out.update({k: np.stack(v, 1) for k, v in rec.items()})
        out.update(head_speed=h_vh.numpy(), speeds=h_v.numpy(), cav_gaps=h_s.numpy(), cav_accel=h_u.numpy())
    return out


class QPController:
    """Batched controller: one :class:`~.qp.DeepLCCSolver` per batch row (or one shared)."""

    def __init__(self, solvers):
        self.solvers = list(solvers)

    def __call__(self, uini, yini, eini) -> np.ndarray:
        if len(self.solvers) == 1:
            s = self.solvers[0]
            return np.stack([s.solve(uini[b], yini[b], eini[b]).u for b in range(uini.shape[0])])
        return np.stack([s.solve(uini[b], yini[b], eini[b]).u for b, s in enumerate(self.solvers)])


def evaluate(controller, cfg: PlatoonConfig, scenarios=None, t_ini: int = 20, qp_params: QPParams | None = None,
             seed: int = 0) -> dict[str, dict]:
    """Run ``controller`` on each scenario (one episode each, seeded) -> ``{name: metrics}``."""
    scenarios = scenarios or list(EVAL_SCENARIOS)
    out = {}
    for i, name in enumerate(scenarios):
        spec = EVAL_SCENARIOS[name]
        gen = torch.Generator().manual_seed(seed + 1000 * i)
        v = spec.head_speed(cfg.dt, 1, gen)
        if hasattr(controller, "reset"):
            controller.reset()
        res = run_closed_loop(controller, v, cfg, t_ini, qp_params, spec.adaptive_v_star,
                              generator=torch.Generator().manual_seed(seed + 1000 * i + 1))
        out[name] = {k: float(np.asarray(v_)[0]) for k, v_ in res.items()}
    return out


def evaluate_in_env(policy, scenario: str, seed: int = 0, **overrides) -> dict:
    """Roll ``policy`` (a TensorDictModule reading uini/yini/eini) in the TorchRL ``deeplcc`` env.

    The env is wrapped with :class:`transforms.deeplcc_history.DeePLCCHistory` (adaptive v* when
    the scenario uses it) and integrates with the explicit Euler rule. Returns the sum of the
    env's stage cost ``("traffic", "J")``, whether a collision happened and the minimum gap.
    """
    from torchrl.envs import TransformedEnv

    from mixed_traffic import make_env
    from transforms.deeplcc_history import DeePLCCHistory

    spec = EVAL_SCENARIOS[scenario]
    kwargs = dict(spec.kwargs)
    if spec.profile == "random_perturbation":
        kwargs.setdefault("v_star", 15.0)
    env = TransformedEnv(make_env("deeplcc", batch_size=1, seed=seed, integration="euler_explicit",
                                  episode_seconds=spec.seconds, profile=spec.profile, profile_kwargs=kwargs,
                                  **overrides), DeePLCCHistory(adaptive_v_star=spec.adaptive_v_star))
    with torch.no_grad():
        td = env.rollout(int(round(spec.seconds / env.dt)), policy, break_when_any_done=False)
    return {"J": float(td["next", "traffic", "J"].sum()), "collision": bool(td["next", "collision"].any()),
            "min_gap": float(td["next", "cav", "gap"].min())}
