"""The ring scenario in SUMO, driven in-process through libsumo.

:class:`SumoRingEnv` emits exactly the keys and specs of the torch backend
(:func:`mixed_traffic.envs.traffic.make_specs`) and computes reward, cost and
observation with the same shared functions, so a policy, transform or loss works
unchanged on either backend. What differs is who moves the cars: SUMO does.

- Network: a single-lane loop of exactly ``ring_length`` generated at start-up with
  netconvert (:mod:`mixed_traffic.envs.sumo_net`); routes loop for the whole episode.
- Human drivers: SUMO's IDM with the scenario's parameters (``v0`` = maxSpeed,
  ``T`` = tau, ``a`` = accel, ``b`` = decel, ``s0`` = minGap, ``delta``,
  ``|a_min|`` = emergencyDecel), speedDev 0, ``sigma`` settable (SUMO's IDM ignores it).
  With ``accel_noise > 0`` every human's own SUMO car-following command is read each
  step (``vehicle.getFollowSpeed``, the IDM step SUMO would take), the scenario's
  saturation and ``N(0, accel_noise)`` are added as in the torch backend (the same draws
  from the env's generator) and SUMO executes the result (``setSpeed``, speed mode 0):
  this is how Flow puts its ``accel_noise`` on SUMO's humans.
- Head (``head=True``): ``setSpeed`` to the profile's speed every step; SUMO bounds it by
  the head vType's accel/decel (= ``head_accel_bounds``) and its IDM safe speed, the same
  rule as the torch backend. ``head=False`` (``ring_wave``): no scripted vehicle.
- ``ring_length_range``: the ring length is drawn per episode (as in the torch backend,
  from the same generator) and a network of that length is built at each reset.
- CAVs: the action is executed as ``setSpeed(max(0, v + a dt))``. ``sumo_safety=False``
  (speed mode 0, default) executes it exactly, as the torch backend does;
  ``sumo_safety=True`` (speed mode 95) lets SUMO cap it at its Krauss safe speed.
- Collisions (``--collision.action warn``, ``--collision.mingap-factor 0``, or any
  gap <= 0 as in the torch backend) terminate the episode and set ``collision``.

libsumo holds one simulation per process: a second live env in the same process
raises ``RuntimeError``; batch with :class:`torchrl.envs.ParallelEnv`. SUMO is
closed by :meth:`close`, after an error inside SUMO and at interpreter exit.

>>> from mixed_traffic import make_env
>>> from torchrl.envs.utils import check_env_specs
>>> env = make_env("ring", backend="sumo", seed=0)
>>> check_env_specs(env)
>>> td = env.rollout(5)
>>> td["next", "traffic", "speed"].shape
torch.Size([1, 5, 4])
>>> env.close()
"""

from __future__ import annotations

import atexit
import dataclasses
import os
import shutil
import tempfile
import threading
from collections import deque

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase

from mixed_traffic.envs.sumo_net import (
    LANE_SPEED,
    RingNetwork,
    VehicleSpec,
    build_ring_network,
    read_ring_network,
    write_routes,
)
from mixed_traffic.envs.traffic import (
    head_gaps,
    initial_positions,
    make_specs,
    observe,
    stage_terms,
    uniform_flow_speed,
)
from mixed_traffic.physics import IDMParams, KraussParams, leader_gaps, saturate_accel
from mixed_traffic.scenarios import TrafficScenario, get_scenario

Tensor = torch.Tensor

SPEED_MODE_SAFE = 95  # SUMO may override: safe speed, max accel/decel, right of way
SPEED_MODE_RAW = 0  # the command is executed as given
SPEED_MODE_HEAD = 31  # SUMO's default: safe speed and accel/decel bounds

# ----------------------------------------------------------------------------- one SUMO per process
_LOCK = threading.Lock()
_OWNER = None  # the SUMO env (ring or platoon) whose simulation libsumo currently runs


def _libsumo():
    if "SUMO_HOME" not in os.environ:  # else SUMO warns about it on every start
        try:
            import sumo  # the eclipse-sumo wheel

            os.environ["SUMO_HOME"] = sumo.SUMO_HOME
        except ImportError:
            pass
    try:
        import libsumo
    except ImportError as e:  # pragma: no cover - libsumo is a dependency
        raise RuntimeError("backend 'sumo' needs libsumo (pip install libsumo eclipse-sumo)") from e
    return libsumo


