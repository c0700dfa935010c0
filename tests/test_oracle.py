"""The clairvoyant least-jerk program: its optimum against a hand solution, its sequence replayed
through the env's integrator, its bound below any controller that keeps the bars, clear errors."""

import pytest
import torch

from mixed_traffic.evaluation.harness import abs_jerk
from mixed_traffic.evaluation.oracle import (
    OwnCost,
    causal_least_jerk,
    history_groups,
    least_jerk,
    least_jerk_of_trace,
    preview_least_jerk,
    steady_mask,
)
from mixed_traffic.physics import idm_accel, integrate

DT = 0.1


def _step_head(v1=10.0, v2=16.0, n1=50, n2=550):
    return torch.cat([torch.full((n1,), v1), torch.full((n2,), v2)]).double()


def test_least_jerk_matches_the_hand_solution_of_a_speed_step():
    # the head drives 6 m/s faster than the CAV from the first step (nothing to anticipate); the gap may
    # open by H = 40 - 20 m. The least variation of the acceleration: one plateau at the smallest A that
    # closes the speed gap before the gap has opened by H (Euler steps: dv^2 / (2 A) - dv dt / 2 = H), then
    # a drop to the small acceleration a_end with which the gap shrinks back from 40 to 5 m by the episode's
    # end (a_end t^2 / 2 = 35 m over the t seconds left); the first step's rise is not counted, as in the report
    head = _step_head(16.0, 16.0, 0, 600)
    r = least_jerk(head, v_start=10.0, gap_start=20.0, dt=DT, warmup=0.0, s_min=5.0, s_max=40.0)
    plateau = 6.0 ** 2 / (2 * (20.0 + 6.0 * DT / 2))
    a_end = 2 * 35.0 / (60.0 - 6.0 / plateau) ** 2
    assert float(r.accel[0]) == pytest.approx(plateau, rel=1e-3)
    assert r.jerk * (head.numel() - 1) * DT == pytest.approx(plateau - a_end, rel=0.01)
    assert float(r.gap.max()) <= 40.0 + 1e-6
    # with the step 5 s ahead, knowing it lets the CAV close in on the head first and spread the change
    early = least_jerk(_step_head(10.0, 16.0, 50, 550), v_start=10.0, gap_start=20.0, dt=DT, warmup=0.0, s_min=5.0,
                       s_max=40.0)
    assert early.jerk < r.jerk and float(early.gap.min()) < 20.0


def test_the_sequence_replayed_through_the_env_integrator_keeps_the_bars_and_costs_the_optimum():
    head = torch.cat([_step_head(), torch.full((300,), 11.0).double()])
    r = least_jerk(head, v_start=12.0, gap_start=30.0, dt=DT, warmup=5.0, s_min=5.0, s_max=40.0)
    x_h, x_c = torch.tensor(30.0, dtype=torch.float64), torch.tensor(0.0, dtype=torch.float64)
    v = torch.tensor(12.0, dtype=torch.float64)
    gaps, accels = [], []
    for t in range(head.numel()):
        x_h = x_h + head[t] * DT  # the head's post-step speed, as in a trace (Euler: x' = x + v' dt)
        x_c, v, executed = integrate(x_c, v, r.accel[t], DT, "euler")
        gaps.append(float(x_h - x_c))
        accels.append(float(executed))
    gaps = torch.tensor(gaps)
    assert torch.allclose(gaps, r.gap.float(), atol=1e-4)
    assert float(gaps[49:].min()) >= 5.0 - 1e-4 and float(gaps[49:].max()) <= 40.0 + 1e-4
    jerk, valid = abs_jerk(torch.tensor([accels]), torch.ones(1, len(accels), dtype=torch.bool), DT)
    assert float(jerk[valid].mean()) == pytest.approx(r.jerk, rel=1e-5)


def test_no_controller_that_keeps_the_bars_has_less_jerk():
    # an IDM follower (closed loop, the env's integrator) keeps [5, 40] m on this head; its jerk is a
    # feasible point of the program, so the optimum lies at or below it
    head = torch.cat([_step_head(10.0, 14.0, 100, 200), torch.full((200,), 8.0), torch.full((200,), 12.0)]).double()
    x_h, x_c, v = 25.0, 0.0, torch.tensor(10.0, dtype=torch.float64)
    gaps, accels = [], []
    for t in range(head.numel()):
        a = idm_accel(torch.tensor(x_h - x_c - 0.0), v, head[t - 1] if t else head[0], v0=30.0, T=1.0, a=2.0, b=3.0,
                      delta=4.0, s0=5.0).clamp(-3.0, 3.0)
        x_h = x_h + float(head[t]) * DT
        x_c, v, executed = integrate(torch.tensor(x_c), v, a, DT, "euler")
        x_c = float(x_c)
        gaps.append(x_h - x_c)
        accels.append(float(executed))
    assert min(gaps) >= 5.0 and max(gaps[200:]) <= 40.0
    jerk, valid = abs_jerk(torch.tensor([accels]), torch.ones(1, len(accels), dtype=torch.bool), DT)
    r = least_jerk(head, v_start=10.0, gap_start=25.0, dt=DT, warmup=20.0, s_min=5.0, s_max=40.0)
    assert 0.0 <= r.jerk <= float(jerk[valid].mean())


