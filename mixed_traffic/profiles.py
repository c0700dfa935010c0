"""Head-vehicle speed profiles.

A profile is a small frozen dataclass with two pure methods:

- ``sample(batch, generator)`` draws the random parameters of ``batch`` episodes
  (a ``[batch, k]`` tensor; deterministic profiles return ``[batch, 0]``);
- ``speed(t, params)`` gives the target speed (m/s) at times ``t`` (``[batch]``, s).

The same objects drive the torch simulator, the SUMO backend and the evaluation
harness, so a profile means the same thing everywhere.

>>> import torch
>>> from mixed_traffic.profiles import make_profile
>>> prof = make_profile("deeplcc_brake")
>>> p = prof.sample(1, torch.Generator().manual_seed(0))
>>> [round(float(prof.speed(torch.tensor([t]), p)), 2) for t in (0.0, 2.0, 7.0, 12.0)]
[15.0, 5.0, 5.0, 15.0]
"""

from __future__ import annotations

import functools
import inspect
import math
from dataclasses import dataclass, field, fields

import torch

Tensor = torch.Tensor


def _interp(t: Tensor, knots_t: Tensor, knots_v: Tensor) -> Tensor:
    """Piecewise-linear interpolation, held constant outside the knots (batched v)."""
    t = t.clamp(float(knots_t[0]), float(knots_t[-1]))
    idx = torch.searchsorted(knots_t, t.contiguous(), right=True).clamp(1, len(knots_t) - 1)
    t0, t1 = knots_t[idx - 1], knots_t[idx]
    if knots_v.dim() == 1:
        v0, v1 = knots_v[idx - 1], knots_v[idx]
    else:
        v0 = knots_v.gather(-1, (idx - 1).unsqueeze(-1)).squeeze(-1)
        v1 = knots_v.gather(-1, idx.unsqueeze(-1)).squeeze(-1)
    w = ((t - t0) / (t1 - t0)).clamp(0.0, 1.0)
    return v0 + w * (v1 - v0)


@dataclass(frozen=True)
class Constant:
    """Constant speed ``v``."""

    v: float = 15.0

    def sample(self, batch: int, generator: torch.Generator | None = None) -> Tensor:
        return torch.zeros(batch, 0)

    def speed(self, t: Tensor, params: Tensor) -> Tensor:
        return torch.full_like(t, self.v)


@dataclass(frozen=True)
class RandomSteps:
    """Speed redrawn from U[v_low, v_high] every ``period`` seconds (the ring seed).

    The first segment starts at ``v_init`` when given (the ring starts every car at
    10 m/s), otherwise it is random too.
    """

    v_low: float = 5.0
    v_high: float = 20.0
    period: float = 15.0
    horizon: float = 500.0
    v_init: float | None = None

    def sample(self, batch: int, generator: torch.Generator | None = None) -> Tensor:
        n = int(math.ceil(self.horizon / self.period)) + 1
        v = self.v_low + (self.v_high - self.v_low) * torch.rand(batch, n, generator=generator)
        if self.v_init is not None:
            v[:, 0] = self.v_init
        return v

    def speed(self, t: Tensor, params: Tensor) -> Tensor:
        idx = (t / self.period).floor().long().clamp(0, params.shape[-1] - 1)
        return params.gather(-1, idx.unsqueeze(-1)).squeeze(-1)


