"""The DeeP-LCC platoon in SUMO: a straight road driven in-process through libsumo.

Two layers:

- :class:`SumoPlatoon` is the SUMO counterpart of :func:`mixed_traffic.controllers.deeplcc.platoon.step`:
  ``start(v0)`` puts the platoon (head + 8 followers) at equilibrium on a straight
  single-lane road, ``step(u, v_head_next)`` moves it one ``dt``. The pre-collection
  (:func:`~mixed_traffic.controllers.deeplcc.precollect.precollect`), the closed loop
  (:func:`~mixed_traffic.controllers.deeplcc.closed_loop.run_closed_loop`) and ``mt-dataset
  backend=sumo`` take it as their ``simulator``.
- :class:`SumoPlatoonEnv` (``make_env("platoon", backend="sumo")``) is
  :class:`~mixed_traffic.envs.platoon.PlatoonEnv` with SUMO moving the cars: same keys,
  specs, head profiles, window, stage cost, reward and cost (it subclasses the torch env and
  replaces only its two physics hooks), batch size ``[1]``.

How the platoon maps onto SUMO:

- road: one edge (``build_straight_network``), long enough for the episode at 35 m/s;
  one edge means every vehicle always sees its leader;
- human drivers: OVM is not a SUMO car-following model, so the humans are SUMO's own
  ``carFollowModel="IDM"`` with the DeeP-LCC IDM set (:meth:`IDMParams.deeplcc`:
  ``v0`` 30 = maxSpeed, ``T`` 1 = tau, ``a`` 1 = accel, ``b`` 1.5 = decel, ``delta`` 4,
  ``s0`` 5 = minGap, ``|a_min|`` 5 = emergencyDecel), ``stepping = dt`` (one IDM update a
  step), speedDev 0, sigma 0: the torch platoon's ``mismatch="idm"`` humans. SUMO has no
  acceleration noise for IDM, so ``accel_noise`` must be 0, and no counterpart of the
  DeeP-LCC emergency-braking rule for humans;
- head: ``setSpeed`` to the profile's next speed, speed mode 0 (imposed exactly, as in torch);
- CAVs: the command clipped to [-5, 2] m/s^2 and passed through the DeeP-LCC emergency
  rule (:func:`~mixed_traffic.physics.saturate_accel`, the torch CAV rule), then
  ``setSpeed(max(0, v + u dt))`` under speed mode 0 (executed exactly);
- update: SUMO's default Euler (``v' = v + a dt``, ``x' = x + v' dt``); the torch platoon
  uses the reference's explicit Euler (``x' = x + v dt``): positions differ by
  ``a dt^2`` a step, which SUMO cannot express;
- collisions: ``--collision.action warn`` (nothing removed), any gap <= 0 counts (torch rule).

libsumo runs one simulation per process: a second live SUMO simulation (ring or platoon)
in the process raises ``RuntimeError``. SUMO is closed by ``close()``, after an error
inside SUMO and at interpreter exit.

>>> from mixed_traffic import make_env
>>> from torchrl.envs.utils import check_env_specs
>>> env = make_env("platoon", backend="sumo", seed=0, episode_seconds=3.0)
>>> check_env_specs(env)
>>> env.rollout(5)["next", "yini"].shape
torch.Size([1, 5, 200])
>>> env.close()
"""

from __future__ import annotations

import math
import os
import shutil
import tempfile

import numpy as np
import torch

from mixed_traffic.controllers.deeplcc.platoon import DTYPE, PlatoonConfig, gaps, init_state
from mixed_traffic.envs import sumo_ring
from mixed_traffic.envs.platoon import PlatoonEnv
from mixed_traffic.envs.sumo_net import LANE_SPEED, VehicleSpec, build_straight_network, write_routes
from mixed_traffic.physics import saturate_accel

Tensor = torch.Tensor

SPEED_CAP = 35.0  # m/s: the road is long enough for every vehicle at this speed for the whole run
ROAD_MARGIN = 100.0  # m before the tail's start and after the head's last position


