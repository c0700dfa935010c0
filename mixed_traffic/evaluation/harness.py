"""Deterministic evaluation of any CAV policy over head profiles and seeds.

A policy is any TensorDictModule reading the env's keys and writing ``"action"``: a
trained PPO actor, a DQN Q-network with its action mapping, a tabular Q policy, or a
classical controller (:mod:`mixed_traffic.controllers.classic`). Each profile runs
``episodes`` episodes side by side (one batched env, ``break_when_any_done=False``);
steps after a row's first ``done`` are masked out.

Metrics per episode (all from the env key contract):

- ``collision`` (0/1), ``min_gap`` (m), ``max_head_gap`` (m, after the warm-up),
- ``time_outside`` (s): time with ``gap < s_min`` or ``head_gap > s_max`` after the warm-up,
  ``time_outside_total`` (s): the same from t = 0 (includes closing the initial gap),
- ``speed_rmse`` (m/s): CAV speed vs head speed after the warm-up,
- ``speed_rmse_steady``: the same on steady-state samples only: the head's speed has
  been constant (|a_head| < 0.05 m/s^2) for ``settle_seconds`` (profiles without such
  plateaus, e.g. a sine, fall back to ``speed_rmse``),
- ``steady_seconds`` (s): how long those steady samples last in the episode; 0 where
  ``speed_rmse_steady`` is the fallback, the whole-episode ``speed_rmse`` (a head that never holds
  its speed for ``settle_seconds``, as a sine's or one that stops and drives off with short holds),
- ``mean_abs_accel`` (m/s^2), ``mean_abs_jerk`` (m/s^3; ``mean_abs_jerk_after``: after the
  warm-up, as the gap bounds are judged), ``return`` (sum of the env's
  transformed reward), ``mean_J`` (DeeP-LCC stage cost), ``safety_clip_rate`` (the
  intervention rate: share of steps where the safety layer changed the command),
  ``mean_abs_delta`` (m/s^2, mean |executed - commanded|),
- ``override_rate``: share of steps where SUMO's speed mode 95 changed the CAV's command
  (``sumo_safety=True`` on either backend: ``("cav", "override")``; 0 without it),
- ``length`` (s).

The policy itself: with ``cfg.eval.without_layer`` every profile also runs with the safety
layer switched off on some rows (:meth:`transforms.SafetyLayer.set_active_rows`; the
intervention cost is then 0), so the policy's own command is executed, from the standard
start and from each ``cfg.eval.close_starts`` spacing. All profiles and starts share one
batched rollout (:func:`run_batched`); a one-profile runner (the SUMO evaluation's) runs each
start as episodes of its own, the layer dropped from the chain. Its results are in
``report["without_layer"][profile][start]`` and in ``report["acceptance"]``.

Episodes: episode ``e`` of every profile is drawn from its own seed ``seed + e``
(:func:`episode_seeds`, :meth:`~mixed_traffic.envs.traffic.TrafficEnv.seed_rows`): the head
profile's parameters, the humans' parameters and any per-step noise are those of a one-row env
seeded ``seed + e``, whatever the batch holds. So every controller evaluated with the same
``seed`` and ``episodes`` meets the same episodes, the policy meets the same ones with and
without its layer, and a comparison can be made episode by episode (``per_episode`` in the
report); the SUMO evaluation seeds its episodes alike (:mod:`mixed_traffic.evaluation.sumo`).
"""

from __future__ import annotations

import inspect
import math
from dataclasses import dataclass
from functools import partial

import torch
from omegaconf import DictConfig
from tensordict import TensorDict, TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type
from tqdm.auto import tqdm

from mixed_traffic.training.builders import TRAINING_ONLY, env_kwargs, make_transformed_env, sensor_filter_model

METRICS = ("collision", "min_gap", "min_gap_after", "max_head_gap", "time_outside", "time_outside_total", "speed_rmse",
           "speed_rmse_steady", "steady_seconds", "mean_abs_accel", "mean_abs_jerk", "mean_abs_jerk_after", "return", "mean_J", "safety_clip_rate",
           "mean_abs_delta", "override_rate", "length")


