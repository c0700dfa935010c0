"""DriveOffCap: after a standstill, the CAV eases onto its leader's speed from below.

Behind a leader that stops and drives off, a car-following law lags the drive-off, the gap opens, and the law
then closes it by driving faster than the leader: during the leader's next steady stretch the CAV is still
above its speed (the steady speed error of a stop-and-go head). This transform caps the executed command after
a standstill at ``gain * (v_leader + overspeed - v)``, so the CAV approaches the leader's speed from below and
then closes the gap at no more than ``overspeed`` above it. The cap lifts as the gap, projected to where a CAV
that closes its speed deficit at ``accel`` would have it, rises from ``gaps[0]`` to ``gaps[1]``: the gap
stays in the band. It engages when the car and its leader are both below ``standstill`` (a car that reads
noisy speeds does not take a dip of its own measurement for a stop) and releases once the car has
matched its leader's speed (within ``match``) and the command has stayed under the cap for ``release`` s: then
the law drives as before. A command below the cap passes untouched; braking is never capped.

With ``follow`` set, the leader's own drive-off also sets a floor: while the cap is engaged and the leader
accelerates by more than ``follow_above``, the command is at least ``min(follow * a_leader, cap)`` (the leader's
acceleration ``("cav", "leader_accel")``, as CACC reads it), so the CAV keeps up with a long drive-off from its
start instead of catching up on it later (off by default; ``docs/results.md``, "Following the leader's drive-off").
A late or wrong reading of the leader's acceleration must not push the CAV into it: with ``guard`` the floor never
exceeds the safety layer's stopping bound (:func:`transforms.safety_layer.safe_accel_upper`).

It stands between the safety layer and the residual in the chain (``transforms.residual.drive_off``), so it
caps the sum of the base and the learned residual, and the safety layer still has the last word. Its state
travels in the tensordict (``("drive_off", "engaged")``, ``("drive_off", "calm")``), so a row reset on its own
starts afresh and a collector's rollouts carry it. TorchRL has no transform that caps an action by a rule with
memory, hence this one.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Composite
from torchrl.envs.transforms import Transform

from transforms.safety_layer import safe_accel_upper
from transforms.specs import carry_to_next, entries_or_none, reset_state, state_entries, with_state_spec

GAP, SPEED, LEADER_SPEED, LEADER_ACCEL = ("cav", "gap"), ("cav", "speed"), ("cav", "leader_speed"), ("cav", "leader_accel")
ENGAGED, CALM = ("drive_off", "engaged"), ("drive_off", "calm")


class DriveOffCap(Transform):
    """Cap the executed acceleration at ``gain * (v_leader + overspeed - v)`` from a standstill until released.

    Args:
        gain: how fast the CAV closes on its leader's speed from below (1/s, > 0).
        overspeed: how far above its leader's speed the CAV may drive while the cap holds (m/s, >= 0).
        gaps: ``(from, full)`` (m, ``0 <= from < full``): the cap lifts linearly as the projected gap
            ``gap + max(v_leader - v, 0)^2 / (2 accel)`` rises from ``from`` to ``full``.
        accel: the acceleration (m/s^2, > 0) at which the projection closes the speed deficit.
        release: how long (s, > 0) the car must have matched its leader with the command under the cap before
            the cap releases.
        standstill: the speed (m/s, > 0) below which the car and its leader engage the cap.
        match: how close below its leader's speed (m/s, > 0) counts as matched.
        dt: the env's step (s, > 0).
        follow: while engaged and the leader accelerates, the command's floor as a share of the leader's
            acceleration (``(0, 1.5]``; None: no floor).
        follow_above: the leader's acceleration (m/s^2, >= 0) above which the floor holds.
        guard: ``(stop_gap, brake, leader_brake)`` (m, m/s^2, m/s^2): the floor stays within the stopping rule that
            keeps ``stop_gap`` whatever the leader does within ``leader_brake``; None: unguarded.
        hold: while the leader stands, the CAV stands too: ``overspeed`` grows from 0 with the leader's speed up to
            ``standstill`` (where it is whole), so the cap behind a stopped leader is ``-gain v`` and a command that
            would creep toward it is held at 0 (False: ``overspeed`` throughout, as before).
        action_key: the executed acceleration (default ``"action"``).

    Example:
        >>> import torch
        >>> from torchrl.envs import Compose, TransformedEnv
        >>> from mixed_traffic import make_env
        >>> from mixed_traffic.controllers.classic import make_classic_policy
        >>> from transforms import DriveOffCap, ResidualAction
        >>> stops = dict(profile="piecewise", profile_kwargs={"times": [0, 10, 17.5, 23.5, 31, 60],
        ...                                                    "speeds": [15, 15, 0, 0, 15, 15]})
        >>> base = make_env("ring", batch_size=1, seed=0, **stops)
        >>> env = TransformedEnv(base, Compose(DriveOffCap(dt=base.scenario.dt),
        ...                                    ResidualAction(make_classic_policy("idm", base), weight=0.0)))
        >>> td = env.rollout(600, lambda td: td.set("action", torch.zeros(1, 1)))
        >>> after = td["next", "cav", "speed"][0, 400:] - td["next", "cav", "leader_speed"][0, 400:]
        >>> bool(after.max() < 0.16)  # after the drive-off the CAV does not pass its leader's speed + overspeed
        True
    """

    def __init__(self, gain: float = 1.0, overspeed: float = 0.15, gaps: tuple[float, float] = (34.0, 38.0),
                 accel: float = 1.5, release: float = 5.0, standstill: float = 0.5, match: float = 0.3, *,
                 dt: float = 0.1, follow: float | None = None, follow_above: float = 0.3, guard=None,
                 hold: bool = False, action_key: NestedKey = "action"):
        for name, value in (("gain", gain), ("accel", accel), ("release", release), ("standstill", standstill),
                            ("match", match), ("dt", dt)):
            if not float(value) > 0.0:
                raise ValueError(f"DriveOffCap: {name}={value!r} is invalid; allowed: > 0")
        if not float(overspeed) >= 0.0:
            raise ValueError(f"DriveOffCap: overspeed={overspeed!r} is invalid; allowed: >= 0 (m/s)")
        if follow is not None and not 0.0 < float(follow) <= 1.5:
            raise ValueError(f"DriveOffCap: follow={follow!r} is invalid; allowed: None or in (0, 1.5]")
        if not float(follow_above) >= 0.0:
            raise ValueError(f"DriveOffCap: follow_above={follow_above!r} is invalid; allowed: >= 0 (m/s^2)")
        if not (len(gaps) == 2 and 0.0 <= float(gaps[0]) < float(gaps[1])):
            raise ValueError(f"DriveOffCap: gaps={gaps!r} is invalid; allowed: (from, full) with 0 <= from < full (m)")
        super().__init__(in_keys=[], out_keys=[], in_keys_inv=[action_key], out_keys_inv=[action_key])
        self.gain, self.overspeed, self.accel = float(gain), float(overspeed), float(accel)
        self.gaps = (float(gaps[0]), float(gaps[1]))
        self.release, self.standstill, self.match, self.dt = float(release), float(standstill), float(match), float(dt)
        self.follow = None if follow is None else float(follow)
        self.follow_above = float(follow_above)
        if guard is not None and not (len(guard) == 3 and float(guard[0]) >= 0 and float(guard[1]) > 0):
            raise ValueError(f"DriveOffCap: guard={guard!r} is invalid; allowed: None or (stop_gap >= 0, brake > 0, "
                             "leader_brake > 0)")
        self.guard = None if guard is None else (float(guard[0]), float(guard[1]), guard[2])
        self.hold = bool(hold)
        self.action_key = action_key

    def cap(self, gap: torch.Tensor, speed: torch.Tensor,
            leader_speed: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(cap, lift)``: the cap (m/s^2) where it holds in full, and how far it is lifted (0: not at all, 1: gone)."""
        overspeed = self.overspeed
        if self.hold:  # none of the allowance while the leader stands: the CAV does not creep toward it
            overspeed = overspeed * (leader_speed / self.standstill).clamp(0.0, 1.0)
        cap = self.gain * (leader_speed + overspeed - speed)
        deficit = (leader_speed - speed).clamp_min(0.0)
        projected = gap + deficit * deficit / (2.0 * self.accel)
        lift = ((projected - self.gaps[0]) / (self.gaps[1] - self.gaps[0])).clamp(0.0, 1.0)
        return cap, lift

    def apply(self, a: torch.Tensor, gap: torch.Tensor, speed: torch.Tensor, leader_speed: torch.Tensor,
              engaged: torch.Tensor, calm: torch.Tensor,
              leader_accel: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """One step of the rule on tensors of one shape: ``(executed, engaged, calm)`` after the command ``a``
        and the state ``(engaged, calm)`` before it (what the transform does to a tensordict; a replayed law
        calls it directly, :class:`mixed_traffic.evaluation.replay.DriveOffLaw`); ``leader_accel``: needed
        with ``follow``."""
        engaged = engaged | ((speed < self.standstill) & (leader_speed < self.standstill))  # both stopped
        cap, lift = self.cap(gap, speed, leader_speed)
        capped = torch.minimum(a, cap)
        executed = torch.where(engaged, capped + lift * (a - capped), a)
        calm = torch.where(engaged & (speed >= leader_speed - self.match) & (a <= cap), calm + self.dt,
                           torch.zeros_like(a))
        released = calm >= self.release - 1e-9
        if self.follow is not None:
            if leader_accel is None:
                raise ValueError("DriveOffCap: follow needs the leader's acceleration (leader_accel)")
            floor = torch.minimum(self.follow * leader_accel, cap)
            if self.guard is not None:
                stop_gap, brake, leader_brake = self.guard
                floor = torch.minimum(floor, safe_accel_upper(gap, speed, leader_speed, s_min=stop_gap, dt=self.dt,
                                                              brake=brake, leader_brake=leader_brake))
            executed = torch.where(engaged & ~released & (leader_accel > self.follow_above),
                                   torch.maximum(executed, floor), executed)
        return executed, engaged & ~released, torch.where(released, torch.zeros_like(calm), calm)

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        got = entries_or_none(self, tensordict, self.action_key)
        if got is None:
            return tensordict
        (a,) = got
        engaged, calm = state_entries("DriveOffCap", tensordict, "drive-off", ENGAGED, CALM)
        gap, v, v_l = (tensordict.get(k).to(a.dtype).reshape(a.shape) for k in (GAP, SPEED, LEADER_SPEED))
        a_l = None
        if self.follow is not None:
            a_l = tensordict.get(LEADER_ACCEL, None)
            if a_l is None:
                raise RuntimeError("DriveOffCap: follow reads the leader's acceleration ('cav', 'leader_accel'), "
                                   "which the step's input lacks; allowed: an env that writes it (the ring's does)")
            a_l = a_l.to(a.dtype).reshape(a.shape)
        executed, engaged_next, calm_next = self.apply(a, gap, v, v_l, engaged.reshape(a.shape),
                                                       calm.to(a.dtype).reshape(a.shape), a_l)
        tensordict.set(self.action_key, executed)
        tensordict.set(ENGAGED, engaged_next.reshape(engaged.shape))
        tensordict.set(CALM, calm_next.to(calm.dtype).reshape(calm.shape))
        return tensordict

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        return carry_to_next(tensordict, next_tensordict, ENGAGED, CALM)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        v = tensordict_reset.get(SPEED)
        return reset_state(tensordict, tensordict_reset,
                           {ENGAGED: torch.zeros_like(v, dtype=torch.bool), CALM: torch.zeros_like(v)})

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        return next_tensordict  # everything happens in _inv_call / _step / _reset

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise RuntimeError("DriveOffCap caps a live env's action; use it inside an env")

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        return with_state_spec(observation_spec, "drive_off", SPEED, engaged=torch.bool, calm=None)

    def __repr__(self) -> str:
        follow = "" if self.follow is None else f", follow={self.follow} above {self.follow_above}"
        hold = ", hold" if self.hold else ""
        return (f"{type(self).__name__}(gain={self.gain}, overspeed={self.overspeed}, gaps={self.gaps}, "
                f"accel={self.accel}, release={self.release}, standstill={self.standstill}{follow}{hold})")
