"""Validation at the door: one error type, one message style, one table of field rules.

Every user mistake is turned into a :class:`ConfigError` (a ``ValueError``) before any
work starts, with the message ``<field>: <what is wrong>; allowed: <range>``. The apps
print it as ``error: <message>`` and exit with status 2 (:func:`run_cli`); set
``MT_DEBUG=1`` to get the traceback instead.

Adding a config field with a range: add one line to :data:`CONFIG_RULES` (dotted path ->
rule). Fields without a rule still get the generic check that every float of the
config is finite. Scenario fields are checked by
:meth:`mixed_traffic.scenarios.TrafficScenario.validate` (types from the dataclass
annotations, so a new scenario field is type- and finiteness-checked without code).

>>> from mixed_traffic.config import compose
>>> validate_config(compose(["loss.gamma=1.5"]))
Traceback (most recent call last):
...
mixed_traffic.validation.ConfigError: loss.gamma: 1.5 is out of range; allowed: a number in (0, 1]
"""

from __future__ import annotations

import math
import numbers
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from omegaconf import DictConfig, ListConfig, OmegaConf

from mixed_traffic.config import SPEED_LAWS, TransformsConfig

DEBUG_ENV = "MT_DEBUG"


class ConfigError(ValueError):
    """A bad value: ``<field>: <problem>; allowed: <allowed>``."""

    def __init__(self, field: str, problem: str, allowed: str):
        self.field, self.problem, self.allowed = field, problem, allowed
        super().__init__(f"{field}: {problem}; allowed: {allowed}")


# ----------------------------------------------------------------------------- single values
def is_real(x) -> bool:
    return isinstance(x, numbers.Real) and not isinstance(x, bool)


@dataclass(frozen=True)
class Real:
    """A finite number in ``[lo, hi]`` (``lo_open`` / ``hi_open`` exclude the ends); ``None`` if ``optional``."""

    lo: float = -math.inf
    hi: float = math.inf
    lo_open: bool = False
    hi_open: bool = False
    optional: bool = False
    integer: bool = False

    def describe(self) -> str:
        def g(v):
            return str(int(v)) if float(v).is_integer() and abs(v) < 1e21 else f"{v:g}"

        kind = "an integer" if self.integer else "a number"
        if self.lo == -math.inf and self.hi == math.inf:
            rng = f"{kind} (finite)"
        elif self.hi == math.inf:
            rng = f"{kind} {'>' if self.lo_open else '>='} {g(self.lo)}"
        elif self.lo == -math.inf:
            rng = f"{kind} {'<' if self.hi_open else '<='} {g(self.hi)}"
        else:
            rng = f"{kind} in {'(' if self.lo_open else '['}{g(self.lo)}, {g(self.hi)}{')' if self.hi_open else ']'}"
        return rng + (" or null" if self.optional else "")

    def __call__(self, field: str, x) -> None:
        if x is None:
            if self.optional:
                return
            raise ConfigError(field, "is missing (null)", self.describe())
        if not is_real(x) or (self.integer and not isinstance(x, numbers.Integral)):
            raise ConfigError(field, f"{x!r} is a {type(x).__name__}", self.describe())
        if not math.isfinite(x):
            raise ConfigError(field, f"{x!r} is not finite", self.describe())
        lo_bad = x <= self.lo if self.lo_open else x < self.lo
        hi_bad = x >= self.hi if self.hi_open else x > self.hi
        if lo_bad or hi_bad:
            raise ConfigError(field, f"{x!r} is out of range", self.describe())


def Int(lo: float = -math.inf, hi: float = math.inf, optional: bool = False) -> Real:  # noqa: N802
    return Real(lo, hi, optional=optional, integer=True)


@dataclass(frozen=True)
class OneOf:
    choices: tuple

    def __call__(self, field: str, x) -> None:
        if x not in self.choices:
            raise ConfigError(field, f"unknown value {x!r}", str(list(self.choices)))