def episode_seeds(seed: int, episodes: int) -> list[int]:
    """Seed of every episode of a profile: ``seed, seed + 1, ...``."""
    return [int(seed) + e for e in range(int(episodes))]


def seed_episodes(env, seeds: list[int]) -> None:
    """Row ``i`` of ``env`` runs the episode of seed ``seeds[i]`` (a base env without
    ``seed_rows`` keeps its one generator)."""
    base = getattr(env, "base_env", env)
    if hasattr(base, "seed_rows"):
        base.seed_rows(seeds)


# what episode_metrics reads of a rollout's "next" (the optional ones where the chain writes them)
METRIC_KEYS = ("done", "collision", "reward", ("traffic", "time"), ("traffic", "accel"), ("traffic", "J"),
               ("cav", "gap"), ("cav", "head_gap"), ("cav", "speed"), ("cav", "head_speed"), ("cav", "accel"),
               ("cav", "override"), ("safety", "clipped"), ("safety", "delta"),
               # the errors transforms.SensorNoise added to the CAV's measurements (eval.sensor_noise_*)
               ("sensor_noise", "gap"), ("sensor_noise", "head_gap"), ("sensor_noise", "speed"),
               ("sensor_noise", "head_speed"),
               # and the errors of transforms.MeasurementFilter's estimates of them (eval.sensor_filter)
               ("sensor_filter", "gap"), ("sensor_filter", "head_gap"), ("sensor_filter", "speed"),
               ("sensor_filter", "head_speed"))


def filter_model(e) -> dict:
    """``{"filter_model": {gap, speed, tau}}`` where ``e.sensor_filter_*`` sets a noise model of the filter other
    than the noise drawn, else ``{}`` (the filter assumes the noise it filters)."""
    if not e.get("sensor_filter", False) or all(e.get(f"sensor_filter_{k}") is None for k in ("gap", "speed", "tau")):
        return {}
    return {"filter_model": sensor_filter_model(e)}


def rollout_for_metrics(env, policy, steps: int, callback=None) -> TensorDictBase:
    """``env.rollout(steps, policy, break_when_any_done=False)`` keeping only :data:`METRIC_KEYS`.

    The same loop as TorchRL's (reset, then ``policy`` and ``step_and_maybe_reset`` per step, a plain
    ``step`` for the last), so the numbers are the same to the bit; a ``ProbabilisticActor`` runs as
    :func:`~mixed_traffic.training.plain_actor.deterministic_action` (its deterministic action without
    the ``TensorDictModule`` bookkeeping). ``env.rollout`` keeps every key of every step: 12 GB for
    60 episodes of every profile and start (960 rows of 5000 steps); this keeps what the metrics need.
    Returns a ``[rows, steps]`` tensordict with ``"next"`` only.
    """
    from mixed_traffic.training.plain_actor import deterministic_action

    act = deterministic_action(policy)
    td = env.reset()
    frames = []
    for i in range(steps):
        if i < steps - 1:
            out, td = env.step_and_maybe_reset(act(td))
        else:  # as TorchRL's rollout: no reset after the last step (it would write into the last step's state)
            out = env.step(act(td))
        frames.append(out.get("next").select(*METRIC_KEYS, strict=False))
        if callback is not None:
            callback()
    nxt = torch.stack(frames, len(env.batch_size))
    return TensorDict({"next": nxt}, batch_size=nxt.batch_size)


@dataclass
class Trace:
    """Time series of one profile's batch of episodes (``[episodes, T]`` tensors)."""

    time: torch.Tensor
    head_speed: torch.Tensor
    cav_speed: torch.Tensor
    cav_accel: torch.Tensor
    head_accel: torch.Tensor
    gap: torch.Tensor
    head_gap: torch.Tensor
    valid: torch.Tensor
    raw_accel: torch.Tensor  # the command before the safety layer (= cav_accel without a layer)


def first_done_mask(done: torch.Tensor) -> torch.Tensor:
    """True up to and including each row's first done step."""
    d = done.long()
    before = torch.cumsum(d, dim=1) - d  # dones strictly before t
    return before == 0