@dataclass(frozen=True)
class RandomRamps:
    """Random holds and ramps: a broad training distribution of head behaviour.

    The head holds its speed for U[hold_min, hold_max] s, then changes to a new speed
    drawn from U[v_low, v_high] at a rate drawn from U[rate_min, rate_max] m/s^2 (the
    head's own bounds clip what it can do), and so on. Short holds and fast rates give
    steps and hard braking, long ramps slow drifts; the first speed is ``v_init`` when
    given. Parameters per episode: ``[t_0 .. t_K, v_0 .. v_K]`` knots.
    """

    v_low: float = 2.0
    v_high: float = 20.0
    hold_min: float = 3.0
    hold_max: float = 20.0
    rate_min: float = 0.5
    rate_max: float = 3.0
    horizon: float = 500.0
    v_init: float | None = None

    def __post_init__(self):
        if not 0 <= self.v_low <= self.v_high:
            raise ValueError(f"random_ramps: v_low={self.v_low}, v_high={self.v_high} are invalid; "
                             "allowed: 0 <= v_low <= v_high")
        if not 0 < self.hold_min <= self.hold_max:
            raise ValueError(f"random_ramps: hold_min={self.hold_min}, hold_max={self.hold_max} are invalid; "
                             "allowed: 0 < hold_min <= hold_max")
        if not 0 < self.rate_min <= self.rate_max:
            raise ValueError(f"random_ramps: rate_min={self.rate_min}, rate_max={self.rate_max} are invalid; "
                             "allowed: 0 < rate_min <= rate_max")

    def sample(self, batch: int, generator: torch.Generator | None = None) -> Tensor:
        n = int(math.ceil(self.horizon / self.hold_min)) + 1  # segments
        v = self.v_low + (self.v_high - self.v_low) * torch.rand(batch, n + 1, generator=generator)
        if self.v_init is not None:
            v[:, 0] = self.v_init
        hold = self.hold_min + (self.hold_max - self.hold_min) * torch.rand(batch, n, generator=generator)
        rate = self.rate_min + (self.rate_max - self.rate_min) * torch.rand(batch, n, generator=generator)
        ramp = (v[:, 1:] - v[:, :-1]).abs() / rate
        # knots: 0, end of hold 0, end of ramp 0, end of hold 1, ...
        durations = torch.stack([hold, ramp], dim=-1).flatten(1)
        times = torch.cat([torch.zeros(batch, 1), torch.cumsum(durations, dim=1)], dim=1)
        speeds = torch.cat([v[:, :1], torch.stack([v[:, :-1], v[:, 1:]], dim=-1).flatten(1)], dim=1)
        return torch.cat([times, speeds], dim=1)

    def speed(self, t: Tensor, params: Tensor) -> Tensor:
        return _knot_speed(t, params)


def _knot_speed(t: Tensor, params: Tensor) -> Tensor:
    """The speed at ``t`` (``[batch]``) through per-episode knots ``params`` (``[batch, 2K]``: ``t_0 .. t_K-1,
    v_0 .. v_K-1``), linear between them and held after the last: the drawn profiles' (:class:`RandomRamps`,
    :class:`RandomStopAndGo`)."""
    k = params.shape[-1] // 2
    times, speeds = params[..., :k].to(t.dtype), params[..., k:].to(t.dtype)
    tt = torch.minimum(t, times[..., -1]).unsqueeze(-1)
    idx = torch.searchsorted(times.contiguous(), tt.contiguous(), right=True).clamp(1, k - 1)
    t0, t1 = times.gather(-1, idx - 1), times.gather(-1, idx)
    v0, v1 = speeds.gather(-1, idx - 1), speeds.gather(-1, idx)
    w = ((tt - t0) / (t1 - t0).clamp_min(1e-9)).clamp(0.0, 1.0)
    return (v0 + w * (v1 - v0)).squeeze(-1)


