"""CommittedAnswer: one acceleration held until the speeds match, with its memory in the tensordict."""

from __future__ import annotations

import pytest
import torch
from torchrl.envs import Compose, TransformedEnv
from torchrl.envs.utils import check_env_specs

from mixed_traffic import make_env
from mixed_traffic.config import compose
from mixed_traffic.controllers.classic import make_classic_policy
from mixed_traffic.physics import committed_answer_accel
from mixed_traffic.training.builders import committed_answer, make_transformed_env
from mixed_traffic.validation import ConfigError, validate_config
from transforms import CommittedAnswer, ResidualAction

LAW = dict(horizon=6.0, horizon_min=3.0, start=0.3, done=0.05, gaps=(6.1, 35.0), ks_edge=0.077, dt=0.1)


def _behind_a_step(law, seconds: float = 20.0, dv0: float = 2.0, gap0: float = 20.0):
    """The CAV at 20 m/s behind a leader that has just stepped to 20 + dv0 m/s and holds it: commands and speeds."""
    v, vl = torch.tensor([20.0], dtype=torch.float64), torch.tensor([20.0 + dv0], dtype=torch.float64)
    gap = torch.tensor([gap0], dtype=torch.float64)
    state = (torch.zeros(1, dtype=torch.float64), torch.zeros(1, dtype=torch.float64))
    a_s, v_s = [], []
    for _ in range(int(round(seconds / 0.1))):
        a, *state = law(gap, v, vl, *state)
        gap = gap + (vl - v) * 0.1 - 0.5 * a * 0.01
        v = v + a * 0.1
        a_s.append(float(a)), v_s.append(float(v))
    return torch.tensor(a_s), torch.tensor(v_s)


def test_a_step_of_the_leader_is_answered_with_a_held_acceleration_that_closes_faster_than_a_lag():
    answer = lambda g, v, vl, tau, sign: committed_answer_accel(g, v, vl, tau, sign, **LAW)  # noqa: E731
    a, v = _behind_a_step(answer)
    held = int((6.0 - 3.0) / 0.1)  # horizon - horizon_min: the time to go counts down to its floor
    torch.testing.assert_close(a[:held], torch.full((held,), 2.0 / 6.0, dtype=a.dtype), atol=1e-9, rtol=0)
    assert bool((a[held:] <= a[held - 1:-1] + 1e-12).all())  # then it eases off, with a gain of 1 / horizon_min
    assert bool((a[-10:].abs() < 1e-3).all())  # and the answer ends: what is left is the band's term on dv < done
    # a memoryless gain of 1 / horizon: the same first command, twice as much of the step still open at the horizon
    lag = lambda g, v, vl, tau, sign: ((vl - v) / 6.0, tau, sign)  # noqa: E731
    a_lag, v_lag = _behind_a_step(lag)
    assert float(a_lag[0]) == pytest.approx(float(a[0]))
    n = int(6.0 / 0.1) - 1
    assert 22.0 - float(v[n]) < 0.5 * (22.0 - float(v_lag[n]))
    assert abs(22.0 - float(v[int(15.0 / 0.1)])) < 0.06


def test_the_gap_stays_in_the_band_behind_a_leader_that_pulls_away_from_near_its_edge():
    answer = lambda g, v, vl, tau, sign: committed_answer_accel(g, v, vl, tau, sign, **LAW)  # noqa: E731
    lag = lambda g, v, vl, tau, sign: ((vl - v) / 6.0, tau, sign)  # noqa: E731

    def gaps(v):
        return 28.0 + torch.cumsum((24.0 - torch.cat([torch.tensor([20.0]), v[:-1]])) * 0.1, 0)

    # 4 m/s faster at 28 m: a gain of 1 / horizon lets the gap run 24 m; the band's term answers harder from the start
    a, v = _behind_a_step(answer, dv0=4.0, gap0=28.0, seconds=30.0)
    _, v_lag = _behind_a_step(lag, dv0=4.0, gap0=28.0, seconds=30.0)
    assert float(a[0]) > 4.0 / 6.0 + 0.4
    assert float(gaps(v).max()) < 37.0 < 40.0 < float(gaps(v_lag).max())
    assert abs(float(v[-1]) - 24.0) < 0.05