# ----------------------------------------------------------------------------- the config table
#: dotted config path -> rule. Paths absent from a config (another loss / trainer) are skipped.
CONFIG_RULES: dict[str, Callable] = {
    "seed": Int(0, 2**63 - 1),
    "threads": Int(0),
    "resume_override": OneOf((True, False)),
    "env.backend": OneOf(("torch", "sumo")),
    "env.episode_seconds": Real(0, lo_open=True, optional=True),
    "env.weight_v": Real(0, optional=True),
    "env.weight_s": Real(0, optional=True),
    "env.weight_u": Real(0, optional=True),
    "env.s_min": Real(0, lo_open=True, optional=True),
    "env.s_max": Real(0, lo_open=True, optional=True),
    "env.hdv_param_noise": Real(0, 1, hi_open=True, optional=True),
    "transforms.safety_layer.s_min": Real(0, lo_open=True),
    "transforms.safety_layer.s_max": Real(0, lo_open=True, optional=True),  # null: no head-gap bound
    "transforms.safety_layer.mode": OneOf(("stopping", "one_step")),
    "transforms.safety_layer.beyond_s_max": OneOf(("push", "hold", "ramp", "recover")),
    "transforms.safety_layer.deployed_beyond_s_max": OneOf((None, "push", "hold", "ramp", "recover")),
    "transforms.safety_layer.deployed_s_max": OneOf((True, False)),
    "transforms.safety_layer.ramp_jerk": Real(0, lo_open=True),
    "transforms.safety_layer.recover_seconds": Real(0, lo_open=True),
    "transforms.safety_layer.hold_seconds": Real(0),
    "transforms.intervention_cost.coef": Real(0, lo_open=True),
    "transforms.intervention_cost.mode": OneOf(("magnitude", "indicator", "both")),
    "transforms.intervention_cost.direction": OneOf(("both", "brake", "push")),
    "transforms.residual.base": OneOf(("idm", "ovm", "soft", "cacc")),
    **{f"transforms.residual.{key}.base": OneOf(("idm", "ovm", "soft", "cacc", None)) for key in SPEED_LAWS},
    **{f"transforms.residual.{key}.v_low": Real(0) for key in SPEED_LAWS},
    **{f"transforms.residual.{key}.brake_floor": Real(0, lo_open=True, optional=True) for key in SPEED_LAWS},
    **{f"transforms.residual.{key}.brake_margin": Real(0) for key in SPEED_LAWS},
    "transforms.residual.weight": Real(0),
    "transforms.residual.saturate_base": OneOf((True, False)),
    "transforms.residual.stop_gap": Real(0, lo_open=True, optional=True),
    "transforms.residual.arrive_gain": Real(0, lo_open=True, optional=True),
    "transforms.residual.envelope_fade": OneOf(("off", "always", "deploy")),
    "transforms.residual.envelope_fade_slack": Real(0, lo_open=True, optional=True),
    "transforms.residual.envelope_fade_slack_below": Real(0, lo_open=True, optional=True),
    "transforms.residual.envelope_fade_slack_brake": Real(0, lo_open=True, optional=True),
    "transforms.residual.catch_up.accel": Real(0, lo_open=True, optional=True),
    "transforms.residual.catch_up.dv": Real(0, lo_open=True),
    "transforms.residual.catch_up.horizon": Real(0),
    "transforms.residual.catch_up.when": OneOf(("always", "deploy")),
    "transforms.residual.feed_forward.gain": Real(0, 1, lo_open=True, optional=True),
    "transforms.residual.feed_forward.accel_max": Real(0, 10, lo_open=True),
    "transforms.residual.feed_forward.when": OneOf(("always", "deploy")),
    "transforms.residual.stand_arrival.stand_gap": Real(0, lo_open=True, optional=True),
    "transforms.residual.stand_arrival.slack": Real(0, lo_open=True),
    "transforms.residual.stand_arrival.leader_brake": Real(0, lo_open=True, optional=True),
    "transforms.residual.drive_off.gain": Real(0, 20, lo_open=True, optional=True),
    "transforms.residual.drive_off.overspeed": Real(0, 5),
    "transforms.residual.drive_off.accel": Real(0, 10, lo_open=True),
    "transforms.residual.drive_off.release": Real(0, 600, lo_open=True),
    "transforms.residual.drive_off.standstill": Real(0, 5, lo_open=True),
    "transforms.residual.drive_off.when": OneOf(("always", "deploy")),
    "transforms.residual.drive_off.residual_play": Real(0, 3, lo_open=True, optional=True),
    "transforms.residual.drive_off.residual_play_release": Real(0, 600, lo_open=True, optional=True),
    "transforms.residual.drive_off.follow": Real(0, 1.5, lo_open=True, optional=True),
    "transforms.residual.drive_off.follow_above": Real(0, 3),
    "transforms.residual.join.gap": Real(0, 200, lo_open=True),
    "transforms.residual.join.fade": Real(0, 600, lo_open=True),
    "transforms.residual.join.seconds": Real(0, 3600, lo_open=True, optional=True),
    "transforms.residual.join.when": OneOf(("always", "deploy")),
    "transforms.residual.answer.horizon": Real(0, 120, lo_open=True, optional=True),
    "transforms.residual.answer.horizon_min": Real(0, 120, lo_open=True),
    "transforms.residual.answer.start": Real(0, 10),
    "transforms.residual.answer.done": Real(0, 10),
    "transforms.residual.answer.ks_edge": Real(0, 5),
    "transforms.residual.answer.when": OneOf(("always", "deploy")),
    "transforms.jerk_limit.max_jerk": Real(0, lo_open=True),
    "transforms.jerk_penalty.weight": Real(0),
    "transforms.discretizer.state_bins": Int(2),
    "transforms.discretizer.action_bins": Int(2),
    "policy.log_std_min": Real(),
    "policy.log_std_max": Real(),
    "loss.gamma": Real(0, 1, lo_open=True),
    "loss.gae_lambda": Real(0, 1),
    "loss.clip_epsilon": Real(0, lo_open=True),
    "loss.entropy_coeff": Real(0),
    "loss.critic_coeff": Real(0),
    "loss.clip_value": Real(0, lo_open=True, optional=True),
    "loss.lambda_init": Real(0),
    "loss.lambda_lr": Real(0),
    "loss.lambda_max": Real(0),
    "loss.lambda_method": OneOf(("dual_ascent", "adam", "sgd", "pid")),
    "loss.lambda_kp": Real(0),
    "loss.lambda_kd": Real(0),
    "loss.critics": OneOf((1, 2)),
    "loss.reward_scale": Real(0, lo_open=True),
    "loss.residual_coeff": Real(0),
    "loss.bc.coeff": Real(0),
    "loss.bc.final_coeff": Real(0, optional=True),
    "loss.bc.pretrain_steps": Int(0),
    "loss.bc.pretrain_lr": Real(0, lo_open=True),
    "loss.bc.expert": OneOf(("nmpc",)),
    "loss.bc.episodes": Int(1),
    "policy.features": OneOf(("none", "intersection")),
    "transforms.barrier_force.rho": Real(0),
    "transforms.barrier_force.K": Real(0),
    "transforms.residual_nmpc.weight": Real(0, lo_open=True),
    "transforms.conflict_cost.anticipation": Real(0),
    "transforms.conflict_cost.horizon_s": Real(0),
    "transforms.conflict_cost.out_of_bounds": Real(0),
    "loss.tau": Real(0, 1, lo_open=True),
    "loss.alpha": Real(0, 1, lo_open=True),
    "trainer.total_frames": Int(0),  # 0: no training (a pure-MPC intersection experiment); ring loops need >= 1
    "trainer.num_envs": Int(1),
    "trainer.rollout_len": Int(1),
    "trainer.collector": OneOf(("single", "multi_sync", "multi_async", "ray")),
    "trainer.collector_workers": Int(1),
    "trainer.checkpoint_every": Int(0),
    "trainer.log_every": Int(1),
    "trainer.max_minutes": Real(0, lo_open=True, optional=True),
    "trainer.max_iterations": Int(1, optional=True),
    "trainer.lr": Real(0, lo_open=True),
    "trainer.epochs": Int(1),
    "trainer.minibatch_size": Int(1),
    "trainer.max_grad_norm": Real(0, lo_open=True),
    "trainer.buffer_size": Int(1),
    "trainer.batch_size": Int(1),
    "trainer.start_learning_after": Int(0),
    "trainer.updates_per_batch": Int(1),
    "trainer.target_update_every": Int(1),
    "trainer.eps_start": Real(0, 1),
    "trainer.eps_end": Real(0, 1),
    "trainer.eps_decay_frames": Int(1),
    "logger.backend": OneOf(("csv", "wandb", "none")),
    "logger.mode": OneOf(("offline", "online", "disabled")),
    "eval.episodes": Int(1),
    "eval.seed": Int(0, 2**63 - 1),
    "eval.episode_seconds": Real(0, lo_open=True, optional=True),
    "eval.hdv_param_noise": Real(0, 1, hi_open=True, optional=True),
    "eval.settle_seconds": Real(0),
    "eval.warmup_seconds": Real(0),
    "eval.plot_episode": Int(0),
    "eval.intervention_bar": Real(0, 1),
    "eval.v2v_delay": Real(0, 10),
    "eval.v2v_loss": Real(0, 1),
    "eval.sensor_noise_gap": Real(0, 10),
    "eval.sensor_noise_speed": Real(0, 5),
    "eval.sensor_noise_tau": Real(0, 60),
    "eval.sensor_noise_margin": Real(0, 10),
    "eval.sensor_filter_gap": Real(0, 10, optional=True),
    "eval.sensor_filter_speed": Real(0, 5, optional=True),
    "eval.sensor_filter_tau": Real(0, 60, optional=True),
    "transforms.safety_layer.gap_margin": Real(0, 50),
    "transforms.safety_layer.speed_margin": Real(0, 10),
    "transforms.residual.gap_margin": Real(0, 50),
    "transforms.residual.speed_margin": Real(0, 10),
    "transforms.v2v_channel.delay": Real(0, 10),
    "transforms.v2v_channel.loss": Real(0, 1),
    "transforms.v2v_channel.seed": Int(0),
    "transforms.onboard_accel.after": Real(0, 60, optional=True),
    "transforms.onboard_accel.tau": Real(0, 60),
    "transforms.sensor_noise.gap": Real(0, 10),
    "transforms.sensor_noise.speed": Real(0, 5),
    "transforms.sensor_noise.tau": Real(0, 60),
    "transforms.sensor_noise.seed": Int(0),
}