class SumoPlatoon:
    """One SUMO simulation of the platoon (batch 1): ``start`` then ``step`` (see the module docstring).

    Args:
        cfg: the platoon; ``hdv_model`` must be ``"idm"`` (SUMO's IDM with ``cfg``'s IDM
            parameters) and ``accel_noise`` 0.
        seconds: the longest run the road must hold (a run past it raises ``RuntimeError``).
        sumo_args: extra SUMO options (one given here replaces the default of that name).
        netconvert: netconvert binary (default: eclipse-sumo's).

    >>> from mixed_traffic.controllers.deeplcc.platoon import PlatoonConfig
    >>> sim = SumoPlatoon(PlatoonConfig(hdv_model="idm", accel_noise=0.0), seconds=2.0)
    >>> pos, vel = sim.start(15.0)
    >>> pos, vel, u = sim.step(torch.zeros(1, 2), torch.tensor([15.0]))
    >>> round(float(vel[0, 4]), 6)
    15.0
    >>> sim.close()
    """

    def __init__(self, cfg: PlatoonConfig, seconds: float, *, sumo_args: tuple[str, ...] | list[str] = (),
                 netconvert: str | None = None):
        check_platoon_for_sumo(cfg)
        if not (isinstance(seconds, (int, float)) and math.isfinite(seconds) and seconds > 0):
            raise ValueError(f"seconds={seconds!r} is invalid; allowed: a finite number > 0")
        self.cfg = cfg
        self.seconds = float(seconds)
        self.sumo_args = tuple(str(a) for a in sumo_args)
        self._closed_sumo = True
        self._ids = [f"v{i}" for i in range(cfg.n_vehicles)]
        self._ci = list(cfg.cav_indices)
        self._cav_ids = [self._ids[i] for i in self._ci]
        self._tmp = tempfile.mkdtemp(prefix="mt_sumo_platoon_")
        self._acquire()
        try:
            # the tail starts ROAD_MARGIN m into the road; the platoon is at most ~n * (40 + L) m long
            self._head0 = ROAD_MARGIN + (cfg.n_vehicles - 1) * (40.0 + cfg.vehicle_length)
            length = self._head0 + SPEED_CAP * self.seconds + ROAD_MARGIN
            self.net = build_straight_network(length, self._tmp, netconvert=netconvert)
            self._routes = os.path.join(self._tmp, "platoon.rou.xml")
        except BaseException:
            self.close()
            raise
        self.pos = np.zeros(cfg.n_vehicles)
        self.vel = np.zeros(cfg.n_vehicles)

    # ------------------------------------------------------------------ one SUMO per process
    def _acquire(self) -> None:
        sumo_ring.claim_process(self, "Close it first (close()) or run the simulations in separate processes "
                                      "(torchrl.envs.ParallelEnv).")

    def _close_sumo(self) -> None:
        sumo_ring.close_simulation(self)

    def close(self) -> None:
        """Close the simulation and remove its files (idempotent)."""
        sumo_ring.release_process(self)
        if self._tmp is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)
            self._tmp = None

    def __del__(self):  # pragma: no cover - best effort
        try:
            self.close()
        except Exception:
            pass

    # ------------------------------------------------------------------ SUMO setup
    def _sumo_cmd(self) -> list[str]:
        cmd = ["-n", self.net.net_file, "-r", self._routes, "--step-length", repr(float(self.cfg.dt)),
               "--no-step-log", "true", "--no-warnings", "true", "--duration-log.disable", "true",
               "--collision.action", "warn", "--collision.mingap-factor", "0", "--time-to-teleport", "-1",
               "--seed", "0"]
        user = {a.lstrip("-") for a in self.sumo_args if a.startswith("-")}
        pairs = [cmd[i:i + 2] for i in range(0, len(cmd), 2)]
        return [t for k, v in pairs if k.lstrip("-") not in user for t in (k, v)] + list(self.sumo_args)

    def vehicle_types(self) -> dict[str, dict]:
        """SUMO vType attributes of the head, the CAVs and the human drivers."""
        cfg = self.cfg
        p = cfg.hdv_param_set()
        common = dict(length=cfg.vehicle_length, speedFactor=1, speedDev=0, sigma=0)
        free = dict(carFollowModel="Krauss", accel=cfg.a_max, decel=-cfg.a_min, emergencyDecel=-cfg.a_min,
                    tau=1.0, minGap=0.0, maxSpeed=LANE_SPEED, **common)
        return {
            "head": dict(id="head", **free),
            "cav": dict(id="cav", **free),
            "hdv": dict(id="hdv", carFollowModel="IDM", accel=p.a, decel=p.b, emergencyDecel=abs(p.a_min),
                        tau=p.T, minGap=p.s0, delta=p.delta, stepping=cfg.dt, maxSpeed=p.v0, **common),
        }

    def start(self, v0: float, v_head: float | None = None) -> tuple[Tensor, Tensor]:
        """(Re)start SUMO with the platoon at equilibrium at ``v0`` (head at ``v_head``, default ``v0``).

        Returns ``pos, vel`` ``[1, n]`` (float64; head at position 0, as in :func:`init_state`).
        """
        cfg = self.cfg
        if self._tmp is None:
            raise RuntimeError("SumoPlatoon: start() after close(); build a new one")
        p = cfg.hdv_param_set()
        if not 0 <= v0 <= p.v0:
            raise ValueError(f"v0={v0!r} is invalid; allowed: [0, {p.v0}] (SUMO never runs a human driver "
                             "above its maxSpeed = IDM v0)")
        pos0, _ = init_state(1, cfg, v0=v0)
        types = self.vehicle_types()
        specs = []
        for i, vid in enumerate(self._ids):
            vt = types["head"] if i == 0 else types["cav"] if i in self._ci else types["hdv"]
            speed = v0 if (i or v_head is None) else float(v_head)
            specs.append(VehicleSpec(vid=vid, vtype=vt, start=self._head0 + float(pos0[0, i]), speed=speed))
        write_routes(self._routes, self.net, specs, laps=None)
        ls = sumo_ring.start_or_reload(self)
        try:
            ls.simulationStep()  # inserts every vehicle at its depart position and speed
            missing = [v for v in self._ids if v not in set(ls.vehicle.getIDList())]
            if missing:
                raise RuntimeError(f"SUMO did not insert vehicles {missing} at t=0")
            for vid in [self._ids[0], *self._cav_ids]:
                ls.vehicle.setSpeedMode(vid, sumo_ring.SPEED_MODE_RAW)
            self._read()
        except BaseException:
            self._close_sumo()
            raise
        self.steps = 0
        return self.state()

    def _read(self) -> None:
        v = sumo_ring._libsumo().vehicle
        present = set(v.getIDList())
        gone = [i for i in self._ids if i not in present]
        if gone:
            raise RuntimeError(f"SumoPlatoon: vehicles {gone} left the {self.net.length:.0f} m road after "
                               f"{self.steps} steps; allowed: runs of at most seconds={self.seconds:g} s")
        self.pos = np.array([v.getLanePosition(i) for i in self._ids]) - self._head0
        self.vel = np.array([v.getSpeed(i) for i in self._ids])

    def state(self) -> tuple[Tensor, Tensor]:
        return torch.from_numpy(self.pos.copy())[None].to(DTYPE), torch.from_numpy(self.vel.copy())[None].to(DTYPE)

    def step(self, u_cav: Tensor, v_head_next: Tensor | float) -> tuple[Tensor, Tensor, Tensor]:
        """Advance one step -> ``(pos', vel', executed CAV accel [1, m])`` (the contract of ``platoon.step``)."""
        cfg = self.cfg
        if self._closed_sumo:
            raise RuntimeError("SumoPlatoon: the simulation is not running (closed or failed); call start()")
        pos, vel = self.state()
        g = gaps(pos, cfg)
        ci = [i - 1 for i in self._ci]
        u = torch.as_tensor(u_cav, dtype=DTYPE).reshape(1, -1).clamp(cfg.a_min, cfg.a_max)
        u = saturate_accel(u, g[:, ci], vel[:, self._ci], vel[:, [i - 1 for i in self._ci]],
                           a_min=cfg.a_min, a_max=cfg.a_max)
        v_cav = (vel[:, self._ci] + u * cfg.dt).clamp_min(0.0)
        executed = (v_cav - vel[:, self._ci]) / cfg.dt
        ls = sumo_ring._libsumo()
        try:
            ls.vehicle.setSpeed(self._ids[0], max(0.0, float(torch.as_tensor(v_head_next).reshape(-1)[0])))
            for vid, v in zip(self._cav_ids, v_cav[0].tolist(), strict=True):
                ls.vehicle.setSpeed(vid, v)
            ls.simulationStep()
            self.steps += 1
            self._read()
        except BaseException:
            self._close_sumo()
            raise
        new_pos, new_vel = self.state()
        return new_pos, new_vel, executed