def test_the_rmse_relaxation_sits_below_the_sequence_that_meets_it():
    head = torch.cat([_step_head(10.0, 14.0, 100, 200), torch.full((300,), 10.0)]).double()
    steady = torch.zeros(head.numel(), dtype=torch.bool)
    steady[250:300] = True
    steady[550:] = True
    kw = dict(v_start=10.0, gap_start=20.0, dt=DT, warmup=5.0, s_min=5.0, s_max=40.0)
    band = least_jerk(head, **kw).jerk
    lower = least_jerk(head, steady=steady, rmse=0.2, norm="l1", **kw)
    upper = least_jerk(head, steady=steady, rmse=0.2, norm="linf", **kw)
    assert band <= lower.jerk + 1e-9 <= upper.jerk + 2e-9
    err = (upper.speed - head)[steady]
    assert float(err.abs().max()) <= 0.2 + 1e-6 and float(err.pow(2).mean().sqrt()) <= 0.2 + 1e-6
    assert float((lower.speed - head)[steady].abs().mean()) <= 0.2 + 1e-6


def test_the_trace_helper_recovers_the_start_and_the_reports_steady_samples():
    from mixed_traffic.evaluation.harness import Trace

    head = _step_head(10.0, 14.0, 100, 200).float()
    n = head.numel()
    time = (torch.arange(n) + 1) * DT
    accel = torch.zeros(n)
    accel[100:140] = 1.0  # the CAV's own answer, which keeps the bars: speed 10 -> 14 over 4 s
    speed = 10.0 + torch.cumsum(accel, 0) * DT
    gap = 20.0 + torch.cumsum(head - speed, 0) * DT
    head_accel = torch.zeros(n)
    head_accel[100] = 40.0
    tr = Trace(time=time[None], head_speed=head[None], cav_speed=speed[None], cav_accel=accel[None],
               head_accel=head_accel[None], gap=gap[None], head_gap=gap[None], valid=torch.ones(1, n, dtype=torch.bool),
               raw_accel=accel[None])
    st = steady_mask(tr, dt=DT, warmup=5.0, settle=8.0)
    # steady: 8 s (80 steps) without the head accelerating, after the 5-s warm-up
    assert st[0, :79].sum() == 0 and bool(st[0, 79:100].all())
    assert st[0, 100:180].sum() == 0 and bool(st[0, 180:].all())
    r = least_jerk_of_trace(tr, 0, dt=DT, warmup=5.0, s_min=5.0, s_max=40.0, steady=st, rmse=0.2)
    own, valid = abs_jerk(accel[None], tr.valid, DT)
    assert r.jerk <= float(own[valid].mean()) + 1e-9
    # the start it recovered from the trace's first step: the CAV at 10 m/s, 20 m behind the head
    assert float(r.speed[0] - r.accel[0] * DT) == pytest.approx(10.0, abs=1e-4)
    assert float(r.gap[0] - DT * (head[0] - r.speed[0])) == pytest.approx(20.0, abs=1e-4)
    tr.head_gap = tr.head_gap + 1.0
    with pytest.raises(ValueError, match="right behind the head"):
        least_jerk_of_trace(tr, 0, dt=DT, warmup=5.0, s_min=5.0, s_max=40.0)


@pytest.mark.parametrize("kwargs, field", [
    ({"dt": 0.0}, "dt"), ({"v_start": -1.0}, "v_start"), ({"gap_start": 0.0}, "gap_start"),
    ({"accel_bounds": (1.0, 3.0)}, "accel_bounds"), ({"s_max": 4.0}, "s_max"), ({"norm": "l2"}, "norm"),
    ({"rmse": 0.2}, "steady"), ({"rmse": -0.1, "steady": torch.ones(600, dtype=torch.bool)}, "rmse"),
    ({"end_speed": -1.0}, "end_speed"), ({"band_weight": 0.0}, "band_weight"), ({"a_prev": float("nan")}, "a_prev"),
    ({"track_weight": -1.0}, "track_weight"),
])
def test_bad_input_names_the_argument(kwargs, field):
    base = dict(v_start=10.0, gap_start=20.0, dt=DT, warmup=0.0, s_min=5.0, s_max=40.0)
    with pytest.raises(ValueError, match=field):
        least_jerk(_step_head(), **{**base, **kwargs})


def test_an_episode_no_command_can_keep_in_the_band_is_reported():
    # the head drives 20 m/s faster from the first step; with 3 m/s^2 the CAV cannot hold the gap within 40 m
    with pytest.raises(ValueError, match="no command sequence"):
        least_jerk(_step_head(30.0, 30.0, 0, 600), v_start=10.0, gap_start=30.0, dt=DT, warmup=0.0, s_min=5.0,
                   s_max=40.0)


def test_the_module_example_runs():
    import doctest

    from mixed_traffic.evaluation import oracle

    result = doctest.testmod(oracle)
    assert result.attempted >= 3 and result.failed == 0


