"""The DeeP-LCC platoon as a batched TorchRL environment (``make_env("platoon")``, ``env=deeplcc``).

Head vehicle + 8 followers, CAVs at vehicle indices 3 and 6, the physics of
:mod:`mixed_traffic.controllers.deeplcc.platoon` (float64, explicit Euler, HDV
acceleration noise, the CAVs' emergency-braking override, head speed imposed). Each row
is one episode of :func:`~mixed_traffic.controllers.deeplcc.closed_loop.run_closed_loop`:
at reset the platoon starts at equilibrium and drives ``t_ini`` steps with zero CAV
input to fill the past-data window, then the policy decides every step until
``episode_seconds`` (warm-up included) have passed. So a QP or NNMPC policy rolled in
this env sees exactly the windows ``run_closed_loop`` would give it, and the sum of
``("traffic", "J")`` over an episode is that function's closed-loop ``cost``.

Head profiles (``profiles``, drawn per episode with ``profile_weights``):
``random1``/``random3``/``random5`` (random perturbation of that amplitude, knots every 1 s),
``brake`` (the DeeP-LCC brake, start U[``brake_start``]), ``sine3``/``sine5`` (period 10 s,
random phase), ``nedc`` (the modified NEDC, a random window of it); with
``randomize=False`` the evaluation's fixed versions (brake at 1 s, sine phase 0, NEDC
from its start 5 s in) as in :data:`~mixed_traffic.controllers.deeplcc.closed_loop.EVAL_SCENARIOS`.
The equilibrium speed v* is fixed (15 m/s) for random/sine and adaptive (mean head speed
over the last ``t_ini`` instants) for brake/NEDC, as in the closed-loop evaluation.

Model mismatch (``mismatch``): the human drivers follow the homogeneous OVM of the
Hankel data (``"none"``), the DeeP-LCC IDM set (``"idm"``), or an OVM whose parameters are
redrawn per vehicle and episode within ±``hetero_spread`` (``"hetero_ovm"``). Controllers
built on the homogeneous-OVM Hankel data keep using it: only the platoon changes.

Keys (``[B]`` first): ``uini`` [40], ``yini`` [200], ``eini`` [20] (the window of the
QP/NNMPC, float32), ``("deeplcc", "v_star")`` [1], ``observation`` [271] (the window and the
current output/disturbance, divided by 5), the car-following contract's ``("cav", ...)``
and ``("traffic", ...)`` entries (``J`` is the DeeP-LCC stage cost
``w_v |v - v*|^2 + w_s |s_cav - s*|^2 + w_u |u|^2`` of the instant the action was taken
from, with the executed ``u``), ``reward = -J``, ``cost`` = the CAVs' spacing-constraint
violation ``sum max(0, s_min - s) / s_min + max(0, s - s_max) / s_max``, ``collision``.

>>> from torchrl.envs.utils import check_env_specs
>>> from mixed_traffic import make_env
>>> env = make_env("platoon", batch_size=4, seed=0)
>>> check_env_specs(env)
>>> env.rollout(3)["next", "yini"].shape
torch.Size([4, 3, 200])
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from mixed_traffic.controllers.deeplcc.closed_loop import head_speed_profile
from mixed_traffic.controllers.deeplcc.platoon import DTYPE, PlatoonConfig, gaps, init_state, step
from mixed_traffic.physics import OVMParams
from mixed_traffic.validation import ConfigError

Tensor = torch.Tensor

PROFILE_KINDS = ("random1", "random3", "random5", "brake", "sine3", "sine5", "nedc")
ADAPTIVE_KINDS = ("brake", "nedc")
MISMATCH = ("none", "idm", "hetero_ovm")
NEDC_SECONDS = 330.0
OBS_SCALE = 5.0


@dataclass(frozen=True)
class PlatoonScenario:
    """Settings of :class:`PlatoonEnv` (validated; bad values raise ``ConfigError`` naming the field)."""

    name: str = "platoon"
    profiles: tuple[str, ...] = PROFILE_KINDS
    profile_weights: tuple[float, ...] | None = None  # None: uniform
    randomize: bool = True  # False: the evaluation's fixed brake start / sine phase / NEDC window
    profile_rows: bool = False  # True: row i always runs profiles[i % len(profiles)] (evaluation batches)
    episode_seconds: float = 40.0  # includes the t_ini warm-up steps
    brake_start: tuple[float, float] = (1.0, 10.0)
    mismatch: str = "none"
    hetero_spread: float = 0.2
    accel_noise: float = 0.1
    t_ini: int = 20
    v_star: float = 15.0
    s_star: float = 20.0
    weight_v: float = 1.0
    weight_s: float = 0.5
    weight_u: float = 0.1
    s_min: float = 5.0
    s_max: float = 40.0
    J_max: float = 500.0  # NonNegativeReward's worst-case stage cost
    cav_accel_bounds: tuple[float, float] = (-5.0, 2.0)
    head_accel_bounds: tuple[float, float] = (-5.0, 2.0)
    cav_indices: tuple[int, ...] = (3, 6)
    n_vehicles: int = 9
    dt: float = 0.05
    head: bool = True
    hdv_param_noise: float = 0.0

    def validate(self) -> PlatoonScenario:
        def bad(f, v, allowed):
            raise ConfigError(f, f"{v!r} is invalid", allowed)

        if not self.profiles or any(p not in PROFILE_KINDS for p in self.profiles):
            bad("profiles", self.profiles, f"a non-empty list of {list(PROFILE_KINDS)}")
        if self.profile_weights is not None and (len(self.profile_weights) != len(self.profiles)
                                                 or any(w < 0 for w in self.profile_weights)
                                                 or sum(self.profile_weights) <= 0):
            bad("profile_weights", self.profile_weights, "null or one weight >= 0 per profile, not all 0")
        if self.mismatch not in MISMATCH:
            bad("mismatch", self.mismatch, f"one of {list(MISMATCH)}")
        if not 0 <= self.hetero_spread < 1:
            bad("hetero_spread", self.hetero_spread, "[0, 1)")
        if not self.accel_noise >= 0:
            bad("accel_noise", self.accel_noise, ">= 0")
        if not (isinstance(self.t_ini, int) and self.t_ini >= 1):
            bad("t_ini", self.t_ini, "an integer >= 1")
        if not self.episode_seconds > (self.t_ini + 1) * self.dt:
            bad("episode_seconds", self.episode_seconds, f"> (t_ini + 1) * dt = {(self.t_ini + 1) * self.dt:g} s")
        if "nedc" in self.profiles and self.episode_seconds > NEDC_SECONDS:
            bad("episode_seconds", self.episode_seconds, f"<= {NEDC_SECONDS:g} s with the 'nedc' profile")
        lo, hi = self.brake_start
        if not 0 <= lo <= hi:
            bad("brake_start", self.brake_start, "[lo, hi] with 0 <= lo <= hi")
        if not 0 < self.s_min < self.s_max:
            bad("s_min", (self.s_min, self.s_max), "0 < s_min < s_max")
        for n in ("weight_v", "weight_s", "weight_u"):
            if getattr(self, n) < 0:
                bad(n, getattr(self, n), ">= 0")
        if not self.J_max > 0:
            bad("J_max", self.J_max, "> 0")
        if self.n_vehicles != 9 or tuple(self.cav_indices) != (3, 6) or self.dt != 0.05:
            bad("n_vehicles/cav_indices/dt", (self.n_vehicles, self.cav_indices, self.dt),
                "the DeeP-LCC platoon (9 vehicles, CAVs at 3 and 6, dt 0.05 s)")
        if tuple(self.cav_accel_bounds) != (-5.0, 2.0):
            bad("cav_accel_bounds", self.cav_accel_bounds, "(-5, 2), the bounds of the DeeP-LCC QP")
        if self.hdv_param_noise != 0.0:
            bad("hdv_param_noise", self.hdv_param_noise, "0 (use mismatch=hetero_ovm and hetero_spread)")
        return self

    @property
    def n_cav(self) -> int:
        return len(self.cav_indices)

    @property
    def is_ring(self) -> bool:
        return False

    @property
    def total_steps(self) -> int:
        return int(round(self.episode_seconds / self.dt))

    @property
    def max_steps(self) -> int:
        """Decision steps per episode (the warm-up excluded)."""
        return self.total_steps - self.t_ini

    def platoon(self) -> PlatoonConfig:
        return PlatoonConfig(hdv_model="idm" if self.mismatch == "idm" else "ovm", accel_noise=self.accel_noise,
                             v_star=self.v_star, s_star=self.s_star)

    def hdv_defaults(self):
        """Nominal human-driver parameters (the safety layer reads their braking bound)."""
        return self.platoon().hdv_param_set()


def get_platoon_scenario(**overrides) -> PlatoonScenario:
    names = {f.name for f in dataclasses.fields(PlatoonScenario)}
    unknown = sorted(set(overrides) - names)
    if unknown:
        raise ConfigError(unknown[0], "is not a field of the platoon scenario", f"one of {sorted(names)}")
    for k in ("profiles", "profile_weights", "brake_start", "cav_accel_bounds", "head_accel_bounds", "cav_indices"):
        if overrides.get(k) is not None:
            overrides[k] = tuple(overrides[k])
    return dataclasses.replace(PlatoonScenario(), **overrides).validate()


def head_profile(kind: str, seconds: float, dt: float, k: int, generator: torch.Generator,
                 randomize: bool = True, brake_start: tuple[float, float] = (1.0, 10.0)) -> Tensor:
    """Head speed ``[k, round(seconds / dt) + 1]`` (float64) of ``k`` episodes of ``kind``."""
    steps = int(round(seconds / dt))
    if kind.startswith("random"):
        return head_speed_profile("random_perturbation", seconds, dt, k, generator,
                                  amplitude=float(kind[6:]), period=1.0, v_star=15.0)
    t = torch.arange(steps + 1, dtype=DTYPE) * dt
    if kind.startswith("sine"):
        phase = torch.rand(k, 1, generator=generator, dtype=DTYPE) * 10.0 if randomize else torch.zeros(k, 1, dtype=DTYPE)
        return 15.0 + float(kind[4:]) * torch.sin(2.0 * math.pi * (t + phase) / 10.0)
    if kind == "brake":
        lo, hi = brake_start
        starts = (lo + (hi - lo) * torch.rand(k, generator=generator, dtype=DTYPE)).tolist() if randomize else [1.0] * k
        return torch.cat([head_speed_profile("deeplcc_brake", seconds, dt, 1, None, start=s) for s in starts])
    if kind == "nedc":
        full = head_speed_profile("nedc", NEDC_SECONDS, dt, 1, None, start=5.0)[0]
        n0 = full.numel() - (steps + 1)
        off = torch.randint(0, n0 + 1, (k,), generator=generator) if randomize else torch.zeros(k, dtype=torch.long)
        return torch.stack([full[o:o + steps + 1] for o in off.tolist()])
    raise ValueError(f"head_profile: kind={kind!r} is invalid; allowed: {list(PROFILE_KINDS)}")


class PlatoonEnv(EnvBase):
    """Batched DeeP-LCC platoon (see the module docstring).

    Args:
        batch_size: number of independent rows.
        device: torch device of the outputs (the simulation runs in float64 on the CPU).
        **overrides: fields of :class:`PlatoonScenario`.
    """

    batch_locked = True

    def __init__(self, *, batch_size: int = 1, device: str | torch.device = "cpu", **overrides):
        sc = get_platoon_scenario(**overrides)
        super().__init__(device=device, batch_size=torch.Size([batch_size]))
        self.scenario = sc
        self.dt = sc.dt
        self.J_max = sc.J_max
        self.cfg = sc.platoon()
        self.rng = torch.Generator().manual_seed(0)
        B, n, m, T = batch_size, sc.n_vehicles, sc.n_cav, sc.t_ini
        nf = n - 1
        self._make_specs(B)
        self._weights = torch.tensor(sc.profile_weights or [1.0] * len(sc.profiles), dtype=DTYPE)
        self._ci = [i - 1 for i in sc.cav_indices]  # follower indices of the CAVs
        # state (float64)
        self.pos = torch.zeros(B, n, dtype=DTYPE)
        self.vel = torch.full((B, n), sc.v_star, dtype=DTYPE)
        self.acc = torch.zeros(B, n, dtype=DTYPE)
        self.k = torch.zeros(B, dtype=torch.long)  # instant index within the episode (warm-up included)
        self.head_v = torch.full((B, sc.total_steps + 1), sc.v_star, dtype=DTYPE)
        self.kind = torch.zeros(B, dtype=torch.long)
        self.adaptive = torch.zeros(B, dtype=torch.bool)
        self.v_star = torch.full((B,), sc.v_star, dtype=DTYPE)
        # the past window (instants k - t_ini .. k - 1): head speed, follower speeds, CAV gaps, executed u
        self.w_vh = torch.full((B, T), sc.v_star, dtype=DTYPE)
        self.w_v = torch.full((B, T, nf), sc.v_star, dtype=DTYPE)
        self.w_s = torch.full((B, T, m), sc.s_star, dtype=DTYPE)
        self.w_u = torch.zeros(B, T, m, dtype=DTYPE)
        base = dataclasses.asdict(self.cfg.hdv_param_set())
        self.hdv = {k: torch.full((B, nf), float(v), dtype=DTYPE) for k, v in base.items()}

    # ------------------------------------------------------------------ specs
    def _make_specs(self, B: int) -> None:
        sc, dev = self.scenario, self.device
        n, m, T = sc.n_vehicles, sc.n_cav, sc.t_ini
        p = n - 1 + m
        f32 = torch.float32

        def u(*shape):
            return Unbounded(shape=(B, *shape), dtype=f32, device=dev)

        def flag():
            return Categorical(2, shape=(B, 1), dtype=torch.bool, device=dev)

        cav = Composite({k: u(m) for k in ("gap", "speed", "leader_speed", "head_gap", "head_speed", "accel")},
                        shape=(B,), device=dev)
        traffic = Composite({**{k: u(n) for k in ("pos", "speed", "accel", "gap")},
                             **{k: u(1) for k in ("time", "v_eq", "J")}}, shape=(B,), device=dev)
        self.observation_spec = Composite(
            observation=u(m * T + p * T + T + p + 1), uini=u(m * T), yini=u(p * T), eini=u(T),
            deeplcc=Composite(v_star=u(1), kind=Unbounded(shape=(B, 1), dtype=torch.long, device=dev),
                              shape=(B,), device=dev),
            cav=cav, traffic=traffic, collision=flag(), shape=(B,), device=dev)
        lo, hi = sc.cav_accel_bounds
        self.action_spec = Bounded(low=torch.full((B, m), lo, dtype=f32, device=dev),
                                   high=torch.full((B, m), hi, dtype=f32, device=dev), shape=(B, m), dtype=f32,
                                   device=dev)
        self.reward_spec = Composite(reward=u(1), cost=u(1), shape=(B,), device=dev)
        self.done_spec = Composite(done=flag(), terminated=flag(), truncated=flag(), shape=(B,), device=dev)

    # ------------------------------------------------------------------ helpers
    def _set_seed(self, seed: int | None) -> None:
        self.rng.manual_seed(int(seed) if seed is not None else torch.seed() % (2**63))

    def _current_v_star(self, rows: Tensor | slice) -> Tensor:
        """v* at the current instant: fixed, or the mean head speed of instants k - t_ini + 1 .. k."""
        T = self.scenario.t_ini
        k = self.k[rows]
        heads = torch.cat([self.w_vh[rows, 1:], self.vel[rows, :1]], -1)
        # fewer than t_ini instants so far (the warm-up): average over those that exist
        count = (k + 1).clamp(max=T)
        idx = torch.arange(T, device=k.device)
        valid = idx[None, :] >= (T - count)[:, None]
        mean = (heads * valid).sum(-1) / count.to(DTYPE)
        return torch.where(self.adaptive[rows], mean, torch.full_like(mean, self.scenario.v_star))

    def _initial_state(self, v0: float) -> tuple[Tensor, Tensor]:
        """One row's platoon at equilibrium at speed ``v0`` (``[1, n]`` positions, speeds); a backend hook."""
        return init_state(1, self.cfg, v0=v0)

    def _physics(self, pos: Tensor, vel: Tensor, u: Tensor, v_head_next: Tensor,
                 params: dict) -> tuple[Tensor, Tensor, Tensor]:
        """Move the rows one step: ``(pos', vel', executed CAV accel)``; a backend hook (SUMO moves them there)."""
        return step(pos, vel, u, v_head_next, self.cfg, self.rng, params=params)

    def _advance(self, rows: Tensor | slice, u: Tensor) -> tuple[Tensor, Tensor]:
        """Step the rows ``rows`` with CAV input ``u``; push the instant into the window. Returns (J, executed).

        ``rows=slice(None)`` (every row, the per-step case) avoids the gathers and scatters.
        """
        sc = self.scenario
        every = isinstance(rows, slice)
        pos, vel = (self.pos, self.vel) if every else (self.pos[rows], self.vel[rows])
        g = gaps(pos, self.cfg)
        g_cav = g[:, self._ci]
        v_star = self.v_star if every else self.v_star[rows]
        k = self.k if every else self.k[rows]
        head = self.head_v if every else self.head_v[rows]
        v_head_next = head.gather(1, (k + 1).clamp(max=head.shape[1] - 1)[:, None]).squeeze(1)
        params = self.hdv if every else {key: v[rows] for key, v in self.hdv.items()}
        new_pos, new_vel, executed = self._physics(pos, vel, u, v_head_next, params)
        J = (sc.weight_v * ((vel[:, 1:] - v_star[:, None]) ** 2).sum(-1)
             + sc.weight_s * ((g_cav - sc.s_star) ** 2).sum(-1)
             + sc.weight_u * (executed ** 2).sum(-1))
        windows = (torch.cat([self.w_vh[rows, 1:], vel[:, :1]], -1),
                   torch.cat([self.w_v[rows, 1:], vel[:, None, 1:]], 1),
                   torch.cat([self.w_s[rows, 1:], g_cav[:, None]], 1),
                   torch.cat([self.w_u[rows, 1:], executed[:, None]], 1))
        acc = (new_vel - vel) / sc.dt
        if every:
            self.w_vh, self.w_v, self.w_s, self.w_u = windows
            self.pos, self.vel, self.acc, self.k = new_pos, new_vel, acc, self.k + 1
        else:
            self.w_vh[rows], self.w_v[rows], self.w_s[rows], self.w_u[rows] = windows
            self.pos[rows], self.vel[rows], self.acc[rows] = new_pos, new_vel, acc
            self.k[rows] += 1
        self.v_star[rows] = self._current_v_star(rows)
        return J, executed

    def _output(self) -> dict:
        sc = self.scenario
        B, T = self.batch_size[0], sc.t_ini
        f = dict(dtype=torch.float32, device=self.device)
        v_star = self.v_star[:, None]
        uini = self.w_u.reshape(B, -1)
        yini = torch.cat([self.w_v - v_star[:, :, None], self.w_s - sc.s_star], -1).reshape(B, -1)
        eini = self.w_vh - v_star
        g = gaps(self.pos, self.cfg)
        y_now = torch.cat([self.vel[:, 1:] - v_star, g[:, self._ci] - sc.s_star], -1)
        e_now = self.vel[:, :1] - v_star
        obs = torch.cat([uini, yini, eini, y_now, e_now], -1) / OBS_SCALE
        ci = [i for i in sc.cav_indices]
        gap_all = torch.cat([torch.full((B, 1), math.inf, dtype=DTYPE), g], -1)
        cav_exec = self.w_u[:, -1]
        cav = {"gap": g[:, self._ci], "speed": self.vel[:, ci], "leader_speed": self.vel[:, [i - 1 for i in ci]],
               "head_gap": self.pos[:, :1] - self.pos[:, ci] - self.cfg.vehicle_length,
               "head_speed": self.vel[:, :1].expand(-1, len(ci)), "accel": cav_exec}
        traffic = {"pos": self.pos, "speed": self.vel, "accel": self.acc, "gap": gap_all,
                   "time": (self.k[:, None] - T) * sc.dt, "v_eq": v_star}
        out = {"observation": obs, "uini": uini, "yini": yini, "eini": eini,
               "deeplcc": {"v_star": v_star, "kind": self.kind[:, None].clone()},
               "cav": cav, "traffic": traffic}
        return _to(out, f)

    # ------------------------------------------------------------------ twin replay (CounterfactualReward)
    #: the per-row simulation state: a twin holding these rows (and the same noise draws) replays them
    STATE = ("pos", "vel", "acc", "k", "head_v", "kind", "adaptive", "v_star", "w_vh", "w_v", "w_s", "w_u")

    #: True: ``step`` keeps the autograd graph from the action to the state and the outputs
    #: (analytic policy gradients, :mod:`mixed_traffic.training.apg`); False: it cuts it
    differentiable: bool = False

    def make_twin(self) -> PlatoonEnv:
        """A second env of this scenario and batch size whose rows can replay this one's (:meth:`copy_rows_from`)."""
        if type(self)._physics is not PlatoonEnv._physics:
            raise ValueError(f"{type(self).__name__}: a twin replays the torch physics with the same noise draws; "
                             "allowed: the torch backend (backend='torch')")
        return PlatoonEnv(batch_size=self.batch_size[0], **dataclasses.asdict(self.scenario))

    def copy_rows_from(self, src: PlatoonEnv, rows: Tensor | None = None) -> None:
        """Set rows ``rows`` (all if None) to ``src``'s state in those rows (same scenario and batch size)."""
        rows = slice(None) if rows is None else rows
        for name in self.STATE:
            getattr(self, name)[rows] = getattr(src, name)[rows]
        for k, v in src.hdv.items():
            self.hdv[k][rows] = v[rows]

    def replay_step(self, u: Tensor, rng_state: Tensor) -> Tensor:
        """Step every row with CAV input ``u`` drawing the noise from ``rng_state``; the stage cost ``J`` [B]."""
        self.rng.set_state(rng_state)
        J, _ = self._advance(slice(None), u.to(DTYPE).reshape(self.batch_size[0], -1))
        return J

    def window(self) -> dict:
        """The DeeP-LCC window of every row (``uini``, ``yini``, ``eini``, float32), as the env outputs it."""
        out = self._output()
        return {k: out[k] for k in ("uini", "yini", "eini")}

    # ------------------------------------------------------------------ EnvBase API
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        sc = self.scenario
        B = self.batch_size[0]
        mask = None
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict.get("_reset").reshape(B).cpu()
        if mask is None:
            mask = torch.ones(B, dtype=torch.bool)
        idx = mask.nonzero().squeeze(-1)
        if idx.numel():
            self._reset_rows(idx)
        out = self._output()
        g = gaps(self.pos, self.cfg)
        j = (sc.weight_v * ((self.vel[:, 1:] - self.v_star[:, None]) ** 2).sum(-1)
             + sc.weight_s * ((g[:, self._ci] - sc.s_star) ** 2).sum(-1))
        out["traffic"]["J"] = j[:, None].to(torch.float32)
        false = torch.zeros(B, 1, dtype=torch.bool, device=self.device)
        out.update(done=false, terminated=false.clone(), truncated=false.clone(), collision=false.clone())
        return TensorDict(out, batch_size=self.batch_size, device=self.device)

    def _reset_rows(self, idx: Tensor) -> None:
        sc = self.scenario
        k, T, nf = int(idx.numel()), sc.t_ini, sc.n_vehicles - 1
        if sc.profile_rows:
            kinds = idx.cpu() % len(sc.profiles)
        else:
            kinds = torch.multinomial(self._weights, k, replacement=True, generator=self.rng)
        head = torch.empty(k, sc.total_steps + 1, dtype=DTYPE)
        for j in kinds.unique().tolist():
            sel = (kinds == j).nonzero().squeeze(-1)
            head[sel] = head_profile(sc.profiles[j], sc.episode_seconds, sc.dt, int(sel.numel()), self.rng,
                                     sc.randomize, sc.brake_start)
        self.head_v[idx] = head
        self.kind[idx] = torch.tensor([PROFILE_KINDS.index(sc.profiles[j]) for j in kinds.tolist()])
        self.adaptive[idx] = torch.tensor([sc.profiles[j] in ADAPTIVE_KINDS for j in kinds.tolist()])
        if sc.mismatch == "hetero_ovm":
            for name in ("alpha", "beta", "v_max", "s_st", "s_go"):
                nominal = float(getattr(OVMParams(), name))
                spread = 1.0 + sc.hetero_spread * (2.0 * torch.rand(k, nf, generator=self.rng, dtype=DTYPE) - 1.0)
                self.hdv[name][idx] = nominal * spread
        for r, v0 in zip(idx.tolist(), head[:, 0].tolist(), strict=True):
            p, v = self._initial_state(v0)
            self.pos[r], self.vel[r] = p[0], v[0]
        self.vel[idx, 0] = head[:, 0]
        self.acc[idx] = 0.0
        self.k[idx] = 0
        self.w_vh[idx] = head[:, :1].expand(k, T)
        self.w_v[idx] = self.vel[idx][:, None, 1:].expand(k, T, nf)
        self.w_s[idx] = gaps(self.pos[idx], self.cfg)[:, None, self._ci].expand(k, T, sc.n_cav)
        self.w_u[idx] = 0.0
        self.v_star[idx] = self._current_v_star(idx)
        zero = torch.zeros(k, sc.n_cav, dtype=DTYPE)
        for _ in range(T):  # fill the past-data window with zero CAV input
            self._advance(idx, zero)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        sc = self.scenario
        B = self.batch_size[0]
        action = tensordict.get("action")
        if action.shape != (B, sc.n_cav):
            raise ValueError(f"action: shape {tuple(action.shape)} is invalid; allowed: {(B, sc.n_cav)} "
                             "(batch, n_cav) accelerations in m/s^2")
        if not bool(torch.isfinite(action).all()):
            raise ValueError("action: non-finite values; allowed: finite accelerations in m/s^2")
        J, _ = self._advance(slice(None), (action if self.differentiable else action.detach()).cpu().to(DTYPE))
        g = gaps(self.pos, self.cfg)
        cav_g = g[:, self._ci]
        collision = (g <= 0).any(-1, keepdim=True)
        cost = ((sc.s_min - cav_g.clamp_min(0.0)).clamp_min(0.0) / sc.s_min
                + (cav_g - sc.s_max).clamp_min(0.0) / sc.s_max).sum(-1, keepdim=True)
        truncated = (self.k >= sc.total_steps)[:, None]
        out = self._output()
        out["traffic"]["J"] = J[:, None].to(torch.float32)
        out.update(reward=(-J[:, None]).to(torch.float32), cost=cost.to(torch.float32), collision=collision,
                   terminated=collision.clone(), truncated=truncated & ~collision, done=collision | truncated)
        return TensorDict(_to(out, dict(device=self.device)), batch_size=self.batch_size, device=self.device)


def _to(tree: dict, kw: dict) -> dict:
    return {k: (_to(v, kw) if isinstance(v, dict) else v.to(**kw) if v.is_floating_point() else v.to(kw["device"]))
            for k, v in tree.items()}


__all__ = ["PlatoonEnv", "PlatoonScenario", "PROFILE_KINDS", "MISMATCH", "head_profile", "get_platoon_scenario"]