def _shutdown_sumo() -> None:
    """Close the process's simulation if one is running (registered with atexit)."""
    global _OWNER
    owner = _OWNER
    if owner is not None:
        try:
            owner._close_sumo()
        except Exception:
            pass
    _OWNER = None


atexit.register(_shutdown_sumo)


def claim_process(owner, hint: str) -> None:
    """Make ``owner`` the process's SUMO user; another live simulation raises ``RuntimeError`` (``hint``: what to do)."""
    global _OWNER
    with _LOCK:
        if _OWNER is not None and _OWNER is not owner and not _OWNER._closed_sumo:
            raise RuntimeError(f"{type(owner).__name__}: a SUMO simulation is already running in this process "
                               f"(pid {os.getpid()}, {type(_OWNER).__name__}); libsumo runs one per process. {hint}")
        _OWNER = owner


def release_process(owner) -> None:
    """Close ``owner``'s simulation and give up the process if it holds it."""
    global _OWNER
    close_simulation(owner)
    with _LOCK:
        if _OWNER is owner:
            _OWNER = None


def close_simulation(owner) -> None:
    """Close ``owner``'s running simulation (idempotent; errors inside SUMO are ignored)."""
    if not owner._closed_sumo:
        owner._closed_sumo = True
        try:
            _libsumo().close()
        except Exception:
            pass


def _run_capturing_stderr(fn, *args):
    """Call ``fn(*args)``; on an exception return SUMO's own stderr text with it.

    SUMO prints its error messages to the C-level stderr and libsumo raises only
    "Process Error"; the text is captured through a temporary file descriptor and
    echoed back to stderr so nothing is lost.
    """
    try:
        fd = 2
        saved = os.dup(fd)
    except OSError:  # no usable stderr: call through
        return fn(*args), ""
    with tempfile.TemporaryFile(mode="w+b") as tmp:
        os.dup2(tmp.fileno(), fd)
        err = None
        try:
            result = fn(*args)
        except Exception as e:  # libsumo.TraCIException and friends
            err, result = e, None
        finally:
            os.dup2(saved, fd)
            os.close(saved)
        tmp.seek(0)
        text = tmp.read().decode(errors="replace")
    if text:
        os.write(2, text.encode())
    if err is not None:
        raise RuntimeError(f"SUMO failed to start: {text.strip() or err}") from err
    return result, text


def start_or_reload(env):
    """Start SUMO with ``env._sumo_cmd()`` (first episode, or after a failure) or reload it.

    ``env`` is a SUMO env holding this process's simulation (``_acquire``, ``_closed_sumo``,
    ``_sumo_cmd``); a failed reload marks it closed so that the next reset starts afresh.
    Returns the libsumo module.
    """
    ls = _libsumo()
    env._acquire()
    if env._closed_sumo:
        _run_capturing_stderr(ls.start, ["sumo"] + env._sumo_cmd())
    else:
        try:
            _run_capturing_stderr(ls.load, env._sumo_cmd())
        except RuntimeError:
            env._closed_sumo = True
            raise
    env._closed_sumo = False
    return ls


