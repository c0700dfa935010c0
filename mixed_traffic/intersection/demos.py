"""Demonstrations for behaviour cloning: the NMPC driving training episodes of the intersection.

A cached artefact with its own command (the training loop makes it when missing, before its
clock starts)::

    python -m mixed_traffic.intersection.demos --episodes 384 --seed 0      # -> outputs/demos/nmpc_seed0_n384.pt
    # the agents of a training bank (close starts, reactive and pausing agents, as `loss.bc.agents: training`)
    python -m mixed_traffic.intersection.demos --episodes 384 --seed 0 --hard-start-fraction 0.3 \
        --reactive-fraction 0.25 --pause-fraction 0.25  # -> outputs/demos/nmpc_seed0_n384_h0.3-r0.25-p0.25.pt

>>> demo = nmpc_demonstrations(2, seed=0, batch=2, progress=False)
>>> demo["expert_action"].shape[-1]
1
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch
from tensordict import TensorDict
from tqdm.auto import tqdm

from mixed_traffic.envs.intersection import HARD_START_X, IntersectionEnv, agent_bank
from mixed_traffic.intersection.nmpc import make_nmpc_policy

MIX_FIELDS = ("hard_start_fraction", "reactive_fraction", "pause_fraction")


def default_path(expert: str, seed: int, episodes: int, mix: dict | None = None) -> Path:
    """The cache file of a set of demonstrations; the name carries the bank's shares (and close-start
    range when it is not the default), so demonstrations of another bank are never loaded instead."""
    tag = ""
    if mix and any(mix.get(k, 0.0) for k in MIX_FIELDS):
        tag = "_" + "-".join(f"{k[0]}{float(mix.get(k, 0.0)):g}" for k in MIX_FIELDS)
        x = tuple(float(v) for v in mix.get("hard_start_x", HARD_START_X))
        if x != HARD_START_X:
            tag += f"-x{x[0]:g}-{x[1]:g}"
    return Path("outputs/demos") / f"{expert}_seed{seed}_n{episodes}{tag}.pt"


@torch.no_grad()
def nmpc_demonstrations(n_episodes: int, *, seed: int, batch: int = 32, start_noise: float = 0.15,
                        progress: bool = True, mix: dict | None = None) -> TensorDict:
    """``(observation, expert_action)`` pairs of the NMPC on ``n_episodes`` training-split episodes.

    ``mix``: shares of the bank (``hard_start_fraction``, ``hard_start_x``, ``reactive_fraction``,
    ``pause_fraction``, as the env's fields); None: mixed-style agents only.
    """
    obs_all, act_all = [], []
    ctrl = make_nmpc_policy().module
    bank = agent_bank(n_episodes, seed=seed + 10_000, split="train", **(mix or {}))
    bar = tqdm(total=n_episodes, unit="episode", desc="NMPC demonstrations", disable=not progress)
    for start in range(0, n_episodes, batch):
        sub = bank.subset(torch.arange(start, min(n_episodes, start + batch)))
        env = IntersectionEnv(batch_size=len(sub), agent_trajectories=sub, agent_sampling="sequential",
                              start_noise=start_noise, seed=seed + start)
        ctrl.reset()
        td = env.reset()
        done = torch.zeros(len(sub), dtype=torch.bool)
        for _ in range(env.max_steps):
            alive = torch.nonzero(~done).squeeze(-1)
            ctrl.set_rows(alive.tolist())
            a = ctrl(td["observation"][alive])
            obs_all.append(td["observation"][alive].clone())
            act_all.append(a.clone())
            action = torch.zeros(len(sub), 1)
            action[alive] = a
            td["action"] = action
            td = env.step(td)
            new = td["next", "done"].squeeze(-1) & ~done
            bar.update(int(new.sum()))
            done = done | new
            if done.all():
                break
            td = td["next"]
        ctrl.set_rows(None)
    bar.close()
    obs, act = torch.cat(obs_all), torch.cat(act_all)
    return TensorDict({"observation": obs, "expert_action": act}, batch_size=[obs.shape[0]])


def load_or_make(path: str | Path | None, *, expert: str, episodes: int, seed: int,
                 mix: dict | None = None) -> TensorDict:
    """The cached demonstrations at ``path`` (default :func:`default_path`), made and saved when missing."""
    if expert != "nmpc":
        raise ValueError(f"loss.bc.expert={expert!r} is invalid; allowed: 'nmpc'")
    path = Path(path) if path else default_path(expert, seed, episodes, mix)
    if path.exists():
        return torch.load(path, weights_only=False)
    print(f"BC demonstrations: {path} is missing; making them now ({episodes} NMPC episodes, not counted in the "
          f"training time; `python -m mixed_traffic.intersection.demos` makes them ahead)", flush=True)
    demo = nmpc_demonstrations(episodes, seed=seed, mix=mix)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(demo, path)
    return demo


def main(argv: list[str] | None = None) -> Path:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--episodes", type=int, default=384)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None, help="default: outputs/demos/nmpc_seed<seed>_n<episodes>[_<mix>].pt")
    for k in MIX_FIELDS:
        ap.add_argument("--" + k.replace("_", "-"), type=float, default=0.0, help="share of the bank (env field)")
    a = ap.parse_args(argv)
    if a.episodes < 1:
        ap.error(f"--episodes {a.episodes} is invalid; allowed: an integer >= 1")
    mix = {k: getattr(a, k) for k in MIX_FIELDS}
    bad = {k: v for k, v in mix.items() if not 0.0 <= v <= 1.0}
    if bad or sum(mix.values()) > 1.0:
        ap.error(f"--hard-start-fraction/--reactive-fraction/--pause-fraction {mix} are invalid; allowed: each in "
                 "[0, 1], sum <= 1")
    path = Path(a.out) if a.out else default_path("nmpc", a.seed, a.episodes, mix)
    demo = load_or_make(path, expert="nmpc", episodes=a.episodes, seed=a.seed, mix=mix)
    print(f"{demo.shape[0]} samples in {path}")
    return path


if __name__ == "__main__":
    main()
