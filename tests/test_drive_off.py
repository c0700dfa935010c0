"""The drive-off cap (transforms.DriveOffCap and transforms.residual.drive_off)."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Binary
from torchrl.envs import Compose, Transform, TransformedEnv
from torchrl.envs.utils import check_env_specs

from mixed_traffic import make_env
from mixed_traffic.config import compose
from mixed_traffic.controllers.classic import make_classic_policy
from mixed_traffic.training.builders import make_transformed_env
from mixed_traffic.validation import ConfigError, validate_config
from transforms import DriveOffCap, ResidualAction

# the head cruises at 15 m/s, stops for 6 s, drives off at 2 m/s^2 and holds 15 m/s for a long time
STOP = dict(profile="piecewise", profile_kwargs={"times": [0, 10, 17.5, 23.5, 31, 400], "speeds": [15, 15, 0, 0, 15, 15]})


def _idm_rollout(steps: int, *, cap: DriveOffCap | None, batch: int = 1, **env_kw):
    """IDM drives the CAV (a residual of weight 0 over it), with or without the cap after it."""
    base = make_env("ring", batch_size=batch, seed=0, **env_kw)
    ts = ([cap] if cap is not None else []) + [ResidualAction(make_classic_policy("idm", base), weight=0.0)]
    env = TransformedEnv(base, Compose(*ts))
    with torch.no_grad():
        return env, env.rollout(steps, lambda td: td.set("action", torch.zeros(batch, 1)), break_when_any_done=False)


def test_specs_hold():
    base = make_env("ring", batch_size=2, seed=0, **STOP)
    check_env_specs(TransformedEnv(base, Compose(DriveOffCap(dt=base.scenario.dt),
                                                 ResidualAction(make_classic_policy("idm", base), weight=0.5))))


def test_after_a_standstill_the_cav_eases_onto_its_leaders_speed_from_below():
    """IDM alone passes the head's speed by more than 0.5 m/s to close the gap the drive-off opened; under the cap
    it stays within the overspeed until the cap releases."""
    _, free = _idm_rollout(900, cap=None, **STOP)
    _, capped = _idm_rollout(900, cap=DriveOffCap(overspeed=0.15), **STOP)
    def over(td):
        return td["next", "cav", "speed"][0, 310:, 0] - td["next", "cav", "leader_speed"][0, 310:, 0]  # from 31 s
    assert float(over(free).max()) > 0.5
    engaged = capped["next", "drive_off", "engaged"][0, 310:, 0]
    assert bool(engaged[:100].all())
    assert float(over(capped)[engaged].max()) <= 0.15 + 1e-4
    before = capped["next", "drive_off", "engaged"][0, :150, 0]  # the first 15 s: no standstill yet
    assert not bool(before.any())


def test_it_releases_once_matched_and_then_leaves_the_command_alone():
    _, td = _idm_rollout(4000, cap=DriveOffCap(overspeed=0.15, release=5.0), **STOP)
    engaged = td["next", "drive_off", "engaged"][0, :, 0]
    last = int(engaged.nonzero().max())  # released after this step
    assert 400 < last < 3900 and not bool(engaged[last + 1:].any())
    executed, base = td["next", "cav", "accel"][0, last + 2:], td["residual", "base_action"][0, last + 2:]
    torch.testing.assert_close(executed, base, atol=1e-3, rtol=0)  # the base drives again, uncapped
    while_engaged = td["next", "cav", "accel"][0, 320:last] - td["residual", "base_action"][0, 320:last]
    assert float(while_engaged.min()) < -0.1  # ... where before the cap held it back


def test_a_long_release_keeps_the_cap_through_the_leaders_next_hold():
    """The default's ``release: 40``: once both cars have stood still, the cap holds until the CAV has matched its
    leader, with its command under the cap, for ``release`` s. After 20 s matched, a cap of 5 s has handed back to
    the law (a command above the leader's speed passes), one of 40 s still caps it at ``overspeed`` above it."""
    def drive(release):
        cap = DriveOffCap(overspeed=0.15, release=release, dt=0.1)
        engaged, calm = torch.zeros(1, dtype=torch.bool), torch.zeros(1)
        zero = torch.zeros(1)
        _, engaged, calm = cap.apply(zero, torch.tensor([6.0]), zero, zero, engaged, calm)  # both stopped
        v = torch.tensor([15.0])
        for _ in range(200):  # 20 s matched at 15 m/s, the command under the cap
            _, engaged, calm = cap.apply(zero, torch.tensor([25.0]), v, v, engaged, calm)
        # the law asks for 1 m/s^2 at the leader's speed (to close the gap)
        executed, engaged, _ = cap.apply(torch.tensor([1.0]), torch.tensor([25.0]), v, v, engaged, calm)
        return float(executed), bool(engaged)

    assert drive(5.0) == (1.0, False)
    executed, engaged = drive(40.0)
    assert engaged and executed == pytest.approx(0.15, abs=1e-5)


def test_no_standstill_no_change():
    kw = dict(profile="random_steps", profile_kwargs={"v_low": 5.0, "v_high": 20.0, "period": 15.0, "v_init": 10.0})
    _, free = _idm_rollout(1500, cap=None, batch=4, **kw)
    _, capped = _idm_rollout(1500, cap=DriveOffCap(), batch=4, **kw)
    assert not bool(capped["next", "drive_off", "engaged"].any())
    torch.testing.assert_close(free["next", "cav", "speed"], capped["next", "cav", "speed"], atol=0, rtol=0)


def test_the_cap_lifts_as_the_projected_gap_nears_the_bands_edge():
    cap = DriveOffCap(gain=1.0, overspeed=0.1, gaps=(34.0, 38.0), accel=2.0)
    gap = torch.tensor([20.0, 34.0, 36.0, 38.0, 30.0, 32.0])
    v = torch.tensor([10.0, 10.0, 10.0, 10.0, 10.0, 6.0])
    v_l = torch.tensor([10.0, 10.0, 10.0, 10.0, 10.0, 10.0])
    c, lift = cap.cap(gap, v, v_l)
    torch.testing.assert_close(c, torch.tensor([0.1, 0.1, 0.1, 0.1, 0.1, 4.1]))
    torch.testing.assert_close(lift, torch.tensor([0.0, 0.0, 0.5, 1.0, 0.0, 0.5]))  # last: 32 + 4^2 / (2 * 2) = 36


def test_a_partial_reset_keeps_the_other_rows_state():
    cap = DriveOffCap()
    state = TensorDict({("drive_off", "engaged"): torch.tensor([[True], [True]]),
                        ("drive_off", "calm"): torch.tensor([[1.5], [2.0]]),
                        "_reset": torch.tensor([[True], [False]])}, batch_size=[2])
    out = cap._reset(state, TensorDict({("cav", "speed"): torch.tensor([[3.0], [3.0]])}, batch_size=[2]))
    assert out["drive_off", "engaged"].flatten().tolist() == [False, True]
    assert out["drive_off", "calm"].flatten().tolist() == [0.0, 2.0]


@pytest.mark.parametrize("kwargs, match", [
    ({"gain": 0.0}, r"DriveOffCap: gain=0.0 is invalid; allowed: > 0"),
    ({"overspeed": -0.1}, r"DriveOffCap: overspeed=-0.1 is invalid; allowed: >= 0"),
    ({"gaps": (38.0, 34.0)}, r"DriveOffCap: gaps=\(38.0, 34.0\) is invalid; allowed: \(from, full\)"),
    ({"release": float("nan")}, r"DriveOffCap: release=nan is invalid"),
])
def test_bad_settings_name_the_argument(kwargs, match):
    with pytest.raises(ValueError, match=match):
        DriveOffCap(**kwargs)


def test_the_config_puts_it_before_the_residual_at_deployment_only():
    cfg = validate_config(compose(["experiment=ring_lagrangian_ppo_drive_off"]))
    env = make_transformed_env(cfg, num_envs=2, seed=0, deploy=True)
    check_env_specs(env)
    deployed = [type(t).__name__ for t in env.transform]
    assert deployed[deployed.index("SafetyLayer"):deployed.index("ResidualAction") + 1] == \
        ["SafetyLayer", "DriveOffCap", "ResidualAction"]
    trained = [type(t).__name__ for t in make_transformed_env(cfg, num_envs=1, seed=0).transform]
    assert "DriveOffCap" not in trained
    always = validate_config(compose(["experiment=ring_lagrangian_ppo_drive_off", "transforms.residual.drive_off.when=always"]))
    assert "DriveOffCap" in [type(t).__name__ for t in make_transformed_env(always, num_envs=1, seed=0).transform]
    off = validate_config(compose(["experiment=ring_lagrangian_ppo_v2v"]))
    assert "DriveOffCap" not in [type(t).__name__ for t in make_transformed_env(off, num_envs=1, seed=0, deploy=True).transform]


@pytest.mark.parametrize("override, match", [
    ("transforms.residual.drive_off.gain=-1.0", r"transforms.residual.drive_off.gain: -1.0 is out of range"),
    ("transforms.residual.drive_off.gaps=[38.0,34.0]", r"transforms.residual.drive_off.gaps: \[38.0, 34.0\]"),
    ("transforms.residual.drive_off.when=never", r"transforms.residual.drive_off.when"),
])
def test_bad_config_fails_at_start_up_naming_the_field(override, match):
    with pytest.raises(ConfigError, match=match):
        validate_config(compose(["experiment=ring_lagrangian_ppo_drive_off", override]))


def test_it_engages_only_when_the_car_and_its_leader_have_both_stopped():
    """A dip of the car's own (noisy) speed below the standstill speed behind a moving leader is no stop."""
    cap = DriveOffCap(standstill=0.5)

    def step(v, v_l, a=2.0):
        td = TensorDict({"action": torch.tensor([[a]]), ("cav", "gap"): torch.tensor([[10.0]]),
                         ("cav", "speed"): torch.tensor([[v]]), ("cav", "leader_speed"): torch.tensor([[v_l]]),
                         ("drive_off", "engaged"): torch.tensor([[False]]), ("drive_off", "calm"): torch.tensor([[0.0]])},
                        batch_size=[1])
        out = cap._inv_call(td)
        return bool(out["drive_off", "engaged"]), float(out["action"])

    assert step(0.3, 2.0) == (False, 2.0)  # the leader still drives: untouched
    engaged, executed = step(0.3, 0.2)
    assert engaged and executed == pytest.approx(1.0 * (0.2 + 0.15 - 0.3))


def test_the_replayed_law_under_the_cap_commands_what_the_env_executes():
    """``DriveOffLaw`` (the cap with its memory, for ``ring_base_replay.py``) gives the transform's commands on the
    states of the env's own rollout, step by step."""
    from mixed_traffic.evaluation.replay import DriveOffLaw

    env, td = _idm_rollout(700, cap=DriveOffCap(), **STOP)
    law = DriveOffLaw(make_classic_policy("idm", env.base_env).module, DriveOffCap())
    law.reset_state()
    gap, v, v_l = (td[k][0, :, 0] for k in (("cav", "gap"), ("cav", "speed"), ("cav", "leader_speed")))
    replayed = torch.stack([law(gap[t:t + 1], v[t:t + 1], v_l[t:t + 1])[0] for t in range(gap.shape[0])])
    moving = td["next", "cav", "speed"][0, :, 0] > 0.05  # at a standstill the env executes less than commanded
    torch.testing.assert_close(replayed.clamp(-3.0, 3.0)[moving], td["next", "cav", "accel"][0, :, 0][moving],
                               atol=1e-3, rtol=0)
    assert bool(td["next", "drive_off", "engaged"].any())  # the cap acted in this rollout


# the residual's backlash while the cap is engaged (transforms.ResidualAction(play=..., play_key=...),
# transforms.residual.drive_off.residual_play)

def _zero_base():
    from tensordict.nn import TensorDictModule

    return TensorDictModule(lambda v: torch.zeros_like(v), in_keys=[("cav", "speed")], out_keys=["base"])


def test_the_backlash_holds_the_residual_through_small_reversals():
    """The executed term stays put until the policy's leaves +-play around it, then follows at that distance
    (starting from 0 at reset); without play it is the policy's own."""
    base = make_env("ring", batch_size=1, seed=0)
    script = iter([0.3, 0.35, 0.28, 0.5, 0.1, 0.15])

    def policy(td):
        return td.set("action", torch.full((1, 1), next(script)))

    env = TransformedEnv(base, ResidualAction(_zero_base(), weight=1.0, play=0.1))
    check_env_specs(env)
    td = env.rollout(6, policy)
    executed = td["next", "cav", "accel"][0, :, 0]
    torch.testing.assert_close(executed, torch.tensor([0.2, 0.25, 0.25, 0.4, 0.2, 0.2]), atol=1e-5, rtol=0)
    torch.testing.assert_close(td["next", "residual", "held"][0, :, 0], executed, atol=1e-5, rtol=0)
    script = iter([0.3, 0.35, 0.28, 0.5, 0.1, 0.15])
    free = TransformedEnv(make_env("ring", batch_size=1, seed=0), ResidualAction(_zero_base(), weight=1.0))
    torch.testing.assert_close(free.rollout(6, policy)["next", "cav", "accel"][0, :, 0],
                               torch.tensor([0.3, 0.35, 0.28, 0.5, 0.1, 0.15]), atol=1e-5, rtol=0)


def test_the_backlash_acts_only_while_the_cap_is_engaged():
    """Behind a head that stops and drives off, a policy that dithers by +-0.05 m/s^2 around 0.2: with the backlash
    tied to the cap, the command stops dithering once the cap engages and dithers as before everywhere else."""
    def run(play):
        base = make_env("ring", batch_size=1, seed=0, **STOP)
        res = ResidualAction(make_classic_policy("idm", base), weight=1.0, play=play,
                             play_key=None if play is None else ("drive_off", "engaged"))
        env = TransformedEnv(base, Compose(DriveOffCap(dt=base.scenario.dt), res))
        k = iter(range(10 ** 6))
        with torch.no_grad():
            return env.rollout(600, lambda td: td.set("action", torch.full((1, 1), 0.2 + 0.05 * (-1) ** next(k))),
                               break_when_any_done=False)

    free, held = run(None), run(0.1)
    engaged = held["next", "drive_off", "engaged"][0, :, 0]
    assert bool(engaged[320:420].all()) and not bool(engaged[:150].any())
    torch.testing.assert_close(held["next", "cav", "accel"][0, :150], free["next", "cav", "accel"][0, :150])
    first = int(engaged.nonzero().min()) + 1  # the first step decided with the cap engaged
    term = held["next", "residual", "held"][0, first + 1:420, 0]
    assert float(term.max() - term.min()) < 1e-6  # held through the dither
    free_term = free["next", "cav", "accel"][0, first:420, 0] - free["residual", "base_action"][0, first:420, 0]
    assert float((free_term[1:] - free_term[:-1]).abs().max()) > 0.09  # ... which passes without the backlash


def test_the_config_ties_the_backlash_to_the_deployed_cap():
    cfg = validate_config(compose(["experiment=ring_lagrangian_ppo_residual_play"]))
    env = make_transformed_env(cfg, num_envs=2, seed=0, deploy=True)
    check_env_specs(env)
    res = next(t for t in env.transform if isinstance(t, ResidualAction))
    assert res.play == 0.1 and res.play_key == ("drive_off", "engaged")
    trained = next(t for t in make_transformed_env(cfg, num_envs=1, seed=0).transform if isinstance(t, ResidualAction))
    assert trained.play is None  # the cap is deploy-only, and the backlash with it: the weights are unchanged
    with pytest.raises(ConfigError, match=r"transforms.residual.drive_off.residual_play: 0.0 is out of range"):
        validate_config(compose(["experiment=ring_lagrangian_ppo_residual_play",
                                 "transforms.residual.drive_off.residual_play=0.0"]))


@pytest.mark.parametrize("kwargs, match", [
    ({"play": 0.0}, r"ResidualAction: play=0.0 is invalid; allowed: > 0"),
    ({"play_key": ("drive_off", "engaged")}, r"ResidualAction: play_key without play"),
])
def test_bad_backlash_settings_name_the_argument(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ResidualAction(_zero_base(), **kwargs)


def test_a_missing_play_key_is_a_clear_error():
    base = make_env("ring", batch_size=1, seed=0)
    env = TransformedEnv(base, ResidualAction(_zero_base(), play=0.1, play_key=("drive_off", "engaged")))
    with pytest.raises(RuntimeError, match=r"play_key \('drive_off', 'engaged'\) is not in the step's input"):
        env.rollout(2, lambda td: td.set("action", torch.zeros(1, 1)))


def test_a_partial_reset_keeps_the_other_rows_held_residual():
    base = make_env("ring", batch_size=2, seed=0)
    env = TransformedEnv(base, ResidualAction(_zero_base(), play=0.1))
    res = env.transform
    state = TensorDict({("residual", "held"): torch.tensor([[0.3], [0.4]]), "_reset": torch.tensor([[True], [False]])},
                       batch_size=[2])
    out = res._reset(state, TensorDict({}, batch_size=[2]))
    torch.testing.assert_close(out["residual", "held"], torch.tensor([[0.0], [0.4]]))


def test_a_partial_reset_keeps_the_other_rows_release_share():
    base = make_env("ring", batch_size=2, seed=0)
    env = TransformedEnv(base, ResidualAction(_zero_base(), play=0.1, play_key=("drive_off", "engaged"),
                                              play_release=5.0))
    state = TensorDict({("residual", "held"): torch.tensor([[0.3], [0.4]]),
                        ("residual", "play_share"): torch.tensor([[0.5], [0.7]]),
                        "_reset": torch.tensor([[True], [False]])}, batch_size=[2])
    out = env.transform._reset(state, TensorDict({}, batch_size=[2]))
    torch.testing.assert_close(out["residual", "play_share"], torch.tensor([[0.0], [0.7]]))
    torch.testing.assert_close(out["residual", "held"], torch.tensor([[0.0], [0.4]]))


class _ScriptedKey(Transform):
    """Writes ``("drive_off", "engaged")``: true at reset and after the first ``steps - 1`` steps, false after."""

    def __init__(self, steps: int):
        super().__init__()
        self.steps, self.k = steps, 0

    def _reset(self, tensordict, tensordict_reset):
        self.k = 0
        on = torch.ones(*tensordict_reset.batch_size, 1, dtype=torch.bool)
        return tensordict_reset.set(("drive_off", "engaged"), on)

    def _step(self, tensordict, next_tensordict):
        self.k += 1
        on = torch.full((*next_tensordict.batch_size, 1), self.k < self.steps, dtype=torch.bool)
        return next_tensordict.set(("drive_off", "engaged"), on)

    def transform_observation_spec(self, observation_spec):
        observation_spec[("drive_off", "engaged")] = Binary(n=1, shape=(*observation_spec.shape, 1), dtype=torch.bool)
        return observation_spec


def test_the_release_fade_lets_the_held_term_reach_the_policys_over_play_release():
    """When the key turns false the held 0.2 reaches the policy's 0.1 in steps of 0.02 over 0.5 s (play 0.1, 5 steps
    of 0.1 s), not in one step of 0.1; without play_release it drops at once. The share counts down with it."""
    script = [0.3, 0.3, 0.25, 0.25] + [0.1] * 6

    def run(release):
        base = make_env("ring", batch_size=1, seed=0)
        res = ResidualAction(_zero_base(), weight=1.0, play=0.1, play_key=("drive_off", "engaged"),
                             play_release=release, dt=base.scenario.dt)
        env = TransformedEnv(base, Compose(_ScriptedKey(4), res))
        check_env_specs(env)
        it = iter(script)
        return env.rollout(len(script), lambda td: td.set("action", torch.full((1, 1), next(it))))

    faded = run(0.5)
    torch.testing.assert_close(faded["next", "cav", "accel"][0, :, 0],
                               torch.tensor([0.2, 0.2, 0.2, 0.2, 0.18, 0.16, 0.14, 0.12, 0.1, 0.1]), atol=1e-5, rtol=0)
    torch.testing.assert_close(faded["next", "residual", "play_share"][0, :, 0],
                               torch.tensor([1.0, 1.0, 1.0, 1.0, 0.8, 0.6, 0.4, 0.2, 0.0, 0.0]), atol=1e-5, rtol=0)
    torch.testing.assert_close(run(None)["next", "cav", "accel"][0, :, 0],
                               torch.tensor([0.2, 0.2, 0.2, 0.2, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1]), atol=1e-5, rtol=0)


def test_the_release_fade_composes_from_config_and_needs_the_backlash():
    """``transforms.residual.drive_off.residual_play_release`` reaches the deployed ResidualAction; set without a
    backlash, or out of range, it is refused naming the field and the allowed range."""
    key = "transforms.residual.drive_off.residual_play_release"
    cfg = validate_config(compose(["experiment=ring_lagrangian_ppo_residual_play", f"{key}=10.0"]))
    env = make_transformed_env(cfg, num_envs=2, seed=0, deploy=True)
    check_env_specs(env)
    res = next(t for t in env.transform if isinstance(t, ResidualAction))
    assert res.play_release == 10.0 and res.dt == env.base_env.scenario.dt
    with pytest.raises(ConfigError, match=rf"{key}: set with residual_play null; allowed: null, or a time"):
        validate_config(compose(["experiment=ring_lagrangian_ppo_safety_net", f"{key}=10.0"]))
    with pytest.raises(ConfigError, match=rf"{key}: 0.0 is out of range"):
        validate_config(compose(["experiment=ring_lagrangian_ppo_residual_play", f"{key}=0.0"]))
    with pytest.raises(ValueError, match=r"ResidualAction: play_release=5.0 is invalid; allowed: > 0 \(s\) with a play_key"):
        ResidualAction(_zero_base(), play=0.1, play_release=5.0)


# the floor from the leader's drive-off (DriveOffCap(follow=...), transforms.residual.drive_off.follow)

def test_the_follow_floor_keeps_up_with_the_leaders_drive_off_and_acts_nowhere_else():
    """A policy that asks for nothing (IDM at weight 0: the law's command) behind a head that stops and drives off at
    2 m/s^2: with follow 0.9 the CAV accelerates at least 0.9 of the head's acceleration (or the cap, where lower)
    while the cap is engaged and the head accelerates, and the run is the plain cap's to the bit before the stop."""
    _, plain = _idm_rollout(600, cap=DriveOffCap(), **STOP)
    _, follow = _idm_rollout(600, cap=DriveOffCap(follow=0.9), **STOP)
    torch.testing.assert_close(plain["next", "cav", "accel"][0, :170], follow["next", "cav", "accel"][0, :170], atol=0, rtol=0)
    a_l = follow["cav", "leader_accel"][0, :, 0]
    engaged = follow["drive_off", "engaged"][0, :, 0] & follow["next", "drive_off", "engaged"][0, :, 0]
    on = engaged & (a_l > 0.3) & (follow["cav", "speed"][0, :, 0] > 0.05)  # moving: the env executes the command
    assert int(on.sum()) > 20  # the head's drive-off, 23.5-31 s
    executed = follow["next", "cav", "accel"][0, :, 0]
    cap = DriveOffCap().cap(*(follow[k][0, :, 0] for k in (("cav", "gap"), ("cav", "speed"), ("cav", "leader_speed"))))[0]
    floor = torch.minimum(0.9 * a_l, cap)
    assert bool((executed[on] >= floor[on] - 1e-4).all())
    below = plain["next", "cav", "accel"][0, :, 0][on] < floor[on] - 0.05
    assert bool(below.any())  # the plain cap's drive-off starts slower: the floor changed something
    speed_gap = follow["next", "cav", "leader_speed"][0, 235:310, 0] - follow["next", "cav", "speed"][0, 235:310, 0]
    plain_gap = plain["next", "cav", "leader_speed"][0, 235:310, 0] - plain["next", "cav", "speed"][0, 235:310, 0]
    assert float(speed_gap.max()) < float(plain_gap.max())  # it keeps closer to the head's speed through the drive-off


def test_the_follow_floor_needs_the_leaders_acceleration_and_valid_settings():
    cap = DriveOffCap(follow=0.9)
    a = torch.zeros(1)
    with pytest.raises(ValueError, match="follow needs the leader's acceleration"):
        cap.apply(a, a + 10, a, a, torch.ones(1, dtype=torch.bool), a)
    for kw, said in (({"follow": 0.0}, r"follow=0.0 is invalid; allowed: None or in \(0, 1.5\]"),
                     ({"follow": 2.0}, r"follow=2.0 is invalid"),
                     ({"follow_above": -0.1}, r"follow_above=-0.1 is invalid; allowed: >= 0")):
        with pytest.raises(ValueError, match=said):
            DriveOffCap(**kw)
    cfg = validate_config(compose(["experiment=ring_lagrangian_ppo_residual_play", "transforms.residual.drive_off.follow=0.9"]))
    env = make_transformed_env(cfg, num_envs=1, seed=0, deploy=True)
    assert next(t for t in env.transform if isinstance(t, DriveOffCap)).follow == 0.9
    with pytest.raises(ConfigError, match=r"transforms.residual.drive_off.follow: 1.6 is out of range"):
        validate_config(compose(["experiment=ring_lagrangian_ppo_residual_play", "transforms.residual.drive_off.follow=1.6"]))
    # the replayed law under the cap reads the leader's acceleration when the cap follows
    from mixed_traffic.evaluation.replay import DriveOffLaw
    law = DriveOffLaw(make_classic_policy("idm", make_env("ring", batch_size=1, seed=0)).module, cap)
    assert law.reads_leader_accel
    law.reset_state()
    args = (torch.tensor([1.5]), torch.tensor([0.2]), torch.tensor([0.3]))  # both stopped, 1.5 m apart: IDM brakes
    assert float(DriveOffLaw(law.law, DriveOffCap())(*args)) < 0.0
    out = law(*args, torch.tensor([2.0]))  # the head drives off at 2 m/s^2: the floor, here at the cap
    assert float(out) == pytest.approx(min(0.9 * 2.0, 1.0 * (0.3 + 0.15 - 0.2)), abs=1e-6)


def test_the_follow_floor_never_pushes_past_the_stopping_rule():
    """A leader's acceleration read as +2 m/s^2 while the CAV is 5.5 m behind it at 10 m/s (a late V2V message, say):
    unguarded, the floor would push the CAV on; guarded, the command stays within the stopping rule that keeps 5 m
    whatever the leader does, as the safety layer's own bound."""
    from transforms.safety_layer import safe_accel_upper

    state = dict(gap=torch.tensor([5.5]), speed=torch.tensor([10.0]), leader_speed=torch.tensor([10.0]))
    engaged, calm, a = torch.ones(1, dtype=torch.bool), torch.zeros(1), torch.tensor([-2.0])  # the law brakes
    free = DriveOffCap(follow=0.9).apply(a, *state.values(), engaged, calm, torch.tensor([2.0]))[0]
    guarded = DriveOffCap(follow=0.9, guard=(5.0, 3.0, 3.0)).apply(a, *state.values(), engaged, calm, torch.tensor([2.0]))[0]
    bound = safe_accel_upper(*state.values(), s_min=5.0, dt=0.1, brake=3.0, leader_brake=3.0)
    assert float(free) > float(bound) and float(guarded) <= float(bound) + 1e-6
    with pytest.raises(ValueError, match=r"guard=\(5.0, 0.0, 3.0\) is invalid"):
        DriveOffCap(follow=0.9, guard=(5.0, 0.0, 3.0))
    cfg = validate_config(compose(["experiment=ring_lagrangian_ppo_residual_play", "transforms.residual.drive_off.follow=0.9"]))
    cap = next(t for t in make_transformed_env(cfg, num_envs=1, seed=0, deploy=True).transform if isinstance(t, DriveOffCap))
    assert cap.guard[:2] == (5.0, 3.0)  # the base's stop_gap and the CAV's braking bound


def test_with_hold_the_cav_stands_while_its_leader_stands():
    """Behind a stopped leader the cap without ``hold`` lets a command creep the CAV toward it at ``gain *
    overspeed``; with ``hold`` the cap there is ``-gain v``, so the same command is held at 0. Once the leader
    drives at ``standstill`` or faster, both caps are the same."""
    zero, stopped = torch.zeros(2), torch.zeros(2, dtype=torch.bool)
    push = torch.full((2,), 0.4)  # a base plus residual that would creep forward
    gap, v, v_l = torch.tensor([6.0, 6.0]), torch.tensor([0.0, 0.2]), zero
    creep, _, _ = DriveOffCap(overspeed=0.15).apply(push, gap, v, v_l, stopped, zero)
    held, engaged, _ = DriveOffCap(overspeed=0.15, hold=True).apply(push, gap, v, v_l, stopped, zero)
    assert bool(engaged.all())
    torch.testing.assert_close(creep, torch.tensor([0.15, -0.05]))
    torch.testing.assert_close(held, torch.tensor([0.0, -0.2]))
    moving = torch.tensor([0.5, 3.0])  # the leader drives off
    for cap in (DriveOffCap(overspeed=0.15), DriveOffCap(overspeed=0.15, hold=True)):
        c, _ = cap.cap(gap, v, moving)
        torch.testing.assert_close(c, moving + 0.15 - v)
    c, _ = DriveOffCap(overspeed=0.15, hold=True).cap(gap, zero, torch.tensor([0.25, 0.1]))  # half, a fifth of 0.5
    torch.testing.assert_close(c, torch.tensor([0.25 + 0.075, 0.1 + 0.03]))


def test_hold_reaches_the_transform_from_the_config():
    """``transforms.residual.drive_off.hold=true`` builds the cap with ``hold``; the default builds it without."""
    from mixed_traffic.training.builders import drive_off_cap

    env = make_env("ring", batch_size=1, seed=0, **STOP)
    held = compose(["experiment=ring_lagrangian_ppo_follow", "transforms.residual.drive_off.hold=true"])
    assert drive_off_cap(held.transforms.residual, env).hold is True
    assert drive_off_cap(compose(["experiment=ring_lagrangian_ppo_follow"]).transforms.residual, env).hold is False
