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
