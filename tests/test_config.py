"""Hydra config tree: every experiment composes, overrides swap one group, bad input fails early."""

import os
import subprocess
import sys
from pathlib import Path

import pytest
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf

from mixed_traffic.config import compose

ROOT = Path(__file__).resolve().parent.parent
EXPERIMENTS = sorted(p.stem for p in (ROOT / "hydra_configs" / "experiment").glob("*.yaml"))
RING = ["ring_q_learning", "ring_dqn", "ring_ppo", "ring_lagrangian_ppo"]
ANY = object()  # a value in `assert_differs_only_in`'s settings: the key may differ, the test checks its value itself
_ABSENT = object()


def assert_differs_only_in(cfg, ref, settings: dict[str, object]) -> None:
    """``cfg`` equals ``ref`` except in ``name`` and at the dotted keys of ``settings``, where ``cfg`` holds the given
    values (a subtree as a dict or list, unresolved; a bool by identity; ``ANY``: present, value not checked). A key
    that ``ref`` lacks is one that ``cfg`` adds. Neither config is changed."""
    for key, want in settings.items():
        got = OmegaConf.select(cfg, key, default=_ABSENT)
        assert got is not _ABSENT, f"{key} is missing"
        if OmegaConf.is_config(got):
            got = OmegaConf.to_container(got)
        if isinstance(want, bool):
            assert got is want, f"{key}: {got!r} is not {want!r}"
        elif want is not ANY:
            assert got == want, f"{key}: {got!r} != {want!r}"
    mine, theirs = OmegaConf.to_container(cfg), OmegaConf.to_container(ref)
    mine["name"] = theirs["name"]
    for key in settings:  # take ref's value, or drop the key where ref has none
        *path, leaf = key.split(".")
        a, b = mine, theirs
        for part in path:
            a, b = a[part], b[part]
        if leaf in b:
            a[leaf] = b[leaf]
        else:
            del a[leaf]
    assert mine == theirs


def test_ring_experiments_exist():
    assert set(RING) <= set(EXPERIMENTS)


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_every_experiment_composes(name):
    cfg = compose([f"experiment={name}"])
    assert cfg.name == name
    for group in ("env", "transforms", "policy", "loss", "trainer", "logger"):
        assert group in cfg
    # the whole tree resolves except Hydra's runtime interpolation of out_dir
    cfg.out_dir = "x"
    OmegaConf.to_container(cfg, resolve=True, throw_on_missing=True)


