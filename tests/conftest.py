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