def test_stopping_constraint_holds_the_layers_own_rule_at_every_step_and_costs_jerk():
    """``stop_gap``: every step of the optimum ends in the stopping-safe set, checked with the safety layer's
    own rule (``safe_accel_upper``, which the program does not call); the constraint can only raise the
    optimum; a stop_gap without the head's braking bound fails, naming it."""
    from transforms.safety_layer import safe_accel_upper

    head = torch.cat([torch.full((150,), 27.0), 27.0 - 0.3 * torch.arange(1, 21), torch.full((150,), 21.0),
                      21.0 + 0.2 * torch.arange(1, 31), torch.full((150,), 27.0)]).double()
    kw = dict(v_start=27.0, gap_start=30.0, dt=DT, warmup=5.0, s_min=5.0, s_max=40.0)
    free = least_jerk(head, **kw)
    safe = least_jerk(head, stop_gap=5.0, leader_brake=3.0, **kw)
    v = torch.cat([torch.tensor([27.0]).double(), safe.speed])
    g = torch.cat([torch.tensor([30.0]).double(), safe.gap])
    vh = torch.cat([head[:1], head])
    upper = safe_accel_upper(g[1:-1], v[1:-1], vh[1:-1], s_min=5.0, dt=DT, brake=3.0, leader_brake=3.0)
    assert float((safe.accel[1:] - upper).max()) <= 1e-6  # the first step is left free
    free_v = torch.cat([torch.tensor([27.0]).double(), free.speed])
    free_g = torch.cat([torch.tensor([30.0]).double(), free.gap])
    free_upper = safe_accel_upper(free_g[1:-1], free_v[1:-1], vh[1:-1], s_min=5.0, dt=DT, brake=3.0, leader_brake=3.0)
    assert float((free.accel[1:] - free_upper).max()) > 0.1  # without it the optimum leaves the safe set
    assert safe.jerk > free.jerk
    with pytest.raises(ValueError, match="leader_brake"):
        least_jerk(head, stop_gap=5.0, **kw)


def test_window_options_end_speed_soft_band_and_the_previous_command():
    """What a plan over a window needs: the last speed fixed, a band made soft so that a start outside it still
    has a plan (which a hard band refuses), and the change from the command before the window priced."""
    head = _step_head(30.0, 30.0, 0, 600)
    kw = dict(v_start=10.0, gap_start=30.0, dt=DT, warmup=0.0, s_min=5.0, s_max=40.0)
    with pytest.raises(ValueError, match="no command sequence"):
        least_jerk(head, **kw)
    soft = least_jerk(head, band_weight=1.0, end_speed=30.0, **kw)
    assert float(soft.speed[-1]) == pytest.approx(30.0, abs=1e-6)
    assert float(soft.gap.max()) > 40.0 and float(soft.gap[-1]) <= 40.0 + 1e-6  # out of the band, and back in
    steady = _step_head(16.0, 16.0, 0, 300)
    free = least_jerk(steady, v_start=16.0, gap_start=20.0, dt=DT, warmup=0.0, s_min=5.0, s_max=40.0)
    assert free.jerk == pytest.approx(0.0, abs=1e-9)  # any constant command that keeps the band: no change
    # the command before the window is 0.02 m/s^2, which the band allows for the whole window (the gap falls by
    # 9 m): changing it would cost, so the plan holds it
    held = least_jerk(steady, v_start=16.0, gap_start=20.0, dt=DT, warmup=0.0, s_min=5.0, s_max=40.0, a_prev=0.02)
    assert torch.allclose(held.accel, torch.full_like(held.accel, 0.02), atol=1e-7)
    assert not torch.allclose(free.accel, held.accel, atol=1e-7)


def test_a_tracking_price_trades_jerk_for_a_smaller_speed_error():
    """With each m/s of speed error priced, the plan follows a head's step more closely (a smaller mean speed
    error) and pays for it in jerk; without the price, the same window's plan has the least jerk."""
    head = _ramp_head(10.0, n=400)
    kw = dict(v_start=20.0, gap_start=20.0, dt=DT, warmup=0.0, s_min=5.0, s_max=40.0)
    free = least_jerk(head, **kw)
    tracked = least_jerk(head, track_weight=0.5, **kw)
    error = lambda r: float((r.speed - head).abs().mean())  # noqa: E731
    assert error(tracked) < 0.5 * error(free)
    assert tracked.jerk > free.jerk


def _ramp_head(t_step: float, n: int = 900, v0: float = 20.0, v1: float = 26.0) -> torch.Tensor:
    t = (torch.arange(n) + 1) * DT
    return torch.clamp(v0 + 2.0 * (t - t_step), v0, v1).double()


def test_a_preview_of_the_head_buys_jerk_and_the_clairvoyant_sequence_stays_below():
    """A step of the head 6 m/s up at 30 s: the CAV that only measures the head answers it inside the band
    with the most jerk, 5 s of preview with less, and the clairvoyant sequence with the least; all keep the
    band, so all stay at or above the clairvoyant optimum."""
    head = _ramp_head(30.0, n=600)  # 60 s: the step and half a minute of steady driving after it
    kw = dict(v_start=20.0, gap_start=20.0, dt=DT, warmup=0.0, s_min=5.0, s_max=40.0)
    blind = preview_least_jerk(head, preview=0.0, horizon=15.0, **kw)
    seen = preview_least_jerk(head, preview=5.0, horizon=15.0, **kw)
    best = least_jerk(head, **kw)
    for r in (blind, seen):
        assert float(r.gap.min()) >= 5.0 - 1e-6 and float(r.gap.max()) <= 40.0 + 1e-6
    assert best.jerk < seen.jerk < blind.jerk
    # the driven sequence, replayed through the env's integrator, gives its gaps
    v, gap = torch.tensor(20.0, dtype=torch.float64), torch.tensor(20.0, dtype=torch.float64)
    for k in range(0, head.numel()):
        _, v, _ = integrate(torch.zeros(()), v, blind.accel[k], DT)
        gap = gap + (head[k] - v) * DT
        assert float(gap) == pytest.approx(float(blind.gap[k]), abs=1e-6)