_MISSING = object()


def _walk(node, prefix: str = ""):
    """(dotted path, value) of every leaf of a config (interpolations unresolved are skipped)."""
    if isinstance(node, DictConfig):
        for k in node.keys():
            if OmegaConf.is_missing(node, k):
                continue
            try:
                v = node[k]
            except Exception:  # an interpolation that only resolves inside a Hydra app
                continue
            yield from _walk(v, f"{prefix}{k}.")
    elif isinstance(node, ListConfig):
        for i, v in enumerate(node):
            yield from _walk(v, f"{prefix}{i}.")
    else:
        yield prefix[:-1], node


def _check_ordered_pair(cfg: DictConfig, path: str, allowed: str) -> None:
    """``path``, where set, is a list of two numbers ``[lo, hi]`` with ``0 <= lo < hi``; ``ConfigError`` naming it
    and ``allowed`` otherwise."""
    pair = OmegaConf.select(cfg, path, default=None)
    if pair is not None and not (OmegaConf.is_list(pair) and len(pair) == 2 and all(is_real(x) for x in pair)
                                 and 0 <= pair[0] < pair[1]):
        raise ConfigError(path, repr(pair), allowed)


def _check_classic_params(cfg: DictConfig, prefix: str, key: str = "params") -> None:
    """``PREFIX.KEY`` (default ``params``) name parameters of the classical model ``PREFIX.base`` and are numbers."""
    params = OmegaConf.select(cfg, f"{prefix}.{key}", default=None)
    if params:
        from mixed_traffic.controllers.classic import classic_parameters

        model = OmegaConf.select(cfg, f"{prefix}.base", default="idm")
        allowed = classic_parameters(model)
        for k, v in params.items():
            if v is None:  # null: no override (an experiment over an IDM base nulls gap_max to switch base)
                continue
            if k not in allowed:
                raise ConfigError(f"{prefix}.{key}.{k}", f"is not a {model} parameter", str(allowed))
            Real()(f"{prefix}.{key}.{k}", v)


