"""Residual action around a base controller: ``a = clip(a_base + w a_res, low, high)``.

TorchRL has no transform that runs a second controller inside the env step and adds
its output to the policy's, hence :class:`ResidualAction`.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.data import Composite
from torchrl.envs.transforms import Transform

from transforms.specs import (
    action_shaped_full,
    carry_to_next,
    entries_or_none,
    kept_rows,
    with_action_shaped_entry,
    with_bounded_action,
)


class ResidualAction(Transform):
    """Executes ``clip(a_base + weight * a_res, low, high)``; the policy outputs ``a_res``.

    The base controller is any ``TensorDictModule`` (MPC, NNMPC, IDM, ...) that reads the
    current observation entries and writes its action (``base_out_key``, default its
    first out key). It runs on a copy, so it cannot overwrite the policy's entries.
    The rollout keeps the policy's residual under ``action`` (right for PPO log-probs)
    and records the base action in ``("next", base_action_key)``.

    Args:
        base: the base controller.
        weight: residual weight ``w`` (>= 0, default 1.0).
        action_key: the action entry (default ``"action"``).
        base_out_key: the key the base writes (default ``base.out_keys[0]``).
        base_action_key: where the base action is logged (default ``("residual", "base_action")``).
        low, high: the clip range; default the parent's action bounds.
        policy_bounds: ``(low, high)`` of the residual the policy outputs; the action spec
            seen by the policy becomes ``Bounded(low, high)`` (e.g. ``(-1, 1)``: a policy whose
            distribution is centred on 0 then starts as the base controller, and
            ``weight`` is the largest correction in m/s^2). Default: the parent's bounds.
        engage_seconds: the residual's weight rises linearly from 0 at the episode's start (time 0
            of ``time_key``) to ``weight`` at ``engage_seconds`` (>= 0; 0, the default: at once). A
            bumpless engagement: the base drives alone at first, so taking over a car whose own
            last acceleration is unknown starts from the base's command, not from the policy's.
        time_key: the episode time (s) read with ``engage_seconds`` (default ``("traffic", "time")``).
        fade_speeds: ``(v_full, v_zero)`` (m/s, ``0 <= v_full < v_zero``): the residual's weight falls
            linearly from full at the car's own speed ``v_full`` to 0 at ``v_zero`` (default None: no fade).
            Set ``v_full`` to the top of the speeds the policy trained on: beyond them the base drives,
            instead of a policy extrapolating outside its training distribution.
        speed_key: the car's own speed (m/s) read with ``fade_speeds`` (default ``("cav", "speed")``).
        room_key: an entry the base writes beside its action: how far (m/s^2, >= 0) its command lies below
            a bound of its own (e.g. the stopping envelope of
            :func:`~mixed_traffic.controllers.classic.stopping_envelope_policy`). A residual that
            accelerates is then scaled by ``clamp(room / r_max, 0, 1)``, ``r_max = weight * max|policy
            bound|`` its largest value, so it fades out as the base nears the bound and the sum never
            exceeds it; a braking residual is left as it is (default None: no such fade).
        slack_key, fade_slack: with ``room_key``, a second entry the base writes, a margin in metres (e.g.
            :meth:`~mixed_traffic.controllers.classic.StoppingEnvelope.slack`), and the margin (m, > 0)
            below which an accelerating residual also fades linearly, ``clamp(slack / fade_slack, 0, 1)``:
            a fade that starts before the bound is reached, where the room alone falls from full to 0
            within centimetres (default None: the room alone).
        slack_below, slack_brake: with ``fade_slack``, the margin fade acts only where the leader is slower than
            ``slack_below`` (m/s, > 0) or brakes harder than ``slack_brake`` (m/s^2, > 0): where a stop is under
            way, and not while the car follows a leader that slows gently at speed (default None for both:
            everywhere).
        leader_speed_key, leader_accel_key: what ``slack_below`` and ``slack_brake`` read (default
            ``("cav", "leader_speed")``, ``("cav", "leader_accel")``).
        play: half-width (m/s^2, > 0) of a backlash on the residual's term (after ``engage_seconds`` and
            ``fade_speeds``): the term executed stays where it was on the last step until the policy's moves more
            than ``play`` away from it, and then follows it at that distance (default None: no backlash). It
            drops the policy's small reversals, which cost jerk, and keeps its level and its large moves. Its
            state travels in the tensordict (``held_key``), reset to 0.
        play_key: a boolean entry (e.g. :class:`transforms.DriveOffCap`'s ``("drive_off", "engaged")``); the
            backlash acts only where it is true, and elsewhere the term passes as the policy gives it (default
            None: everywhere).
        held_key: where the backlash keeps the term it executed (default ``("residual", "held")``).
        play_release: with ``play_key``, the backlash does not end at once where the key turns false: its
            half-width shrinks linearly from ``play`` to 0 over these seconds (> 0), so the term executed reaches
            the policy's over that time instead of within one step (default None: at once). Its state, the share
            of ``play`` still held, travels in the tensordict (``share_key``).
        share_key: where that share is kept (default ``("residual", "play_share")``).
        dt: the env's step (s, > 0), read with ``play_release``.

    Example:
        >>> from mixed_traffic import make_env
        >>> from mixed_traffic.controllers.classic import make_classic_policy
        >>> from torchrl.envs import TransformedEnv
        >>> from transforms import ResidualAction
        >>> base_env = make_env("ring", batch_size=2, seed=0)
        >>> env = TransformedEnv(base_env, ResidualAction(make_classic_policy("idm", base_env), weight=0.5))
        >>> td = env.rollout(5, lambda td: td.set("action", torch.zeros(2, 1)))
        >>> td["next", "residual", "base_action"].shape
        torch.Size([2, 5, 1])
    """

    def __init__(self, base: TensorDictModuleBase, weight: float = 1.0, *, action_key: NestedKey = "action",
                 base_out_key: NestedKey | None = None,
                 base_action_key: NestedKey = ("residual", "base_action"),
                 low: float | None = None, high: float | None = None,
                 policy_bounds: tuple[float, float] | None = None, engage_seconds: float = 0.0,
                 time_key: NestedKey = ("traffic", "time"), fade_speeds: tuple[float, float] | None = None,
                 speed_key: NestedKey = ("cav", "speed"), room_key: NestedKey | None = None,
                 slack_key: NestedKey | None = None, fade_slack: float | None = None,
                 slack_below: float | None = None, slack_brake: float | None = None,
                 leader_speed_key: NestedKey = ("cav", "leader_speed"),
                 leader_accel_key: NestedKey = ("cav", "leader_accel"), play: float | None = None,
                 play_key: NestedKey | None = None, held_key: NestedKey = ("residual", "held"),
                 play_release: float | None = None, share_key: NestedKey = ("residual", "play_share"),
                 dt: float = 0.1):
        if not weight >= 0:
            raise ValueError(f"ResidualAction: weight={weight!r} is invalid; allowed: >= 0")
        if not engage_seconds >= 0:
            raise ValueError(f"ResidualAction: engage_seconds={engage_seconds!r} is invalid; allowed: >= 0 (s)")
        if fade_speeds is not None and not (len(fade_speeds) == 2 and 0 <= fade_speeds[0] < fade_speeds[1]):
            raise ValueError(f"ResidualAction: fade_speeds={fade_speeds!r} is invalid; allowed: (v_full, v_zero) "
                             "with 0 <= v_full < v_zero (m/s), or None")
        if low is not None and high is not None and not low < high:
            raise ValueError(f"ResidualAction: low={low!r}, high={high!r} are invalid; allowed: low < high")
        if policy_bounds is not None and not (len(policy_bounds) == 2 and policy_bounds[0] < policy_bounds[1]):
            raise ValueError(f"ResidualAction: policy_bounds={policy_bounds!r} is invalid; allowed: (low, high) "
                             "with low < high, or None")
        if (slack_key is None) != (fade_slack is None) or (slack_key is not None and room_key is None):
            raise ValueError("ResidualAction: slack_key and fade_slack go together, and with a room_key")
        if fade_slack is not None and not fade_slack > 0:
            raise ValueError(f"ResidualAction: fade_slack={fade_slack!r} is invalid; allowed: > 0 (m)")
        for name, value in (("slack_below", slack_below), ("slack_brake", slack_brake)):
            if value is not None and not (fade_slack is not None and value > 0):
                raise ValueError(f"ResidualAction: {name}={value!r} is invalid; allowed: > 0 with a fade_slack, "
                                 "or None")
        if play is not None and not play > 0:
            raise ValueError(f"ResidualAction: play={play!r} is invalid; allowed: > 0 (m/s^2), or None")
        if play_key is not None and play is None:
            raise ValueError("ResidualAction: play_key without play; give play (m/s^2) or drop play_key")
        if play_release is not None and not (play_key is not None and play_release > 0):
            raise ValueError(f"ResidualAction: play_release={play_release!r} is invalid; allowed: > 0 (s) with a "
                             "play_key, or None")
        if not dt > 0:
            raise ValueError(f"ResidualAction: dt={dt!r} is invalid; allowed: > 0 (s)")
        super().__init__(in_keys=[], out_keys=[base_action_key], in_keys_inv=[action_key], out_keys_inv=[action_key])
        self.play, self.play_key, self.held_key = None if play is None else float(play), play_key, held_key
        self.play_release = None if play_release is None else float(play_release)
        self.share_key, self.dt = share_key, float(dt)
        self.policy_bounds = None if policy_bounds is None else (float(policy_bounds[0]), float(policy_bounds[1]))
        self.base = base
        self.weight = float(weight)
        self.engage_seconds, self.time_key = float(engage_seconds), time_key
        self.fade_speeds = None if fade_speeds is None else (float(fade_speeds[0]), float(fade_speeds[1]))
        self.speed_key, self.room_key = speed_key, room_key
        self.slack_key, self.fade_slack = slack_key, None if fade_slack is None else float(fade_slack)
        self.slack_below = None if slack_below is None else float(slack_below)
        self.slack_brake = None if slack_brake is None else float(slack_brake)
        self.leader_speed_key, self.leader_accel_key = leader_speed_key, leader_accel_key
        self.action_key = action_key
        if base_out_key is None:
            out_keys = getattr(base, "out_keys", None)
            if not out_keys:
                raise ValueError("ResidualAction: base_out_key=None but the base controller has no out_keys; "
                                 "pass base_out_key")
            base_out_key = out_keys[0]
        self.base_out_key = base_out_key
        self.base_action_key = base_action_key
        self._low, self._high = low, high

    def _bounds(self, like: torch.Tensor):
        spec = self.parent.full_action_spec[self.action_key] if (self._low is None or self._high is None) else None
        low = self._low if self._low is not None else spec.space.low
        high = self._high if self._high is not None else spec.space.high
        return torch.as_tensor(low).to(like), torch.as_tensor(high).to(like)

    def base_action(self, tensordict: TensorDictBase) -> torch.Tensor:
        return self._run_base(tensordict).get(self.base_out_key)

    def _run_base(self, tensordict: TensorDictBase) -> TensorDictBase:
        # no torch.no_grad here: a differentiable base (e.g. the NNMPC) passes the gradient
        # through to the state it reads (analytic policy gradients); a frozen one adds no parameters.
        # Its inputs only, in a tensordict of their own: its outputs stay out of the step's, and the rest of the step
        # (observation, traffic state, transforms' entries) is not copied for it every step
        return self.base(tensordict.select(*self.base.in_keys, strict=False))

    def _residual_max(self, like: torch.Tensor) -> torch.Tensor:
        if self.policy_bounds is not None:
            low, high = (torch.as_tensor(b).to(like) for b in self.policy_bounds)
        else:
            low, high = self._bounds(like)
        return self.weight * torch.maximum(low.abs(), high.abs())

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        got = entries_or_none(self, tensordict, self.action_key)
        if got is None:
            return tensordict
        (a_res,) = got
        base_out = self._run_base(tensordict)
        a_base = base_out.get(self.base_out_key).to(a_res.dtype).reshape(a_res.shape)
        low, high = self._bounds(a_res)
        weight = self.weight
        if self.engage_seconds > 0:
            t = tensordict.get(self.time_key).to(a_res.dtype).reshape(*a_res.shape[:-1], -1)[..., :1]
            weight = weight * (t / self.engage_seconds).clamp(0.0, 1.0)
        if self.fade_speeds is not None:
            v_full, v_zero = self.fade_speeds
            v = tensordict.get(self.speed_key).to(a_res.dtype).reshape(a_res.shape)
            weight = weight * ((v_zero - v) / (v_zero - v_full)).clamp(0.0, 1.0)
        residual = weight * a_res
        if self.play is not None:
            residual = self._backlash(tensordict, residual)
        if self.room_key is not None:
            room = base_out.get(self.room_key).to(a_res.dtype).reshape(a_res.shape).clamp_min(0.0)
            fade = (room / self._residual_max(a_res).clamp_min(1e-9)).clamp(max=1.0)
            if self.slack_key is not None:
                slack = base_out.get(self.slack_key).to(a_res.dtype).reshape(a_res.shape)
                gate = self._slack_gate(tensordict, a_res)
                by_slack = (slack / self.fade_slack).clamp(0.0, 1.0)
                fade = torch.minimum(fade, by_slack if gate is None else torch.where(gate, by_slack, fade))
            residual = torch.where(residual > 0, torch.minimum(residual * fade, room), residual)  # the min: an
            # action outside the policy's bounds
        executed = torch.minimum(torch.maximum(a_base + residual, low), high)
        tensordict.set(self.action_key, executed)
        tensordict.set(self.base_action_key, a_base)
        return tensordict

    def _slack_gate(self, tensordict: TensorDictBase, like: torch.Tensor) -> torch.Tensor | None:
        """Where the margin fade acts (``slack_below`` / ``slack_brake``); None: everywhere."""
        gate = None
        for value, key, sign in ((self.slack_below, self.leader_speed_key, 1.0),
                                 (self.slack_brake, self.leader_accel_key, -1.0)):
            if value is None:
                continue
            x = tensordict.get(key, None)
            if x is None:
                raise RuntimeError(f"ResidualAction: the margin fade's gate reads {key!r}, which the step's input "
                                   "lacks; allowed: an env that writes it (the ring's does)")
            hit = x.to(like.dtype).reshape(like.shape) < sign * value  # slower than slack_below, or braking harder
            gate = hit if gate is None else gate | hit
        return gate

    def _backlash(self, tensordict: TensorDictBase, residual: torch.Tensor) -> torch.Tensor:
        """The residual's term through the backlash (``play``), its state updated in ``tensordict``."""
        held = tensordict.get(self.held_key, None)
        if held is None:
            raise RuntimeError("ResidualAction: the step's input has no held residual (play); reset the env through "
                               "the TransformedEnv before stepping it")
        held = held.to(residual.dtype).reshape(residual.shape)
        played = torch.minimum(torch.maximum(held, residual - self.play), residual + self.play)
        if self.play_key is not None:
            on = tensordict.get(self.play_key, None)
            if on is None:
                raise RuntimeError(f"ResidualAction: play_key {self.play_key!r} is not in the step's input; put the "
                                   "transform that writes it (e.g. DriveOffCap) in the chain")
            on = on.reshape(residual.shape)
            if self.play_release is None:
                played = torch.where(on, played, residual)
            else:  # after the key turns false the half-width shrinks to 0 over play_release seconds
                share = tensordict.get(self.share_key, None)
                if share is None:
                    raise RuntimeError("ResidualAction: the step's input has no play share (play_release); reset the "
                                       "env through the TransformedEnv before stepping it")
                share = torch.where(on, torch.ones_like(residual),
                                    (share.to(residual.dtype).reshape(residual.shape)
                                     - self.dt / self.play_release).clamp_min(0.0))
                width = self.play * share
                played = torch.where(on, played, torch.minimum(torch.maximum(held, residual - width), residual + width))
                tensordict.set(self.share_key, share)
        tensordict.set(self.held_key, played.detach())
        return played

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        return carry_to_next(tensordict, next_tensordict, self.base_action_key, *self._state_keys())

    def _state_keys(self) -> tuple:
        """The backlash's state: its held term, and with ``play_release`` the share of ``play`` still held."""
        if self.play is None:
            return ()
        return (self.held_key,) if self.play_release is None else (self.held_key, self.share_key)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        tensordict_reset.set(self.base_action_key, action_shaped_full(self.parent, self.action_key, 0.0))
        for key in self._state_keys():  # the backlash's held term and share, 0 at a reset
            state = action_shaped_full(self.parent, self.action_key, 0.0)
            keep = kept_rows(tensordict, state, key)
            if keep is not None:  # rows not reset keep their state
                state = torch.where(keep, tensordict.get(key).to(state), state)
            tensordict_reset.set(key, state)
        return tensordict_reset

    def transform_action_spec(self, action_spec):
        if self.policy_bounds is None:
            return action_spec
        return with_bounded_action(action_spec, self.action_key, *self.policy_bounds)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        observation_spec = with_action_shaped_entry(observation_spec, self.parent, self.action_key, self.base_action_key)
        for key in self._state_keys():
            observation_spec = with_action_shaped_entry(observation_spec, self.parent, self.action_key, key)
        return observation_spec

    def __repr__(self) -> str:
        engage = f", engage_seconds={self.engage_seconds}" if self.engage_seconds else ""
        fade = f", fade_speeds={self.fade_speeds}" if self.fade_speeds else ""
        room = f", room_key={self.room_key}" if self.room_key is not None else ""
        room += f", fade_slack={self.fade_slack}" if self.fade_slack is not None else ""
        room += f", slack_below={self.slack_below}" if self.slack_below is not None else ""
        room += f", slack_brake={self.slack_brake}" if self.slack_brake is not None else ""
        room += f", play={self.play}" + (f" while {self.play_key}" if self.play_key is not None else "") if self.play else ""
        room += f", play_release={self.play_release}" if self.play_release is not None else ""
        return f"{type(self).__name__}(weight={self.weight}{engage}{fade}{room}, base={type(self.base).__name__})"
