"""Analytic policy gradient (APG): back-propagation through a differentiable closed loop.

The torch platoon (:class:`~mixed_traffic.envs.platoon.PlatoonEnv`) and the torch ring
(:class:`~mixed_traffic.envs.traffic.TrafficEnv`) are pure tensor arithmetic, so the cost of
the next ``horizon`` steps is a differentiable function of the policy's parameters through
the humans' car following, the residual's base controller (the frozen NNMPC, IDM), the safety
layer, the clip and the chain's reward and cost transforms. :func:`apg_pretrain` fits the
actor's deterministic action by gradient descent on that cost over short windows (truncated
back-propagation through time, as in short-horizon actor-critic methods), each window starting
where the last one ended::

    for it in range(iterations):
        state <- state.detach()                       # the window starts where the last one ended
        loss = mean over rows and H steps of  J_t / J_ref[profile] + cost_coeff * c_t   (platoon)
                                             -r_t + cost_coeff * c_t                     (ring)
        loss.backward(); clip_grad_norm_; Adam step

Why this exists beside TorchRL's losses: every TorchRL objective estimates the gradient from
sampled returns (likelihood ratios or a learned critic). Here a residual command's effect on
the traffic's cost shows over seconds and is small against the head profile's and the humans'
noise, and PPO's estimate of it stays noise (``docs/deeplcc.md``, "Two reward fixes tried");
the simulator gives the exact gradient instead. It needs the torch backends (SUMO and the
intersection are not differentiable) and is the pre-training of a policy that Lagrangian PPO
then trains as usual (``policy.apg``; ``trainer.total_frames`` of PPO after it).

>>> from mixed_traffic.config import compose
>>> from mixed_traffic.training.builders import make_transformed_env
>>> from mixed_traffic.training.on_policy import build_ppo
>>> cfg = compose(["experiment=ring_lagrangian_ppo", "policy.apg.iterations=1", "policy.apg.horizon=2",
...               "policy.apg.num_envs=2"])
>>> actor = build_ppo(cfg, make_transformed_env(cfg, num_envs=2, seed=0))[0]
>>> apg_pretrain(actor, cfg, log=None)["iterations"]
1
"""

from __future__ import annotations

import time

import torch
from omegaconf import DictConfig
from torchrl.envs.utils import ExplorationType, set_exploration_type
from tqdm.auto import tqdm

from mixed_traffic.envs.platoon import PROFILE_KINDS, PlatoonEnv
from mixed_traffic.training.plain_actor import deterministic_action


def _j_ref(cfg_ref, field: str) -> torch.Tensor:
    """Per profile kind (``PROFILE_KINDS`` order) the stage cost a step is measured against (1 where not given)."""
    ref = dict(cfg_ref or {})
    bad = {k: v for k, v in ref.items() if k not in PROFILE_KINDS or not float(v) > 0}
    if bad:
        raise ValueError(f"{field}={bad} is invalid; allowed: a positive stage cost per profile in {list(PROFILE_KINDS)}")
    return torch.tensor([float(ref.get(k, 1.0)) for k in PROFILE_KINDS], dtype=torch.float64)


def cut_graph(env) -> None:
    """Detach every tensor the env (base and transforms) holds as state: the next window starts here."""
    for obj in [env.base_env, *getattr(env, "transform", [])]:
        for name, v in list(vars(obj).items()):
            if torch.is_tensor(v) and v.requires_grad:
                setattr(obj, name, v.detach())


