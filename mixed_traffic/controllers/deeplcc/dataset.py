"""(state, QP solution) dataset of DeeP-LCC closed loops: generation, atomic .npz write, validating load.

Each episode pre-collects its own Hankel data (:mod:`.precollect`), then runs
the platoon (torch, or SUMO with ``backend="sumo"``) in closed loop under the exact QP (:class:`.qp.DeepLCCSolver`) on a
head-speed scenario from the mix, recording every controlled step's
``(uini, yini, eini) -> u_opt``. Episodes take scenarios in contiguous blocks.

File schema (``E`` episodes, ``N`` samples, ``m`` CAVs, ``p`` outputs, ``M`` Hankel columns):

==========  ===================  ==============================================
key         shape                meaning
==========  ===================  ==============================================
uini        (N, m*t_ini) f4      past CAV accelerations, time-major
yini        (N, p*t_ini) f4      past outputs (8 speed errors + 2 CAV spacing errors)
eini        (N, t_ini) f4        past head speed errors
u_opt       (N, m) f8            first optimal action of the QP
episode     (N,) i4              episode of each sample
metadata    (6,) f8              [v_star, s_star, t_ini, N, lambda_g, lambda_y]
Up .. Yf    (E, rows, M) f4      per-episode Hankel data (exact: trajectories are float32)
qp          str (JSON)           QP parameters (weights, regularisation, bounds, s_star)
config      str (JSON)           generation config, scenario per episode, solver counters
==========  ===================  ==============================================

The stored ``uini/yini/eini`` are float32 and ``u_opt`` was computed from exactly
those float32 values, so re-solving a stored sample reproduces ``u_opt``.

>>> import tempfile, os
>>> cfg = DatasetConfig(episodes=1, episode_seconds=1.5, T=300, t_ini=5, n=10, workers=1)
>>> path = os.path.join(tempfile.mkdtemp(), "d.npz")
>>> _ = write_dataset(path, generate_dataset(cfg, progress=False))
>>> load_dataset(path)["uini"].shape
(25, 10)
"""

from __future__ import annotations

import dataclasses
import json
import multiprocessing
import os
import tempfile
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field

import numpy as np
import torch

from mixed_traffic.controllers.deeplcc.closed_loop import ScenarioSpec, run_closed_loop
from mixed_traffic.controllers.deeplcc.hankel import HANKEL_KEYS
from mixed_traffic.controllers.deeplcc.platoon import PlatoonConfig
from mixed_traffic.controllers.deeplcc.precollect import precollect
from mixed_traffic.controllers.deeplcc.qp import PRESETS, DeepLCCSolver, QPParams
from mixed_traffic.validation import ConfigError, Real, is_real

#: scenario kinds of the mix -> how an episode of that kind is built
MIX_KINDS = ("random1", "random3", "random5", "brake", "sine3", "sine5")
DEFAULT_MIX = {"random1": 0.30, "random3": 0.15, "random5": 0.10, "brake": 0.25, "sine3": 0.10, "sine5": 0.10}
QP_FIELDS = ("weight_v", "weight_s", "weight_u", "lambda_g", "lambda_y", "acel_max", "dcel_max",
             "spacing_min", "spacing_max", "s_star")


