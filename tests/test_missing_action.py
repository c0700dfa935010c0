"""An action transform's inverse step without its inputs: a clear KeyError, or the tensordict untouched where
TorchRL asks for tolerance (transforms.specs.entries_or_none)."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from mixed_traffic import make_env
from mixed_traffic.controllers.classic import make_classic_policy
from transforms import DriveOffCap, JerkLimit, ResidualAction, SafetyLayer


def _transforms():
    env = make_env("ring", batch_size=1, seed=0)
    return [DriveOffCap(), JerkLimit(1.0, dt=0.1), ResidualAction(make_classic_policy("idm", env)), SafetyLayer(dt=0.1)]


@pytest.mark.parametrize("i", range(4))
def test_a_missing_action_names_the_transform_and_the_key(i):
    t = _transforms()[i]
    with pytest.raises(KeyError, match=rf"{type(t).__name__}: 'action'.* not found in the input tensordict"):
        t.inv(TensorDict({"other": torch.zeros(1, 1)}, batch_size=[1]))


@pytest.mark.parametrize("i", range(4))
def test_a_tolerated_missing_action_leaves_the_tensordict_as_it_is(i):
    t = _transforms()[i]
    t.set_missing_tolerance(True)
    td = TensorDict({"other": torch.ones(1, 1)}, batch_size=[1])
    out = t.inv(td)
    assert set(out.keys()) == {"other"} and bool((out["other"] == 1).all())
