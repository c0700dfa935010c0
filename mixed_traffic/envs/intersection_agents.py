"""Generative model of a human driver crossing the ego's path at an unsignalised intersection.

Geometry (metres, right-hand traffic, intersection box ``[-1.5, 1.5]^2``): the ego drives
north on the line ``x = 0.5``. The human-driven agent approaches from the east, westbound
on the lane ``y = +0.5``, and then

* ``straight``: keeps going west along ``y = 0.5`` (crosses the ego's line at ``(0.5, 0.5)``);
* ``left``: turns left (south) on an arc of radius 2 about ``(1.5, -1.5)`` into the
  southbound lane ``x = -0.5`` (crosses the ego's line at about ``(0.5, 0.23)``);
* ``right``: turns right (north) on an arc of radius 1 about ``(1.5, 1.5)`` and merges into
  the ego's lane ``x = 0.5`` ahead of it (enters the ego's line at ``(0.5, 1.5)``);
* ``zigzag`` (held out for out-of-distribution tests): goes west while weaving across its
  lane with a triangle wave of amplitude 0.25-0.45 m.

Longitudinal behaviour: a nominal speed with sinusoidal variation, optional *hesitation*
(slowing almost to a stop for a while before the box) and *yielding* (a full stop at the stop
line for a random wait), integrated with bounded acceleration. Perception: each axis carries
an EKF-like standard deviation (prediction grows it with speed, measurement updates shrink
it, measurements drop out in bursts), and the observed position/velocity are the true ones
plus AR(1) noise of that standard deviation.

Trajectories are open loop and pre-generated, so a fixed, seeded test set is identical for
every controller. Splits: ``"train"`` and ``"test"`` draw from the same distributions with
independent seed streams; ``zigzag`` is excluded from training by default.

>>> from mixed_traffic.envs.intersection_agents import sample_agent_trajectories
>>> bank = sample_agent_trajectories(8, seed=0, split="test", horizon=50)
>>> bank.observed.shape, bank.true.shape
(torch.Size([8, 51, 6]), torch.Size([8, 51, 4]))
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

Tensor = torch.Tensor

BEHAVIOURS = ("straight", "left", "right", "zigzag")
"""Agent route families; index in this tuple is the behaviour id (``recorded`` is 4)."""
RECORDED = 4
BEHAVIOUR_NAMES = BEHAVIOURS + ("recorded",)
TRAIN_BEHAVIOURS = ("straight", "left", "right")
DT = 0.1
LANE_Y = 0.5  # westbound lane of the agent
BOX = 1.5  # half width of the intersection box
STOP_LINE_X = 1.9  # agent's centre stops here when yielding (box edge + radius + margin)
EGO_LINE_X = 0.5  # the ego drives north on x = 0.5
STYLES = ("mixed", "plain", "stop_in_zone", "reactive", "pause")
#: columns of ``AgentTrajectories.params`` (reactive agents)
REACTIVE_PARAMS = ("x0", "v_nom", "offset", "assertiveness", "delay_steps", "go_speed", "patience", "speed_up", "v0")


@dataclass
class AgentModelParams:
    """Distributions of the agent model (uniform ranges ``(low, high)``).

    >>> p = AgentModelParams(speed=(0.6, 1.0))
    >>> p.speed
    (0.6, 1.0)
    """

    start_x: tuple[float, float] = (2.2, 5.5)  # start of the agent's centre, east of the box
    speed: tuple[float, float] = (0.5, 1.2)  # nominal speed (m/s)
    speed_variation: tuple[float, float] = (0.0, 0.2)  # relative amplitude of the sinusoid
    speed_period: tuple[float, float] = (2.0, 6.0)  # s
    accel_max: float = 1.0  # m/s^2, human comfort bound
    decel_max: float = 1.5
    p_hesitate: float = 0.25
    hesitate_duration: tuple[float, float] = (0.5, 2.5)  # s
    p_yield: float = 0.25
    yield_wait: tuple[float, float] = (0.5, 3.0)  # s at the stop line
    lane_offset_std: float = 0.05  # lateral offset of the driven line (m)
    zigzag_amplitude: tuple[float, float] = (0.25, 0.45)
    zigzag_wavelength: tuple[float, float] = (1.0, 2.0)
    meas_std: tuple[float, float] = (0.03, 0.10)  # measurement noise of the tracker (m)
    process_std: float = 0.08  # process noise (m per sqrt(s)) per m/s of speed, plus a floor
    p_dropout: float = 0.05  # chance per step that a measurement dropout burst starts
    dropout_len: tuple[float, float] = (0.3, 1.5)  # s
    sigma_range: tuple[float, float] = (0.02, 0.35)  # clamp of the reported sigma (m)
    noise_corr: float = 0.85  # AR(1) correlation of the position error per step
    # style="stop_in_zone": the agent stops with its centre just past the ego's line for stop_wait s
    stop_x: tuple[float, float] = (0.15, 0.45)
    stop_wait: tuple[float, float] = (2.0, 8.0)
    # style="pause" (training): one pause at an arc length drawn uniformly from the stop line to
    # pause_past m beyond the conflict point (the approach, the crossing and its exit), for pause_wait s
    pause_past: float = 1.2
    pause_wait: tuple[float, float] = (0.5, 10.0)
    # style="reactive" (reactive_step): how the agent answers the ego's motion
    assertiveness: tuple[float, float] = (0.0, 1.0)  # < 0.4 yields, < 0.7 hesitates, else speeds up
    reaction_time: tuple[float, float] = (0.2, 0.8)  # s: it sees the ego this late
    go_speed: tuple[float, float] = (0.3, 0.8)  # m/s: the ego speed it reads as "the ego is going"
    patience: tuple[float, float] = (1.0, 4.0)  # s a hesitating agent crawls before it goes anyway
    speed_up: tuple[float, float] = (1.3, 1.7)  # factor on the nominal speed when it tries to go first

    def validate(self) -> None:
        for name in ("start_x", "speed", "speed_variation", "speed_period", "hesitate_duration", "yield_wait",
                     "zigzag_amplitude", "zigzag_wavelength", "meas_std", "dropout_len", "sigma_range", "stop_x",
                     "stop_wait", "pause_wait", "assertiveness", "reaction_time", "go_speed", "patience", "speed_up"):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo <= hi):
                raise ValueError(f"{name}={(lo, hi)!r} is invalid; allowed: 0 <= low <= high, finite")
        if self.start_x[0] <= BOX:
            raise ValueError(f"start_x low={self.start_x[0]} is invalid; allowed: > {BOX} (outside the box)")
        for name in ("p_hesitate", "p_yield", "p_dropout", "noise_corr"):
            p = getattr(self, name)
            if not 0.0 <= p <= 1.0 or (name == "noise_corr" and p >= 1.0):
                raise ValueError(f"{name}={p!r} is invalid; allowed: [0, 1]" + (" exclusive of 1" if name == "noise_corr" else ""))
        if not (math.isfinite(self.pause_past) and self.pause_past >= 0):
            raise ValueError(f"pause_past={self.pause_past!r} is invalid; allowed: >= 0, finite")
        for name in ("accel_max", "decel_max"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name}={getattr(self, name)!r} is invalid; allowed: > 0")


@dataclass
class AgentTrajectories:
    """A bank of agent trajectories, all of ``horizon + 1`` samples at 0.1 s.

    Attributes:
        true: ``[N, T+1, 4]`` true ``x, y, vx, vy`` (for collision checks and rendering).
        observed: ``[N, T+1, 6]`` perceived ``x, y, vx, vy, sigma_x, sigma_y`` (the policy's view).
        behaviour: ``[N]`` int64 index into :data:`BEHAVIOUR_NAMES`.
        hesitate, yields: ``[N]`` bool style flags (False for recorded data).
        reactive: ``[N]`` bool: the agent reacts to the ego (:func:`reactive_step`); its ``true``
            is then only the open-loop reference and ``observed - true`` its perception error.
        params: ``[N, len(REACTIVE_PARAMS)]`` the reactive agent's parameters (zeros otherwise).
    """

    true: Tensor
    observed: Tensor
    behaviour: Tensor
    hesitate: Tensor
    yields: Tensor
    reactive: Tensor | None = None
    params: Tensor | None = None

    def __post_init__(self):
        n = self.true.shape[0]
        if self.reactive is None:
            self.reactive = torch.zeros(n, dtype=torch.bool, device=self.true.device)
        if self.params is None:
            self.params = torch.zeros(n, len(REACTIVE_PARAMS), device=self.true.device)

    def _fields(self):
        return (self.true, self.observed, self.behaviour, self.hesitate, self.yields, self.reactive, self.params)

    def __len__(self) -> int:
        return self.true.shape[0]

    @property
    def horizon(self) -> int:
        return self.true.shape[1] - 1

    def subset(self, idx) -> AgentTrajectories:
        return AgentTrajectories(*(t[idx] for t in self._fields()))

    def to(self, device) -> AgentTrajectories:
        return AgentTrajectories(*(t.to(device) for t in self._fields()))

    @staticmethod
    def cat(banks: list[AgentTrajectories]) -> AgentTrajectories:
        h = min(b.horizon for b in banks)
        return AgentTrajectories(
            torch.cat([b.true[:, : h + 1] for b in banks]), torch.cat([b.observed[:, : h + 1] for b in banks]),
            *(torch.cat([b._fields()[i] for b in banks]) for i in range(2, 7)))


def split_seed(seed: int, split: str) -> int:
    """Seed of the generator of one split; ``train`` and ``test`` never share a stream."""
    if split not in ("train", "test"):
        raise ValueError(f"split={split!r} is invalid; allowed: 'train', 'test'")
    if not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed={seed!r} is invalid; allowed: an integer >= 0")
    return (seed * 2 + (0 if split == "train" else 1)) * 1_000_003 + 17


def _uniform(gen: torch.Generator, n: int, rng: tuple[float, float]) -> Tensor:
    lo, hi = rng
    return lo + (hi - lo) * torch.rand(n, generator=gen, dtype=torch.float64)


def _path(route: Tensor, s: Tensor, x0: Tensor, offset: Tensor, zz_amp: Tensor, zz_len: Tensor) -> Tensor:
    """Position ``[N, T, 2]`` at arc length ``s`` ``[N, T]`` along each route."""
    x0 = x0[:, None]
    off = offset[:, None]
    lead = x0 - BOX  # straight run up to the box edge
    # straight (and zigzag): west along y = 0.5 + offset
    x_st = x0 - s
    y_st = torch.full_like(s, LANE_Y) + off
    tri = 2.0 * torch.abs(2.0 * torch.frac(s / zz_len[:, None] + 0.25) - 1.0) - 1.0  # triangle wave in [-1, 1]
    in_zz = (x_st < BOX + 0.5).to(s.dtype)  # weave from just before the box on
    y_zz = y_st + zz_amp[:, None] * tri * in_zz
    # left: arc radius 2 about (1.5, -1.5), then south along x = -0.5
    r_l = 2.0 - off  # offset keeps the driven line parallel
    u = (s - lead).clamp(min=0.0)
    th_l = (u / r_l).clamp(max=math.pi / 2)
    arc_l_len = r_l * math.pi / 2
    x_l = torch.where(s < lead, x_st, BOX - r_l * torch.sin(th_l))
    y_l = torch.where(s < lead, y_st, -BOX + r_l * torch.cos(th_l) - (u - arc_l_len).clamp(min=0.0))
    # right: arc radius 1 about (1.5, 1.5), then north along x = 0.5
    r_r = 1.0 + off
    th_r = (u / r_r).clamp(max=math.pi / 2)
    arc_r_len = r_r * math.pi / 2
    x_r = torch.where(s < lead, x_st, BOX - r_r * torch.sin(th_r))
    y_r = torch.where(s < lead, y_st, BOX - r_r * torch.cos(th_r) + (u - arc_r_len).clamp(min=0.0))
    r = route[:, None]
    x = torch.where(r == 1, x_l, torch.where(r == 2, x_r, x_st))
    y = torch.where(r == 1, y_l, torch.where(r == 2, y_r, torch.where(r == 3, y_zz, y_st)))
    return torch.stack([x, y], dim=-1)


def arc_to_x(route: Tensor, x: Tensor, x0: Tensor, offset: Tensor) -> Tensor:
    """Arc length at which a westbound (straight / zig-zag) or left-turning agent's centre reaches ``x``."""
    lead = x0 - BOX
    r_l = 2.0 - offset
    s_left = lead + r_l * torch.asin(((BOX - x) / r_l).clamp(-1.0, 1.0))
    return torch.where(route == 1, s_left, x0 - x)


def conflict_point(route: Tensor, x0: Tensor, offset: Tensor) -> tuple[Tensor, Tensor]:
    """``(arc length, ego y)`` where the agent's path meets the ego's line (right turners: the merge)."""
    lead = x0 - BOX
    r_l, r_r = 2.0 - offset, 1.0 + offset
    th = torch.asin((BOX - EGO_LINE_X) / r_l)
    s_c = torch.where(route == 1, lead + r_l * th, torch.where(route == 2, lead + r_r * math.pi / 2, x0 - EGO_LINE_X))
    y_c = torch.where(route == 1, -BOX + r_l * torch.cos(th), torch.where(route == 2, BOX + 0 * x0, LANE_Y + offset))
    return s_c, y_c


def sample_agent_trajectories(n: int, *, seed: int, split: str = "train", behaviours=None, horizon: int = 500,
                              params: AgentModelParams | None = None, style: str = "mixed") -> AgentTrajectories:
    """Sample ``n`` agent trajectories, behaviours spread evenly over ``behaviours``.

    Args:
        n: number of trajectories.
        seed: integer >= 0; with ``split`` it fixes the result exactly.
        split: ``"train"`` or ``"test"`` (independent streams).
        behaviours: names from :data:`BEHAVIOURS`; default: ``TRAIN_BEHAVIOURS`` for train,
            all four for test.
        horizon: number of 0.1 s steps (the trajectory has ``horizon + 1`` samples).
        style: ``"mixed"`` (hesitation/yielding at their probabilities), ``"plain"`` (neither),
            ``"stop_in_zone"`` (every agent stops with its centre just past the ego's line for
            ``stop_wait`` s; straight and left routes only; a held-out test style),
            ``"reactive"`` (the agent answers the ego's motion in the env, :func:`reactive_step`;
            the trajectory is its open-loop reference and carries its perception error) or
            ``"pause"`` (a training style: hesitation as in ``mixed``, and every agent pauses once
            for ``pause_wait`` s at an arc length uniform from its stop line to ``pause_past`` m
            beyond the point where its path meets the ego's line, so on the approach, inside the
            crossing or on its way out; any route).

    >>> b = sample_agent_trajectories(6, seed=1, behaviours=["left", "right"], horizon=10)
    >>> b.behaviour.tolist()
    [1, 2, 1, 2, 1, 2]
    """
    p = params or AgentModelParams()
    p.validate()
    if not isinstance(n, int) or n < 1:
        raise ValueError(f"n={n!r} is invalid; allowed: an integer >= 1")
    if not isinstance(horizon, int) or horizon < 1:
        raise ValueError(f"horizon={horizon!r} is invalid; allowed: an integer >= 1")
    if style not in STYLES:
        raise ValueError(f"style={style!r} is invalid; allowed: {list(STYLES)}")
    if behaviours is None:
        behaviours = TRAIN_BEHAVIOURS if split == "train" else BEHAVIOURS
    behaviours = list(behaviours)
    bad = [b for b in behaviours if b not in BEHAVIOURS]
    if style == "stop_in_zone":
        bad += [b for b in behaviours if b not in ("straight", "left")]
    if bad or not behaviours:
        raise ValueError(f"behaviours={behaviours!r} is invalid; allowed: a non-empty subset of {list(BEHAVIOURS)}")
    gen = torch.Generator().manual_seed(split_seed(seed, split))
    T = horizon + 1
    route = torch.tensor([BEHAVIOURS.index(behaviours[i % len(behaviours)]) for i in range(n)], dtype=torch.long)

    x0 = _uniform(gen, n, p.start_x)
    v_nom = _uniform(gen, n, p.speed)
    v_amp = _uniform(gen, n, p.speed_variation)
    v_per = _uniform(gen, n, p.speed_period)
    v_phase = _uniform(gen, n, (0.0, 2 * math.pi))
    mixed = style == "mixed"
    hes = (torch.rand(n, generator=gen) < p.p_hesitate) & (mixed or style == "pause")
    yld = (torch.rand(n, generator=gen) < p.p_yield) & mixed
    # hesitation starts somewhere on the approach (before reaching the box) and lasts a while
    hes_t0 = _uniform(gen, n, (0.0, 1.0)) * ((x0 - BOX) / v_nom)
    hes_dur = _uniform(gen, n, p.hesitate_duration)
    hes_speed = _uniform(gen, n, (0.0, 0.3)) * v_nom
    wait = _uniform(gen, n, p.yield_wait)
    offset = p.lane_offset_std * torch.randn(n, generator=gen, dtype=torch.float64)
    zz_amp = _uniform(gen, n, p.zigzag_amplitude)
    zz_len = _uniform(gen, n, p.zigzag_wavelength)
    v0 = v_nom * _uniform(gen, n, (0.7, 1.0))
    if style == "stop_in_zone":  # every agent stops on the ego's line (its centre just past it), then goes on
        yld = torch.ones(n, dtype=torch.bool)
        hes = torch.zeros(n, dtype=torch.bool)
        stop_at = arc_to_x(route, _uniform(gen, n, p.stop_x), x0, offset)
        wait = _uniform(gen, n, p.stop_wait)
    if style == "pause":  # one pause anywhere from the stop line to beyond the crossing, then on
        yld = torch.ones(n, dtype=torch.bool)
        s_c, _ = conflict_point(route, x0, offset)
        lo = x0 - STOP_LINE_X
        stop_at = lo + (s_c + p.pause_past - lo) * _uniform(gen, n, (0.0, 1.0))
        wait = _uniform(gen, n, p.pause_wait)
    reactive = style == "reactive"
    if reactive:  # the env simulates the longitudinal motion; the reference below is plain
        hes = torch.zeros(n, dtype=torch.bool)
        yld = torch.zeros(n, dtype=torch.bool)
        react = torch.stack([x0, v_nom, offset, _uniform(gen, n, p.assertiveness),
                             torch.round(_uniform(gen, n, p.reaction_time) / DT), _uniform(gen, n, p.go_speed),
                             _uniform(gen, n, p.patience), _uniform(gen, n, p.speed_up), v0], dim=-1).float()

    # longitudinal simulation along the path
    s_stop = stop_at if style in ("stop_in_zone", "pause") else x0 - STOP_LINE_X  # arc length to where it stops
    s = torch.zeros(n, dtype=torch.float64)
    v = v0.clone()
    waited = torch.zeros(n, dtype=torch.float64)
    released = ~yld | (s_stop <= 0.1)
    s_hist = torch.empty(n, T, dtype=torch.float64)
    for k in range(T):
        s_hist[:, k] = s
        t = k * DT
        v_des = v_nom * (1 + v_amp * torch.sin(2 * math.pi * t / v_per + v_phase))
        in_hes = hes & (t >= hes_t0) & (t < hes_t0 + hes_dur)
        v_des = torch.where(in_hes, hes_speed, v_des)
        # yielding: brake to stop at the stop line, wait, then go
        dist = (s_stop - s).clamp(min=0.0)
        v_stop = torch.sqrt(2 * 0.8 * p.decel_max * dist)
        holding = ~released
        v_des = torch.where(holding, torch.minimum(v_des, v_stop), v_des)
        at_line = holding & (dist < 0.05) & (v < 0.05)
        waited = waited + at_line.to(waited.dtype) * DT
        released = released | (waited >= wait)
        a = ((v_des - v) / 0.5).clamp(-p.decel_max, p.accel_max)
        v_new = (v + a * DT).clamp(min=0.0)
        s_new = s + 0.5 * (v + v_new) * DT
        over = holding & (s_new > s_stop)
        s = torch.where(over, torch.maximum(s, s_stop), s_new)
        v = torch.where(over, torch.zeros_like(v_new), v_new)

    pos = _path(route, s_hist, x0, offset, zz_amp, zz_len)  # [n, T, 2]
    vel = torch.zeros_like(pos)
    vel[:, 1:-1] = (pos[:, 2:] - pos[:, :-2]) / (2 * DT)
    vel[:, 0] = (pos[:, 1] - pos[:, 0]) / DT
    vel[:, -1] = (pos[:, -1] - pos[:, -2]) / DT
    true = torch.cat([pos, vel], dim=-1)

    # perception: EKF-like sigma per axis, AR(1) errors of that sigma
    meas = _uniform(gen, n, p.meas_std)
    speed = vel.norm(dim=-1)
    P = (meas**2)[:, None].repeat(1, 2)
    err = torch.zeros(n, 2, dtype=torch.float64)
    verr = torch.zeros(n, 2, dtype=torch.float64)
    drop_left = torch.zeros(n, dtype=torch.float64)
    sig = torch.empty(n, T, 2, dtype=torch.float64)
    errs = torch.empty(n, T, 2, dtype=torch.float64)
    verrs = torch.empty(n, T, 2, dtype=torch.float64)
    lo, hi = p.sigma_range
    rho = p.noise_corr
    for k in range(T):
        # predict: process noise grows with speed; the along-track axis (x for the approach) more
        q = (p.process_std**2) * DT * (0.3 + speed[:, k]) ** 2
        P = P + q[:, None] * torch.tensor([1.5, 1.0], dtype=torch.float64)
        start = (torch.rand(n, generator=gen) < p.p_dropout) & (drop_left <= 0)
        drop_left = torch.where(start, _uniform(gen, n, p.dropout_len), drop_left)
        measured = drop_left <= 0
        R = (meas**2)[:, None]
        P = torch.where(measured[:, None], P * R / (P + R), P)
        drop_left = drop_left - DT
        sk = P.sqrt().clamp(lo, hi)
        sig[:, k] = sk
        err = rho * err + math.sqrt(1 - rho**2) * sk * torch.randn(n, 2, generator=gen, dtype=torch.float64)
        verr = rho * verr + math.sqrt(1 - rho**2) * 0.5 * sk * torch.randn(n, 2, generator=gen, dtype=torch.float64)
        errs[:, k] = err
        verrs[:, k] = verr
    observed = torch.cat([pos + errs, vel + verrs, sig], dim=-1)
    out = AgentTrajectories(true.float(), observed.float(), route, hes, yld)
    if reactive:
        out.reactive[:] = True
        out.params = react
    return out


def reactive_step(route: Tensor, params: Tensor, s: Tensor, v: Tensor, timer: Tensor, ego_y: Tensor, ego_v: Tensor,
                  *, accel_max: float = 1.0, decel_max: float = 1.5, dt: float = DT) -> tuple[Tensor, Tensor, Tensor]:
    """One step of the interaction-aware human driver; returns ``(s, v, timer)`` after ``dt``.

    The agent sees the ego's position ``ego_y`` and speed ``ego_v`` as they were its reaction
    time ago (the caller passes the delayed values). While neither has passed the conflict
    point (where its path meets the ego's line) and the ego is moving (``ego_v > go_speed``),
    it answers according to its assertiveness ``a``:

    * ``a < 0.4`` **yields**: brakes to stop at the stop line (or at once, if past it) and
      waits until the ego has crossed or stops again;
    * ``0.4 <= a < 0.7`` **hesitates**: crawls at 30% of its speed for ``patience`` s, then
      goes on whatever the ego does;
    * ``a >= 0.7`` **speeds up** to ``speed_up`` times its nominal speed, to pass first.

    A stopped or slow ego is read as an invitation: the agent **goes** at its nominal speed.
    Every agent brakes hard when the ego is inside the conflict zone ahead of it and it could
    not otherwise stop before it (a human avoids an imminent crash, late by its reaction time).
    All tensors ``[n]``; ``params`` ``[n, len(REACTIVE_PARAMS)]``.
    """
    x0, v_nom, off, assertive, _, go_speed, patience, speed_up, _ = params.unbind(-1)
    s_c, y_c = conflict_point(route, x0, off)
    d_a, d_e = s_c - s, y_c - ego_y
    open_road = (d_a < -0.8) | (d_e < -0.8)  # one of them is past the conflict point
    ego_going = (ego_v > go_speed) & ~open_road
    yields, hesitates = ego_going & (assertive < 0.4), ego_going & (assertive >= 0.4) & (assertive < 0.7)
    hesitates = hesitates & (timer < patience)
    s_stop = x0 - STOP_LINE_X
    v_stop = torch.sqrt(2 * 0.8 * decel_max * (s_stop - s).clamp(min=0.0))
    v_des = torch.where(ego_going & (assertive >= 0.7), speed_up * v_nom, v_nom)
    v_des = torch.where(hesitates, 0.3 * v_nom, v_des)
    v_des = torch.where(yields, torch.minimum(v_nom, v_stop), v_des)
    a = ((v_des - v) / 0.5).clamp(-decel_max, accel_max)
    # imminent conflict: the ego occupies the crossing ahead of the agent, which could not stop before it
    brake_dist = v**2 / (2 * decel_max) + 0.75
    danger = (d_e.abs() < 0.75) & (d_a > 0) & (d_a < brake_dist + 0.5)
    a = torch.where(danger, torch.full_like(a, -2.0 * decel_max), a)
    v_new = (v + a * dt).clamp(min=0.0)
    s_new = s + 0.5 * (v + v_new) * dt
    timer = timer + dt * (ego_going & (assertive >= 0.4) & (assertive < 0.7)).to(timer.dtype)
    return s_new, v_new, timer


def make_test_set(n_per_behaviour: int = 80, *, seed: int = 2024, horizon: int = 500,
                  behaviours=BEHAVIOURS, style: str = "mixed") -> AgentTrajectories:
    """The fixed test set: ``n_per_behaviour`` episodes of each behaviour (default 4 x 80 = 320).

    ``style="reactive"`` / ``"stop_in_zone"`` give the held-out sets of reactive agents and of
    agents that stop on the ego's line (see :func:`sample_agent_trajectories`).

    >>> ts = make_test_set(2, horizon=20)
    >>> ts.behaviour.tolist()
    [0, 1, 2, 3, 0, 1, 2, 3]
    """
    return sample_agent_trajectories(n_per_behaviour * len(behaviours), seed=seed, split="test",
                                     behaviours=behaviours, horizon=horizon, style=style)


def load_recorded_trajectories(path_or_array, *, horizon: int = 500, routes=None) -> AgentTrajectories:
    """Load recorded agent trajectories from a ``.npy`` (or an array) of rows at 0.1 s.

    Rows are ``[x, y, vx, vy, sx, sy]`` (the perceived state; it is then also taken as the
    truth) or ``[x, y, vx, vy, sx, sy, ex, ey]`` with the perception error of the position
    (perceived minus true), so collisions use the true position ``(x - ex, y - ey)``.
    Layouts: ``[T, C]`` (one trajectory), ``[N, T, C]``, a list / object array of ``[T_i, C]``,
    or a pickled dict ``{"trajectories": ..., "routes": [...]}``. ``routes`` (or the dict's)
    labels each trajectory with a name of :data:`BEHAVIOURS` so per-route tables keep it;
    without labels every trajectory is ``recorded``. Short trajectories continue at their
    last velocity; long ones are cut.

    >>> import numpy as np
    >>> rows = np.zeros((30, 8)); rows[:, 0] = np.linspace(3, 0, 30); rows[:, 1] = 0.5
    >>> rows[:, 2] = -1.0; rows[:, 4:6] = 0.05; rows[:, 6] = 0.1
    >>> b = load_recorded_trajectories(rows, horizon=40, routes=["straight"])
    >>> b.true.shape, round(float(b.observed[0, 0, 0] - b.true[0, 0, 0]), 3), b.behaviour.tolist()
    (torch.Size([1, 41, 4]), 0.1, [0])
    """
    where = "array"
    if isinstance(path_or_array, (str, Path)):
        where = str(path_or_array)
        p = Path(path_or_array)
        if not p.exists():
            raise FileNotFoundError(f"recorded trajectories: no file at {where}")
        try:
            data = np.load(p, allow_pickle=True)
        except Exception as e:  # noqa: BLE001 - re-raise with the file named
            raise ValueError(f"recorded trajectories {where}: not a readable .npy file ({e})") from e
    else:
        data = path_or_array
    if isinstance(data, np.ndarray) and data.dtype == object and data.ndim == 0:
        data = data.item()
    if isinstance(data, dict):
        if "trajectories" not in data:
            raise ValueError(f"recorded trajectories {where}: a dict needs the key 'trajectories' (and 'routes')")
        routes = data.get("routes", routes)
        data = data["trajectories"]
    if isinstance(data, np.ndarray) and data.dtype != object and data.ndim == 2:
        trajs = [data]
    elif isinstance(data, np.ndarray) and data.dtype != object and data.ndim == 3:
        trajs = list(data)
    elif isinstance(data, (list, tuple)) or (isinstance(data, np.ndarray) and data.dtype == object):
        trajs = [np.asarray(t, dtype=np.float64) for t in list(data)]
    else:
        raise ValueError(f"recorded trajectories {where}: shape {getattr(data, 'shape', None)} is invalid; "
                         "allowed: [T, 6], [N, T, 6] or a list of [T_i, 6] arrays (8 columns with the error)")
    if not trajs:
        raise ValueError(f"recorded trajectories {where}: contains no trajectory")
    if not isinstance(horizon, int) or horizon < 1:
        raise ValueError(f"horizon={horizon!r} is invalid; allowed: an integer >= 1")
    if routes is not None:
        routes = list(routes)
        bad = [r for r in routes if r not in BEHAVIOURS]
        if len(routes) != len(trajs) or bad:
            raise ValueError(f"recorded trajectories {where}: routes={routes[:5]!r}... is invalid; allowed: one name "
                             f"of {list(BEHAVIOURS)} per trajectory ({len(trajs)})")
    T = horizon + 1
    names = ["x", "y", "vx", "vy", "sigma_x", "sigma_y", "error_x", "error_y"]
    out = []
    for i, t in enumerate(trajs):
        t = np.asarray(t, dtype=np.float64)
        if t.ndim != 2 or t.shape[1] not in (6, 8):
            raise ValueError(f"recorded trajectories {where}: trajectory {i} has shape {t.shape}; "
                             "allowed: [T, 6] rows of x, y, vx, vy, sigma_x, sigma_y (+ error_x, error_y)")
        if t.shape[0] < 2:
            raise ValueError(f"recorded trajectories {where}: trajectory {i} has {t.shape[0]} rows; allowed: >= 2")
        if not np.isfinite(t).all():
            r, c = np.argwhere(~np.isfinite(t))[0]
            raise ValueError(f"recorded trajectories {where}: trajectory {i} row {r} column {names[c]} is not finite")
        if (t[:, 4:6] < 0).any():
            r, c = np.argwhere(t[:, 4:6] < 0)[0]
            raise ValueError(f"recorded trajectories {where}: trajectory {i} row {r} "
                             f"{['sigma_x', 'sigma_y'][c]}={t[r, 4 + c]} is invalid; allowed: >= 0")
        if t.shape[1] == 6:
            t = np.concatenate([t, np.zeros((t.shape[0], 2))], axis=1)
        if t.shape[0] < T:
            k = np.arange(1, T - t.shape[0] + 1)[:, None] * DT
            ext = np.concatenate([t[-1, :2] + k * t[-1, 2:4], np.repeat(t[-1:, 2:], len(k), 0)], axis=1)
            t = np.concatenate([t, ext], axis=0)
        out.append(t[:T])
    arr = torch.tensor(np.stack(out), dtype=torch.float32)
    n = arr.shape[0]
    true = torch.cat([arr[..., :2] - arr[..., 6:8], arr[..., 2:4]], dim=-1)
    behaviour = (torch.tensor([BEHAVIOURS.index(r) for r in routes]) if routes is not None
                 else torch.full((n,), RECORDED, dtype=torch.long))
    false = torch.zeros(n, dtype=torch.bool)
    return AgentTrajectories(true, arr[..., :6].clone(), behaviour, false, false.clone())


__all__ = ["AgentModelParams", "AgentTrajectories", "BEHAVIOURS", "BEHAVIOUR_NAMES", "TRAIN_BEHAVIOURS",
           "STYLES", "REACTIVE_PARAMS", "reactive_step", "conflict_point", "arc_to_x",
           "sample_agent_trajectories", "make_test_set", "load_recorded_trajectories", "split_seed"]