@dataclass(frozen=True)
class RandomStopAndGo:
    """Stop-and-go with every part drawn per episode: the head holds a speed from U[v_low, v_high] for
    U[hold_min, hold_max] s, brakes to a standstill at U[rate_min, rate_max] m/s^2, stands U[stop_min, stop_max] s,
    drives off at a rate from the same range to the next speed, and so on (the head's own bounds clip what it can
    do). The first speed is ``v_init`` when given. Unlike a fixed stop-and-go profile (``piecewise``), each
    evaluation seed draws other stops, so a seed that tunes a rule and one that tests it see different episodes.
    Parameters per episode: ``[t_0 .. t_K, v_0 .. v_K]`` knots, as :class:`RandomRamps`.

        >>> import torch
        >>> p = RandomStopAndGo(v_low=10.0, v_high=10.0, hold_min=5.0, hold_max=5.0, stop_min=2.0, stop_max=2.0,
        ...                     rate_min=2.0, rate_max=2.0, horizon=20.0)
        >>> knots = p.sample(1)
        >>> [float(p.speed(torch.tensor([t]), knots)) for t in (0.0, 5.0, 7.5, 10.0, 11.0, 12.0, 14.5)]
        [10.0, 10.0, 5.0, 0.0, 0.0, 0.0, 5.0]
    """

    v_low: float = 8.0
    v_high: float = 16.0
    hold_min: float = 6.0
    hold_max: float = 15.0
    stop_min: float = 3.0
    stop_max: float = 10.0
    rate_min: float = 1.5
    rate_max: float = 2.5
    horizon: float = 500.0
    v_init: float | None = None

    def __post_init__(self):
        for lo, hi, names in ((self.v_low, self.v_high, ("v_low", "v_high")),
                              (self.hold_min, self.hold_max, ("hold_min", "hold_max")),
                              (self.stop_min, self.stop_max, ("stop_min", "stop_max")),
                              (self.rate_min, self.rate_max, ("rate_min", "rate_max"))):
            if not 0 < lo <= hi:
                raise ValueError(f"random_stop_and_go: {names[0]}={lo}, {names[1]}={hi} are invalid; allowed: "
                                 f"0 < {names[0]} <= {names[1]}")

    def sample(self, batch: int, generator: torch.Generator | None = None) -> Tensor:
        n = int(math.ceil(self.horizon / (self.hold_min + self.stop_min))) + 1  # cycles: hold, brake, stand, drive off

        def draw(lo, hi, k):
            return lo + (hi - lo) * torch.rand(batch, k, generator=generator)

        v = draw(self.v_low, self.v_high, n + 1)
        if self.v_init is not None:
            v[:, 0] = self.v_init
        hold, stand = draw(self.hold_min, self.hold_max, n), draw(self.stop_min, self.stop_max, n)
        brake, drive = draw(self.rate_min, self.rate_max, n), draw(self.rate_min, self.rate_max, n)
        # knots per cycle k: end of hold (v_k), standstill (0), end of the stand (0), at speed v_{k+1}
        durations = torch.stack([hold, v[:, :-1] / brake, stand, v[:, 1:] / drive], dim=-1).flatten(1)
        times = torch.cat([torch.zeros(batch, 1), torch.cumsum(durations, dim=1)], dim=1)
        zeros = torch.zeros_like(hold)
        speeds = torch.cat([v[:, :1], torch.stack([v[:, :-1], zeros, zeros, v[:, 1:]], dim=-1).flatten(1)], dim=1)
        return torch.cat([times, speeds], dim=1)

    def speed(self, t: Tensor, params: Tensor) -> Tensor:
        return _knot_speed(t, params)


@dataclass(frozen=True)
class RandomPerturbation:
    """Persistent random perturbation around ``v_star`` of amplitude ``amplitude``.

    Knots U[v* - A, v* + A] every ``period`` seconds, linearly interpolated (the
    DeeP-LCC dataset's ±1/±3/±5 m/s scenarios). ``period`` equal to the time step
    gives white noise on the target speed.
    """

    v_star: float = 15.0
    amplitude: float = 1.0
    period: float = 1.0
    horizon: float = 500.0

    def sample(self, batch: int, generator: torch.Generator | None = None) -> Tensor:
        n = int(math.ceil(self.horizon / self.period)) + 2
        u = torch.rand(batch, n, generator=generator) * 2.0 - 1.0
        u[:, 0] = 0.0  # start at the equilibrium speed
        return self.v_star + self.amplitude * u

    def speed(self, t: Tensor, params: Tensor) -> Tensor:
        knots = torch.arange(params.shape[-1], dtype=t.dtype) * self.period
        return _interp(t, knots, params)


@dataclass(frozen=True)
class Sine:
    """``v_star + amplitude * sin(2 pi t / period)``."""

    v_star: float = 15.0
    amplitude: float = 5.0
    period: float = 10.0

    def sample(self, batch: int, generator: torch.Generator | None = None) -> Tensor:
        return torch.zeros(batch, 0)

    def speed(self, t: Tensor, params: Tensor) -> Tensor:
        return self.v_star + self.amplitude * torch.sin(2.0 * math.pi * t / self.period)