def test_a_preview_controller_does_not_use_what_it_cannot_see():
    """Two heads equal up to 30 s and different after it: with no preview the commands up to 30 s are the same;
    with 5 s of preview they are the same up to 25 s and differ before 30 s (it saw the step coming)."""
    up, down = _ramp_head(30.0, n=400), _ramp_head(30.0, n=400, v1=20.0)  # 40 s: 10 s past where they part
    kw = dict(v_start=20.0, gap_start=20.0, dt=DT, warmup=0.0, s_min=5.0, s_max=40.0, horizon=15.0)
    k30, k25 = 299, 249  # the steps that end at 30 s and 25 s
    a, b = (preview_least_jerk(h, preview=0.0, **kw).accel for h in (up, down))
    assert torch.equal(a[:k30 + 1], b[:k30 + 1]) and not torch.allclose(a, b)
    a, b = (preview_least_jerk(h, preview=5.0, **kw).accel for h in (up, down))
    assert torch.equal(a[:k25 + 1], b[:k25 + 1]) and not torch.allclose(a[:k30], b[:k30])


def test_a_blind_preview_controller_inside_the_stopping_set_survives_a_head_that_stops():
    """The head brakes from 15 m/s to a standstill at 3 m/s^2 at 20 s. The controller that only measures it
    keeps every step in the stopping-safe set of a 5-m gap and a 3 m/s^2 head, so it stops with at least
    5 m to spare, and it needs no emergency step to do so."""
    t = (torch.arange(600) + 1) * DT
    head = torch.clamp(15.0 - 3.0 * (t - 20.0).clamp_min(0.0), min=0.0).double()
    r = preview_least_jerk(head, preview=0.0, horizon=10.0, v_start=15.0, gap_start=25.0, dt=DT, warmup=0.0,
                           s_min=5.0, s_max=40.0, accel_bounds=(-3.0, 2.0), stop_gap=5.0, leader_brake=3.0)
    assert float(r.gap.min()) >= 5.0 - 1e-4 and float(r.speed[-1]) == pytest.approx(0.0, abs=1e-6)
    assert r.status.endswith(", 0 steps braked without one")


@pytest.mark.parametrize("kwargs, field", [({"preview": -1.0}, "preview"), ({"preview": 20.0}, "horizon"),
                                           ({"replan": 30.0}, "replan")])
def test_bad_preview_input_names_the_argument(kwargs, field):
    base = dict(preview=2.0, horizon=15.0, v_start=20.0, gap_start=20.0, dt=DT, warmup=0.0, s_min=5.0, s_max=40.0)
    with pytest.raises(ValueError, match=field):
        preview_least_jerk(_ramp_head(30.0), **{**base, **kwargs})


# ----------------------------------------------------------------------------- the causal bound over head futures
def _futures(n_before=100, n_after=200, speeds=(10.0, 8.0, 13.0)):
    """Heads at 10 m/s that, after ``n_before`` steps, keep it or step to 8 or 13 m/s (a tree of one decision)."""
    return torch.stack([torch.cat([torch.full((n_before,), 10.0), torch.full((n_after,), v)]) for v in speeds]).double()


CAUSAL_KW = dict(v_start=10.0, gap_start=20.0, dt=DT, warmup=0.0, s_min=12.0, s_max=30.0)


def test_history_groups_split_heads_where_their_measured_speeds_first_differ():
    heads = _futures(3, 2)
    ids = history_groups(heads)
    assert ids[:, :4].eq(0).all()  # step 3's command is chosen before its speeds are measured
    assert len(set(ids[:, 4].tolist())) == 3


def test_the_causal_bound_of_one_head_is_the_clairvoyant_optimum():
    head = _futures()[2]
    one = causal_least_jerk(head[None], **CAUSAL_KW)
    twice = causal_least_jerk(torch.stack([head, head]), **CAUSAL_KW)
    alone = least_jerk(head, **CAUSAL_KW)
    assert one.jerk == pytest.approx(alone.jerk, abs=1e-7)
    assert twice.jerk == pytest.approx(alone.jerk, abs=1e-7)


