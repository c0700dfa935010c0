"""Evaluate a ring policy on the SUMO backend with the torch harness's metrics and report.

>>> from mixed_traffic.evaluation.policies import checkpoint_config, policy_factory_from_state
>>> from mixed_traffic.evaluation.sumo import evaluate_on_sumo
>>> cfg, state = checkpoint_config("outputs/results/ring_lagrangian_ppo_seed0/final.pt")  # doctest: +SKIP
>>> report, traces = evaluate_on_sumo(cfg, policy_factory=policy_factory_from_state(cfg, state),
...                                   profiles=["random_steps"], episodes=2, seed=1000)  # doctest: +SKIP

The env is the torch evaluation's env of ``cfg`` with its base swapped: the same deployed
``cfg.transforms.chain`` less the training-only terms (``chain_transforms(cfg, base,
without=TRAINING_ONLY, deploy=True)`` of :mod:`mixed_traffic.training.builders`, exactly as
``harness.run_profile`` builds it) around a ``ParallelEnv`` of ``workers`` SUMO rings
(``make_env("ring", backend="sumo")``, speed mode 0 unless ``sumo_safety=True``: SUMO executes
the action the transforms, e.g. the ``SafetyLayer``, hand it).

Episodes and seeds: episode ``e`` (0-based) of every profile runs on a SUMO env seeded
``seed + e`` (:func:`episode_seeds`); ``episodes`` episodes take ``ceil(episodes / workers)``
rounds, each round a fresh ``ParallelEnv`` whose worker ``w`` holds episode
``round * workers + w``. A SUMO env seeded ``s`` draws the same head profile as a torch
env with ``batch_size=1`` seeded ``s`` (docs/sumo.md), and so does row ``e`` of the torch
harness (:func:`mixed_traffic.evaluation.harness.evaluate`, which seeds its episodes alike):
the torch evaluation with the same ``seed`` replays exactly these episodes.
:func:`evaluate_on_torch_seeds` does the same one env per episode.

Episode length: ``episode_seconds`` if given, else ``cfg.eval.episode_seconds``, else
:data:`DEFAULT_EPISODE_SECONDS` (120 s; the scenario's 500 s is slow in SUMO).

Metrics: :func:`mixed_traffic.evaluation.harness.episode_metrics` on the ``[episodes, T]``
rollout; the report is built by :func:`mixed_traffic.evaluation.harness.evaluate` itself (``runner=``)
(with this module's per-profile runner in place of the torch one), so it has the same
structure, plus ``backend``, ``episode_seconds``, ``episode_seeds``, ``workers`` and
``sumo_safety``; :func:`mixed_traffic.evaluation.report.write_report` writes it.

The policy itself: with ``cfg.eval.without_layer`` (the default) and a safety layer in the chain, every profile
also runs without the layer from the standard start and from each ``cfg.eval.close_starts`` gap, in episodes of
its own (the layer and its intervention cost dropped from the chain, the SUMO ring started at that gap), so the
report holds the same layer-free bars as the torch evaluation's (``report["without_layer"]``, the acceptance's
``no_layer_*``). That runs each profile's episodes 2 + len(close_starts) times (with the layer, then from each
start without it); ``eval.without_layer=false`` skips it.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import math

import torch
from omegaconf import DictConfig
from torchrl.envs import ParallelEnv, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from mixed_traffic.evaluation import harness
from mixed_traffic.evaluation.harness import episode_metrics, episode_seeds, eval_env_overrides
from mixed_traffic.scenarios import get_scenario
from mixed_traffic.training.builders import TRAINING_ONLY, chain_transforms, check_chain, env_kwargs

DEFAULT_EPISODE_SECONDS = 120.0
SUMO_ONLY = ("sumo_safety", "sigma", "net_file", "run_dir", "sumo_args", "netconvert")


def eval_config(cfg: DictConfig, episode_seconds: float | None = None) -> DictConfig:
    """A copy of ``cfg`` with ``eval.episode_seconds`` set (given, else the config's, else 120 s)."""
    cfg = copy.deepcopy(cfg)  # interpolations (out_dir -> hydra:...) stay unresolved
    if episode_seconds is None:
        episode_seconds = cfg.eval.episode_seconds if cfg.eval.episode_seconds is not None else DEFAULT_EPISODE_SECONDS
    cfg.eval.episode_seconds = float(episode_seconds)
    return cfg


def make_sumo_eval_env(cfg: DictConfig, seeds: list[int], *, sumo_safety: bool = False, in_process: bool = False,
                       without: tuple[str, ...] = (), **env_overrides) -> TransformedEnv:
    """``cfg``'s deployed transform chain, less the training-only terms (and ``without``), around
    ``ParallelEnv(len(seeds))`` of SUMO rings, worker ``w`` seeded ``seeds[w]``.

    ``in_process=True`` (one seed only): the SUMO env itself, in this process, no worker
    (libsumo allows one live simulation per process).

    The chain is :func:`mixed_traffic.training.builders.chain_transforms`, as the torch evaluation's
    ``make_transformed_env(..., deploy=True)`` builds it (which builds its base env itself with
    ``batch_size=num_envs``, impossible for SUMO). The transforms read
    ``dt``, ``J_max`` and ``scenario`` from the parent env; a ``ParallelEnv`` does not have
    them, so they are set on it from the same scenario the workers build.
    """
    if cfg.env.scenario != "ring":
        raise ValueError(f"evaluate_on_sumo: env.scenario={cfg.env.scenario!r} is invalid; allowed: 'ring'")
    check_chain(cfg.transforms.chain)
    kw = env_kwargs(cfg.env, **env_overrides)
    kw.pop("sumo_safety", None)  # the argument wins over env.overrides
    if in_process:
        if len(seeds) != 1:
            raise ValueError(f"make_sumo_eval_env: in_process=True takes one seed, got {len(seeds)}")
        from mixed_traffic.envs import make_env

        base = make_env("ring", backend="sumo", seed=int(seeds[0]), device=str(cfg.device),
                        sumo_safety=bool(sumo_safety), **kw)
    else:
        fns = [functools.partial(_make_sumo_env, seed=int(s), device=str(cfg.device), sumo_safety=bool(sumo_safety),
                                 **kw) for s in seeds]
        base = ParallelEnv(len(seeds), fns, serial_for_single=False)
        sc = dataclasses.replace(_scenario(kw), sumo_safety=bool(sumo_safety))
        base.scenario, base.dt, base.J_max = sc, sc.dt, sc.J_max
    # as the torch evaluation builds it (harness.run_profile): the deployed chain, less the training-only terms
    return TransformedEnv(base, chain_transforms(cfg, base, without=TRAINING_ONLY + tuple(without), deploy=True))


def _scenario(kw: dict):
    """The scenario a SUMO worker builds from ``kw`` (minus the SUMO-only arguments)."""
    return get_scenario("ring", **{k: v for k, v in kw.items() if k not in SUMO_ONLY})


def _make_sumo_env(seed: int, device: str, **kw):
    # module-level (picklable) factory; the worker imports mixed_traffic itself
    import torch as _torch

    from mixed_traffic.envs import make_env

    _torch.set_num_threads(1)
    return make_env("ring", backend="sumo", seed=seed, device=device, **kw)


def run_profile_sumo(cfg: DictConfig, policy, profile: str, *, episodes: int, seed: int, policy_factory=None,
                     workers: int = 2, sumo_safety: bool = False, without: tuple[str, ...] = (),
                     init_spacing: float | None = None):
    """``harness.run_profile`` on SUMO: ``episodes`` deterministic episodes in rounds of ``workers``.

    ``workers=0``: one episode at a time in this process (no worker processes; tests). ``without``: transforms
    dropped from the chain (the layer-free runs drop ``harness.LAYER_FREE_WITHOUT``); ``init_spacing``: the CAV
    starts this many m behind its leader (None: the profile's standard start).
    """
    seeds = episode_seeds(seed, episodes)
    overrides = eval_env_overrides(cfg, profile)
    if init_spacing is not None:
        overrides["init_spacing"] = float(init_spacing)
    per_round = max(1, int(workers))
    tds = []
    for r in range(math.ceil(len(seeds) / per_round)):
        env = make_sumo_eval_env(cfg, seeds[r * per_round:(r + 1) * per_round], sumo_safety=sumo_safety,
                                 in_process=workers == 0, without=without, **overrides)
        try:
            pol = policy_factory(env) if policy_factory is not None else policy
            torch.manual_seed(seed)
            with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
                td = env.rollout(env.base_env.scenario.max_steps, pol, break_when_any_done=False)
            keep = [("next", k) for k in ("done", "collision", "reward", "cav", "traffic", "safety", "sensor_noise", "sensor_filter")]
            td = td.select(*keep, strict=False)
            # ParallelEnv of batch-[1] envs: [workers, 1, T] -> [workers, T], the harness's layout
            tds.append(td.reshape(-1, td.shape[-1]))
        finally:
            env.close(raise_if_closed=False)
    td = torch.cat(tds, 0)
    sc = _scenario(env_kwargs(cfg.env, **overrides))
    return episode_metrics(td, dt=sc.dt, s_min=cfg.eval.s_min, s_max=cfg.eval.s_max,
                           warmup=cfg.eval.warmup_seconds, settle=cfg.eval.settle_seconds)


def evaluate_on_sumo(cfg: DictConfig, policy=None, *, policy_factory=None, profiles=None, episodes: int | None = None,
                     seed: int | None = None, workers: int = 2, episode_seconds: float | None = None,
                     sumo_safety: bool = False) -> tuple[dict, dict]:
    """Evaluate ``policy`` (or ``policy_factory(env)``) on SUMO; returns (report, traces) like ``harness.evaluate``.

    ``cfg`` is a run config (e.g. from :func:`mixed_traffic.evaluation.policies.checkpoint_config`,
    with the caller's ``eval``); ``profiles`` / ``episodes`` / ``seed`` default to ``cfg.eval``.
    ``workers`` SUMO processes run side by side (``ParallelEnv``); ``workers=0`` runs the
    episodes one by one in this process (no spawn cost; no other live SUMO env allowed here).
    """
    cfg = eval_config(cfg, episode_seconds)
    episodes = int(episodes or cfg.eval.episodes)
    seed = int(cfg.eval.seed if seed is None else seed)
    workers = min(int(workers), episodes)  # 0: in this process, one episode at a time

    def run(cfg_, policy_, profile, *, episodes, seed, policy_factory=None, without=(), init_spacing=None):
        return run_profile_sumo(cfg_, policy_, profile, episodes=episodes, seed=seed, policy_factory=policy_factory,
                                workers=workers, sumo_safety=sumo_safety, without=without, init_spacing=init_spacing)

    report, traces = harness.evaluate(cfg, policy, policy_factory=policy_factory, profiles=profiles,
                                      episodes=episodes, seed=seed, runner=run)
    report.update(backend="sumo", speed_mode=95 if sumo_safety else 0, sumo_safety=bool(sumo_safety),
                  episode_seconds=float(cfg.eval.episode_seconds), episode_seeds=episode_seeds(seed, episodes),
                  workers=workers)
    return report, traces


def evaluate_on_torch_seeds(cfg: DictConfig, policy=None, *, policy_factory=None, profiles=None,
                            episodes: int | None = None, seed: int | None = None,
                            episode_seconds: float | None = None) -> tuple[dict, dict]:
    """The torch harness on the same episodes as :func:`evaluate_on_sumo`: one ``batch_size=1`` env per seed.

    Episode ``e`` is ``harness.run_profile`` with ``episodes=1, seed=seed + e``: the episode row ``e``
    of ``harness.evaluate`` runs too (its rows are seeded per episode), one env per episode.
    """
    cfg = eval_config(cfg, episode_seconds)
    episodes = int(episodes or cfg.eval.episodes)
    seed = int(cfg.eval.seed if seed is None else seed)
    torch_run = harness.run_profile

    def run(cfg_, policy_, profile, *, episodes, seed, policy_factory=None, without=(), init_spacing=None):
        rows = None if init_spacing is None else [float(init_spacing)]
        ms, trs = [], []
        for s in episode_seeds(seed, episodes):
            m, tr = torch_run(cfg_, policy_, profile, episodes=1, seed=s, policy_factory=policy_factory,
                              without=tuple(without), init_spacing_rows=rows)
            ms.append(m)
            trs.append(tr)
        m = {k: torch.cat([x[k] for x in ms]) for k in ms[0]}
        tr = harness.Trace(**{f: torch.cat([getattr(t, f) for t in trs]) for f in harness.Trace.__dataclass_fields__})
        return m, tr

    report, traces = harness.evaluate(cfg, policy, policy_factory=policy_factory, profiles=profiles,
                                      episodes=episodes, seed=seed, runner=run)
    report.update(backend="torch", episode_seconds=float(cfg.eval.episode_seconds),
                  episode_seeds=episode_seeds(seed, episodes))
    return report, traces


def comparison_rows(reports: dict[str, dict]) -> list[dict]:
    """Per profile (and overall) the key metrics of each backend's report: ``{"profile", "<backend>": {...}}``."""
    first = next(iter(reports.values()))
    rows = []
    for prof in list(first["profiles"]) + ["overall"]:
        row = {"profile": prof}
        for name, rep in reports.items():
            if prof == "overall":
                ov = rep["overall"]
                row[name] = {"collisions": ov["collisions"], "min_gap": ov["min_gap"],
                             "max_head_gap": ov["max_head_gap"], "speed_rmse_steady": ov["speed_rmse_steady"],
                             "mean_abs_accel": ov["mean_abs_accel"], "return": ov["return"]}
            else:
                r = rep["profiles"][prof]
                m = r["metrics"]
                row[name] = {"collisions": r["collisions"], "min_gap": m["min_gap"]["min"],
                             "max_head_gap": m["max_head_gap"]["max"],
                             "speed_rmse_steady": m["speed_rmse_steady"]["mean"],
                             "mean_abs_accel": m["mean_abs_accel"]["mean"], "return": m["return"]["mean"]}
        rows.append(row)
    return rows


def comparison_markdown(reports: dict[str, dict]) -> str:
    """Markdown table: one line per profile and backend (min gap: min, max head gap: max, others: mean)."""
    head = ("| profile | backend | collisions | min gap (m) | max head gap (m) | steady RMSE (m/s) | "
            "mean abs a (m/s2) | return |")
    lines = [head, "|---|---|---|---|---|---|---|---|"]
    for row in comparison_rows(reports):
        for name in reports:
            v = row[name]
            lines.append(f"| {row['profile']} | {name} | {v['collisions']} | {v['min_gap']:.3f} | "
                         f"{v['max_head_gap']:.2f} | {v['speed_rmse_steady']:.3f} | {v['mean_abs_accel']:.3f} | "
                         f"{v['return']:.1f} |")
    return "\n".join(lines)


__all__ = ["evaluate_on_sumo", "evaluate_on_torch_seeds", "run_profile_sumo", "make_sumo_eval_env", "episode_seeds",
           "eval_config", "comparison_rows", "comparison_markdown", "DEFAULT_EPISODE_SECONDS"]