@dataclass
class DatasetConfig:
    """Everything that defines a dataset (validated by :meth:`validate`)."""

    episodes: int = 100
    episode_seconds: float = 40.0
    T: int = 2000
    t_ini: int = 20
    n: int = 50
    dt: float = 0.05
    qp_preset: str = "dataset"
    hdv_model: str = "ovm"
    accel_noise: float = 0.1
    v_star: float = 15.0
    s_star: float = 20.0
    mix: dict = field(default_factory=lambda: dict(DEFAULT_MIX))
    seed: int = 0
    workers: int = 2
    brake_start: tuple = (1.0, 10.0)  # brake episodes start braking at U[lo, hi] s
    backend: str = "torch"  # "sumo": pre-collection and closed loop in SUMO (hdv_model idm, accel_noise 0)

    def validate(self) -> DatasetConfig:
        def bad(name, allowed):
            raise ConfigError(name, f"{getattr(self, name)!r} is invalid", str(allowed))

        for f in dataclasses.fields(self):
            if f.type in ("float", "int"):
                Real(integer=f.type == "int")(f.name, getattr(self, f.name))

        if not (isinstance(self.episodes, int) and self.episodes >= 1):
            bad("episodes", "an integer >= 1")
        if not (isinstance(self.t_ini, int) and self.t_ini >= 1):
            bad("t_ini", "an integer >= 1")
        if not (isinstance(self.n, int) and self.n >= 1):
            bad("n", "an integer >= 1")
        if not self.dt > 0:
            bad("dt", "> 0")
        if not self.episode_seconds > (self.t_ini + 1) * self.dt:
            bad("episode_seconds", f"> (t_ini + 1) * dt = {(self.t_ini + 1) * self.dt:g} s")
        if not (isinstance(self.T, int) and self.T >= self.t_ini + self.n + 1):
            bad("T", f"an integer >= t_ini + n + 1 ({self.t_ini + self.n + 1})")
        if self.qp_preset not in PRESETS:
            bad("qp_preset", sorted(PRESETS))
        if self.hdv_model not in ("ovm", "idm"):
            bad("hdv_model", "'ovm' or 'idm'")
        if not 0 <= self.accel_noise:
            bad("accel_noise", ">= 0")
        if self.backend not in ("torch", "sumo"):
            bad("backend", "'torch' or 'sumo'")
        if self.backend == "sumo" and self.hdv_model != "idm":
            bad("hdv_model", "'idm' with backend=sumo (SUMO's IDM; OVM is not a SUMO car-following model)")
        if self.backend == "sumo" and self.accel_noise != 0:
            bad("accel_noise", "0 with backend=sumo (SUMO's IDM has no acceleration noise)")
        if not (isinstance(self.workers, int) and self.workers >= 1):
            bad("workers", "an integer >= 1")
        mix = dict(self.mix)
        unknown = set(mix) - set(MIX_KINDS)
        if unknown:
            raise ConfigError("mix", f"unknown kind(s) {sorted(unknown)}", str(list(MIX_KINDS)))
        if any(not (is_real(v) and 0 <= v < float("inf")) for v in mix.values()) or not sum(mix.values()) > 0:
            bad("mix", "non-negative fractions with a positive sum")
        if not (len(self.brake_start) == 2 and all(is_real(x) for x in self.brake_start)):
            bad("brake_start", "(lo, hi) with 0 <= lo <= hi")
        lo, hi = self.brake_start
        if not 0 <= lo <= hi < float("inf"):
            bad("brake_start", "(lo, hi) with 0 <= lo <= hi")
        self.qp_params()
        return self

    def platoon(self) -> PlatoonConfig:
        return PlatoonConfig(dt=self.dt, hdv_model=self.hdv_model, accel_noise=self.accel_noise,
                             v_star=self.v_star, s_star=self.s_star)

    def qp_params(self) -> QPParams:
        return QPParams.preset(self.qp_preset, s_star=self.s_star)

    def episode_kinds(self) -> list[str]:
        """Scenario kind of every episode: contiguous blocks in the order of MIX_KINDS."""
        w = np.array([float(self.mix.get(k, 0.0)) for k in MIX_KINDS])
        edges = np.cumsum(w / w.sum()) * self.episodes
        idx = np.searchsorted(np.round(edges, 9), np.arange(self.episodes) + 0.5)
        return [MIX_KINDS[min(i, len(MIX_KINDS) - 1)] for i in idx]


def episode_scenario(kind: str, cfg: DatasetConfig, rng: np.random.Generator) -> ScenarioSpec:
    """Head-speed scenario of one episode of ``kind``."""
    s = cfg.episode_seconds
    if kind.startswith("random"):
        return ScenarioSpec(kind, "random_perturbation",
                            (("v_star", cfg.v_star), ("amplitude", float(kind[6:])), ("period", 1.0)), s)
    if kind.startswith("sine"):
        return ScenarioSpec(kind, "sine", (("v_star", cfg.v_star), ("amplitude", float(kind[4:])), ("period", 10.0)), s)
    if kind == "brake":
        start = float(rng.uniform(*cfg.brake_start))
        return ScenarioSpec(kind, "deeplcc_brake", (("start", start), ("v0", cfg.v_star)), s, adaptive_v_star=True)
    raise ValueError(f"episode_scenario: kind={kind!r} is invalid; allowed: {list(MIX_KINDS)}")


