"""MeasurementFilter: a Kalman filter between a CAV's noisy sensors and whatever acts on them.

:class:`transforms.SensorNoise` gives the CAV radar- and odometer-grade errors on its gaps and speeds; every
controller behind it (the policy, a residual's base, the safety layer, IDM, CACC) then reacts to the noise,
and its jerk grows with it. A CAV does not act on raw measurements: it tracks them. This transform is that
tracker, a Kalman filter per CAV over

    x = [gap, v, v_leader, head_gap, v_head,  e_gap, e_v, e_leader, e_head_gap, e_head]

the five measured quantities and the five measurement errors, modelled as the first-order Gauss-Markov
processes :class:`transforms.SensorNoise` draws (correlated over ``tau`` s; white when ``tau`` is 0). Its
prediction uses what a CAV knows without a sensor: its own executed acceleration (``("cav", "accel")``) and
its leader's, received over V2V (``("cav", "leader_accel")``, degraded by :class:`transforms.V2VChannel` when
it stands before this transform); the head's acceleration too where the head is the CAV's leader. The motion
is the env's Euler rule (``v' = v + a dt``, ``gap' = gap + (v_l' - v') dt``).

Over a late link (``leader_accel_delay`` steps late) the received acceleration is the leader's of that long
ago, so it cannot drive the prediction. The filter then carries the leader's accelerations of the last
``leader_accel_delay + 1`` steps as states: the newest moves the leader and changes from step to step by up
to ``leader_jerk_std``, and the received value is a measurement of the oldest. The leader's speed measurements
tell the filter what the leader has done since; the late message pins down what it did before.

The model is linear and time-invariant, so the error covariance does not depend on the data, only on the
time since the reset: the gains of every step are computed once at construction (the Riccati recursion from
the first measurement's covariance, until it reaches the steady state of the discrete Riccati equation), and
each step is one matrix product with the gain of its row's age. ``posterior_std`` gives the steady state's
error standard deviation of each estimate, which is what a safety margin should be sized on
behind the filter (``eval.sensor_noise_margin`` does so when the filter is on).

It writes the estimates over the measured entries, moves the observation vector with them (as
:class:`transforms.SensorNoise` moves it with the noise), keeps its state in ``("sensor_filter", "state")``,
and writes each estimate's error against the true state to ``("sensor_filter", <entry>)`` for the
evaluation's true-state metrics (it reads :class:`transforms.SensorNoise`'s errors for that bookkeeping
only; the estimate never uses them). TorchRL has no state estimator transform, hence this one.
"""

from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Composite, Unbounded
from torchrl.envs.transforms import Transform

from transforms.sensor_noise import check_layout, observation_shift
from transforms.specs import state_entries

MEASURED = (("cav", "gap"), ("cav", "speed"), ("cav", "leader_speed"), ("cav", "head_gap"), ("cav", "head_speed"))
OWN_ACCEL, LEADER_ACCEL = ("cav", "accel"), ("cav", "leader_accel")
STATE, STEPS = ("sensor_filter", "state"), ("sensor_filter", "steps")


