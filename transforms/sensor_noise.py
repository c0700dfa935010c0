"""SensorNoise: what a CAV measures of its gap and speeds, with measurement noise.

The env writes what each CAV measures exactly: its gap to the leader and to the head (``("cav", "gap")``,
``("cav", "head_gap")``), its own speed and its leader's and the head's (``("cav", "speed")``,
``("cav", "leader_speed")``, ``("cav", "head_speed")``), and the policy's observation vector built from them.
A real CAV reads these from radar and odometry. This transform adds Gaussian noise to each measurement at
every step and at reset, white or correlated in time (a first-order Gauss-Markov error, as a tracked radar
target's or an odometer's drifts), and moves the observation vector's features by what the noise moves
in them, so the policy, a residual's base and the safety layer all act on the same noisy measurements. The
simulation itself (``("traffic", ...)``, collisions, the reward) still runs on the true state. TorchRL has
no transform that perturbs a set of entries and a vector derived from them consistently, hence this one.
"""

from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase
from torchrl.data import Composite, Unbounded
from torchrl.envs.transforms import Transform

from transforms.specs import state_entries

GAPS = (("cav", "gap"), ("cav", "head_gap"))
SPEEDS = (("cav", "speed"), ("cav", "leader_speed"), ("cav", "head_speed"))


def observation_shift(delta: dict, obs: torch.Tensor, *, observation: str, s_max: float,
                      who: str = "SensorNoise") -> torch.Tensor:
    """How :func:`~mixed_traffic.envs.traffic.observe`'s ``observation`` layout moves when the measured entries
    move by ``delta`` (``{key: change}`` over :data:`GAPS` and :data:`SPEEDS`). The features are linear in the
    measurements, so the change is the features of ``delta`` itself, with the uniform-flow speed and the own
    acceleration (not measured here) unchanged. Shared by :class:`SensorNoise` and
    :class:`transforms.MeasurementFilter`."""
    from mixed_traffic.envs.traffic import relative_features

    v, zero = delta[("cav", "speed")], torch.zeros_like(delta[("cav", "speed")])
    feats = relative_features(v, delta[("cav", "leader_speed")], delta[("cav", "gap")], delta[("cav", "head_gap")],
                              delta[("cav", "head_speed")], zero, zero, s_max=s_max, a_scale=1.0)
    if observation == "relative_no_speed":
        feats = feats[1:]
    elif observation in ("relative_accel", "relative_time"):
        feats.append(torch.zeros_like(v))
    shift = torch.stack(feats, -1).flatten(-2)
    if shift.shape[-1] != obs.shape[-1]:
        raise RuntimeError(f"{who}: the observation has {obs.shape[-1]} features, the {observation!r} layout "
                           f"{shift.shape[-1]}; pass the env's own observation")
    return shift


def check_layout(name: str, observation: str, s_max: float) -> None:
    """Refuse an observation layout whose features :func:`observation_shift` cannot move, and a bad ``s_max``."""
    from mixed_traffic.scenarios import HEAD_OBSERVATIONS  # the "relative" family (mixed_traffic imports
    # the transforms package lazily, so this import is too)

    if observation not in HEAD_OBSERVATIONS:
        raise ValueError(f"{name}: observation={observation!r} is not supported; allowed: {list(HEAD_OBSERVATIONS)} "
                         "(the layouts whose features it can move)")
    if not float(s_max) > 0.0:
        raise ValueError(f"{name}: s_max={s_max!r} is invalid; allowed: > 0 (m)")