def generate_episode(cfg: DatasetConfig, episode: int) -> dict:
    """One episode's samples and Hankel data (deterministic in ``(cfg.seed, episode)``)."""
    gen = torch.Generator().manual_seed(cfg.seed * 1_000_003 + episode)
    rng = np.random.default_rng([cfg.seed, episode])
    pc = cfg.platoon()
    sim = None
    if cfg.backend == "sumo":
        from mixed_traffic.envs.sumo_platoon import SumoPlatoon

        sim = SumoPlatoon(pc, seconds=max(cfg.T * cfg.dt, cfg.episode_seconds))
    try:
        [h] = precollect(pc, T=cfg.T, t_ini=cfg.t_ini, n=cfg.n, generator=gen, simulator=sim)
        solver = DeepLCCSolver(h, cfg.qp_params())
        kind = cfg.episode_kinds()[episode]
        spec = episode_scenario(kind, cfg, rng)
        v = spec.head_speed(cfg.dt, 1, gen)

        def controller(uini, yini, eini):
            # the QP sees exactly the float32 values that are stored
            u32, y32, e32 = (x.astype(np.float32).astype(np.float64) for x in (uini, yini, eini))
            return np.stack([solver.solve(u32[b], y32[b], e32[b]).u for b in range(uini.shape[0])])

        out = run_closed_loop(controller, v, pc, cfg.t_ini, cfg.qp_params(), spec.adaptive_v_star, gen, record=True,
                              simulator=sim)
    finally:
        if sim is not None:
            sim.close()
    return {
        "uini": out["uini"][0].astype(np.float32), "yini": out["yini"][0].astype(np.float32),
        "eini": out["eini"][0].astype(np.float32), "u_opt": out["u"][0].astype(np.float64),
        "hankel": {k: v_.astype(np.float32) for k, v_ in h.as_dict().items()},
        "info": {"episode": episode, "kind": kind, "scenario": dataclasses.asdict(spec),
                 "cost": float(out["cost"][0]), "collision": bool(out["collisions"][0]),
                 "min_gap": float(out["min_gap"][0]), "qp_stats": solver.stats.as_dict()},
    }


_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _limit_threads():
    torch.set_num_threads(1)


def generate_dataset(cfg: DatasetConfig, progress: bool = True) -> dict[str, np.ndarray]:
    """All episodes (in a process pool when ``workers > 1``) -> arrays ready for :func:`write_dataset`."""
    cfg.validate()
    from tqdm import tqdm

    episodes = range(cfg.episodes)
    bar = tqdm(total=cfg.episodes, desc="mt-dataset", unit="episode", disable=not progress)
    results = [None] * cfg.episodes
    if cfg.workers == 1:
        for e in episodes:
            results[e] = generate_episode(cfg, e)
            bar.update(1)
    else:
        # one BLAS thread per worker process: workers are spawned lazily, so the
        # variables stay set while the pool lives and are restored afterwards
        saved = {k: os.environ.get(k) for k in _THREAD_VARS}
        os.environ.update({k: "1" for k in _THREAD_VARS})
        try:
            ctx = multiprocessing.get_context("spawn")
            with ProcessPoolExecutor(max_workers=cfg.workers, mp_context=ctx, initializer=_limit_threads) as pool:
                futures = {pool.submit(generate_episode, cfg, e): e for e in episodes}
                for fut in as_completed(futures):
                    results[futures[fut]] = fut.result()
                    bar.update(1)
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
    bar.close()
    return assemble(cfg, results)


