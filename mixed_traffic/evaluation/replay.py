"""A ring CAV's law replayed behind recorded head traces: its own metrics without running the ring.

On the ring the CAV's leader is the head, which tracks the profile's speed: what the CAV does reaches it
only through the humans behind the CAV, who are the head's own leaders around the ring, and only where
the head comes close to them (after a stop of the head, or on a short ring). So one rollout records the
head's speeds (:class:`~mixed_traffic.evaluation.harness.Trace`),
and any follower law ``law(gap, speed, leader_speed) -> accel`` (CACC also reads the head's last
acceleration) can then be re-driven behind them with
the env's own actuator bounds and integration rule (:func:`mixed_traffic.physics.integrate`). The
CAV-side metrics (gaps, steady speed RMSE, jerk) come out as the env computes them
(:func:`~mixed_traffic.evaluation.harness.episode_metrics`), at a fraction of a rollout's cost and for a
batch of laws at once; the return (which sums the humans' speeds) cannot be replayed.

Replaying the recording CAV's own law gives the env's metrics to float precision; another law, within
what its different humans change of the head's speeds (measured: on random steps at 20-28 m/s 0.02 m/s of
head speed, 0.03 m of gap, 0.1 % of jerk; on ``brake_from_25`` 0.06 m/s and 0.1 m of the largest gap;
``tests/test_replay.py``). Good for searching a
residual's classical base before anything is trained (``benchmarks/ring_base_replay.py``), with the
chosen settings then run in the env. TorchRL has no trace replay of a car-following law.

    >>> from mixed_traffic.config import compose
    >>> from mixed_traffic.controllers.classic import make_classic_policy
    >>> from mixed_traffic import make_env
    >>> cfg = compose(["eval.episodes=2", "eval.episode_seconds=30", "eval.profiles=[sine]"])
    >>> traces = record_head_traces(cfg, seed=5)
    >>> idm = make_classic_policy("idm", make_env("ring", batch_size=1, seed=0)).module
    >>> m = replay(idm, traces["sine"], **replay_settings(cfg, "sine"))
    >>> bool(m["collision"].any()), m["gap"].shape
    (False, torch.Size([2, 300]))
"""

from __future__ import annotations

import dataclasses

import torch
from omegaconf import DictConfig, open_dict

from mixed_traffic.controllers.classic import reads_leader_accel
from mixed_traffic.evaluation.harness import Trace, follower_metrics
from mixed_traffic.physics import integrate


def _recorder(env):
    """IDM inside a 2-m stopping envelope: it never ends an episode early by hitting the head."""
    from mixed_traffic.controllers.classic import make_classic_policy, stopping_envelope_policy

    return stopping_envelope_policy(make_classic_policy("idm", env), env, stop_gap=2.0)


def record_head_traces(cfg: DictConfig, *, seed: int | None = None, policy_factory=None) -> dict[str, Trace]:
    """``{profile: Trace}`` of ``cfg``'s evaluation profiles (``eval.profiles``, ``eval.episodes``, evaluation
    seed ``seed`` or ``eval.seed``) with no layer. Only the head's speeds and the start state matter to
    :func:`replay`, and (but for the humans' reach, see the module docstring) neither depends on the CAV's
    law. The recording CAV is ``policy_factory(env)``, by default IDM inside a 2-m stopping envelope, so that
    no episode ends at a collision before the profile's end."""
    from mixed_traffic.evaluation.harness import evaluate

    cfg = cfg.copy()
    with open_dict(cfg):
        cfg.transforms.chain, cfg.eval.without_layer = ["non_negative_reward"], False
        if seed is not None:
            cfg.eval.seed = seed
    traces = evaluate(cfg, policy_factory=policy_factory or _recorder)[1]
    for profile, tr in traces.items():
        if not bool(tr.valid.all()):
            raise ValueError(f"{profile}: an episode ended before the profile's end (a collision of the recording "
                             "CAV); the head's speeds after it are unknown, so nothing can be replayed past it")
    return traces