def test_specs_hold_and_below_its_speeds_the_command_passes_untouched():
    def rollout(answer: bool):
        base = make_env("ring", batch_size=2, seed=0, init_spacing_range=[20.0, 20.0])
        ts = [ResidualAction(make_classic_policy("idm", base), weight=0.0)]
        if answer:
            ts.insert(0, CommittedAnswer(speeds=(40.0, 41.0), dt=base.scenario.dt))
        env = TransformedEnv(base, Compose(*ts))
        with torch.no_grad():
            return env.rollout(200, lambda td: td.set("action", torch.zeros(2, 1)))

    with_answer, without = rollout(True), rollout(False)
    base = make_env("ring", batch_size=2, seed=0)
    check_env_specs(TransformedEnv(base, Compose(CommittedAnswer(dt=base.scenario.dt),
                                                 ResidualAction(make_classic_policy("idm", base), weight=0.0))))
    torch.testing.assert_close(with_answer["next", "cav", "accel"], without["next", "cav", "accel"], atol=0, rtol=0)
    assert with_answer["next", "answer", "tau"].shape == with_answer["next", "cav", "speed"].shape


def test_above_its_speeds_it_drives_and_remembers_its_answer_across_steps():
    base = make_env("ring", batch_size=1, seed=0, init_spacing_range=[20.0, 20.0])
    env = TransformedEnv(base, Compose(CommittedAnswer(speeds=(0.0, 0.5), dt=base.scenario.dt),
                                       ResidualAction(make_classic_policy("idm", base), weight=0.0)))
    with torch.no_grad():
        td = env.rollout(300, lambda td: td.set("action", torch.zeros(1, 1)))
    sign, tau = td["next", "answer", "sign"][0, :, 0], td["next", "answer", "tau"][0, :, 0]
    running = sign != 0
    assert bool(running.any()) and not bool(td["next", "collision"].any())
    # while an answer runs, its time to go counts down by one step from where the last step left it
    both = running[1:] & running[:-1]
    torch.testing.assert_close(tau[1:][both], tau[:-1][both] - 0.1, atol=1e-5, rtol=0)
    executed, base_cmd = td["next", "cav", "accel"][0, :, 0], td["next", "residual", "base_action"][0, :, 0]
    assert float((executed - base_cmd).abs().max()) > 0.05  # it, not the base, drives


def test_the_answer_stays_inside_the_base_stopping_envelope():
    cfg = validate_config(compose(["experiment=ring_lagrangian_ppo_fast_band", "transforms.residual.answer.horizon=6.0"]))
    env = make_env("ring", batch_size=1, seed=0)
    t = committed_answer(cfg.transforms.residual, env)
    g = torch.Generator().manual_seed(0)
    n = 4000
    gap = 5.0 + 40.0 * torch.rand(n, generator=g)
    v = 18.0 + 8.0 * torch.rand(n, generator=g)
    vl = v + 6.0 * (torch.rand(n, generator=g) - 0.5)
    a_l = -2.0 * torch.rand(n, generator=g)
    sign = torch.sign(torch.randn(n, generator=g))
    tau = 6.0 * torch.rand(n, generator=g)
    a, _, _ = t.answer(gap, v, vl, tau, sign, a_l)
    bound = t.envelope.bound(gap, v, vl)
    assert bool((a <= bound + 1e-6).all())
    assert bool((a < bound - 1e-3).any())  # and it is not simply the bound


def test_deploy_only_by_default_placed_between_the_join_and_the_residual():
    cfg = validate_config(compose(["experiment=ring_lagrangian_ppo_fast_band", "transforms.residual.answer.horizon=6.0"]))
    trained = make_transformed_env(cfg, num_envs=1, seed=0)
    deployed = make_transformed_env(cfg, num_envs=1, seed=0, deploy=True)
    names = lambda env: [type(t).__name__ for t in env.transform]  # noqa: E731
    assert "CommittedAnswer" not in names(trained)
    order = names(deployed)
    assert order.index("JoinBlend") < order.index("CommittedAnswer") < order.index("ResidualAction")
    assert "CommittedAnswer" not in names(make_transformed_env(validate_config(compose(
        ["experiment=ring_lagrangian_ppo_fast_band"])), num_envs=1, seed=0, deploy=True))  # off by default