def window_loss(env, actor, td, horizon: int, j_ref: torch.Tensor | None, cost_coeff: float,
                gap_margin: float | None = None, head_gap_max: float | None = None, head_gap_after: float = 0.0):
    """``(loss, last step's tensordict, episode ended)`` of one window of at most ``horizon`` steps from ``td``.

    ``loss``: the mean over rows and steps of ``J / j_ref[profile] + cost_coeff * cost`` on the
    platoon (``j_ref`` per profile kind), of ``-reward + cost_coeff * cost`` on the ring
    (``j_ref=None``); with ``gap_margin`` (m) the CAVs' ``("cav", "gap")`` below it adds
    ``cost_coeff * (gap_margin - gap) / gap_margin`` (a margin the policy keeps by itself, not
    left to the safety layer); with ``head_gap_max`` (m) a ``("cav", "head_gap")`` above it adds
    ``cost_coeff * (head_gap - head_gap_max) / head_gap_max`` from ``head_gap_after`` seconds into the
    episode on (the CAV keeps up with the head by itself, also where the layer only holds the gap, and
    closes a long start gap by then at its own pace); differentiable in the actor's parameters.
    """
    total, steps, ended = 0.0, 0, False
    act = deterministic_action(actor)
    while steps < horizon and not ended:
        td = env.step(act(td))["next"]
        if j_ref is None:
            j = -td["reward"].reshape(-1).to(torch.float64)
        else:
            j = td["traffic", "J"].reshape(-1).to(torch.float64) / j_ref[td["deeplcc", "kind"].reshape(-1)]
        c = td["cost"].reshape(-1).to(torch.float64)
        if gap_margin is not None:
            short = (gap_margin - td["cav", "gap"].to(torch.float64)).clamp_min(0.0) / gap_margin
            c = c + short.reshape(len(c), -1).sum(-1)
        if head_gap_max is not None:
            far = (td["cav", "head_gap"].to(torch.float64) - head_gap_max).clamp_min(0.0) / head_gap_max
            if head_gap_after > 0:
                far = far * (td["traffic", "time"].to(torch.float64) > head_gap_after)
            c = c + far.reshape(len(c), -1).sum(-1)
        total = total + j.mean() + cost_coeff * c.mean()
        steps, ended = steps + 1, bool(td["done"].any())
    return total / steps, td, ended


def window_settings(a: DictConfig) -> dict:
    """:func:`window_loss`'s ``gap_margin``, ``head_gap_max`` and ``head_gap_after`` from ``cfg.policy.apg`` ``a``,
    checked: a bad one is an error that names it."""
    margin = a.get("gap_margin")
    if margin is not None and not float(margin) > 0:
        raise ValueError(f"policy.apg.gap_margin={margin!r} is invalid; allowed: null or > 0 (m)")
    head_max = a.get("head_gap_max")
    if head_max is not None and not float(head_max) > 0:
        raise ValueError(f"policy.apg.head_gap_max={head_max!r} is invalid; allowed: null or > 0 (m)")
    head_after = float(a.get("head_gap_after") or 0.0)
    if not head_after >= 0:
        raise ValueError(f"policy.apg.head_gap_after={head_after!r} is invalid; allowed: >= 0 (s)")
    return {"gap_margin": None if margin is None else float(margin),
            "head_gap_max": None if head_max is None else float(head_max), "head_gap_after": head_after}


def apg_env(cfg: DictConfig):
    """``(env, j_ref)``: the env analytic gradients train on (the run's transforms less ``policy.apg.without``, with
    ``policy.apg.num_envs`` rows and its own seed) and the platoon's per-profile cost references (None on the ring)."""
    from mixed_traffic.envs.traffic import TrafficEnv
    from mixed_traffic.training.builders import make_transformed_env

    a = cfg.policy.apg
    env = make_transformed_env(cfg, num_envs=a.num_envs, seed=int(cfg.seed) + 7_919,
                               without=tuple(a.get("without") or ()))
    base = env.base_env
    if type(base) not in (PlatoonEnv, TrafficEnv):  # the SUMO backends and the intersection are not differentiable
        raise ValueError(f"policy.apg needs a differentiable torch env (env=deeplcc or the ring, backend torch); "
                         f"got {type(base).__name__}")
    if a.get("head_gap_max") is not None and type(base) is not TrafficEnv:
        raise ValueError(f"policy.apg.head_gap_max={a.head_gap_max!r} is invalid on {type(base).__name__}; allowed: "
                         "null (the head gap is the ring's)")
    j_ref = _j_ref(a.J_ref, "policy.apg.J_ref") if type(base) is PlatoonEnv else None
    if j_ref is None and a.J_ref:
        raise ValueError(f"policy.apg.J_ref={dict(a.J_ref)} is invalid on {type(base).__name__}; allowed: {{}} "
                         "(per-profile references are the platoon's)")
    return env, j_ref