def assemble(cfg: DatasetConfig, results: list[dict]) -> dict[str, np.ndarray]:
    qp = cfg.qp_params()
    data = {k: np.concatenate([r[k] for r in results]) for k in ("uini", "yini", "eini", "u_opt")}
    data["episode"] = np.concatenate([np.full(len(r["u_opt"]), r["info"]["episode"], np.int32) for r in results])
    for k in HANKEL_KEYS:
        data[k] = np.stack([r["hankel"][k] for r in results])
    data["metadata"] = np.array([cfg.v_star, cfg.s_star, cfg.t_ini, cfg.n, qp.lambda_g, qp.lambda_y], dtype=np.float64)
    data["qp"] = np.array(json.dumps({k: getattr(qp, k) for k in QP_FIELDS}, sort_keys=True))
    cfg_d = dataclasses.asdict(cfg)
    cfg_d["episodes_info"] = [r["info"] for r in results]
    data["config"] = np.array(json.dumps(cfg_d))
    return data


def write_dataset(path: str | os.PathLike, data: dict[str, np.ndarray]) -> str:
    """Validate ``data`` and write it atomically (temp file in the same directory, then rename)."""
    validate_dataset(data)
    path = os.fspath(path)
    d = os.path.dirname(os.path.abspath(path))
    os.makedirs(d, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=".npz", dir=d)
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        with os.fdopen(fd, "wb") as f:
            np.savez(f, **data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


@dataclass(frozen=True)
class ArrayInfo:
    """Shape and dtype of a stored array that was not read (validation without loading)."""

    shape: tuple
    dtype: np.dtype


def _shape(x):
    return tuple(x.shape)


def validate_dataset(data, check_values: bool = True) -> dict:
    """Check keys, shapes and dtypes; raise ValueError naming the key and the expected shape.

    Values may be arrays or :class:`ArrayInfo`; values are checked for finiteness
    when ``check_values`` and the value is an array. Returns the dimensions.
    """
    required = ("uini", "yini", "eini", "u_opt", "episode", "metadata", "qp", *HANKEL_KEYS)
    missing = [k for k in required if k not in data]
    if missing:
        raise ValueError(f"dataset: missing key(s) {missing}; required: {list(required)}")
    data = {k: (v if isinstance(v, ArrayInfo) else np.asarray(v)) for k, v in data.items()}
    md = data["metadata"]
    if _shape(md) != (6,) or isinstance(md, ArrayInfo):
        raise ValueError(f"dataset: key 'metadata' has shape {_shape(md)}; expected (6,) "
                         "[v_star, s_star, t_ini, N, lambda_g, lambda_y]")
    t_ini, n = int(md[2]), int(md[3])
    if t_ini < 1 or n < 1:
        raise ValueError(f"dataset: key 'metadata' holds t_ini={t_ini}, N={n}; expected both >= 1")
    u = _shape(data["u_opt"])
    if len(u) != 2:
        raise ValueError(f"dataset: key 'u_opt' has shape {u}; expected (N, m)")
    N, m = u
    y = _shape(data["yini"])
    if len(y) != 2 or y[1] % t_ini:
        raise ValueError(f"dataset: key 'yini' has shape {y}; expected (N, p*t_ini) with t_ini={t_ini}")
    p = y[1] // t_ini
    up = _shape(data["Up"])
    if len(up) != 3:
        raise ValueError(f"dataset: key 'Up' has shape {up}; expected (episodes, m*t_ini, columns)")
    E, M = up[0], up[-1]
    expected = {"uini": ((N, m * t_ini), "(N, m*t_ini)"), "yini": ((N, p * t_ini), "(N, p*t_ini)"),
                "eini": ((N, t_ini), "(N, t_ini)"), "episode": ((N,), "(N,)"),
                "Up": ((E, m * t_ini, M), "(episodes, m*t_ini, columns)"), "Uf": ((E, m * n, M), "(episodes, m*N, columns)"),
                "Ep": ((E, t_ini, M), "(episodes, t_ini, columns)"), "Ef": ((E, n, M), "(episodes, N, columns)"),
                "Yp": ((E, p * t_ini, M), "(episodes, p*t_ini, columns)"), "Yf": ((E, p * n, M), "(episodes, p*N, columns)")}
    for k, (shape, desc) in expected.items():
        if _shape(data[k]) != shape:
            raise ValueError(f"dataset: key {k!r} has shape {_shape(data[k])}; expected {shape} = {desc} "
                             f"with N={N}, m={m}, p={p}, t_ini={t_ini}, horizon N={n}, episodes={E}, columns={M}")
    for k in ("uini", "yini", "eini", "u_opt", *HANKEL_KEYS):
        if not np.issubdtype(data[k].dtype, np.floating):
            raise ValueError(f"dataset: key {k!r} has dtype {data[k].dtype}; expected a float type")
        if check_values and not isinstance(data[k], ArrayInfo) and not np.all(np.isfinite(data[k])):
            raise ValueError(f"dataset: key {k!r} contains non-finite values")
    ep = data["episode"]
    if not np.issubdtype(ep.dtype, np.integer):
        raise ValueError(f"dataset: key 'episode' has dtype {ep.dtype}; expected integers in [0, {E})")
    if N and not isinstance(ep, ArrayInfo) and (ep.min() < 0 or ep.max() >= E):
        raise ValueError(f"dataset: key 'episode' holds values outside [0, {E})")
    try:
        qp = json.loads(str(data["qp"]))
    except json.JSONDecodeError as e:
        raise ValueError(f"dataset: key 'qp' is not a JSON string: {e}") from e
    absent = [f for f in QP_FIELDS if f not in qp]
    if absent:
        raise ValueError(f"dataset: key 'qp' lacks field(s) {absent}; expected {list(QP_FIELDS)}")
    # the metadata and the solutions must agree with the stored QP settings
    for i, name in ((1, "s_star"), (4, "lambda_g"), (5, "lambda_y")):
        if not np.isclose(float(md[i]), float(qp[name]), rtol=1e-9, atol=0.0):
            raise ValueError(f"dataset: key 'metadata' holds {name}={float(md[i])!r} but key 'qp' says {qp[name]!r}; "
                             "expected the same value (metadata = [v_star, s_star, t_ini, N, lambda_g, lambda_y])")
    u_opt = data["u_opt"]
    if check_values and not isinstance(u_opt, ArrayInfo) and N:
        lo, hi = float(qp["dcel_max"]), float(qp["acel_max"])
        if u_opt.min() < lo - 1e-6 or u_opt.max() > hi + 1e-6:
            raise ValueError(f"dataset: key 'u_opt' holds values in [{u_opt.min():g}, {u_opt.max():g}]; expected "
                             f"QP solutions within the stored bounds [dcel_max, acel_max] = [{lo:g}, {hi:g}] m/s^2")
    return {"N": N, "m": m, "p": p, "t_ini": t_ini, "n": n, "episodes": E, "columns": M}


def load_dataset(path: str | os.PathLike, hankel: bool = True) -> dict:
    """Load and validate a dataset -> dict of arrays plus ``dims`` and ``qp_params`` (:class:`QPParams`).

    With ``hankel=False`` the (large) Hankel arrays are not read, only their shapes checked.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"dataset: no such file {path!r}; allowed: a .npz written by mt-dataset")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {}
            for k in z.keys():
                if hankel or k not in HANKEL_KEYS:
                    data[k] = z[k]
                else:
                    data[k] = ArrayInfo(*_npz_header(z, k))
    except Exception as e:  # BadZipFile, EOFError, a pickled or truncated member ...
        raise ValueError(f"dataset: {path!r} cannot be read ({type(e).__name__}: {e}); allowed: a complete .npz "
                         "written by mt-dataset (regenerate it)") from None
    try:
        dims = validate_dataset(data)
        data["qp_params"] = QPParams(**json.loads(str(data["qp"])))
    except (ValueError, TypeError) as e:
        raise ValueError(f"{path}: {e}") from None
    data["dims"] = dims
    return data


def _npz_header(z, key) -> tuple:
    """(shape, dtype) of an array in an open npz without reading its data."""
    from numpy.lib import format as npf

    with z.zip.open(key + ".npy") as f:
        major, _ = npf.read_magic(f)
        read = npf.read_array_header_1_0 if major == 1 else npf.read_array_header_2_0
        shape, _, dtype = read(f)
    return tuple(shape), dtype


def nn_inputs(data: dict) -> np.ndarray:
    """The NNMPC input ``[uini, yini, eini]`` (N, 260) as float32."""
    return np.concatenate([data["uini"], data["yini"], data["eini"]], axis=1).astype(np.float32)