def stack_traces(traces: list[Trace]) -> tuple[Trace, list[slice]]:
    """One :class:`Trace` of all rows of ``traces`` (shorter ones padded at the end with invalid steps) and
    each input's rows in it, so that traces of several profiles replay in one pass."""
    T = max(tr.valid.shape[1] for tr in traces)

    def pad(x: torch.Tensor, name: str) -> torch.Tensor:
        n = T - x.shape[1]
        if n == 0:
            return x
        if name == "valid":
            return torch.cat([x, torch.zeros(x.shape[0], n, dtype=x.dtype)], 1)
        return torch.cat([x, x[:, -1:].expand(-1, n)], 1)  # held: a padded step changes nothing it counts

    names = [f.name for f in dataclasses.fields(Trace)]
    out = Trace(**{f: torch.cat([pad(getattr(tr, f), f) for tr in traces], 0) for f in names})
    ends = torch.tensor([tr.valid.shape[0] for tr in traces]).cumsum(0).tolist()
    return out, [slice(e - tr.valid.shape[0], e) for e, tr in zip(ends, traces)]


def replay_settings(cfg: DictConfig, profile: str) -> dict:
    """The keyword arguments of :func:`replay` for ``profile`` under ``cfg``: the evaluated scenario's step,
    integration rule and the CAV's action bounds, and the evaluation's warm-up and settling times."""
    from mixed_traffic.evaluation.harness import eval_scenario

    sc = eval_scenario(cfg, profile)
    lo, hi = sc.cav_accel_bounds
    return {"dt": sc.dt, "low": lo, "high": hi, "integration": sc.integration,
            "warmup": cfg.eval.warmup_seconds, "settle": cfg.eval.settle_seconds}


