"""Build the pieces of a run from its config: env + transform chain, networks, losses.

Everything here is plain TorchRL: ``TransformedEnv(make_env(...), Compose(...))``,
``ProbabilisticActor`` + value ``TensorDictModule``, ``ClipPPOLoss``, ``QValueActor`` + ``DQNLoss``.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.data import Composite, OneHot, Unbounded
from torchrl.envs import Compose, EnvBase, RewardSum, StepCounter, Transform, TransformedEnv
from torchrl.modules import MLP, ProbabilisticActor, QValueActor, TanhNormal

from mixed_traffic.config import SPEED_LAWS
from mixed_traffic.envs import make_env

ENV_FIELDS = ("observation", "profile", "profile_kwargs", "episode_seconds", "weight_v", "weight_s", "weight_u",
              "s_min", "s_max", "hdv_param_noise", "sumo_safety")


# ----------------------------------------------------------------------------- env
def env_kwargs(env_cfg: DictConfig | dict, **extra) -> dict:
    """Scenario overrides from an env config: the named fields that are set, then ``overrides``."""
    cfg = OmegaConf.to_container(env_cfg, resolve=True) if isinstance(env_cfg, DictConfig) else dict(env_cfg)
    kw = {k: cfg[k] for k in ENV_FIELDS if cfg.get(k) is not None}
    kw.update(cfg.get("overrides") or {})
    kw.update(extra)
    return kw


def _non_negative_reward(tcfg, env):
    from transforms import NonNegativeReward

    return NonNegativeReward(collision_reward=tcfg.non_negative_reward.collision_reward)


def _profile_reward(tcfg, env):
    from mixed_traffic.envs.platoon import PROFILE_KINDS
    from transforms import ProfileNormalisedReward

    c = tcfg.profile_reward
    return ProfileNormalisedReward(dict(c.J_max), kinds=PROFILE_KINDS, collision_reward=c.collision_reward)


def _counterfactual_reward(tcfg, env):
    from mixed_traffic.controllers.deeplcc.rlmpc import nnmpc_base
    from mixed_traffic.envs.platoon import PROFILE_KINDS
    from transforms import CounterfactualReward

    c = tcfg.counterfactual_reward
    return CounterfactualReward(nnmpc_base(c.checkpoint, "transforms.counterfactual_reward.checkpoint"), dict(c.J_ref),
                                kinds=PROFILE_KINDS, scale=c.scale, offset=c.offset,
                                collision_reward=c.collision_reward)


def safety_layer_settings(s, *, deploy: bool = False) -> dict:
    """The ``SafetyLayer`` arguments of ``transforms.safety_layer`` (``s``); built for evaluation or deployment
    (``deploy``), its rule beyond ``s_max`` is ``deployed_beyond_s_max`` where that is set, and it has no
    ``s_max`` at all with ``deployed_s_max: false`` (only the s_min rule, the guarantee). The evaluation report
    states the deployed settings from here."""
    beyond, s_max = s.get("beyond_s_max", "push"), s.s_max
    if deploy and s.get("deployed_beyond_s_max") is not None:
        beyond = s.deployed_beyond_s_max
    if deploy and not s.get("deployed_s_max", True):
        s_max = None
    return dict(s_min=s.s_min, s_max=s_max, mode=s.mode, beyond_s_max=beyond, ramp_jerk=s.get("ramp_jerk", 1.0),
                recover_seconds=s.get("recover_seconds", 5.0), hold_seconds=s.get("hold_seconds", 0.0),
                gap_margin=s.get("gap_margin", 0.0), speed_margin=s.get("speed_margin", 0.0))


def _safety_layer(tcfg, env, *, deploy: bool = False):
    """``transforms.safety_layer``, as it trains or (``deploy``) as it is deployed (:func:`safety_layer_settings`)."""
    from transforms import SafetyLayer

    return SafetyLayer(**safety_layer_settings(tcfg.safety_layer, deploy=deploy))


def _residual_damper(tcfg, env):
    from mixed_traffic.controllers.dampers import make_damper
    from transforms import ResidualAction

    r = tcfg.residual_damper
    return ResidualAction(make_damper(r.base, env), weight=r.weight)


def _set_point(tcfg, env):
    from mixed_traffic.controllers.dampers import make_damper
    from transforms import SetPointAction

    c = tcfg.set_point
    return SetPointAction(make_damper("follower_stopper", env).module, ratio0=c.ratio0, weight=c.weight, rate=c.rate,
                          low=c.low, high=c.high, ramp_to=c.ramp_to, ramp_start=c.ramp_start, ramp_end=c.ramp_end)


def _blend(tcfg, env):
    from mixed_traffic.controllers.dampers import make_damper
    from mixed_traffic.evaluation.waves import parse_controller
    from transforms import ControllerBlend

    c = tcfg.blend
    dampers = []
    for field, name in (("first", c.first), ("second", c.second)):
        damper, kwargs = parse_controller(name, f"transforms.blend.{field}")
        try:
            dampers.append(make_damper(damper, env, **kwargs))
        except ValueError as e:  # an unknown damper or argument: name the config field
            raise ValueError(f"transforms.blend.{field}={name!r} is invalid: {e}") from e
    return ControllerBlend(*dampers, rate=c.rate, weight0=c.weight0, weight1=c.weight1, start=c.start, end=c.end)


def _intervention_cost(tcfg, env):
    from transforms import InterventionCost

    c = tcfg.intervention_cost
    return InterventionCost(coef=c.coef, mode=c.mode, direction=c.direction)


def _jerk_penalty(tcfg, env):
    from transforms import JerkPenalty

    j = tcfg.jerk_penalty
    return JerkPenalty(weight=j.weight, weight_after=j.get("weight_after"), after_seconds=j.get("after_seconds", 0.0))


def _jerk_limit(tcfg, env):
    from transforms import JerkLimit

    return JerkLimit(max_jerk=tcfg.jerk_limit.max_jerk)


def _v2v_channel(tcfg, env):
    from mixed_traffic.validation import v2v_delay_steps
    from transforms import V2VChannel

    c = tcfg.v2v_channel
    rng = getattr(env, "rng", None)  # the env's generator: its seed sets the worker's own loss draws
    seed = int(c.seed) + (int(rng.initial_seed()) if isinstance(rng, torch.Generator) else 0)
    return V2VChannel(delay_steps=v2v_delay_steps(float(c.delay), float(env.scenario.dt), "transforms.v2v_channel.delay"),
                      loss=float(c.loss), seed=seed % 2**63)


def _onboard_accel(tcfg, env):
    from transforms import OnboardLeaderAccel

    c = tcfg.onboard_accel
    return OnboardLeaderAccel(dt=float(env.scenario.dt), after=None if c.after is None else float(c.after),
                              tau=float(c.tau))


def measurement_filter_for(sc, gap: float, speed: float, tau: float, **kwargs):
    """A :class:`transforms.MeasurementFilter` of ``gap`` m / ``speed`` m/s errors over ``tau`` s laid out for the
    scenario ``sc`` (its observation, ``s_max``, step, and which CAVs follow the head directly); ``kwargs`` go
    to the filter (its link settings)."""
    from transforms import MeasurementFilter

    return MeasurementFilter(gap, speed, tau=tau, dt=float(sc.dt), observation=sc.observation, s_max=float(sc.s_max),
                             leader_is_head=tuple(i == 1 for i in sc.cav_indices), **kwargs)


def filter_link(delay: float, loss: float, dt: float, name: str = "eval.v2v_delay") -> dict:
    """The :class:`transforms.MeasurementFilter` settings for a V2V link ``delay`` s late (the config field
    ``name``) that loses the share ``loss`` of its messages.

    The filter's default for the perfect link, less trust for a lossy one (a lost message holds the last). A
    late link's message is a measurement of the leader's acceleration that long ago (the filter's delayed-link
    model: the speeds tell what the leader did since). A dead link, or one both late and lossy (a held
    message's age is unknown), is not read at all, and the leader may then brake or speed up as hard as any car
    (the leader's speed is then followed about as closely as measured)."""
    from mixed_traffic.validation import v2v_delay_steps

    if delay == 0.0 and loss == 0.0:
        return {}
    if delay == 0.0 and loss < 1.0:
        return {"leader_accel_std": 0.5}
    if loss == 0.0:
        return {"leader_accel_delay": v2v_delay_steps(delay, dt, name)}
    return {"leader_accel_key": None, "leader_accel_std": 10.0}


def sensor_filter_model(e) -> dict:
    """The noise the evaluation's filter assumes: ``{gap, speed, tau}`` from ``e.sensor_filter_*`` where set,
    from ``e.sensor_noise_*`` (the noise drawn) where null (``e``: the ``eval`` node)."""
    return {k: float(e.get(f"sensor_noise_{k}", 0.0) if e.get(f"sensor_filter_{k}") is None else e.get(f"sensor_filter_{k}"))
            for k in ("gap", "speed", "tau")}


def _eval_noise(cfg: DictConfig) -> tuple[float, float]:
    """``(eval.sensor_noise_gap, eval.sensor_noise_speed)``, (0, 0) without an ``eval`` node."""
    e = cfg.get("eval")
    return (0.0, 0.0) if e is None else (float(e.get("sensor_noise_gap", 0.0)), float(e.get("sensor_noise_speed", 0.0)))


def _sensor_noise(tcfg, env):
    from torchrl.envs import Compose

    from transforms import SensorNoise

    c, sc = tcfg.sensor_noise, env.scenario
    rng = getattr(env, "rng", None)  # the env's generator: its seed sets the worker's own draws
    seed = int(c.seed) + (int(rng.initial_seed()) if isinstance(rng, torch.Generator) else 0)
    try:
        noise = SensorNoise(float(c.gap), float(c.speed), seed=seed % 2**63, tau=float(c.tau), dt=float(sc.dt),
                            observation=sc.observation, s_max=float(sc.s_max))
        if not c.filter:
            return noise
        link = {}
        if "v2v_channel" in tcfg.chain:  # before this entry (checked at start-up): the filter reads the link as received
            v = tcfg.v2v_channel
            link = filter_link(float(v.delay), float(v.loss), float(sc.dt), "transforms.v2v_channel.delay")
        return Compose(noise, measurement_filter_for(sc, float(c.gap), float(c.speed), float(c.tau), **link))
    except ValueError as err:
        raise ValueError(f"transforms.sensor_noise: {err}") from None


def envelope_stop_gap(rcfg) -> float:
    """The gap (m) the deploy-time rules keep with the stopping rule: the base's ``stop_gap`` (``rcfg``: the
    ``residual`` node), or 5 m where the base has no envelope."""
    stop_gap = rcfg.get("stop_gap")
    return 5.0 if stop_gap is None else float(stop_gap)


def _switched_on(rcfg, name: str, switch: str, *, deploy: bool, when: str = "deploy"):
    """The node ``name`` of ``transforms.residual`` (``rcfg``) when its ``switch`` is set and it acts in the env being
    built: always, or, with its ``when`` at ``deploy`` (``when``: the node's default), only where the policy is
    evaluated or deployed (``deploy``); None otherwise."""
    node = rcfg.get(name)
    if node is None or node.get(switch) is None or not (deploy or node.get("when", when) == "always"):
        return None
    return node


def drive_off_cap(rcfg, env):
    """The :class:`transforms.DriveOffCap` of ``transforms.residual.drive_off`` (``rcfg``: the ``residual`` node) for
    ``env``'s step, or None when its ``gain`` is null (off). Where it acts (deploy or always) is the caller's."""
    from transforms import DriveOffCap

    d = rcfg.get("drive_off")
    if d is None or d.get("gain") is None:
        return None
    guard = None
    if d.get("follow") is not None:  # the floor stays inside the stopping rule of the base's envelope (or 5 m)
        from mixed_traffic.controllers.classic import action_bounds
        from transforms.safety_layer import scenario_leader_brake

        guard = (envelope_stop_gap(rcfg), -float(action_bounds(env)[0]),
                 scenario_leader_brake(env.scenario))
    return DriveOffCap(gain=d.gain, overspeed=d.overspeed, gaps=tuple(d.gaps), accel=d.accel, release=d.release,
                       standstill=d.standstill, dt=float(env.scenario.dt), follow=d.get("follow"),
                       follow_above=d.get("follow_above", 0.3), guard=guard, hold=bool(d.get("hold", False)))


def classic_law(base: str, params, env, **bounds):
    """The classical law ``base`` (:func:`mixed_traffic.controllers.classic.make_classic_policy`) for ``env`` with a
    config node's ``params``; a null parameter is left to the model (an experiment nulls one to undo an override)."""
    from mixed_traffic.controllers.classic import make_classic_policy

    return make_classic_policy(base, env, **bounds, **{k: v for k, v in dict(params or {}).items() if v is not None})


def join_blend(rcfg, env, *, deploy: bool = True):
    """The :class:`transforms.JoinBlend` of ``transforms.residual.join`` (``rcfg``: the ``residual`` node) for ``env``,
    or None when its ``base`` is null (off) or it is deploy-only and ``deploy`` is False. The join law runs inside
    the stopping envelope of the base's ``stop_gap`` (5 m where the base has none); with ``fast_params`` it is
    scheduled on the leader's speed over ``fast_leader_speeds``."""
    from mixed_traffic.controllers.classic import speed_scheduled_policy, stopping_envelope_policy
    from transforms import JoinBlend

    j = _switched_on(rcfg, "join", "base", deploy=deploy)
    if j is None:
        return None
    params = dict(j.get("params") or {})
    law = classic_law(j.base, params, env)
    if j.get("fast_params") is not None:
        v1, v2 = (float(v) for v in j.fast_leader_speeds)
        fast = classic_law(j.base, {**params, **dict(j.fast_params)}, env)
        law = speed_scheduled_policy(law, fast, v1, v2, on="leader_speed")
    law = stopping_envelope_policy(law, env, envelope_stop_gap(rcfg))
    seconds = j.get("seconds")
    speeds = j.get("leader_speeds")
    return JoinBlend(law, gap=float(j.gap), fade=float(j.fade), seconds=None if seconds is None else float(seconds),
                     leader_speeds=None if speeds is None else (float(speeds[0]), float(speeds[1])),
                     dt=float(env.scenario.dt))


def committed_answer(rcfg, env, *, deploy: bool = True):
    """The :class:`transforms.CommittedAnswer` of ``transforms.residual.answer`` (``rcfg``: the ``residual`` node) for
    ``env``, or None when its ``horizon`` is null (off) or it is deploy-only and ``deploy`` is False. It is bounded by
    the base's stopping envelope (``stop_gap`` with the base's arrival and stand terms and measurement margins), none
    where the base has no ``stop_gap``; with ``answer.catch_up`` the base's catch-up lifts it inside the envelope, as
    it lifts the base's band law."""
    from tensordict.nn import TensorDictModule

    from mixed_traffic.controllers.classic import CatchUp, stopping_envelope_policy
    from transforms import CommittedAnswer
    from transforms.committed_answer import GAP, LEADER_SPEED, SPEED, GivenCommand

    c = _switched_on(rcfg, "answer", "horizon", deploy=deploy)
    if c is None:
        return None
    law = GivenCommand()
    catch = _catch_up(rcfg, deploy=deploy) if c.get("catch_up", False) else None
    if catch is not None:  # the base's catch-up, as over its band law
        law = CatchUp(law, **catch)
    envelope = law if isinstance(law, CatchUp) else None
    if rcfg.get("stop_gap") is not None:
        given = TensorDictModule(law, in_keys=[GAP, SPEED, LEADER_SPEED], out_keys=["action"])
        envelope = stopping_envelope_policy(given, env, rcfg.stop_gap, **_envelope_settings(rcfg)).module
    idm = c.get("idm")
    return CommittedAnswer(horizon=c.horizon, horizon_min=c.horizon_min, start=c.start, done=c.done,
                           gaps=tuple(c.gaps), ks_edge=c.ks_edge, speeds=tuple(c.speeds),
                           idm=None if idm is None else dict(idm), envelope=envelope, dt=float(env.scenario.dt))


def _residual_idm(tcfg, env, *, deploy: bool = False):
    from transforms import ResidualAction
    from transforms.drive_off import ENGAGED

    r = tcfg.residual
    try:
        mode = r.get("envelope_fade", "off")
        room_key = ENVELOPE_ROOM_KEY if mode == "always" or (mode == "deploy" and deploy) else None
        fade_slack = r.get("envelope_fade_slack") if room_key is not None else None
        gate = {} if fade_slack is None else {"slack_below": r.get("envelope_fade_slack_below"),
                                              "slack_brake": r.get("envelope_fade_slack_brake")}
        slack_key = ENVELOPE_SLACK_KEY if fade_slack is not None else None
        base = residual_base(r, env, saturate=r.get("saturate_base", True), room_key=room_key, slack_key=slack_key,
                             deploy=deploy)
        fade = r.get("fade_speeds")
        cap = drive_off_cap(r, env)
        if cap is not None and _switched_on(r, "drive_off", "gain", deploy=deploy) is None:
            cap = None  # a deploy-only cap while training
        play = None if cap is None else r.drive_off.get("residual_play")
        residual = ResidualAction(base, weight=r.weight, engage_seconds=r.get("engage_seconds", 0.0),
                                  fade_speeds=None if fade is None else tuple(fade), room_key=room_key,
                                  slack_key=slack_key, fade_slack=fade_slack, **gate, play=play,
                                  play_key=None if play is None else ENGAGED,
                                  play_release=None if play is None else r.drive_off.get("residual_play_release"),
                                  dt=float(env.scenario.dt))
        join = join_blend(r, env, deploy=deploy)
        answer = committed_answer(r, env, deploy=deploy)
        steps = [t for t in (cap, join, answer) if t is not None]
        # the action passes the residual, the committed answer, the join, then the cap
        return [*steps, residual] if steps else residual
    except ValueError as e:
        raise ValueError(f"transforms.residual: {e}") from None


def _stand_arrival(rcfg) -> dict:
    """``stopping_envelope_policy``'s stand-arrival arguments from ``transforms.residual.stand_arrival`` (none when
    it is off)."""
    node = rcfg.get("stand_arrival")
    if node is None or node.get("stand_gap") is None:
        return {}
    brake = node.get("leader_brake")
    return {"stand_gap": node.stand_gap, "stand_speeds": tuple(node.speeds), "stand_slack": node.slack,
            "stand_leader_brake": math.inf if brake is None else brake}


def _catch_up(rcfg, *, deploy: bool) -> dict | None:
    """``CatchUp``'s arguments from ``transforms.residual.catch_up`` (``rcfg``: the ``residual`` node), or None when
    it is off (``accel`` null) or deploy-only and ``deploy`` is False."""
    catch = _switched_on(rcfg, "catch_up", "accel", deploy=deploy, when="always")
    if catch is None:
        return None
    return {"accel": catch.accel, "gaps": tuple(catch.gaps), "dv": catch.dv, "horizon": catch.get("horizon", 0.0)}


def _envelope_settings(rcfg) -> dict:
    """``stopping_envelope_policy``'s settings of the base's envelope beside its ``stop_gap``: the measurement margins,
    the arrival term and the stand arrival."""
    return {"gap_margin": rcfg.get("gap_margin", 0.0), "speed_margin": rcfg.get("speed_margin", 0.0),
            "arrive_gain": rcfg.get("arrive_gain"), **_stand_arrival(rcfg)}


ENVELOPE_ROOM_KEY = ("residual", "envelope_room")  # where the base writes its room below the envelope (m/s^2)
ENVELOPE_SLACK_KEY = ("residual", "envelope_slack")  # ... and the envelope's margin (m)


def residual_base(rcfg, env, *, saturate: bool = True, room_key=None, slack_key=None, deploy: bool = True):
    """The classical base of ``transforms.residual`` (``rcfg``) for ``env``: ``base`` with ``params`` (a null
    parameter: the model's own), joined by speed to ``high_speed``, ``top_speed`` and then ``beyond_speed`` when they are set
    (each with its ``brake_floor`` when set),
    with the leader's acceleration fed forward by ``feed_forward`` when its ``gain`` is set (deploy-only unless its
    ``when`` is ``always``), lifted by ``catch_up`` when its ``accel`` is set, inside the stopping envelope of ``stop_gap`` when it is set (with its ``stand_arrival`` when that is set; writing its room below it to ``room_key``
    and its margin to ``slack_key`` when given). ``saturate=False``: its command is not clipped to the env's action bounds
    (``ResidualAction`` clips the sum). ``deploy``: the base as evaluated or deployed; False, as it trains
    (without a ``catch_up`` or ``feed_forward`` whose ``when`` is ``deploy``)."""
    from mixed_traffic.controllers.classic import (
        catch_up_policy,
        leader_accel_feed_policy,
        leader_brake_floor_policy,
        speed_scheduled_policy,
        stopping_envelope_policy,
    )

    bounds = {} if saturate else {"low": -math.inf, "high": math.inf}

    def law(node):
        return classic_law(node.base, node.get("params"), env, **bounds)

    base = law(rcfg)
    for key in SPEED_LAWS:
        node = rcfg.get(key)
        if node is not None and node.get("base") is not None:
            high = law(node)
            if node.get("brake_floor") is not None:
                high = leader_brake_floor_policy(high, env, floor=node.brake_floor, margin=node.brake_margin)
            base = speed_scheduled_policy(base, high, node.v_low, node.v_high)
    feed = _switched_on(rcfg, "feed_forward", "gain", deploy=deploy)
    if feed is not None:
        base = leader_accel_feed_policy(base, env, gain=feed.gain, accel_max=feed.accel_max, speeds=tuple(feed.speeds))
    catch = _catch_up(rcfg, deploy=deploy)
    if catch is not None:
        base = catch_up_policy(base, **catch)
    if rcfg.get("stop_gap") is not None:
        base = stopping_envelope_policy(base, env, rcfg.stop_gap, room_key=room_key, slack_key=slack_key,
                                        **_envelope_settings(rcfg))
    return base


def _residual_nnmpc(tcfg, env):
    from mixed_traffic.controllers.deeplcc.rlmpc import residual_nnmpc

    r = tcfg.residual_nnmpc
    return residual_nnmpc(r.checkpoint, weight=r.weight)


def _state_discretizer(tcfg, env):
    from transforms import StateDiscretizer

    return StateDiscretizer(n_bins=tcfg.discretizer.state_bins)


def _barrier_force(tcfg, env):
    from transforms import BarrierForce

    return BarrierForce(rho=tcfg.barrier_force.rho, K=tcfg.barrier_force.K)


def _residual_nmpc(tcfg, env):
    from mixed_traffic.intersection.residual import ResidualNMPC

    return ResidualNMPC(weight=tcfg.residual_nmpc.weight)


def _conflict_cost(tcfg, env):
    from transforms import ConflictCost

    c = tcfg.conflict_cost
    return ConflictCost(anticipation=c.anticipation, horizon_s=c.horizon_s, out_of_bounds=c.out_of_bounds,
                        ego_caused=c.ego_caused, margin=c.margin)


class EpisodeRewardSum(RewardSum):
    """TorchRL's ``RewardSum`` with an unbounded ``episode_reward`` spec.

    ``RewardSum`` clones the per-step reward's spec for the episode sum, bounds included, so a
    bounded reward (e.g. the wave reward in [-1, 1]) gives a sum outside its own spec after a
    few steps and ``check_env_specs`` fails on the env.
    """

    def _generate_episode_reward_spec(self) -> Composite:
        spec = super()._generate_episode_reward_spec()
        for key in list(spec.keys(True, True)):
            leaf = spec[key]
            spec[key] = Unbounded(shape=leaf.shape, dtype=leaf.dtype, device=leaf.device)
        return spec


# name -> factory(transforms_cfg, base_env) -> Transform, or a list of them in chain order (residual_idm with
# its drive-off cap).  Order comes from the config's `chain`.
TRANSFORMS: dict[str, Callable] = {
    "non_negative_reward": _non_negative_reward,
    "profile_reward": _profile_reward,
    "counterfactual_reward": _counterfactual_reward,
    "safety_layer": _safety_layer,
    "residual_damper": _residual_damper,
    "set_point": _set_point,
    "blend": _blend,
    "intervention_cost": _intervention_cost,
    "residual_idm": _residual_idm,
    "residual_nnmpc": _residual_nnmpc,
    "jerk_penalty": _jerk_penalty,
    "jerk_limit": _jerk_limit,
    "v2v_channel": _v2v_channel,
    "onboard_accel": _onboard_accel,
    "sensor_noise": _sensor_noise,
    "state_discretizer": _state_discretizer,
    "barrier_force": _barrier_force,
    "residual_nmpc": _residual_nmpc,
    "conflict_cost": _conflict_cost,
}
#: transforms that shape training only; the evaluation runs the env without them
TRAINING_ONLY = ("conflict_cost", "jerk_penalty", "v2v_channel", "sensor_noise")  # the evaluated link and noise:
# eval.v2v_* and eval.sensor_noise_*
# built differently for evaluation / deployment (make_transformed_env(deploy=True))
DEPLOY_AWARE = ("residual_idm", "safety_layer")


def check_chain(chain) -> None:
    unknown = [c for c in chain if c not in TRANSFORMS]
    if unknown:
        raise ValueError(f"transforms.chain: unknown transform(s) {unknown}; allowed: {sorted(TRANSFORMS)}")


def make_transformed_env(cfg: DictConfig, *, num_envs: int, seed: int, without: tuple[str, ...] = (),
                         deploy: bool = False, **env_overrides) -> TransformedEnv:
    """The base env of ``cfg.env`` wrapped in ``cfg.transforms.chain`` (+ episode bookkeeping).

    ``without`` drops named transforms from the chain (the evaluation removes
    ``safety_layer`` and ``intervention_cost`` to run the policy's raw actions). ``deploy``: the chain as
    the policy is evaluated or deployed (the transforms in :data:`DEPLOY_AWARE` build their deployment
    form, e.g. ``transforms.residual.envelope_fade: deploy``); False: as it trains.

    ``RewardSum`` (``episode_reward``: the task reward summed over the episode, before any
    Lagrangian penalty) and ``StepCounter`` come last so logs see the transformed reward.
    """
    check_chain(cfg.transforms.chain)
    base: EnvBase = make_env(cfg.env.scenario, backend=cfg.env.backend, batch_size=num_envs, seed=seed,
                             device=cfg.device, **env_kwargs(cfg.env, **env_overrides))
    return TransformedEnv(base, chain_transforms(cfg, base, without=without, deploy=deploy))


def chain_transforms(cfg: DictConfig, base: EnvBase, *, without: tuple[str, ...] = (), deploy: bool = False) -> Compose:
    """``cfg.transforms.chain`` less ``without``, built for ``base`` (``deploy`` as in :func:`make_transformed_env`),
    then ``EpisodeRewardSum`` and ``StepCounter``: what :func:`make_transformed_env` wraps its env in, and what the
    SUMO evaluation wraps its ``ParallelEnv`` of SUMO rings in, so both evaluate the same chain."""
    measured = (eval_sensor_noise(cfg, base), eval_v2v_channel(cfg, base), eval_measurement_filter(cfg, base)) \
        if deploy else (None, None, None)
    tcfg = noise_margined(cfg, measured[2]) if deploy else cfg.transforms
    ts = [m for m in measured if m is not None]
    for name in cfg.transforms.chain:
        if name not in without:
            built = TRANSFORMS[name](tcfg, base, **({"deploy": deploy} if name in DEPLOY_AWARE else {}))
            ts += built if isinstance(built, list) else [built]  # a factory may give several, in chain order
    ts += [EpisodeRewardSum(in_keys=["reward"], out_keys=["episode_reward"]), StepCounter()]
    return Compose(*ts)


def eval_v2v_channel(cfg: DictConfig, base: EnvBase):
    """The evaluation's V2V link (``eval.v2v_delay`` s, ``eval.v2v_loss``) as a :class:`transforms.V2VChannel`
    seeded by ``eval.seed``, or None for the perfect link (both 0, or no ``eval`` node)."""
    from mixed_traffic.validation import Real, v2v_delay_steps
    from transforms import V2VChannel

    e = cfg.get("eval")
    delay, loss = (0.0, 0.0) if e is None else (float(e.get("v2v_delay", 0.0)), float(e.get("v2v_loss", 0.0)))
    if delay == 0.0 and loss == 0.0:
        return None
    Real(0, 1)("eval.v2v_loss", loss)
    return V2VChannel(delay_steps=v2v_delay_steps(delay, float(base.scenario.dt)), loss=loss, seed=int(e.seed))


def noise_margined(cfg: DictConfig, measurement_filter=None) -> DictConfig:
    """``cfg.transforms`` with the safety layer's and the residual envelope's measurement margins set to
    ``eval.sensor_noise_margin`` standard deviations of the evaluation's noise (``k * eval.sensor_noise_gap`` m,
    ``k * eval.sensor_noise_speed`` m/s), added to any margins they already have; ``cfg.transforms`` itself
    when ``k`` is 0 or there is no noise. Behind a :class:`transforms.MeasurementFilter` the standard deviations
    are its estimates' (``posterior_std``: the gap's, and the larger of the own and the leader's speed's)."""
    from omegaconf import OmegaConf, open_dict

    e = cfg.get("eval")
    k = 0.0 if e is None else float(e.get("sensor_noise_margin", 0.0))
    gap, speed = _eval_noise(cfg)
    if k == 0.0 or (gap == 0.0 and speed == 0.0):
        return cfg.transforms
    if measurement_filter is not None:
        stds = [measurement_filter.posterior_std[f] for f in set(measurement_filter.leader_is_head)]
        gap, speed = max(s[0] for s in stds), max(max(s[1], s[2]) for s in stds)
    tcfg = OmegaConf.create(OmegaConf.to_container(cfg.transforms, resolve=True))
    with open_dict(tcfg):
        for node in ("safety_layer", "residual"):
            if tcfg.get(node) is not None:
                tcfg[node].gap_margin = float(tcfg[node].get("gap_margin", 0.0)) + k * gap
                tcfg[node].speed_margin = float(tcfg[node].get("speed_margin", 0.0)) + k * speed
    return tcfg


def eval_sensor_noise(cfg: DictConfig, base: EnvBase):
    """The evaluation's measurement noise (``eval.sensor_noise_gap`` m, ``eval.sensor_noise_speed`` m/s, correlated
    over ``eval.sensor_noise_tau`` s) as a :class:`transforms.SensorNoise` seeded by ``eval.seed``, or None for
    exact measurements (both 0, or no ``eval`` node)."""
    from mixed_traffic.validation import Real
    from transforms import SensorNoise

    e = cfg.get("eval")
    gap, speed = _eval_noise(cfg)
    if gap == 0.0 and speed == 0.0:
        return None
    Real(0, 10)("eval.sensor_noise_gap", gap)
    Real(0, 5)("eval.sensor_noise_speed", speed)
    tau = float(e.get("sensor_noise_tau", 0.0))
    Real(0, 60)("eval.sensor_noise_tau", tau)
    sc = base.scenario
    try:
        return SensorNoise(gap, speed, seed=int(e.seed), observation=sc.observation, s_max=float(sc.s_max), tau=tau,
                           dt=float(sc.dt))
    except ValueError as err:  # the env's observation is one the noise cannot move
        raise ValueError(f"eval.sensor_noise_*: {err}") from None


def eval_measurement_filter(cfg: DictConfig, base: EnvBase):
    """The evaluation's Kalman filter of the noisy measurements (``eval.sensor_filter``) as a
    :class:`transforms.MeasurementFilter` whose model is ``eval.sensor_filter_gap`` / ``_speed`` / ``_tau`` where
    set, ``eval.sensor_noise_*`` where null, or None when it is off or there is no noise to filter."""
    e = cfg.get("eval")
    if e is None or not bool(e.get("sensor_filter", False)) or _eval_noise(cfg) == (0.0, 0.0):
        return None
    delay, loss = float(e.get("v2v_delay", 0.0)), float(e.get("v2v_loss", 0.0))
    link = filter_link(delay, loss, float(base.scenario.dt))
    model = sensor_filter_model(e)
    return measurement_filter_for(base.scenario, model["gap"], model["speed"], model["tau"], **link)


def desynchronize(env: EnvBase, seed: int) -> bool:
    """Put each row of a freshly reset car-following env at a random time of its episode.

    All rows start at t = 0 after the first reset, so without this every row of a batch
    is at the same episode phase (the random-steps head changes speed at the same
    instants in every row, every row truncates at once). Here each row's clock jumps to
    a uniform time in [0, episode); its rolling v_eq window is filled with the current
    head speed, so the reward stays consistent. Later episodes start at t = 0 as usual.
    The SUMO ring (one row) moves its episode clock the same way: the head's profile and
    the time limit follow that clock, the SUMO simulation itself is not touched.
    Returns False (and does nothing) for envs without that clock.
    """
    base = env
    while isinstance(base, TransformedEnv):
        base = base.base_env
    g = torch.Generator().manual_seed(int(seed) + 7919)
    if hasattr(base, "_head_hist") and isinstance(base.step_count, int):  # SUMO ring: one row, a python clock
        base.step_count = int(torch.randint(0, base.scenario.max_steps, (1,), generator=g))
        return True  # its v_eq window (the head's recent speeds) already holds the current head speed
    needed = ("step_count", "head_hist", "head_sum", "vel", "scenario")
    if not all(hasattr(base, a) for a in needed):
        return False
    B, window = base.head_hist.shape
    start = torch.randint(0, base.scenario.max_steps, (B,), generator=g).to(base.step_count)
    base.step_count = start
    v0 = base.vel[:, 0]
    base.head_hist = v0[:, None].expand(B, window).clone()
    base.head_sum = v0 * (start + 1).clamp(max=window).to(v0.dtype)
    return True


# ----------------------------------------------------------------------------- networks
def _activation(name: str) -> type[nn.Module]:
    table = {"tanh": nn.Tanh, "relu": nn.ReLU, "elu": nn.ELU, "silu": nn.SiLU}
    if name not in table:
        raise ValueError(f"policy.activation={name!r} is invalid; allowed: {sorted(table)}")
    return table[name]


def _ortho(layer: nn.Linear, gain: float) -> nn.Linear:
    nn.init.orthogonal_(layer.weight, gain)
    nn.init.zeros_(layer.bias)
    return layer


class Trunk(nn.Sequential):
    """Linear/activation stack with orthogonal init (gain sqrt 2)."""

    def __init__(self, in_dim: int, hidden: list[int], activation: str):
        layers, d = [], in_dim
        for h in hidden:
            layers += [_ortho(nn.Linear(d, h), math.sqrt(2.0)), _activation(activation)()]
            d = h
        super().__init__(*layers)
        self.out_dim = d


class GaussianHead(nn.Module):
    """Mean from a linear head (orthogonal, gain 0.01) and a state-independent log-std, clamped."""

    def __init__(self, in_dim: int, act_dim: int, log_std_init: float, log_std_min: float, log_std_max: float):
        super().__init__()
        self.mean = _ortho(nn.Linear(in_dim, act_dim), 0.01)
        self.log_std = nn.Parameter(torch.full((act_dim,), float(log_std_init)))
        self.log_std_min, self.log_std_max = float(log_std_min), float(log_std_max)

    def forward(self, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        loc = self.mean(h)
        scale = self.log_std.clamp(self.log_std_min, self.log_std_max).exp().expand_as(loc)
        return loc, scale


class NetworkInput(nn.Module):
    """Concatenates the network's inputs, through ``features`` when set, then runs ``body``."""

    def __init__(self, body: nn.Module, features: nn.Module | None = None):
        super().__init__()
        self.body, self.features = body, features

    def forward(self, *xs: torch.Tensor) -> torch.Tensor:
        return self.body(self.features(*xs) if self.features is not None else torch.cat(xs, dim=-1))


def _net(body: nn.Module, feats: nn.Module | None, p) -> nn.Module:
    """``body`` alone for a plain observation input (the checkpoints' layout), else a :class:`NetworkInput`."""
    return body if feats is None and len(_in_keys(p)) == 1 else NetworkInput(body, feats)


def _in_keys(p) -> list:
    return ["observation"] + [tuple(k.split(".")) if "." in k else k for k in p.get("extra_in_keys", [])]


def _input(p, env: EnvBase) -> tuple[nn.Module | None, int]:
    """The policy's feature module (``policy.features``) and its output width."""
    keys = _in_keys(p)
    dims = [env.observation_spec[k].shape[-1] for k in keys]
    if p.get("features", "none") == "intersection":
        from mixed_traffic.envs.intersection import ObservationFeatures

        return ObservationFeatures(), ObservationFeatures.n_features + sum(dims[1:])
    return None, sum(dims)


def _value_head(width: int, p) -> nn.Linear:
    """The critic's output layer: orthogonal init, bias ``policy.value_bias_init``."""
    lin = _ortho(nn.Linear(width, 1), 1.0)
    nn.init.constant_(lin.bias, float(p.get("value_bias_init", 0.0)))
    return lin


def make_value(cfg: DictConfig, env: EnvBase, out_key: str = "state_value", trunk: Trunk | None = None):
    """A critic with its own trunk (``policy.hidden``; built here unless given) writing ``out_key``."""
    p = cfg.policy
    feats, in_dim = _input(p, env)
    trunk = trunk if trunk is not None else Trunk(in_dim, list(p.hidden), p.activation)
    hidden = "hidden_v" if out_key == "state_value" else f"hidden_{out_key}"
    lin = _value_head(trunk.out_dim, p)
    return TensorDictSequential(TensorDictModule(_net(trunk, feats, p), in_keys=_in_keys(p), out_keys=[hidden]),
                                TensorDictModule(lin, in_keys=[hidden], out_keys=[out_key]))


def make_actor_critic(cfg: DictConfig, env: EnvBase) -> tuple[ProbabilisticActor, TensorDictModule]:
    """PPO actor (TanhNormal to the action bounds) and critic, sharing one trunk when ``policy.shared_trunk``."""
    p = cfg.policy
    if p.kind != "actor_critic":
        raise ValueError(f"policy.kind={p.kind!r} is invalid for loss {cfg.loss.name!r}; allowed: 'actor_critic'")
    spec = env.action_spec_unbatched
    feats, in_dim = _input(p, env)
    trunk = Trunk(in_dim, list(p.hidden), p.activation)
    trunk_mod = TensorDictModule(_net(trunk, feats, p), in_keys=_in_keys(p), out_keys=["hidden"])
    critic_trunk = None if p.shared_trunk else Trunk(in_dim, list(p.hidden), p.activation)
    head = TensorDictModule(GaussianHead(trunk.out_dim, spec.shape[-1], p.log_std_init, p.log_std_min,
                                         p.log_std_max), in_keys=["hidden"], out_keys=["loc", "scale"])
    actor = ProbabilisticActor(
        TensorDictSequential(trunk_mod, head), in_keys=["loc", "scale"], spec=spec,
        distribution_class=TanhNormal,
        distribution_kwargs={"low": spec.space.low, "high": spec.space.high},
        return_log_prob=True,
    )
    if critic_trunk is not None:
        return actor, make_value(cfg, env, trunk=critic_trunk)
    v_lin = _value_head(trunk.out_dim, p)
    critic = TensorDictSequential(trunk_mod, TensorDictModule(v_lin, in_keys=["hidden"], out_keys=["state_value"]))
    return actor, critic


class DiscreteToContinuous(nn.Module):
    """Maps a one-hot over ``levels`` (per CAV) to the acceleration command."""

    def __init__(self, levels: torch.Tensor):
        super().__init__()
        self.register_buffer("levels", levels)

    def forward(self, onehot: torch.Tensor) -> torch.Tensor:
        return (onehot.to(self.levels.dtype) * self.levels).sum(-1, keepdim=True)


def action_levels(env: EnvBase, n_bins: int) -> torch.Tensor:
    spec = env.action_spec_unbatched
    if spec.shape[-1] != 1:
        raise ValueError(f"discrete policies support one CAV (action dim 1), got {spec.shape[-1]}")
    lo, hi = float(spec.space.low.flatten()[0]), float(spec.space.high.flatten()[0])
    return torch.linspace(lo, hi, n_bins)


def make_qnet_policy(cfg: DictConfig, env: EnvBase) -> tuple[QValueActor, TensorDictModule]:
    """DQN Q-network over ``action_bins`` accelerations; the actor writes ``action_onehot``."""
    p = cfg.policy
    n_bins = cfg.transforms.discretizer.action_bins
    obs_dim = env.observation_spec["observation"].shape[-1]
    net = MLP(in_features=obs_dim, out_features=n_bins, num_cells=list(p.hidden), activation_class=_activation(p.activation))
    qactor = QValueActor(net, in_keys=["observation"], spec=OneHot(n_bins), action_space=None,
                         action_value_key="action_value")
    # QValueActor writes "action"; rename to "action_onehot" so the env receives the acceleration
    qactor.module[-1].out_keys = ["action_onehot", "action_value", "chosen_action_value"]
    qactor.module[-1].action_key = "action_onehot"
    to_accel = TensorDictModule(DiscreteToContinuous(action_levels(env, n_bins)), in_keys=["action_onehot"],
                                out_keys=["action"])
    return qactor, to_accel


COLLECTORS = ("single", "multi_sync", "multi_async", "ray")


class DesyncStart(Transform):
    """Applies :func:`desynchronize` once, at the env's first reset.

    A collector worker builds and resets its own env inside its process, where the main
    process cannot reach it; this transform puts the desynchronisation in that env
    itself. Later resets (episode ends) are left alone. (No TorchRL transform moves an
    env's episode clock, hence this one.)

    Example:
        >>> from mixed_traffic import make_env
        >>> env = TransformedEnv(make_env("ring", batch_size=4, seed=0), DesyncStart(seed=0))
        >>> bool((env.reset()["traffic", "time"] == 0).all()) and bool((env.base_env.step_count > 0).any())
        True
    """

    def __init__(self, seed: int):
        super().__init__()
        self.seed = int(seed)
        self.done = False

    def _reset(self, tensordict, tensordict_reset):
        if not self.done:
            self.done = True
            desynchronize(self.parent, self.seed)
        return tensordict_reset


def worker_seed(seed: int, worker: int, start_iter: int = 0) -> int:
    """Seed of collector worker ``worker``: the run seed for worker 0 of a fresh run, distinct otherwise."""
    return (int(seed) + 1_000_003 * int(worker) + 7_919 * int(start_iter)) % (2**63)


def make_worker_env(cfg: DictConfig, num_envs: int, seed: int, desync: bool) -> TransformedEnv:
    """The env of one collector worker (module-level, so ``spawn`` and Ray can pickle it)."""
    from mixed_traffic.training.run import set_threads

    set_threads(cfg.threads)
    env = make_transformed_env(cfg, num_envs=num_envs, seed=seed)
    if desync:
        env.append_transform(DesyncStart(seed))
    return env


def collector_rows(cfg: DictConfig) -> int:
    """Rows of the env each collector process steps: ``num_envs / collector_workers`` past one process."""
    tc = cfg.trainer
    if tc.get("collector", "single") == "single":
        return int(tc.num_envs)
    return int(tc.num_envs) // int(tc.collector_workers)


def check_collector_config(cfg: DictConfig) -> None:
    """``trainer.collector`` / ``collector_workers`` against ``num_envs`` and the backend (before any work)."""
    from mixed_traffic.validation import ConfigError

    tc = cfg.trainer
    kind, workers, rows = tc.get("collector", "single"), int(tc.get("collector_workers", 1)), int(tc.num_envs)
    if kind not in COLLECTORS:
        raise ConfigError("trainer.collector", f"unknown value {kind!r}", str(list(COLLECTORS)))
    if kind != "single" and rows % workers:
        raise ConfigError("trainer.num_envs", f"{rows} rows do not split over trainer.collector_workers={workers}",
                          f"a multiple of {workers} (each worker steps num_envs / collector_workers rows)")
    if cfg.env.get("backend") == "sumo":
        per = collector_rows(cfg)
        if per != 1:
            raise ConfigError(
                "trainer.num_envs", f"{rows} with env.backend=sumo and trainer.collector={kind} (collector_workers="
                f"{workers}) asks for {per} SUMO simulations in one process; libsumo runs one per process",
                f"trainer.num_envs=1, or one SUMO process per row: trainer.collector=multi_sync "
                f"trainer.collector_workers={rows} (or multi_async / ray)" if "collector" in tc else
                f"trainer.num_envs=1 (trainer={tc.kind} collects in one process)")


def make_collector(cfg: DictConfig, env: EnvBase, policy, *, resume: dict | None = None):
    """The TorchRL collector of a training loop and its batch arithmetic.

    ``trainer.collector`` picks TorchRL's own collector:

    - ``single`` (default): :class:`torchrl.collectors.Collector` stepping ``env`` in this
      process; with ``trainer.desync_start`` (and not resuming) the rows start at
      spread-out points of their episode clock.
    - ``multi_sync``: :class:`~torchrl.collectors.MultiSyncCollector`, ``collector_workers``
      processes each stepping ``num_envs / collector_workers`` rows; every batch stacks all
      workers' rollouts (``[num_envs, rollout_len]``, the same shape as ``single``).
    - ``multi_async``: :class:`~torchrl.collectors.MultiAsyncCollector`, the same workers,
      each batch is one worker's rollout (``[num_envs / workers, rollout_len]``) as soon
      as it is ready (the other workers keep stepping meanwhile, one policy version behind).
    - ``ray``: :class:`~torchrl.collectors.distributed.RayCollector` (``sync=True``), one
      Ray actor per worker, on ``trainer.ray_address`` (null: a local Ray started with
      ``collector_workers`` CPUs; ``auto``: the running cluster).

    Past one process, each worker builds its own env (:func:`make_worker_env`, seed
    :func:`worker_seed`; ``desync_start`` through :class:`DesyncStart`), so the SUMO
    backend runs one simulation per worker; the loop pushes the new weights after each
    update with ``collector.update_policy_weights_()``. ``env`` is then only used for
    specs. Returns ``(collector, frames_per_batch, n_iterations)``.
    """
    from torchrl.collectors import Collector

    check_collector_config(cfg)
    tc = cfg.trainer
    kind = tc.get("collector", "single")
    fpb = tc.num_envs * tc.rollout_len
    if kind == "single":
        n_iters = max(1, math.ceil(tc.total_frames / fpb))
        collector = Collector(env, policy, frames_per_batch=fpb, total_frames=-1, device=cfg.device,
                              auto_register_policy_transforms=False)
        if tc.get("desync_start", False) and resume is None:
            desynchronize(env, cfg.seed)
        return collector, fpb, n_iters
    import functools

    workers, rows = int(tc.collector_workers), collector_rows(cfg)
    start_iter = int(resume["iteration"]) if resume is not None else 0
    desync = bool(tc.get("desync_start", False)) and resume is None
    factories = [functools.partial(make_worker_env, cfg, rows, worker_seed(cfg.seed, i, start_iter), desync)
                 for i in range(workers)]
    if kind == "multi_async":
        fpb = rows * tc.rollout_len  # one worker's rollout a batch
    n_iters = max(1, math.ceil(tc.total_frames / fpb))
    common = dict(frames_per_batch=fpb, total_frames=-1, device=cfg.device)
    if kind in ("multi_sync", "multi_async"):
        from torchrl.collectors import MultiAsyncCollector, MultiSyncCollector

        cls = MultiSyncCollector if kind == "multi_sync" else MultiAsyncCollector
        collector = cls(factories, policy, **common, auto_register_policy_transforms=False)
    else:
        try:
            import ray  # noqa: F401
        except ImportError:
            from mixed_traffic.validation import ConfigError

            raise ConfigError("trainer.collector", "'ray' needs Ray, which is not installed",
                              "'single', 'multi_sync', 'multi_async', or install the extra: pip install "
                              "'mixed-traffic[ray]'") from None
        from torchrl.collectors.distributed import RayCollector

        address = tc.get("ray_address")
        init = {"address": address} if address else {"num_cpus": workers}
        common["total_frames"] = n_iters * fpb  # RayCollector stops at once with total_frames=-1
        collector = RayCollector(factories, policy, **common, sync=True, num_collectors=workers,
                                 collector_class=Collector, ray_init_config=init,
                                 remote_configs={"num_cpus": 1},
                                 collector_kwargs={"auto_register_policy_transforms": False})
    collector.update_policy_weights_(policy)
    return collector, fpb, n_iters
