"""Evaluation harness: deterministic episodes over head profiles, report.json/.md and plots.

>>> from mixed_traffic.config import compose
>>> from mixed_traffic.evaluation import evaluate_and_report
>>> cfg = compose(["experiment=ring_lagrangian_ppo", "controller=idm", "eval.episodes=2"])  # doctest: +SKIP
>>> paths = evaluate_and_report(cfg, out_dir="outputs/eval_idm")  # doctest: +SKIP
"""

from __future__ import annotations

from functools import partial
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from mixed_traffic.evaluation.background import Background
from mixed_traffic.evaluation.harness import METRICS, episode_metrics, evaluate, with_pass
from mixed_traffic.evaluation.policies import (
    checkpoint_config,
    classic_factory,
    policy_factory_from_state,
    residual_base_factory,
    zero_residual_factory,
)
from mixed_traffic.evaluation.report import plot_training_curves, read_scalars, write_report
from mixed_traffic.evaluation.results import ZERO_RESIDUAL
from mixed_traffic.validation import ConfigError


def evaluate_and_report(cfg: DictConfig, out_dir: str | Path, *, checkpoint: str | Path | None = None,
                        controller: str | None = None, title: str | None = None, deploy_overrides=()) -> dict:
    """Evaluate a checkpoint (its own env/transform config, with ``cfg.eval``) or a classical controller.

    ``deploy_overrides``: ``(key, value)`` pairs of the checkpoint's transforms to deploy it with
    (:func:`mixed_traffic.validation.parse_deploy_overrides`; ``mt-eval checkpoint=... transforms.KEY=VALUE``), a
    variant evaluated without retraining; the report names them.

    Returns the report dict with ``paths`` (report.json, report.md, plots).
    """
    checkpoint = checkpoint if checkpoint is not None else cfg.get("checkpoint")
    controller = controller if controller is not None else cfg.get("controller")
    if (checkpoint is None) == (controller is None):
        problem = ("neither checkpoint nor controller is set" if checkpoint is None
                   else f"both are set ({checkpoint!r} and controller={controller!r})")
        raise ConfigError("checkpoint", f"{problem}: give exactly one of the two",
                          "checkpoint=PATH (a run directory or a .pt), or controller=idm|ovm|soft|base|zero_residual "
                          "(NAME:key=number;... for parameters)")
    if deploy_overrides and checkpoint is None:
        raise ConfigError("transforms", "deploy-time overrides apply to a checkpoint", "checkpoint=PATH with "
                          "transforms.KEY=VALUE; a classical controller takes the experiment's transforms as composed")
    loaded = checkpoint_config(checkpoint) if checkpoint is not None else None  # read once: (its config, its state)
    own = loaded[0] if loaded is not None else cfg
    intersection = own.env.scenario == "intersection"
    waves = not intersection and is_wave_ring(own)
    if deploy_overrides and (intersection or waves):
        raise ConfigError(deploy_overrides[0][0], "deploy-time overrides apply to the ring's head-profile evaluation",
                          "no transforms.* override with an intersection or wave-ring checkpoint")
    if intersection:
        from mixed_traffic.intersection.evaluate import evaluate_run

        return evaluate_run(cfg, out_dir, checkpoint=checkpoint, controller=controller)
    if waves:
        return evaluate_waves_and_report(cfg, out_dir, checkpoint=checkpoint, controller=controller, title=title)
    run_dir = None
    if checkpoint is not None:
        run_cfg, state = loaded
        if deploy_overrides:
            from mixed_traffic.validation import with_deploy_overrides

            run_cfg = with_deploy_overrides(run_cfg, deploy_overrides)
        run_seconds, run_reference = run_cfg.eval.get("episode_seconds"), run_cfg.eval.get("reference")
        run_cfg.eval = cfg.eval  # evaluation settings come from the caller
        if cfg.eval.get("episode_seconds") is None and run_seconds is not None:
            run_cfg.eval.episode_seconds = run_seconds  # ... but a run's evaluation length is kept
        if cfg.eval.get("reference") is None and run_reference is not None:
            run_cfg.eval.reference = run_reference  # ... and the reference of its acceptance
        factory = policy_factory_from_state(run_cfg, state)
        label = str(checkpoint) + (" deployed with " + " ".join(f"{k}={v}" for k, v in deploy_overrides)
                                   if deploy_overrides else "")
        p = Path(checkpoint)
        run_dir = p if p.is_dir() else (p.parent.parent if p.parent.name == "checkpoints" else p.parent)
        eval_cfg = run_cfg
    else:
        if controller == ZERO_RESIDUAL:  # the experiment's deployed chain, cap and join included, its residual at 0
            try:
                factory = zero_residual_factory(cfg)  # refuses a chain without residual_idm
            except ValueError as e:
                raise ConfigError("controller", f"{ZERO_RESIDUAL!r}: {e}",
                                  f"{ZERO_RESIDUAL} with an experiment that trains a residual (e.g. "
                                  "experiment=ring_lagrangian_ppo_follow), or a classical controller (idm, ovm, soft, "
                                  "cacc)") from None
        elif controller == "base":  # the experiment's residual base driving alone: what the learned residual adds to
            try:
                factory = residual_base_factory(cfg)  # refuses a chain without residual_idm
            except ValueError as e:
                raise ConfigError("controller", f"'base': {e}",
                                  "base with an experiment that trains a residual (e.g. "
                                  "experiment=ring_lagrangian_ppo_band_stop), or a classical controller (idm, ovm, soft, cacc)"
                                  ) from None
        else:
            factory = classic_factory(controller)
        label = ZERO_RESIDUAL if controller == ZERO_RESIDUAL else f"{controller}-as-CAV"
        eval_cfg = cfg
        if "residual_idm" in cfg.transforms.chain and controller != ZERO_RESIDUAL:  # a classical controller drives the CAV
            eval_cfg = OmegaConf.create(OmegaConf.to_container(cfg, resolve=False))
            eval_cfg.transforms.chain = [c for c in cfg.transforms.chain if c != "residual_idm"]
    run = evaluate
    if cfg.env.backend == "sumo":  # the caller's choice: a checkpoint's own config says torch
        from mixed_traffic.evaluation.sumo import evaluate_on_sumo as run
    reference = eval_cfg.eval.get("reference") if checkpoint is not None else None
    if reference is not None:  # a bad name fails before any rollout
        try:
            ref_factory = classic_factory(reference)
        except ValueError:
            raise ConfigError("eval.reference", f"{reference!r} is not a classical controller",
                              "idm, ovm, soft, cacc (NAME:key=number;... for parameters, e.g. 'idm:s0=6'), "
                              "or null") from None
    ref_job = None
    if reference is not None:  # on the same episodes, in a second process beside the policy's rollout where it can
        beside = run is evaluate and bool(eval_cfg.eval.get("parallel_reference", True))
        ref_job = Background(partial(reference_report, eval_cfg, ref_factory, run, progress=not beside),
                             enabled=beside, name=f"the reference {reference}-as-CAV's evaluation")
    try:
        report, traces = run(eval_cfg, policy_factory=factory)
    except BaseException:
        if ref_job is not None:
            ref_job.cancel()
        raise
    if ref_job is not None:
        report["reference"] = against_reference(eval_cfg, report, reference, ref_job.result())
        report["acceptance"].update(reference_bars(report["reference"]))
        with_pass(report["acceptance"])
    report["policy"] = label
    report["env"] = OmegaConf.to_container(eval_cfg.env, resolve=True)
    report["transforms"] = list(eval_cfg.transforms.chain)
    if deploy_overrides:
        report["deploy_overrides"] = {k: v for k, v in deploy_overrides}
    if "safety_layer" in eval_cfg.transforms.chain:  # the layer as it was deployed here (noise margins aside)
        from mixed_traffic.training.builders import safety_layer_settings

        report["safety_layer"] = safety_layer_settings(eval_cfg.transforms.safety_layer, deploy=True)
    paths = write_report(report, out_dir, traces, title=title or label, plot_episode=cfg.eval.plot_episode,
                         s_min=cfg.eval.s_min, s_max=cfg.eval.s_max, run_dir=run_dir)
    report["paths"] = {k: str(v) for k, v in paths.items()}
    return report


