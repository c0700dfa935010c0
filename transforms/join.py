"""JoinBlend: a CAV that starts far behind its leader joins it under a smooth law, then hands over to the policy.

A CAV whose episode starts far behind its leader (the ring's spread start puts 73 m between them) must first
close that gap. Under the policy's command that approach runs through every slot of the base at once (the speed
schedule's handover, the catch-up, the envelope) and costs jerk that has nothing to do with following. This
transform lets a smooth join law (a classical law inside its own stopping envelope) drive while the CAV joins,
and hands over to the policy's command linearly over ``fade`` seconds once the gap first falls to ``gap`` (or,
with ``seconds``, at that episode time at the latest). A CAV that starts at or below ``gap`` is not joining: the
policy drives from the first step.

It stands between the safety layer and the residual in the chain (``transforms.residual.join``), so it blends
the command of the base plus the learned residual, and the safety layer still has the last word. Its state (the
policy's share of the command) travels in the tensordict (``("join", "share")``), so a row reset on its own
starts afresh. TorchRL has no transform that hands an action over between two controllers on a rule with
memory, hence this one.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.data import Composite
from torchrl.envs.transforms import Transform

from transforms.specs import carry_to_next, entries_or_none, kept_rows, state_entries, with_state_spec

GAP, TIME, LEADER_SPEED = ("cav", "gap"), ("traffic", "time"), ("cav", "leader_speed")
SHARE = ("join", "share")


class JoinBlend(Transform):
    """Executes ``share * a + (1 - share) * a_join``: the join law drives until the gap first falls to ``gap``.

    Args:
        law: the join law, any ``TensorDictModule`` that reads the observation entries and writes its action
            (``law_out_key``, default its first out key); it runs on a copy. Keep it inside a stopping envelope
            (:func:`mixed_traffic.controllers.classic.stopping_envelope_policy`).
        gap: the gap (m, > 0) at or below which the CAV has joined: from the first step at or below it the
            policy's share rises from 0 to 1 over ``fade`` seconds, and stays there.
        fade: the handover's length (s, > 0).
        seconds: the handover begins at the latest at this episode time (s, > 0; None: only at ``gap``).
        leader_speeds: ``(v_off, v_on)`` (m/s, ``0 <= v_off < v_on``): while the CAV joins, the join law's part of the
            command grows linearly with the leader's speed from none at ``v_off`` to all of it at ``v_on``, so the
            policy drives a join behind a slow leader (default None: the join law at every speed).
        leader_speed_key: the leader's speed read with ``leader_speeds`` (default ``("cav", "leader_speed")``).
        dt: the env's step (s, > 0).
        action_key: the executed acceleration (default ``"action"``).
        gap_key: the CAV's gap to its leader (default ``("cav", "gap")``).
        time_key: the episode time (s) read with ``seconds`` (default ``("traffic", "time")``).
        law_out_key: the key the law writes (default ``law.out_keys[0]``).

    Example:
        >>> import torch
        >>> from torchrl.envs import Compose, TransformedEnv
        >>> from mixed_traffic import make_env
        >>> from mixed_traffic.controllers.classic import make_classic_policy
        >>> from transforms import JoinBlend, ResidualAction
        >>> base = make_env("ring", batch_size=1, seed=0, init_spacing_range=[73.4, 73.4])
        >>> join = JoinBlend(make_classic_policy("idm", base, s0=7.0, v0=40.0, b=2.0), gap=35.0, fade=10.0,
        ...                  dt=base.scenario.dt)
        >>> env = TransformedEnv(base, Compose(join, ResidualAction(make_classic_policy("idm", base), weight=0.0)))
        >>> td = env.rollout(400, lambda td: td.set("action", torch.zeros(1, 1)))
        >>> share = td["next", "join", "share"][0, :, 0]
        >>> bool(share[0] < 1.0), bool(share[-1] == 1.0)  # the join law drives first, the policy's command last
        (True, True)
    """

    def __init__(self, law: TensorDictModuleBase, gap: float = 35.0, fade: float = 10.0, seconds: float | None = None,
                 *, leader_speeds: tuple[float, float] | None = None, dt: float = 0.1, action_key: NestedKey = "action",
                 gap_key: NestedKey = GAP, time_key: NestedKey = TIME, leader_speed_key: NestedKey = LEADER_SPEED,
                 law_out_key: NestedKey | None = None):
        for name, value in (("gap", gap), ("fade", fade), ("dt", dt)):
            if not float(value) > 0.0:
                raise ValueError(f"JoinBlend: {name}={value!r} is invalid; allowed: > 0")
        if seconds is not None and not float(seconds) > 0.0:
            raise ValueError(f"JoinBlend: seconds={seconds!r} is invalid; allowed: > 0 (s), or None")
        if leader_speeds is not None and not (len(leader_speeds) == 2
                                              and 0.0 <= float(leader_speeds[0]) < float(leader_speeds[1])):
            raise ValueError(f"JoinBlend: leader_speeds={leader_speeds!r} is invalid; allowed: (v_off, v_on) with "
                             "0 <= v_off < v_on (m/s), or None")
        self.leader_speeds = None if leader_speeds is None else (float(leader_speeds[0]), float(leader_speeds[1]))
        self.leader_speed_key = leader_speed_key
        super().__init__(in_keys=[], out_keys=[], in_keys_inv=[action_key], out_keys_inv=[action_key])
        if law_out_key is None:
            out_keys = getattr(law, "out_keys", None)
            if not out_keys:
                raise ValueError("JoinBlend: law_out_key=None but the join law has no out_keys; pass law_out_key")
            law_out_key = out_keys[0]
        self.law, self.law_out_key = law, law_out_key
        self.gap, self.fade, self.dt = float(gap), float(fade), float(dt)
        self.seconds = None if seconds is None else float(seconds)
        self.action_key, self.gap_key, self.time_key = action_key, gap_key, time_key

    def apply(self, a: torch.Tensor, a_join: torch.Tensor, gap: torch.Tensor, share: torch.Tensor,
              time: torch.Tensor | None = None,
              leader_speed: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """One step on tensors of one shape: ``(executed, share)`` after the policy's command ``a``, the join law's
        ``a_join`` and the share before the step (``time``: the episode time, needed with ``seconds``;
        ``leader_speed``: needed with ``leader_speeds``). ``share`` is the policy's share by the join's progress;
        the executed command also gives the policy the part that ``leader_speeds`` takes from the join law."""
        joined = (share > 0.0) | (gap <= self.gap)
        if self.seconds is not None:
            if time is None:
                raise ValueError("JoinBlend: seconds needs the episode time (time)")
            joined = joined | (time >= self.seconds - 1e-9)
        share = share + self.dt / self.fade
        share = torch.where(share >= 1.0 - 1e-6, torch.ones_like(share), share)  # whole after fade / dt steps
        share = torch.where(joined, share, torch.zeros_like(share))
        law = 1.0 - share
        if self.leader_speeds is not None:
            if leader_speed is None:
                raise ValueError("JoinBlend: leader_speeds needs the leader's speed (leader_speed)")
            v_off, v_on = self.leader_speeds
            law = law * ((leader_speed - v_off) / (v_on - v_off)).clamp(0.0, 1.0)
        return a + law * (a_join - a), share

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        got = entries_or_none(self, tensordict, self.action_key)
        if got is None:
            return tensordict
        (a,) = got
        (share,) = state_entries("JoinBlend", tensordict, "join", SHARE)
        share = share.to(a.dtype).reshape(a.shape)
        if bool((share >= 1.0).all()):  # every row has joined: the law need not run
            return tensordict
        a_join = self.law(tensordict.select(*self.law.in_keys, strict=False)).get(self.law_out_key).to(a.dtype).reshape(a.shape)
        gap = tensordict.get(self.gap_key).to(a.dtype).reshape(a.shape)
        time = None
        if self.seconds is not None:
            time = tensordict.get(self.time_key).to(a.dtype).reshape(*a.shape[:-1], -1)[..., :1].expand_as(a)
        v_l = None
        if self.leader_speeds is not None:
            v_l = tensordict.get(self.leader_speed_key).to(a.dtype).reshape(a.shape)
        executed, share_next = self.apply(a, a_join, gap, share, time, v_l)
        tensordict.set(self.action_key, executed)
        tensordict.set(SHARE, share_next)
        return tensordict

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        return carry_to_next(tensordict, next_tensordict, SHARE)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        gap = tensordict_reset.get(self.gap_key)
        share = (gap <= self.gap).to(gap.dtype)  # a CAV that starts close has joined already
        keep = kept_rows(tensordict, share, SHARE)
        if keep is not None:  # rows not reset keep their state
            share = torch.where(keep, tensordict.get(SHARE).to(share), share)
        tensordict_reset.set(SHARE, share)
        return tensordict_reset

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        return next_tensordict  # everything happens in _inv_call / _step / _reset

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise RuntimeError("JoinBlend blends a live env's action; use it inside an env")

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        return with_state_spec(observation_spec, "join", self.gap_key, share=None)

    def __repr__(self) -> str:
        seconds = "" if self.seconds is None else f", seconds={self.seconds}"
        speeds = "" if self.leader_speeds is None else f", leader_speeds={self.leader_speeds}"
        return f"{type(self).__name__}(gap={self.gap}, fade={self.fade}{seconds}{speeds}, law={type(self.law).__name__})"
