"""Structured configs (the schema of ``hydra_configs/``), registered in Hydra's ConfigStore.

Every YAML file of a config group starts from one of the schemas below
(``defaults: [<schema name>]``), so a misspelt key or a value of the wrong type fails at
start-up with Hydra's own message, e.g.::

    $ mt-train loss.clip_epsilom=0.2
    Could not override 'loss.clip_epsilom'. ... Key 'clip_epsilom' not in 'PPOLossConfig'

Groups and their schemas (``name`` registered in group ``group``):

| group | schema (ConfigStore name) | dataclass |
|---|---|---|
| env | ``env_schema`` | :class:`EnvConfig` |
| transforms | ``transforms_schema`` | :class:`TransformsConfig` |
| policy | ``policy_schema`` | :class:`PolicyConfig` |
| loss | ``ppo_schema``, ``dqn_schema``, ``q_learning_schema`` | :class:`PPOLossConfig`, :class:`DQNLossConfig`, :class:`QLearningLossConfig` |
| trainer | ``on_policy_schema``, ``off_policy_schema``, ``tabular_schema`` | :class:`OnPolicyTrainerConfig`, ... |
| logger | ``logger_schema`` | :class:`LoggerConfig` |
| (top level) | ``base_config`` | :class:`Config` (``eval`` is :class:`EvalConfig`) |

Call :func:`register_configs` (idempotent; importing this module does it) before
composing: the apps and tests do.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any  # noqa: UP035  (OmegaConf needs typing generics)

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, DictConfig

# ----------------------------------------------------------------------------- env


@dataclass
class EnvConfig:
    """Which environment to build: ``make_env(scenario, backend=..., batch_size=num_envs, **overrides)``.

    The named fields are the scenario fields the experiments change; ``None`` keeps the
    preset's value. Any other scenario field goes in ``overrides`` (validated by
    :func:`mixed_traffic.scenarios.get_scenario`, which names unknown fields):
    ``env.overrides.ring_length=230`` works as is (no ``+`` needed: ``overrides`` is the
    one open node of the config; a misspelt field name fails when the env is built). The apps
    pass ``env.profile_kwargs.<arg>=v`` as ``++...`` too, so a profile's argument the experiment
    does not set (``random_mix``'s ``weights``) needs no ``+`` either; the profile names a misspelt one.
    ``num_envs`` lives in the trainer (rows stepped together).
    """

    scenario: str = "ring"
    backend: str = "torch"
    observation: str | None = None  # "seed" ([v/30, p/L]), "relative" (per-CAV physical features), "relative_accel"
    # ("relative" + the leader's acceleration), "relative_no_speed" ("relative" less the CAV's speed),
    # "relative_time" ("relative" + the time since engaging, saturating at 30 s) or "wave"
    profile: str | None = None
    profile_kwargs: dict[str, Any] | None = None
    episode_seconds: float | None = None
    weight_v: float | None = None
    weight_s: float | None = None
    weight_u: float | None = None
    s_min: float | None = None
    s_max: float | None = None
    hdv_param_noise: float | None = None
    # SUMO's speed mode 95 for the CAVs on either backend (the seed's PPO / DQN / Q-learning ran with it)
    sumo_safety: bool | None = None
    overrides: Any = field(default_factory=lambda: DictConfig({}, flags={"struct": False}))


# ----------------------------------------------------------------------------- transforms


@dataclass
class SafetyLayerConfig:
    """One-step safety filter: s_min clips the action down, s_max (head gap) clips it up.

    ``s_max: null`` switches the head-gap bound off (rings without a head, ``ring_wave``).
    """

    s_min: float = 5.0
    s_max: float | None = 40.0
    mode: str = "stopping"  # "stopping": collision-free under bounded braking; "one_step": the seed's rule
    # a head gap beyond s_max: "push" (full acceleration back), "hold" (keep it from growing) or
    # "ramp" (hold, and push with a demand rising at ramp_jerk m/s^3 from the current acceleration) or
    # "recover" (close it at least at (gap - s_max) / recover_seconds)
    beyond_s_max: str = "push"
    # the rule beyond s_max where the chain is built for evaluation or deployment (null: beyond_s_max, as in
    # training); the layer's s_min rule, its guarantee, is the same either way
    deployed_beyond_s_max: str | None = None
    # false: where the chain is built for evaluation or deployment the layer keeps only its s_min rule, its
    # guarantee, and the band's upper edge is the policy's own (as the band bar measures it, without the layer)
    deployed_s_max: bool = True
    ramp_jerk: float = 1.0
    recover_seconds: float = 5.0
    # during the first hold_seconds of an episode a head gap beyond s_max is only held (0: push from the start)
    hold_seconds: float = 0.0
    # measurement margins of the s_min rule (m, m/s): it holds for the worst state within them of the measured
    # one (eval.sensor_noise_margin sets them from the evaluation's noise)
    gap_margin: float = 0.0
    speed_margin: float = 0.0


@dataclass
class ResidualDamperConfig:
    """``residual_damper`` in the chain: executed = clip(damper(state) + weight * action).

    ``base`` is a wave damper of :mod:`mixed_traffic.controllers.dampers` (``pi_saturation``,
    ``follower_stopper``, ``idm``); the policy learns a bounded correction to it.
    """

    base: str = "pi_saturation"
    weight: float = 0.5


@dataclass
class InterventionCostConfig:
    """The safety layer's intervention added to the constraint cost (``transforms.InterventionCost``).

    Per step: ``coef * c_int`` with ``c_int`` = ``|delta| / (action range)`` (``magnitude``),
    the clip flag (``indicator``) or their mean (``both``); ``direction`` counts every
    correction (``both``), only the layer's braking (``brake``) or only its push-ups (``push``).
    """

    coef: float = 1.0
    mode: str = "both"
    direction: str = "both"


@dataclass
class SensorNoiseConfig:
    """``sensor_noise`` in the chain: the measurement noise the policy trains under (``transforms.SensorNoise``,
    and with ``filter`` a ``transforms.MeasurementFilter`` of it behind).

    Errors of standard deviation ``gap`` (m) on every gap and ``speed`` (m/s) on every speed the CAV measures,
    correlated over ``tau`` s (0: white). Training only, like ``v2v_channel``: the evaluation's noise is
    ``eval.sensor_noise_*`` (none by default) and its filter ``eval.sensor_filter``. The draws are seeded by
    ``seed`` plus the env's own seed, so every worker draws its own and a run repeats under its seed. With
    ``filter`` and a ``v2v_channel`` in the chain, the channel must come first (checked at start-up), and the
    filter reads the link as the evaluation's filter reads ``eval.v2v_*``'s: a late link as a late measurement,
    a lossy one with less trust, a dead or late and lossy one not at all.
    """

    gap: float = 0.0  # m
    speed: float = 0.0  # m/s
    tau: float = 0.0  # s
    filter: bool = False
    seed: int = 0


@dataclass
class V2VChannelConfig:
    """``v2v_channel`` in the chain: the V2V link the policy trains over (``transforms.V2VChannel``).

    Every message of the leader's acceleration arrives ``delay`` seconds late (a multiple of the env's step)
    and is lost with probability ``loss``, the last one received held. Training only, like ``jerk_penalty``:
    the evaluation's link is ``eval.v2v_delay`` / ``eval.v2v_loss`` (perfect by default). The loss draws are
    seeded by ``seed`` plus the env's own seed, so every worker draws its own and a run repeats under its seed.
    """

    delay: float = 0.0  # s
    loss: float = 0.0
    seed: int = 0


@dataclass
class OnboardAccelConfig:
    """``onboard_accel`` in the chain: the leader's acceleration from the CAV's own measurement of its speed
    (``transforms.OnboardLeaderAccel``) wherever the V2V message it holds is older than ``after`` seconds (null:
    always, a CAV without V2V). The estimate is the measured leader speed's change over a step, low-passed over
    ``tau`` seconds (0: none). Put it after ``v2v_channel`` where the chain has one; the evaluation's link, noise
    and filter (``eval.*``) come before the whole chain. Over the perfect link it replaces nothing."""

    after: float | None = 1.0  # s
    tau: float = 0.0  # s


@dataclass
class JerkLimitConfig:
    """``jerk_limit`` in the chain: the command moves at most ``max_jerk * dt`` from the current acceleration."""

    max_jerk: float = 2.0  # m/s^3


@dataclass
class JerkPenaltyConfig:
    """Training-only smoothness term ``r -= weight * |a_t - a_{t-1}| / (action range)``."""

    weight: float = 1.0
    weight_after: float | None = None  # the weight from after_seconds of the episode on (null: weight throughout)
    after_seconds: float = 0.0


@dataclass
class SpeedLawConfig:
    """A classical law that takes over the residual's base by speed
    (``mixed_traffic.controllers.classic.SpeedScheduledCAV``): the laws below it (``transforms.residual.base``,
    then ``high_speed``) drive below ``v_low``, this one above ``v_high`` (m/s), a linear blend between.
    ``base`` null (the default): off. Used three times, as ``transforms.residual.high_speed``, ``top_speed`` and
    ``beyond_speed``.
    """

    base: str | None = None  # "idm", "ovm", "soft" or "cacc"; null: off
    params: Any = field(default_factory=lambda: DictConfig({}, flags={"struct": False}))
    v_low: float = 10.0
    v_high: float = 16.0
    # this law brakes at most max(brake_floor, |a_leader| + brake_margin) (m/s^2), the leader's acceleration
    # read over V2V (mixed_traffic.controllers.classic.LeaderBrakeFloor); null: off
    brake_floor: float | None = None
    brake_margin: float = 0.3


SPEED_LAWS = ("high_speed", "top_speed", "beyond_speed")  # ResidualConfig's SpeedLawConfig fields, in order


@dataclass
class CatchUpConfig:
    """``transforms.residual.catch_up``: the base lifted toward ``accel`` (m/s^2) while its leader pulls away
    from a large gap (``mixed_traffic.controllers.classic.CatchUp``): not at all up to ``gaps[0]`` (m) or while
    the leader is not faster, fully from ``gaps[1]`` with the leader ``dv`` (m/s) or more faster. ``horizon``
    (s, >= 0): the gate reads the gap projected this far ahead, ``gap + horizon (v_leader - v)^+``; 0: the gap
    itself. ``when``: ``always`` (training and deployment) or ``deploy`` (only where the policy is evaluated or
    deployed, as ``envelope_fade: deploy``: the policy trains on the base without it, weights unchanged).
    ``accel`` null (the default): off.
    """

    accel: float | None = None  # m/s^2; null: off
    gaps: Any = field(default_factory=lambda: [15.0, 25.0])  # [from, full] (m)
    dv: float = 4.0  # m/s
    horizon: float = 0.0  # s; the gate reads gap + horizon * (v_leader - v)^+
    when: str = "always"  # "always" or "deploy" (evaluation and deployment only)


@dataclass
class FeedForwardConfig:
    """``transforms.residual.feed_forward``: the leader's acceleration, received over V2V and clipped to
    ``accel_max`` (m/s^2), times ``gain`` added to the base above ``speeds`` (``[v_off, v_on]`` m/s, by the CAV's
    own speed, linearly between), inside the base's catch-up and stopping envelope
    (``mixed_traffic.controllers.classic.LeaderAccelFeed``). A smooth head's speed swings (a sine's acceleration
    stays within a few tenths of m/s^2) then reach the CAV in phase, so the gap stays put, while the head's
    harder ramps and steps pass only up to ``accel_max``. ``when``: ``deploy`` (only where the policy is evaluated
    or deployed, as ``catch_up.when``) or ``always``. ``gain`` null (the default): off.
    """

    gain: float | None = None  # in (0, 1]; null: off
    accel_max: float = 0.25  # m/s^2
    speeds: Any = field(default_factory=lambda: [18.0, 20.0])  # [v_off, v_on] (m/s)
    when: str = "deploy"  # "always" or "deploy"


@dataclass
class StandArrivalConfig:
    """``transforms.residual.stand_arrival`` (needs ``stop_gap``): near the stopping envelope's edge behind a
    braking leader, the base is held at or below the constant deceleration that brings the car to rest
    ``stand_gap`` (m) behind the point where its leader, braking on as it brakes now (over V2V), will stand
    (``StoppingEnvelope(stand_gap=...)``; the leader's braking counted at most ``leader_brake`` m/s^2, null: all
    of it): all of it on the edge at the car's speeds up to ``speeds[0]`` (m/s),
    none from ``slack`` metres of the envelope's margin or from ``speeds[1]``, linear between. Without it a base
    that rides the edge down to a stop ends every stop braking at the car's full braking. ``stand_gap`` null (the
    default): off. It acts in training and deployment alike (a change of the base: retrain). The other defaults are
    the setting of ``experiment=ring_lagrangian_ppo_smooth_stop`` (docs/results.md, "Stops that end on a constant
    deceleration": at 9-12 m/s, or with the leader's braking counted in full, the head's speed steps look like stops).
    """

    stand_gap: float | None = None  # m, > 0; null: off
    speeds: Any = field(default_factory=lambda: [6.0, 9.0])  # [full, none] (m/s)
    slack: float = 3.0  # m: the envelope's margin from which the term acts not at all
    leader_brake: float | None = 1.5  # m/s^2, > 0: the leader's braking counted at most this much; null: all of it


@dataclass
class DriveOffConfig:
    """``transforms.residual.drive_off``: after a standstill the executed command (base plus residual) is capped at
    ``gain * (v_leader + overspeed - v)`` until the CAV has matched its leader for ``release`` s
    (:class:`transforms.DriveOffCap`, placed between the safety layer and the residual): it eases onto its leader's
    speed from below instead of closing the gap by passing it. The cap lifts as the gap projected at ``accel``
    rises through ``gaps`` (m), so the gap stays in the band. ``when``: ``deploy`` (only where the policy is
    evaluated or deployed, as ``catch_up.when``) or ``always``. ``gain`` null (the default): off. A long ``release``
    (the default experiment's 40 s) keeps the cap through the leader's next hold and into its next stop.
    ``residual_play`` (m/s^2, > 0, or null): while the cap is engaged, the learned residual's term passes through
    a backlash of this half-width (``transforms.ResidualAction(play=..., play_key=("drive_off", "engaged"))``): it
    holds its level and drops the policy's small reversals behind a leader that drives off; null (the default): off.
    ``residual_play_release`` (s, > 0, or null): when the cap releases, the backlash's half-width shrinks to 0 over
    this time instead of at once (``ResidualAction(play_release=...)``), so the held term reaches the policy's
    without a step; null (the default): at once.
    ``follow`` (share, in (0, 1.5], or null): while the cap is engaged and the leader accelerates by more than
    ``follow_above`` (m/s^2), the command is at least ``min(follow * a_leader, cap)``: the CAV keeps up with a long
    drive-off from its start; null (the default): off.
    ``hold`` (bool): while the leader stands (below ``standstill``), the overspeed allowance grows from 0 with its
    speed, so the CAV stands behind a stopped leader instead of creeping toward it (``DriveOffCap(hold=True)``);
    false (the default): the allowance throughout.
    """

    gain: float | None = None  # 1/s; null: off
    overspeed: float = 0.15  # m/s
    gaps: Any = field(default_factory=lambda: [34.0, 38.0])  # [from, full] (m)
    accel: float = 1.5  # m/s^2
    release: float = 5.0  # s (matched, the command under the cap, before the cap releases)
    standstill: float = 0.5  # m/s: the car and its leader both below it engage the cap
    when: str = "deploy"  # "always" or "deploy"
    residual_play: float | None = None  # m/s^2: the residual's backlash while the cap is engaged; null: off
    residual_play_release: float | None = None  # s: the backlash's width shrinks to 0 over this after the release
    follow: float | None = None  # share of the leader's acceleration kept as a floor while engaged; null: off
    follow_above: float = 0.3  # m/s^2: the leader's acceleration above which that floor holds
    hold: bool = False  # the CAV stands while its leader stands (no overspeed allowance behind a stopped leader)


@dataclass
class AnswerConfig:
    """``transforms.residual.answer``: above ``speeds`` (``[v_off, v_on]`` m/s, by the CAV's own speed, linearly
    between) the command is the committed answer (:class:`transforms.CommittedAnswer`, placed between the join and
    the residual): a speed difference beyond ``start`` (m/s) starts an answer with a time to go of ``horizon`` (s)
    that counts down, commanding ``dv / max(time to go, horizon_min)`` (behind a step: one acceleration held for
    ``horizon - horizon_min`` s, then eased off), ended when ``dv`` has closed to ``done`` (m/s); the
    gap floats inside ``gaps`` (``[low, high]`` m; the constant acceleration that matches the leader at the edge
    ahead where that asks for more, ``ks_edge`` (1/s^2) beyond them), bounded by an IDM term (``idm``: ``v0``,
    ``T``, ``a``, ``b``, ``s0``; null: none) and by the base's stopping envelope (``stop_gap`` and its arrival and
    stand terms; none where the base has no ``stop_gap``); with ``catch_up`` the base's catch-up lifts it inside that
    envelope, as it lifts the band law. ``when``: ``deploy`` (only where the policy is evaluated
    or deployed, as ``catch_up.when``) or ``always``. ``horizon`` null (the default): off.
    """

    horizon: float | None = None  # s; null: off
    horizon_min: float = 3.0  # s
    start: float = 0.3  # m/s
    done: float = 0.05  # m/s
    gaps: Any = field(default_factory=lambda: [6.1, 35.0])  # [low, high] (m)
    ks_edge: float = 0.077  # 1/s^2
    speeds: Any = field(default_factory=lambda: [18.0, 20.0])  # [v_off, v_on] (m/s)
    idm: Any = field(default_factory=lambda: {"v0": 60.0, "T": 0.3, "a": 1.834, "b": 5.0, "s0": 4.571})
    catch_up: bool = False  # the base's catch-up (transforms.residual.catch_up) lifts the answer inside the envelope
    when: str = "deploy"  # "always" or "deploy"


@dataclass
class JoinConfig:
    """``transforms.residual.join``: a CAV that starts farther than ``gap`` (m) behind its leader joins it under a
    classical law (``base`` with ``params``, as :func:`mixed_traffic.controllers.classic.make_classic_policy` takes
    them, inside the base's stopping envelope of ``stop_gap``), and the policy's command (base plus residual) takes
    over linearly over ``fade`` (s) from the first step at which the gap is at or below ``gap``, or at the latest
    from the episode time ``seconds`` (s, or null: no such limit); with ``leader_speeds`` (``[v_off, v_on]`` m/s,
    or null) the join law's part grows linearly with the leader's speed between the two, so the policy drives a
    join behind a slow leader (:class:`transforms.JoinBlend`, placed between the safety layer and the residual). A
    CAV that starts at or below ``gap`` is driven by the policy from the start. ``when``: ``deploy`` (only where the policy is evaluated or
    deployed, as ``catch_up.when``) or ``always``. ``base`` null (the default): off. ``fast_params`` with
    ``fast_leader_speeds`` (``[v1, v2]`` m/s): behind a leader at or above ``v2`` the join law is ``base`` with
    ``params`` updated by ``fast_params``, at or below ``v1`` with ``params`` alone, blended linearly between
    (:class:`mixed_traffic.controllers.classic.SpeedScheduledCAV` on the leader's speed); both null: one law.
    """

    base: str | None = None  # "idm", "ovm", "soft" or "cacc"; null: off
    params: Any = field(default_factory=lambda: DictConfig({}, flags={"struct": False}))
    gap: float = 35.0  # m: the gap at or below which the CAV has joined
    fade: float = 10.0  # s: the handover to the policy's command
    seconds: float | None = None  # s: the handover begins at the latest at this episode time; null: only at gap
    leader_speeds: Any = None  # [v_off, v_on] (m/s): the join law's part grows with the leader's speed; null: all
    when: str = "deploy"  # "always" or "deploy"
    fast_params: Any = None  # params' overrides behind a fast leader (with fast_leader_speeds); null: one law
    fast_leader_speeds: Any = None  # [v1, v2] (m/s): params alone at or below v1, with fast_params at or above v2


@dataclass
class ResidualConfig:
    """``residual_idm`` in the chain: executed = clip(base(state) + weight * action) (bounded residual).

    ``params`` override the base model's parameters (``transforms.residual.params.s0=6.0``: an IDM
    that stops 6 m behind its leader); unknown names fail when the env is built, naming the allowed ones.
    ``engage_seconds`` (s, >= 0): the residual's weight rises linearly from 0 at the episode's start
    to ``weight`` at this time (a bumpless engagement: the base drives alone at first); 0: at once.
    ``high_speed`` (:class:`SpeedLawConfig`): a second law that takes the base over by speed;
    ``top_speed`` (the same fields): a third that takes over from the first two (scheduled as one) above
    its own ``v_low`` / ``v_high``; ``beyond_speed`` (the same fields): a fourth that takes over from the
    first three in the same way, e.g. above the speeds the policy trains on, where ``fade_speeds`` has faded
    the residual out and this law alone drives.
    ``fade_speeds`` (``[v_full, v_zero]`` m/s, or null): the residual's weight falls linearly from full at
    the car's own speed ``v_full`` to 0 at ``v_zero``, so that above the speeds the policy trained on the
    base drives (``transforms.ResidualAction``).
    ``stop_gap`` (m, > 0, or null): the base never commands more than the largest acceleration that keeps
    every future gap at or above ``stop_gap`` if the leader brakes as hard as it can from the next step on
    (``mixed_traffic.controllers.classic.StoppingEnvelope``, the safety layer's stopping rule as a term of
    the base); null: no envelope.
    ``arrive_gain`` (1/s^2, > 0, or null; needs ``stop_gap``): inside the envelope the base's law is also held
    below an arrival term that reaches the envelope's braking where the constant deceleration matching a slower
    leader's speed at ``stop_gap`` does, so in the last metres before a standstill the law hands over to that
    smooth term instead of to the envelope's bound at full braking (``StoppingEnvelope(arrive_gain=...)``);
    null: off.
    ``catch_up`` (:class:`CatchUpConfig`): the base (inside the envelope) lifted toward an acceleration while
    its leader pulls away from a large gap; off by default.
    ``feed_forward`` (:class:`FeedForwardConfig`): above a speed, the leader's acceleration (clipped) fed forward
    into the base (inside the envelope, under the catch-up); off by default.
    ``stand_arrival`` (:class:`StandArrivalConfig`; needs ``stop_gap``): near the envelope's edge the base is
    held at or below a constant deceleration to rest behind where a braking leader will stand; off by default.
    ``drive_off`` (:class:`DriveOffConfig`): after a standstill, the command capped so that the CAV eases onto
    its leader's speed from below; off by default.
    ``join`` (:class:`JoinConfig`): a CAV that starts far behind its leader joins it under a classical law and
    then hands over to the policy's command; off by default.
    ``envelope_fade`` (``off``, ``always`` or ``deploy``; not ``off`` needs ``stop_gap``): a residual that
    accelerates fades out as the base nears its envelope (``ResidualAction(room_key=...)``), so base +
    residual never exceeds it; a braking residual is left as it is. ``always``: in training too;
    ``deploy``: only where the policy is evaluated or deployed (the evaluation harness, ``mt-eval``), so
    training still pays the safety layer's price for leaning on that bound instead of being faded silently.
    ``envelope_fade_slack`` (m, > 0, or null): while the car closes on its leader it also fades linearly as
    the envelope's margin in metres (``StoppingEnvelope.slack``) falls from this value to 0, so the fade
    begins before the bound is reached; null: the room below the envelope alone.
    ``envelope_fade_slack_below`` (m/s, > 0, or null) and ``envelope_fade_slack_brake`` (m/s^2, > 0, or null),
    with ``envelope_fade_slack``: the margin fade acts only behind a leader slower than the first or braking
    harder than the second (its acceleration over V2V), so where a stop is under way and not while the car
    follows a leader that slows gently at speed; both null: behind any leader.
    ``saturate_base``: true clips the base's command to the action bounds before the residual is added;
    false adds the residual to the base's own command and clips the sum once, so where the base asks for
    more braking than the actuator has, a residual cannot take part of the braking back.
    """

    base: str = "idm"  # "idm", "ovm", "soft" or "cacc" (mixed_traffic.controllers.classic)
    weight: float = 0.5
    params: Any = field(default_factory=lambda: DictConfig({}, flags={"struct": False}))  # no "+" needed
    engage_seconds: float = 0.0
    high_speed: SpeedLawConfig = field(default_factory=SpeedLawConfig)
    top_speed: SpeedLawConfig = field(default_factory=SpeedLawConfig)
    beyond_speed: SpeedLawConfig = field(default_factory=SpeedLawConfig)
    fade_speeds: Any = None  # [v_full, v_zero] (m/s) or null
    catch_up: CatchUpConfig = field(default_factory=CatchUpConfig)
    feed_forward: FeedForwardConfig = field(default_factory=FeedForwardConfig)
    stand_arrival: StandArrivalConfig = field(default_factory=StandArrivalConfig)
    drive_off: DriveOffConfig = field(default_factory=DriveOffConfig)
    join: JoinConfig = field(default_factory=JoinConfig)
    answer: AnswerConfig = field(default_factory=AnswerConfig)
    stop_gap: float | None = None  # m, > 0; null: no stopping envelope on the base
    arrive_gain: float | None = None  # 1/s^2, > 0: the base's law held below an arrival at stop_gap; null: off
    # the envelope's measurement margins (m, m/s), as the safety layer's (eval.sensor_noise_margin sets them)
    gap_margin: float = 0.0
    speed_margin: float = 0.0
    envelope_fade: str = "off"  # "off", "always", "deploy": the residual's push fades out near the envelope
    envelope_fade_slack: float | None = None  # m, > 0: ... from this margin of the envelope on; null: at the bound
    envelope_fade_slack_below: float | None = None  # m/s, > 0: that margin fade only behind a leader slower than this
    envelope_fade_slack_brake: float | None = None  # m/s^2, > 0: ... or one braking harder than this
    saturate_base: bool = True


@dataclass
class ResidualNNMPCConfig:
    """``residual_nnmpc`` in the chain (RLMPC): executed = clip(NNMPC(window) + weight * action), action in [-1, 1].

    ``checkpoint``: the frozen NNMPC (see :mod:`mixed_traffic.controllers.deeplcc.rlmpc`).
    """

    checkpoint: str = "outputs/deeplcc/nnmpc/nnmpc_bc_relabelled.pt"
    weight: float = 1.0


@dataclass
class NonNegativeRewardConfig:
    """Reward ``max(J_max - J, 0) / J_max`` in [0, 1]; a collision gives ``collision_reward``."""

    collision_reward: float = -1.0


@dataclass
class ProfileRewardConfig:
    """:class:`transforms.ProfileNormalisedReward`: ``max(J_max[p] - J, 0) / J_max[p]`` per head profile ``p``.

    ``J_max``: ``{profile: value > 0}`` for every profile the env draws (the platoon's ``profiles``).
    """

    J_max: dict[str, float] = field(default_factory=dict)
    collision_reward: float = -1.0


@dataclass
class CounterfactualRewardConfig:
    """:class:`transforms.CounterfactualReward`: ``max(0, offset + (J_twin - J) / (scale J_ref[p]))``.

    The twin is driven by the NNMPC of ``checkpoint`` on the same disturbances; ``J_ref``:
    ``{profile: the NNMPC's mean stage cost per step > 0}`` for every profile the env draws.
    """

    checkpoint: str = "outputs/deeplcc/nnmpc/nnmpc_bc_relabelled.pt"
    J_ref: dict[str, float] = field(default_factory=dict)
    scale: float = 5.0
    offset: float = 1.0
    collision_reward: float = -1.0


@dataclass
class SetPointConfig:
    """``set_point`` in the chain: the policy sets FollowerStopper's set point, ``U = U_uniform (ratio0 + weight a)``.

    ``a`` in [-1, 1] per CAV (:class:`transforms.SetPointAction`); ``U_uniform`` is the ring's
    uniform-flow speed (the humans' IDM at spacing ``L / n``). With ``rate`` set, the action
    moves the ratio instead, ``ratio += rate a`` per step within ``[low, high]`` from ``ratio0``.
    With ``ramp_to`` set, ``ratio0`` becomes the ramped FollowerStopper's schedule (``ratio0``
    until ``ramp_start``, linear to ``ramp_to`` at ``ramp_end``) and the action corrects it.
    """

    ratio0: float = 0.9
    weight: float = 0.1
    rate: float | None = None  # set: the action is the ratio's rate of change per step (ratio kept in [low, high])
    low: float = 0.8
    high: float = 1.05
    ramp_to: float | None = None  # set: a = 0 follows the schedule ratio0 -> ramp_to over [ramp_start, ramp_end] s
    ramp_start: float = 150.0
    ramp_end: float = 300.0


@dataclass
class BlendConfig:
    """``blend`` in the chain: the policy moves the weight ``m`` of ``(1 - m) first + m second``.

    ``first`` and ``second`` are wave dampers named as in ``eval.wave.controllers``
    (``name:key=number;...``, :func:`mixed_traffic.controllers.dampers.make_damper`).
    ``m = b(t) + c``: the schedule ``b`` (``weight0`` until ``start``, linear to ``weight1`` at
    ``end`` s) plus the policy's correction, ``c += rate a`` per step, ``m`` kept in [0, 1]
    (:class:`transforms.ControllerBlend`): at ``a = 0`` the classical hand-over, e.g. the
    ``fs_then_pi`` damper.
    """

    first: str = "follower_stopper:u_ratio=0.87;ramp_to=1.0"
    second: str = "pi_saturation"
    rate: float = 0.001  # correction per step at |a| = 1
    weight0: float = 0.0
    weight1: float = 1.0
    start: float = 300.0
    end: float = 330.0


@dataclass
class DiscretizerConfig:
    """State bins for tabular Q (per observation dim) and action bins for DQN / tabular Q."""

    state_bins: int = 20
    action_bins: int = 21


@dataclass
class BarrierForceConfig:
    """Intersection barrier force filter (``transforms.barrier_force.BarrierForce``): ``u = v + rho dB_u + K dB_x``."""

    rho: float = 0.2
    K: float = 0.5


@dataclass
class ResidualNMPCConfig:
    """``residual_nmpc`` in the chain: executed = clip(a_nmpc + weight * action) around the intersection NMPC."""

    weight: float = 1.0


@dataclass
class ConflictCostConfig:
    """Training-only intersection costs (``transforms.ConflictCost``), added to ``("next", "cost")``.

    ``anticipation`` weighs the distance cost at the closest predicted approach over the next
    ``horizon_s`` seconds (constant velocities); ``out_of_bounds`` is charged on leaving the road;
    ``ego_caused`` charges only the part of the predicted conflict the ego's own motion adds;
    ``margin`` (m) widens the separation the predicted approach is charged for.
    """

    anticipation: float = 1.0
    horizon_s: float = 1.5
    out_of_bounds: float = 150.0
    ego_caused: bool = False
    margin: float = 0.0


@dataclass
class TransformsConfig:
    """The env-side transform chain, applied in ``chain`` order.

    Known names: ``non_negative_reward``, ``safety_layer``, ``intervention_cost`` (after the
    layer), ``residual_idm`` (after the layer: the layer clips the sum), ... (see
    :data:`mixed_traffic.training.builders.TRANSFORMS`; an unknown name fails at start-up).
    The Lagrangian penalty belongs to ``loss=lagrangian_ppo`` (lambda is an optimisation
    variable, updated by dual ascent after each batch in the main process).
    """

    chain: list[str] = field(default_factory=lambda: ["non_negative_reward"])
    safety_layer: SafetyLayerConfig = field(default_factory=SafetyLayerConfig)
    residual_damper: ResidualDamperConfig = field(default_factory=ResidualDamperConfig)
    intervention_cost: InterventionCostConfig = field(default_factory=InterventionCostConfig)
    residual: ResidualConfig = field(default_factory=ResidualConfig)
    residual_nnmpc: ResidualNNMPCConfig = field(default_factory=ResidualNNMPCConfig)
    jerk_penalty: JerkPenaltyConfig = field(default_factory=JerkPenaltyConfig)
    jerk_limit: JerkLimitConfig = field(default_factory=JerkLimitConfig)
    v2v_channel: V2VChannelConfig = field(default_factory=V2VChannelConfig)
    onboard_accel: OnboardAccelConfig = field(default_factory=OnboardAccelConfig)
    sensor_noise: SensorNoiseConfig = field(default_factory=SensorNoiseConfig)
    non_negative_reward: NonNegativeRewardConfig = field(default_factory=NonNegativeRewardConfig)
    profile_reward: ProfileRewardConfig = field(default_factory=ProfileRewardConfig)
    counterfactual_reward: CounterfactualRewardConfig = field(default_factory=CounterfactualRewardConfig)
    set_point: SetPointConfig = field(default_factory=SetPointConfig)
    blend: BlendConfig = field(default_factory=BlendConfig)
    discretizer: DiscretizerConfig = field(default_factory=DiscretizerConfig)
    barrier_force: BarrierForceConfig = field(default_factory=BarrierForceConfig)
    residual_nmpc: ResidualNMPCConfig = field(default_factory=ResidualNMPCConfig)
    conflict_cost: ConflictCostConfig = field(default_factory=ConflictCostConfig)


# ----------------------------------------------------------------------------- policy


@dataclass
class APGConfig:
    """Analytic-policy-gradient pre-training on the differentiable torch platoon (``iterations: 0``: off).

    ``iterations`` Adam steps, each on the mean over ``num_envs`` rows and ``horizon`` steps of
    ``J / J_ref[profile] + cost_coeff * cost`` (``mixed_traffic.training.apg``).
    """

    iterations: int = 0
    horizon: int = 50
    num_envs: int = 64
    lr: float = 1e-3
    max_grad_norm: float = 1.0
    cost_coeff: float = 10.0
    J_ref: dict[str, float] = field(default_factory=dict)  # per profile kind; 1 where not given
    # chain entries left out of the APG env (e.g. [safety_layer, intervention_cost]: the policy
    # learns to keep its gaps by itself) and a gap (m) below which the CAVs' gap is priced as cost
    without: list[str] = field(default_factory=list)
    gap_margin: float | None = None
    head_gap_max: float | None = None  # ring: a head gap (m) above which the excess is priced as cost ...
    head_gap_after: float = 0.0  # ... from this time (s) into the episode on
    average_last: int = 0  # the policy kept is the mean of the parameters after each of the last N steps (0: the last)


@dataclass
class CEMConfig:
    """Cross-entropy-method training of the actor on whole-episode scores (``generations: 0``: off).

    Each generation runs ``population`` parameter vectors around the mean for ``episodes``
    episodes each (one batched rollout) and moves the mean to the best ``elite`` fraction
    (``mixed_traffic.training.cem``).
    """

    generations: int = 0
    population: int = 32
    episodes: int = 8
    elite: float = 0.25
    sigma: float = 0.1  # initial std of the parameter perturbations
    sigma_min: float = 0.01  # floor of the std (keeps the search from collapsing)
    cost_coeff: float = 10.0  # score = mean reward - cost_coeff * (max(mean cost - cost_limit, 0) + collided)
    cost_limit: float = 0.0  # mean cost per step that is free (a budget: the layer's work below it is not penalised)
    seconds: float | None = None  # episode length run (s); null: the scenario's
    score_after: float = 0.0  # the score counts from this time (s) on (a collision before it still counts)
    init: str = "actor"  # the first mean: "actor" (its parameters) or "zero_action" (output layer zeroed: action 0)


@dataclass
class WarmStartConfig:
    """Warm Start RL: before PPO, fit the actor's deterministic action to an NNMPC's (BC on its closed loop).

    ``nnmpc: null`` switches it off.
    """

    nnmpc: str | None = None
    frames: int = 20000
    epochs: int = 30
    lr: float = 1e-3


@dataclass
class PolicyConfig:
    """Network of the learner.

    ``kind``: ``actor_critic`` (PPO: shared tanh trunk, orthogonal init, state-independent
    log-std clamped to [log_std_min, log_std_max], TanhNormal to the action bounds),
    ``qnet`` (DQN: MLP to Q-values over the discretised actions), ``q_table`` (tabular).
    """

    kind: str = "actor_critic"
    hidden: list[int] = field(default_factory=lambda: [256, 256])
    activation: str = "tanh"
    shared_trunk: bool = True
    log_std_init: float = 0.0
    log_std_min: float = -2.0
    log_std_max: float = 0.5
    value_bias_init: float = 0.0  # critic output bias at start (~ expected discounted return)
    warm_start: WarmStartConfig = field(default_factory=WarmStartConfig)
    apg: APGConfig = field(default_factory=APGConfig)
    cem: CEMConfig = field(default_factory=CEMConfig)
    # observation features computed inside the networks: "none" or "intersection"
    # (normalised observation + ego/agent relational features, see mixed_traffic.envs.intersection)
    features: str = "none"
    # further tensordict entries the networks read besides the observation (dotted nested keys,
    # e.g. "residual.base_action": the base controller's action under residual_nmpc)
    extra_in_keys: list[str] = field(default_factory=list)


# ----------------------------------------------------------------------------- losses


@dataclass
class BCConfig:
    """Optional behaviour-cloning term of the PPO losses (``losses.BCLoss`` on cached demonstrations).

    ``coeff > 0`` switches it on: ``pretrain_steps`` Adam steps of BC before the first batch,
    then ``+ w * loss_bc`` on every minibatch, ``w`` going linearly from ``coeff`` to
    ``final_coeff`` over the run. Demonstrations (``observation``, ``expert_action``) come
    from ``demos`` (a ``.pt`` file; made by the ``expert`` on ``episodes`` training episodes
    when missing: ``python -m mixed_traffic.intersection.demos``).
    """

    coeff: float = 0.0
    final_coeff: float | None = None  # None: constant coeff
    pretrain_steps: int = 0
    pretrain_lr: float = 1e-3
    expert: str = "nmpc"
    episodes: int = 384
    agents: str = "mixed"  # "mixed": mixed-style agents; "training": the env's bank shares (close starts, reactive, pausing)
    # NMPCConfig fields of the expert; add one with +loss.bc.expert_overrides.margin=0.25
    expert_overrides: dict[str, Any] = field(default_factory=dict)
    demos: str | None = None  # None: outputs/demos/<expert>_seed<seed>_n<episodes>[_<shares>][_<overrides>].pt


@dataclass
class PPOLossConfig:
    """Clipped PPO (``name=ppo``) or Lagrangian PPO (``name=lagrangian_ppo``).

    Lagrangian PPO: the advantage is computed on ``r - lambda * c`` (c = the env's
    normalised s_min violation ``("next", "cost")``) and after each batch
    ``lambda <- clip(lambda + lambda_lr * (mean(c) - violation_tolerance), 0, lambda_max)``.
    """

    name: str = "ppo"
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_epsilon: float = 0.2
    entropy_coeff: float = 0.01
    critic_coeff: float = 0.5
    clip_value: float | None = None  # value-function clipping (seed LPPO: 0.2)
    normalize_advantage: bool = True
    loss_critic_type: str = "l2"
    # Lagrangian (name=lagrangian_ppo)
    lambda_init: float = 1.0
    lambda_lr: float = 0.05
    lambda_max: float = 10.0
    violation_tolerance: float = 0.1
    lambda_method: str = "dual_ascent"  # "dual_ascent", "adam", "sgd" or "pid" (Stooke et al. 2020)
    lambda_kp: float = 0.0  # pid: proportional gain (the integral gain is lambda_lr)
    lambda_kd: float = 0.0  # pid: derivative gain
    # 1: the reward is penalised (r - lambda c) before one GAE; 2: reward and cost critics, two GAEs,
    # A = (A_R - lambda A_C) / (1 + lambda) in losses.LagrangianPPOLoss (lambda_method dual ascent on the batch cost)
    critics: int = 1
    reward_scale: float = 1.0  # rewards and costs are multiplied by this for the critics (after the lambda update)
    bc: BCConfig = field(default_factory=BCConfig)
    # > 0: residual policies are pulled towards the base controller: + residual_coeff * mean(a_res_det^2)
    residual_coeff: float = 0.0



@dataclass
class DQNLossConfig:
    """Double DQN with a Huber loss and soft target updates."""

    name: str = "dqn"
    gamma: float = 0.99
    double_dqn: bool = True
    loss_function: str = "smooth_l1"
    tau: float = 0.01


@dataclass
class QLearningLossConfig:
    """Tabular TD(0) Q-learning on the discretised state and action."""

    name: str = "q_learning"
    gamma: float = 0.98
    alpha: float = 0.2


# ----------------------------------------------------------------------------- trainers


@dataclass
class _TrainerCommon:
    total_frames: int = 1_000_000  # env transitions (rows x steps) over the whole run
    num_envs: int = 256  # rows of the batched env stepped together
    rollout_len: int = 16  # steps per row per collected batch: frames_per_batch = num_envs * rollout_len
    checkpoint_every: int = 20  # iterations (batches) between checkpoints; 0 disables
    log_every: int = 1
    progress: bool = True  # tqdm bar
    # stop after this wall-clock budget (checkpoint first); a policy.cem search before the run
    # stops before a generation that would end past it, on its own clock
    max_minutes: float | None = None
    max_iterations: int | None = None  # stop after this many iterations in this process (checkpoint first)
    # start the rows at random points of their episode clock, so a batch mixes all phases
    # of the head profile instead of every row meeting the same speed change at once
    desync_start: bool = True


@dataclass
class OnPolicyTrainerConfig(_TrainerCommon):
    kind: str = "on_policy"
    # TorchRL collector: "single" (Collector, this process), "multi_sync" / "multi_async"
    # (MultiSyncCollector / MultiAsyncCollector, `collector_workers` processes, each stepping
    # num_envs / collector_workers rows), "ray" (RayCollector, one Ray actor a worker); see
    # mixed_traffic.training.builders.make_collector and docs/scaling.md
    collector: str = "single"
    collector_workers: int = 1
    ray_address: str | None = None  # collector=ray: null starts a local Ray; "auto" or "<host>:<port>" joins a cluster
    lr: float = 3e-4
    anneal_lr: bool = True
    epochs: int = 6
    minibatch_size: int = 4096
    max_grad_norm: float = 0.5


@dataclass
class OffPolicyTrainerConfig(_TrainerCommon):
    kind: str = "off_policy"
    lr: float = 5e-4
    buffer_size: int = 200_000
    batch_size: int = 128
    start_learning_after: int = 10_000
    updates_per_batch: int = 1
    target_update_every: int = 1  # iterations between soft target updates
    eps_start: float = 1.0
    eps_end: float = 0.1
    eps_decay_frames: int = 500_000
    max_grad_norm: float = 10.0


@dataclass
class TabularTrainerConfig(_TrainerCommon):
    kind: str = "tabular"
    eps_start: float = 1.0
    eps_end: float = 0.05
    eps_decay_frames: int = 1_000_000


# ----------------------------------------------------------------------------- logger / eval


@dataclass
class LoggerConfig:
    """TorchRL logger: ``csv`` (default, no account), ``wandb`` (offline unless mode=online), ``none``."""

    backend: str = "csv"
    project: str = "mixed-traffic"
    mode: str = "offline"
    log_dir: str = "logs"  # relative to the run directory


@dataclass
class WaveEvalConfig:
    """The stop-and-go wave report of rings without a head (``env=ring_wave``).

    Every controller in ``controllers`` (``human``: all-human ring, ``idm``,
    ``follower_stopper``, ``pi_saturation``, and ``policy`` when a checkpoint is given)
    runs the same ``episodes`` per ring length; metrics are taken after ``warmup_seconds``.
    """

    controllers: list[str] = field(default_factory=lambda: ["human", "idm", "follower_stopper", "pi_saturation"])
    ring_lengths: list[float] = field(default_factory=lambda: [260.0])
    episodes: int = 8
    episode_seconds: float = 600.0
    warmup_seconds: float = 300.0
    hard_brake: float = -2.0  # m/s^2: a hard-braking event starts when a vehicle's acceleration drops below this
    safety_layer: bool = True  # run the learned policy behind transforms.safety_layer
    without_layer: bool = True  # ... and without it (raw actions executed)
    # every controller but the all-human ring again behind transforms.safety_layer (rows "<name> (layer)"):
    # what the layer would change of it, and its speed when it must respect the same bound as the policy
    classical_with_layer: bool = False


@dataclass
class EvalConfig:
    """Deterministic evaluation after training (and by ``mt-eval``)."""

    after_train: bool = False  # mt-train evaluates the final policy into <run>/eval (mt-main always does)
    profiles: list[str] = field(default_factory=lambda: ["random_steps", "emergency_brake", "eudc", "sine"])
    episodes: int = 20  # per profile (run as one batch)
    seed: int = 1000  # evaluation seed (different from training seeds)
    episode_seconds: float | None = None  # None: the scenario's
    # per-episode spread of the human drivers' parameters (None: the scenario's, 0 on the ring);
    # > 0 makes the episodes of a deterministic head profile differ from one another
    hdv_param_noise: float | None = None
    settle_seconds: float = 8.0  # steady state: the head's speed held this long
    warmup_seconds: float = 20.0  # ignored at the episode start for tracking metrics
    plot_episode: int = 0  # which episode of each profile is drawn
    # head-profile arguments used by the evaluation (random_steps: the scenario's own)
    profile_kwargs: dict[str, Any] = field(default_factory=lambda: {
        "random_steps": {"v_low": 5.0, "v_high": 20.0, "period": 15.0, "v_init": 10.0},
        "emergency_brake": {"start": 50.0, "v_cruise": 15.0, "v_low": 2.0},
        "eudc": {"v_low": 5.0, "v_high": 20.0},
        "sine": {"v_star": 12.5, "amplitude": 5.0, "period": 40.0},
    })
    # acceptance bar written into the report
    s_min: float = 5.0
    s_max: float = 40.0
    rmse_bar: float = 1.0
    wave: WaveEvalConfig = field(default_factory=WaveEvalConfig)
    intervention_bar: float = 0.05  # largest share of steps the safety layer may change (per profile)
    # a classical controller (e.g. idm: IDM driving the CAV) run on the same episodes when a checkpoint is evaluated,
    # under the task's reward alone (no layer): the report compares the policy's jerk and return with its on every
    # profile, with the layer and without it from the standard start, and the acceptance gains the bars "jerk at most
    # its" and "return at least its" (null: no reference, no such bars)
    reference: str | None = None
    # the reference's rollout runs in a forked second process beside the policy's (the same numbers, the second
    # core's time; the torch backend only): false runs it after the policy's, in this process
    parallel_reference: bool = True
    # the policy itself: every profile again with the safety layer removed (raw actions
    # executed), from the standard start and from each of these start spacings (m)
    without_layer: bool = True
    close_starts: list[float] = field(default_factory=lambda: [8.0, 15.0])
    # the V2V link the CAVs receive their leader's acceleration over (transforms.V2VChannel, first in the
    # evaluated chain when either is > 0): every message late by v2v_delay seconds (a multiple of the env's
    # step), each lost with probability v2v_loss (the last one received is held); CACC and the residual
    # base's brake_floor read it, the gap and the speeds are measured on board and stay exact
    v2v_delay: float = 0.0
    v2v_loss: float = 0.0
    # measurement noise (transforms.SensorNoise, first in the evaluated chain when either is > 0): Gaussian
    # errors of this standard deviation on every gap (m) and every speed (m/s) the CAV measures, correlated over
    # sensor_noise_tau seconds (0: white, drawn afresh each step; seeded by eval.seed); the policy, the
    # residual's base and the safety layer all read the noisy values, the simulation runs on the true ones
    sensor_noise_gap: float = 0.0
    sensor_noise_speed: float = 0.0
    sensor_noise_tau: float = 0.0
    # k >= 0: the deployed safety layer and the residual base's stopping envelope keep their stopping rule for
    # the worst state within k standard deviations of the noise (their gap_margin / speed_margin set to
    # k * sensor_noise_gap / k * sensor_noise_speed); 0: they read the measurements as exact
    sensor_noise_margin: float = 0.0
    # true: a Kalman filter (transforms.MeasurementFilter, after the noise and the V2V link) tracks the noisy gaps
    # and speeds from the CAV's own acceleration and its leader's received over V2V, and everything behind it acts
    # on its estimates; its model is the noise above; sensor_noise_margin then counts the estimates' standard
    # deviations instead of the sensor's; without noise it does nothing
    sensor_filter: bool = False
    # the noise the filter assumes, where it is not the noise drawn (null: sensor_noise_gap / _speed / _tau): a
    # deployed filter's model is an estimate of its sensors
    sensor_filter_gap: float | None = None
    sensor_filter_speed: float | None = None
    sensor_filter_tau: float | None = None


# ----------------------------------------------------------------------------- top level


@dataclass
class Config:
    env: EnvConfig = MISSING
    transforms: TransformsConfig = MISSING
    policy: PolicyConfig = MISSING
    loss: Any = MISSING  # one of the loss schemas
    trainer: Any = MISSING  # one of the trainer schemas
    logger: LoggerConfig = MISSING
    eval: EvalConfig = field(default_factory=EvalConfig)
    name: str = "run"  # experiment name (set by experiment=...)
    seed: int = 0
    device: str = "cpu"
    threads: int = 1  # torch intra-op threads per run (the joblib launcher runs jobs side by side)
    checkpoint: str | None = None  # mt-eval: a checkpoint (.pt) or a run directory to evaluate
    # mt-eval: a classical controller instead ("idm", "ovm", "soft", "cacc"; "base": the experiment's residual base's laws
    # alone; "zero_residual": the experiment's deployed chain with its learned residual at zero; wave rings: a damper
    # or "all")
    controller: str | None = None
    resume: str | None = None  # path to a checkpoint (.pt) or a run directory
    resume_override: bool = False  # resume even though budgets/hyper-parameters differ from the checkpoint's
    out_dir: str = "${hydra:runtime.output_dir}"


_REGISTERED = False


def register_configs() -> None:
    """Register the schemas in Hydra's ConfigStore (safe to call more than once)."""
    global _REGISTERED
    if _REGISTERED:
        return
    cs = ConfigStore.instance()
    cs.store(name="base_config", node=Config)
    cs.store(group="env", name="env_schema", node=EnvConfig)
    cs.store(group="transforms", name="transforms_schema", node=TransformsConfig)
    cs.store(group="policy", name="policy_schema", node=PolicyConfig)
    cs.store(group="loss", name="ppo_schema", node=PPOLossConfig)
    cs.store(group="loss", name="dqn_schema", node=DQNLossConfig)
    cs.store(group="loss", name="q_learning_schema", node=QLearningLossConfig)
    cs.store(group="trainer", name="on_policy_schema", node=OnPolicyTrainerConfig)
    cs.store(group="trainer", name="off_policy_schema", node=OffPolicyTrainerConfig)
    cs.store(group="trainer", name="tabular_schema", node=TabularTrainerConfig)
    cs.store(group="logger", name="logger_schema", node=LoggerConfig)
    _REGISTERED = True


register_configs()

CONFIG_PATH = "pkg://hydra_configs"
CONFIG_NAME = "config"


# compositions already made in this process: (overrides, config name) -> (the config tree's stamp, the config)
_COMPOSED: dict[tuple, tuple] = {}
_COMPOSED_MAX = 256


def config_tree_stamp() -> tuple:
    """``(path, size, mtime)`` of every file of ``hydra_configs``: a kept composition is used while this is unchanged."""
    import os

    import hydra_configs

    root = os.path.dirname(os.path.abspath(hydra_configs.__file__))
    out = []
    for d, _, files in os.walk(root):
        for f in files:
            st = os.stat(os.path.join(d, f))
            out.append((os.path.relpath(os.path.join(d, f), root), st.st_size, st.st_mtime_ns))
    return tuple(sorted(out))


def compose(overrides: list[str] | None = None, config_name: str = CONFIG_NAME, return_hydra_config: bool = False):
    """Compose the project config outside a Hydra app (tests, notebooks, scripts).

    Each composition is kept per ``(overrides, config_name)`` while no file of ``hydra_configs`` changes (size or
    modification time; :func:`config_tree_stamp`), and every call returns a copy of its own to change as it likes:
    Hydra parses each file of the defaults chain again on every compose (about 0.6 s for the default experiment's
    twenty files on the 2-core machine, a deep copy 0.02 s), and the tests and notebooks compose the same overrides
    many times. ``return_hydra_config=True`` is composed afresh each time (its runtime section reads the working
    directory)."""
    import copy

    from hydra import compose as _compose
    from hydra import initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    key = (tuple(overrides or []), config_name)
    stamp = None if return_hydra_config else config_tree_stamp()
    kept = _COMPOSED.get(key) if stamp is not None else None
    if kept is not None and kept[0] == stamp:
        return copy.deepcopy(kept[1])
    register_configs()
    if GlobalHydra.instance().is_initialized():
        GlobalHydra.instance().clear()
    with initialize_config_module(config_module="hydra_configs", version_base="1.3"):
        cfg = _compose(config_name=config_name, overrides=list(overrides or []),
                       return_hydra_config=return_hydra_config)
    if stamp is not None:
        if len(_COMPOSED) >= _COMPOSED_MAX:
            _COMPOSED.pop(next(iter(_COMPOSED)))  # the oldest
        _COMPOSED[key] = (stamp, copy.deepcopy(cfg))
    return cfg