def test_lagrangian_ppo_reproduces_the_seed_settings():
    for name in ("ring_lagrangian_ppo", "ring_lagrangian_ppo_no_apg"):
        cfg = compose([f"experiment={name}"])
        assert (cfg.env.weight_v, cfg.env.weight_s, cfg.env.weight_u) == (5.0, 0.5, 0.1)
        assert cfg.loss.name == "lagrangian_ppo"
        assert cfg.loss.clip_epsilon == 0.15 and cfg.loss.clip_value == 0.2 and cfg.trainer.epochs == 6
        assert cfg.trainer.num_envs * cfg.trainer.rollout_len == 4096
        # PID multiplier on (s_min violation + the layer's intervention) against a 1 % budget
        assert (cfg.loss.lambda_method, cfg.loss.lambda_init, cfg.loss.lambda_lr, cfg.loss.lambda_kp,
                cfg.loss.lambda_max, cfg.loss.violation_tolerance) == ("pid", 1.0, 0.5, 5.0, 10.0, 0.01)
        assert list(cfg.transforms.chain)[:4] == ["non_negative_reward", "safety_layer", "residual_idm",
                                                  "intervention_cost"]
        assert cfg.transforms.residual.weight == 0.5
        # trained on a broad distribution, not on the evaluation profiles
        assert cfg.env.profile == "random_ramps" and cfg.env.profile_kwargs.v_high == 20.0
        assert list(cfg.env.overrides.init_spacing_range) == [8.0, 73.4] and cfg.env.hdv_param_noise == 0.1
        assert (cfg.eval.s_min, cfg.eval.s_max) == (5.0, 40.0)
    # the default: APG first, then PPO with little noise; IDM with a 6 m standstill gap underneath;
    # the layer's head-gap bound is 2 m inside the evaluation's 40 m
    cfg = compose(["experiment=ring_lagrangian_ppo"])
    assert cfg.policy.apg.iterations > 0 and cfg.trainer.total_frames > 0 and not cfg.policy.shared_trunk
    assert dict(cfg.transforms.residual.params) == {"s0": 7.0, "v0": 40.0, "gap_max": 34.0} and cfg.transforms.chain[-1] == "jerk_penalty"
    assert (cfg.transforms.safety_layer.s_min, cfg.transforms.safety_layer.s_max) == (5.0, 38.0)
    # the variant that holds a long start gap instead of closing it at full throttle (docs/results.md)
    hold = compose(["experiment=ring_lagrangian_ppo_hold"])
    assert (cfg.transforms.safety_layer.beyond_s_max, hold.transforms.safety_layer.beyond_s_max) == ("push", "hold")
    assert dict(hold.transforms.residual.params) == {"s0": 7.0, "v0": 40.0, "T": 0.8, "gap_max": None}
    assert (hold.policy.apg.head_gap_max, hold.policy.apg.head_gap_after, hold.transforms.jerk_penalty.weight) == \
        (38.0, 15.0, 15.0)
    assert hold.policy.apg.iterations == cfg.policy.apg.iterations and hold.env.profile == cfg.env.profile
    # the smooth-start variant: the default with these settings changed and nothing else (docs/results.md)
    smooth = compose(["experiment=ring_lagrangian_ppo_smooth"])
    changed = {"name": "ring_lagrangian_ppo_smooth", "env.profile_kwargs.v_init": None,
               "transforms.safety_layer.hold_seconds": 15.0, "transforms.residual.params.v0": 60.0,
               "transforms.residual.params.gap_max": 27.0, "transforms.residual.engage_seconds": 5.0,
               "transforms.jerk_penalty.weight": 12.5,
               "policy.apg.head_gap_max": 37.0, "policy.apg.head_gap_after": 15.0, "policy.apg.average_last": 50,
               "policy.apg.iterations": 100, "policy.apg.num_envs": 128, "trainer.total_frames": 50000}
    assert {k: OmegaConf.select(smooth, k) for k in changed} == changed
    from mixed_traffic.training.builders import make_transformed_env
    from transforms import ResidualAction, SafetyLayer

    chain = make_transformed_env(smooth, num_envs=1, seed=0).transform
    residual = [t for t in chain if isinstance(t, ResidualAction)]
    assert [r.engage_seconds for r in residual] == [5.0]  # the setting reaches the transform
    assert [(t.beyond_s_max, t.hold_seconds) for t in chain if isinstance(t, SafetyLayer)] == [("push", 15.0)]
    recover = compose(["experiment=ring_lagrangian_ppo_smooth", "transforms.safety_layer.beyond_s_max=recover",
                       "transforms.safety_layer.recover_seconds=2.5"])
    assert [(t.beyond_s_max, t.recover_seconds) for t in make_transformed_env(recover, num_envs=1, seed=0).transform
            if isinstance(t, SafetyLayer)] == [("recover", 2.5)]  # the option reaches the layer
    same = compose(["experiment=ring_lagrangian_ppo", *(f"{k}={'null' if v is None else v}" for k, v in changed.items())])
    assert OmegaConf.to_container(same, resolve=False) == OmegaConf.to_container(smooth, resolve=False)
    old = compose(["experiment=ring_lagrangian_ppo_no_apg"])
    assert old.policy.apg.iterations == 0 and old.transforms.safety_layer.s_max == 30.0 and old.trainer.lr == 3e-4
    scratch = compose(["experiment=ring_lagrangian_ppo_scratch"])
    assert list(scratch.transforms.chain) == ["non_negative_reward", "safety_layer", "intervention_cost"]


def test_baselines_use_the_seed_settings():
    ppo = compose(["experiment=ring_ppo"])
    assert "safety_layer" not in ppo.transforms.chain and ppo.loss.name == "ppo" and ppo.loss.clip_value is None
    assert (ppo.env.weight_v, ppo.env.weight_s, ppo.env.weight_u) == (1.0, 0.5, 0.2)
    dqn = compose(["experiment=ring_dqn"])
    assert dqn.transforms.discretizer.action_bins == 21 and list(dqn.policy.hidden) == [128]
    assert (dqn.trainer.lr, dqn.trainer.batch_size, dqn.trainer.buffer_size, dqn.loss.tau) == (5e-4, 128, 200000, 0.01)
    q = compose(["experiment=ring_q_learning"])
    assert (q.loss.alpha, q.loss.gamma, q.transforms.discretizer.state_bins) == (0.2, 0.98, 20)


def test_one_override_swaps_a_loss_or_the_transform_chain():
    cfg = compose(["experiment=ring_ppo", "loss=lagrangian_ppo"])
    assert cfg.loss.name == "lagrangian_ppo" and cfg.loss.lambda_init == 1.0
    cfg = compose(["experiment=ring_lagrangian_ppo", "transforms=reward"])
    assert list(cfg.transforms.chain) == ["non_negative_reward"]
    cfg = compose(["experiment=ring_lagrangian_ppo", "transforms.chain=[safety_layer]"])
    assert list(cfg.transforms.chain) == ["safety_layer"]


@pytest.mark.parametrize("override, fragment", [
    ("loss.clip_epsilom=0.2", "clip_epsilom"),
    ("trainer.lr=fast", "trainer.lr"),
    ("loss=ppo_typo", "ppo_typo"),
    ("env.observtion=relative", "observtion"),
])
def test_bad_override_fails_with_hydras_message(override, fragment):
    with pytest.raises(ConfigCompositionException) as e:
        compose(["experiment=ring_lagrangian_ppo", override])
    assert fragment in str(e.value)


