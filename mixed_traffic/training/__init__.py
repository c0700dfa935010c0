"""Training loops (on-policy PPO / Lagrangian PPO, off-policy DQN, tabular Q) and their bookkeeping.

>>> from mixed_traffic.config import compose
>>> from mixed_traffic.training import train
>>> cfg = compose(["experiment=ring_lagrangian_ppo", "trainer.total_frames=4096"])  # doctest: +SKIP
>>> result = train(cfg, out_dir="outputs/tmp")  # doctest: +SKIP
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from mixed_traffic.training.run import set_threads

TRAINERS = ("on_policy", "off_policy", "tabular")
LOSSES_OF = {"on_policy": ("ppo", "lagrangian_ppo"), "off_policy": ("dqn",), "tabular": ("q_learning",)}


def check_config(cfg: DictConfig) -> None:
    """Every check that can run before any work: field ranges, the scenario, cross-group rules."""
    from mixed_traffic.validation import ConfigError, check_env_config, validate_config

    validate_config(cfg)
    kind = cfg.trainer.kind
    if kind not in TRAINERS:
        raise ConfigError("trainer.kind", f"unknown value {kind!r}", str(list(TRAINERS)))
    if cfg.loss.name not in LOSSES_OF[kind]:
        raise ValueError(f"loss: {cfg.loss.name!r} does not go with trainer={kind!r}; allowed losses: "
                         f"{list(LOSSES_OF[kind])} (pick an experiment=..., e.g. ring_dqn, to switch both)")
    from mixed_traffic.training.builders import check_chain, check_collector_config

    check_chain(cfg.transforms.chain)
    check_collector_config(cfg)
    pretrain_only = kind == "on_policy" and (int(cfg.policy.get("apg", {}).get("iterations", 0) or 0) > 0
                                        or int(cfg.policy.get("cem", {}).get("generations", 0) or 0) > 0)
    for k in ("total_frames", "num_envs", "rollout_len"):
        if int(cfg.trainer[k]) < (0 if k == "total_frames" and pretrain_only else 1):
            raise ConfigError(f"trainer.{k}", f"{cfg.trainer[k]!r} is out of range",
                              "an integer >= 1 (total_frames >= 0 with policy.apg.iterations > 0 or policy.cem.generations > 0)"
                              if k == "total_frames" else "an integer >= 1")
    check_env_config(cfg)


#: keys a resumed run may change freely (budgets, bookkeeping); everything else must match the checkpoint
RESUME_FREE = ("resume", "resume_override", "out_dir", "threads", "checkpoint", "controller", "trainer.progress",
               "trainer.collector", "trainer.ray_address",
               "trainer.max_minutes", "trainer.max_iterations", "trainer.checkpoint_every", "trainer.log_every",
               "eval.")
#: keys the saved state depends on (network shapes, env batch, collector carrier): never changed on resume
RESUME_FIXED = ("env.", "policy.", "transforms.", "trainer.kind", "trainer.num_envs", "trainer.rollout_len",
                "loss.name", "device", "seed")


def _flat(d, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict) and v:
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def resume_differences(cfg: DictConfig, stored: dict) -> dict[str, tuple]:
    """``{key: (stored, new)}`` of the keys where ``cfg`` and a checkpoint's config differ (free keys left out)."""
    cfg = cfg.copy()
    cfg.out_dir = ""  # `${hydra:...}` resolves only inside a Hydra app; out_dir is free anyway
    new = _flat(OmegaConf.to_container(cfg, resolve=True))
    old = _flat(stored)
    keys = sorted(set(new) | set(old))
    return {k: (old.get(k, "<absent>"), new.get(k, "<absent>")) for k in keys
            if not k.startswith(RESUME_FREE) and old.get(k, "<absent>") != new.get(k, "<absent>")}