@dataclass(frozen=True)
class RandomSine:
    """A smooth head: ``c + A sin(2 pi t / P + phi)`` with every part drawn per episode.

    ``A`` from U[amplitude_min, amplitude_max], ``P`` from U[period_min, period_max], ``phi`` from U[0, 2 pi) and
    the centre ``c`` from U[v_low + A, v_high - A], so the head stays within [v_low, v_high]. It complements
    :class:`RandomRamps`, whose heads hold and ramp: here the head's acceleration changes all the time. Parameters
    per episode: ``[c, A, P, phi]``.

        >>> import torch
        >>> p = RandomSine(v_low=5.0, v_high=15.0, amplitude_min=5.0, amplitude_max=5.0, period_min=20.0,
        ...                period_max=20.0)
        >>> knots = p.sample(1, torch.Generator().manual_seed(0))
        >>> float(knots[0, 0]), float(knots[0, 1])
        (10.0, 5.0)
    """

    v_low: float = 2.0
    v_high: float = 20.0
    amplitude_min: float = 1.0
    amplitude_max: float = 6.0
    period_min: float = 20.0
    period_max: float = 80.0
    horizon: float = 500.0  # unused: a sine needs no knots (accepted as the drawn profiles' common argument)

    def __post_init__(self):
        if not 0 <= self.v_low <= self.v_high:
            raise ValueError(f"random_sine: v_low={self.v_low}, v_high={self.v_high} are invalid; "
                             "allowed: 0 <= v_low <= v_high")
        if not 0 <= self.amplitude_min <= self.amplitude_max <= (self.v_high - self.v_low) / 2:
            raise ValueError(f"random_sine: amplitude_min={self.amplitude_min}, amplitude_max={self.amplitude_max} "
                             f"are invalid; allowed: 0 <= amplitude_min <= amplitude_max <= (v_high - v_low) / 2 "
                             f"= {(self.v_high - self.v_low) / 2}")
        if not 0 < self.period_min <= self.period_max:
            raise ValueError(f"random_sine: period_min={self.period_min}, period_max={self.period_max} are invalid; "
                             "allowed: 0 < period_min <= period_max")

    def sample(self, batch: int, generator: torch.Generator | None = None) -> Tensor:
        u = torch.rand(batch, 4, generator=generator)
        amp = self.amplitude_min + (self.amplitude_max - self.amplitude_min) * u[:, 1]
        centre = self.v_low + amp + (self.v_high - self.v_low - 2 * amp) * u[:, 0]
        period = self.period_min + (self.period_max - self.period_min) * u[:, 2]
        return torch.stack([centre, amp, period, 2.0 * math.pi * u[:, 3]], dim=-1)

    def speed(self, t: Tensor, params: Tensor) -> Tensor:
        c, a, p, phi = (params[..., i].to(t.dtype) for i in range(4))
        return c + a * torch.sin(2.0 * math.pi * t / p + phi)


@dataclass(frozen=True)
class RandomMix:
    """Each episode follows one of several drawn profiles, picked at random per episode.

    ``parts`` maps a profile name of :data:`PROFILES` to its arguments; ``weights`` (one per part, default equal)
    are the odds of each. A training distribution that holds several kinds of head, e.g. holds and ramps
    (``random_ramps``) beside smooth oscillations (``random_sine``). Unlike :class:`RowProfiles`, which fixes a
    row's part, the part is redrawn at every reset. Parameters per episode: ``[part index, part params...]``,
    padded to the widest part.

        >>> import torch
        >>> mix = RandomMix(parts={"constant": {"v": 10.0}, "sine": {"v_star": 20.0, "amplitude": 0.0}})
        >>> sorted(set(mix.speed(torch.zeros(64), mix.sample(64, torch.Generator().manual_seed(0))).tolist()))
        [10.0, 20.0]
    """

    parts: dict = field(default_factory=lambda: {"random_ramps": {}, "random_sine": {}})
    weights: tuple[float, ...] | None = None
    # given to every part that takes the argument and does not set it (None: the part's own default)
    v_low: float | None = None
    v_high: float | None = None
    v_init: float | None = None
    horizon: float | None = None

    def __post_init__(self):
        if not self.parts or not isinstance(self.parts, dict):
            raise ValueError(f"random_mix: parts={self.parts!r} is invalid; allowed: a mapping of one or more "
                             f"profile names to their arguments")
        for name in self.parts:
            if name not in PROFILES or name == "random_mix":
                raise ValueError(f"random_mix: part {name!r} is invalid; allowed: "
                                 f"{sorted(set(PROFILES) - {'random_mix'})}")
        if self.weights is not None and (len(self.weights) != len(self.parts) or any(w < 0 for w in self.weights)
                                         or sum(self.weights) <= 0):
            raise ValueError(f"random_mix: weights={self.weights!r} is invalid; allowed: {len(self.parts)} "
                             "non-negative numbers, not all 0")

    @functools.cached_property
    def built(self) -> tuple:
        """The parts as profile objects, in ``parts``' order."""
        out = []
        for name, kwargs in self.parts.items():
            kwargs = dict(kwargs or {})
            for arg in ("v_low", "v_high", "v_init", "horizon"):
                if getattr(self, arg) is not None and takes_argument(name, arg):
                    kwargs.setdefault(arg, getattr(self, arg))
            out.append(make_profile(name, **kwargs))
        return tuple(out)

    @functools.cached_property
    def widths(self) -> tuple[int, ...]:
        return tuple(int(part.sample(0).shape[-1]) for part in self.built)

    def sample(self, batch: int, generator: torch.Generator | None = None) -> Tensor:
        w = torch.tensor(self.weights if self.weights is not None else [1.0] * len(self.parts), dtype=torch.float64)
        which = torch.multinomial(w / w.sum(), batch, replacement=True, generator=generator) if batch else \
            torch.zeros(0, dtype=torch.long)
        # every part draws for the whole batch: a row's draw does not depend on the other rows' parts
        drawn = [part.sample(batch, generator)[which == j] for j, part in enumerate(self.built)]
        return _pack_by_part(which, drawn, self.widths)

    def speed(self, t: Tensor, params: Tensor) -> Tensor:
        return _speed_by_part(self.built, self.widths, t, params)