def test_misspelt_key_in_a_yaml_file_fails(tmp_path):
    """The schema also guards the files: an option file with an unknown key does not compose."""
    import shutil

    from hydra import compose as hcompose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    shutil.copytree(ROOT / "hydra_configs", tmp_path / "conf")
    (tmp_path / "conf" / "loss" / "bad.yaml").write_text("defaults:\n  - ppo_schema\nname: ppo\nclip_epsilom: 0.1\n")
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(tmp_path / "conf"), version_base="1.3"):
        with pytest.raises(Exception) as e:
            hcompose(config_name="config", overrides=["loss=bad"])
    GlobalHydra.instance().clear()
    assert "clip_epsilom" in str(e.value)


@pytest.mark.parametrize("launcher, target", [
    ("basic", "BasicLauncher"),
    ("joblib", "JoblibLauncher"),
    ("joblib_local", "JoblibLauncher"),
    ("slurm", "SlurmLauncher"),
    ("submitit_local", "LocalLauncher"),
    ("ray", "RayLauncher"),
])
def test_launcher_configs_compose(launcher, target):
    if launcher in ("slurm", "submitit_local"):
        pytest.importorskip("hydra_plugins.hydra_submitit_launcher",
                            reason="the slurm extra is not installed (pip install 'mixed-traffic[slurm]')")
    cfg = compose(["experiment=ring_ppo", f"hydra/launcher={launcher}"], return_hydra_config=True)
    assert cfg.hydra.launcher._target_.endswith(target)


def test_cross_group_mismatch_fails_before_training():
    from mixed_traffic.training import check_config

    with pytest.raises(ValueError, match="does not go with trainer"):
        check_config(compose(["experiment=ring_ppo", "loss=dqn"]))
    with pytest.raises(ValueError, match="unknown transform"):
        check_config(compose(["experiment=ring_ppo", "transforms.chain=[safety_layr]"]))


def _script(name):
    exe = Path(sys.executable).parent / name
    if not exe.exists():
        pytest.skip(f"{name} console script not installed")
    return str(exe)


def test_installed_script_finds_the_configs_from_any_directory(tmp_path):
    out = subprocess.run([_script("mt-train"), "experiment=ring_ppo", "--cfg", "job"], cwd=tmp_path,
                         capture_output=True, text=True, timeout=120, env=dict(os.environ))
    assert out.returncode == 0, out.stderr
    assert "name: ring_ppo" in out.stdout


@pytest.mark.slow  # the same error is checked through compose() above; this adds the console script
def test_installed_script_rejects_a_misspelt_key(tmp_path):
    out = subprocess.run([_script("mt-train"), "experiment=ring_ppo", "trainer.totl_frames=10"], cwd=tmp_path,
                         capture_output=True, text=True, timeout=120, env=dict(os.environ))
    assert out.returncode != 0
    assert "totl_frames" in out.stderr and "Could not override" in out.stderr
    assert not (tmp_path / "outputs").exists() or not any((tmp_path / "outputs").rglob("final.pt"))


def test_small_budget_keeps_the_main_jobs_apg_settings_valid():
    """``MT_SMALL_BUDGET=1 mt-main`` shrinks APG to 3 steps; the default's ``average_last`` (90)
    shrinks with it instead of failing APG's check after the run has started."""
    from mixed_traffic.apps.main_job import DEFAULT_EXPERIMENT, apply_small_budget

    cfg = compose([f"experiment={DEFAULT_EXPERIMENT}"])
    assert cfg.policy.apg.average_last > 3
    apply_small_budget(cfg)
    assert cfg.policy.apg.iterations == 3 and cfg.policy.apg.average_last == 3
    assert cfg.trainer.total_frames <= 4 * cfg.trainer.num_envs * cfg.trainer.rollout_len


def test_soft_experiment_is_the_default_over_the_speed_scaled_soft_base():
    """``experiment=ring_lagrangian_ppo_soft`` changes only the residual's base: its parameters are
    ``physics.SOFT_SCALED`` and the IDM base's ``gap_max`` is nulled (dropped) so the soft base builds."""
    from mixed_traffic.physics import SOFT_SCALED
    from mixed_traffic.training.builders import make_transformed_env
    from mixed_traffic.validation import validate_config

    soft, smooth = (compose([f"experiment={n}"]) for n in ("ring_lagrangian_ppo_soft", "ring_lagrangian_ppo_smooth"))
    params = dict(soft.transforms.residual.params)
    assert soft.transforms.residual.base == "soft" and params.pop("gap_max") is None and params.pop("v0") == 60.0
    assert params == SOFT_SCALED
    for key in ("policy", "loss", "trainer", "env"):
        assert OmegaConf.to_container(soft[key]) == OmegaConf.to_container(smooth[key]), key
    validate_config(soft)
    env = make_transformed_env(soft, num_envs=2, seed=0)
    assert env.rollout(5)["next", "cav", "gap"].shape[:2] == (2, 5)
    # a null elsewhere is no override either; a number for a parameter the base lacks still fails
    validate_config(compose(["experiment=ring_lagrangian_ppo_soft", "transforms.residual.params.s9=null"]))
    with pytest.raises(ValueError, match=r"transforms\.residual\.params\.gap_max"):
        validate_config(compose(["experiment=ring_lagrangian_ppo_soft", "transforms.residual.params.gap_max=27.0"]))


