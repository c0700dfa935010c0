import os

import pytest
import torch

os.environ.setdefault("WANDB_MODE", "offline")
os.environ.setdefault("MT_SMALL_BUDGET", "1")


@pytest.fixture(autouse=True)
def _single_thread():
    # Two cores, two xdist workers: keep each test on one intra-op thread.
    torch.set_num_threads(1)
    yield