# ----------------------------------------------------------------------------- the env
class SumoRingEnv(EnvBase):
    """The ring scenario simulated by SUMO (libsumo), batch size ``[1]``.

    Args:
        scenario: ``"ring"``, ``"ring_wave"`` or a :class:`TrafficScenario` with ``road="ring"``,
            ``hdv_model="idm"`` and ``integration`` ``"euler"`` or ``"ballistic"`` (with or
            without a head, fixed or per-episode ring length, with or without ``accel_noise``).
        device: torch device of the emitted tensors.
        sumo_safety: ``False`` (speed mode 0): the CAV action executes exactly and only
            a safety layer guards it; ``True`` (speed mode 95): SUMO caps it at its
            safe speed and accel/decel bounds, and ``("cav", "override")`` marks the
            capped commands. ``None``: the scenario's ``sumo_safety`` field.
        sigma: SUMO's driver imperfection for the human drivers (SUMO's IDM ignores it; human
            noise is ``accel_noise``).
        net_file: an existing ring network (from :func:`~mixed_traffic.envs.sumo_net.build_ring_network`)
            instead of generating one.
        run_dir: folder for the generated files (default: a temporary folder removed on close).
        sumo_args: extra SUMO command-line options (e.g. ``["--seed", "3"]``); one of the
            defaults set here (``--seed``, ``--collision.action`` ...) is replaced, not repeated.
        netconvert: path of the netconvert binary (default: eclipse-sumo's).
        **overrides: scenario fields (``ring_length``, ``n_vehicles``, ``cav_indices``,
            ``hdv_params``, ``dt``, ``episode_seconds``, ``profile``, bounds, ...).

    >>> env = SumoRingEnv("ring", ring_length=260.0, n_vehicles=6, cav_indices=(2,))
    >>> _ = env.set_seed(1)
    >>> env.reset()["traffic", "gap"].shape
    torch.Size([1, 6])
    >>> env.close()
    """

    batch_locked = True

    def __init__(self, scenario: str | TrafficScenario = "ring", *, device: str | torch.device = "cpu",
                 sumo_safety: bool | None = None, sigma: float = 0.0, net_file: str | None = None,
                 run_dir: str | None = None, sumo_args: tuple[str, ...] | list[str] = (),
                 netconvert: str | None = None, **overrides):
        if isinstance(scenario, TrafficScenario):
            sc = dataclasses.replace(scenario, **overrides).validate()
        else:
            sc = get_scenario(scenario, **overrides)
        if sumo_safety is not None:
            sc = dataclasses.replace(sc, sumo_safety=bool(sumo_safety)).validate()
        self._check_scenario(sc)
        if not 0.0 <= float(sigma) <= 1.0:
            raise ValueError(f"sigma={sigma!r} is invalid; allowed: [0, 1] (SUMO driver imperfection)")
        self._closed_sumo = True
        self._released = False
        self._tmp_dir = None
        super().__init__(device=device, batch_size=torch.Size([1]))
        self.scenario = sc
        self.dt = sc.dt
        self.J_max = sc.J_max
        self.profile = sc.make_profile()
        self.rng = torch.Generator().manual_seed(0)
        self.sumo_safety = sc.sumo_safety
        self.sigma = float(sigma)
        self.sumo_args = tuple(str(a) for a in sumo_args)
        specs = make_specs(sc, (1,), device=self.device)
        self.observation_spec = specs["observation"]
        self.action_spec = specs["action"]
        self.reward_spec = specs["reward"]
        self.done_spec = specs["done"]

        n = sc.n_vehicles
        self._ids = [f"v{i}" for i in range(n)]
        self._cav = list(sc.cav_indices)
        self._cav_ids = [self._ids[i] for i in self._cav]
        self._hdv_idx = list(sc.hdv_indices)
        self._window = max(1, int(round(sc.v_eq_window / sc.dt)))
        self._cav_window = max(1, int(round(sc.cav_speed_window / sc.dt)))
        self._netconvert = netconvert
        self._user_net = net_file is not None
        self.ring_length = float(sc.ring_length)
        self._v_ref = None  # reward="wave_relative": the episode's uniform-flow speed ([1, 1]), set at reset
        self.init_pos = initial_positions(sc, torch.zeros(1, dtype=torch.long), torch.Generator().manual_seed(0))[0][0]
        self.init_pos = self.init_pos.double().numpy()
        self._hdv_base = sc.hdv_defaults()
        self.profile_params = self.profile.sample(1, self.rng)
        self.hdv_params = {f.name: np.full(n, float(getattr(self._hdv_base, f.name)))
                           for f in dataclasses.fields(self._hdv_base)}
        self.override_steps = 0  # steps in which SUMO executed an acceleration other than commanded
        self.override_count = 0  # (CAV, step) pairs overridden
        self.commanded_accel = np.zeros(sc.n_cav)
        self._override = np.zeros(sc.n_cav)

        self._acquire()
        try:
            if run_dir is None:
                self._tmp_dir = tempfile.mkdtemp(prefix="mt_sumo_ring_")
                run_dir = self._tmp_dir
            os.makedirs(run_dir, exist_ok=True)
            self.run_dir = run_dir
            if net_file is None:
                self.net: RingNetwork = build_ring_network(sc.ring_length, run_dir, netconvert=netconvert)
            else:
                if sc.ring_length_range is not None:
                    raise ValueError("SUMO backend: net_file is a ring of one length; allowed with "
                                     "ring_length_range=None only")
                self.net = read_ring_network(net_file, sc.ring_length)
            self._offsets = self.net.edge_offsets()
            self._route_file = os.path.join(run_dir, "ring.rou.xml")
            # ring coordinate of torch position 0 (the head's start): off the edge boundary
            self._s0 = sc.vehicle_length
            self._start_episode()  # fail early on bad input; reset() restarts it
            self.is_closed = False  # EnvBase.__del__ then closes SUMO too
        except BaseException:
            self._release()
            raise

    # ------------------------------------------------------------------ validation / guard
    @staticmethod
    def _check_scenario(sc: TrafficScenario) -> None:
        def bad(name, value, allowed):
            raise ValueError(f"SUMO backend: {name}={value!r} is not supported; allowed: {allowed}")

        if sc.road != "ring":
            bad("road", sc.road, "'ring'")
        if sc.hdv_model != "idm":
            bad("hdv_model", sc.hdv_model, "'idm' (SUMO's IDM)")
        if sc.reset_accel != "zero":
            bad("reset_accel", sc.reset_accel, "'zero' (SUMO starts every vehicle at rest acceleration)")
        if sc.integration not in ("euler", "ballistic"):
            bad("integration", sc.integration, "'euler' (SUMO's default) or 'ballistic'")
        if sc.init_spacing_range is not None:
            bad("init_spacing_range", sc.init_spacing_range, "None (use init_spacing)")
        if sc.init_spacing_rows is not None:
            bad("init_spacing_rows", sc.init_spacing_rows, "None (use init_spacing)")

    def _acquire(self) -> None:
        claim_process(self, "Close it first (env.close()) or run several envs in separate processes with "
                            "torchrl.envs.ParallelEnv(n, functools.partial(make_env, 'ring', backend='sumo')).")

    def _release(self) -> None:
        self._released = True
        release_process(self)
        if self._tmp_dir is not None:
            shutil.rmtree(self._tmp_dir, ignore_errors=True)
            self._tmp_dir = None

    def _close_sumo(self) -> None:
        close_simulation(self)

    def close(self, *, raise_if_closed: bool = True) -> None:
        """Close the SUMO simulation and remove the temporary files."""
        self._release()
        super().close(raise_if_closed=raise_if_closed)

    # ------------------------------------------------------------------ SUMO setup
    def _sumo_cmd(self) -> list[str]:
        sc = self.scenario
        cmd = ["-n", self.net.net_file, "-r", self._route_file, "--step-length", repr(float(sc.dt)),
               "--no-step-log", "true", "--no-warnings", "true", "--duration-log.disable", "true",
               "--collision.action", "warn", "--collision.mingap-factor", "0", "--collision.check-junctions", "true",
               "--time-to-teleport", "-1", "--seed", "0"]
        if sc.integration == "ballistic":
            cmd += ["--step-method.ballistic", "true"]
        # an option given in sumo_args replaces the default of the same name (SUMO refuses a repeat)
        user = {a.lstrip("-") for a in self.sumo_args if a.startswith("-")}
        pairs = [cmd[i:i + 2] for i in range(0, len(cmd), 2)]
        return [t for k, v in pairs if k.lstrip("-") not in user for t in (k, v)] + list(self.sumo_args)

    def _vehicle_specs(self) -> list[VehicleSpec]:
        sc = self.scenario
        hl, hh = sc.head_accel_bounds
        cl, ch = sc.cav_accel_bounds
        idm = IDMParams()
        common = dict(length=sc.vehicle_length, speedFactor=1, speedDev=0)
        head = dict(id="head", carFollowModel="IDM", accel=hh, decel=-hl, emergencyDecel=-hl, sigma=0,
                    tau=idm.T, minGap=idm.s0, delta=idm.delta, stepping=sc.dt, maxSpeed=idm.v0, **common)
        kp = KraussParams()  # the torch backend's speed mode 95 models this vType
        cav = dict(id="cav", carFollowModel="Krauss", accel=ch, decel=-cl, emergencyDecel=max(kp.emergency_decel, -sc.cav_exec_bounds[0]),
                   sigma=0, tau=kp.tau, minGap=kp.min_gap, maxSpeed=LANE_SPEED, **common)
        out = []
        for i, vid in enumerate(self._ids):
            start = self._s0 + float(self.init_pos[i])
            if i == 0 and sc.head:
                vt = head
            elif i in self._cav:
                vt = cav
            else:
                p = {k: float(v[i]) for k, v in self.hdv_params.items()}
                vt = dict(id=f"hdv{i}" if sc.hdv_param_noise > 0 else "hdv", carFollowModel="IDM",
                          accel=p["a"], decel=p["b"], emergencyDecel=abs(p["a_min"]), sigma=self.sigma,
                          tau=p["T"], minGap=p["s0"], delta=p["delta"], stepping=sc.dt, maxSpeed=p["v0"], **common)
            out.append(VehicleSpec(vid=vid, vtype=vt, start=start, speed=sc.v_init))
        return out

    def _start_episode(self) -> None:
        """Write the routes for the current parameters and (re)start SUMO at episode time 0."""
        sc = self.scenario
        v0_min = float(self.hdv_params["v0"][list(sc.hdv_indices)].min()) if sc.hdv_indices else float("inf")
        if sc.v_init > v0_min:
            raise ValueError(f"SUMO backend: v_init={sc.v_init} is above the human drivers' v0 ({v0_min:.3f}); "
                             "SUMO never runs a vehicle above its maxSpeed (= v0); allowed: v_init <= v0")
        laps = int(np.ceil(sc.episode_seconds * 60.0 / self.ring_length)) + 2
        write_routes(self._route_file, self.net, self._vehicle_specs(), laps=laps)
        ls = start_or_reload(self)
        try:
            ls.simulationStep()  # inserts every vehicle at its depart position and speed
            present = set(ls.vehicle.getIDList())
            missing = [v for v in self._ids if v not in present]
            if missing:
                raise RuntimeError(f"SUMO did not insert vehicles {missing} at t=0 (n_vehicles={sc.n_vehicles}, "
                                   f"ring_length={sc.ring_length})")
            mode = SPEED_MODE_SAFE if self.sumo_safety else SPEED_MODE_RAW
            for vid in self._cav_ids:
                ls.vehicle.setSpeedMode(vid, mode)
            if sc.head:
                ls.vehicle.setSpeedMode(self._ids[0], SPEED_MODE_HEAD)
            if sc.accel_noise > 0:  # the humans' noisy command is executed as given (see _human_speeds)
                for i in sc.hdv_indices:
                    ls.vehicle.setSpeedMode(self._ids[i], SPEED_MODE_RAW)
            self._read_state()
        except BaseException:
            self._close_sumo()
            raise
        self.acc = np.zeros(sc.n_vehicles)
        self._override = np.zeros(sc.n_cav)
        self.step_count = 0
        self._head_hist = deque([self._tracked_speed()], maxlen=self._window)
        self._cav_hist = deque([self.vel[self._cav].copy()], maxlen=self._cav_window)

    def _tracked_speed(self) -> float:
        """The speed averaged into ``v_eq``: the head's, or the ring's mean without a head (as in torch)."""
        return float(self.vel[0]) if self.scenario.head else float(np.mean(self.vel))

    def _human_speeds(self, gap: np.ndarray) -> np.ndarray:
        """Next speeds of the humans: their own SUMO car-following step plus the scenario's noise.

        ``vehicle.getFollowSpeed`` returns the speed SUMO's IDM of that vehicle would
        drive next (its gap argument excludes minGap, as inside SUMO); the acceleration it
        implies is saturated and perturbed exactly as the torch backend's humans
        (``saturate_accel``, then ``+ accel_noise N(0, 1)`` from the env's generator,
        clipped to ``[a_min, a_max]``).
        """
        sc = self.scenario
        ls = _libsumo()
        hdv = self._hdv_idx
        v = self.vel
        lead = [(i - 1) % sc.n_vehicles for i in hdv]
        s0 = self.hdv_params["s0"][hdv]
        v_next = np.array([ls.vehicle.getFollowSpeed(self._ids[i], float(v[i]), float(gap[i] - s0[k]),
                                                     float(v[lead[k]]), float(self.hdv_params["b"][lead[k]]),
                                                     self._ids[lead[k]])
                           for k, i in enumerate(hdv)])
        a_min = self.hdv_params["a_min"][hdv]
        a_max = self.hdv_params["a_max"][hdv]
        acc = torch.from_numpy((v_next - v[hdv]) / sc.dt)
        acc = saturate_accel(acc, torch.from_numpy(gap[hdv]), torch.from_numpy(v[hdv]),
                             torch.from_numpy(v[lead]), a_min=torch.from_numpy(a_min),
                             a_max=torch.from_numpy(a_max)).numpy()
        noise = torch.randn(1, sc.n_vehicles, generator=self.rng)[0].double().numpy()
        acc = np.clip(acc + sc.accel_noise * noise[hdv], a_min, a_max)
        return np.maximum(0.0, v[hdv] + acc * sc.dt)

    def _read_state(self) -> None:
        ls = _libsumo()
        v = ls.vehicle
        L = self.ring_length
        s = np.array([self._offsets[v.getRoadID(i)] + v.getLanePosition(i) for i in self._ids])
        self.pos = np.remainder(s - self._s0, L)
        self.vel = np.array([v.getSpeed(i) for i in self._ids])

    # ------------------------------------------------------------------ outputs
    def _gaps(self) -> np.ndarray:
        sc = self.scenario
        return leader_gaps(torch.from_numpy(self.pos), sc.vehicle_length, self.ring_length).numpy()

    def _output(self, gap: np.ndarray) -> dict:
        sc = self.scenario
        f = dict(dtype=torch.float32, device=self.device)
        pos = torch.as_tensor(self.pos, **f).unsqueeze(0)
        vel = torch.as_tensor(self.vel, **f).unsqueeze(0)
        acc = torch.as_tensor(self.acc, **f).unsqueeze(0)
        g = torch.as_tensor(gap, **f).unsqueeze(0)
        v_eq = torch.tensor([[float(np.mean(self._head_hist))]], **f)
        ci = self._cav
        cav_acc = acc[:, ci]
        L = torch.tensor([[self.ring_length]], **f)
        j, cost = stage_terms(sc, vel, g, cav_acc, v_eq, self._v_ref)
        leaders = [(i - 1) % sc.n_vehicles for i in ci]
        cav = {"gap": g[:, ci], "speed": vel[:, ci], "leader_speed": vel[:, leaders], "leader_accel": acc[:, leaders],
               "accel": cav_acc}
        speed_avg = None
        if sc.head:
            cav["head_gap"] = head_gaps(sc, pos, L)
            cav["head_speed"] = vel[:, :1].expand(-1, len(ci)).clone()
        else:
            speed_avg = cav["speed_avg"] = torch.as_tensor(np.mean(self._cav_hist, axis=0), **f).unsqueeze(0)
        if sc.sumo_safety:
            cav["override"] = torch.as_tensor(self._override, **f).unsqueeze(0)
        out = {
            "observation": observe(sc, pos, vel, g, cav_acc, v_eq, ring_length=L, speed_avg=speed_avg, accel=acc,
                                   time=torch.tensor([[self.step_count * sc.dt]], **f)),
            "cav": cav,
            "traffic": {
                "pos": pos, "speed": vel, "accel": acc, "gap": g,
                "time": torch.tensor([[self.step_count * sc.dt]], **f), "v_eq": v_eq, "J": j,
                "ring_length": L,
            },
        }
        return out, j, cost

    # ------------------------------------------------------------------ EnvBase API
    def _set_seed(self, seed: int | None) -> None:
        self.rng.manual_seed(int(seed) if seed is not None else torch.seed() % (2**63))

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        sc = self.scenario
        if self._released:
            raise RuntimeError("SumoRingEnv: reset() after close(); build a new env")
        # the torch backend's draws, in its order: ring length, wave phase, profile, human parameters
        pos, L = initial_positions(sc, torch.zeros(1, dtype=torch.long), self.rng)
        self.init_pos = pos[0].double().numpy()
        L = float(L[0, 0])
        if L != self.ring_length:
            self.ring_length = L
            self.net = build_ring_network(L, self.run_dir, netconvert=self._netconvert)
            self._offsets = self.net.edge_offsets()
        if sc.reward == "wave_relative":  # once per episode: the bisection need not run every step
            self._v_ref = uniform_flow_speed(sc, torch.tensor([[L]])).to(dtype=torch.float32, device=self.device)
        self.profile_params = self.profile.sample(1, self.rng)
        if sc.hdv_param_noise > 0:
            base = {f.name: float(getattr(self._hdv_base, f.name)) for f in dataclasses.fields(self._hdv_base)}
            for name in ("v0", "T", "a", "b", "s0"):
                noise = 1.0 + sc.hdv_param_noise * (2 * torch.rand(1, sc.n_vehicles, generator=self.rng) - 1)
                self.hdv_params[name] = base[name] * noise[0].double().numpy()
        self._start_episode()
        out, _, _ = self._output(self._gaps())
        false = torch.zeros(1, 1, dtype=torch.bool, device=self.device)
        out.update(done=false, terminated=false.clone(), truncated=false.clone(), collision=false.clone())
        return TensorDict(out, batch_size=self.batch_size, device=self.device)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        sc = self.scenario
        action = tensordict.get("action")
        if tuple(action.shape) != (1, sc.n_cav):
            raise ValueError(f"action: shape {tuple(action.shape)} is invalid; allowed: (1, {sc.n_cav}) "
                             "(batch, n_cav) accelerations in m/s^2")
        if self._closed_sumo:
            raise RuntimeError("SumoRingEnv: the SUMO simulation is not running (closed or failed); call reset()")
        lo, hi = sc.cav_exec_bounds  # the action range, widened by the safety layer's emergency braking
        a = action.detach().double().cpu().numpy()[0].clip(lo, hi)
        if not np.all(np.isfinite(a)):
            raise ValueError(f"action: {a.tolist()} is invalid; allowed: finite accelerations in [{lo}, {hi}] m/s^2")
        ls = _libsumo()
        v_old = self.vel
        try:
            if sc.head:
                t_next = torch.tensor([(self.step_count + 1) * sc.dt], dtype=torch.float64)
                v_target = float(self.profile.speed(t_next, self.profile_params.double()))
                ls.vehicle.setSpeed(self._ids[0], max(0.0, v_target))
            if sc.accel_noise > 0:
                for i, v_next in zip(self._hdv_idx, self._human_speeds(self._gaps()), strict=True):
                    ls.vehicle.setSpeed(self._ids[i], float(v_next))
            for k, vid in enumerate(self._cav_ids):
                ls.vehicle.setSpeed(vid, max(0.0, float(v_old[self._cav[k]] + a[k] * sc.dt)))
            ls.simulationStep()
            self._read_state()
            sumo_collision = ls.simulation.getCollidingVehiclesNumber() > 0
        except BaseException:
            self._close_sumo()
            raise
        self.acc = (self.vel - v_old) / sc.dt
        self.commanded_accel = a
        executed = self.acc[self._cav]
        commanded = np.maximum(0.0, v_old[self._cav] + a * sc.dt) - v_old[self._cav]
        overridden = np.abs(executed * sc.dt - commanded) > 1e-6
        self.override_count += int(overridden.sum())
        self.override_steps += int(overridden.any())
        self._override = overridden.astype(np.float64)
        self.step_count += 1
        self._head_hist.append(self._tracked_speed())
        self._cav_hist.append(self.vel[self._cav].copy())
        gap = self._gaps()
        out, j, cost = self._output(gap)
        collision = bool(sumo_collision or (gap <= 0).any())
        truncated = self.step_count >= sc.max_steps
        t = lambda x: torch.tensor([[bool(x)]], dtype=torch.bool, device=self.device)  # noqa: E731
        out.update(reward=-j, cost=cost, collision=t(collision), terminated=t(collision),
                   truncated=t(truncated and not collision), done=t(collision or truncated))
        return TensorDict(out, batch_size=self.batch_size, device=self.device)


__all__ = ["SumoRingEnv", "SPEED_MODE_SAFE", "SPEED_MODE_RAW"]