def steady_state_gain(F: torch.Tensor, G: torch.Tensor, Q: torch.Tensor, H: torch.Tensor,
                      R: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The steady-state Kalman gain ``K`` and updated covariance ``P+`` of ``x' = F x + G w``, ``z = H x + r``
    (``w ~ N(0, Q)``, ``r ~ N(0, R)``): the discrete algebraic Riccati equation's solution (scipy), float64.

    Raises ValueError when it has none (a model whose errors the measurements cannot pin down)."""
    import numpy as np
    from scipy.linalg import solve_discrete_are

    f, h, gqg, r = (np.asarray(m, dtype=np.float64) for m in (F, H, G @ Q @ G.T, R))
    try:
        prior = solve_discrete_are(f.T, h.T, gqg, r)
    except (np.linalg.LinAlgError, ValueError) as err:
        raise ValueError(f"steady_state_gain: no steady state ({err})") from None
    K = prior @ h.T @ np.linalg.inv(h @ prior @ h.T + r)
    post = (np.eye(f.shape[0]) - K @ h) @ prior
    return torch.from_numpy(K), torch.from_numpy(0.5 * (post + post.T))


def gain_sequence(F: torch.Tensor, G: torch.Tensor, Q: torch.Tensor, H: torch.Tensor, R: torch.Tensor,
                  P0: torch.Tensor, K_ss: torch.Tensor, *, tol: float = 1e-5, max_steps: int = 5000) -> torch.Tensor:
    """The Kalman gains of steps 1, 2, ... from the covariance ``P0`` at step 0 (the Riccati recursion, float64),
    up to the first within ``tol`` of the steady state's ``K_ss`` (``[steps, n, m]``; at most ``max_steps``;
    the filter uses ``K_ss`` from then on)."""
    eye, GQG, P, gains = torch.eye(F.shape[0], dtype=torch.float64), G @ Q @ G.T, P0, []
    for _ in range(max_steps):
        prior = F @ P @ F.T + GQG
        K = prior @ H.T @ torch.linalg.inv(H @ prior @ H.T + R)
        P = (eye - K @ H) @ prior
        gains.append(K)
        if float((K - K_ss).abs().max()) < tol:
            break
    return torch.stack(gains + [K_ss])


class MeasurementFilter(Transform):
    """Replace each CAV's measured gaps and speeds by a Kalman filter's estimates of them.

    Args:
        gap_std: standard deviation of the gap measurements' errors the filter assumes (m, >= 0).
        speed_std: standard deviation of the speed measurements' errors (m/s, >= 0).
        tau: their correlation time (s, >= 0; 0: white).
        dt: the env's step (s, > 0).
        observation: the env's observation layout (the ``"relative"`` family, as :class:`transforms.SensorNoise`).
        s_max: the scenario's ``s_max`` (m), the scale of the observation's gap features.
        leader_is_head: per CAV, whether its leader is the head (its head then moves with the received leader
            acceleration too); one flag for every CAV, or a tuple with one per CAV.
        own_accel_std: how far the CAV's executed acceleration may be from ``("cav", "accel")`` (m/s^2, > 0).
        leader_accel_std: how far the leader's may be from the one received over V2V, or from 0 when nothing
            is received (m/s^2, > 0).
        head_accel_std: the head's acceleration where nothing is received of it (m/s^2, > 0).
        gap_drift_std: how far a gap may move in one step beyond what the speeds explain (m, > 0).
        leader_accel_key: where the leader's received acceleration is (None: nothing is received; the leader
            then moves as ``leader_accel_std`` allows, and the head as ``head_accel_std`` does).
        leader_accel_delay: how many steps late the received acceleration arrives (an integer >= 0, the
            :class:`transforms.V2VChannel`'s ``delay_steps``); > 0 needs ``leader_accel_key`` and uses the
            delayed-link model above (``leader_accel_std`` is then unused).
        leader_jerk_std: over a late link, how far the leader's acceleration may change in one step (m/s^2, > 0).

    The accelerations' defaults suit exact V2V and an actuator that does what it is told. The evaluation
    (:func:`mixed_traffic.training.builders.eval_measurement_filter`) trusts a lossy link less
    (``leader_accel_std=0.5``), reads a late one with the delayed-link model (``leader_accel_delay``), and does
    not read a dead one, or one both late and lossy (``leader_accel_key=None``, ``leader_accel_std=10``). A
    stale acceleration taken for the present says the leader cruises while it brakes, and puts the estimate
    metres per second behind it.

    Attributes:
        posterior_std: ``{leader_is_head flag: [gap, speed, leader_speed, head_gap, head_speed]}``, the steady
            state's standard deviation of each estimate's error (m, m/s).

    Example:
        >>> import torch
        >>> from torchrl.envs import Compose, TransformedEnv
        >>> from mixed_traffic import make_env
        >>> from transforms import MeasurementFilter, SensorNoise
        >>> base = make_env("ring", batch_size=4, seed=0, observation="relative")
        >>> sc = base.scenario
        >>> env = TransformedEnv(base, Compose(
        ...     SensorNoise(1.0, 0.3, seed=0, s_max=sc.s_max, tau=1.0),
        ...     MeasurementFilter(1.0, 0.3, tau=1.0, s_max=sc.s_max)))
        >>> td = env.rollout(600, lambda td: td.set("action", torch.zeros(4, 1)))
        >>> raw = td["next", "sensor_noise", "gap"][:, 300:].std()  # the sensor's error, after 30 s
        >>> est = td["next", "sensor_filter", "gap"][:, 300:].std()  # the filter's
        >>> bool(est < 0.5 * raw)
        True
    """

    def __init__(self, gap_std: float = 0.0, speed_std: float = 0.0, *, tau: float = 0.0, dt: float = 0.1,
                 observation: str = "relative", s_max: float = 40.0, leader_is_head: bool | tuple[bool, ...] = True,
                 own_accel_std: float = 0.02, leader_accel_std: float = 0.1, head_accel_std: float = 1.0,
                 gap_drift_std: float = 0.003, leader_accel_key: NestedKey | None = LEADER_ACCEL,
                 leader_accel_delay: int = 0, leader_jerk_std: float = 0.5):
        if isinstance(leader_accel_delay, bool) or not isinstance(leader_accel_delay, int) or leader_accel_delay < 0:
            raise ValueError(f"MeasurementFilter: leader_accel_delay={leader_accel_delay!r} is invalid; allowed: an "
                             "integer >= 0 (steps)")
        if leader_accel_delay > 0 and leader_accel_key is None:
            raise ValueError("MeasurementFilter: leader_accel_delay > 0 needs a leader_accel_key (what arrives late)")
        for name, value in (("gap_std", gap_std), ("speed_std", speed_std), ("tau", tau)):
            if not float(value) >= 0.0:
                raise ValueError(f"MeasurementFilter: {name}={value!r} is invalid; allowed: >= 0")
        for name, value in (("dt", dt), ("own_accel_std", own_accel_std), ("leader_accel_std", leader_accel_std),
                            ("head_accel_std", head_accel_std), ("gap_drift_std", gap_drift_std),
                            ("leader_jerk_std", leader_jerk_std)):
            if not float(value) > 0.0:
                raise ValueError(f"MeasurementFilter: {name}={value!r} is invalid; allowed: > 0")
        check_layout("MeasurementFilter", observation, s_max)
        keys = list(MEASURED)
        super().__init__(in_keys=keys, out_keys=keys)
        self.gap_std, self.speed_std, self.tau, self.dt = float(gap_std), float(speed_std), float(tau), float(dt)
        self.observation, self.s_max = observation, float(s_max)
        self.accel_std = (float(own_accel_std), float(leader_accel_std), float(head_accel_std))
        self.gap_drift_std = float(gap_drift_std)
        self.leader_accel_key = leader_accel_key
        self.delay, self.leader_jerk_std = int(leader_accel_delay), float(leader_jerk_std)
        self.n_state = 10 + (self.delay + 1 if self.delay else 0)  # + the leader's accelerations over a late link
        self._stds = [self.gap_std, self.speed_std, self.speed_std, self.gap_std, self.speed_std]  # MEASURED's
        flags = (leader_is_head,) if isinstance(leader_is_head, bool) else tuple(bool(f) for f in leader_is_head)
        self.leader_is_head = flags
        self._by_flag = {}  # per flag: F, B, the gains from the reset on (the last: the steady state's), P+
        for f in sorted(set(flags)):
            F, B, G, Q, H, R = self._model(f)
            K_ss, P_ss = steady_state_gain(F, G, Q, H, R)
            S = torch.diag(torch.diagonal(R)[:5] + torch.tensor(self._stds, dtype=torch.float64) ** 2)  # the first
            # measurement's error
            P0 = torch.zeros(self.n_state, self.n_state, dtype=torch.float64)
            P0[:10, :10] = torch.cat([torch.cat([S, -S], 1), torch.cat([-S, S], 1)])  # x = z - e, e unknown
            P0[10:, 10:] = torch.eye(self.n_state - 10, dtype=torch.float64)  # the leader's accelerations: 1 m/s^2
            self._by_flag[f] = (F, B, gain_sequence(F, G, Q, H, R, P0, K_ss), P_ss, H)
        self._cache: dict = {}
        # the steady state's standard deviation of each estimate's error, in MEASURED's order, per flag
        self.posterior_std = {f: torch.sqrt(torch.diagonal(m[3])[:5]).tolist() for f, m in self._by_flag.items()}

    # ------------------------------------------------------------------ the model

    def _model(self, head_from_leader: bool):
        """``F``, the input matrix ``B`` (inputs: own, leader and head acceleration), ``G``, ``Q``, ``H``, ``R``.

        Over a late link (``delay`` > 0) the leader's acceleration is no input but states ``10 .. 10 + delay``
        (the newest first), and the received value a measurement of the last."""
        dt, n = self.dt, self.n_state
        F = torch.eye(n, dtype=torch.float64)
        F[0, 1], F[0, 2] = -dt, dt   # gap' = gap + (v_l - v) dt + (a_l - a) dt^2
        F[3, 1], F[3, 4] = -dt, dt   # head_gap' likewise with the head
        rho = math.exp(-dt / self.tau) if self.tau > 0 else 0.0
        for i in range(5, 10):
            F[i, i] = rho
        B = torch.zeros(n, 3, dtype=torch.float64)
        B[0, 0], B[3, 0], B[1, 0] = -dt * dt, -dt * dt, dt
        B[0, 1], B[2, 1] = dt * dt, dt
        B[3, 2], B[4, 2] = dt * dt, dt
        G = torch.zeros(n, 10, dtype=torch.float64)
        G[:, :3] = B
        if self.delay:  # the newest acceleration moves the leader (and the head) and walks by w_1 per step
            moved = (0, 2, 3, 4) if head_from_leader else (0, 2)
            for i in moved:
                F[i, 10] = B[i, 1] + B[i, 2]  # the leader's rows carry B's leader column, the head's its head column
            G[:, 1] = F[:, 10].clone()
            G[10, 1] = 1.0
            B[:, 1] = 0.0
            for j in range(1, self.delay + 1):  # the older ones shift down the line
                F[10 + j, 10 + j] = 0.0
                F[10 + j, 9 + j] = 1.0
        for j in range(5):
            G[5 + j, 3 + j] = 1.0
        G[0, 8], G[3, 9] = 1.0, 1.0  # the gaps' own drift (the integration's rounding, a simulator's other rule)
        stds = self._stds
        own, leader, head = self.accel_std
        if self.delay:
            leader = self.leader_jerk_std
        Q = torch.diag(torch.tensor([own ** 2, leader ** 2, (leader if head_from_leader else head) ** 2]
                                    + [(1.0 - rho ** 2) * s ** 2 for s in stds] + [self.gap_drift_std ** 2] * 2,
                                    dtype=torch.float64))
        m = 5 + (1 if self.delay else 0)
        H = torch.zeros(m, n, dtype=torch.float64)
        H[:5, :5], H[:5, 5:10] = torch.eye(5, dtype=torch.float64), torch.eye(5, dtype=torch.float64)
        if self.delay:
            H[5, n - 1] = 1.0  # the received value: the oldest acceleration the filter carries
        # a floor under the measurement noise: the errors are states, but a zero R with a zero std is singular
        R = torch.diag(torch.tensor([(1e-2 * s) ** 2 + 1e-8 for s in stds] + [1e-6] * (m - 5), dtype=torch.float64))
        return F, B, G, Q, H, R

    # ------------------------------------------------------------------ the filter

    def _matrices(self, n_cav: int, like: torch.Tensor):
        flags = self.leader_is_head * n_cav if len(self.leader_is_head) == 1 else self.leader_is_head
        if len(flags) != n_cav:
            raise RuntimeError(f"MeasurementFilter: leader_is_head has {len(flags)} flags for {n_cav} CAVs; "
                               "give one, or one per CAV")
        key = (n_cav, like.device, like.dtype)
        if key not in self._cache:
            F, B, H = (torch.stack([self._by_flag[f][i] for f in flags]).to(like) for i in (0, 1, 4))
            seqs = [self._by_flag[f][2] for f in flags]
            T = max(len(s) for s in seqs)  # padded with each one's steady state
            K = torch.stack([torch.cat([s, s[-1:].expand(T - len(s), -1, -1)]) for s in seqs], 1).to(like)
            self._cache[key] = (F, B, K, torch.tensor(flags, device=like.device), H)
        return self._cache[key]

    def _z(self, td: TensorDictBase) -> torch.Tensor:
        return torch.stack([td.get(k) for k in MEASURED], -1)  # [..., n_cav, 5]

    def _write(self, td: TensorDictBase, state: torch.Tensor, steps: torch.Tensor, z: torch.Tensor) -> TensorDictBase:
        est = state[..., :5]
        delta = {k: est[..., i] - z[..., i] for i, k in enumerate(MEASURED)}
        for i, k in enumerate(MEASURED):
            noise = td.get(("sensor_noise", k[-1]), None)
            td.set(k, est[..., i])
            # the estimate's error against the true state (= the measurement less the sensor's error)
            td.set(("sensor_filter", k[-1]), delta[k] + (noise if noise is not None else 0.0))
        td.set(STATE, state)
        td.set(STEPS, steps)
        obs = td.get("observation", None)
        if obs is not None:
            td.set("observation", obs + observation_shift(delta, obs, observation=self.observation, s_max=self.s_max,
                                                                  who="MeasurementFilter"))
        return td

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        z = self._z(tensordict_reset)
        steps = torch.zeros(z.shape[:-1], dtype=torch.int64, device=z.device)
        state = [z, torch.zeros_like(z)]
        if self.delay:  # the leader's last accelerations: the one received at the reset
            state.append(self._received(tensordict_reset).unsqueeze(-1).expand(*z.shape[:-1], self.delay + 1))
        return self._write(tensordict_reset, torch.cat(state, -1), steps, z)

    def _received(self, td: TensorDictBase) -> torch.Tensor | None:
        a_l = None if self.leader_accel_key is None else td.get(self.leader_accel_key, None)
        if a_l is None and self.leader_accel_key is not None:
            raise RuntimeError(f"MeasurementFilter: no {self.leader_accel_key!r} in the env's output; pass "
                               "leader_accel_key=None for a CAV that receives nothing over V2V")
        return a_l

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        (prev,) = state_entries("MeasurementFilter", tensordict, "filter", STATE)
        z = self._z(next_tensordict)
        F, B, K, flags, H = self._matrices(z.shape[-2], z)
        a = next_tensordict.get(OWN_ACCEL)
        received = self._received(next_tensordict)
        a_l = torch.zeros_like(a) if received is None or self.delay else received  # late: a measurement, no input
        a_h = torch.where(flags, a_l, torch.zeros_like(a_l))
        u = torch.stack([a, a_l, a_h], -1)  # [..., n_cav, 3]
        prior = (F @ prev.unsqueeze(-1)).squeeze(-1) + (B @ u.unsqueeze(-1)).squeeze(-1)
        if self.delay:
            z = torch.cat([z, received.unsqueeze(-1)], -1)
        innovation = z - (H @ prior.unsqueeze(-1)).squeeze(-1)
        age = tensordict.get(STEPS).clamp_max(K.shape[0] - 1)  # the gain of step age + 1 is K[age]
        gain = K[age, torch.arange(K.shape[1], device=age.device)]  # [..., n_cav, n_state, 5 (+ 1 when late)]
        state = prior + (gain @ innovation.unsqueeze(-1)).squeeze(-1)
        return self._write(next_tensordict, state, (age + 1).clamp_max(K.shape[0] - 1), z[..., :5])

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        return next_tensordict  # everything happens in _step / _reset

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise RuntimeError("MeasurementFilter tracks a live env's measurements; use it inside an env")

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        leaf = observation_spec[MEASURED[0]]
        leaves = {k[-1]: Unbounded(shape=leaf.shape, dtype=leaf.dtype, device=leaf.device) for k in MEASURED}
        leaves["state"] = Unbounded(shape=(*leaf.shape, self.n_state), dtype=leaf.dtype, device=leaf.device)
        leaves["steps"] = Unbounded(shape=leaf.shape, dtype=torch.int64, device=leaf.device)
        observation_spec["sensor_filter"] = Composite(**leaves, shape=observation_spec.shape,
                                                      device=observation_spec.device)
        return observation_spec

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(gap_std={self.gap_std}, speed_std={self.speed_std}, tau={self.tau}, "
                f"accel_std={self.accel_std}" + (f", leader_accel_delay={self.delay}, leader_jerk_std="
                                                  f"{self.leader_jerk_std}" if self.delay else "") + ")")