def test_not_knowing_the_step_costs_jerk_and_commands_agree_until_the_heads_differ():
    heads = _futures()
    r = causal_least_jerk(heads, **CAUSAL_KW)
    clairvoyant = sum(least_jerk(h, **CAUSAL_KW).jerk for h in heads) / 3
    # knowing which step comes, the CAV eases into it before it starts (no command change at all here)
    assert clairvoyant < 1e-6 and r.jerk > 0.005
    for i in (1, 2):
        assert torch.allclose(r.accel[0, :101], r.accel[i, :101], atol=1e-7)
        assert not torch.allclose(r.accel[0, 101:], r.accel[i, 101:], atol=1e-3)
    assert float(r.gap.min()) >= 12.0 - 1e-6 and float(r.gap.max()) <= 30.0 + 1e-6
    # weights move the optimum toward the likely futures: a rare up-step buys a smaller answer to the others
    rare = causal_least_jerk(heads, weights=[0.45, 0.45, 0.1], **CAUSAL_KW)
    assert float(rare.per_head[2]) > float(r.per_head[2])


def test_no_causal_controller_that_keeps_the_band_on_every_head_has_less_jerk():
    # a proportional follower measures the head only (its command at step t uses the head's speed after t - 1),
    # so it is causal; it keeps the band on all three heads, so its mean jerk bounds the program's optimum
    heads = _futures()
    v = torch.full((3,), 10.0, dtype=torch.float64)
    gap, head_prev, a_prev = torch.full((3,), 20.0, dtype=torch.float64), heads[:, 0].clone(), torch.zeros(3)
    changes, gaps = [], []
    for t in range(heads.shape[1]):
        a = (0.6 * (head_prev - v) + 0.05 * (gap - 20.0)).clamp(-3.0, 3.0)
        v_next = (v + a * DT).clamp_min(0.0)
        gap = gap + (heads[:, t] - v_next) * DT
        changes.append((a - a_prev).abs()) if t else None
        v, a_prev, head_prev = v_next, a, heads[:, t]
        gaps.append(gap)
    gaps = torch.stack(gaps, 1)
    assert float(gaps.min()) >= 12.0 and float(gaps.max()) <= 30.0
    follower = float(torch.stack(changes, 1).sum(1).mean()) / ((heads.shape[1] - 1) * DT)
    assert causal_least_jerk(heads, **CAUSAL_KW).jerk <= follower


def test_counted_window_and_a_settled_end():
    heads = _futures()
    ends = heads[:, -1]
    settled = causal_least_jerk(heads, end_speeds=ends, a_prev=0.0, **CAUSAL_KW)
    assert torch.allclose(settled.speed[:, -1], ends, atol=1e-6)
    # the step 0 change from a_prev counts: per_head is the mean over every step, with the command before them
    change = torch.cat([torch.zeros(3, 1, dtype=torch.float64), settled.accel], 1).diff(dim=1).abs()
    assert torch.allclose(settled.per_head, change.sum(1) / (heads.shape[1] * DT), atol=1e-9)
    before = causal_least_jerk(heads, count_to=100, **CAUSAL_KW)  # only the steady start counts: nothing to do
    assert before.jerk == pytest.approx(0.0, abs=1e-7)


@pytest.mark.parametrize("kwargs, field", [
    (dict(head_speeds=torch.ones(5)), "head_speeds"),
    (dict(weights=[1.0, 1.0]), "weights"),
    (dict(weights=[1.0, -1.0, 1.0]), "weights"),
    (dict(count_from=299), "count_from"),
    (dict(count_to=400), "count_to"),
    (dict(end_speeds=[10.0]), "end_speeds"),
    (dict(s_min=-1.0), "s_min"),
])
def test_bad_causal_input_names_the_argument(kwargs, field):
    args = dict(head_speeds=_futures(), **CAUSAL_KW)
    args.update(kwargs)
    with pytest.raises(ValueError, match=field):
        causal_least_jerk(**args)


def test_the_speed_bar_on_steady_samples_is_kept_on_every_head():
    # the band-only optimum lets the speed drift off the head's to save jerk; the bar forbids it where it counts
    heads = _futures()
    steady = torch.zeros_like(heads, dtype=torch.bool)
    steady[:, 250:] = True  # the last 5 s of each future
    free = causal_least_jerk(heads, **CAUSAL_KW)
    err = lambda r: ((r.speed - heads).abs() * steady).sum(1) / steady.sum(1)  # noqa: E731
    assert float(err(free).max()) > 0.3
    l1 = causal_least_jerk(heads, steady=steady, rmse=0.1, **CAUSAL_KW)
    assert float(err(l1).max()) <= 0.1 + 1e-6 and l1.jerk >= free.jerk - 1e-9
    linf = causal_least_jerk(heads, steady=steady, rmse=0.1, norm="linf", **CAUSAL_KW)
    assert float(((linf.speed - heads).abs() * steady).max()) <= 0.1 + 1e-6 and linf.jerk >= l1.jerk - 1e-9
    # one head with the bar is least_jerk's program with the same bar
    alone = least_jerk(heads[2], steady=steady[2], rmse=0.1, **CAUSAL_KW)
    assert causal_least_jerk(heads[2:], steady=steady[2:], rmse=0.1, **CAUSAL_KW).jerk == pytest.approx(alone.jerk, abs=1e-7)
    with pytest.raises(ValueError, match="steady"):
        causal_least_jerk(heads, steady=steady[:2], rmse=0.1, **CAUSAL_KW)
    with pytest.raises(ValueError, match="steady"):
        causal_least_jerk(heads, rmse=0.1, **CAUSAL_KW)