def test_scheduled_experiment_adds_the_high_speed_law_to_the_soft_base():
    """``experiment=ring_lagrangian_ppo_scheduled`` is ``ring_lagrangian_ppo_soft`` with the default's capped
    IDM taking the base over from 10 to 16 m/s, a stronger closing gain and the base unclipped; bad
    ``high_speed`` fields fail naming the field."""
    from mixed_traffic.controllers.classic import SpeedScheduledCAV
    from mixed_traffic.training.builders import make_transformed_env
    from mixed_traffic.validation import validate_config

    sched, soft = (compose([f"experiment={n}"]) for n in ("ring_lagrangian_ppo_scheduled", "ring_lagrangian_ppo_soft"))
    assert soft.transforms.residual.high_speed.base is None  # off unless set
    high = {"base": "idm", "params": {"s0": 7.0, "v0": 60.0, "gap_max": 27.0}, "v_low": 10.0, "v_high": 16.0,
            "brake_floor": None, "brake_margin": 0.3}
    assert_differs_only_in(sched, soft, {"transforms.residual.high_speed": high,
                                         "transforms.residual.saturate_base": False,
                                         "transforms.residual.params.kv_closing": 1.0})
    cfg = validate_config(compose(["experiment=ring_lagrangian_ppo_scheduled"]))
    env = make_transformed_env(cfg, num_envs=2, seed=0)
    bases = [t.base.module for t in env.transform if hasattr(t, "base")]
    assert len(bases) == 1 and isinstance(bases[0], SpeedScheduledCAV)
    assert env.rollout(5)["next", "cav", "gap"].shape[:2] == (2, 5)
    for bad, field in (("transforms.residual.high_speed.v_low=20.0", "high_speed.v_high"),
                       ("transforms.residual.high_speed.v_low=-1.0", "high_speed.v_low"),
                       ("transforms.residual.high_speed.params.s9=1.0", "high_speed.params.s9"),
                       ("transforms.residual.high_speed.base=pid", "high_speed.base")):
        with pytest.raises(ValueError, match=field.replace(".", r"\.")):
            validate_config(compose(["experiment=ring_lagrangian_ppo_scheduled", bad]))


def test_tight_experiment_reshapes_only_the_soft_laws_speed_gains():
    """``experiment=ring_lagrangian_ppo_tight`` is ``ring_lagrangian_ppo_scheduled`` with the soft follower's
    kv, kv_closing and kv_closing_near changed and nothing else; a negative ``kv_closing_near`` fails at
    the build, naming it."""
    from mixed_traffic.training.builders import make_transformed_env
    from mixed_traffic.validation import validate_config

    tight, sched = (compose([f"experiment={n}"]) for n in ("ring_lagrangian_ppo_tight", "ring_lagrangian_ppo_scheduled"))
    assert_differs_only_in(tight, sched, {"transforms.residual.params.kv": 1.5,
                                          "transforms.residual.params.kv_closing": 0.71,
                                          "transforms.residual.params.kv_closing_near": 0.75})
    bad = validate_config(compose(["experiment=ring_lagrangian_ppo_tight", "transforms.residual.params.kv_closing_near=-1"]))
    with pytest.raises(ValueError, match="kv_closing_near"):
        make_transformed_env(bad, num_envs=1, seed=0)


def test_band_experiment_adds_a_third_law_and_the_fade_and_nothing_else():
    """``experiment=ring_lagrangian_ppo_band`` is ``ring_lagrangian_ppo_tight`` with ``top_speed`` (the
    soft follower's band terms above 20 m/s) and ``fade_speeds`` set and nothing else; both reach the
    built base and transform; a reversed speed pair fails at start-up, naming the field."""
    from mixed_traffic.controllers.classic import SpeedScheduledCAV
    from mixed_traffic.training.builders import make_transformed_env
    from mixed_traffic.validation import ConfigError, validate_config
    from transforms import ResidualAction

    band, tight = (compose([f"experiment={n}"]) for n in ("ring_lagrangian_ppo_band", "ring_lagrangian_ppo_tight"))
    top = band.transforms.residual.top_speed
    assert (top.base, top.v_low, top.v_high) == ("soft", 18.0, 20.0)
    assert {"match_gap_min", "match_gap_max", "ks_edge"} <= set(top.params)
    assert tight.transforms.residual.fade_speeds is None
    assert_differs_only_in(band, tight, {"transforms.residual.top_speed": ANY,
                                         "transforms.residual.fade_speeds": [18.0, 20.0]})
    cfg = validate_config(compose(["experiment=ring_lagrangian_ppo_band"]))
    res = [t for t in make_transformed_env(cfg, num_envs=1, seed=0).transform if isinstance(t, ResidualAction)]
    assert res[0].fade_speeds == (18.0, 20.0)
    outer = res[0].base.module
    assert isinstance(outer, SpeedScheduledCAV) and isinstance(outer.low, SpeedScheduledCAV)  # three laws
    assert (outer.v_low, outer.v_high) == (18.0, 20.0) and outer.high.params["match_gap_max"] == 32.0
    for bad, field in (("transforms.residual.fade_speeds=[20.0,18.0]", "transforms.residual.fade_speeds"),
                       ("transforms.residual.top_speed.v_high=10.0", "transforms.residual.top_speed.v_high"),
                       ("transforms.residual.top_speed.params.ks_edge=x", "transforms.residual.top_speed.params.ks_edge")):
        with pytest.raises(ConfigError, match=field.replace(".", r"\.")):
            validate_config(compose(["experiment=ring_lagrangian_ppo_band", bad]))