def _names_a_law_parameter(key: str) -> bool:
    """Whether the dotted ``key`` is a classical law's parameter: a key directly under ``params`` or ``fast_params``
    (checked against the law's model by :func:`validate_config`, not against the keys the config lists)."""
    return key.rpartition(".")[0].endswith((".params", ".fast_params"))


def parse_deploy_overrides(items) -> list[tuple[str, object]]:
    """``transforms.KEY=VALUE`` items (Hydra's value syntax) as ``(key, value)`` pairs: the deploy-time settings of a
    trained run's transforms (``mt-eval checkpoint=...``, ``ring_generalization.py --set``). ``ConfigError`` naming
    the item unless it sets a key under ``transforms.``: a trained policy keeps the env it was trained on. An
    appended item (``+transforms....``) is taken only for a classical law's parameter (a key under ``params`` or
    ``fast_params``), where Hydra asks for the ``+`` to add a parameter the run's config does not list.

        >>> parse_deploy_overrides(["transforms.residual.drive_off.follow=0.9"])
        [('transforms.residual.drive_off.follow', 0.9)]
    """
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parser, out = OverridesParser.create(), []
    for item in items:
        try:
            ov = parser.parse_overrides([item])[0]
        except Exception as e:  # Hydra's parse errors: name the item
            raise ConfigError(str(item), f"cannot be parsed ({e})", "transforms.KEY=VALUE") from None
        appended_ok = not ov.is_add() or _names_a_law_parameter(ov.key_or_group)
        if not ov.key_or_group.startswith("transforms.") or ov.is_delete() or not appended_ok:
            raise ConfigError(str(item), "not a deployed setting of the run's transforms",
                              "transforms.KEY=VALUE (the run's env and policy stay as trained)")
        out.append((ov.key_or_group, ov.value()))
    return out