def test_heads_no_causal_controller_can_follow_in_the_band_are_reported():
    # the head steps from 10 to 20 m/s with 2 m of room: only a CAV that knew could have closed in first
    heads = _futures(50, 100, speeds=(10.0, 20.0))
    with pytest.raises(ValueError, match="no causal command sequence"):
        causal_least_jerk(heads, v_start=10.0, gap_start=20.0, dt=DT, warmup=0.0, s_min=18.0, s_max=22.0,
                          accel_bounds=(-1.0, 1.0))


def _v_eq(head, window=200):
    """The env's v_eq after each step: the head's mean over the last ``window`` steps."""
    return torch.stack([head[max(0, t - window + 1):t + 1].mean() for t in range(len(head))])


def test_an_own_cost_cap_trades_jerk_for_the_return_and_holds_on_the_true_cost():
    head = _step_head(20.0, 24.0, 100, 400)
    kw = dict(v_start=20.0, gap_start=20.0, dt=DT, warmup=0.0, s_min=5.0, s_max=40.0, a_prev=0.0, end_speed=24.0)
    free = least_jerk(head, **kw)
    cost = OwnCost(v_eq=_v_eq(head), budget=1.0)
    spent = float(cost.of(free.speed, free.gap))
    jerks = []
    for share in (0.5, 0.3, 0.2):
        r = least_jerk(head, own_cost=OwnCost(v_eq=_v_eq(head), budget=share * spent), **kw)
        # the tangents under-estimate each square by at most w d^2 / 4 a step (d = 2 m and 1 m/s here)
        assert float(cost.of(r.speed, r.gap)) <= share * spent + len(head) * (0.5 + 0.25)
        assert float(cost.of(r.speed, r.gap)) > 0.9 * share * spent  # the cap binds: the free plan spends more
        jerks.append(r.jerk)
    assert free.jerk < jerks[0] < jerks[1] < jerks[2]  # each tighter cap costs jerk (the free plan spends more)
    with pytest.raises(ValueError, match="no command sequence"):
        least_jerk(head, own_cost=OwnCost(v_eq=_v_eq(head), budget=1.0), **kw)  # the speed step alone costs more
    with pytest.raises(ValueError, match="own_cost.budget"):
        least_jerk(head, own_cost=OwnCost(v_eq=_v_eq(head), budget=0.0), **kw)
    with pytest.raises(ValueError, match="own_cost.v_eq"):
        least_jerk(head, own_cost=OwnCost(v_eq=_v_eq(head)[:-1], budget=1.0), **kw)


def test_the_causal_bound_with_own_costs_counts_the_same_jerk_and_caps_each_head():
    heads = _futures()
    kw = {**CAUSAL_KW, "a_prev": 0.5}  # the change from a_prev counts: the own-cost columns that follow must not
    loose = [OwnCost(v_eq=_v_eq(h), budget=1e9, s_star=20.0) for h in heads]
    plain = causal_least_jerk(heads, **kw)
    assert causal_least_jerk(heads, own_costs=loose, **kw).jerk == pytest.approx(plain.jerk, abs=1e-7)
    spent = torch.stack([c.of(plain.speed[i], plain.gap[i]) for i, c in enumerate(loose)])
    tight = [OwnCost(v_eq=_v_eq(h), budget=0.5 * float(spent[i])) for i, h in enumerate(heads)]
    r = causal_least_jerk(heads, own_costs=tight, **kw)
    assert r.jerk > plain.jerk
    for i, c in enumerate(tight):
        assert float(c.of(r.speed[i], r.gap[i])) <= c.budget + heads.shape[1] * 0.75
    with pytest.raises(ValueError, match="own_costs"):
        causal_least_jerk(heads, own_costs=tight[:2], **kw)


def test_the_step_tree_drives_the_head_as_the_ring_does(benchmark_script):
    tree = benchmark_script("ring_causal_bound").step_tree
    heads, w, choices = tree(speeds=[20.0, 27.0], v0=24.0, epoch=5.0, depth=2, p_hold=0.5, tail=5.0, dt=DT,
                             head_bounds=(-3.0, 2.0))
    assert heads.shape == (9, 200) and float(w.sum()) == pytest.approx(1.0) and float(w[0]) == pytest.approx(0.25)
    up = choices.index([27.0, None])
    # the target of time 5 s drives step 49; the head ramps at its 2 m/s^2 bound to 27 m/s and holds it
    assert torch.all(heads[up, :49] == 24.0) and float(heads[up, 49]) == pytest.approx(24.2)
    assert torch.allclose(heads[up, 63:], torch.tensor(27.0, dtype=torch.float64)) and float(heads[up, 62]) < 26.9
    down = choices.index([20.0, None])
    assert float(heads[down, 49]) == pytest.approx(23.7)  # braking at its 3 m/s^2 bound
    rel, _, steps = tree(speeds=[-2.0, 2.0], v0=24.0, epoch=5.0, depth=2, p_hold=0.0, tail=5.0, dt=DT,
                         head_bounds=(-3.0, 2.0), relative=True)
    assert len(steps) == 4 and float(rel[steps.index([2.0, 2.0]), -1]) == pytest.approx(28.0)
    ramp, _, accels = tree(speeds=[-0.5, 0.5], v0=24.0, epoch=5.0, depth=2, p_hold=0.0, tail=5.0, dt=DT,
                           head_bounds=(-3.0, 2.0), ramps=True)
    up_down = ramp[accels.index([0.5, -0.5])]  # +0.5 m/s^2 from 5 s, -0.5 from 10 s, its speed held from 15 s
    assert float(up_down[98]) == pytest.approx(26.5) and float(up_down[148]) == pytest.approx(24.0)
    assert torch.allclose(up_down[148:], torch.tensor(24.0, dtype=torch.float64))


