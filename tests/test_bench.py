import json

import pytest

from mixed_traffic.apps.bench import main, main_env


def test_bench_env_small_run_writes_json(tmp_path):
    out = tmp_path / "bench.json"
    res = main_env(["--batch-sizes", "2", "8", "--steps", "10", "--collector-steps", "4", "--repeats", "1",
                    "--out", str(out)])
    rows = json.loads(out.read_text())["rows"]
    assert [r["batch"] for r in rows] == [2, 8]
    assert all(r["rollout_fps"] > 0 and r["collector_fps"] > 0 for r in rows)
    assert res["rows"] == rows


def test_bench_bad_input_is_a_clear_error(capsys):
    with pytest.raises(SystemExit):
        main_env(["--repeats", "0"])
    assert "--repeats must be >= 1" in capsys.readouterr().err
    with pytest.raises(SystemExit, match="choose a subcommand"):
        main(["envs"])


def test_bench_apg_times_a_window_and_counts_its_graph(tmp_path):
    """``mt-bench apg``: the seconds of an analytic-gradient window of the experiment's own env, forward and backward,
    and the backward graph's nodes per step (what make run's first phase is made of)."""
    from mixed_traffic.apps.bench import main_apg

    out = tmp_path / "apg.json"
    res = main_apg(["experiment=ring_lagrangian_ppo_gentle_join", "policy.apg.horizon=5", "policy.apg.num_envs=4",
                    "--windows", "1", "--repeats", "1", "--out", str(out)])
    assert json.loads(out.read_text()) == res
    assert (res["rows"], res["horizon"], res["windows"]) == (4, 5, 1)
    assert res["forward_s"] > 0 and res["backward_s"] > 0
    assert 100 < res["nodes_per_step"] < 2000  # a step of the ring's chain: a few hundred differentiable operations


def test_bench_gauge_and_bad_input(tmp_path, capsys):
    from mixed_traffic.apps.bench import main_apg, main_gauge

    res = main_gauge(["--batch-sizes", "1", "4", "--steps", "20", "--repeats", "1", "--out", str(tmp_path / "g.json")])
    assert [r["batch"] for r in res["rows"]] == [1, 4] and all(r["steps_per_s"] > 0 for r in res["rows"])
    for bad, cmd in ((["--windows", "0"], main_apg), (["--steps", "0"], main_gauge), (["--batch-sizes", "0"], main_gauge)):
        with pytest.raises(SystemExit):
            cmd(bad)
        assert bad[0] in capsys.readouterr().err
