"""OnboardLeaderAccel: the leader's acceleration from the CAV's own measurements when the V2V link is silent.

A CAV measures its leader's speed on board (radar range rate plus its own speed), so it can tell its leader's
acceleration without a radio: the measured speed's change over a step. The V2V message is the better source
while it arrives (the leader's own reading, unaffected by the CAV's sensors); over a dead or late link a held
message says nothing of what the leader does now, and whatever reads it (the residual base's brake floor and
margin gate, CACC) acts on stale news. This transform keeps an on-board estimate and puts it in place of the
received value once that value is older than ``after`` seconds (``("v2v", "age")``, written by
:class:`transforms.V2VChannel`); without a channel the link is perfect and nothing is replaced.

TorchRL has no transform that differentiates an entry over time, hence this one.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Composite
from torchrl.envs.transforms import Transform

from transforms.specs import kept_rows, with_state_spec

LEADER_SPEED, LEADER_ACCEL, AGE = ("cav", "leader_speed"), ("cav", "leader_accel"), ("v2v", "age")


class OnboardLeaderAccel(Transform):
    """Replace ``accel_key`` by the change of the measured ``speed_key`` over a step when the link is silent.

    Each step the estimate moves toward ``(v_leader - v_leader_before) / dt`` by ``dt / (tau + dt)`` (a
    first-order low-pass over ``tau`` s; 0: the raw difference). On an exact measurement the raw difference is
    the leader's acceleration of the last step, the value a perfect link delivers. Behind noisy sensors,
    difference the tracked speed of a :class:`transforms.MeasurementFilter` (put this transform after it) or set
    a ``tau``.

    The received value is replaced on the rows whose message is older than ``after`` seconds (``age_key``, in
    steps; a missing entry counts as fresh); ``after=None``: always (a CAV without V2V). The estimate and the
    last measured speed travel in ``("onboard_accel", "estimate")`` / ``("onboard_accel", "speed")``, and
    ``("onboard_accel", "used")`` says where the estimate was read. At reset the
    estimate is the env's reset value of ``accel_key``; a row reset alone keeps the others'. Put it after the
    transforms that write ``speed_key`` and ``age_key`` (the evaluation puts its noise, link and filter first).

    Args:
        dt: the env's step (s).
        after: seconds a received value may age before the estimate replaces it (>= 0), or None.
        tau: time constant of the estimate's low-pass (s, >= 0).
        speed_key, accel_key, age_key: the measured leader speed, the entry replaced, and the link's age.

    Example:
        >>> import torch
        >>> from torchrl.envs import Compose, TransformedEnv
        >>> from mixed_traffic import make_env
        >>> from transforms import OnboardLeaderAccel, V2VChannel
        >>> kw = dict(profile="sine", profile_kwargs={"v_star": 12.5, "amplitude": 5.0, "period": 10.0})
        >>> dead = Compose(V2VChannel(loss=1.0), OnboardLeaderAccel(dt=0.1, after=0.5))
        >>> env = TransformedEnv(make_env("ring", batch_size=1, seed=0, **kw), dead)
        >>> act = lambda td: td.set("action", torch.zeros(1, 1))
        >>> got = env.rollout(40, act)["next", "cav", "leader_accel"]
        >>> sent = make_env("ring", batch_size=1, seed=0, **kw).rollout(40, act)["next", "cav", "leader_accel"]
        >>> bool(torch.allclose(got[:, 10:], sent[:, 10:], atol=1e-3)), bool((got[:, :5] == 0).all())
        (True, True)
    """

    def __init__(self, dt: float, after: float | None = 1.0, tau: float = 0.0, *, speed_key: NestedKey = LEADER_SPEED,
                 accel_key: NestedKey = LEADER_ACCEL, age_key: NestedKey = AGE):
        if not float(dt) > 0:
            raise ValueError(f"OnboardLeaderAccel: dt={dt!r} is invalid; allowed: > 0 (s)")
        if after is not None and not float(after) >= 0:
            raise ValueError(f"OnboardLeaderAccel: after={after!r} is invalid; allowed: >= 0 (s), or None (always)")
        if not float(tau) >= 0:
            raise ValueError(f"OnboardLeaderAccel: tau={tau!r} is invalid; allowed: >= 0 (s)")
        super().__init__(in_keys=[speed_key, accel_key], out_keys=[accel_key])
        self.dt, self.after, self.tau = float(dt), None if after is None else float(after), float(tau)
        self.speed_key, self.accel_key, self.age_key = speed_key, accel_key, age_key
        self.estimate_key, self.last_key, self.used_key = (("onboard_accel", "estimate"), ("onboard_accel", "speed"),
                                                           ("onboard_accel", "used"))

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        speed, accel = tensordict_reset.get(self.speed_key), tensordict_reset.get(self.accel_key)
        estimate, used = accel.clone(), torch.zeros_like(accel, dtype=torch.bool)
        keep = kept_rows(tensordict, speed, self.last_key)
        if keep is not None:  # rows not reset keep their estimate (and what they read)
            estimate = torch.where(keep, tensordict.get(self.estimate_key), estimate)
            speed = torch.where(keep, tensordict.get(self.last_key), speed)
            used = torch.where(keep, tensordict.get(self.used_key), used)
            tensordict_reset.set(self.accel_key, torch.where(used, estimate, accel))
        tensordict_reset.set(self.estimate_key, estimate)
        tensordict_reset.set(self.last_key, speed.clone())
        tensordict_reset.set(self.used_key, used)
        return tensordict_reset

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        last, estimate = tensordict.get(self.last_key, None), tensordict.get(self.estimate_key, None)
        if last is None or estimate is None:
            raise RuntimeError("OnboardLeaderAccel: the step's input has no estimate; reset the env through the "
                               "TransformedEnv before stepping it")
        speed = next_tensordict.get(self.speed_key)
        estimate = estimate + (self.dt / (self.tau + self.dt)) * ((speed - last) / self.dt - estimate)
        if self.after is None:
            used = torch.ones_like(speed, dtype=torch.bool)
        else:
            age = next_tensordict.get(self.age_key, None)
            used = torch.zeros_like(speed, dtype=torch.bool) if age is None else age * self.dt > self.after + 1e-9
        next_tensordict.set(self.accel_key, torch.where(used, estimate, next_tensordict.get(self.accel_key)))
        next_tensordict.set(self.estimate_key, estimate)
        next_tensordict.set(self.last_key, speed)
        next_tensordict.set(self.used_key, used)
        return next_tensordict

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        return next_tensordict  # everything happens in _step / _reset (needs the last step's speed)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise RuntimeError("OnboardLeaderAccel differentiates a live env's entry over time; use it inside an env")

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        return with_state_spec(observation_spec, "onboard_accel", self.speed_key, estimate=None, speed=None,
                               used=torch.bool)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(dt={self.dt}, after={self.after}, tau={self.tau})"