def test_band_stop_experiment_adds_the_stopping_envelope_and_nothing_else():
    """``experiment=ring_lagrangian_ppo_band_stop`` is ``ring_lagrangian_ppo_band`` with ``stop_gap`` 5 m (the
    safety layer's s_min) and ``envelope_fade: deploy`` and nothing else; the envelope wraps the built base;
    the residual reads the base's room below it where the policy is evaluated (``deploy=True``) and not in
    training; a gap of 0, a fade without a gap or a margin without a fade fails at start-up naming the field."""
    from mixed_traffic.controllers.classic import SpeedScheduledCAV, StoppingEnvelope
    from mixed_traffic.training.builders import make_transformed_env
    from mixed_traffic.validation import ConfigError, validate_config
    from transforms import ResidualAction

    stop, band = (compose([f"experiment={n}"]) for n in ("ring_lagrangian_ppo_band_stop", "ring_lagrangian_ppo_band"))
    assert stop.transforms.residual.stop_gap == stop.transforms.safety_layer.s_min == 5.0
    assert band.transforms.residual.stop_gap is None and band.transforms.residual.envelope_fade == "off"
    assert_differs_only_in(stop, band, {"transforms.residual.stop_gap": 5.0, "transforms.residual.envelope_fade": "deploy"})
    cfg = validate_config(compose(["experiment=ring_lagrangian_ppo_band_stop"]))
    train = [t for t in make_transformed_env(cfg, num_envs=1, seed=0).transform if isinstance(t, ResidualAction)]
    assert train[0].room_key is None and isinstance(train[0].base.module, StoppingEnvelope)
    res = [t for t in make_transformed_env(cfg, num_envs=1, seed=0, deploy=True).transform
           if isinstance(t, ResidualAction)]
    env_ = res[0].base.module.envelope
    assert isinstance(env_, StoppingEnvelope) and isinstance(env_.law, SpeedScheduledCAV) and env_.stop_gap == 5.0
    assert res[0].room_key == res[0].base.out_keys[1] and res[0].slack_key is None
    with pytest.raises(ConfigError, match=r"transforms\.residual\.stop_gap"):
        validate_config(compose(["experiment=ring_lagrangian_ppo_band", "transforms.residual.stop_gap=0"]))
    with pytest.raises(ConfigError, match=r"transforms\.residual\.envelope_fade"):
        validate_config(compose(["experiment=ring_lagrangian_ppo_band", "transforms.residual.envelope_fade=always"]))
    with pytest.raises(ConfigError, match=r"transforms\.residual\.envelope_fade"):
        validate_config(compose(["experiment=ring_lagrangian_ppo_band_stop", "transforms.residual.envelope_fade=true"]))
    with pytest.raises(ConfigError, match=r"transforms\.residual\.envelope_fade_slack"):
        validate_config(compose(["experiment=ring_lagrangian_ppo_band_stop", "transforms.residual.envelope_fade=off",
                                 "transforms.residual.envelope_fade_slack=3"]))
    with pytest.raises(ConfigError, match=r"transforms\.residual\.envelope_fade_slack"):
        validate_config(compose(["experiment=ring_lagrangian_ppo_band_stop", "transforms.residual.envelope_fade_slack=0"]))


def test_band_stop_lift_experiment_is_band_stop_with_a_deploy_only_lift_and_nothing_else():
    """``experiment=ring_lagrangian_ppo_band_stop_lift`` differs from the default only in ``catch_up``, lifted at
    deployment only: the same training config, so the same weights."""
    lift, stop = (compose([f"experiment={n}"]) for n in ("ring_lagrangian_ppo_band_stop_lift",
                                                        "ring_lagrangian_ppo_band_stop"))
    assert lift.transforms.residual.catch_up.when == "deploy" and lift.transforms.residual.catch_up.accel > 0
    assert_differs_only_in(lift, stop, {"transforms.residual.catch_up": ANY})


def test_wide_band_experiment_is_the_lift_experiment_with_a_law_beyond_the_training_range_and_nothing_else():
    """``experiment=ring_lagrangian_ppo_wide_band`` adds only ``beyond_speed``, a band law with a wider band that
    takes over from 20 m/s, the top of the training range: below it the base, and so training, are unchanged."""
    from mixed_traffic.validation import ConfigError, validate_config

    wide, lift = (compose([f"experiment={n}"]) for n in ("ring_lagrangian_ppo_wide_band",
                                                        "ring_lagrangian_ppo_band_stop_lift"))
    validate_config(wide)  # raises on a bad field
    for bad, field in (("transforms.residual.beyond_speed.v_high=19.0", "transforms.residual.beyond_speed.v_high"),
                       ("transforms.residual.beyond_speed.base=gipps", "transforms.residual.beyond_speed.base"),
                       ("transforms.residual.beyond_speed.params.kvv=0.3", "transforms.residual.beyond_speed.params")):
        with pytest.raises(ConfigError, match=field.replace(".", r"\.")):
            validate_config(compose(["experiment=ring_lagrangian_ppo_wide_band", bad]))
    beyond, top = wide.transforms.residual.beyond_speed, wide.transforms.residual.top_speed
    assert beyond.base == "soft" and beyond.v_low >= top.v_high == 20.0  # the training profile's top speed
    assert beyond.params.match_gap_min < top.params.match_gap_min
    assert top.params.match_gap_max < beyond.params.match_gap_max <= 40.0  # the band's edge
    assert lift.transforms.residual.beyond_speed.base is None
    assert_differs_only_in(wide, lift, {"transforms.residual.beyond_speed": ANY})