def check_resume(cfg: DictConfig, state: dict, path: Path) -> dict[str, tuple]:
    """Refuse a resume whose config differs from the checkpoint's (unless ``resume_override=true``)."""
    from mixed_traffic.validation import ConfigError

    diff = resume_differences(cfg, state["config"])
    if not diff:
        return diff

    def listing(keys):
        shown = [f"{k} ({diff[k][0]!r} -> {diff[k][1]!r})" for k in keys[:12]]
        return ", ".join(shown) + (f" and {len(keys) - 12} more" if len(keys) > 12 else "")

    fixed = [k for k in diff if k.startswith(RESUME_FIXED)]
    if fixed:
        raise ConfigError("resume", f"the checkpoint {str(path)!r} was trained with other values of "
                          f"{listing(fixed)}, which its saved state depends on",
                          "the run's own values (its config.yaml); start a new run to change them")
    if not cfg.get("resume_override", False):
        raise ConfigError("resume", f"the command line differs from the checkpoint {str(path)!r} in {listing(list(diff))}",
                          "the run's own values (its config.yaml), or resume_override=true to continue with the new ones")
    return diff


def check_fresh_out_dir(out_dir: Path) -> None:
    """A new run never writes into a directory that holds another run's results."""
    from mixed_traffic.validation import ConfigError

    held = [n for n in ("final.pt", "summary.json", "checkpoints/latest.pt") if (out_dir / n).exists()]
    logs = out_dir / "logs"
    if logs.is_dir() and any(p.is_file() for p in logs.rglob("*")):
        held.append("logs/")
    if held:
        raise ConfigError("out_dir", f"{str(out_dir)!r} already holds a run ({', '.join(held)})",
                          f"a new directory, or resume={str(out_dir)!r} to continue that run")


def train(cfg: DictConfig, out_dir: str | Path | None = None, resume: str | Path | None = None) -> dict:
    """Run the loop chosen by ``cfg.trainer.kind``; returns the summary, the trained policy and paths."""
    check_config(cfg)
    set_threads(cfg.threads)
    state = None
    resume = resume if resume is not None else cfg.get("resume")
    if resume:
        from mixed_traffic.training.checkpoint import load_checkpoint, resolve_checkpoint

        path = resolve_checkpoint(resume)
        state = load_checkpoint(path)
        out_dir = path.parent.parent if path.parent.name == "checkpoints" else path.parent
        diff = check_resume(cfg, state, path)
        print(f"resuming from {path} (iteration {state['iteration']}, {state['frames']} frames); writing to {out_dir}")
        if diff:
            print(f"resume_override=true: continuing with new values of {sorted(diff)} "
                  f"(saved as config.resumed_{state['iteration']}.yaml)")
    if out_dir is None:
        try:
            out_dir = cfg.out_dir
        except Exception as e:  # outside a Hydra app `${hydra:...}` does not resolve
            raise ValueError("out_dir: unknown outside a Hydra app; allowed: train(cfg, out_dir=...)") from e
    out_dir = Path(out_dir)
    if state is None:
        check_fresh_out_dir(out_dir)
    else:
        from mixed_traffic.training.run import trim_scalars

        trim_scalars(out_dir, state["frames"])  # rows logged after the checkpoint are logged again
    from mixed_traffic.validation import check_writable_dir

    check_writable_dir("out_dir", out_dir)
    if state is not None:
        cfg.resume = str(resume)
    cfg.out_dir = str(out_dir)  # resolved here, so the stored config does not depend on Hydra's runtime
    if state is not None and (out_dir / "config.yaml").exists():
        new = OmegaConf.to_yaml(cfg, resolve=True)
        if new != (out_dir / "config.yaml").read_text():
            (out_dir / f"config.resumed_{state['iteration']}.yaml").write_text(new)
    kind = cfg.trainer.kind
    if kind == "on_policy":
        from mixed_traffic.training.on_policy import train_on_policy as fn
    elif kind == "off_policy":
        from mixed_traffic.training.off_policy import train_off_policy as fn
    else:
        from mixed_traffic.training.tabular import train_tabular as fn
    return fn(cfg, out_dir, resume=state)


__all__ = ["train", "check_config", "check_resume", "resume_differences", "TRAINERS"]