def classical_chain(chain, *, layer: bool = False) -> list[str]:
    """The transforms a classical controller runs under when it stands beside a run's policy: the run's reward
    transforms (``*_reward``, so that its return is the task's), and its ``safety_layer`` where ``layer``, in the
    run's order; no residual, no training-only shaping, no constraint cost.

    >>> classical_chain(["onboard_accel", "non_negative_reward", "safety_layer", "residual_idm", "jerk_penalty"])
    ['non_negative_reward']
    >>> classical_chain(["non_negative_reward", "safety_layer", "residual_idm"], layer=True)
    ['non_negative_reward', 'safety_layer']
    """
    return [t for t in chain if t.endswith("_reward") or (layer and t == "safety_layer")]


def reference_report(cfg: DictConfig, factory, run=evaluate, *, progress: bool = True) -> dict:
    """The report of the classical controller of ``factory`` (:func:`~mixed_traffic.evaluation.policies.classic_factory`'s)
    on the episodes of ``cfg`` (the policy's evaluated config) with the chain cut to its reward transforms (no layer,
    no residual), run by ``run``: what :func:`against_reference` compares the policy with."""
    ref_cfg = OmegaConf.create(OmegaConf.to_container(cfg, resolve=False))
    ref_cfg.transforms.chain = classical_chain(cfg.transforms.chain)
    ref_cfg.eval.without_layer = False
    if not progress:
        ref_cfg.trainer.progress = False
    return run(ref_cfg, policy_factory=factory)[0]


