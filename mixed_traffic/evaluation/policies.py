"""Turn a checkpoint (or a classical controller name) into an evaluation policy."""

from __future__ import annotations

import sys
from pathlib import Path

from omegaconf import DictConfig, OmegaConf
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey

from mixed_traffic.training.checkpoint import load_checkpoint


def checkpoint_config(path: str | Path) -> tuple[DictConfig, dict]:
    """The run config stored in a checkpoint (final.pt, checkpoints/latest.pt or a run directory)."""
    p = Path(path)
    if p.is_dir() and (p / "final.pt").is_file():
        p = p / "final.pt"
    state = load_checkpoint(p, field="checkpoint")
    if "iteration" in state:  # a periodic checkpoint: say so, the numbers are not the final policy's
        total = state["config"].get("trainer", {}).get("total_frames", "?")
        print(f"note: checkpoint={str(path)!r} is a mid-run checkpoint (iteration {state['iteration']}, "
              f"{state.get('frames', '?')} of {total} frames): the run has no final.pt yet", file=sys.stderr)
    return with_schema_defaults(state["config"]), state


def with_schema_defaults(stored: dict) -> DictConfig:
    """A stored run config with the fields added to the schemas since it was saved.

    A checkpoint keeps the config of its run; a field that a later version added (a new
    transform option, say) is missing from it, and the builders that read the field would
    fail with "Missing key". Each group whose schema is known is merged onto the schema's
    defaults, so old checkpoints load with the new field at its default (which reproduces
    the old behaviour). A group that does not fit its schema is kept as stored.
    """
    from mixed_traffic import config as C

    schemas = {"env": C.EnvConfig, "transforms": C.TransformsConfig, "policy": C.PolicyConfig,
               "eval": C.EvalConfig, "logger": C.LoggerConfig}
    loss = stored.get("loss") or {}
    schemas["loss"] = {"ppo": C.PPOLossConfig, "lagrangian_ppo": C.PPOLossConfig, "dqn": C.DQNLossConfig,
                       "q_learning": C.QLearningLossConfig}.get(loss.get("name"))
    out = dict(stored)
    for key, schema in schemas.items():
        if schema is None or not isinstance(stored.get(key), dict):
            continue
        try:
            merged = OmegaConf.merge(OmegaConf.structured(schema), stored[key])
            out[key] = OmegaConf.to_container(merged, resolve=False)
        except Exception:  # noqa: BLE001 - an older or foreign layout: keep it as stored
            pass
    return OmegaConf.create(out)


def policy_factory_from_state(cfg: DictConfig, state: dict):
    """A ``factory(env) -> deterministic policy`` rebuilding the trained network for any eval env."""
    kind = state.get("kind", "ppo")

    def factory(env):
        if kind == "ppo":
            from mixed_traffic.training.on_policy import build_ppo

            actor, _, loss, _, _ = build_ppo(cfg, env)
            if "actor" in state:
                actor.load_state_dict(state["actor"])
            else:  # a mid-run checkpoint: the loss module holds the actor's weights
                loss.load_state_dict(state["model"], strict=False)
            return actor
        if kind == "dqn":
            from mixed_traffic.training.off_policy import build_dqn_policy

            return build_dqn_policy(cfg, env, state)
        if kind == "q_table":
            from mixed_traffic.training.tabular import build_table_policy

            return build_table_policy(cfg, env, state)
        raise ValueError(f"checkpoint kind {kind!r} is invalid; allowed: 'ppo', 'dqn', 'q_table'")

    return factory


def residual_base_factory(cfg):
    """``factory(env)`` for the classical base of ``cfg.transforms.residual`` driving alone (the learned
    residual at zero): what the policy adds is measured against it on the same episodes."""
    from mixed_traffic.training.builders import residual_base

    if "residual_idm" not in cfg.transforms.chain:
        raise ValueError(f"the run has no residual base: transforms.chain {list(cfg.transforms.chain)} lacks "
                         "residual_idm")
    rcfg = cfg.transforms.residual
    return lambda env: residual_base(rcfg, env)


class ZeroAction(TensorDictModuleBase):
    """Writes an all-zero action of ``action_spec`` on every step.

    Through a chain with a learned residual (``residual_idm``) the CAV then drives by the deployed classical part
    alone: the base's laws, stopping envelope and catch-up, and the drive-off cap and join, which act on the base
    plus the residual. TorchRL has no constant-action policy (``RandomPolicy`` samples its spec), hence this one.

    >>> from mixed_traffic import make_env
    >>> env = make_env("ring", batch_size=2, seed=0)
    >>> ZeroAction(env.action_spec)(env.reset())["action"].abs().sum().item()
    0.0
    """

    def __init__(self, action_spec, action_key: NestedKey = "action"):
        super().__init__()
        self.action_spec = action_spec
        self.in_keys, self.out_keys = [], [action_key]

    def forward(self, tensordict):
        return tensordict.set(self.out_keys[0], self.action_spec.zero())


def zero_residual_factory(cfg):
    """``factory(env)`` for :class:`ZeroAction` behind ``cfg``'s chain, which must carry the learned residual
    (``residual_idm``): what the policy adds to its deployed classical part is measured against it on the same
    episodes, with the drive-off cap and the join acting on both (:func:`residual_base_factory` drives the base's
    laws alone, without them)."""
    if "residual_idm" not in cfg.transforms.chain:
        raise ValueError(f"the run has no learned residual: transforms.chain {list(cfg.transforms.chain)} lacks "
                         "residual_idm")
    return lambda env: ZeroAction(env.action_spec)


def classic_factory(name: str):
    """``factory(env)`` for ``controller=NAME`` or ``NAME:param=value[;param=value]`` (``"idm:s0=6"``)."""
    from mixed_traffic.controllers.classic import make_classic_policy
    from mixed_traffic.evaluation.waves import parse_controller

    model, params = parse_controller(name, field="controller")
    try:  # bad names and values fail here, before any rollout
        make_classic_policy(model, low=-1.0, high=1.0, **params)
    except ValueError as e:
        raise ValueError(f"controller={name!r}: {e}") from None
    return lambda env: make_classic_policy(model, env, **params)