def with_deploy_overrides(run_cfg: DictConfig, pairs) -> DictConfig:
    """A copy of a trained run's config with the pairs of :func:`parse_deploy_overrides` set, validated
    (:func:`validate_config`); ``ConfigError`` naming a key the run's config does not have (a typo fails before
    anything runs) or a value out of range."""
    cfg = OmegaConf.create(OmegaConf.to_container(run_cfg, resolve=False))
    if cfg.get("transforms") is not None:
        # a transform, or a node of a transform's settings (e.g. transforms.residual.answer), added since the run was
        # trained and set or put in the chain here: the schema's node with its defaults, parents before children
        schema = OmegaConf.structured(TransformsConfig)
        paths = [".".join(key.split(".")[1:depth]) for key, _ in pairs for depth in range(2, key.count(".") + 1)]
        paths += [n for key, value in pairs if key == "transforms.chain" and isinstance(value, list)
                  for n in value if isinstance(n, str)]
        for path in paths:
            parent = path.rpartition(".")[0]
            node = OmegaConf.select(schema, path, default=None)
            if (OmegaConf.is_dict(node) and OmegaConf.select(cfg.transforms, path, default="<missing>") == "<missing>"
                    and (not parent or OmegaConf.select(cfg.transforms, parent, default=None) is not None)):
                OmegaConf.update(cfg.transforms, path, OmegaConf.to_container(node), merge=False)
    for key, value in pairs:
        parent = key.rpartition(".")[0]
        is_param = _names_a_law_parameter(key) and OmegaConf.is_dict(OmegaConf.select(cfg, parent, default=None))
        if not is_param and OmegaConf.select(cfg, key, default="<missing>") == "<missing>":  # a law's parameter is
            # checked against its model below (validate_config); any other key must exist
            raise ConfigError(key, "not a setting of the run's config",
                              "an existing transforms.* key (see the run's config.yaml), or a classical law's "
                              "parameter under an existing params or fast_params")
        OmegaConf.update(cfg, key, value, merge=False)
    if pairs:
        validate_config(cfg)
    return cfg


