"""Training loops (on-policy PPO / Lagrangian PPO, off-policy DQN, tabular Q) and their bookkeeping.

>>> from mixed_traffic.config import compose
>>> from mixed_traffic.training import train
>>> cfg = compose(["experiment=ring_lagrangian_ppo", "trainer.total_frames=4096"])  # doctest: +SKIP
>>> result = train(cfg, out_dir="outputs/tmp")  # doctest: +SKIP
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from mixed_traffic.training.run import set_threads

TRAINERS = ("on_policy", "off_policy", "tabular")
LOSSES_OF = {"on_policy": ("ppo", "lagrangian_ppo"), "off_policy": ("dqn",), "tabular": ("q_learning",)}


def check_config(cfg: DictConfig) -> None:
    """Cross-group checks Hydra's schema cannot express (fail before any work)."""
    kind = cfg.trainer.kind
    if kind not in TRAINERS:
        raise ValueError(f"trainer.kind={kind!r} is invalid; allowed: {list(TRAINERS)}")
    if cfg.loss.name not in LOSSES_OF[kind]:
        raise ValueError(f"loss={cfg.loss.name!r} does not go with trainer={kind!r}; allowed losses: "
                         f"{list(LOSSES_OF[kind])} (pick an experiment=..., e.g. ring_dqn, to switch both)")
    from mixed_traffic.training.builders import check_chain

    check_chain(cfg.transforms.chain)
    for k in ("total_frames", "num_envs", "rollout_len"):
        if int(cfg.trainer[k]) < 1:
            raise ValueError(f"trainer.{k}={cfg.trainer[k]!r} is invalid; allowed: >= 1")


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
        print(f"resuming from {path} (iteration {state['iteration']}, {state['frames']} frames); writing to {out_dir}")
    if out_dir is None:
        try:
            out_dir = cfg.out_dir
        except Exception as e:  # outside a Hydra app `${hydra:...}` does not resolve
            raise ValueError("train: pass out_dir=... when calling outside a Hydra app") from e
    out_dir = Path(out_dir)
    cfg.out_dir = str(out_dir)  # resolved here, so the stored config does not depend on Hydra's runtime
    kind = cfg.trainer.kind
    if kind == "on_policy":
        from mixed_traffic.training.on_policy import train_on_policy as fn
    elif kind == "off_policy":
        from mixed_traffic.training.off_policy import train_off_policy as fn
    else:
        from mixed_traffic.training.tabular import train_tabular as fn
    return fn(cfg, out_dir, resume=state)


__all__ = ["train", "check_config", "TRAINERS"]