def against_reference(cfg: DictConfig, report: dict, name: str, ref_report: dict) -> dict:
    """The policy's jerk and return beside those of the classical controller ``name`` on the same episodes, from its
    :func:`reference_report` ``ref_report``. Per profile of ``report``: the reference's mean ``|jerk|`` and return,
    its collisions, and for the policy with the layer (``"with the layer"``, or ``"policy"`` without a layer in the
    chain) and without it from the standard start (``"without the layer"``) its own, the jerk in % of the
    reference's and the return's difference."""
    layered = "with the layer" if "safety_layer" in cfg.transforms.chain else "policy"
    out = {}
    for prof, entry in report["profiles"].items():
        r = ref_report["profiles"][prof]
        ref = {"jerk": r["metrics"]["mean_abs_jerk"]["mean"], "return": r["metrics"]["return"]["mean"]}
        rows = {layered: entry}
        free = (report.get("without_layer") or {}).get(prof)
        if free:
            rows["without the layer"] = free[next(iter(free))]  # the standard start
        out[prof] = {"reference": {**ref, "collisions": r["collisions"]}}
        for label, e in rows.items():
            jerk, ret = e["metrics"]["mean_abs_jerk"]["mean"], e["metrics"]["return"]["mean"]
            out[prof][label] = {"jerk": jerk, "return": ret, "jerk_pct": 100.0 * (jerk / ref["jerk"] - 1.0),
                                "return_diff": ret - ref["return"]}
    return {"controller": f"{name}-as-CAV", "profiles": out}


def policy_rows(profiles: dict) -> list[dict]:
    """The policy's rows of :func:`against_reference`'s ``profiles`` (or some of them), every profile's with and
    without the layer: what the reference's bars judge and ``mt-main`` sums up."""
    return [v for e in profiles.values() for k, v in e.items() if k != "reference"]


def reference_bars(comparison: dict) -> dict:
    """The acceptance's bars against the reference (:func:`against_reference`'s ``comparison``): on every profile
    where the reference completes its episodes without a collision, the policy's jerk at most its and the return at
    least its, with the layer and without it (a reference that collides is no yardstick: that profile is left out
    and named)."""
    judged = {p: e for p, e in comparison["profiles"].items() if e["reference"]["collisions"] == 0}
    rows = policy_rows(judged)
    bars = {"jerk_within_reference": all(r["jerk_pct"] <= 0.0 for r in rows),
            "return_within_reference": all(r["return_diff"] >= 0.0 for r in rows)}
    skipped = sorted(set(comparison["profiles"]) - set(judged))
    if skipped:
        bars["reference_collided_on"] = ", ".join(skipped)
    return bars


def is_wave_ring(cfg: DictConfig) -> bool:
    """Whether ``cfg.env`` is a ring without a head (the stop-and-go wave report applies)."""
    from mixed_traffic.scenarios import PRESETS, get_scenario
    from mixed_traffic.training.builders import env_kwargs

    if cfg.env.scenario not in PRESETS:
        return False
    kw = env_kwargs(cfg.env)
    head = kw.get("head", PRESETS[cfg.env.scenario]().head)
    return get_scenario(cfg.env.scenario, **kw).is_ring and not head


def evaluate_waves_and_report(cfg: DictConfig, out_dir: str | Path, *, checkpoint=None, controller=None,
                              title: str | None = None) -> dict:
    """The wave report (:mod:`mixed_traffic.evaluation.waves`) of a checkpoint against the classical
    dampers of ``cfg.eval.wave.controllers``, or of ``controller`` (a name of
    :data:`mixed_traffic.controllers.dampers.DAMPERS`, or ``all`` for the whole list)."""
    from mixed_traffic.evaluation.waves import acceptance, evaluate_waves, write_wave_report

    if checkpoint is not None:
        run_cfg, state = checkpoint_config(checkpoint)
        run_cfg.eval = cfg.eval
        run_cfg.env.backend = cfg.env.backend  # the caller's choice: a policy trained on torch, evaluated in SUMO
        report, traces = evaluate_waves(run_cfg, policy_factory=policy_factory_from_state(run_cfg, state))
        report["acceptance"] = acceptance(report)
        label, eval_cfg = str(checkpoint), run_cfg
    else:
        names = None if controller == "all" else [controller]
        report, traces = evaluate_waves(cfg, controllers=names)
        label, eval_cfg = str(controller), cfg
    report["policy"] = label
    report["env"] = OmegaConf.to_container(eval_cfg.env, resolve=True)
    report["transforms"] = list(eval_cfg.transforms.chain)
    paths = write_wave_report(report, traces, out_dir, title=title or f"Stop-and-go waves: {label}")
    report["paths"] = {k: str(v) for k, v in paths.items()}
    report["overall"] = {"collisions": sum(r["collisions"] for e in report["rings"].values()
                                           for r in e["controllers"].values())}
    return report


__all__ = ["against_reference", "reference_report", "classical_chain", "policy_rows", "reference_bars", "is_wave_ring", "evaluate_waves_and_report", "evaluate", "evaluate_and_report", "episode_metrics", "write_report", "plot_training_curves",
           "read_scalars", "METRICS"]
