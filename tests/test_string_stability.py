"""``benchmarks/string_stability.py``: the linearised follower's gain against its closed-form criterion."""

import argparse

import pytest


@pytest.mark.parametrize("ks, kv, h, stable", [(0.4, 0.55, 1.3, True), (0.05, 0.4, 1.3, False),
                                                (0.3, 0.9, 1.0, True), (0.3, 0.5, 1.0, False)])
def test_linear_law_gain_stays_under_one_exactly_when_the_criterion_holds(benchmark_script, ks, kv, h, stable):
    """A linear spring and damper on the gap ``s0 + h v``: its slope is ``h``, its gains are its own, and the peak of
    |H(jw)| is 1 (at w -> 0) when ``2 kv h + ks h^2 >= 2`` and above 1 when not."""
    mod = benchmark_script("string_stability")
    _, f = mod.law(argparse.Namespace(linear=(ks, kv, h, 2.0), idm=[]))
    r = mod.linearise(f, 12.0)
    assert r["gap"] == pytest.approx(2.0 + h * 12.0, abs=1e-6)
    assert (r["ks"], r["kv"], r["slope"]) == pytest.approx((ks, kv, h), abs=1e-6)
    assert (2 * kv * h + ks * h**2 >= 2) == stable
    assert (r["max_h"] <= 1.0 + 1e-9) == stable


def test_idm_equilibrium_is_idms_own_and_its_gain_is_marginally_above_one(benchmark_script):
    """IDM (``IDMParams()``) at 10 m/s drives steadily at ``(s0 + v T) / sqrt(1 - (v/v0)^4)`` and amplifies its
    leader's oscillation a little (the criterion 1.68 < 2)."""
    mod = benchmark_script("string_stability")
    _, f = mod.law(argparse.Namespace(linear=None, idm=[]))
    r = mod.linearise(f, 10.0)
    assert r["gap"] == pytest.approx(12.5 / (1 - (10 / 30) ** 4) ** 0.5, rel=1e-6)
    assert r["criterion"] < 2 and 1.0 < r["max_h"] < 1.05


def test_an_unknown_idm_parameter_is_named(benchmark_script):
    mod = benchmark_script("string_stability")
    with pytest.raises(SystemExit, match="'tau' is not an IDM parameter"):
        mod.law(argparse.Namespace(linear=None, idm=["tau=1.0"]))