def test_v2v_experiment_is_the_wide_band_with_a_brake_floor_and_a_longer_apg_average_and_nothing_else():
    """``experiment=ring_lagrangian_ppo_v2v`` (the default's training) is the wide band's config with the IDM slot's braking
    floored by the leader's (read over V2V) and the pre-training's weights averaged over 90 of its 100 steps."""
    from mixed_traffic.validation import ConfigError, validate_config

    v2v, wide = (compose([f"experiment={n}"]) for n in ("ring_lagrangian_ppo_v2v", "ring_lagrangian_ppo_wide_band"))
    validate_config(v2v)
    assert v2v.transforms.residual.high_speed.brake_margin == 0.3
    assert v2v.policy.apg.average_last < v2v.policy.apg.iterations == 100
    with pytest.raises(ConfigError, match=r"policy\.apg\.average_last"):  # more steps than the pre-training has
        validate_config(compose(["experiment=ring_lagrangian_ppo_v2v", "policy.apg.average_last=101"]))
    assert_differs_only_in(v2v, wide, {"transforms.residual.high_speed.brake_floor": 1.0, "policy.apg.average_last": 90})


def test_the_drive_off_experiment_is_v2v_with_a_drive_off_cap_at_deployment_and_nothing_else():
    """``experiment=ring_lagrangian_ppo_drive_off`` trains as ``ring_lagrangian_ppo_v2v`` and adds the drive-off cap
    where the policy is evaluated or deployed."""
    from mixed_traffic.validation import validate_config

    d, v2v = (compose([f"experiment={n}"]) for n in ("ring_lagrangian_ppo_drive_off", "ring_lagrangian_ppo_v2v"))
    validate_config(d)
    assert d.transforms.residual.drive_off.gain == 1.0 and d.transforms.residual.drive_off.when == "deploy"
    assert_differs_only_in(d, v2v, {"transforms.residual.drive_off": ANY})


def test_the_layer_recover_experiment_is_drive_off_with_the_recover_rule_at_deployment_and_nothing_else():
    """``experiment=ring_lagrangian_ppo_layer_recover`` trains as ``ring_lagrangian_ppo_drive_off`` and deploys the
    safety layer with ``recover`` beyond its s_max."""
    from mixed_traffic.validation import validate_config

    d, prev = (compose([f"experiment={n}"]) for n in ("ring_lagrangian_ppo_layer_recover", "ring_lagrangian_ppo_drive_off"))
    validate_config(d)
    assert d.transforms.safety_layer.beyond_s_max == "push"
    assert prev.transforms.safety_layer.deployed_beyond_s_max is None
    assert_differs_only_in(d, prev, {"transforms.safety_layer.deployed_beyond_s_max": "recover"})


def test_cap_hold_is_residual_play_with_the_drive_off_cap_held_for_40_s_and_nothing_else():
    """``experiment=ring_lagrangian_ppo_cap_hold`` (the previous default) is ``ring_lagrangian_ppo_residual_play`` with
    the (deploy-only) drive-off cap released 40 s after the CAV has matched its leader instead of 5 s."""
    from mixed_traffic.validation import validate_config

    d, prev = (compose([f"experiment={n}"]) for n in ("ring_lagrangian_ppo_cap_hold", "ring_lagrangian_ppo_residual_play"))
    validate_config(d)
    assert d.transforms.residual.drive_off.when == "deploy" and prev.transforms.residual.drive_off.release == 5.0
    assert_differs_only_in(d, prev, {"transforms.residual.drive_off.release": 40.0})


def test_residual_play_is_the_safety_net_with_the_residuals_backlash_under_the_drive_off_cap_and_nothing_else():
    """``experiment=ring_lagrangian_ppo_residual_play`` is ``ring_lagrangian_ppo_safety_net`` with a backlash of
    0.1 m/s^2 on the residual while the (deploy-only) drive-off cap is engaged."""
    from mixed_traffic.validation import validate_config

    d, prev = (compose([f"experiment={n}"]) for n in ("ring_lagrangian_ppo_residual_play", "ring_lagrangian_ppo_safety_net"))
    validate_config(d)
    assert d.transforms.residual.drive_off.when == "deploy" and prev.transforms.residual.drive_off.residual_play is None
    assert_differs_only_in(d, prev, {"transforms.residual.drive_off.residual_play": 0.1})