def validate_config(cfg: DictConfig) -> DictConfig:
    """Check every rule of :data:`CONFIG_RULES` present in ``cfg`` and that all floats are finite."""
    for path, node in _walk(cfg):
        if path.startswith("hydra."):
            continue
        if isinstance(node, float) and not math.isfinite(node) and path not in CONFIG_RULES:
            raise ConfigError(path, f"{node!r} is not finite", "a finite number")
    for path, rule in CONFIG_RULES.items():
        value = OmegaConf.select(cfg, path, default=_MISSING, throw_on_missing=False)
        if value is not _MISSING:
            rule(path, value)
    tc = cfg.get("transforms")
    if (tc is not None and "safety_layer" in tc and tc.safety_layer.s_max is not None
            and not tc.safety_layer.s_min < tc.safety_layer.s_max):
        raise ConfigError("transforms.safety_layer.s_min", f"{tc.safety_layer.s_min} >= s_max {tc.safety_layer.s_max}",
                          "s_min < s_max")
    if (tc is not None and "safety_layer" in tc and tc.safety_layer.get("deployed_s_max", True) is False
            and tc.safety_layer.get("deployed_beyond_s_max") is not None):
        raise ConfigError("transforms.safety_layer.deployed_beyond_s_max",
                          f"{tc.safety_layer.deployed_beyond_s_max!r} has no effect with deployed_s_max: false "
                          "(the deployed layer has no s_max)", "null, or deployed_s_max: true")
    _check_classic_params(cfg, "transforms.residual")
    join_base = OmegaConf.select(cfg, "transforms.residual.join.base", default=None)
    if join_base is not None:
        from mixed_traffic.controllers.classic import CLASSIC

        OneOf(tuple(CLASSIC))("transforms.residual.join.base", join_base)
        _check_classic_params(cfg, "transforms.residual.join")
        _check_ordered_pair(cfg, "transforms.residual.join.leader_speeds",
                            "[v_off, v_on] with 0 <= v_off < v_on (m/s), or null")
        _check_classic_params(cfg, "transforms.residual.join", "fast_params")
        _check_ordered_pair(cfg, "transforms.residual.join.fast_leader_speeds",
                            "[v1, v2] with 0 <= v1 < v2 (m/s), or null")
        fast = [OmegaConf.select(cfg, f"transforms.residual.join.{k}", default=None)
                for k in ("fast_params", "fast_leader_speeds")]
        if (fast[0] is None) != (fast[1] is None):
            raise ConfigError("transforms.residual.join.fast_leader_speeds", repr(fast[1]),
                              "set together with transforms.residual.join.fast_params (both, or both null)")
    _check_ordered_pair(cfg, "transforms.residual.fade_speeds", "[v_full, v_zero] with 0 <= v_full < v_zero (m/s), or null")
    for field, needs, allowed in (  # a setting of another that must be on
            ("arrive_gain", "stop_gap", "null, or a gain (1/s^2, > 0) with a stop_gap (the envelope it arrives at)"),
            ("stand_arrival.stand_gap", "stop_gap", "null, or a gap (m, > 0) with a stop_gap (the envelope it acts near)"),
            ("envelope_fade_slack_below", "envelope_fade_slack",
             "null, or a leader speed (m/s, > 0) with an envelope_fade_slack"),
            ("envelope_fade_slack_brake", "envelope_fade_slack",
             "null, or a leader deceleration (m/s^2, > 0) with an envelope_fade_slack"),
            ("drive_off.residual_play_release", "drive_off.residual_play", "null, or a time (s, > 0) with a residual_play")):
        if (OmegaConf.select(cfg, f"transforms.residual.{field}", default=None) is not None
                and OmegaConf.select(cfg, f"transforms.residual.{needs}", default=None) is None):
            raise ConfigError(f"transforms.residual.{field}", f"set with {needs.rpartition('.')[2]} null", allowed)
    fade_mode = OmegaConf.select(cfg, "transforms.residual.envelope_fade", default="off")
    if fade_mode != "off" and OmegaConf.select(cfg, "transforms.residual.stop_gap", default=None) is None:
        raise ConfigError("transforms.residual.envelope_fade", f"{fade_mode} with stop_gap null",
                          "off, or always / deploy with a stop_gap (the envelope it fades against)")
    if (OmegaConf.select(cfg, "transforms.residual.envelope_fade_slack", default=None) is not None
            and fade_mode == "off"):
        raise ConfigError("transforms.residual.envelope_fade_slack", "set with envelope_fade off",
                          "null, or a margin (m, > 0) with envelope_fade always / deploy")
    for name in ("transforms.residual.catch_up.gaps", "transforms.residual.drive_off.gaps"):
        _check_ordered_pair(cfg, name, "[from, full] with 0 <= from < full (m)")
    _check_ordered_pair(cfg, "transforms.residual.stand_arrival.speeds", "[full, none] with 0 <= full < none (m/s)")
    _check_ordered_pair(cfg, "transforms.residual.feed_forward.speeds", "[v_off, v_on] with 0 <= v_off < v_on (m/s)")
    if OmegaConf.select(cfg, "transforms.residual.answer.horizon", default=None) is not None:
        ans = OmegaConf.select(cfg, "transforms.residual.answer")
        _check_ordered_pair(cfg, "transforms.residual.answer.gaps", "[low, high] with 0 <= low < high (m)")
        _check_ordered_pair(cfg, "transforms.residual.answer.speeds", "[v_off, v_on] with 0 <= v_off < v_on (m/s)")
        if not ans.horizon_min <= ans.horizon:
            raise ConfigError("transforms.residual.answer.horizon_min", f"{ans.horizon_min} > horizon {ans.horizon}",
                              "0 < horizon_min <= horizon (s)")
        if not ans.done <= ans.start:
            raise ConfigError("transforms.residual.answer.done", f"{ans.done} > start {ans.start}",
                              "0 <= done <= start (m/s)")
        if ans.get("idm") is not None:
            idm_keys = ("v0", "T", "a", "b", "s0")
            for k, v in ans.idm.items():
                if k not in idm_keys:
                    raise ConfigError(f"transforms.residual.answer.idm.{k}", "is not an IDM term's parameter",
                                      str(list(idm_keys)))
                Real(0, 1000, lo_open=k != "s0")(f"transforms.residual.answer.idm.{k}", v)
    for key in SPEED_LAWS:
        node = OmegaConf.select(cfg, f"transforms.residual.{key}", default=None)
        if node is not None and node.get("base") is not None:  # null base: the schedule is off
            _check_classic_params(cfg, f"transforms.residual.{key}")
            if not node.v_low < node.v_high:
                raise ConfigError(f"transforms.residual.{key}.v_high", f"{node.v_high} <= v_low {node.v_low}",
                                  "v_high > v_low (m/s)")
    pol = cfg.get("policy")
    if pol is not None and "log_std_min" in pol and not pol.log_std_min <= pol.log_std_max:
        raise ConfigError("policy.log_std_min", f"{pol.log_std_min} > log_std_max {pol.log_std_max}",
                          "log_std_min <= log_std_max")
    apg = OmegaConf.select(cfg, "policy.apg", default=None)
    if apg is not None and is_real(apg.get("iterations")) and apg.get("average_last") is not None:
        Int(0, apg.iterations)("policy.apg.average_last", apg.average_last)  # at most the steps it averages over
    chain = list(OmegaConf.select(cfg, "transforms.chain", default=None) or [])
    if ("sensor_noise" in chain and "v2v_channel" in chain and chain.index("v2v_channel") > chain.index("sensor_noise")
            and bool(OmegaConf.select(cfg, "transforms.sensor_noise.filter", default=False))):
        raise ConfigError("transforms.chain", f"{chain}: sensor_noise (with transforms.sensor_noise.filter) before "
                          "v2v_channel", "v2v_channel before sensor_noise, so that the filter reads the link as received")
    if "onboard_accel" in chain and "v2v_channel" in chain and chain.index("v2v_channel") > chain.index("onboard_accel"):
        raise ConfigError("transforms.chain", f"{chain}: onboard_accel before v2v_channel",
                          "v2v_channel before onboard_accel, so that the estimate replaces the link's held message")
    for name in ("eval.v2v_delay", "transforms.v2v_channel.delay"):
        delay = OmegaConf.select(cfg, name, default=0.0)
        if is_real(delay) and delay > 0:
            dt = _env_dt(cfg)
            if dt is not None:
                v2v_delay_steps(delay, dt, name)
    return cfg