def abs_jerk(accel: torch.Tensor, valid: torch.Tensor, dt: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``|a_t - a_{t-1}| / dt`` per step of ``[episodes, T]`` accelerations (0 at the first step) and the
    steps it counts on: ``valid`` less the first step, whose previous acceleration is unknown."""
    jerk = torch.zeros_like(accel)
    jerk[:, 1:] = (accel[:, 1:] - accel[:, :-1]).abs() / dt
    jvalid = valid.clone()
    jvalid[:, 0] = False
    return jerk, jvalid


def jerk_shares_by(accel: torch.Tensor, valid: torch.Tensor, dt: float, by: torch.Tensor, edges) -> list[float]:
    """The report's mean ``|jerk|`` (:func:`abs_jerk`) split by the bins ``[lo, hi)`` of ``edges`` over ``by``
    (``[episodes, T]``: the time, the CAV's speed, ...): per bin, its steps' summed ``|jerk|`` over all counted
    steps, averaged over episodes, so the shares add up to the whole-episode mean when the bins cover ``by``."""
    jerk, jvalid = abs_jerk(accel, valid, dt)
    n = jvalid.sum(1).clamp_min(1)
    return [float(((jerk * (jvalid & (by >= lo) & (by < hi))).sum(1) / n).mean()) for lo, hi in zip(edges[:-1], edges[1:])]


def steady_samples(head_accel: torch.Tensor, after: torch.Tensor, settle_steps: int) -> torch.Tensor:
    """``[episodes, T]`` mask of the steady-state samples: ``after`` and the head's acceleration below
    0.05 m/s^2 for the last ``settle_steps`` steps (the samples ``speed_rmse_steady`` counts)."""
    still = head_accel.abs() < 0.05
    # length of the current run of "still" steps: the index less that of the last step that was not still
    idx = torch.arange(still.shape[1]).expand_as(still)
    last_break = torch.where(~still, idx, torch.full_like(idx, -1)).cummax(1).values
    return after & ((idx - last_break) >= settle_steps)


def _masked_mean(x: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
    return (x * m).sum(1) / m.sum(1).clamp_min(1)


def follower_metrics(*, gap: torch.Tensor, head_gap: torch.Tensor, speed: torch.Tensor, head_speed: torch.Tensor,
                     accel: torch.Tensor, head_accel: torch.Tensor, valid: torch.Tensor, after: torch.Tensor,
                     dt: float, settle: float) -> dict[str, torch.Tensor]:
    """The first CAV's own per-episode metrics from ``[episodes, T]`` series (``valid``: the steps that count,
    ``after``: those after the warm-up): ``min_gap``, ``max_head_gap``, ``min_gap_after``, ``speed_rmse``,
    ``speed_rmse_steady``, ``steady_seconds``, ``mean_abs_accel``, ``mean_abs_jerk`` and ``mean_abs_jerk_after``. Shared by
    :func:`episode_metrics` and :func:`mixed_traffic.evaluation.replay.replay`."""
    inf = torch.tensor(float("inf"))
    err2 = (speed - head_speed).pow(2)
    rmse = _masked_mean(err2, after).sqrt()
    steady = steady_samples(head_accel, after, settle_steps=int(round(settle / dt)))
    jerk, jvalid = abs_jerk(accel, valid, dt)
    return {
        "min_gap": torch.where(valid, gap, inf).min(1).values,
        "max_head_gap": torch.where(after, head_gap, -inf).max(1).values,
        "min_gap_after": torch.where(after, gap, inf).min(1).values,
        "speed_rmse": rmse,
        "speed_rmse_steady": torch.where(steady.sum(1) > 0, _masked_mean(err2, steady).sqrt(), rmse),
        "steady_seconds": steady.sum(1).to(speed.dtype) * dt,
        "mean_abs_accel": _masked_mean(accel.abs(), valid),
        "mean_abs_jerk": _masked_mean(jerk, jvalid),
        "mean_abs_jerk_after": _masked_mean(jerk, jvalid & after),
    }


def episode_metrics(td: TensorDictBase, *, dt: float, s_min: float, s_max: float, warmup: float,
                    settle: float) -> tuple[dict[str, torch.Tensor], Trace]:
    """Per-episode metrics of a ``[episodes, T]`` rollout (see the module docstring)."""
    nxt = td.get("next")
    done = nxt.get("done").squeeze(-1)
    valid = first_done_mask(done)
    t = nxt.get(("traffic", "time")).squeeze(-1)
    after = valid & (t >= warmup)

    def true(name: str) -> torch.Tensor:
        """The CAV's entry ``name`` as it was, not as the CAV measured it: less the error that
        :class:`transforms.SensorNoise` added, or :class:`transforms.MeasurementFilter`'s estimate's error behind
        one (the metrics are of the true state under measurement noise)."""
        x = nxt.get(("cav", name))
        err = nxt.get(("sensor_filter", name), None)
        err = nxt.get(("sensor_noise", name), None) if err is None else err
        return (x if err is None else x - err)[..., 0]

    gap, head_gap, v, vh = true("gap"), true("head_gap"), true("speed"), true("head_speed")
    a = nxt.get(("cav", "accel"))[..., 0]
    a_head = nxt.get(("traffic", "accel"))[..., 0]
    f = follower_metrics(gap=gap, head_gap=head_gap, speed=v, head_speed=vh, accel=a, head_accel=a_head,
                         valid=valid, after=after, dt=dt, settle=settle)

    out: dict[str, torch.Tensor] = {}
    out["collision"] = (nxt.get("collision").squeeze(-1) & valid).any(1).float()
    for key in ("min_gap", "max_head_gap", "min_gap_after"):
        out[key] = f[key]
    outside = (gap < s_min) | (head_gap > s_max)
    out["time_outside"] = (outside & after).sum(1).float() * dt
    out["time_outside_total"] = (outside & valid).sum(1).float() * dt
    for key in ("speed_rmse", "speed_rmse_steady", "steady_seconds", "mean_abs_accel", "mean_abs_jerk",
                "mean_abs_jerk_after"):
        out[key] = f[key]
    out["return"] = (nxt.get("reward").squeeze(-1) * valid).sum(1)
    out["mean_J"] = _masked_mean(nxt.get(("traffic", "J")).squeeze(-1), valid)
    clipped = nxt.get(("safety", "clipped"), None)
    out["safety_clip_rate"] = _masked_mean(clipped[..., 0].float(), valid) if clipped is not None else torch.zeros(
        valid.shape[0])
    delta = nxt.get(("safety", "delta"), None)
    delta = delta[..., 0] if delta is not None else torch.zeros_like(a)
    out["mean_abs_delta"] = _masked_mean(delta.abs(), valid)
    override = nxt.get(("cav", "override"), None)
    out["override_rate"] = _masked_mean(override[..., 0].float(), valid) if override is not None else torch.zeros(
        valid.shape[0])
    out["length"] = valid.sum(1).float() * dt
    trace = Trace(time=t, head_speed=vh, cav_speed=v, cav_accel=a, head_accel=a_head, gap=gap, head_gap=head_gap,
                  valid=valid, raw_accel=a - delta)
    return out, trace


def eval_env_overrides(cfg: DictConfig, profile: str) -> dict:
    """Scenario overrides of one evaluation profile (random_steps keeps the scenario's arguments)."""
    ov: dict = {"profile": profile, "init_spacing_range": None}  # evaluation starts are fixed
    kw = (cfg.eval.profile_kwargs or {}).get(profile)
    if kw is not None:
        ov["profile_kwargs"] = dict(kw)
    elif profile != (cfg.env.profile or "random_steps"):
        ov["profile_kwargs"] = {}
    if cfg.eval.episode_seconds is not None:
        ov["episode_seconds"] = cfg.eval.episode_seconds
    if cfg.eval.get("hdv_param_noise") is not None:
        ov["hdv_param_noise"] = cfg.eval.hdv_param_noise
    return ov


def profile_env(cfg: DictConfig, profile: str, *, episodes: int, seed: int, without: tuple[str, ...] = (),
                init_spacing_rows: list[float] | None = None):
    """The deployed env of one evaluation profile, ``episodes`` rows seeded as every evaluation seeds them
    (``without``: transforms dropped from the chain; ``init_spacing_rows``: row ``i`` starts at gap
    ``init_spacing_rows[i % len]``)."""
    ov = eval_env_overrides(cfg, profile)
    if init_spacing_rows is not None:
        ov["init_spacing_rows"] = tuple(float(x) for x in init_spacing_rows)
    env = make_transformed_env(cfg, num_envs=episodes, seed=seed, without=tuple(without) + TRAINING_ONLY, deploy=True,
                               **ov)
    seed_episodes(env, episode_seeds(seed, episodes))
    return env


def run_profile(cfg: DictConfig, policy, profile: str, *, episodes: int, seed: int, policy_factory=None,
                without: tuple[str, ...] = (), init_spacing_rows: list[float] | None = None):
    """Run ``episodes`` deterministic episodes of ``profile``; returns (metrics, trace).

    ``without`` drops transforms from the chain (e.g. the safety layer);
    ``init_spacing_rows`` gives row ``i`` the start gap ``init_spacing_rows[i % len]``.
    """
    env = profile_env(cfg, profile, episodes=episodes, seed=seed, without=without, init_spacing_rows=init_spacing_rows)
    if policy_factory is not None:
        policy = policy_factory(env)
    base = env.base_env
    sc = base.scenario
    torch.manual_seed(seed)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        td = rollout_for_metrics(env, policy, sc.max_steps)
    m, trace = episode_metrics(td, dt=sc.dt, s_min=cfg.eval.s_min, s_max=cfg.eval.s_max,
                               warmup=cfg.eval.warmup_seconds, settle=cfg.eval.settle_seconds)
    env.close()
    return m, trace


def eval_scenario(cfg: DictConfig, profile: str):
    """The scenario one evaluation profile runs (``cfg.env`` with :func:`eval_env_overrides`)."""
    from mixed_traffic.scenarios import get_scenario

    return get_scenario(cfg.env.scenario, **env_kwargs(cfg.env, **eval_env_overrides(cfg, profile)))


LAYER_FREE_WITHOUT = ("safety_layer", "intervention_cost")
"""What a one-profile runner drops from the chain to run the policy without its layer: the layer, and the cost of its
interventions, which reads what the layer wrote (the batched rollout switches the layer off on some rows instead)."""


def layer_free_starts(cfg: DictConfig, profile: str) -> list[tuple[str, float]]:
    """The starts the policy runs from without its layer, ``(label, start gap in m)``: the profile's standard start
    first, then each ``cfg.eval.close_starts`` (the labels of ``report["without_layer"][profile]``)."""
    standard = eval_scenario(cfg, profile).initial_spacing()
    return [(f"standard ({standard:.1f} m)", float(standard))] + [(f"{x:g} m", float(x))
                                                                  for x in (cfg.eval.close_starts or [])]


def split_rows(m: dict, tr: Trace, rows: torch.Tensor) -> tuple[dict, Trace]:
    """The metrics and trace of a subset of rows."""
    return ({k: v[rows] for k, v in m.items()}, Trace(**{f: getattr(tr, f)[rows] for f in Trace.__dataclass_fields__}))


def run_batched(cfg: DictConfig, policy, profiles: list[str], *, episodes: int, seed: int, policy_factory=None,
                layer_free: bool = False):
    """Every profile, with the layer and (``layer_free``) without it, in one batched rollout.

    Row ``r`` follows ``profiles[r % P]`` (:class:`~mixed_traffic.profiles.RowProfiles`)
    in variant ``(r // P) % V``: variant 0 runs with the chain as configured, variants
    ``1..`` run with the safety layer switched off on their rows
    (:meth:`transforms.SafetyLayer.set_active_rows`), from the standard start and from
    each close start. The per-step cost of a small batch is mostly fixed overhead, so one
    rollout of ``P * V * episodes`` rows takes about as long as one profile's.

    Returns ``({profile: (metrics, trace)}, {profile: {start label: (metrics, trace)}})``.
    """
    from mixed_traffic.profiles import RowProfiles

    P = len(profiles)
    scenarios = [eval_scenario(cfg, p) for p in profiles]
    labelled = [layer_free_starts(cfg, p) for p in profiles]
    # start gaps per profile: variant 0 (with the layer) and 1 start at the standard gap
    starts = [[gap for _, gap in lab] for lab in labelled]
    V = 1 + (len(starts[0]) if layer_free else 0)
    ov = eval_env_overrides(cfg, profiles[0])
    ov["init_spacing_rows"] = tuple(starts[i % P][max(0, (i // P) % V - 1)] for i in range(P * V))  # row i % (P*V)
    env = make_transformed_env(cfg, num_envs=P * V * episodes, seed=seed, without=TRAINING_ONLY, deploy=True, **ov)
    base = env.base_env
    base.set_profile(RowProfiles(tuple(sc.make_profile() for sc in scenarios)))
    rows = torch.arange(P * V * episodes)
    seeds = episode_seeds(seed, episodes)
    seed_episodes(env, [seeds[r // (P * V)] for r in rows.tolist()])  # every profile and variant: episode e
    variant = (rows // P) % V
    if layer_free:
        layers = [t for t in env.transform.transforms if hasattr(t, "set_active_rows")]
        if not layers:
            raise ValueError("evaluation: eval.without_layer needs a safety layer in transforms.chain")
        for t in layers:
            t.set_active_rows(variant == 0)
    if policy_factory is not None:
        policy = policy_factory(env)
    steps = base.scenario.max_steps
    bar = tqdm(total=steps, desc=f"evaluation ({len(rows)} episodes)", unit="step", leave=False, miniters=steps // 50,
               disable=not cfg.get("trainer", {}).get("progress", True))
    torch.manual_seed(seed)
    # inference_mode, not no_grad: no autograd bookkeeping on any tensor (the same numbers; a step is a few hundred
    # small operations, each a little cheaper); the env is closed below and the metrics only read the rollout
    with torch.inference_mode(), set_exploration_type(ExplorationType.DETERMINISTIC):
        td = rollout_for_metrics(env, policy, steps, callback=bar.update)
    bar.close()
    m, trace = episode_metrics(td, dt=base.scenario.dt, s_min=cfg.eval.s_min, s_max=cfg.eval.s_max,
                               warmup=cfg.eval.warmup_seconds, settle=cfg.eval.settle_seconds)
    env.close()
    with_layer, without_layer = {}, {}
    for j, prof in enumerate(profiles):
        with_layer[prof] = split_rows(m, trace, rows[(rows % P == j) & (variant == 0)])
        if layer_free:
            without_layer[prof] = {label: split_rows(m, trace, rows[(rows % P == j) & (variant == v + 1)])
                                   for v, (label, _) in enumerate(labelled[j])}
    return with_layer, without_layer


def aggregate(values: torch.Tensor) -> dict:
    v = values.double()
    finite = v[torch.isfinite(v)]
    if finite.numel() == 0:
        return {"mean": float("nan"), "std": float("nan"), "min": float("nan"), "max": float("nan")}
    return {"mean": float(finite.mean()), "std": float(finite.std(unbiased=False)) if finite.numel() > 1 else 0.0,
            "min": float(finite.min()), "max": float(finite.max())}


def steady_only(per_episode: dict) -> list[float]:
    """The steady RMSEs of the episodes that had steady samples (``steady_seconds`` > 0), from a report's
    ``per_episode``: the others' figures are their whole-episode RMSE, which the steady bar does not judge."""
    return [r for r, t in zip(per_episode["speed_rmse_steady"], per_episode["steady_seconds"]) if t > 0]


def steadiness(per_episode: dict) -> dict:
    """``steady_episodes``: how many of the episodes have steady samples (``steady_seconds`` > 0);
    ``steady_seconds``: their mean length over all episodes (s); ``steady_only_rmse``: the mean steady RMSE of
    the episodes that have them (None if none has). An episode without steady samples reports the whole-episode
    RMSE as its steady RMSE (the metric's fallback), which the steady speed bar does not judge. Empty for a
    report written before ``steady_seconds`` existed."""
    secs = per_episode.get("steady_seconds")
    if secs is None:
        return {}
    steady = steady_only(per_episode)
    return {"steady_episodes": len(steady), "steady_seconds": sum(secs) / max(len(secs), 1),
            "steady_only_rmse": sum(steady) / len(steady) if steady else None}


def steady_rmse_mean(profile_report: dict) -> float | None:
    """A profile's steady RMSE as the acceptance judges it: the mean over its episodes with steady samples
    (:func:`steady_only`; all of them: the report's mean itself), None where no episode had any."""
    per = profile_report["per_episode"]
    if all(t > 0 for t in per["steady_seconds"]):
        return profile_report["metrics"]["speed_rmse_steady"]["mean"]
    return steadiness(per)["steady_only_rmse"]


def profile_entry(m: dict[str, torch.Tensor]) -> dict:
    """One profile's (or one layer-free start's) entry of report.json from its per-episode metrics ``m``: the
    aggregates, the collisions, every episode's figures and their :func:`steadiness` (``steady_only_rmse``: the
    steady RMSE over the episodes that settle, where ``metrics.speed_rmse_steady`` averages in the others'
    whole-episode fallback)."""
    per_episode = {k: [float(x) for x in v] for k, v in m.items()}
    return {"metrics": {k: aggregate(v) for k, v in m.items()}, "collisions": int(m["collision"].sum()),
            "per_episode": per_episode, **steadiness(per_episode)}


def evaluate(cfg: DictConfig, policy=None, *, policy_factory=None, profiles=None, episodes: int | None = None,
             seed: int | None = None, runner=None) -> tuple[dict, dict[str, Trace]]:
    """Evaluate over ``profiles``; returns the report dict and the traces (for plots).

    Pass ``policy`` (a module usable with any env of ``cfg``'s observation layout) or
    ``policy_factory(env) -> policy``. By default every profile (and, with
    ``cfg.eval.without_layer``, every layer-free start) runs in one batched torch rollout
    (:func:`run_batched`); ``runner(cfg, policy, profile, *, episodes, seed, policy_factory, without,
    init_spacing)`` runs one profile at a time instead (the SUMO evaluation passes its own): once with the chain
    as configured (``without=()``, ``init_spacing=None``) and, with ``cfg.eval.without_layer``, once per start of
    :func:`layer_free_starts` with :data:`LAYER_FREE_WITHOUT` dropped from the chain and the CAV starting
    ``init_spacing`` m behind its leader, so its report holds the same layer-free bars.
    """
    profiles = list(profiles or cfg.eval.profiles)
    episodes = int(episodes or cfg.eval.episodes)
    seed = int(cfg.eval.seed if seed is None else seed)
    report = {"episodes_per_profile": episodes, "eval_seed": seed, "episode_seeds": episode_seeds(seed, episodes),
              "profiles": {},
              "sumo_safety": bool(env_kwargs(cfg.env).get("sumo_safety", False)),
              # the V2V link the leader's acceleration was received over (0, 0: the perfect link)
              "v2v": {"delay": float(cfg.eval.get("v2v_delay", 0.0)), "loss": float(cfg.eval.get("v2v_loss", 0.0))},
              # the measurement noise's standard deviations (0, 0: exact measurements)
              "sensor_noise": {"gap": float(cfg.eval.get("sensor_noise_gap", 0.0)),
                               "speed": float(cfg.eval.get("sensor_noise_speed", 0.0)),
                               "tau": float(cfg.eval.get("sensor_noise_tau", 0.0)),
                               "margin": float(cfg.eval.get("sensor_noise_margin", 0.0)),
                               "filter": bool(cfg.eval.get("sensor_filter", False)),
                               **filter_model(cfg.eval)}}
    traces = {}
    all_m: dict[str, list] = {k: [] for k in METRICS}
    chain = list(cfg.transforms.chain)
    layer_free = "safety_layer" in chain and bool(cfg.eval.get("without_layer", False))
    if runner is None:
        results, free = run_batched(cfg, policy, profiles, episodes=episodes, seed=seed,
                                    policy_factory=policy_factory, layer_free=layer_free)
    else:  # one profile and start at a time: with the layer, then without it from each start
        if layer_free and not {"without", "init_spacing"} <= set(inspect.signature(runner).parameters):
            # a runner that swallowed them (**kwargs) would run the layer and report it as the layer-free runs
            raise TypeError("evaluate: runner must take the keyword arguments without= and init_spacing= to run the "
                            "policy without its safety layer (eval.without_layer=true); allowed: a runner that takes "
                            "them, or eval.without_layer=false")
        starts = {prof: layer_free_starts(cfg, prof) if layer_free else [] for prof in profiles}
        bar = tqdm(total=sum(1 + len(s) for s in starts.values()), desc="evaluation", unit="run", leave=False,
                   disable=not cfg.get("trainer", {}).get("progress", True))
        results, free = {}, {}
        run = partial(runner, cfg, policy, episodes=episodes, seed=seed, policy_factory=policy_factory)
        for prof in profiles:
            bar.set_postfix_str(prof)
            results[prof] = run(prof, without=(), init_spacing=None)
            bar.update()
            free[prof] = {}
            for label, gap in starts[prof]:
                bar.set_postfix_str(f"{prof}, no layer, {label}")
                free[prof][label] = run(prof, without=LAYER_FREE_WITHOUT, init_spacing=gap)
                bar.update()
        bar.close()
    for prof in profiles:
        m, trace = results[prof]
        traces[prof] = trace
        report["profiles"][prof] = profile_entry(m)
        for k in METRICS:
            all_m[k].append(m[k])
    cat = {k: torch.cat(v) for k, v in all_m.items() if v}
    ov = {k: aggregate(v)["mean"] for k, v in cat.items()}
    ov["collisions"] = int(cat["collision"].sum())
    ov["min_gap"] = float(cat["min_gap"].min())
    ov["max_head_gap"] = float(cat["max_head_gap"].max())
    ov["worst_speed_rmse_steady"] = float(cat["speed_rmse_steady"].max())
    ov["episodes"] = int(cat["collision"].numel())
    report["overall"] = ov
    e = cfg.eval
    # steady-state tracking is judged on the profiles with plateaus (where it is defined): not the sine, nor any
    # profile whose head held its speed long enough to settle in no episode (its figure is the whole episode's)
    steady = {p: steady_rmse_mean(report["profiles"][p]) for p in profiles if p != "sine"}
    rmse = max((r for r in steady.values() if r is not None), default=math.nan)
    report["acceptance"] = {
        "zero_collisions": ov["collisions"] == 0,
        "gap_within_bounds": bool(ov["min_gap"] >= e.s_min - 1e-6 and ov["max_head_gap"] <= e.s_max + 1e-6),
        "steady_speed_rmse": rmse,
        "rmse_within_bar": bool(rmse <= e.rmse_bar),
    }
    if "safety_layer" in chain:
        rate = max(report["profiles"][p]["metrics"]["safety_clip_rate"]["mean"] for p in profiles)
        report["acceptance"]["intervention_rate_max"] = rate
        report["acceptance"]["intervention_within_bar"] = bool(rate <= e.get("intervention_bar", 0.05))
    if layer_free:
        report["without_layer"] = {}
        coll, gmin, hmax = 0, math.inf, -math.inf
        for prof in profiles:
            res = free[prof]
            report["without_layer"][prof] = {}
            for label, (m, _tr) in res.items():
                report["without_layer"][prof][label] = profile_entry(m)
                coll += int(m["collision"].sum())
                # gap bounds after the warm-up (min_gap counts from t = 0, which a close start begins below)
                gmin = min(gmin, float(m["min_gap_after"].min()))
                hmax = max(hmax, float(m["max_head_gap"].max()))
            traces[f"{prof}_without_layer"] = res[next(iter(res))][1]
            traces[f"{prof}_without_layer_close"] = res[list(res)[1]][1] if len(res) > 1 else None
        traces = {k: v for k, v in traces.items() if v is not None}
        report["acceptance"]["no_layer_zero_collisions"] = coll == 0
        report["acceptance"]["no_layer_min_gap_after_warmup"] = gmin
        report["acceptance"]["no_layer_max_head_gap"] = hmax
        report["acceptance"]["no_layer_gap_within_bounds"] = bool(gmin >= e.s_min - 1e-6 and hmax <= e.s_max + 1e-6)
    with_pass(report["acceptance"])
    return report, traces


def with_pass(acceptance: dict) -> dict:
    """``acceptance`` with its ``pass`` (re)computed and last: every boolean bar in it met (the figures beside them,
    floats and names, are not bars). Bars added later (:func:`mixed_traffic.evaluation.reference_bars`) call it again."""
    acceptance.pop("pass", None)
    acceptance["pass"] = all(v for v in acceptance.values() if isinstance(v, bool))
    return acceptance
