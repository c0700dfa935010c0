"""Batched car-following environment in pure torch (ring road or open road).

``B`` independent scenarios are stepped as tensor operations; each row resets on
its own when it collides or reaches the time limit. Physics, profiles and the
reward are the pure functions of :mod:`mixed_traffic.physics`,
:mod:`mixed_traffic.profiles` and :func:`stage_terms`, which the SUMO backend shares.

>>> from mixed_traffic import make_env
>>> from torchrl.envs.utils import check_env_specs
>>> env = make_env("ring", batch_size=4, seed=0)
>>> check_env_specs(env)
>>> td = env.rollout(10)
>>> td["next", "cav", "gap"].shape
torch.Size([4, 10, 1])
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from mixed_traffic.physics import (
    IDMParams,
    KraussParams,
    car_following_accel,
    idm_accel,
    idm_equilibrium_speed,
    integrate,
    leader_gaps,
    params_as_tensors,
    sumo_speed_mode_95,
)
from mixed_traffic.scenarios import TrafficScenario, get_scenario

Tensor = torch.Tensor


# ----------------------------------------------------------------------------- shared pieces
OBS_FEATURES = {"seed": None, "relative": 7, "relative_accel": 8, "relative_no_speed": 6, "relative_time": 8,
                "wave": 5, "wave_ring": 6, "wave_ring_time": 7}
ENGAGE_SECONDS = 30.0  # observation="relative_time": the time since engaging saturates here


def observation_dim(sc: TrafficScenario) -> int:
    return 2 * sc.n_vehicles if sc.observation == "seed" else OBS_FEATURES[sc.observation] * sc.n_cav


def cav_keys(sc: TrafficScenario) -> tuple[str, ...]:
    """The ``("cav", ...)`` entries: head gap/speed with a head, the CAV's mean speed without;
    ``leader_accel``: the leader's acceleration of the last step (what CACC receives over V2V);
    ``override`` (1.0 where SUMO's speed mode 95 changed the command) with ``sumo_safety``."""
    head = ("head_gap", "head_speed") if sc.head else ("speed_avg",)
    return ("gap", "speed", "leader_speed", "leader_accel", *head, "accel") + (("override",) if sc.sumo_safety else ())


def make_specs(sc: TrafficScenario, batch: tuple[int, ...], device=None, dtype=torch.float32) -> dict:
    """Specs of the car-following envs (both backends use these, so keys cannot drift)."""
    n, nc = sc.n_vehicles, sc.n_cav

    def u(*shape):
        return Unbounded(shape=(*batch, *shape), dtype=dtype, device=device)

    def flag():
        return Categorical(2, shape=(*batch, 1), dtype=torch.bool, device=device)

    cav = Composite({k: u(nc) for k in cav_keys(sc)}, shape=batch, device=device)
    traffic_1 = ("time", "v_eq", "J") + (("ring_length",) if sc.is_ring else ())
    traffic = Composite({**{k: u(n) for k in ("pos", "speed", "accel", "gap")},
                         **{k: u(1) for k in traffic_1}}, shape=batch, device=device)
    observation = Composite(observation=u(observation_dim(sc)), cav=cav, traffic=traffic, collision=flag(),
                            shape=batch, device=device)
    lo, hi = sc.cav_accel_bounds
    action = Bounded(low=torch.full((*batch, nc), lo, dtype=dtype, device=device),
                     high=torch.full((*batch, nc), hi, dtype=dtype, device=device),
                     shape=(*batch, nc), dtype=dtype, device=device)
    reward = Composite(reward=u(1), cost=u(1), shape=batch, device=device)
    done = Composite(done=flag(), terminated=flag(), truncated=flag(), shape=batch, device=device)
    return {"observation": observation, "action": action, "reward": reward, "done": done}


def uniform_flow_speed(sc: TrafficScenario, ring_length: Tensor | float) -> Tensor:
    """Speed of the ring's uniform flow: the humans' nominal IDM in equilibrium at gap ``L / n - l``.

    The physical optimum of a wave damper on a ring of length ``L`` (every car at the same
    gap and speed); per row when ``ring_length`` is a tensor.
    """
    p = dataclasses.asdict(sc.hdv_defaults())
    return idm_equilibrium_speed(torch.as_tensor(ring_length, dtype=torch.float64) / sc.n_vehicles - sc.vehicle_length,
                                 **p)


def stage_terms(sc: TrafficScenario, speed: Tensor, gap: Tensor, cav_accel: Tensor, v_eq: Tensor,
                v_ref: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Stage cost J and the constraint cost, both ``[..., 1]``.

    ``reward="deeplcc"``: J = w_v sum_{i != head} (v_i - v_eq)^2 + w_s sum_cav clip(s - s*, +-clip)^2
    + w_u sum_cav a^2 (every vehicle's speed counts when there is no head).
    ``reward="wave"``: J = 1 - r, r = w_v mean(v)/v* - w_s std(v)/v* - w_u sum_cav |a|/a_max.
    ``reward="wave_relative"``: the same with ``v* = v_ref`` (``[..., 1]``, per row: the ring's
    uniform-flow speed), so rings of different lengths score on one scale (1 = uniform flow).
    cost = sum_cav max(0, s_min - s) / s_min  (gap clamped at 0, so each term is in [0, 1])
    """
    cav_gap = gap[..., list(sc.cav_indices)]
    if sc.reward in ("wave", "wave_relative"):
        a_max = max(abs(sc.cav_accel_bounds[0]), abs(sc.cav_accel_bounds[1]))
        if sc.reward == "wave_relative" and v_ref is None:
            raise ValueError("stage_terms: reward='wave_relative' needs the ring's uniform-flow speed (v_ref=)")
        scale = sc.v_star if sc.reward == "wave" else v_ref.to(speed.dtype)
        r = (sc.weight_v * speed.mean(-1, keepdim=True) / scale
             - sc.weight_s * speed.std(-1, unbiased=False, keepdim=True) / scale
             - sc.weight_u * cav_accel.abs().sum(-1, keepdim=True) / a_max)
        j = 1.0 - r
    else:
        hdv_speed = speed[..., 1:] if sc.head else speed
        j = (sc.weight_v * (hdv_speed - v_eq).pow(2).sum(-1, keepdim=True)
             + sc.weight_s * (cav_gap - sc.s_star).clamp(-sc.spacing_clip, sc.spacing_clip).pow(2).sum(-1, keepdim=True)
             + sc.weight_u * cav_accel.pow(2).sum(-1, keepdim=True))
    cost = ((sc.s_min - cav_gap.clamp_min(0.0)).clamp_min(0.0) / sc.s_min).sum(-1, keepdim=True)
    return j, cost


def head_gaps(sc: TrafficScenario, pos: Tensor, ring_length: Tensor | float | None = None) -> Tensor:
    """Distance from each CAV's front bumper to the head's rear bumper along the road."""
    d = pos[..., :1] - pos[..., list(sc.cav_indices)]
    if sc.is_ring:
        d = torch.remainder(d, sc.ring_length if ring_length is None else ring_length)
    return d - sc.vehicle_length


def relative_features(v: Tensor, v_lead: Tensor, gap: Tensor, head_gap: Tensor, v_head: Tensor, v_eq: Tensor,
                      cav_accel: Tensor, *, s_max: float, a_scale: float) -> list[Tensor]:
    """The seven features every ``"relative"`` observation starts with, per CAV: own speed, the leader's and
    the head's speed relative to it, the gap and the gap to the head, the uniform-flow speed relative to it,
    its last acceleration (each ``[..., n_cav]``). Linear in its inputs, so it also gives how the features move
    when the inputs move (:class:`transforms.SensorNoise`)."""
    return [v / 30.0, (v_lead - v) / 10.0, gap / s_max, head_gap / (2 * s_max), (v_head - v) / 10.0,
            (v_eq - v) / 10.0, cav_accel / a_scale]


def observe(sc: TrafficScenario, pos: Tensor, speed: Tensor, gap: Tensor, cav_accel: Tensor, v_eq: Tensor,
            *, ring_length: Tensor | float | None = None, speed_avg: Tensor | None = None,
            accel: Tensor | None = None, time: Tensor | None = None) -> Tensor:
    """The policy input (see ``TrafficScenario.observation``).

    ``ring_length`` (per row, ``[..., 1]``) defaults to the scenario's; ``speed_avg``
    (each CAV's mean speed, ``[..., n_cav]``) is needed by ``observation="wave"``, ``accel``
    (every vehicle's last acceleration, ``[..., n]``) by ``observation="relative_accel"``.
    """
    L = sc.ring_length if ring_length is None else ring_length
    if sc.observation == "seed":
        if sc.is_ring:
            p = torch.remainder(pos, L) / L
        else:
            p = (pos - pos[..., :1]) / 100.0
        return torch.cat([speed / 30.0, p], dim=-1)
    ci = list(sc.cav_indices)
    v = speed[..., ci]
    v_lead = speed[..., [i - 1 for i in ci]]
    a_scale = max(abs(sc.cav_accel_bounds[0]), abs(sc.cav_accel_bounds[1]))
    if sc.observation in ("wave", "wave_ring", "wave_ring_time"):
        feats = [v / 10.0, (v_lead - v) / 10.0, gap[..., ci] / 20.0, (speed_avg - v) / 10.0, cav_accel / a_scale]
        if sc.observation != "wave":  # the ring's length, which sets its uniform-flow speed
            ring = L if torch.is_tensor(L) else torch.full_like(v[..., :1], float(L))
            feats.append(ring.expand_as(v) / 260.0)
        if sc.observation == "wave_ring_time":  # time since the controller engaged, saturating at 600 s
            if time is None:
                raise ValueError("observe: observation='wave_ring_time' needs the episode time (time=)")
            feats.append((time / 600.0).clamp(0.0, 1.0).expand_as(v))
    else:
        feats = relative_features(v, v_lead, gap[..., ci], head_gaps(sc, pos, L), speed[..., :1], v_eq, cav_accel,
                                  s_max=sc.s_max, a_scale=a_scale)
        if sc.observation == "relative_accel":
            if accel is None:
                raise ValueError("observe: observation='relative_accel' needs every vehicle's acceleration (accel=)")
            feats.append(accel[..., [i - 1 for i in ci]] / a_scale)
        elif sc.observation == "relative_no_speed":
            feats = feats[1:]
        elif sc.observation == "relative_time":  # time since the controller engaged, saturating at 30 s
            if time is None:
                raise ValueError("observe: observation='relative_time' needs the episode time (time=)")
            feats.append((time / ENGAGE_SECONDS).clamp(0.0, 1.0).expand_as(v))
    return torch.stack(feats, dim=-1).flatten(-2)


def initial_positions(sc: TrafficScenario, rows: Tensor, rng: torch.Generator, *, device=None,
                      dtype=torch.float32) -> tuple[Tensor, Tensor]:
    """Initial positions ``[k, n]`` and ring lengths ``[k, 1]`` of the rows ``rows`` being reset.

    Centre-to-centre spacing per row: ``init_spacing_range`` (a bumper gap drawn per
    episode) or ``init_spacing_rows`` (row ``i`` takes entry ``i % len``) when set, else
    ``init_spacing``, else the ring's even spacing ``L / n`` (open road: the equilibrium
    gap), which ``init_wave`` turns into one stop-and-go wave. Draws from ``rng`` in a
    fixed order: ring length, wave phase, start gap. Both backends call it, so the same
    seed gives the same start (ring length, wave phase) in torch and in SUMO.
    """
    k = int(rows.numel())
    f = dict(dtype=dtype, device=device)
    idx = torch.arange(sc.n_vehicles, **f)
    lo, hi = sc.ring_lengths
    if sc.is_ring:
        L = lo + (hi - lo) * torch.rand(k, 1, generator=rng).to(**f) if hi > lo else torch.full((k, 1), lo, **f)
        spacing = L / sc.n_vehicles if sc.init_spacing is None else torch.full_like(L, sc.init_spacing
                                                                                   + sc.vehicle_length)
    else:
        L = torch.full((k, 1), float(sc.ring_length), **f)
        spacing = torch.full((k, 1), sc.initial_spacing() + sc.vehicle_length, **f)
    phi = 2 * torch.pi * torch.rand(k, 1, generator=rng).to(**f) if sc.init_wave > 0 else None
    if sc.init_spacing_range is not None:
        g_lo, g_hi = sc.init_spacing_range
        if sc.is_ring:
            g_hi = min(g_hi, sc.ring_length / sc.n_vehicles - sc.vehicle_length)
        spacing = (g_lo + (g_hi - g_lo) * torch.rand(k, 1, generator=rng)).to(**f) + sc.vehicle_length
        phi = None
    elif sc.init_spacing_rows is not None:
        gaps = torch.tensor(sc.init_spacing_rows, **f)
        spacing = gaps[rows.to(gaps.device) % len(gaps)].unsqueeze(-1) + sc.vehicle_length
        phi = None
    offs = -spacing * idx
    if phi is not None:
        # gaps g (1 + A sin(2 pi i / n + phi)): one stop-and-go wave around the ring, random phase
        gap = spacing - sc.vehicle_length
        gaps = gap * (1 + sc.init_wave * torch.sin(2 * torch.pi * idx / sc.n_vehicles + phi))
        offs = -torch.cumsum(gaps + sc.vehicle_length, dim=-1)
        offs = offs - offs[:, :1]
    return (torch.remainder(offs, L) if sc.is_ring else offs), L


def check_action_finite(action: Tensor) -> None:
    """A NaN/inf action would leave its row's state NaN for the rest of the episode: refuse it."""
    finite = torch.isfinite(action)
    if not bool(finite.all()):
        rows = (~finite).reshape(finite.shape[0], -1).any(-1).nonzero().flatten().tolist()
        raise ValueError(f"action: non-finite values in row(s) {rows[:10]}; allowed: finite accelerations in m/s^2 "
                         "(clipped to cav_accel_bounds)")


# ----------------------------------------------------------------------------- the env
class TrafficEnv(EnvBase):
    """Batched ring/open-road car-following environment (see the module docstring).

    Args:
        scenario: a preset name (``"ring"``, ``"deeplcc"``) or a :class:`TrafficScenario`.
        batch_size: number of independent rows.
        device: torch device of all tensors.
        **overrides: scenario fields to override.

    With ``sumo_safety=True`` the CAVs' commands pass SUMO's speed mode 95
    (:func:`~mixed_traffic.physics.sumo_speed_mode_95`: capped by the Krauss safe speed of
    the SUMO backend's CAV vType, then by the accel/decel bounds), as on the SUMO backend.
    ``("cav", "override")`` marks the changed commands; ``override_steps`` (row-steps
    with at least one CAV changed) and ``override_count`` ((row, CAV, step) triples) count
    them over the env's life, like :class:`~mixed_traffic.envs.sumo_ring.SumoRingEnv`'s.

    >>> env = TrafficEnv("ring", batch_size=2, sumo_safety=True)
    >>> td = env.rollout(50, lambda td: td.set("action", torch.full((2, 1), 3.0)))
    >>> env.override_steps > 0, td["next", "cav", "override"].shape
    (True, torch.Size([2, 50, 1]))
    """

    batch_locked = True

    def __init__(self, scenario: str | TrafficScenario = "ring", *, batch_size: int = 1,
                 device: str | torch.device = "cpu", **overrides):
        if isinstance(scenario, TrafficScenario):
            sc = dataclasses.replace(scenario, **overrides).validate()
        else:
            sc = get_scenario(scenario, **overrides)
        super().__init__(device=device, batch_size=torch.Size([batch_size]))
        self.scenario = sc
        self.dt = sc.dt
        self.J_max = sc.J_max
        self.profile = sc.make_profile()
        self.rng = torch.Generator().manual_seed(0)
        self.row_rngs: list[torch.Generator] | None = None  # seed_rows
        self.start_period: int | None = None  # share_starts
        B, n = batch_size, sc.n_vehicles
        specs = make_specs(sc, (B,), device=self.device)
        self.observation_spec = specs["observation"]
        self.action_spec = specs["action"]
        self.reward_spec = specs["reward"]
        self.done_spec = specs["done"]

        f = dict(dtype=torch.float32, device=self.device)
        self._cav = torch.tensor(sc.cav_indices, dtype=torch.long, device=self.device)
        self._a_lo, self._a_hi = sc.cav_accel_bounds
        self._exec_lo = sc.cav_exec_bounds[0]  # below _a_lo only for the safety layer's emergency braking
        self._head_lo, self._head_hi = sc.head_accel_bounds
        self._head_idm = params_as_tensors(IDMParams(), (), **f)
        self._hdv_base = sc.hdv_defaults()
        # the humans' parameters drawn per episode (hdv_param_noise > 0), in drawing order
        names = {f.name for f in dataclasses.fields(self._hdv_base)}
        self._noisy = [n for n in ("alpha", "beta", "v_max", "s_st", "s_go", "v0", "T", "a", "b", "s0")
                       if n in names] if sc.hdv_param_noise > 0 else []
        self._window = max(1, int(round(sc.v_eq_window / sc.dt)))
        self._cav_window = max(1, int(round(sc.cav_speed_window / sc.dt)))
        self._hdv_lo = float(self._hdv_base.a_min)
        self._hdv_hi = float(self._hdv_base.a_max)
        if sc.sumo_safety and sc.integration != "euler":
            raise ValueError(f"integration: {sc.integration!r} is invalid with sumo_safety=True; allowed: 'euler' "
                             "(the Krauss safe speed modelled is SUMO's default Euler update)")
        self.override_steps = 0  # row-steps in which speed mode 95 changed a CAV's command
        self.override_count = 0  # (row, CAV, step) triples changed
        self._override = torch.zeros(B, sc.n_cav, **f)
        # state
        self.pos = torch.zeros(B, n, **f)
        self.vel = torch.zeros(B, n, **f)
        self.acc = torch.zeros(B, n, **f)
        self.step_count = torch.zeros(B, dtype=torch.long, device=self.device)
        self.profile_params = self.profile.sample(B, self.rng).to(self.device)
        self.hdv_params = params_as_tensors(self._hdv_base, (B, n), **f)
        self.head_hist = torch.zeros(B, self._window, **f)
        self.head_sum = torch.zeros(B, **f)
        self.ring_len = torch.full((B, 1), float(sc.ring_length), **f)
        self.v_ref = uniform_flow_speed(sc, self.ring_len).to(**f) if sc.reward == "wave_relative" else None
        self.cav_hist = torch.zeros(B, self._cav_window, sc.n_cav, **f)
        self.cav_sum = torch.zeros(B, sc.n_cav, **f)

    # ------------------------------------------------------------------ helpers
    def _initial_positions(self, rows: Tensor, rng: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
        """Initial positions ``[k, n]`` and ring lengths ``[k, 1]`` of the rows being reset
        (:func:`initial_positions`, from ``rng``, by default the env's generator)."""
        return initial_positions(self.scenario, rows, self.rng if rng is None else rng, device=self.device)

    def _v_eq(self) -> Tensor:
        count = (self.step_count + 1).clamp(max=self._window).to(self.head_sum.dtype)
        return (self.head_sum / count).unsqueeze(-1)

    def _push_head_speed(self, v_head: Tensor, step: Tensor) -> None:
        """Record the head speed of step ``step`` in the rolling window (slot step % W)."""
        slot = (step % self._window).unsqueeze(-1)
        old = self.head_hist.gather(1, slot).squeeze(-1)
        full = step >= self._window
        self.head_sum = self.head_sum + v_head - torch.where(full, old, torch.zeros_like(old))
        # out of place: a differentiable rollout (analytic policy gradients) reads the old window
        self.head_hist = self.head_hist.scatter(1, slot, v_head.unsqueeze(-1))

    def _gaps(self, pos: Tensor) -> Tensor:
        sc = self.scenario
        return leader_gaps(pos, sc.vehicle_length, self.ring_len if sc.is_ring else None)

    def _push_cav_speed(self, v_cav: Tensor, step: Tensor) -> None:
        """Each CAV's speed of step ``step`` into its rolling window (``("cav", "speed_avg")``)."""
        slot = (step % self._cav_window)
        rows = torch.arange(v_cav.shape[0], device=v_cav.device)
        old = self.cav_hist[rows, slot]
        full = (step >= self._cav_window).unsqueeze(-1)
        self.cav_sum = self.cav_sum + v_cav - torch.where(full, old, torch.zeros_like(old))
        self.cav_hist = self.cav_hist.index_put((rows, slot), v_cav)  # out of place, as head_hist

    def _cav_speed_avg(self) -> Tensor:
        count = (self.step_count + 1).clamp(max=self._cav_window).to(self.cav_sum.dtype).unsqueeze(-1)
        return self.cav_sum / count

    def _tracked_speed(self, vel: Tensor) -> Tensor:
        """The speed averaged into ``v_eq``: the head's, or the ring's mean without a head."""
        return vel[:, 0] if self.scenario.head else vel.mean(-1)

    def _output(self, gap: Tensor, v_eq: Tensor, j: Tensor) -> dict:
        sc = self.scenario
        cav_acc = self.acc[:, self._cav]
        ci = self._cav
        cav = {"gap": gap[:, ci], "speed": self.vel[:, ci], "leader_speed": self.vel[:, ci - 1],
               "leader_accel": self.acc[:, ci - 1], "accel": cav_acc}
        if sc.sumo_safety:
            cav["override"] = self._override
        speed_avg = None
        if sc.head:
            cav["head_gap"] = head_gaps(sc, self.pos, self.ring_len)
            cav["head_speed"] = self.vel[:, :1].expand(-1, len(ci))
        else:
            speed_avg = cav["speed_avg"] = self._cav_speed_avg()
        traffic = {
            "pos": self.pos, "speed": self.vel, "accel": self.acc, "gap": gap,
            "time": (self.step_count.unsqueeze(-1) * sc.dt).to(gap.dtype), "v_eq": v_eq, "J": j,
        }
        if sc.is_ring:
            traffic["ring_length"] = self.ring_len
        return {
            "observation": observe(sc, self.pos, self.vel, gap, cav_acc, v_eq, ring_length=self.ring_len,
                                   speed_avg=speed_avg, accel=self.acc, time=traffic["time"]),
            "cav": cav,
            "traffic": traffic,
        }

    def set_profile(self, profile) -> None:
        """Drive the head by ``profile`` (any object with ``sample``/``speed``) from the next reset on.

        E.g. a :class:`~mixed_traffic.profiles.RowProfiles` runs several head profiles
        side by side in one batch.
        """
        self.profile = profile
        B = self.batch_size[0]
        self.profile_params = self._sample_profile(torch.arange(B))

    def _sample_profile(self, rows: Tensor, rng: torch.Generator | None = None) -> Tensor:
        """Fresh profile parameters of the rows ``rows`` (row-aware profiles keep each row's part)."""
        rng = self.rng if rng is None else rng
        if hasattr(self.profile, "sample_rows"):
            return self.profile.sample_rows(rows.cpu(), rng).to(self.device)
        return self.profile.sample(int(rows.numel()), rng).to(self.device)

    def seed_rows(self, seeds: Sequence[int] | None) -> None:
        """Draw row ``i``'s episodes from a generator of its own, seeded ``seeds[i]``.

        Row ``i`` then runs what a one-row env seeded ``seeds[i]`` runs: the same start (ring
        length, positions), head profile parameters, humans' parameters and per-step noise,
        whatever the batch size and whatever the other rows do. The evaluation uses it so that
        every controller, and one policy with and without its safety layer, meet the same
        episodes (``mixed_traffic.evaluation.harness``). Takes effect from the next reset;
        ``None`` goes back to the env's one generator.

        >>> env = TrafficEnv("ring", batch_size=3, episode_seconds=5.0)
        >>> env.seed_rows([7, 8, 9])
        >>> one = TrafficEnv("ring", batch_size=1, episode_seconds=5.0)
        >>> _ = one.set_seed(8)
        >>> bool((env.reset()["cav", "gap"][1] == one.reset()["cav", "gap"][0]).all())
        True
        """
        if seeds is None:
            self.row_rngs = None
            return
        seeds = [int(s) for s in seeds]
        if len(seeds) != self.batch_size[0]:
            raise ValueError(f"seed_rows: {len(seeds)} seeds is invalid; allowed: None or one seed per row "
                             f"({self.batch_size[0]})")
        self.row_rngs = [torch.Generator().manual_seed(s) for s in seeds]

    # ------------------------------------------------------------------ EnvBase API
    def share_starts(self, period: int | None) -> None:
        """Start row ``i`` in the same state as row ``i % period`` (common random numbers).

        From the next reset on, rows ``i, i + period, i + 2 period, ...`` start the same
        episode: ring length, positions, speeds, the humans' parameters and the head profile's;
        only the humans' per-step noise differs. Comparing policies row block by row block
        then compares them on the same episodes (``mixed_traffic.training.cem`` scores its
        candidates so). ``None`` switches it off.
        """
        B = self.batch_size[0]
        if period is not None and not (isinstance(period, int) and 1 <= period <= B and B % period == 0):
            raise ValueError(f"share_starts: period={period!r} is invalid; allowed: None or a divisor of the "
                             f"batch size {B}")
        self.start_period = period

    def _share_starts(self, mask: Tensor) -> None:
        B = self.batch_size[0]
        rows = torch.arange(B, device=self.device)
        src = rows % self.start_period
        copy = mask & mask[src] & (rows != src)  # the source row starts a new episode in the same reset
        if not bool(copy.any()):
            return
        dst, src = rows[copy], src[copy]
        for name in ("pos", "vel", "ring_len", "v_ref", "profile_params"):
            t = getattr(self, name)
            if t is not None:
                t[dst] = t[src]
        for t in self.hdv_params.values():
            t[dst] = t[src]

    def _set_seed(self, seed: int | None) -> None:
        self.rng.manual_seed(int(seed) if seed is not None else torch.seed() % (2**63))

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        B, sc = self.batch_size[0], self.scenario
        mask = None
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict.get("_reset").reshape(B)
        if mask is None:
            mask = torch.ones(B, dtype=torch.bool, device=self.device)
        idx = mask.nonzero().squeeze(-1)
        k = int(idx.numel())
        if k:
            if self.row_rngs is None:
                draws = [self._draw_episodes(idx, self.rng)]
            else:  # each row from its own generator, as a one-row env would draw
                draws = [self._draw_episodes(idx[j:j + 1], self.row_rngs[int(i)]) for j, i in enumerate(idx)]
            pos, ring_len, prof, hdv = (torch.cat(parts) for parts in zip(*draws))
            self.pos[idx], self.ring_len[idx] = pos, ring_len
            if self.v_ref is not None:
                self.v_ref[idx] = uniform_flow_speed(sc, self.ring_len[idx]).to(self.v_ref.dtype)
            self.vel[idx] = sc.v_init
            self.step_count[idx] = 0
            self.profile_params[idx] = prof
            for j, name in enumerate(self._noisy):
                self.hdv_params[name][idx] = hdv[:, j]
            if self.start_period:
                self._share_starts(mask)
            self.acc = self.acc.clone()
            self.acc[idx] = 0.0
            self.head_hist[idx] = 0.0
            self.head_sum[idx] = 0.0
            self._push_head_speed_rows(idx)
            self.cav_hist[idx] = 0.0
            self.cav_hist[idx, 0] = self.vel[idx][:, self._cav]
            self.cav_sum[idx] = self.vel[idx][:, self._cav]
            self._override = self._override.clone()
            self._override[idx] = 0.0
        gap = self._gaps(self.pos)
        if k and sc.reset_accel == "model":
            model = self._drivers_accel(gap, self.vel, torch.roll(self.vel, 1, dims=-1), noise=False)
            model[:, self._cav] = model[:, self._cav].clamp(self._a_lo, self._a_hi)
            self.acc[idx] = model[idx].to(self.acc.dtype)
        v_eq = self._v_eq()
        j, _ = stage_terms(sc, self.vel, gap, self.acc[:, self._cav], v_eq, self.v_ref)
        out = self._output(gap, v_eq, j)
        false = torch.zeros(B, 1, dtype=torch.bool, device=self.device)
        out.update(done=false, terminated=false.clone(), truncated=false.clone(), collision=false.clone())
        return TensorDict(out, batch_size=self.batch_size, device=self.device)

    def _draw_episodes(self, idx: Tensor, rng: torch.Generator):
        """``(positions, ring lengths, profile parameters, humans' parameters [k, p, n])`` of new
        episodes for rows ``idx``, drawn from ``rng`` in a fixed order."""
        sc, k = self.scenario, int(idx.numel())
        pos, ring_len = self._initial_positions(idx, rng)
        prof = self._sample_profile(idx, rng)
        names = self._noisy
        hdv = torch.zeros(k, len(names), sc.n_vehicles, dtype=self.pos.dtype, device=self.device)
        if names:
            base = params_as_tensors(self._hdv_base, (k, sc.n_vehicles), device=self.device)
            for j, name in enumerate(names):
                noise = 1.0 + sc.hdv_param_noise * (2 * torch.rand(k, sc.n_vehicles, generator=rng) - 1)
                hdv[:, j] = base[name] * noise.to(self.device)
        return pos, ring_len, prof, hdv

    def _vtype_decel(self) -> Tensor:
        """Each vehicle's SUMO vType ``decel`` ``[B, n]`` (what SUMO's safe speed assumes of a leader).

        Head: ``-head_accel_bounds[0]``; CAVs: ``-cav_accel_bounds[0]``; humans: IDM ``b``
        (OVM: ``-a_min``), as the SUMO backend writes them.
        """
        sc = self.scenario
        hdv = self.hdv_params["b"] if "b" in self.hdv_params else -self.hdv_params["a_min"]
        decel = hdv.clone()
        if sc.head:
            decel[:, 0] = -self._head_lo
        decel[:, self._cav] = -self._a_lo
        return decel

    def _speed_mode_95(self, cav_accel: Tensor, gap: Tensor, vel: Tensor) -> tuple[Tensor, Tensor]:
        """SUMO's speed mode 95 on the CAVs' (clipped) commands: executed accelerations and the override flags."""
        ci = self._cav
        lead = (ci - 1) % self.scenario.n_vehicles
        return sumo_speed_mode_95(cav_accel, gap[:, ci], vel[:, ci], vel[:, lead], accel_max=self._a_hi,
                                  decel=-self._a_lo, leader_decel=self._vtype_decel()[:, lead], dt=self.scenario.dt,
                                  params=KraussParams(emergency_decel=max(-self._a_lo, KraussParams.emergency_decel)))

    def _push_head_speed_rows(self, idx: Tensor) -> None:
        v = self._tracked_speed(self.vel[idx])
        self.head_hist[idx, 0] = v
        self.head_sum[idx] = v

    def _drivers_accel(self, gap: Tensor, vel: Tensor, v_lead: Tensor, *, noise: bool) -> Tensor:
        """Every vehicle's command ``[B, n]`` from this state but the CAVs' own: the humans' model
        (with ``accel_noise`` when ``noise``) in every column, the head's profile command in column 0."""
        sc = self.scenario
        acc = car_following_accel(sc.hdv_model, gap, vel, v_lead, self.hdv_params)
        if noise and sc.accel_noise > 0:
            if self.row_rngs is None:
                draw = torch.randn(vel.shape, generator=self.rng).to(acc)
            else:
                draw = torch.cat([torch.randn(1, vel.shape[-1], generator=g) for g in self.row_rngs]).to(acc)
            acc = torch.minimum(torch.maximum(acc + sc.accel_noise * draw, self.hdv_params["a_min"]),
                                self.hdv_params["a_max"])
        if sc.head:
            # head: track the profile's next speed within its bounds; on a ring never into its leader
            t_next = (self.step_count + 1).to(vel.dtype) * sc.dt
            v_target = self.profile.speed(t_next, self.profile_params)
            a_head = ((v_target - vel[:, 0]) / sc.dt).clamp(self._head_lo, self._head_hi)
            if sc.is_ring:
                a_safe = idm_accel(gap[:, 0], vel[:, 0], v_lead[:, 0], **self._head_idm)
                a_head = torch.minimum(a_head, a_safe).clamp_min(self._head_lo)
            acc = torch.cat([a_head.unsqueeze(-1), acc[:, 1:]], -1)
        return acc

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        sc = self.scenario
        action = tensordict.get("action")
        if action.shape != (self.batch_size[0], sc.n_cav):
            raise ValueError(f"action: shape {tuple(action.shape)} is invalid; allowed: "
                             f"{(self.batch_size[0], sc.n_cav)} (batch, n_cav) accelerations in m/s^2")
        check_action_finite(action)
        pos, vel = self.pos, self.vel
        gap = self._gaps(pos)
        v_lead = torch.roll(vel, 1, dims=-1)
        acc = self._drivers_accel(gap, vel, v_lead, noise=True)
        acc[:, self._cav] = action.to(acc.dtype).clamp(self._exec_lo, self._a_hi)
        if sc.sumo_safety:
            acc[:, self._cav], over = self._speed_mode_95(acc[:, self._cav], gap, vel)
            self._override = over.to(acc.dtype)
            self.override_count += int(over.sum())
            self.override_steps += int(over.any(-1).sum())
        new_pos, new_vel, executed = integrate(pos, vel, acc, sc.dt, sc.integration)
        if sc.is_ring:
            new_pos = torch.remainder(new_pos, self.ring_len)
        self.pos, self.vel, self.acc = new_pos, new_vel, executed
        self.step_count = self.step_count + 1
        self._push_head_speed(self._tracked_speed(new_vel), self.step_count)
        if not sc.head:
            self._push_cav_speed(new_vel[:, self._cav], self.step_count)
        new_gap = self._gaps(new_pos)
        collision = (new_gap[:, 1:] <= 0).any(-1, keepdim=True)
        if sc.is_ring:
            collision = collision | (new_gap[:, :1] <= 0)
        v_eq = self._v_eq()
        j, cost = stage_terms(sc, new_vel, new_gap, executed[:, self._cav], v_eq, self.v_ref)
        truncated = (self.step_count >= sc.max_steps).unsqueeze(-1)
        out = self._output(new_gap, v_eq, j)
        out.update(reward=-j, cost=cost, collision=collision, terminated=collision,
                   truncated=truncated & ~collision, done=collision | truncated)
        return TensorDict(out, batch_size=self.batch_size, device=self.device)