@pytest.mark.parametrize("override, field", [
    ("transforms.residual.answer.horizon=-1.0", "transforms.residual.answer.horizon"),
    ("transforms.residual.answer.horizon_min=9.0", "transforms.residual.answer.horizon_min"),
    ("transforms.residual.answer.gaps=[35.0,6.0]", "transforms.residual.answer.gaps"),
    ("transforms.residual.answer.speeds=[20.0,18.0]", "transforms.residual.answer.speeds"),
    ("transforms.residual.answer.done=0.5", "transforms.residual.answer.done"),
    ("+transforms.residual.answer.idm.delta=4.0", "transforms.residual.answer.idm.delta"),
])
def test_bad_settings_name_the_field(override, field):
    on = [] if "horizon=" in override else ["transforms.residual.answer.horizon=6.0"]
    with pytest.raises(ConfigError, match=field.replace(".", r"\.")):
        validate_config(compose(["experiment=ring_lagrangian_ppo_fast_band", *on, override]))
    with pytest.raises(ValueError, match="horizon_min"):
        CommittedAnswer(horizon=6.0, horizon_min=8.0)


def test_a_partial_reset_keeps_the_other_rows_answer():
    from tensordict import TensorDict

    t = CommittedAnswer()
    state = TensorDict({("answer", "tau"): torch.tensor([[4.0], [2.5]]), ("answer", "sign"): torch.tensor([[1.0], [-1.0]]),
                        "_reset": torch.tensor([[True], [False]])}, batch_size=[2])
    out = t._reset(state, TensorDict({("cav", "speed"): torch.tensor([[20.0], [20.0]])}, batch_size=[2]))
    assert out["answer", "tau"].tolist() == [[0.0], [2.5]] and out["answer", "sign"].tolist() == [[0.0], [-1.0]]


def test_a_run_saved_before_the_setting_existed_deploys_it_and_a_typo_still_fails():
    from omegaconf import OmegaConf

    from mixed_traffic.validation import parse_deploy_overrides, with_deploy_overrides

    old = OmegaConf.to_container(compose(["experiment=ring_lagrangian_ppo_fast_band"]))
    del old["transforms"]["residual"]["answer"]  # as a run trained before transforms.residual.answer was added
    old = OmegaConf.create(old)  # a saved config.yaml, loaded
    cfg = with_deploy_overrides(old, parse_deploy_overrides(["transforms.residual.answer.horizon=8.0"]))
    assert cfg.transforms.residual.answer.horizon == 8.0 and cfg.transforms.residual.answer.horizon_min == 3.0
    with pytest.raises(ConfigError, match=r"transforms\.residual\.answer\.horzon"):
        with_deploy_overrides(old, parse_deploy_overrides(["transforms.residual.answer.horzon=8.0"]))


def test_with_catch_up_the_base_catch_up_lifts_the_answer_near_the_band_top_and_nowhere_else():
    env = make_env("ring", batch_size=1, seed=0)
    on = ["experiment=ring_lagrangian_ppo_fast_band", "transforms.residual.answer.horizon=6.0"]
    plain = committed_answer(validate_config(compose(on)).transforms.residual, env)
    lifted = committed_answer(validate_config(compose([*on, "transforms.residual.answer.catch_up=true"]))
                              .transforms.residual, env)
    gap, v, vl = torch.tensor([33.0, 20.0]), torch.tensor([21.0, 21.0]), torch.tensor([22.0, 22.0])
    zeros, a_l = torch.zeros(2), torch.zeros(2)
    a_plain, a_lifted = (t.answer(gap, v, vl, zeros, zeros, a_l)[0] for t in (plain, lifted))
    assert float(a_lifted[0]) > float(a_plain[0]) + 0.3  # a leader pulling away near the top: the catch-up lifts it
    assert float(a_lifted[1]) == pytest.approx(float(a_plain[1]))  # mid-band: the same answer


def test_a_step_before_a_reset_through_the_transformed_env_names_the_missing_state():
    base = make_env("ring", batch_size=2, seed=0)
    env = TransformedEnv(base, Compose(CommittedAnswer(dt=base.scenario.dt),
                                       ResidualAction(make_classic_policy("idm", base), weight=0.0)))
    td = base.reset().set("action", torch.zeros(2, 1))  # the base env's reset: no answer state in it
    with pytest.raises(RuntimeError, match=r"CommittedAnswer: the step's input has no answer state; reset the env "
                                           r"through the TransformedEnv"):
        env.step(td)
    env.step(env.reset().set("action", torch.zeros(2, 1)))  # through the TransformedEnv it steps
