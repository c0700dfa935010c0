"""Scenario presets for the car-following environments, with validation.

A :class:`TrafficScenario` is a plain dataclass: every field can be overridden by
keyword (``make_env("ring", ring_length=260.0)``) or from a Hydra config, and
:meth:`TrafficScenario.validate` turns bad input into a ``ValueError`` that names
the field and what is allowed.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import torch

from mixed_traffic.physics import IDMParams, OVMParams, ovm_equilibrium_gap
from mixed_traffic.profiles import PROFILES, make_profile, profile_arguments
from mixed_traffic.validation import ConfigError, Real, is_real

# the policy inputs a scenario can give (``TrafficScenario.observation``); the ones built around a head
OBSERVATIONS = ("seed", "relative", "relative_accel", "relative_no_speed", "relative_time", "wave", "wave_ring",
                "wave_ring_time")
HEAD_OBSERVATIONS = ("relative", "relative_accel", "relative_no_speed", "relative_time")


@dataclass
class TrafficScenario:
    """One car-following scenario: road, vehicles, models, head profile, reward.

    Vehicles are ordered head first along the direction of travel: index 0 is the
    head (driven by ``profile``), ``cav_indices`` are driven by the action, the
    rest are human drivers following ``hdv_model``. With ``head=False`` (ring only)
    there is no scripted vehicle: index 0 is a human driver or a CAV like any other.

    Wave-related fields (the ``ring_wave`` preset):

    * ``accel_noise``: standard deviation (m/s^2) of a Gaussian term added to every
      human's acceleration at every step (Flow's ``accel_noise``: ``accel +=
      N(0, noise)`` per step, 0.2 in its ring), then clipped to ``[a_min, a_max]``;
    * ``ring_length_range``: ``(low, high)`` draws the ring length per episode,
      uniformly; ``None`` keeps ``ring_length``;
    * ``init_wave``: amplitude ``A`` of one sinusoidal wave of the initial gaps,
      ``g_i = g (1 + A sin(2 pi i / n + phi))`` with a random phase ``phi``, so waves
      are there from the start instead of after minutes of noise-driven growth;
    * ``reward="wave"``: ``r = weight_v mean(v)/v_star - weight_s std(v)/v_star -
      weight_u sum_cav |a| / a_max`` over all vehicles (average speed and
      smoothness, in the spirit of Flow's wave-attenuation reward, which also
      penalises the mean absolute acceleration of the automated vehicles); the env reports it
      as ``J = 1 - r`` with ``J_max = 1``, so ``NonNegativeReward`` gives ``max(r, 0)``;
    * ``reward="wave_relative"``: the same with ``v_star`` replaced by each row's uniform-flow
      speed (``envs.traffic.uniform_flow_speed``): 1 is the ring's physical optimum whatever its
      length, so episodes on rings of different lengths score on one scale;
    * ``observation="wave"``: each CAV's local view ``[v/10, (v_lead - v)/10, gap/20,
      (v_avg - v)/10, a/a_max]`` where ``v_avg`` is its own mean speed over the last
      ``cav_speed_window`` seconds (``("cav", "speed_avg")``);
    * ``observation="relative_accel"``: ``"relative"`` plus the leader's acceleration of the
      last step over ``a_max`` (what a CAV receives from its leader over V2V, as in CACC: it
      sees the leader speed up or brake before the gap and the speed difference show it);
    * ``observation="relative_no_speed"``: ``"relative"`` without the CAV's own speed ``v/30``:
      differences and gaps only, so a policy cannot tie its command to the speeds it trained at
      (the speed still reaches the command through a residual's base controller);
    * ``observation="relative_time"``: ``"relative"`` plus the time since the controller
      engaged (the episode's start) / 30 s, saturating at 1: a policy can close a long gap it
      engages with differently from one that opens later (the safety layer's ``hold_seconds``);
    * ``observation="wave_ring"``: ``"wave"`` plus the ring's length / 260 m (what sets the
      ring's uniform-flow speed, from which FollowerStopper's set point is computed);
    * ``observation="wave_ring_time"``: ``"wave_ring"`` plus the time since the controller
      engaged (the episode's start) / 600 s, saturating at 1 (what a set-point schedule reads).
    """

    name: str = "ring"
    road: str = "ring"  # "ring" (positions modulo ring_length) or "open"
    ring_length: float = 313.65
    n_vehicles: int = 4
    cav_indices: tuple[int, ...] = (1,)
    hdv_model: str = "idm"  # "idm" or "ovm"
    hdv_params: dict = field(default_factory=dict)  # overrides of the model's defaults
    hdv_param_noise: float = 0.0  # per-episode relative spread, U[1-x, 1+x] per vehicle
    vehicle_length: float = 5.0
    dt: float = 0.1
    episode_seconds: float = 500.0
    v_init: float = 10.0
    init_spacing: float | None = None  # bumper gap at start; None: ring even / open OVM equilibrium
    # per-episode bumper gap at start drawn from U[lo, hi] (torch backend; ring: at most the even spacing)
    init_spacing_range: tuple[float, float] | None = None
    # fixed start gap per row (row i of the batch: entry i % len; torch backend; evaluation of close starts)
    init_spacing_rows: tuple[float, ...] | None = None
    integration: str = "euler"  # see mixed_traffic.physics.integrate
    profile: str = "random_steps"
    profile_kwargs: dict = field(default_factory=lambda: {"v_low": 5.0, "v_high": 20.0, "period": 15.0, "v_init": 10.0})
    head_accel_bounds: tuple[float, float] = (-3.0, 2.0)
    cav_accel_bounds: tuple[float, float] = (-3.0, 3.0)
    # the hardest braking (m/s^2, > 0) a CAV can execute, for the safety layer alone: the policy and the
    # controllers command within cav_accel_bounds, the layer may brake down to -cav_emergency_decel when
    # the gap demands it, and its worst case assumes the CAV brakes that hard (None: -cav_accel_bounds[0])
    cav_emergency_decel: float | None = None
    observation: str = "seed"  # "seed": [v_i/30, p_i/L]; "relative": per-CAV physical features; "wave"
    head: bool = True  # a scripted head at index 0 (False: ring only, every car a human or a CAV)
    accel_noise: float = 0.0  # std (m/s^2) of the per-step Gaussian noise on human accelerations
    ring_length_range: tuple[float, float] | None = None  # per-episode ring length U[low, high]
    init_wave: float = 0.0  # amplitude of a sinusoidal initial gap wave, fraction of the mean gap
    cav_speed_window: float = 38.0  # s, window of ("cav", "speed_avg") (no-head scenarios)
    reward: str = "deeplcc"  # "deeplcc" (stage cost J), "wave" (average speed and smoothness) or
    # "wave_relative" (the same over the ring's uniform-flow speed)
    # SUMO's speed mode 95 for the CAVs: the executed acceleration is capped by SUMO's Krauss safe
    # speed and the accel/decel bounds (torch: mixed_traffic.physics.sumo_speed_mode_95; SUMO: the
    # mode itself); both backends then emit ("cav", "override") and count env.override_steps
    sumo_safety: bool = False
    # every vehicle's acceleration at reset (what the first observation and the first step's jerk
    # penalty read): "zero", or "model": the humans' model at the start state for the humans and the
    # CAVs (as if they had been driving before the controller engaged), the head's first command
    # (torch backend)
    reset_accel: str = "zero"
    # reward (DeeP-LCC cost) and constraint cost
    weight_v: float = 1.0
    weight_s: float = 0.5
    weight_u: float = 0.2
    s_star: float = 20.0
    spacing_clip: float = 20.0
    v_eq_window: float = 20.0
    v_dev_max: float = 15.0  # speed error used for the worst-case J_max
    v_star: float = 15.0  # nominal equilibrium speed (DeeP-LCC errors are taken around it)
    s_min: float = 5.0
    s_max: float = 40.0

    # ----------------------------------------------------------------- derived
    @property
    def is_ring(self) -> bool:
        return self.road == "ring"

    @property
    def max_steps(self) -> int:
        return int(round(self.episode_seconds / self.dt))

    @property
    def cav_exec_bounds(self) -> tuple[float, float]:
        """The CAV accelerations the vehicle executes: ``cav_accel_bounds`` widened down to
        ``-cav_emergency_decel`` (what the safety layer may brake at; the action range is unchanged)."""
        lo, hi = self.cav_accel_bounds
        if self.cav_emergency_decel is None:
            return (float(lo), float(hi))
        return (min(float(lo), -float(self.cav_emergency_decel)), float(hi))

    @property
    def n_cav(self) -> int:
        return len(self.cav_indices)

    @property
    def hdv_indices(self) -> tuple[int, ...]:
        first = 1 if self.head else 0
        return tuple(i for i in range(first, self.n_vehicles) if i not in self.cav_indices)

    @property
    def ring_lengths(self) -> tuple[float, float]:
        """The range ring lengths are drawn from (``(L, L)`` when fixed)."""
        if self.ring_length_range is None:
            return (float(self.ring_length), float(self.ring_length))
        return (float(self.ring_length_range[0]), float(self.ring_length_range[1]))

    def hdv_defaults(self):
        base = IDMParams() if self.hdv_model == "idm" else OVMParams()
        return dataclasses.replace(base, **self.hdv_params)

    @property
    def J_max(self) -> float:
        """Worst-case DeeP-LCC cost of one step (maps the reward into [0, 1]); 1 for ``reward="wave"``."""
        if self.reward in ("wave", "wave_relative"):
            return 1.0
        a_abs = max(abs(self.cav_accel_bounds[0]), abs(self.cav_accel_bounds[1]))
        return (self.weight_v * (self.n_vehicles - 1) * self.v_dev_max**2
                + self.weight_s * self.n_cav * self.spacing_clip**2
                + self.weight_u * self.n_cav * a_abs**2)

    def initial_spacing(self) -> float:
        if self.init_spacing is not None:
            return float(self.init_spacing)
        if self.is_ring:
            return self.ring_length / self.n_vehicles - self.vehicle_length
        return self.equilibrium_gap(self.v_init)

    def equilibrium_gap(self, v: float) -> float:
        """The humans' steady bumper gap at speed ``v`` (m): where their car-following model's acceleration
        behind a leader at the same speed is 0."""
        p = self.hdv_defaults()
        if self.hdv_model == "ovm":
            return ovm_equilibrium_gap(v, p.v_max, p.s_st, p.s_go)
        return (p.s0 + v * p.T) / math.sqrt(max(1e-6, 1.0 - (v / p.v0) ** p.delta))

    def make_profile(self):
        """The head's profile from ``profile`` and ``profile_kwargs``. An argument set to None that the profile does
        not have is left out (None means unset, as in ``random_mix``'s shared arguments), so an experiment's
        ``v_init: null`` does not stop ``env.profile=random_sine`` from the command line."""
        known = profile_arguments(self.profile) if self.profile in PROFILES else None
        kwargs = {k: v for k, v in dict(self.profile_kwargs).items()
                  if not (v is None and known is not None and k not in known)}
        if known is not None and "horizon" in known:  # the drawn profiles' knots
            kwargs.setdefault("horizon", self.episode_seconds)
        return make_profile(self.profile, **kwargs)

    # -------------------------------------------------------------- validation
    def _check_types(self) -> None:
        """Every field holds a value of its annotated type; numbers are finite."""
        for f in dataclasses.fields(self):
            name, x, t = f.name, getattr(self, f.name), str(f.type).replace(" ", "")
            if x is None and t.endswith("|None"):
                continue
            if t.startswith("tuple[") and t.endswith("|None"):
                t = t[: -len("|None")]
            if t in ("float", "int", "float|None", "int|None"):
                Real(optional=t.endswith("None"), integer=t.startswith("int"))(name, x)
            elif t == "str" and not isinstance(x, str):
                raise ConfigError(name, f"{x!r} is a {type(x).__name__}", "a string")
            elif t == "bool" and not isinstance(x, bool):
                raise ConfigError(name, f"{x!r} is a {type(x).__name__}", "true or false")
            elif t.startswith(("tuple[float", "tuple[int")):
                integer = t.startswith("tuple[int")
                if not isinstance(x, (tuple, list)) or (t.count(",") and not t.endswith("...]")
                                                        and len(x) != t.count(",") + 1):
                    raise ConfigError(name, f"{x!r} is invalid", f"a sequence of {t.count(',') + 1} numbers")
                for v in x:
                    Real(integer=integer)(name, v)
            elif t == "dict":
                if not isinstance(x, dict):
                    raise ConfigError(name, f"{x!r} is a {type(x).__name__}", "a mapping")
                for k, v in x.items():
                    # model parameters and profile numbers (a bool is not one); other dicts may hold anything
                    if name == "hdv_params" or is_real(v) or (name == "profile_kwargs" and isinstance(v, bool)):
                        Real()(f"{name}.{k}", v)

    def validate(self) -> TrafficScenario:
        """Raise :class:`~mixed_traffic.validation.ConfigError` (a ValueError) naming the first bad field.

        Types come from the field annotations (numbers finite, ints integral, strings
        strings), so a new field is checked without new code; ranges follow.
        """
        def bad(name, value, allowed):
            raise ConfigError(name, f"{value!r} is invalid (scenario {self.name!r})", str(allowed))

        self._check_types()
        if self.road not in ("ring", "open"):
            bad("road", self.road, "'ring' or 'open'")
        if not self.dt > 0:
            bad("dt", self.dt, "dt > 0")
        if not self.episode_seconds >= self.dt:
            bad("episode_seconds", self.episode_seconds, f">= dt ({self.dt})")
        if self.n_vehicles < 2:
            bad("n_vehicles", self.n_vehicles, ">= 2 (a head and at least one follower)")
        if not self.head and not self.is_ring:
            bad("head", self.head, "True on an open road (head=False needs road='ring')")
        if self.n_cav < 1:
            bad("cav_indices", self.cav_indices, "at least one CAV index")
        first = 1 if self.head else 0
        for i in self.cav_indices:
            if not (isinstance(i, int) and first <= i < self.n_vehicles):
                bad("cav_indices", self.cav_indices, f"distinct integers in [{first}, {self.n_vehicles - 1}]"
                    + (" (0 is the head)" if self.head else ""))
        if len(set(self.cav_indices)) != self.n_cav:
            bad("cav_indices", self.cav_indices, "distinct indices")
        if self.hdv_model not in ("idm", "ovm"):
            bad("hdv_model", self.hdv_model, "'idm' or 'ovm'")
        base = IDMParams() if self.hdv_model == "idm" else OVMParams()
        unknown = set(self.hdv_params) - {f.name for f in dataclasses.fields(base)}
        if unknown:
            bad("hdv_params", sorted(unknown), [f.name for f in dataclasses.fields(base)])
        if not 0.0 <= self.hdv_param_noise < 1.0:
            bad("hdv_param_noise", self.hdv_param_noise, "[0, 1)")
        if self.vehicle_length <= 0:
            bad("vehicle_length", self.vehicle_length, "> 0")
        if self.ring_length_range is not None:
            r = self.ring_length_range
            if not (len(r) == 2 and 0 < r[0] <= r[1]):
                bad("ring_length_range", r, "(low, high) with 0 < low <= high, or None")
            if not self.is_ring:
                bad("ring_length_range", r, "None on an open road")
        if self.is_ring:
            if not self.ring_length > 0:
                bad("ring_length", self.ring_length, "> 0")
            min_len = self.n_vehicles * (self.vehicle_length + 1.0)
            shortest = min(self.ring_lengths)
            if shortest < min_len:
                bad("n_vehicles", self.n_vehicles,
                    f"at most {int(shortest // (self.vehicle_length + 1.0))} vehicles on a "
                    f"{shortest} m ring (vehicle_length {self.vehicle_length} m + 1 m minimum gap each)")
        if not self.accel_noise >= 0:
            bad("accel_noise", self.accel_noise, ">= 0 (m/s^2)")
        if not 0 <= self.init_wave < 1:
            bad("init_wave", self.init_wave, "[0, 1) (fraction of the mean gap)")
        if not self.cav_speed_window >= self.dt:
            bad("cav_speed_window", self.cav_speed_window, f">= dt ({self.dt})")
        if self.reward not in ("deeplcc", "wave", "wave_relative"):
            bad("reward", self.reward, "'deeplcc', 'wave' or 'wave_relative'")
        if self.reward == "wave_relative" and not (self.is_ring and not self.head and self.hdv_model == "idm"):
            bad("reward", self.reward, "'wave_relative' on a ring without a head of IDM humans only (its scale is "
                "their uniform flow)")
        if self.init_spacing is not None and self.init_spacing <= 0:
            bad("init_spacing", self.init_spacing, "> 0 or None")
        if self.init_spacing_range is not None:
            r = tuple(self.init_spacing_range)
            if len(r) != 2 or not 0 < r[0] <= r[1]:
                bad("init_spacing_range", self.init_spacing_range, "(lo, hi) with 0 < lo <= hi, or None")
            if self.is_ring and r[0] > self.ring_length / self.n_vehicles - self.vehicle_length:
                bad("init_spacing_range", self.init_spacing_range,
                    f"lo <= {self.ring_length / self.n_vehicles - self.vehicle_length:.2f} m (even spacing on the ring)")
        if self.init_spacing_rows is not None:
            rows = tuple(self.init_spacing_rows)
            even = self.ring_length / self.n_vehicles - self.vehicle_length if self.is_ring else math.inf
            if len(rows) == 0 or not all(0 < x <= even + 1e-6 for x in rows):
                bad("init_spacing_rows", self.init_spacing_rows,
                    f"a non-empty list of gaps in (0, {even:.2f}] m, or None")
            if self.init_spacing_range is not None:
                bad("init_spacing_rows", self.init_spacing_rows, "None when init_spacing_range is set")
        if (self.init_spacing_range is not None or self.init_spacing_rows is not None) and \
                getattr(self, "ring_length_range", None) is not None:
            bad("init_spacing_range", self.init_spacing_range or self.init_spacing_rows,
                "None when ring_length_range is set (one ring length per start spacing)")
        if self.v_init < 0:
            bad("v_init", self.v_init, ">= 0")
        for name in ("head_accel_bounds", "cav_accel_bounds"):
            lo, hi = getattr(self, name)
            if not lo < 0 < hi:
                bad(name, (lo, hi), "(low, high) with low < 0 < high")
        if self.cav_emergency_decel is not None and not (
                math.isfinite(self.cav_emergency_decel) and self.cav_emergency_decel >= -self.cav_accel_bounds[0]):
            bad("cav_emergency_decel", self.cav_emergency_decel,
                f"None or a finite braking (m/s^2) >= -cav_accel_bounds[0] = {-self.cav_accel_bounds[0]:g}")
        if self.integration not in ("euler", "euler_explicit", "ballistic"):
            bad("integration", self.integration, "'euler', 'euler_explicit' or 'ballistic'")
        if self.reset_accel not in ("zero", "model"):
            bad("reset_accel", self.reset_accel, "'zero' or 'model'")
        if self.observation not in OBSERVATIONS:
            bad("observation", self.observation,
                ", ".join(map(repr, OBSERVATIONS[:-1])) + f" or {OBSERVATIONS[-1]!r}")
        if self.observation in HEAD_OBSERVATIONS and not self.head:
            bad("observation", self.observation, "'seed' or 'wave' without a head (head=False)")
        if self.profile not in PROFILES:
            bad("profile", self.profile, sorted(PROFILES))
        try:
            prof = self.make_profile()
            params = prof.sample(1, torch.Generator().manual_seed(0))
            if not bool(torch.isfinite(prof.speed(torch.zeros(1), params)).all()):
                raise ValueError("the head speed is not finite")
        except ConfigError:
            raise
        except (ValueError, TypeError) as e:
            raise ConfigError("profile_kwargs", f"{self.profile_kwargs!r} rejected by profile {self.profile!r} ({e})",
                              "the profile's own arguments (see mixed_traffic.profiles)") from None
        if not 0 < self.s_min < self.s_max:
            bad("s_min", (self.s_min, self.s_max), "0 < s_min < s_max")
        for name in ("weight_v", "weight_s", "weight_u", "v_star"):
            if getattr(self, name) < 0:
                bad(name, getattr(self, name), ">= 0")
        for name in ("v_eq_window", "spacing_clip", "v_dev_max", "s_star"):
            if getattr(self, name) <= 0:
                bad(name, getattr(self, name), "> 0")
        return self


def _ring() -> TrafficScenario:
    return TrafficScenario()


def _deeplcc() -> TrafficScenario:
    return TrafficScenario(
        name="deeplcc", road="open", n_vehicles=9, cav_indices=(3, 6), hdv_model="ovm",
        dt=0.05, episode_seconds=50.0, v_init=15.0, profile="random_perturbation",
        profile_kwargs={"v_star": 15.0, "amplitude": 1.0, "period": 1.0},
        head_accel_bounds=(-5.0, 2.0), cav_accel_bounds=(-5.0, 2.0), observation="relative",
        weight_v=1.0, weight_s=0.5, weight_u=0.1, v_dev_max=5.0,
    )


def _ring_wave() -> TrafficScenario:
    """Sugiyama / Flow ring: 22 cars, 260 m, no head, one CAV.

    ``ring_length_range=[220, 270]`` draws the length per episode (Flow's training range).

    Humans follow Flow's IDM (v0 30, T 1, a 1, b 1.5, delta 4, s0 2; SUMO's IDM
    emergency bound -9 m/s^2) with per-step acceleration noise N(0, 0.2) and a 10%
    per-vehicle, per-episode spread of their parameters; they start at 4 m/s
    with one sinusoidal wave of 50% of the mean gap. The CAV (car 0) commands
    accelerations in [-3, 3] m/s^2 (symmetric, so a fresh Gaussian policy starts at 0).
    """
    return TrafficScenario(
        name="ring_wave", road="ring", ring_length=260.0, n_vehicles=22,
        cav_indices=(0,), head=False, hdv_model="idm",
        hdv_params={"v0": 30.0, "T": 1.0, "a": 1.0, "b": 1.5, "delta": 4.0, "s0": 2.0},
        hdv_param_noise=0.1, accel_noise=0.2, init_wave=0.5, v_init=4.0, dt=0.1, episode_seconds=300.0,
        cav_accel_bounds=(-3.0, 3.0), observation="wave", reward="wave",
        weight_v=1.0, weight_s=0.2, weight_u=0.3, v_star=10.0, s_min=2.0, s_max=40.0,
    )


PRESETS = {"ring": _ring, "deeplcc": _deeplcc, "ring_wave": _ring_wave}


def get_scenario(name: str, **overrides) -> TrafficScenario:
    """A validated preset with ``overrides`` applied (unknown fields raise ValueError)."""
    if name not in PRESETS:
        raise ConfigError("scenario", f"unknown preset {name!r}", str(sorted(PRESETS)))
    sc = PRESETS[name]()
    allowed = {f.name for f in dataclasses.fields(sc)}
    unknown = set(overrides) - allowed
    if unknown:
        raise ConfigError(sorted(unknown)[0], f"unknown override(s) {sorted(unknown)} (not fields of scenario {name!r})",
                          str(sorted(allowed)))
    for key in ("cav_indices", "head_accel_bounds", "cav_accel_bounds", "ring_length_range", "init_spacing_range",
                "init_spacing_rows"):
        if isinstance(overrides.get(key), list):
            overrides[key] = tuple(overrides[key])
    return dataclasses.replace(sc, **overrides).validate()
