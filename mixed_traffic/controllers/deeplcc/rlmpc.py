"""RL over the NNMPC: the cached NNMPC, its residual transform (RLMPC) and the warm start.

- **RLMPC** (``transforms.chain`` entry ``residual_nnmpc``): the executed command is
  ``clip(u_nn + weight * a)`` with ``u_nn`` the frozen NNMPC's action on the DeeP-LCC window
  and ``a`` in [-1, 1] the policy's output (:class:`transforms.ResidualAction` with
  ``policy_bounds=(-1, 1)``): a fresh policy (mean ~0) is the NNMPC, and ``weight`` bounds
  the correction in m/s^2.
- **Warm Start RL** (``policy.warm_start.nnmpc``): before Lagrangian PPO the actor's
  deterministic action is fitted to the NNMPC's (:class:`losses.BCLoss`, MSE) on the states
  the NNMPC visits in the training env; PPO then starts from a copy of the NNMPC that reads
  the policy's own observation.

The NNMPC is a cached artefact (``DEFAULT_NNMPC``), produced once by::

    mt-dataset episodes=24 workers=1 output=outputs/deeplcc/dataset_small.npz
    python -m mixed_traffic.controllers.deeplcc.train --dataset outputs/deeplcc/dataset_small.npz \\
        --out outputs/deeplcc/nnmpc --relabel --skip-stored --max-seconds 240
"""

from __future__ import annotations

import time
from pathlib import Path

import torch
from tensordict.nn import TensorDictModule

from mixed_traffic.controllers.deeplcc.nnmpc import NNMPC, nnmpc_policy

DEFAULT_NNMPC = "outputs/deeplcc/nnmpc/nnmpc_bc_relabelled.pt"
MAKE_NNMPC = ("mt-dataset episodes=24 workers=1 output=outputs/deeplcc/dataset_small.npz && "
              "python -m mixed_traffic.controllers.deeplcc.train --dataset outputs/deeplcc/dataset_small.npz "
              "--out outputs/deeplcc/nnmpc --relabel --skip-stored --max-seconds 240")


def load_nnmpc(path: str | Path = DEFAULT_NNMPC, field: str = "checkpoint") -> NNMPC:
    """The frozen NNMPC of ``path``; a missing file raises naming ``field`` and the command that makes it."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{field}: NNMPC checkpoint {str(p)!r} not found; allowed: an NNMPC .pt file "
                                f"(make the default one with: {MAKE_NNMPC})")
    net = NNMPC.load(p)
    for q in net.parameters():
        q.requires_grad_(False)
    return net


def nnmpc_base(path: str | Path = DEFAULT_NNMPC, field: str = "checkpoint") -> TensorDictModule:
    """The NNMPC as a policy module ``(uini, yini, eini) -> action`` (frozen)."""
    return nnmpc_policy(load_nnmpc(path, field))


def residual_nnmpc(path: str | Path = DEFAULT_NNMPC, weight: float = 1.0):
    """``ResidualAction`` over the frozen NNMPC with a policy residual in [-1, 1] (RLMPC)."""
    from transforms import ResidualAction

    return ResidualAction(nnmpc_base(path, "transforms.residual_nnmpc.checkpoint"), weight=weight,
                          policy_bounds=(-1.0, 1.0), base_action_key=("residual", "base_action"))


def warm_start_actor(actor, env, nnmpc_path: str | Path, *, frames: int = 20_000, epochs: int = 30,
                     lr: float = 1e-3, minibatch: int = 1024, seed: int = 0, log=print) -> dict:
    """Fit the actor's deterministic action to the NNMPC's on the NNMPC's own closed-loop states.

    The NNMPC drives ``env`` (the training env with its transforms) for ``frames``
    transitions; every visited state is labelled with the NNMPC's action and the actor is
    trained by :class:`losses.BCLoss` (MSE of its deterministic action) for ``epochs``
    passes. Returns ``{"frames", "bc_mse", "seconds"}``.
    """
    from losses import BCLoss

    t0 = time.perf_counter()
    base = nnmpc_base(nnmpc_path, "policy.warm_start.nnmpc")
    n_env = env.batch_size[0] if env.batch_size else 1
    steps = max(1, frames // n_env)
    with torch.no_grad():
        td = env.rollout(steps, base, break_when_any_done=False)
    data = td.reshape(-1).select("observation", "action")
    data.rename_key_("action", "expert_action")
    env.reset()
    loss_fn = BCLoss(actor, expert_action_key="expert_action")
    params = [p for p in actor.parameters() if p.requires_grad]
    opt = torch.optim.Adam(params, lr=lr)
    g = torch.Generator().manual_seed(seed)
    n = data.numel()
    mse = float("nan")
    for ep in range(epochs):
        perm = torch.randperm(n, generator=g)
        tot = 0.0
        for s in range(0, n, minibatch):
            batch = data[perm[s:s + minibatch]]
            loss = loss_fn(batch)["loss_bc"]
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            tot += float(loss.detach()) * batch.numel()
        mse = tot / n
        if log and (ep + 1) % 10 == 0:
            log(f"warm start: epoch {ep + 1}/{epochs}, BC MSE to the NNMPC {mse:.4f}")
    return {"frames": n, "bc_mse": mse, "seconds": time.perf_counter() - t0}
