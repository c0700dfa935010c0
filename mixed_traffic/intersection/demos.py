"""Demonstrations for behaviour cloning: the NMPC driving training episodes of the intersection.

A cached artefact with its own command (the training loop makes it when missing, before its
clock starts)::

    python -m mixed_traffic.intersection.demos --episodes 384 --seed 0      # -> outputs/demos/nmpc_seed0_n384.pt
    # the agents of a training bank (close starts, reactive and pausing agents, as `loss.bc.agents: training`)
    python -m mixed_traffic.intersection.demos --episodes 384 --seed 0 --hard-start-fraction 0.3 \
        --reactive-fraction 0.25 --pause-fraction 0.25  # -> outputs/demos/nmpc_seed0_n384_h0.3-r0.25-p0.25.pt
    # a more cautious expert: NMPCConfig fields overridden (as `loss.bc.expert_overrides`)
    python -m mixed_traffic.intersection.demos --episodes 384 --seed 0 --nmpc margin=0.25  # -> ..._margin0.25.pt
    # DAgger: a trained policy drives, the NMPC labels the states it visits (added to the expert's own)
    python -m mixed_traffic.intersection.demos --episodes 384 --seed 0 --driver <run>/final.pt --out dagger.pt

>>> demo = nmpc_demonstrations(2, seed=0, batch=2, progress=False)
>>> demo["expert_action"].shape[-1]
1
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch
from tensordict import TensorDict
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type
from tqdm.auto import tqdm

from mixed_traffic.envs.intersection import HARD_START_X, IntersectionEnv, agent_bank
from mixed_traffic.intersection.nmpc import NMPCConfig, make_nmpc_policy, nmpc_config

MIX_FIELDS = ("hard_start_fraction", "reactive_fraction", "pause_fraction")


def default_path(expert: str, seed: int, episodes: int, mix: dict | None = None,
                 expert_overrides: dict | None = None) -> Path:
    """The cache file of a set of demonstrations; the name carries the bank's shares (and close-start
    range when it is not the default) and the expert's overridden fields, so demonstrations of another
    bank or another expert are never loaded instead."""
    tag = ""
    if mix and any(mix.get(k, 0.0) for k in MIX_FIELDS):
        tag = "_" + "-".join(f"{k[0]}{float(mix.get(k, 0.0)):g}" for k in MIX_FIELDS)
        x = tuple(float(v) for v in mix.get("hard_start_x", HARD_START_X))
        if x != HARD_START_X:
            tag += f"-x{x[0]:g}-{x[1]:g}"
    for k, v in sorted((expert_overrides or {}).items()):
        tag += f"_{k}{v:g}" if isinstance(v, (int, float)) else f"_{k}{v}"
    return Path("outputs/demos") / f"{expert}_seed{seed}_n{episodes}{tag}.pt"


@torch.no_grad()
def nmpc_demonstrations(n_episodes: int, *, seed: int, batch: int = 32, start_noise: float = 0.15,
                        progress: bool = True, mix: dict | None = None,
                        expert_overrides: dict | None = None, driver=None, transform=None) -> TensorDict:
    """``(observation, expert_action)`` pairs of the NMPC on ``n_episodes`` training-split episodes.

    ``mix``: shares of the bank (``hard_start_fraction``, ``hard_start_x``, ``reactive_fraction``,
    ``pause_fraction``, as the env's fields); None: mixed-style agents only.
    ``expert_overrides``: :class:`NMPCConfig` fields of the expert (e.g. ``{"margin": 0.25}``).
    ``driver``: a policy (TensorDict module writing ``action``, run deterministically, behind
    ``transform`` when given) whose actions are executed while the NMPC only labels the states it
    visits: the data aggregation step of DAgger (Ross, Gordon & Bagnell 2011), which puts expert
    labels on the states where the learner's own mistakes take it; None: the NMPC drives.
    """
    obs_all, act_all = [], []
    ctrl = make_nmpc_policy(**(expert_overrides or {})).module
    bank = agent_bank(n_episodes, seed=seed + 10_000, split="train", **(mix or {}))
    bar = tqdm(total=n_episodes, unit="episode", disable=not progress,
               desc="NMPC demonstrations" if driver is None else "NMPC labels on the driver's states")
    for start in range(0, n_episodes, batch):
        sub = bank.subset(torch.arange(start, min(n_episodes, start + batch)))
        env = IntersectionEnv(batch_size=len(sub), agent_trajectories=sub, agent_sampling="sequential",
                              start_noise=start_noise, seed=seed + start)
        if transform is not None:
            env = TransformedEnv(env, transform.clone())
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
            if driver is None:
                action[alive] = a
            else:
                with set_exploration_type(ExplorationType.DETERMINISTIC):
                    action[alive] = driver(td[alive].clone())["action"]
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
                 mix: dict | None = None, expert_overrides: dict | None = None) -> TensorDict:
    """The cached demonstrations at ``path`` (default :func:`default_path`), made and saved when missing."""
    if expert != "nmpc":
        raise ValueError(f"loss.bc.expert={expert!r} is invalid; allowed: 'nmpc'")
    expert_overrides = dict(expert_overrides or {})
    try:  # a bad field fails here, before any episode runs
        nmpc_config(**expert_overrides)
    except ValueError as e:
        raise ValueError(f"loss.bc.expert_overrides: {e}") from None
    path = Path(path) if path else default_path(expert, seed, episodes, mix, expert_overrides)
    if path.exists():
        return torch.load(path, weights_only=False)
    print(f"BC demonstrations: {path} is missing; making them now ({episodes} NMPC episodes, not counted in the "
          f"training time; `python -m mixed_traffic.intersection.demos` makes them ahead)", flush=True)
    demo = nmpc_demonstrations(episodes, seed=seed, mix=mix, expert_overrides=expert_overrides)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(demo, path)
    return demo


def dagger(checkpoint: str | Path, *, episodes: int = 384, out: str | Path | None = None,
           progress: bool = True) -> Path:
    """One DAgger aggregation: the run's demonstrations plus NMPC labels on the states its policy visits.

    The run at ``checkpoint`` drives ``episodes`` episodes of its own training bank (its
    ``env.overrides`` shares, its ``seed``); the NMPC (with the run's ``loss.bc.expert_overrides``)
    labels every state. The output (default ``outputs/demos/dagger_<run dir>_n<episodes>.pt``) is
    the run's demonstrations followed by these labels; train on it with ``loss.bc.demos=<output>``.
    """
    from mixed_traffic.intersection.evaluate import load_policy
    from mixed_traffic.training.on_policy import demo_agent_mix

    policy, make_transform, run_cfg = load_policy(checkpoint)
    bc = run_cfg.loss.get("bc")
    if bc is None or not bc.coeff > 0:
        raise ValueError(f"--driver {str(checkpoint)!r}: the run has no BC term (loss.bc.coeff > 0); allowed: "
                         "a run trained with demonstrations, e.g. experiment=intersection_lppo_bc")
    mix, overrides = demo_agent_mix(run_cfg), dict(bc.get("expert_overrides") or {})
    seed = int(run_cfg.seed)
    ckpt = Path(checkpoint)
    run_dir = ckpt if ckpt.is_dir() else ckpt.parent
    out = Path(out) if out else Path("outputs/demos") / f"dagger_{run_dir.name}_n{episodes}.pt"
    base = load_or_make(bc.demos, expert=bc.expert, episodes=int(bc.episodes), seed=seed, mix=mix,
                        expert_overrides=overrides)
    new = nmpc_demonstrations(episodes, seed=seed, mix=mix, expert_overrides=overrides, driver=policy,
                              transform=make_transform(), progress=progress)
    out.parent.mkdir(parents=True, exist_ok=True)
    torch.save(torch.cat([base, new]), out)
    print(f"{base.shape[0]} expert + {new.shape[0]} DAgger samples in {out}; train on them with loss.bc.demos={out}")
    return out


def _parse_field(item: str) -> tuple[str, object]:
    """``"margin=0.25"`` -> ``("margin", 0.25)``, typed as the :class:`NMPCConfig` field's default."""
    k, sep, v = item.partition("=")
    default = getattr(NMPCConfig, k, None)
    if not sep or default is None:
        raise ValueError(f"--nmpc {item!r} is invalid; allowed: FIELD=VALUE with FIELD one of "
                         f"{sorted(NMPCConfig.__dataclass_fields__)}")
    if isinstance(default, bool):
        return k, v.lower() in ("1", "true", "yes")
    try:
        return k, type(default)(v)
    except ValueError:
        raise ValueError(f"--nmpc {item!r} is invalid; {k} takes a {type(default).__name__}") from None


def main(argv: list[str] | None = None) -> Path:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--episodes", type=int, default=384)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None, help="default: outputs/demos/nmpc_seed<seed>_n<episodes>[_<mix>].pt")
    for k in MIX_FIELDS:
        ap.add_argument("--" + k.replace("_", "-"), type=float, default=0.0, help="share of the bank (env field)")
    ap.add_argument("--nmpc", nargs="*", default=[], metavar="FIELD=VALUE",
                    help="NMPCConfig fields of the expert, e.g. margin=0.25 (as loss.bc.expert_overrides)")
    ap.add_argument("--driver", default=None, metavar="CHECKPOINT",
                    help="DAgger: this trained run drives, the NMPC labels; the bank's shares, the expert's fields "
                         "and the seed are the run's; the output holds the expert's own demonstrations too")
    a = ap.parse_args(argv)
    if a.episodes < 1:
        ap.error(f"--episodes {a.episodes} is invalid; allowed: an integer >= 1")
    if a.driver:
        return dagger(a.driver, episodes=a.episodes, out=a.out)
    mix = {k: getattr(a, k) for k in MIX_FIELDS}
    bad = {k: v for k, v in mix.items() if not 0.0 <= v <= 1.0}
    if bad or sum(mix.values()) > 1.0:
        ap.error(f"--hard-start-fraction/--reactive-fraction/--pause-fraction {mix} are invalid; allowed: each in "
                 "[0, 1], sum <= 1")
    try:
        overrides = dict(_parse_field(item) for item in a.nmpc)
    except ValueError as e:
        ap.error(str(e))
    path = Path(a.out) if a.out else default_path("nmpc", a.seed, a.episodes, mix, overrides)
    try:
        demo = load_or_make(path, expert="nmpc", episodes=a.episodes, seed=a.seed, mix=mix, expert_overrides=overrides)
    except ValueError as e:
        ap.error(str(e).replace("loss.bc.expert_overrides", "--nmpc"))
    print(f"{demo.shape[0]} samples in {path}")
    return path


if __name__ == "__main__":
    main()
