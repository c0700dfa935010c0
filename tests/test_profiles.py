import pytest
import torch

from mixed_traffic.profiles import make_profile


def speeds(prof, ts, params=None):
    params = prof.sample(1, torch.Generator().manual_seed(0)) if params is None else params
    return [float(prof.speed(torch.tensor([t], dtype=torch.float32), params)) for t in ts]


def test_deeplcc_brake_shape():
    v = speeds(make_profile("deeplcc_brake"), [0.0, 1.0, 2.0, 4.0, 7.0, 9.5, 12.0, 30.0])
    assert v == pytest.approx([15.0, 10.0, 5.0, 5.0, 5.0, 10.0, 15.0, 15.0])


def test_emergency_brake_shape():
    v = speeds(make_profile("emergency_brake"), [10.0, 50.0, 53.0, 60.0, 63.0, 68.0, 90.0])
    assert v == pytest.approx([15.0, 15.0, 2.0, 2.0, 2.0, 15.0, 15.0])


def test_random_steps_hold_for_period_and_stay_in_range():
    prof = make_profile("random_steps", v_init=10.0, horizon=100.0)
    p = prof.sample(64, torch.Generator().manual_seed(1))
    t = torch.full((64,), 0.0)
    assert torch.all(prof.speed(t, p) == 10.0)
    a, b = prof.speed(torch.full((64,), 15.0), p), prof.speed(torch.full((64,), 29.9), p)
    assert torch.equal(a, b)
    assert (a >= 5).all() and (a <= 20).all()
    assert a.unique().numel() > 50  # rows differ


def test_random_perturbation_amplitude_and_seed():
    prof = make_profile("random_perturbation", v_star=15.0, amplitude=3.0, horizon=50.0)
    g1, g2 = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    p1, p2 = prof.sample(8, g1), prof.sample(8, g2)
    assert torch.equal(p1, p2)
    t = torch.linspace(0, 50, 501)
    v = torch.stack([prof.speed(t, p1[i].expand(501, -1)) for i in range(8)])
    assert v.min() >= 12.0 - 1e-5 and v.max() <= 18.0 + 1e-5
    assert v.std() > 0.5


def test_sine_and_eudc_ranges():
    sine = make_profile("sine", v_star=15.0, amplitude=5.0, period=10.0)
    assert speeds(sine, [2.5])[0] == pytest.approx(20.0)
    eudc = make_profile("eudc")
    v = torch.tensor(speeds(eudc, list(range(0, 330, 2))))
    assert v.min() == pytest.approx(5.0) and v.max() == pytest.approx(20.0)


def test_bad_profile_names_and_arguments():
    with pytest.raises(ValueError, match="unknown name 'warp'"):
        make_profile("warp")
    with pytest.raises(ValueError, match=r"unknown arguments \['amplitud'\]"):
        make_profile("sine", amplitud=3.0)
    # only the unknown one is named, not the valid arguments given beside it
    with pytest.raises(ValueError, match=r"unknown arguments \['v_init'\]; allowed: \['v_low'"):
        make_profile("random_sine", v_low=2.0, v_high=20.0, v_init=None)


def test_random_sine_stays_in_range_and_draws_every_part_per_episode():
    prof = make_profile("random_sine", v_low=2.0, v_high=20.0, amplitude_min=1.0, amplitude_max=6.0,
                        period_min=20.0, period_max=80.0)
    p = prof.sample(256, torch.Generator().manual_seed(4))
    t = torch.linspace(0, 200, 801)
    v = torch.stack([prof.speed(t, p[i].expand(801, -1)) for i in range(256)])
    assert v.min() >= 2.0 - 1e-4 and v.max() <= 20.0 + 1e-4
    swing = (v.max(1).values - v.min(1).values) / 2  # 200 s is at least 2.5 periods: the amplitude is reached
    assert torch.allclose(swing, p[:, 1], atol=0.02)
    assert swing.min() >= 1.0 - 0.02 and swing.max() <= 6.0 + 0.02
    assert p[:, 2].min() >= 20.0 and p[:, 2].max() <= 80.0 and p[:, 0].std() > 2.0  # periods, centres drawn
    with pytest.raises(ValueError, match=r"amplitude_max=12.0 are invalid; allowed: .* <= \(v_high - v_low\) / 2"):
        make_profile("random_sine", v_low=2.0, v_high=20.0, amplitude_max=12.0)


