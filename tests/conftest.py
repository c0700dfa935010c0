import importlib.util
import os
from pathlib import Path

import pytest
import torch

os.environ.setdefault("WANDB_MODE", "offline")
os.environ.setdefault("MT_SMALL_BUDGET", "1")


@pytest.fixture(autouse=True)
def _single_thread():
    # Two cores, two xdist workers: keep each test on one intra-op thread.
    torch.set_num_threads(1)
    yield


# `make test` hands whole files to its two workers (--dist loadfile --no-loadscope-reorder) in collection order; a
# long file handed out last leaves the other core idle at the end. The longest files go first, longest first
# (their times: docs/benchmarks.md, "Test suite"); the others keep pytest's order after them.
LONGEST_FIRST = ("test_policy_itself.py", "test_notebooks.py", "test_oracle.py", "test_intersection_experiments.py",
                 "test_bad_input.py", "test_measurement_filter.py", "test_drive_off.py", "test_config.py",
                 "test_eval_sumo.py", "test_replay.py", "test_safety_layer.py", "test_stop_margin.py", "test_physics.py",
                 "test_eval.py", "test_train.py")


def pytest_collection_modifyitems(session, config, items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: each file's tests keep their order


BENCHMARKS = Path(__file__).resolve().parent.parent / "benchmarks"


@pytest.fixture(scope="session")
def benchmark_script():
    """``benchmark_script("NAME")``: the script ``benchmarks/NAME.py`` loaded as a module (the benchmarks are
    scripts run by path, not a package), so a test calls the functions the script's command line runs."""

    def load(name: str):
        spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f"{name}.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        return mod

    return load