def test_the_stop_tree_stops_and_drives_off_as_stop_and_go_does(benchmark_script):
    tree = benchmark_script("ring_causal_bound").stop_tree
    heads, w, choices = tree(speeds=[10.0, 15.0], depth=2, rate=2.0, holds=[10.0, 15.0], stops=[6.0], tail=5.0, dt=DT)
    assert heads.shape[0] == len(choices) == 8 and float(w.sum()) == pytest.approx(1.0)  # 2 x 2 first, 2 last
    i = choices.index([(15.0, 10.0, 6.0), (10.0, 15.0)])  # the last hold: holds[0] + tail, whatever was drawn
    h = heads[i]
    # 7.5 s up at 2 m/s^2, 10 s at 15 m/s, 7.5 s down, 6 s stopped, 5 s up to 10 m/s, then held
    assert float(h[0]) == pytest.approx(0.2) and float(h[74]) == pytest.approx(15.0) and float(h[73]) < 15.0
    assert torch.all(h[74:175] == 15.0) and float(h[175]) == pytest.approx(14.8)
    assert torch.all(h[249:310] == 0.0) and float(h[310]) == pytest.approx(0.2) and torch.all(h[359:] == 10.0)
    longer = heads[choices.index([(15.0, 15.0, 6.0), (10.0, 15.0)])]
    assert torch.all(longer[74:225] == 15.0)  # held 5 s longer before it brakes
    stood, _, picks = tree(speeds=[15.0], depth=2, rate=2.0, holds=[10.0], stops=[6.0, 9.0], tail=5.0, dt=DT)
    long_stop = stood[picks.index([(15.0, 10.0, 9.0), (15.0, 15.0)])]
    assert torch.all(long_stop[249:340] == 0.0) and float(long_stop[340]) == pytest.approx(0.2)  # 3 s longer
    # the CAV tells the drive-off speeds apart when the slower head stops accelerating (history_groups)
    ids = history_groups(heads)
    slow, fast = choices.index([(10.0, 10.0, 6.0), (10.0, 15.0)]), choices.index([(15.0, 10.0, 6.0), (10.0, 15.0)])
    first = int((ids[slow] != ids[fast]).nonzero()[0])  # the first command chosen after a speed that differs
    assert float(heads[slow, first - 2]) == float(heads[fast, first - 2]) == 10.0  # both reach 10 m/s, then
    assert float(heads[slow, first - 1]) == 10.0 and float(heads[fast, first - 1]) > 10.0  # only one goes on


def test_the_causal_bound_benchmark_as_a_user_runs_it(benchmark_script, tmp_path):
    mod = benchmark_script("ring_causal_bound")
    res = mod.main(["--depth", "1", "--epoch", "5", "--tail", "10", "--speeds", "22", "26", "--out", str(tmp_path)])
    rows = res["rows"]
    assert rows["clairvoyant"]["jerk"] <= rows["causal bound"]["jerk"]
    lo, hi = rows["causal bound"]["gaps"]
    assert 5.0 - 1e-6 <= lo and hi <= 40.0 + 1e-6
    assert all(rows[k]["collisions"] == 0 for k in mod.CLASSICAL)
    text = (tmp_path / "causal_bound.md").read_text()
    assert text.startswith("3 futures of 20 s") and "solved in" in text.splitlines()[0] and text.count("|") > 20
    capped = mod.main(["--depth", "1", "--epoch", "5", "--tail", "10", "--speeds", "22", "26", "--own-cost", "0.9",
                       "--out", str(tmp_path)])["rows"]
    assert rows["IDM-as-CAV"]["own_cost"] == pytest.approx(1.0) == capped["IDM-as-CAV"]["own_cost"]
    # the return with the humans replayed: a reward in [0, 1] a step over the 20 s, against IDM-as-CAV's
    assert rows["IDM-as-CAV"]["return"] == 0.0
    assert all(0 < x <= 200 for x in rows["IDM-as-CAV"]["return_per_future"])
    assert all(abs(r["return"]) < 200 for r in rows.values())
    assert capped["causal bound"]["own_cost"] <= 0.9 + 0.05 and capped["causal bound"]["jerk"] > rows["causal bound"]["jerk"]
    assert "own cost <= 0.9 x IDM-as-CAV's" in (tmp_path / "causal_bound.md").read_text()
    with pytest.raises(SystemExit, match="--own-cost"):
        mod.main(["--own-cost", "0", "--out", str(tmp_path)])
    with pytest.raises(SystemExit, match="--gap"):
        mod.main(["--gap", "50", "--out", str(tmp_path)])
    with pytest.raises(SystemExit, match="--stop-gap"):
        mod.main(["--stop-gap", "-1", "--out", str(tmp_path)])
    with pytest.raises(SystemExit, match="--speeds"):
        mod.main(["--stops", "--speeds", "0", "10", "--out", str(tmp_path)])
    with pytest.raises(SystemExit, match="--stops"):
        mod.main(["--stops", "--ramps", "--out", str(tmp_path)])


