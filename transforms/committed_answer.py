"""CommittedAnswer: above a speed, the CAV answers each change of its leader's speed with one held acceleration.

A memoryless follower answers a step of its leader's speed at once and then eases off as the speed difference
closes (``k (v_leader - v)``): its command jumps, then decays, and the gap settles slowly. A controller that only
measures its leader can do better on both counts (``docs/results.md``, "What a controller that only measures the
head can reach"): answer the step with one small acceleration held until the speeds match, letting the gap float
inside its band. :func:`mixed_traffic.physics.committed_answer_accel` is that law; it needs a memory (a time to go,
and the sign of the answer that runs), so it cannot be one of the base's laws, which are functions of the present
gap and speeds. This transform runs it with its state in the tensordict and takes the command over by the CAV's
own speed: none of it below ``speeds[0]``, all of it from ``speeds[1]``, linearly between.

The answer is bounded as the base's band law is: by an IDM term (``idm``, delta 4; the soft law's envelope) and
by the base's stopping envelope (``envelope``, a :class:`mixed_traffic.controllers.classic.StoppingEnvelope` whose
law is the answer; the builder passes the base's), so with it the answer never leaves the stopping-safe set the base
keeps. It stands between the safety layer and
the residual in the chain (``transforms.residual.answer``), so above ``speeds`` it replaces the base plus the
learned residual (which fades out there in the default experiment), and the safety layer still has the last word.
Its state (``("answer", "tau")``, ``("answer", "sign")``) travels in the tensordict, so a row reset on its own
starts afresh. TorchRL has no transform that replaces an action by a rule with memory, hence this one.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import Composite
from torchrl.envs.transforms import Transform

from mixed_traffic.physics import committed_answer_accel, idm_accel
from transforms.specs import carry_to_next, entries_or_none, reset_state, state_entries, with_state_spec

GAP, SPEED, LEADER_SPEED, LEADER_ACCEL = ("cav", "gap"), ("cav", "speed"), ("cav", "leader_speed"), ("cav", "leader_accel")
TAU, SIGN = ("answer", "tau"), ("answer", "sign")


class GivenCommand(nn.Module):
    """A law that returns the command it was last given: the answer, as the law inside a stopping envelope
    (``StoppingEnvelope(GivenCommand(), ...)``), so the envelope's own arrival and stand terms bound it."""

    def __init__(self):
        super().__init__()
        self.command: torch.Tensor | None = None

    def forward(self, gap: torch.Tensor, speed: torch.Tensor, leader_speed: torch.Tensor, *extra) -> torch.Tensor:
        if self.command is None:
            raise RuntimeError("GivenCommand: no command given; set .command before calling it")
        return self.command