def test_the_safety_net_is_drive_off_with_the_layer_deployed_as_the_safety_net_alone_and_nothing_else():
    """``experiment=ring_lagrangian_ppo_safety_net`` trains as ``ring_lagrangian_ppo_drive_off`` and deploys the
    safety layer with its s_min rule only."""
    from mixed_traffic.validation import validate_config

    d, prev = (compose([f"experiment={n}"]) for n in ("ring_lagrangian_ppo_safety_net", "ring_lagrangian_ppo_drive_off"))
    validate_config(d)
    assert d.transforms.safety_layer.s_max == 38.0 and prev.transforms.safety_layer.deployed_s_max is True
    assert_differs_only_in(d, prev, {"transforms.safety_layer.deployed_s_max": False})


def test_gentle_experiment_changes_only_the_soft_laws_spring_the_stand_and_the_arrival():
    """``experiment=ring_lagrangian_ppo_gentle`` is ``ring_lagrangian_ppo_follow`` with the soft law's ks, kv,
    kv_closing and kv_closing_near changed, the drive-off cap's ``hold`` on and the envelope's arrival term on
    (``arrive_gain``), and nothing else."""
    gentle, follow = (compose([f"experiment={n}"]) for n in ("ring_lagrangian_ppo_gentle", "ring_lagrangian_ppo_follow"))
    assert follow.transforms.residual.drive_off.hold is False and follow.transforms.residual.arrive_gain is None
    changed = {"ks": 0.06, "kv": 1.25, "kv_closing": 0.5, "kv_closing_near": 1.0}
    assert_differs_only_in(gentle, follow, {**{f"transforms.residual.params.{k}": v for k, v in changed.items()},
                                            "transforms.residual.drive_off.hold": True,
                                            "transforms.residual.arrive_gain": 1.0})


def test_gentle_join_and_lag_experiments_change_only_the_join_and_the_soft_law():
    """``experiment=ring_lagrangian_ppo_gentle_join`` (the default's deployment) is ``ring_lagrangian_ppo_gentle`` with the join law's headway,
    braking and leader-speed gate changed, a deploy-only part (so it trains the gentle experiment's weights); and
    ``experiment=ring_lagrangian_ppo_lag`` is the former with the soft law's speed gains at 1 / h (a first-order lag)."""
    gentle, join, lag = (compose([f"experiment=ring_lagrangian_ppo_{n}"]) for n in ("gentle", "gentle_join", "lag"))
    assert join.transforms.residual.join.when == "deploy"
    assert (join.transforms.residual.join.params.T, join.transforms.residual.join.params.b) == (1.0, 2.0)
    assert join.transforms.residual.join.leader_speeds is None
    assert list(gentle.transforms.residual.join.leader_speeds) == [16.0, 20.0]
    params = lag.transforms.residual.params
    assert params.kv == params.kv_closing == pytest.approx(1 / params.h, abs=1e-3) and params.kv_closing_near == 0.0
    for cfg, ref in ((join, gentle), (lag, join)):
        assert_differs_only_in(cfg, ref, {"transforms.residual.join": ANY, "transforms.residual.params": ANY})


def test_default_experiment_is_fast_band_and_paced_join_is_apg60_with_a_join_paced_by_the_leaders_speed():
    """The default (``mt-main``) is ``experiment=ring_lagrangian_ppo_fast_band`` (``ring_lagrangian_ppo_smooth_stop``,
    the default before it, with one band law from 18 m/s up and a brake floor on its IDM; ``smooth_stop`` is
    ``ring_lagrangian_ppo_near_gap`` with a stand arrival in its base and a softer answer to a leader that pulls away;
    ``near_gap`` is ``ring_lagrangian_ppo_paced_join`` with its base's gaps changed; tests/test_physics.py checks what
    each changes). ``ring_lagrangian_ppo_paced_join`` (the default before those) is ``ring_lagrangian_ppo_apg60`` with the join law's settings changed and nothing else; the
    join is deploy-only, so the chain it trains is apg60's."""
    from mixed_traffic.apps.main_job import DEFAULT_EXPERIMENT

    assert DEFAULT_EXPERIMENT == "ring_lagrangian_ppo_fast_band"
    # fast_band deploys a gentler drive-off follow than smooth_stop (0.8, from 0.9), a deploy-only part: the chain it
    # trains has no drive-off cap, so the weights are the same
    from mixed_traffic.training.builders import make_transformed_env
    from mixed_traffic.validation import validate_config
    from transforms import DriveOffCap

    fast = validate_config(compose(["experiment=ring_lagrangian_ppo_fast_band"]))
    assert compose(["experiment=ring_lagrangian_ppo_smooth_stop"]).transforms.residual.drive_off.follow == 0.9
    trained, deployed = ([t for t in make_transformed_env(fast, num_envs=1, seed=0, deploy=dep).transform
                          if isinstance(t, DriveOffCap)] for dep in (False, True))
    assert trained == [] and deployed[0].follow == 0.8
    apg60, paced = (compose([f"experiment=ring_lagrangian_ppo_{n}"]) for n in ("apg60", "paced_join"))
    assert paced.transforms.residual.join.when == "deploy"
    assert_differs_only_in(paced, apg60, {"transforms.residual.join.params.v0": 40.0,
                                          "transforms.residual.join.params.gap_max": None,
                                          "transforms.residual.join.fast_params": {"v0": 60.0, "gap_max": 27.0},
                                          "transforms.residual.join.fast_leader_speeds": [19.0, 21.0]})