def test_the_whole_return_with_the_humans_replayed_is_the_envs_own(benchmark_script):
    # IDM-as-CAV in the ring env behind a head that steps down and back, every car starting steady at IDM's
    # equilibrium gap: the benchmark's replay of the humans behind the CAV's recorded speeds gives the env's return
    from mixed_traffic import make_env
    from mixed_traffic.controllers.classic import make_classic_policy

    mod = benchmark_script("ring_causal_bound")
    profile = {"times": (0.0, 25.0, 27.0, 45.0, 47.0), "speeds": (24.0, 24.0, 20.0, 20.0, 24.0)}
    env = make_env("ring", batch_size=1, seed=0, profile="piecewise", profile_kwargs=profile, v_init=24.0,
                   init_spacing_rows=(34.48,), episode_seconds=60.0, reset_accel="model")
    nx = env.rollout(600, make_classic_policy("idm", env), break_when_any_done=False)["next"]
    sc = env.scenario
    j_env = nx["traffic", "J"][0, :, 0].double()
    env_return = float(((sc.J_max - j_env).clamp_min(0.0) / sc.J_max).sum())
    row = lambda key: nx[key][0, :, 0][None].double()  # noqa: E731
    replayed = mod.return_with_humans(sc, row(("cav", "head_speed")), nx["traffic", "v_eq"][0, :, 0][None],
                                      row(("cav", "speed")), row(("cav", "accel")), row(("cav", "gap")), v0=24.0)
    assert float(j_env.max()) > 50.0  # the step moves every car: the humans' terms are in the return
    assert float(replayed[0]) == pytest.approx(env_return, abs=0.01)


def test_the_stop_and_go_bound_with_the_speed_bar_as_a_user_runs_it(benchmark_script, tmp_path):
    mod = benchmark_script("ring_causal_bound")
    args = ["--stops", "--speeds", "6", "10", "--depth", "1", "--tail", "5", "--gap", "8", "--out", str(tmp_path)]
    free = mod.main(args)["rows"]
    res = mod.main([*args, "--rmse", "0.05", "--rmse-norm", "linf", "--stop-gap", "5"])
    bar = res["rows"]
    assert free["causal bound"]["rmse"] > 0.05 and res["stop_rule_excess"] <= 1e-9  # stopping-safe by the rule itself
    # every steady sample within 0.05 m/s of the head's speed, at a price in jerk the band alone does not pay
    assert free["causal bound"]["rmse"] > 0.05 >= bar["causal bound"]["rmse"]
    assert max(bar["causal bound"]["rmse_per_future"]) <= 0.05 + 1e-6
    assert bar["causal bound"]["jerk"] > free["causal bound"]["jerk"]
    assert bar["clairvoyant"]["jerk"] <= bar["causal bound"]["jerk"] + 1e-9
    assert bar["IDM-as-CAV"] == free["IDM-as-CAV"]  # the replays do not depend on the bar or the stopping rule
    assert "speed error on steady samples (linf) <= 0.05 m/s" in (tmp_path / "causal_bound.md").read_text()
    # one future beside IDM-as-CAV and the base, as a picture
    mod.main([*args, "--plot", str(tmp_path / "tree.png"), "--plot-future", "1"])
    assert (tmp_path / "tree.png").stat().st_size > 0 and (tmp_path / "tree_future1.png").stat().st_size > 0
    with pytest.raises(SystemExit, match="--plot-future"):
        mod.main([*args, "--plot", str(tmp_path / "tree.png"), "--plot-future", "2"])  # two futures: 0 and 1


def test_the_jerk_oracle_benchmark_as_a_user_runs_it(benchmark_script, tmp_path):
    # a tiny trained ring policy; the script's columns on one 60-s held-out episode
    from mixed_traffic.config import compose
    from mixed_traffic.training import train

    run = tmp_path / "run"
    train(compose(["experiment=ring_ppo", "trainer.total_frames=32", "trainer.num_envs=8", "trainer.rollout_len=4",
                   "trainer.epochs=1", "trainer.minibatch_size=16", "trainer.progress=false",
                   "env.episode_seconds=1.0"]), out_dir=run)
    mod = benchmark_script("ring_jerk_oracle")
    res = mod.main(["--checkpoint", str(run), "--episodes", "1", "--seconds", "60", "--cases", "fast_steps",
                    "--preview", "0", "5", "--out", str(tmp_path / "out")])
    row = {k: v[0] for k, v in res["fast_steps"].items()}
    band, l1, linf = (row[f"clairvoyant: band{x}"] for x in ("", " + rmse (l1)", " + rmse (linf)"))
    assert 0.0 <= band <= l1 + 1e-9 <= linf + 2e-9  # each adds to the bars of the one before
    assert band < row["IDM-as-CAV"]  # IDM-as-CAV keeps its own gaps, the band's floor is far below its jerk
    assert {mod.preview_label(0), mod.preview_label(5)} <= set(row)
    table = (tmp_path / "out" / "jerk_oracle.md").read_text()
    assert table.count("\n") == 3 and "fast_steps" in table