def _advance(v: torch.Tensor, a: torch.Tensor, dt: float,
             method: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(distance, v', executed a)`` of one step of :func:`mixed_traffic.physics.integrate` from position 0."""
    return integrate(torch.zeros_like(v), v, a, dt, method)


class DriveOffLaw(torch.nn.Module):
    """``law`` followed by a :class:`transforms.DriveOffCap`, as the deployed chain applies it, replayable: the
    cap's state (engaged, calm) lives in the module and :func:`replay` clears it at the start of each replay.

        >>> from mixed_traffic import make_env
        >>> from mixed_traffic.controllers.classic import make_classic_policy
        >>> from transforms import DriveOffCap
        >>> law = DriveOffLaw(make_classic_policy("idm", make_env("ring", batch_size=1, seed=0)).module, DriveOffCap())
        >>> law.reset_state(); law(torch.tensor([8.0]), torch.tensor([0.2]), torch.tensor([0.3]))  # both stopped: capped
        tensor([0.2500])
    """

    def __init__(self, law, cap):
        super().__init__()
        self.law, self.cap = law, cap
        self.reset_state()

    @property
    def reads_leader_accel(self) -> bool:
        return reads_leader_accel(self.law) or self.cap.follow is not None

    def reset_state(self) -> None:
        self._engaged = self._calm = None

    def forward(self, gap: torch.Tensor, speed: torch.Tensor, leader_speed: torch.Tensor, *extra) -> torch.Tensor:
        a = self.law(gap, speed, leader_speed, *(extra if reads_leader_accel(self.law) else ()))
        if self._engaged is None or self._engaged.shape != a.shape:
            self._engaged, self._calm = torch.zeros_like(a, dtype=torch.bool), torch.zeros_like(a)
        leader_accel = extra[0].to(a) if self.cap.follow is not None else None
        executed, self._engaged, self._calm = self.cap.apply(a, gap.to(a), speed.to(a), leader_speed.to(a),
                                                             self._engaged, self._calm, leader_accel)
        return executed


class AnswerLaw(torch.nn.Module):
    """``law`` followed by a :class:`transforms.CommittedAnswer`, as the deployed chain applies it, replayable: the
    answer's state (time to go, sign) lives in the module and :func:`replay` clears it at the start of each replay.
    Put a :class:`DriveOffLaw` around it for a chain that also caps the drive-off (the cap acts last).

        >>> from mixed_traffic import make_env
        >>> from mixed_traffic.controllers.classic import make_classic_policy
        >>> from transforms import CommittedAnswer
        >>> law = AnswerLaw(make_classic_policy("idm", make_env("ring", batch_size=1, seed=0)).module,
        ...                 CommittedAnswer(speeds=(0.0, 1.0)))
        >>> law.reset_state(); law(torch.tensor([20.0]), torch.tensor([20.0]), torch.tensor([21.0]))  # 1 m/s over 6 s
        tensor([0.1667])
    """

    def __init__(self, law, answer):
        super().__init__()
        self.law, self.answer = law, answer
        self.reset_state()

    @property
    def reads_leader_accel(self) -> bool:
        return reads_leader_accel(self.law) or self.answer.reads_leader_accel

    def reset_state(self) -> None:
        self._tau = self._sign = None
        if hasattr(self.law, "reset_state"):
            self.law.reset_state()

    def forward(self, gap: torch.Tensor, speed: torch.Tensor, leader_speed: torch.Tensor, *extra) -> torch.Tensor:
        a = self.law(gap, speed, leader_speed, *(extra if reads_leader_accel(self.law) else ()))
        if self._tau is None or self._tau.shape != a.shape:
            self._tau, self._sign = torch.zeros_like(a), torch.zeros_like(a)
        leader_accel = extra[0].to(a) if self.answer.reads_leader_accel else None
        executed, self._tau, self._sign = self.answer.apply(a, gap.to(a), speed.to(a), leader_speed.to(a), self._tau,
                                                            self._sign, leader_accel)
        return executed


def replay(law, trace: Trace, *, dt: float, low: float, high: float, warmup: float, settle: float,
           integration: str = "euler") -> dict[str, torch.Tensor]:
    """The CAV driven by ``law`` behind ``trace``'s head, from the recorded start state.

    ``law(gap, speed, leader_speed)`` maps ``[episodes]`` tensors (float64) to commands (a law with memory, such
    as :class:`DriveOffLaw`, has ``reset_state()`` called first), clipped to
    ``[low, high]`` as the env clips an action (a module in float32 can be replayed as it is, or after
    ``.double()``). A law whose ``reads_leader_accel`` is true (CACC) is called as
    ``law(gap, speed, leader_speed, leader_accel)`` with the head's acceleration of the last step, as the
    env's ``("cav", "leader_accel")`` gives it (0 before the first step). ``trace`` may hold several
    profiles' rows (:func:`stack_traces`).
    Returns per-row metrics named as :func:`~mixed_traffic.evaluation.harness.episode_metrics` names them:
    ``collision``, ``min_gap``, ``min_gap_after``, ``max_head_gap``, ``speed_rmse_steady``, ``mean_abs_jerk``,
    and the series ``gap``, ``accel``, ``speed``.
    """
    f64 = torch.float64
    vh, valid, t = trace.head_speed.to(f64), trace.valid, trace.time.to(f64)
    a_head, a0 = trace.head_accel.to(f64), trace.cav_accel.to(f64)[:, 0]
    v0_after, gap0_after = trace.cav_speed.to(f64)[:, 0], trace.gap.to(f64)[:, 0]
    # the state before the first recorded step: undo that step (speeds at a standstill stay put)
    v = torch.where(v0_after > 0, v0_after - a0 * dt, v0_after)
    vh_prev = torch.where(vh[:, 0] > 0, vh[:, 0] - a_head[:, 0] * dt, vh[:, 0])
    # the head's speed at the start of each step and its distance over it: the recording, whatever the law
    v_head = torch.cat([vh_prev[:, None], vh[:, :-1]], 1)
    x_head, _, _ = _advance(v_head, (vh - v_head) / dt, dt, integration)
    x_cav, _, _ = _advance(v, (v0_after - v) / dt, dt, integration)
    gap = gap0_after - (x_head[:, 0] - x_cav)
    gaps, accels, speeds = [], [], []
    # the head's acceleration of the last step: what ("cav", "leader_accel") holds when step k is decided
    a_seen = torch.cat([torch.zeros_like(a_head[:, :1]), a_head[:, :-1]], 1)
    reads_accel = reads_leader_accel(law)
    if hasattr(law, "reset_state"):  # a law with memory (DriveOffLaw) starts afresh
        law.reset_state()
    for k in range(vh.shape[1]):
        a = law(gap, v, v_head[:, k], a_seen[:, k]) if reads_accel else law(gap, v, v_head[:, k])
        a = a.to(f64).clamp(low, high)
        x, v, executed = _advance(v, a, dt, integration)
        gap = gap + x_head[:, k] - x
        gaps.append(gap), accels.append(executed), speeds.append(v)
    gap, accel, speed = (torch.stack(s, 1) for s in (gaps, accels, speeds))
    m = follower_metrics(gap=gap, head_gap=gap, speed=speed, head_speed=vh, accel=accel, head_accel=a_head,
                         valid=valid, after=valid & (t >= warmup), dt=dt, settle=settle)
    return {"collision": ((gap <= 0) & valid).any(1).to(f64),
            **{k: m[k] for k in ("min_gap", "min_gap_after", "max_head_gap", "speed_rmse_steady", "mean_abs_jerk")},
            "gap": gap, "accel": accel, "speed": speed}