@dataclass(frozen=True)
class PiecewiseLinear:
    """Speed through fixed (time, speed) knots, held constant outside them."""

    times: tuple[float, ...] = (0.0,)
    speeds: tuple[float, ...] = (15.0,)

    def __post_init__(self):
        if len(self.times) != len(self.speeds) or len(self.times) == 0:
            raise ValueError("profile knots: 'times' and 'speeds' must be non-empty and of equal length")
        if any(b < a for a, b in zip(self.times, self.times[1:])):
            raise ValueError("profile knots: 'times' must be non-decreasing")

    def sample(self, batch: int, generator: torch.Generator | None = None) -> Tensor:
        return torch.zeros(batch, 0)

    def speed(self, t: Tensor, params: Tensor) -> Tensor:
        if len(self.times) == 1:
            return torch.full_like(t, self.speeds[0])
        return _interp(t, torch.tensor(self.times, dtype=t.dtype), torch.tensor(self.speeds, dtype=t.dtype))


@dataclass(frozen=True)
class RowProfiles:
    """A different profile per batch row: row ``i`` follows ``parts[i % len(parts)]``.

    Lets one batched env run several head profiles side by side (the evaluation runs
    all its profiles in one rollout). Parameters per row: ``[part index, part params...]``
    padded to the widest part. The env calls :meth:`sample_rows` with the row indices it
    resets, so a row keeps its part across resets.

    >>> import torch
    >>> from mixed_traffic.profiles import Constant, RowProfiles
    >>> prof = RowProfiles((Constant(10.0), Constant(20.0)))
    >>> prof.speed(torch.zeros(3), prof.sample(3)).tolist()
    [10.0, 20.0, 10.0]
    """

    parts: tuple = ()

    def __post_init__(self):
        if not self.parts:
            raise ValueError("RowProfiles: parts is empty; allowed: one or more profiles")

    @functools.cached_property
    def widths(self) -> tuple[int, ...]:
        """Number of parameters of each part (fixed by its settings)."""
        return tuple(int(part.sample(0).shape[-1]) for part in self.parts)

    def sample_rows(self, rows: Tensor, generator: torch.Generator | None = None) -> Tensor:
        rows = torch.as_tensor(rows, dtype=torch.long).reshape(-1)
        which = rows % len(self.parts)
        drawn = [part.sample(int((which == j).sum()), generator) for j, part in enumerate(self.parts)]
        return _pack_by_part(which, drawn, self.widths)

    def sample(self, batch: int, generator: torch.Generator | None = None) -> Tensor:
        return self.sample_rows(torch.arange(batch), generator)

    def speed(self, t: Tensor, params: Tensor) -> Tensor:
        return _speed_by_part(self.parts, self.widths, t, params)


def _pack_by_part(which: Tensor, drawn: list[Tensor], widths) -> Tensor:
    """Part-indexed parameters (:class:`RandomMix`, :class:`RowProfiles`): row ``i`` is ``[which[i], its part's
    parameters...]``, padded to the widest part; ``drawn[j]`` holds, in row order, the parameters of the rows of part
    ``j``."""
    out = torch.zeros(which.numel(), 1 + max(widths))
    out[:, 0] = which.float()
    for j, d in enumerate(drawn):
        out[which == j, 1:1 + d.shape[-1]] = d.float()
    return out


def _speed_by_part(parts, widths, t: Tensor, params: Tensor) -> Tensor:
    """The speed of rows whose parameters are ``[part index, the part's parameters...]`` (:class:`RandomMix`,
    :class:`RowProfiles`): each row through its own part."""
    which = params[..., 0].long()
    out = torch.empty_like(t)
    for j, (part, k) in enumerate(zip(parts, widths)):
        m = which == j
        if bool(m.any()):
            out[m] = part.speed(t[m], params[m, 1:1 + k]).to(t.dtype)
    return out