def _env_dt(cfg: DictConfig) -> float | None:
    """The step of ``cfg.env``'s scenario (s), or None where it has none to read (no env, another family)."""
    if OmegaConf.select(cfg, "env.scenario", default=None) is None:
        return None
    scenario = check_env_config(cfg)
    return None if scenario is None else float(scenario.dt)


def v2v_delay_steps(delay: float, dt: float, name: str = "eval.v2v_delay") -> int:
    """A V2V delay (s; the config field ``name``) in steps of ``dt``; a delay between steps is a :class:`ConfigError`."""
    steps = round(delay / dt)
    if abs(steps * dt - delay) > 1e-6 * max(1.0, delay):
        raise ConfigError(name, f"{delay!r} is not a whole number of steps",
                          f"a multiple of the env's step dt = {dt:g} s")
    return steps


def check_env_config(cfg: DictConfig, **extra):
    """Build (and so validate) the scenario of ``cfg.env`` without starting anything, and return it (None for
    the families that validate their own arguments, e.g. the intersection).

    Errors name the config path: ``env.<field>`` for the named fields, else
    ``env.overrides.<field>``.
    """
    from mixed_traffic.scenarios import PRESETS, get_scenario
    from mixed_traffic.training.builders import ENV_FIELDS, env_kwargs

    env = cfg.env
    if env.scenario not in PRESETS:  # the intersection env validates its own arguments
        return None
    try:
        return get_scenario(env.scenario, **env_kwargs(env, **extra))
    except ConfigError as e:
        where = "env." if e.field in ENV_FIELDS else "env.overrides."
        raise ConfigError(where + e.field, e.problem, e.allowed) from None