def test_random_mix_redraws_its_part_per_episode_and_passes_the_shared_arguments():
    mix = make_profile("random_mix", v_low=2.0, v_high=20.0, horizon=100.0, weights=(3.0, 1.0),
                       parts={"random_ramps": {"v_init": 10.0}, "random_sine": {"amplitude_max": 2.0}})
    ramps, sine = mix.built
    assert (ramps.v_low, ramps.v_high, ramps.horizon, ramps.v_init) == (2.0, 20.0, 100.0, 10.0)
    assert (sine.v_low, sine.v_high, sine.amplitude_max) == (2.0, 20.0, 2.0)
    g = torch.Generator().manual_seed(5)
    p = mix.sample(4000, g)
    share = float((p[:, 0] == 0).float().mean())
    assert share == pytest.approx(0.75, abs=0.03)  # the weights are the odds
    assert not torch.equal(p[:, 0], mix.sample(4000, g)[:, 0])  # a reset draws the part again
    v0 = mix.speed(torch.zeros(4000), p)
    assert torch.all(v0[p[:, 0] == 0] == 10.0)  # a ramps episode starts at its v_init
    s = p[p[:, 0] == 1][:, 1:5]  # a sine episode follows its own parameters
    assert torch.allclose(mix.speed(torch.zeros(len(s)), p[p[:, 0] == 1]), s[:, 0] + s[:, 1] * torch.sin(s[:, 3]),
                          atol=1e-4)
    with pytest.raises(ValueError, match="part 'warp' is invalid"):
        make_profile("random_mix", parts={"warp": {}})
    with pytest.raises(ValueError, match="weights=.* is invalid; allowed: 2 non-negative numbers"):
        make_profile("random_mix", parts={"random_ramps": {}, "random_sine": {}}, weights=(1.0,))


def test_a_bad_mix_part_fails_at_env_build_naming_profile_kwargs_and_the_part_argument():
    from mixed_traffic import make_env
    from mixed_traffic.config import compose
    from mixed_traffic.training.builders import env_kwargs

    cfg = compose(["experiment=ring_lagrangian_ppo_mix"])
    env = make_env("ring", **env_kwargs(cfg.env))  # the experiment's own mix builds and draws both kinds of head
    assert env.profile.built[1].v_low == 2.0 and env.profile.built[1].v_high == 20.0
    with pytest.raises(ValueError, match=r"^profile_kwargs.*amplitude_max=10.0 are invalid; allowed: .*v_low\) / 2"):
        make_env("ring", profile="random_mix", profile_kwargs={
            "v_low": 2.0, "v_high": 20.0, "parts": {"random_ramps": {}, "random_sine": {"amplitude_max": 10.0}}})


def test_a_profile_switched_on_the_command_line_ignores_an_unset_argument_it_lacks():
    """The default's ``profile_kwargs`` hold ``v_init: null`` (for random_ramps); ``env.profile=random_sine`` still
    builds, while an argument the profile lacks that is set still fails, naming it."""
    from mixed_traffic import make_env
    from mixed_traffic.config import compose
    from mixed_traffic.training.builders import env_kwargs

    cfg = compose(["experiment=ring_lagrangian_ppo_follow", "env.profile=random_sine"])
    assert cfg.env.profile_kwargs.v_init is None
    env = make_env("ring", **env_kwargs(cfg.env))
    assert (env.profile.v_low, env.profile.v_high) == (2.0, 20.0)
    # a profile that is a function (its parameters are its arguments) too: the EUDC shape within 2-20 m/s
    cfg = compose(["experiment=ring_lagrangian_ppo_follow", "env.profile=eudc"])
    v = torch.tensor(speeds(make_env("ring", **env_kwargs(cfg.env)).profile, list(range(0, 400, 2))))
    assert v.min() == pytest.approx(2.0) and v.max() == pytest.approx(20.0)
    with pytest.raises(ValueError, match=r"^profile_kwargs.*unknown arguments \['v_init'\]"):
        make_env("ring", profile="random_sine", profile_kwargs={"v_low": 2.0, "v_high": 20.0, "v_init": 10.0})


def test_random_mix_passes_its_shared_speeds_to_a_function_part_that_takes_them():
    mix = make_profile("random_mix", v_low=3.0, v_high=12.0, parts={"eudc": {}, "emergency_brake": {"v_cruise": 10.0}})
    eudc, brake = mix.built
    v = torch.tensor(speeds(eudc, list(range(0, 400, 2))))
    assert v.min() == pytest.approx(3.0) and v.max() == pytest.approx(12.0)
    assert min(speeds(brake, list(range(0, 120)))) == pytest.approx(3.0)  # its v_low, the mix's
