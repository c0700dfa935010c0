"""Unsignalised intersection: a batched TorchRL environment.

The ego drives north on the line ``x = 0.5`` with double-integrator dynamics (state
``[y, v]``, action = acceleration in m/s^2, dt 0.1 s) from ``y = -1.25`` to ``y >= 1.25``
while a human-driven agent (see :mod:`mixed_traffic.envs.intersection_agents`) crosses its
path. Every row is an independent episode that auto-resets on its own (``"_reset"`` mask).

Keys (all ``[B, ...]``):

| key | shape | meaning |
|---|---|---|
| ``observation`` | [B, 8] | ``[y_ego, v_ego, x_a, y_a, vx_a, vy_a, sigma_x, sigma_y]`` (agent as perceived) |
| ``action`` | [B, 1] | acceleration, ``Bounded(-a_max, a_max)`` (clamped by the env) |
| ``("next", "reward")``, ``("next", "cost")`` | [B, 1] | see below; ``env.reward_keys == ["cost", "reward"]`` |
| ``collision``, ``success``, ``out_of_bounds`` | [B, 1] bool | terminal events (all terminate) |
| ``truncated`` | [B, 1] bool | the step cap (500) was reached |
| ``("ego", "pos")`` | [B, 2] | ego centre ``(0.5, y)`` |
| ``("ego", "accel")`` | [B, 1] | acceleration executed in the last step |
| ``("agent", "true_pos")``, ``("agent", "true_vel")`` | [B, 2] | the agent's true state |
| ``("agent", "behaviour")``, ``("agent", "episode")`` | [B, 1] int64 | behaviour id, index in the trajectory bank |
| ``step_count`` | [B, 1] int64 | steps since the row's reset |

Reward: ``w_prog v dt - w_time dt - w_speed max(0, v - v_limit)^2 - w_comf a^2 - w_reverse max(0, -v) dt``
plus ``+R_goal`` on success and ``-C_crash`` on collision (``w_reverse`` is 0 unless a training
config sets it). Cost:
``mu max(0, (2R + sqrt(sx^2 + sy^2))^2 - d^2) + c_crash [collision]`` with ``d`` the distance
from the ego to the *perceived* agent centre (the quantity the controller can act on).

>>> from mixed_traffic import make_env
>>> env = make_env("intersection", batch_size=4, seed=0)
>>> td = env.rollout(5, break_when_any_done=False)
>>> td["next", "cost"].shape
torch.Size([4, 5, 1])
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from mixed_traffic.envs.intersection_agents import (
    BEHAVIOURS,
    TRAIN_BEHAVIOURS,
    AgentModelParams,
    AgentTrajectories,
    _path,
    load_recorded_trajectories,
    reactive_step,
    sample_agent_trajectories,
)

EGO_X = 0.5
OBS_SCALE = (1.5, 1.0, 2.0, 1.0, 1.0, 1.0, 0.1, 0.1)
OBS_SHIFT = (0.0, 0.8, 0.5, 0.3, -0.5, 0.0, 0.1, 0.1)


def relational_features(obs: torch.Tensor) -> torch.Tensor:
    """Ego-agent features an MLP finds hard to compute from raw coordinates (all O(1)), ``[..., 5]``.

    Relative position, distance, the agent's time to reach the ego's line and the ego's time
    to reach the agent's ``y`` (both clipped to [-5, 5] s).
    """
    y, v, xa, ya, vxa = obs[..., 0:1], obs[..., 1:2], obs[..., 2:3], obs[..., 3:4], obs[..., 4:5]
    dx, dy = xa - EGO_X, ya - y
    d = torch.sqrt(dx**2 + dy**2)
    t_agent = (dx / (-vxa).clamp(min=0.05)).clamp(-5, 5)
    t_ego = (dy / v.clamp(min=0.1)).clamp(-5, 5)
    return torch.cat([dx / 2, dy / 2, d / 2, t_agent / 2, t_ego / 2], dim=-1)


class ObservationFeatures(nn.Module):
    """Network input for the intersection (``policy.features=intersection``): normalised observation + relations.

    ``forward(observation, *extra)`` returns ``[..., 8 + 5 + sum(extra dims)]``; extra inputs
    (e.g. a base controller's acceleration) are divided by ``extra_scale``.

    >>> ObservationFeatures()(torch.zeros(3, 8), torch.zeros(3, 1)).shape
    torch.Size([3, 14])
    """

    n_features = 8 + 5

    def __init__(self, extra_scale: float = 3.2):
        super().__init__()
        self.register_buffer("shift", torch.tensor(OBS_SHIFT))
        self.register_buffer("scale", torch.tensor(OBS_SCALE))
        self.extra_scale = float(extra_scale)

    def forward(self, obs: torch.Tensor, *extra: torch.Tensor) -> torch.Tensor:
        x = [((obs - self.shift) / self.scale).clamp(-10, 10), relational_features(obs)]
        return torch.cat(x + [e / self.extra_scale for e in extra], dim=-1)


#: where close-start agents start (m, x0 range) unless ``hard_start_x`` says otherwise
HARD_START_X = (2.2, 2.6)


def agent_bank(n: int, *, seed: int, style: str = "mixed", hard_start_fraction: float = 0.0,
               hard_start_x: tuple[float, float] = HARD_START_X, reactive_fraction: float = 0.0,
               pause_fraction: float = 0.0, **kw) -> AgentTrajectories:
    """A training bank of ``n`` agents: ``style`` agents, with the given shares replaced by close
    starts (``x0`` in ``hard_start_x``), reactive agents and pausing agents (``kw``: ``split``,
    ``behaviours``, ``horizon`` of :func:`sample_agent_trajectories`)."""
    n_hard = int(round(hard_start_fraction * n))
    n_react = int(round(reactive_fraction * n))
    n_pause = int(round(pause_fraction * n))
    n_plain = max(0, n - n_hard - n_react - n_pause)
    banks = [sample_agent_trajectories(n_plain, seed=abs(seed), style=style, **kw)] if n_plain else []
    if n_hard:
        banks.append(sample_agent_trajectories(n_hard, seed=abs(seed) + 7919, style=style, **kw,
                                               params=AgentModelParams(start_x=tuple(hard_start_x))))
    if n_react:
        banks.append(sample_agent_trajectories(n_react, seed=abs(seed) + 104_729, style="reactive", **kw))
    if n_pause:
        banks.append(sample_agent_trajectories(n_pause, seed=abs(seed) + 130_363, style="pause", **kw))
    return AgentTrajectories.cat(banks)


class IntersectionEnv(EnvBase):
    """Batched unsignalised-intersection environment (see the module docstring for keys).

    Args:
        batch_size: number of independent episodes stepped together.
        device: torch device.
        dt, a_max, y_start, y_goal, y_min, y_max, max_steps, radius: geometry/dynamics.
        v_min, v_max: clamp of the ego speed (m/s); the default lets it reverse slowly.
        start_noise: half width of the uniform random start offset (m), 0 .. 0.15.
        agent_split, agent_behaviours, agent_bank_size, agent_style: the agent model's
            trajectory bank, resampled on every ``set_seed``.
        hard_start_fraction, hard_start_x: share of the generated bank replaced by agents whose
            start ``x`` is drawn from ``hard_start_x`` (close starts, which reach the crossing
            ~1.5 s after the ego starts; an independent seed stream).
        reactive_fraction: share of the generated bank made of reactive agents, which answer
            the ego's motion (yield, hesitate, speed up or go;
            :func:`~mixed_traffic.envs.intersection_agents.reactive_step`).
        pause_fraction: share of the generated bank made of agents that pause once for 0.5-10 s
            anywhere from their stop line to beyond the crossing (style ``"pause"``; an
            independent seed stream of ``agent_split``).
        random_start_fraction, random_start_y, random_start_v: share of resets (training:
            exploring starts) that put the ego at ``y ~ U(random_start_y)`` moving at
            ``v ~ U(random_start_v)`` instead of at rest at ``y_start``; the agent starts as usual.
        agent_trajectories: an :class:`AgentTrajectories` bank or a path to a ``.npy`` of
            recorded rows ``[x, y, vx, vy, sx, sy]``; replaces the generative model.
        agent_sampling: ``"random"`` (each reset draws a bank index) or ``"sequential"``
            (resets take indices 0, 1, 2, ... in order; row ``b``'s first episode is ``b``).
        w_prog, w_time, w_speed, v_limit, w_comf, w_reverse, r_goal, c_crash_reward, mu, c_crash: reward/cost.

    >>> env = IntersectionEnv(batch_size=2, start_noise=0.1)
    >>> from torchrl.envs.utils import check_env_specs
    >>> check_env_specs(env)
    """

    def __init__(self, *, batch_size: int = 1, device="cpu", dt: float = 0.1, a_max: float = 3.2,
                 y_start: float = -1.25, y_goal: float = 1.25, y_min: float = -6.0, y_max: float = 25.0,
                 max_steps: int = 500, radius: float = 0.3328, v_min: float = -1.0, v_max: float = 3.0,
                 start_noise: float = 0.0, agent_split: str = "train", agent_behaviours=None,
                 agent_bank_size: int = 2048, agent_style: str = "mixed", hard_start_fraction: float = 0.0,
                 hard_start_x: tuple[float, float] = HARD_START_X, reactive_fraction: float = 0.0,
                 pause_fraction: float = 0.0, random_start_fraction: float = 0.0,
                 random_start_y: tuple[float, float] = (-1.25, 0.5), random_start_v: tuple[float, float] = (0.0, 1.5),
                 agent_trajectories: AgentTrajectories | str | None = None, agent_sampling: str = "random",
                 w_prog: float = 25.0, w_time: float = 0.5, w_speed: float = 90.0, v_limit: float = 1.5,
                 w_comf: float = 0.697, w_reverse: float = 0.0, r_goal: float = 200.0, c_crash_reward: float = 150.0,
                 mu: float = 200.0, c_crash: float = 150.0, seed: int = 0):
        if not (isinstance(batch_size, int) and batch_size >= 1):
            raise ValueError(f"batch_size={batch_size!r} is invalid; allowed: an integer >= 1")
        checks = {"dt": (dt, 0.0, 1.0), "a_max": (a_max, 0.0, 50.0), "radius": (radius, 0.0, 5.0),
                  "start_noise": (start_noise, -1e-12, 0.15 + 1e-12), "mu": (mu, -1e-12, 1e9),
                  "w_reverse": (w_reverse, -1e-12, 1e9)}
        for name, (val, lo, hi) in checks.items():
            if not (isinstance(val, (int, float)) and lo < val <= hi):
                raise ValueError(f"{name}={val!r} is invalid; allowed: ({max(lo, 0)}, {hi}]")
        if not (y_min < y_start < y_goal < y_max):
            raise ValueError(f"y_min, y_start, y_goal, y_max = {(y_min, y_start, y_goal, y_max)} are invalid; "
                             "allowed: y_min < y_start < y_goal < y_max")
        if not (isinstance(max_steps, int) and max_steps >= 1):
            raise ValueError(f"max_steps={max_steps!r} is invalid; allowed: an integer >= 1")
        if not v_min < v_max:
            raise ValueError(f"v_min={v_min}, v_max={v_max} are invalid; allowed: v_min < v_max")
        if agent_sampling not in ("random", "sequential"):
            raise ValueError(f"agent_sampling={agent_sampling!r} is invalid; allowed: 'random', 'sequential'")
        if not (isinstance(agent_bank_size, int) and agent_bank_size >= 1):
            raise ValueError(f"agent_bank_size={agent_bank_size!r} is invalid; allowed: an integer >= 1")
        fractions = {"hard_start_fraction": hard_start_fraction, "reactive_fraction": reactive_fraction,
                     "pause_fraction": pause_fraction}
        for name, frac in fractions.items():
            if not (isinstance(frac, (int, float)) and 0.0 <= frac <= 1.0):
                raise ValueError(f"{name}={frac!r} is invalid; allowed: a number in [0, 1]")
        if not (isinstance(random_start_fraction, (int, float)) and 0.0 <= random_start_fraction <= 1.0):
            raise ValueError(f"random_start_fraction={random_start_fraction!r} is invalid; allowed: a number in [0, 1]")
        for name, (lo, hi), (lo_ok, hi_ok) in (("random_start_y", random_start_y, (y_min, y_goal)),
                                               ("random_start_v", random_start_v, (v_min, v_max))):
            if not lo_ok <= lo <= hi < hi_ok:
                raise ValueError(f"{name}={(lo, hi)!r} is invalid; allowed: {lo_ok} <= low <= high < {hi_ok}")
        if sum(fractions.values()) > 1.0:
            raise ValueError(f"hard_start_fraction + reactive_fraction + pause_fraction = {sum(fractions.values())} "
                             "is invalid; allowed: <= 1")
        super().__init__(device=device, batch_size=torch.Size([batch_size]))
        self.hard_start_fraction, self.hard_start_x = float(hard_start_fraction), tuple(hard_start_x)
        self.reactive_fraction, self.pause_fraction = float(reactive_fraction), float(pause_fraction)
        self.random_start_fraction = float(random_start_fraction)
        self.random_start_y, self.random_start_v = tuple(random_start_y), tuple(random_start_v)
        self.dt, self.a_max, self.y_start, self.y_goal = float(dt), float(a_max), float(y_start), float(y_goal)
        self.y_min, self.y_max, self.max_steps, self.radius = float(y_min), float(y_max), max_steps, float(radius)
        self.v_min, self.v_max, self.start_noise = float(v_min), float(v_max), float(start_noise)
        self.w_prog, self.w_time, self.w_speed, self.v_limit = w_prog, w_time, w_speed, v_limit
        self.w_comf, self.r_goal, self.c_crash_reward = w_comf, r_goal, c_crash_reward
        self.w_reverse = float(w_reverse)
        self.mu, self.c_crash = mu, c_crash
        self.agent_split = agent_split
        self.agent_behaviours = list(agent_behaviours) if agent_behaviours is not None else (
            list(TRAIN_BEHAVIOURS) if agent_split == "train" else list(BEHAVIOURS))
        self.agent_bank_size, self.agent_style = agent_bank_size, agent_style
        self.agent_sampling = agent_sampling
        self._fixed_bank = agent_trajectories is not None
        if isinstance(agent_trajectories, str):
            agent_trajectories = load_recorded_trajectories(agent_trajectories, horizon=max_steps)
        if agent_trajectories is not None and agent_trajectories.horizon < max_steps:
            raise ValueError(f"agent_trajectories horizon={agent_trajectories.horizon} is invalid; "
                             f"allowed: >= max_steps={max_steps}")
        self._rng = torch.Generator(device="cpu")
        self._seq = 0
        self.bank = agent_trajectories.to(self.device) if agent_trajectories is not None else None
        self._set_seed(seed)
        B = self.batch_size
        z = torch.zeros(*B, 1, device=self.device)
        self._state = {"y": z.clone(), "v": z.clone(), "t": z.long(), "idx": z.long(),
                       # reactive agents: arc length, speed, hesitation timer, ego (y, v) history (newest first)
                       "s": z.clone(), "va": z.clone(), "timer": z.clone(),
                       "hist": torch.zeros(*B, self.HIST, 2, device=self.device)}
        self._make_specs()

    # ------------------------------------------------------------------ specs
    def _make_specs(self):
        B = self.batch_size
        d = self.device
        bool1 = lambda: Categorical(2, shape=(*B, 1), dtype=torch.bool, device=d)  # noqa: E731
        self.observation_spec = Composite(
            observation=Unbounded(shape=(*B, 8), device=d),
            collision=bool1(), success=bool1(), out_of_bounds=bool1(),
            step_count=Unbounded(shape=(*B, 1), dtype=torch.int64, device=d),
            ego=Composite(pos=Unbounded(shape=(*B, 2), device=d), accel=Unbounded(shape=(*B, 1), device=d),
                          shape=B, device=d),
            agent=Composite(true_pos=Unbounded(shape=(*B, 2), device=d), true_vel=Unbounded(shape=(*B, 2), device=d),
                            behaviour=Unbounded(shape=(*B, 1), dtype=torch.int64, device=d),
                            episode=Unbounded(shape=(*B, 1), dtype=torch.int64, device=d), shape=B, device=d),
            shape=B, device=d)
        self.action_spec = Bounded(-self.a_max, self.a_max, shape=(*B, 1), device=d)
        self.reward_spec = Composite(reward=Unbounded(shape=(*B, 1), device=d), cost=Unbounded(shape=(*B, 1), device=d),
                                     shape=B, device=d)
        self.done_spec = Composite(done=bool1(), terminated=bool1(), truncated=bool1(), shape=B, device=d)

    # ------------------------------------------------------------------ seeding / agent bank
    def _set_seed(self, seed: int | None):
        seed = 0 if seed is None else int(seed)
        self._rng.manual_seed(seed)
        self._seq = 0
        if not self._fixed_bank:
            self.bank = agent_bank(self.agent_bank_size, seed=seed, style=self.agent_style,
                                   hard_start_fraction=self.hard_start_fraction, hard_start_x=self.hard_start_x,
                                   reactive_fraction=self.reactive_fraction, pause_fraction=self.pause_fraction,
                                   split=self.agent_split, behaviours=self.agent_behaviours,
                                   horizon=self.max_steps).to(self.device)
        return seed

    # ------------------------------------------------------------------ helpers
    HIST = 9  # ego history kept for the reactive agents' reaction time (up to 0.8 s)

    def _agent(self, idx: torch.Tensor, t: torch.Tensor):
        """Perceived ``[B, 6]`` and true ``[B, 4]`` agent state; reactive rows from their live arc length."""
        t = t.clamp(max=self.bank.horizon)
        i, k = idx.squeeze(-1), t.squeeze(-1)
        obs, true = self.bank.observed[i, k], self.bank.true[i, k]
        r = self.bank.reactive[i].nonzero().squeeze(-1)
        if not len(r):
            return obs, true
        prm, route = self.bank.params[i[r]], self.bank.behaviour[i[r]]
        s, va = self._state["s"][r], self._state["va"][r]
        arcs = torch.cat([s, s - va * self.dt], dim=-1)  # now and one step back (finite-difference velocity)
        pos = _path(route, arcs, prm[:, 0], prm[:, 2], torch.zeros_like(s[:, 0]), torch.ones_like(s[:, 0]))
        live = torch.cat([pos[:, 0], (pos[:, 0] - pos[:, 1]) / self.dt], dim=-1)
        obs, true = obs.clone(), true.clone()
        obs[r, :4] += live - true[r]  # live state plus the reference trajectory's perception error
        true[r] = live
        return obs, true

    def _obs_td(self, y, v, t, idx, accel, collision, success, oob, agent=None) -> TensorDict:
        obs_a, true_a = self._agent(idx, t) if agent is None else agent
        B = self.batch_size
        return TensorDict({
            "observation": torch.cat([y, v, obs_a], dim=-1),
            "collision": collision, "success": success, "out_of_bounds": oob, "step_count": t.clone(),
            "ego": {"pos": torch.cat([torch.full_like(y, EGO_X), y], -1), "accel": accel},
            "agent": {"true_pos": true_a[:, :2], "true_vel": true_a[:, 2:4],
                      "behaviour": self.bank.behaviour[idx.squeeze(-1)].unsqueeze(-1), "episode": idx.clone()},
        }, batch_size=B, device=self.device)

    def safety_cost(self, y: torch.Tensor, obs_agent: torch.Tensor) -> torch.Tensor:
        """``mu max(0, (2R + |sigma|)^2 - d^2)`` for ego ``y`` [B,1] and perceived agent [B,6]."""
        d2 = (EGO_X - obs_agent[:, 0:1]) ** 2 + (y - obs_agent[:, 1:2]) ** 2
        sig = obs_agent[:, 4:6].norm(dim=-1, keepdim=True)
        return self.mu * torch.clamp((2 * self.radius + sig) ** 2 - d2, min=0.0)

    # ------------------------------------------------------------------ reset / step
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        B = self.batch_size
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict["_reset"].reshape(*B, 1).to(self.device)
        else:
            mask = torch.ones(*B, 1, dtype=torch.bool, device=self.device)
        n = int(mask.sum())
        st = self._state
        if n:
            noise = (2 * torch.rand(n, 1, generator=self._rng) - 1).to(self.device) * self.start_noise
            if self.agent_sampling == "random":
                new_idx = torch.randint(len(self.bank), (n, 1), generator=self._rng).to(self.device)
            else:
                new_idx = (torch.arange(n, device=self.device).unsqueeze(-1) + self._seq) % len(self.bank)
                self._seq += n
            m = mask.squeeze(-1)
            st["y"] = st["y"].clone()
            st["v"] = st["v"].clone()
            st["t"] = st["t"].clone()
            st["idx"] = st["idx"].clone()
            st["y"][m] = self.y_start + noise
            st["v"][m] = 0.0
            if self.random_start_fraction > 0:  # exploring starts: somewhere along the ego's path, moving
                u = torch.rand(n, 3, generator=self._rng).to(self.device)
                pick = u[:, 0] < self.random_start_fraction
                (ylo, yhi), (vlo, vhi) = self.random_start_y, self.random_start_v
                st["y"][m] = torch.where(pick[:, None], ylo + (yhi - ylo) * u[:, 1:2], st["y"][m])
                st["v"][m] = torch.where(pick[:, None], vlo + (vhi - vlo) * u[:, 2:3], st["v"][m])
            st["t"][m] = 0
            st["idx"][m] = new_idx
            for k in ("s", "va", "timer", "hist"):
                st[k] = st[k].clone()
            st["s"][m] = 0.0
            st["va"][m] = self.bank.params[new_idx.squeeze(-1), -1:]  # v0 (reactive agents)
            st["timer"][m] = 0.0
            st["hist"][m] = torch.cat([st["y"][m], st["v"][m]], -1)[:, None].expand(-1, self.HIST, -1)
        f = torch.zeros(*B, 1, dtype=torch.bool, device=self.device)
        out = self._obs_td(st["y"], st["v"], st["t"], st["idx"], torch.zeros_like(st["y"]), f, f.clone(), f.clone())
        out.set("done", f.clone())
        out.set("terminated", f.clone())
        out.set("truncated", f.clone())
        return out

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        st = self._state
        a = tensordict["action"].reshape(*self.batch_size, 1).to(self.device).clamp(-self.a_max, self.a_max)
        y, v, t, idx = st["y"], st["v"], st["t"], st["idx"]
        v_new = (v + a * self.dt).clamp(self.v_min, self.v_max)
        y_new = y + 0.5 * (v + v_new) * self.dt
        a_exec = (v_new - v) / self.dt
        t_new = t + 1
        hist = torch.cat([torch.cat([y_new, v_new], -1)[:, None], st["hist"][:, :-1]], dim=1)
        i = idx.squeeze(-1)
        r = self.bank.reactive[i].nonzero().squeeze(-1)
        if len(r):  # reactive agents answer the ego as it was their reaction time ago
            ir = i[r]
            seen = hist[r, self.bank.params[ir, 4].long().clamp(0, self.HIST - 1)]
            out = reactive_step(self.bank.behaviour[ir], self.bank.params[ir], st["s"][r, 0], st["va"][r, 0],
                                st["timer"][r, 0], seen[:, 0], seen[:, 1], dt=self.dt)
            st = dict(st)
            for k, new in zip(("s", "va", "timer"), out):
                st[k] = st[k].clone()
                st[k][r, 0] = new
        self._state = dict(st, hist=hist)
        obs_a, true_a = self._agent(idx, t_new)
        d_true = torch.sqrt((EGO_X - true_a[:, 0:1]) ** 2 + (y_new - true_a[:, 1:2]) ** 2)
        collision = d_true < 2 * self.radius
        success = (y_new >= self.y_goal) & ~collision
        oob = ((y_new < self.y_min) | (y_new > self.y_max)) & ~collision & ~success
        terminated = collision | success | oob
        truncated = (t_new >= self.max_steps) & ~terminated
        reward = (self.w_prog * v_new * self.dt - self.w_time * self.dt
                  - self.w_speed * torch.clamp(v_new - self.v_limit, min=0.0) ** 2 - self.w_comf * a_exec**2
                  - self.w_reverse * torch.clamp(-v_new, min=0.0) * self.dt
                  + self.r_goal * success.float() - self.c_crash_reward * collision.float())
        cost = self.safety_cost(y_new, obs_a) + self.c_crash * collision.float()
        self._state.update(y=y_new, v=v_new, t=t_new, idx=idx)
        out = self._obs_td(y_new, v_new, t_new, idx, a_exec, collision, success, oob, agent=(obs_a, true_a))
        out.set("reward", reward)
        out.set("cost", cost)
        out.set("done", terminated | truncated)
        out.set("terminated", terminated)
        out.set("truncated", truncated)
        return out


__all__ = ["IntersectionEnv", "EGO_X", "ObservationFeatures", "relational_features"]