# ----------------------------------------------------------------------------- paths
def check_writable_dir(field: str, directory: str | Path) -> Path:
    """``directory`` exists or can be created, and a file can be written in it (probed, then removed)."""
    d = Path(directory).expanduser().absolute()
    for parent in (d, *d.parents):
        if parent.exists():
            if not parent.is_dir():
                raise ConfigError(field, f"cannot write in {str(d)!r} ({str(parent)!r} is a file, not a directory)",
                                  "a writable directory")
            break
    try:
        d.mkdir(parents=True, exist_ok=True)
        probe = d / f".mt-write-probe-{os.getpid()}"
        probe.write_bytes(b"x")
        probe.unlink()
    except OSError as e:
        raise ConfigError(field, f"cannot write in {str(d)!r} ({e.strerror or e})",
                          "a writable directory") from None
    return d


# ----------------------------------------------------------------------------- apps
def known_experiments() -> list[str]:
    import hydra_configs

    root = Path(hydra_configs.__file__).parent / "experiment"
    return sorted(p.stem for p in root.glob("*.yaml"))


def check_argv(argv: list[str]) -> list[str]:
    """Checks Hydra cannot do on the command line; returns the (possibly rewritten) argv.

    - ``experiment=<name>`` must name a file of ``hydra_configs/experiment`` (a misspelt
      name would otherwise fall back to the defaults).
    - ``env.overrides.<field>=v`` and ``env.profile_kwargs.<arg>=v`` may be new keys of free-form dicts
      (a scenario field, a profile's argument, e.g. ``random_mix``'s ``weights``): they are passed to Hydra as
      ``++...`` so no ``+`` is needed. A misspelt name still fails at start-up, when the env is built, naming it.
    """
    out = []
    names = None
    for a in argv:
        key, eq, value = a.partition("=")
        if eq and key.lstrip("+~") == "experiment" and not key.startswith("~"):
            names = names or known_experiments()
            for v in value.split(","):  # a sweep over experiments
                if v not in names:
                    raise ConfigError("experiment", f"unknown name {v!r}", str(names))
        if eq and key.startswith(("env.overrides.", "env.profile_kwargs.")) and not key.startswith("+"):
            a = "++" + a
        out.append(a)
    return out


def _debug() -> bool:
    return os.environ.get(DEBUG_ENV, "0") not in ("", "0", "false", "False")


def _job_error_class():
    from hydra.errors import CompactHydraException

    class JobError(CompactHydraException):
        """A user error inside one job of a sweep: Hydra prints its message without a traceback."""

    return JobError


JobError = _job_error_class()


def _in_multirun() -> bool:
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN


def report_error(e: BaseException, prog: str) -> None:
    print(f"error: {e}", file=sys.stderr)
    print(f"({prog}: set {DEBUG_ENV}=1 for the traceback)", file=sys.stderr)


USER_ERRORS = (ValueError, FileNotFoundError, FileExistsError, PermissionError)


def guarded(fn: Callable, prog: str):
    """Call ``fn()``; a user error becomes ``error: ...`` on stderr and exit status 2.

    ``MT_DEBUG=1`` re-raises instead (full traceback).
    """
    try:
        return fn()
    except USER_ERRORS as e:
        if _debug():
            raise
        if _in_multirun():  # Hydra records the failed job (the sweep goes on) and prints this message only
            raise JobError(f"error: {e}") from e
        report_error(e, prog)
        raise SystemExit(2) from None
    except OSError as e:  # a full disk, an unreadable file: name it without a traceback
        if _debug():
            raise
        err = ConfigError(getattr(e, "filename", None) or "file", e.strerror or str(e),
                          "a readable/writable path with free space")
        if _in_multirun():
            raise JobError(f"error: {err}") from e
        report_error(err, prog)
        raise SystemExit(2) from None


def run_cli(hydra_main: Callable, prog: str, argv: list[str] | None = None) -> None:
    """Entry point of a Hydra app: argv checks, then Hydra, with errors as ``error:`` lines and exit 2.

    Hydra's own start-up errors (an unknown key, a wrong type) keep Hydra's message and
    exit with status 2 too.
    """
    argv = sys.argv[1:] if argv is None else list(argv)
    new_argv = guarded(lambda: check_argv(argv), prog)
    saved = sys.argv
    sys.argv = [saved[0] if saved else prog, *new_argv]
    try:
        hydra_main()
    except SystemExit as e:
        if e.code == 1:  # Hydra's composition errors
            raise SystemExit(2) from None
        raise
    finally:
        sys.argv = saved


__all__ = ["ConfigError", "Real", "Int", "OneOf", "CONFIG_RULES", "validate_config", "check_env_config", "v2v_delay_steps",
           "check_writable_dir", "check_argv", "guarded", "run_cli", "known_experiments", "DEBUG_ENV"]