def apg_pretrain(actor, cfg: DictConfig, *, log=print) -> dict:
    """Train ``actor`` (its deterministic action) on the run's env by analytic gradients (``cfg.policy.apg``).

    The env is the run's own (``make_transformed_env``: the same transforms less
    ``policy.apg.without``, with ``policy.apg.num_envs`` rows); the loss of a window is the mean over rows and steps of
    ``J / J_ref[profile] + cost_coeff * cost`` on the platoon (``J`` the DeeP-LCC stage cost,
    ``cost`` the spacing constraint's), ``-reward + cost_coeff * cost`` on the torch ring (the
    chain's reward and constraint cost, e.g. the layer's priced intervention). With
    ``policy.apg.average_last: N`` the actor keeps the mean of its parameters after each of the
    last N steps (a Polyak / stochastic-weight average) instead of the last step's, which carry
    the noise of the last few windows. Returns ``{"iterations", "loss_first", "loss_last", "seconds"}``.
    """
    a = cfg.policy.apg
    for name, v in (("iterations", a.iterations), ("horizon", a.horizon), ("num_envs", a.num_envs)):
        if not (isinstance(v, int) and v >= 1):
            raise ValueError(f"policy.apg.{name}={v!r} is invalid; allowed: an integer >= 1")
    if not (a.lr > 0 and a.max_grad_norm > 0 and a.cost_coeff >= 0):
        raise ValueError(f"policy.apg: lr={a.lr}, max_grad_norm={a.max_grad_norm}, cost_coeff={a.cost_coeff} "
                         "are invalid; allowed: lr > 0, max_grad_norm > 0, cost_coeff >= 0")
    without = tuple(a.get("without") or ())
    bad = [n for n in without if n not in cfg.transforms.chain]
    if bad:
        raise ValueError(f"policy.apg.without={list(without)} is invalid; allowed: entries of transforms.chain "
                         f"{list(cfg.transforms.chain)}")
    window = window_settings(a)
    average_last = a.get("average_last") or 0
    if not (isinstance(average_last, int) and 0 <= average_last <= a.iterations):
        raise ValueError(f"policy.apg.average_last={average_last!r} is invalid; allowed: an integer in "
                         f"[0, policy.apg.iterations={a.iterations}]")
    env, j_ref = apg_env(cfg)
    base = env.base_env
    params = [p for p in actor.parameters() if p.requires_grad]
    opt = torch.optim.Adam(params, lr=a.lr)
    t0, losses = time.perf_counter(), []
    averaged = [torch.zeros_like(p) for p in params] if average_last else None
    td = env.reset()
    base.differentiable = True  # the platoon cuts the graph at the action unless told not to
    try:
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            bar = tqdm(range(a.iterations), desc="APG", unit="step",
                       disable=not bool(cfg.trainer.get("progress", True)))
            for it in bar:
                cut_graph(env)
                td = td.detach()
                loss, td, ended = window_loss(env, actor, td, a.horizon, j_ref, a.cost_coeff, **window)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                torch.nn.utils.clip_grad_norm_(params, a.max_grad_norm)
                opt.step()
                if averaged is not None and it >= a.iterations - average_last:
                    for s_, p in zip(averaged, params):
                        s_.add_(p.detach(), alpha=1.0 / average_last)
                losses.append(float(loss.detach()))
                bar.set_postfix(window_loss=f"{losses[-1]:.4f}", refresh=False)
                if ended:  # the rows run in lockstep: a window ends where their episodes end
                    cut_graph(env)
                    td = env.reset()
                if log and (it + 1) % max(1, a.iterations // 10) == 0:
                    log(f"apg: iteration {it + 1}/{a.iterations}, window loss {losses[-1]:.4f}")
    finally:
        base.differentiable = False
        cut_graph(env)
    if averaged is not None:  # Polyak average of the last steps: less of the last windows' noise in the policy
        with torch.no_grad():
            for s_, p in zip(averaged, params):
                p.copy_(s_)
    env.close()
    return {"iterations": a.iterations, "loss_first": losses[0], "loss_last": losses[-1],
            "seconds": time.perf_counter() - t0}