def check_platoon_for_sumo(cfg: PlatoonConfig) -> None:
    """What the SUMO platoon cannot express raises ``ValueError`` naming the field."""
    if cfg.hdv_model != "idm":
        raise ValueError(f"SUMO backend: hdv_model={cfg.hdv_model!r} is not supported; allowed: 'idm' (SUMO's IDM "
                         "with the DeeP-LCC IDM set; OVM is not a SUMO car-following model)")
    if cfg.accel_noise != 0:
        raise ValueError(f"SUMO backend: accel_noise={cfg.accel_noise!r} is not supported; allowed: 0 "
                         "(SUMO's IDM has no acceleration noise)")


class SumoPlatoonEnv(PlatoonEnv):
    """:class:`PlatoonEnv` with SUMO moving the cars (batch size ``[1]``; see the module docstring).

    Args:
        device: torch device of the outputs.
        sumo_args: extra SUMO command-line options.
        netconvert: netconvert binary.
        **overrides: :class:`~mixed_traffic.envs.platoon.PlatoonScenario` fields; ``mismatch``
            defaults to (and must be) ``"idm"``, ``accel_noise`` to (and must be) 0.

    >>> env = SumoPlatoonEnv(profiles=["brake"], randomize=False, episode_seconds=3.0)
    >>> td = env.rollout(10, break_when_any_done=False)
    >>> bool(td["next", "collision"].any())
    False
    >>> env.close()
    """

    def __init__(self, *, batch_size: int = 1, device: str | torch.device = "cpu",
                 sumo_args: tuple[str, ...] | list[str] = (), netconvert: str | None = None, **overrides):
        if batch_size != 1:
            raise ValueError(f"batch_size: {batch_size!r} is invalid for the SUMO backend; allowed: 1 (one SUMO "
                             "simulation per process; batch with torchrl.envs.ParallelEnv)")
        overrides.setdefault("mismatch", "idm")
        overrides.setdefault("accel_noise", 0.0)
        if overrides["mismatch"] != "idm":
            raise ValueError(f"SUMO backend: mismatch={overrides['mismatch']!r} is not supported; allowed: 'idm' "
                             "(the humans are SUMO's IDM with the DeeP-LCC IDM set; OVM is not a SUMO "
                             "car-following model)")
        if overrides["accel_noise"] != 0:
            raise ValueError(f"SUMO backend: accel_noise={overrides['accel_noise']!r} is not supported; allowed: 0 "
                             "(SUMO's IDM has no acceleration noise)")
        self.sim = None
        super().__init__(batch_size=1, device=device, **overrides)
        self.sim = SumoPlatoon(self.cfg, self.scenario.episode_seconds, sumo_args=sumo_args, netconvert=netconvert)
        try:
            self.sim.start(self.scenario.v_star)  # fail early on bad SUMO options
        except BaseException:
            self.sim.close()
            raise
        self.is_closed = False  # EnvBase.__del__ then closes SUMO too

    def _initial_state(self, v0: float) -> tuple[Tensor, Tensor]:
        return self.sim.start(v0)

    def _physics(self, pos, vel, u, v_head_next, params):
        return self.sim.step(u, v_head_next)

    def close(self, *, raise_if_closed: bool = True) -> None:
        """Close the SUMO simulation and remove its files."""
        if self.sim is not None:
            self.sim.close()
        super().close(raise_if_closed=raise_if_closed)


__all__ = ["SumoPlatoon", "SumoPlatoonEnv", "check_platoon_for_sumo"]