class CommittedAnswer(Transform):
    """Above ``speeds``, executes the committed answer (:func:`mixed_traffic.physics.committed_answer_accel`).

    Args:
        horizon: the time to go (s, > 0) an answer starts with: its first command is ``dv / horizon``.
        horizon_min: the least time to go (s, ``0 < horizon_min <= horizon``): the answer's largest gain. Behind a
            step the command holds for ``horizon - horizon_min`` seconds, then eases off with this time constant.
        start: the speed difference (m/s, >= 0) beyond which an answer starts.
        done: the speed difference (m/s, ``0 <= done <= start``) at which it ends.
        gaps: ``(low, high)`` (m, ``0 <= low < high``): the band the gap floats in.
        ks_edge: the gap gain (1/s^2, >= 0) beyond the band's edges.
        speeds: ``(v_off, v_on)`` (m/s, ``0 <= v_off < v_on``): the CAV's speeds over which the answer takes over.
        idm: the IDM term's parameters (``v0``, ``T``, ``a``, ``b``, ``s0``; delta 4) that bound the answer, or
            None: no such bound.
        envelope: a module that bounds the answer, holding one :class:`GivenCommand` as the law it bounds: a
            ``StoppingEnvelope`` over it (the base's, as :func:`mixed_traffic.training.builders.committed_answer`
            builds it, with the base's ``CatchUp`` between them when ``catch_up`` is set), or None: no bound.
        dt: the env's step (s, > 0).
        action_key: the executed acceleration (default ``"action"``).

    Example:
        >>> import torch
        >>> from torchrl.envs import TransformedEnv
        >>> from mixed_traffic import make_env
        >>> from transforms import CommittedAnswer
        >>> base = make_env("ring", batch_size=1, seed=0, init_spacing_range=[20.0, 20.0])
        >>> env = TransformedEnv(base, CommittedAnswer(speeds=(0.0, 1.0)))
        >>> td = env.rollout(100, lambda td: td.set("action", torch.zeros(1, 1)))
        >>> td["next", "answer", "tau"].shape, bool(td["next", "collision"].any())
        (torch.Size([1, 100, 1]), False)
    """

    def __init__(self, horizon: float = 6.0, horizon_min: float = 3.0, start: float = 0.3, done: float = 0.05,
                 gaps: tuple[float, float] = (6.1, 35.0), ks_edge: float = 0.077,
                 speeds: tuple[float, float] = (18.0, 20.0), *, idm: dict | None = None,
                 envelope: nn.Module | None = None, dt: float = 0.1, action_key: NestedKey = "action"):
        for name, value in (("horizon", horizon), ("horizon_min", horizon_min), ("dt", dt)):
            if not float(value) > 0.0:
                raise ValueError(f"CommittedAnswer: {name}={value!r} is invalid; allowed: > 0 (s)")
        if not float(horizon_min) <= float(horizon):
            raise ValueError(f"CommittedAnswer: horizon_min={horizon_min!r} is invalid; allowed: <= horizon ({horizon})")
        if not 0.0 <= float(done) <= float(start):
            raise ValueError(f"CommittedAnswer: start={start!r}, done={done!r} are invalid; allowed: "
                             "0 <= done <= start (m/s)")
        if not float(ks_edge) >= 0.0:
            raise ValueError(f"CommittedAnswer: ks_edge={ks_edge!r} is invalid; allowed: >= 0 (1/s^2)")
        for name, pair in (("gaps", gaps), ("speeds", speeds)):
            if not (len(pair) == 2 and 0.0 <= float(pair[0]) < float(pair[1])):
                raise ValueError(f"CommittedAnswer: {name}={list(pair)!r} is invalid; allowed: [low, high] with "
                                 "0 <= low < high")
        given = [] if envelope is None else [m for m in envelope.modules() if isinstance(m, GivenCommand)]
        if envelope is not None and len(given) != 1:
            raise ValueError("CommittedAnswer: envelope must hold exactly one GivenCommand (its law, or the law of a "
                             "law it wraps, such as a CatchUp)")
        super().__init__(in_keys=[], out_keys=[], in_keys_inv=[action_key], out_keys_inv=[action_key])
        self.horizon, self.horizon_min = float(horizon), float(horizon_min)
        self.start, self.done = float(start), float(done)
        self.gaps, self.ks_edge = (float(gaps[0]), float(gaps[1])), float(ks_edge)
        self.speeds = (float(speeds[0]), float(speeds[1]))
        self.idm = None if idm is None else {k: float(v) for k, v in dict(idm).items()}
        self.envelope, self.dt, self.action_key = envelope, float(dt), action_key
        self._given = given[0] if given else None

    @property
    def reads_leader_accel(self) -> bool:
        return self.envelope is not None and bool(getattr(self.envelope, "reads_leader_accel", False))

    def answer(self, gap: torch.Tensor, speed: torch.Tensor, leader_speed: torch.Tensor, tau: torch.Tensor,
               sign: torch.Tensor, leader_accel: torch.Tensor | None = None):
        """``(answer, tau, sign)``: the bounded answer and the state after one step, from the state before it."""
        a, tau, sign = committed_answer_accel(gap, speed, leader_speed, tau, sign, horizon=self.horizon,
                                              horizon_min=self.horizon_min, start=self.start, done=self.done,
                                              gaps=self.gaps, ks_edge=self.ks_edge, dt=self.dt)
        if self.idm is not None:
            a = torch.minimum(a, idm_accel(gap, speed, leader_speed, delta=4.0, **self.idm))
        if self.envelope is not None:
            self._given.command = a
            try:
                a = self.envelope(gap, speed, leader_speed, *(() if leader_accel is None else (leader_accel,)))
            finally:
                self._given.command = None
        return a, tau, sign

    def apply(self, a: torch.Tensor, gap: torch.Tensor, speed: torch.Tensor, leader_speed: torch.Tensor,
              tau: torch.Tensor, sign: torch.Tensor, leader_accel: torch.Tensor | None = None):
        """One step on tensors of one shape: ``(executed, tau, sign)`` after the command ``a`` and the state before
        it (what the transform does to a tensordict; a replayed law calls it directly)."""
        answer, tau, sign = self.answer(gap, speed, leader_speed, tau, sign, leader_accel)
        v_off, v_on = self.speeds
        w = ((speed - v_off) / (v_on - v_off)).clamp(0.0, 1.0)
        return a + w * (answer - a), tau, sign

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        got = entries_or_none(self, tensordict, self.action_key)
        if got is None:
            return tensordict
        (a,) = got
        tau, sign = state_entries("CommittedAnswer", tensordict, "answer", TAU, SIGN)
        gap, v, v_l = (tensordict.get(k).to(a.dtype).reshape(a.shape) for k in (GAP, SPEED, LEADER_SPEED))
        a_l = None
        if self.reads_leader_accel:
            a_l = tensordict.get(LEADER_ACCEL, None)
            if a_l is None:
                raise RuntimeError("CommittedAnswer: the envelope's stand arrival reads the leader's acceleration "
                                   "('cav', 'leader_accel'), which the step's input lacks; allowed: an env that "
                                   "writes it (the ring's does)")
            a_l = a_l.to(a.dtype).reshape(a.shape)
        executed, tau_next, sign_next = self.apply(a, gap, v, v_l, tau.to(a.dtype).reshape(a.shape),
                                                   sign.to(a.dtype).reshape(a.shape), a_l)
        tensordict.set(self.action_key, executed)
        tensordict.set(TAU, tau_next.to(tau.dtype).reshape(tau.shape))
        tensordict.set(SIGN, sign_next.to(sign.dtype).reshape(sign.shape))
        return tensordict

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        return carry_to_next(tensordict, next_tensordict, TAU, SIGN)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        v = tensordict_reset.get(SPEED)
        return reset_state(tensordict, tensordict_reset, {TAU: torch.zeros_like(v), SIGN: torch.zeros_like(v)})

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        return next_tensordict  # everything happens in _inv_call / _step / _reset

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise RuntimeError("CommittedAnswer replaces a live env's action; use it inside an env")

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        return with_state_spec(observation_spec, "answer", SPEED, tau=None, sign=None)

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(horizon={self.horizon}, horizon_min={self.horizon_min}, start={self.start}, "
                f"done={self.done}, gaps={self.gaps}, ks_edge={self.ks_edge}, speeds={self.speeds}, "
                f"idm={self.idm is not None}, envelope={self.envelope is not None})")