def test_apg60_is_the_gentle_join_with_fewer_analytic_gradient_steps():
    """``experiment=ring_lagrangian_ppo_apg60`` (the default before ``ring_lagrangian_ppo_paced_join``, whose weights
    it trains) is ``ring_lagrangian_ppo_gentle_join`` with 60 analytic-gradient steps, the last 50 averaged, and
    nothing else changed."""
    join, short = (compose([f"experiment=ring_lagrangian_ppo_{n}"]) for n in ("gentle_join", "apg60"))
    assert (join.policy.apg.iterations, join.policy.apg.average_last) == (100, 90)
    assert_differs_only_in(short, join, {"policy.apg.iterations": 60, "policy.apg.average_last": 50})


def test_calm_join_is_apg60_with_a_join_law_that_accelerates_at_1_4_and_nothing_else():
    """``experiment=ring_lagrangian_ppo_calm_join`` is ``ring_lagrangian_ppo_apg60`` with the join law's acceleration
    at 1.4 m/s^2 (IDM's 2.0 before), a deploy-only part, so it trains apg60's weights."""
    apg60, calm = (compose([f"experiment=ring_lagrangian_ppo_{n}"]) for n in ("apg60", "calm_join"))
    assert calm.transforms.residual.join.when == "deploy" and "a" not in apg60.transforms.residual.join.params
    assert_differs_only_in(calm, apg60, {"transforms.residual.join.params.a": 1.4})


def test_stable_experiment_is_apg60_with_a_linear_string_stable_base_and_the_calm_join():
    """``experiment=ring_lagrangian_ppo_stable`` (tried, not kept) is ``ring_lagrangian_ppo_apg60`` with the soft law
    made linear at every speed below the top-speed laws (the high-speed IDM off, no speed scaling, one speed gain
    both ways) with ``2 kv h + ks h^2 >= 2`` (no oscillation of the leader's speed amplified, linearised), and the join
    accelerating at 1.4 m/s^2 and handing over at 26 m or 40 s."""
    apg60, stable = (compose([f"experiment=ring_lagrangian_ppo_{n}"]) for n in ("apg60", "stable"))
    p = stable.transforms.residual.params
    assert 2 * p.kv * p.h + p.ks * p.h**2 >= 2 and p.kv == p.kv_closing
    assert_differs_only_in(stable, apg60, {
        "transforms.residual.params.ks": 0.4, "transforms.residual.params.kv": 0.55,
        "transforms.residual.params.kv_closing": 0.55, "transforms.residual.params.kv_closing_near": 0.0,
        "transforms.residual.params.h": 1.3, "transforms.residual.params.s0": 0.5,
        "transforms.residual.params.v_ref": None, "transforms.residual.high_speed.base": None,
        "transforms.residual.join.params.a": 1.4, "transforms.residual.join.gap": 26.0,
        "transforms.residual.join.seconds": 40.0})


def test_lead_join_is_apg60_with_the_join_law_desired_speed_tied_to_the_leaders_and_nothing_else():
    """``experiment=ring_lagrangian_ppo_lead_join`` (tried, not the default) is ``ring_lagrangian_ppo_apg60`` with the
    join law's IDM desired speed max(30 m/s, 1.8 x the leader's): only ``transforms.residual.join.params.v0`` and
    ``.v0_leader`` differ (and the name), so the training, and the weights, are apg60's."""
    base, lead = (compose([f"experiment=ring_lagrangian_ppo_{n}"]) for n in ("apg60", "lead_join"))
    assert base.transforms.residual.join.params.v0 == 60.0 and "v0_leader" not in base.transforms.residual.join.params
    assert_differs_only_in(lead, base, {"transforms.residual.join.params.v0": 30.0,
                                        "transforms.residual.join.params.v0_leader": 1.8})


def test_compose_keeps_a_composition_hands_out_copies_and_sees_a_changed_config_file():
    """``compose`` keeps what it composed while no file of hydra_configs changes: a second call returns an equal
    config of its own (a change to one is not seen by the next), and a config file touched on disk is composed
    again."""
    import hydra_configs
    from mixed_traffic import config as C

    over = ["experiment=ring_ppo", "seed=7"]
    first = compose(over)
    first.trainer.lr = 123.0  # the caller's copy
    again = compose(over)
    assert again.trainer.lr != 123.0 and again.seed == 7 and again is not first
    assert OmegaConf.to_yaml(again) == OmegaConf.to_yaml(compose(over))
    kept = C._COMPOSED[(tuple(over), C.CONFIG_NAME)][0]
    path = os.path.join(os.path.dirname(hydra_configs.__file__), "experiment", "ring_ppo.yaml")
    st = os.stat(path)
    try:
        os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))
        compose(over)
        assert C._COMPOSED[(tuple(over), C.CONFIG_NAME)][0] != kept  # composed again from the tree as it is now
    finally:
        os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