class SensorNoise(Transform):
    """Add noise of standard deviation ``gap_std`` to each measured gap and ``speed_std`` to each measured speed.

    Each measurement's error is a stationary first-order Gauss-Markov process of correlation time ``tau``:
    ``e_{k+1} = rho e_k + sqrt(1 - rho^2) std w_k``, ``rho = exp(-dt / tau)``, ``w_k ~ N(0, 1)``, drawn afresh at
    reset (``tau = 0``: white noise, independent every step). Each entry is its own reading with its own error: the
    leader's gap and speed from the CAV's radar, the head's over V2V (its broadcast position and speed), the CAV's
    own speed from its odometer. Where the CAV's leader is the head (the ring's CAV right behind it), that car is
    read twice, by two sensors, with independent errors; the safety layer and a residual's stopping envelope act
    on the leader's reading. The errors travel in the tensordict
    (``("sensor_noise", <entry>)``), so a collector's rollouts carry them. Draws come from the transform's own
    generator (``seed``), so two controllers evaluated on the same episodes with the same seed see the same noise. The observation
    vector (``"observation"``, one block of features per CAV) is moved by the noise in the features
    :func:`mixed_traffic.envs.traffic.observe` builds from these entries for the ``"relative"`` family of
    observations; any other observation is refused at construction.

    Args:
        gap_std: standard deviation of the gap noise (m, >= 0).
        speed_std: standard deviation of the speed noise (m/s, >= 0).
        seed: seed of the draws.
        observation: the env's observation layout (``TrafficScenario.observation``), one of
            ``"relative"``, ``"relative_accel"``, ``"relative_time"``, ``"relative_no_speed"``.
        s_max: the scenario's ``s_max`` (m), the scale of the observation's gap features.
        tau: correlation time of the errors (s, >= 0; 0, the default: white noise).
        dt: the env's step (s, > 0), with ``tau``.

    Example:
        >>> import torch
        >>> from torchrl.envs import TransformedEnv
        >>> from mixed_traffic import make_env
        >>> from transforms import SensorNoise
        >>> base = make_env("ring", batch_size=1, seed=0, observation="relative")
        >>> env = TransformedEnv(base, SensorNoise(1.0, 0.2, seed=0, observation=base.scenario.observation,
        ...                                          s_max=base.scenario.s_max))
        >>> td = env.rollout(5, lambda td: td.set("action", torch.zeros(1, 1)))
        >>> truth = make_env("ring", batch_size=1, seed=0, observation="relative").rollout(
        ...     5, lambda td: td.set("action", torch.zeros(1, 1)))
        >>> bool((td["next", "traffic", "gap"] == truth["next", "traffic", "gap"]).all())  # the physics: untouched
        True
        >>> bool((td["next", "cav", "gap"] == truth["next", "cav", "gap"]).any())  # what the CAV measures: noisy
        False
    """

    def __init__(self, gap_std: float = 0.0, speed_std: float = 0.0, *, seed: int = 0,
                 observation: str = "relative", s_max: float = 40.0, tau: float = 0.0, dt: float = 0.1):
        for name, value in (("gap_std", gap_std), ("speed_std", speed_std)):
            if not float(value) >= 0.0:
                raise ValueError(f"SensorNoise: {name}={value!r} is invalid; allowed: >= 0")
        check_layout("SensorNoise", observation, s_max)
        if not float(tau) >= 0.0:
            raise ValueError(f"SensorNoise: tau={tau!r} is invalid; allowed: >= 0 (s)")
        if not float(dt) > 0.0:
            raise ValueError(f"SensorNoise: dt={dt!r} is invalid; allowed: > 0 (s)")
        keys = [*GAPS, *SPEEDS]
        super().__init__(in_keys=keys, out_keys=keys)
        self.gap_std, self.speed_std, self.seed = float(gap_std), float(speed_std), int(seed)
        self.observation, self.s_max = observation, float(s_max)
        self.tau, self.dt = float(tau), float(dt)
        self.rho = math.exp(-self.dt / self.tau) if self.tau > 0 else 0.0
        self._gen = torch.Generator().manual_seed(self.seed)

    def _noise(self, like: torch.Tensor, std: float) -> torch.Tensor:
        if std == 0.0:
            return torch.zeros_like(like)
        return (std * torch.randn(like.shape, generator=self._gen, dtype=torch.float64)).to(like)

    @staticmethod
    def _state_key(key) -> tuple[str, str]:
        return ("sensor_noise", key[-1])

    def _measure(self, td: TensorDictBase, last: TensorDictBase | None) -> TensorDictBase:
        """Add this step's errors to ``td``'s measurements (following on ``last``'s errors; None: stationary
        draws, at reset) and move its observation vector with them."""
        n = {}
        for key in (*GAPS, *SPEEDS):
            std = self.gap_std if key in GAPS else self.speed_std
            fresh = self._noise(td.get(key), std)
            prev = None if last is None else last.get(self._state_key(key), None)
            n[key] = fresh if prev is None or self.rho == 0.0 else self.rho * prev + math.sqrt(1.0 - self.rho ** 2) * fresh
        for key, x in n.items():
            td.set(key, td.get(key) + x)
            td.set(self._state_key(key), x)
        obs = td.get("observation", None)
        if obs is not None:
            td.set("observation", obs + observation_shift(n, obs, observation=self.observation, s_max=self.s_max))
        return td

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._measure(tensordict_reset, None)

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        state_entries("SensorNoise", tensordict, "noise", self._state_key(GAPS[0]))
        return self._measure(next_tensordict, tensordict)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        return next_tensordict  # everything happens in _step / _reset

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise RuntimeError("SensorNoise perturbs a live env's measurements; use it inside an env")

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        leaves = {}
        for key in (*GAPS, *SPEEDS):
            leaf = observation_spec[key]
            leaves[key[-1]] = Unbounded(shape=leaf.shape, dtype=leaf.dtype, device=leaf.device)
        observation_spec["sensor_noise"] = Composite(**leaves, shape=observation_spec.shape, device=observation_spec.device)
        return observation_spec

    def __repr__(self) -> str:
        tau = f", tau={self.tau}" if self.tau else ""
        return f"{type(self).__name__}(gap_std={self.gap_std}, speed_std={self.speed_std}{tau}, seed={self.seed})"
