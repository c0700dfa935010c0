"""One comparison of every DeeP-LCC platoon controller, in the TorchRL platoon env.

    python -m mixed_traffic.controllers.deeplcc.compare --out outputs/deeplcc/compare \\
        --rl outputs/runs/deeplcc_lppo_s0 --warmstart outputs/runs/deeplcc_warmstart_s0 \\
        --rlmpc outputs/runs/deeplcc_rlmpc_s0

    python -m mixed_traffic.controllers.deeplcc.compare --out outputs/deeplcc/compare_sumo \\
        --backend torch sumo --mismatch idm --controllers hdv qp qp_sumo nnmpc --no-compute

Scenarios of the same length run as one batched env (torch) or one SUMO simulation each
(``--backend sumo``: the platoon in SUMO, humans = SUMO's IDM with the DeeP-LCC IDM set).
Controllers: ``hdv`` (all-HDV: the CAVs drive like the platoon's humans), ``qp`` (the exact
DeeP-LCC QP on one homogeneous-OVM Hankel set, pre-collected with ``--qp-seed``), ``qp_sumo``
(the same QP on a Hankel set pre-collected in SUMO, same seed), ``qp_idm`` (on a torch
IDM-human Hankel set), ``nnmpc``
(the cached NNMPC), and the learned ``rl`` (Lagrangian PPO from scratch), ``warmstart``
(actor initialised from the NNMPC) and ``rlmpc`` (residual over the NNMPC) from their run
directories. Each runs the five evaluation scenarios of the DeeP-LCC package (random ±1,
random ±5, brake at 1 s, sine ±5, NEDC; ``randomize=False``), ``--episodes`` rows each, with
the humans of every ``--mismatch`` setting, behind the safety layer (s_min 5 m) and without
it. The env is seeded with ``--seed`` (not a training seed): every controller meets the same
head profiles and the same human noise. Deterministic policies.

Metrics per scenario (mean over its rows; a row stops counting at its first collision):
``cost`` (sum of the DeeP-LCC stage cost), ``fuel`` (mL, the reference's model over the
vehicles from the first CAV to the tail), ``min_gap`` (m, every follower), ``collisions``
(rows with one), ``clip_rate`` (share of CAV commands the safety layer changed). Per-step
compute: median time of one decision at batch 1 on one CPU thread (for RLMPC the NNMPC and
the actor), as plain torch on tensors and as the TorchRL module call (see :func:`per_step_compute`).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
from tensordict.nn import TensorDictModule
from torchrl.envs import Compose, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from mixed_traffic.controllers.deeplcc.closed_loop import fuel_rate

SCENARIOS = {"random1": "random1", "random5": "random5", "brake": "brake", "sine": "sine5", "nedc": "nedc"}
SECONDS = {"nedc": 330.0}
CLASSICAL = ("hdv", "qp", "nnmpc", "qp_sumo", "qp_idm")
#: the Hankel data each QP controller is built on: (pre-collection backend, human model)
QP_DATA = {"qp": ("torch", "ovm"), "qp_sumo": ("sumo", "idm"), "qp_idm": ("torch", "idm")}
BACKENDS = ("torch", "sumo")
LEARNED = ("rl", "warmstart", "rlmpc")
S_MIN = 5.0


class HumanCAV(torch.nn.Module):
    """All-HDV baseline: each CAV takes the acceleration its human model would (the env's human parameters)."""

    def __init__(self, env):
        super().__init__()
        self.env = env.base_env if isinstance(env, TransformedEnv) else env

    def forward(self, gap: torch.Tensor, speed: torch.Tensor) -> torch.Tensor:
        from mixed_traffic.physics import car_following_accel

        e = self.env
        ci = list(e.scenario.cav_indices)
        params = {k: v[:, [i - 1 for i in ci]].to(speed.dtype) for k, v in e.hdv.items()}
        return car_following_accel(e.cfg.hdv_model, gap[:, ci], speed[:, ci], speed[:, [i - 1 for i in ci]], params)


def hdv_policy(env) -> TensorDictModule:
    return TensorDictModule(HumanCAV(env), in_keys=[("traffic", "gap"), ("traffic", "speed")], out_keys=["action"])


def qp_policy(seed: int = 12345, data: str = "qp") -> TensorDictModule:
    """The exact QP on one Hankel set pre-collected with ``seed`` from the data source ``QP_DATA[data]``.

    ``"qp"``: the homogeneous-OVM torch platoon (the deployed QP), ``"qp_sumo"``: the SUMO
    platoon (SUMO's IDM humans), ``"qp_idm"``: the torch platoon with IDM humans.
    """
    from mixed_traffic.controllers.deeplcc.controller import deeplcc_policy
    from mixed_traffic.controllers.deeplcc.train import deployed_solver

    backend, hdv = QP_DATA[data]
    _, solver = deployed_solver(seed, hdv_model=hdv, backend=backend)
    return deeplcc_policy(solver)


def groups(scenarios) -> list[tuple[str, ...]]:
    """Scenarios of the same length run as one batched env (row i: scenario i % len)."""
    short = tuple(s for s in scenarios if s not in SECONDS)
    return ([short] if short else []) + [(s,) for s in scenarios if s in SECONDS]


def build(controller: str, *, scenarios: tuple[str, ...], mismatch: str, episodes: int, seed: int, safety: bool,
          runs: dict, nnmpc: str, qp_seed: int = 12345, cache: dict | None = None, backend: str = "torch"):
    """``(env, policy)`` of one controller on a group of equally long scenarios, ``episodes`` rows each.

    ``backend="sumo"``: one SUMO platoon (batch 1, one scenario; ``rollout_metrics`` rolls
    its ``episodes`` one after the other), humans = SUMO's IDM (``mismatch`` must be ``"idm"``).
    """
    from mixed_traffic import make_env
    from transforms import SafetyLayer

    if backend not in BACKENDS:
        raise ValueError(f"backend: {backend!r} is invalid; allowed: {list(BACKENDS)}")
    if backend == "sumo" and (len(scenarios) != 1 or mismatch != "idm"):
        raise ValueError(f"backend 'sumo': scenarios={scenarios}, mismatch={mismatch!r} are invalid; allowed: one "
                         "scenario at a time and mismatch 'idm' (SUMO's humans are IDM)")
    ov = dict(profiles=[SCENARIOS[s] for s in scenarios], profile_rows=True, randomize=False, mismatch=mismatch,
              episode_seconds=SECONDS.get(scenarios[0], 40.0))
    rows = episodes * len(scenarios) if backend == "torch" else 1
    cache = {} if cache is None else cache
    if controller in CLASSICAL:
        policy = None
        if controller in QP_DATA:  # pre-collect before the env exists: one SUMO per process
            if controller not in cache:
                cache[controller] = qp_policy(qp_seed, controller)
            cache[controller].module.reset()
            policy = cache[controller]
        elif controller == "nnmpc":
            from mixed_traffic.controllers.deeplcc.rlmpc import nnmpc_base

            policy = nnmpc_base(nnmpc, "--nnmpc")
        base = make_env("platoon", backend=backend, batch_size=rows, seed=seed, **ov)
        env = TransformedEnv(base, Compose(SafetyLayer(s_min=S_MIN, s_max=None)) if safety else Compose())
        return env, (hdv_policy(env) if controller == "hdv" else policy)
    from omegaconf import open_dict

    from mixed_traffic.evaluation.policies import checkpoint_config, policy_factory_from_state
    from mixed_traffic.training.builders import make_transformed_env

    if controller not in runs or runs[controller] is None:
        raise ValueError(f"--{controller}: no run directory given; allowed: a run directory or final.pt")
    cfg, state = cache.get(controller) or checkpoint_config(runs[controller])
    cache[controller] = (cfg, state)
    cfg = cfg.copy()
    with open_dict(cfg):
        cfg.env.backend = backend
        if backend == "sumo" and cfg.env.get("overrides"):
            cfg.env.overrides.pop("accel_noise", None)
    without = () if safety else ("safety_layer", "intervention_cost")
    env = make_transformed_env(cfg, num_envs=rows, seed=seed, without=without, **ov)
    return env, policy_factory_from_state(cfg, state)(env)


def rollout_metrics(env, policy, scenarios: tuple[str, ...], episodes: int | None = None) -> dict:
    """Roll one episode per row; metrics per scenario, averaged over its rows (see the module docstring).

    A one-row env (SUMO) with ``episodes`` > 1 rolls its episodes one after the other
    (each rollout resets: the next head-profile draw of the env's generator).
    """
    base = env.base_env
    steps = base.scenario.max_steps
    runs = episodes if (episodes and base.batch_size[0] == 1 and len(scenarios) == 1) else 1
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        td = torch.cat([env.rollout(steps, policy, break_when_any_done=False) for _ in range(runs)], 0)
    nxt = td["next"]
    done = nxt["done"][..., 0]
    valid = (done.long().cumsum(-1) - done.long()) == 0  # up to and including the first done
    J = nxt["traffic", "J"][..., 0]
    cost = (J * valid).sum(-1)
    first = min(base.scenario.cav_indices)
    v = td["traffic", "speed"][..., first:].double().numpy()
    a = nxt["traffic", "accel"][..., first:].double().numpy()
    fuel = torch.as_tensor((fuel_rate(v, a).sum(-1) * valid.numpy()).sum(-1) * base.dt)
    gap = nxt["traffic", "gap"][..., 1:].min(-1).values
    min_gap = torch.where(valid, gap, torch.full_like(gap, float("inf"))).min(-1).values
    coll = (nxt["collision"][..., 0] & valid).any(-1)
    clipped = nxt.get(("safety", "clipped"), None)
    out = {}
    row_scen = torch.arange(td.shape[0]) % len(scenarios)
    for i, sc in enumerate(scenarios):
        r = row_scen == i
        m = {"cost": float(cost[r].mean()), "fuel": float(fuel[r].mean()), "min_gap": float(min_gap[r].min()),
             "collisions": int(coll[r].sum()), "episodes": int(r.sum())}
        if clipped is not None:
            m["clip_rate"] = float(clipped[r][valid[r]].float().mean())
        out[sc] = m
    return out


def _actor_mean_fn(actor):
    """The actor's deterministic action as plain torch: trunk -> mean head -> tanh -> the action bounds."""
    seq, prob = actor.module[0], actor.module[1]
    trunk, head = seq.module[0].module, seq.module[1].module
    low, high = prob.distribution_kwargs["low"], prob.distribution_kwargs["high"]

    def f(obs):
        loc = head.mean(trunk(obs))
        return low + (torch.tanh(loc) + 1.0) * 0.5 * (high - low)

    return f


def per_step_compute(controller: str, runs: dict, nnmpc: str, repeats: int = 300, qp_seed: int = 12345,
                     cache: dict | None = None) -> dict:
    """Median seconds of one decision at batch 1 on one CPU thread, on a reset state.

    ``module``: the TorchRL policy call on the env's tensordict (RLMPC: plus the NNMPC
    module of the residual transform); ``network``: the same arithmetic as plain torch on
    tensors (NNMPC and actor networks, tanh, bounds, residual sum), i.e. what a deployed
    controller computes.
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        env, policy = build(controller, scenarios=("random5",), mismatch="none", episodes=1, seed=0, safety=True,
                            runs=runs, nnmpc=nnmpc, qp_seed=qp_seed, cache=cache)
        td = env.reset()
        res_t = next((t for t in env.transform if hasattr(t, "base_action")), None)
        x = torch.cat([td["uini"], td["yini"], td["eini"]], -1)
        obs = td["observation"]
        if controller in LEARNED:
            mean = _actor_mean_fn(policy)
            if res_t is not None:
                net, w = res_t.base.module, res_t.weight

                def network():
                    return (net.forward_flat(x) + w * mean(obs)).clamp(-5.0, 2.0)
            else:
                def network():
                    return mean(obs)
        elif controller == "nnmpc":
            def network():
                return policy.module.forward_flat(x)
        elif controller == "qp":
            def network():
                return policy.module(td["uini"], td["yini"], td["eini"])
        else:
            def network():
                return policy.module(td["traffic", "gap"], td["traffic", "speed"])

        def module():
            out = policy(td.clone(False))
            if res_t is not None:
                res_t.base(td.clone(False))
            return out

        out = {}
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            for name, fn in (("module", module), ("network", network)):
                times = []
                for i in range(repeats + 20):
                    t0 = time.perf_counter()
                    fn()
                    if i >= 20:
                        times.append(time.perf_counter() - t0)
                out[name] = float(np.median(times))
        return out
    finally:
        torch.set_num_threads(threads)


def compare(controllers, *, runs: dict, nnmpc: str, mismatches=("none", "idm"), scenarios=tuple(SCENARIOS),
            episodes: int = 3, seed: int = 10_000, safety=(True, False), compute: bool = True, log=print,
            backends=("torch",)) -> dict:
    """Every controller on every scenario; ``results[key][controller][scenario]``.

    Keys: ``"{mismatch}/{layer|no_layer}"`` for the torch platoon and
    ``"sumo/idm/{layer|no_layer}"`` for the SUMO platoon (SUMO's IDM humans; every
    scenario in its own SUMO simulation, seeded with ``seed`` + its index, episodes one
    after the other).
    """
    cache: dict = {}
    res: dict = {"seed": seed, "episodes": episodes, "runs": {k: str(v) for k, v in runs.items() if v},
                 "nnmpc": nnmpc, "results": {}, "compute_s": {}}
    plan = [("torch", mm) for mm in mismatches if "torch" in backends]
    plan += [("sumo", "idm")] if "sumo" in backends else []
    for backend, mm in plan:
        grps = groups(scenarios) if backend == "torch" else [(sc,) for sc in scenarios]
        for sf in safety:
            key = f"{'sumo/' if backend == 'sumo' else ''}{mm}/{'layer' if sf else 'no_layer'}"
            res["results"][key] = {}
            for c in controllers:
                res["results"][key][c] = {}
                for gi, grp in enumerate(grps):
                    t0 = time.perf_counter()
                    env, pol = build(c, scenarios=grp, mismatch=mm, episodes=episodes, seed=seed + gi, safety=sf,
                                     runs=runs, nnmpc=nnmpc, cache=cache, backend=backend)
                    try:
                        ms = rollout_metrics(env, pol, grp, episodes)
                    finally:
                        env.close()
                    res["results"][key][c].update(ms)
                    if log:
                        for sc, m in ms.items():
                            log(f"{key:16s} {c:10s} {sc:8s} cost {m['cost']:12.1f} fuel {m['fuel']:8.1f} "
                                f"min gap {m['min_gap']:6.2f} coll {m['collisions']}")
                        log(f"  ({time.perf_counter() - t0:.0f} s)")
    if compute:
        for c in controllers:
            res["compute_s"][c] = per_step_compute(c, runs, nnmpc, cache=cache)
    return res


def summary(res: dict) -> dict:
    """RLMPC vs NNMPC per scenario, the QP's fuel saving vs all-HDV in the brake scenario."""
    out = {}
    for key, table in res["results"].items():
        s = {}
        if "rlmpc" in table and "nnmpc" in table:
            d = {sc: 100.0 * (table["rlmpc"][sc]["cost"] / table["nnmpc"][sc]["cost"] - 1.0) for sc in table["nnmpc"]}
            s["rlmpc_vs_nnmpc_pct"] = d
            s["rlmpc_vs_nnmpc_mean_pct"] = float(np.mean(list(d.values())))
        if "qp" in table and "hdv" in table and "brake" in table["qp"]:
            s["qp_fuel_saving_brake_pct"] = 100.0 * (1.0 - table["qp"]["brake"]["fuel"] / table["hdv"]["brake"]["fuel"])
        if "qp_sumo" in table and "qp" in table:
            d = {sc: 100.0 * (table["qp_sumo"][sc]["cost"] / table["qp"][sc]["cost"] - 1.0) for sc in table["qp"]}
            s["qp_sumo_vs_qp_pct"] = d
            s["qp_sumo_vs_qp_mean_pct"] = float(np.mean(list(d.values())))
        s["collisions"] = {c: sum(m["collisions"] for m in t.values()) for c, t in table.items()}
        out[key] = s
    return out


def markdown(res: dict) -> str:
    lines = []
    for key, table in res["results"].items():
        scen = list(next(iter(table.values())))
        lines += [f"### {key}", "", "| controller | " + " | ".join(f"{s} cost" for s in scen)
                  + " | fuel (mL, brake) | min gap (m) | collisions |",
                  "|---" * (len(scen) + 4) + "|"]
        for c, t in table.items():
            lines.append(f"| {c} | " + " | ".join(f"{t[s]['cost']:.4g}" for s in scen)
                         + f" | {t.get('brake', {}).get('fuel', float('nan')):.1f} | "
                         f"{min(m['min_gap'] for m in t.values()):.2f} | {sum(m['collisions'] for m in t.values())} |")
        lines.append("")
    lines += ["| controller | per step, batch 1: network (us) | TorchRL module call (us) |", "|---|---|---|"]
    lines += [f"| {c} | {1e6 * s['network']:.1f} | {1e6 * s['module']:.1f} |" for c, s in res["compute_s"].items()]
    return "\n".join(lines)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(prog="python -m mixed_traffic.controllers.deeplcc.compare", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True)
    ap.add_argument("--nnmpc", default=None, help="NNMPC checkpoint (default: the cached one)")
    for c in LEARNED:
        ap.add_argument(f"--{c}", default=None, help=f"run directory (or final.pt) of the {c} controller")
    ap.add_argument("--controllers", nargs="*", default=None, help="default: hdv qp nnmpc + the runs given")
    ap.add_argument("--mismatch", nargs="*", default=["none", "idm"], choices=["none", "idm", "hetero_ovm"])
    ap.add_argument("--scenarios", nargs="*", default=list(SCENARIOS), choices=list(SCENARIOS))
    ap.add_argument("--episodes", type=int, default=3)
    ap.add_argument("--seed", type=int, default=10_000)
    ap.add_argument("--layer", default="on", choices=["on", "off", "both"],
                    help="behind the safety layer (on), without it (off) or both")
    ap.add_argument("--no-compute", action="store_true", help="skip the per-step compute timing")
    ap.add_argument("--backend", nargs="*", default=["torch"], choices=list(BACKENDS),
                    help="torch (the --mismatch settings) and/or sumo (SUMO's IDM humans)")
    a = ap.parse_args(argv)
    from mixed_traffic.controllers.deeplcc.rlmpc import DEFAULT_NNMPC

    if a.episodes < 1:
        ap.error(f"--episodes: {a.episodes} is invalid; allowed: >= 1")
    runs = {c: getattr(a, c) for c in LEARNED}
    controllers = a.controllers or ["hdv", "qp", "nnmpc", *(["qp_sumo"] if "sumo" in a.backend else []),
                                    *[c for c in LEARNED if runs[c]]]
    res = compare(controllers, runs=runs, nnmpc=a.nnmpc or DEFAULT_NNMPC, mismatches=a.mismatch,
                  scenarios=a.scenarios, episodes=a.episodes, seed=a.seed,
                  safety={"on": (True,), "off": (False,), "both": (True, False)}[a.layer], compute=not a.no_compute,
                  backends=tuple(a.backend))
    res["summary"] = summary(res)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "compare.json").write_text(json.dumps(res, indent=2))
    md = markdown(res) + "\n\n```\n" + json.dumps(res["summary"], indent=2) + "\n```\n"
    (out / "compare.md").write_text(md)
    print(md)
    return res


if __name__ == "__main__":
    main()