def deeplcc_brake(start: float = 0.0, v0: float = 15.0) -> PiecewiseLinear:
    """DeeP-LCC brake: -5 m/s^2 for 2 s from v0, hold 5 s, +2 m/s^2 for 5 s."""
    return PiecewiseLinear(times=(0.0, start, start + 2.0, start + 7.0, start + 12.0),
                           speeds=(v0, v0, v0 - 10.0, v0 - 10.0, v0))


def emergency_brake(start: float = 50.0, v_cruise: float = 15.0, v_low: float = 2.0) -> PiecewiseLinear:
    """Cruise, ramp to ``v_low`` over 3 s at ``start``, hold 10 s, back over 5 s."""
    return PiecewiseLinear(times=(0.0, start, start + 3.0, start + 13.0, start + 18.0),
                           speeds=(v_cruise, v_cruise, v_low, v_low, v_cruise))


# EUDC speed breakpoints (km/h) from its 50 km/h cruise to the final 50 km/h, in s.
_EUDC_T = (0, 13, 15, 63, 66, 67, 69, 140, 153, 154, 156, 203, 238, 268, 288, 289, 290, 298, 314, 322)
_EUDC_V = (50, 70, 70, 70, 59, 59, 50, 50, 70, 70, 70, 70, 100, 100, 120, 120, 120, 120, 80, 50)


def eudc(v_low: float = 5.0, v_high: float = 20.0, start: float = 0.0) -> PiecewiseLinear:
    """The EUDC cycle's shape (50-120 km/h) mapped linearly into [v_low, v_high] m/s."""
    lo, hi = min(_EUDC_V), max(_EUDC_V)
    speeds = tuple(v_low + (v - lo) / (hi - lo) * (v_high - v_low) for v in _EUDC_V)
    times = tuple(start + t for t in _EUDC_T)
    return PiecewiseLinear(times=(0.0,) + times, speeds=(speeds[0],) + speeds)


def nedc(start: float = 0.0) -> PiecewiseLinear:
    """Modified NEDC for the DeeP-LCC platoon: the EUDC shape within 50-75 km/h.

    The DeeP-LCC reference ships its modified cycle as a binary file; this keeps
    the cycle's shape and squeezes it into the platoon's 14-21 m/s operating range.
    """
    return eudc(v_low=50 / 3.6, v_high=75 / 3.6, start=start)


PROFILES = {
    "constant": Constant,
    "random_steps": RandomSteps,
    "random_perturbation": RandomPerturbation,
    "random_ramps": RandomRamps,
    "random_stop_and_go": RandomStopAndGo,
    "random_sine": RandomSine,
    "random_mix": RandomMix,
    "sine": Sine,
    "piecewise": PiecewiseLinear,
    "deeplcc_brake": deeplcc_brake,
    "emergency_brake": emergency_brake,
    "eudc": eudc,
    "nedc": nedc,
}


def profile_arguments(name: str) -> list[str]:
    """The arguments of the profile ``name`` of :data:`PROFILES`: its dataclass's fields, or its function's
    parameters."""
    factory = PROFILES[name]
    if hasattr(factory, "__dataclass_fields__"):
        return [f.name for f in fields(factory)]
    return list(inspect.signature(factory).parameters)


def takes_argument(name: str, arg: str) -> bool:
    """Whether the profile ``name`` of :data:`PROFILES` has the argument ``arg``."""
    return arg in profile_arguments(name)


def make_profile(name: str, **kwargs):
    """Build a profile by name; unknown names or fields raise a ValueError naming them."""
    if name not in PROFILES:
        raise ValueError(f"profile: unknown name {name!r}; allowed: {sorted(PROFILES)}")
    factory = PROFILES[name]
    try:
        return factory(**kwargs)
    except TypeError as e:
        allowed = profile_arguments(name)
        unknown = sorted(k for k in kwargs if k not in allowed)
        what = f"unknown arguments {unknown}" if unknown else f"bad arguments {sorted(kwargs)} ({e})"
        raise ValueError(f"profile {name!r}: {what}; allowed: {allowed}") from e


__all__ = ["make_profile", "PROFILES", "Constant", "RandomSteps", "RandomRamps", "RandomStopAndGo", "RandomPerturbation", "Sine",
           "RandomSine", "RandomMix",
           "PiecewiseLinear", "profile_arguments", "takes_argument", "RowProfiles", "deeplcc_brake", "emergency_brake", "eudc", "nedc", "field"]
