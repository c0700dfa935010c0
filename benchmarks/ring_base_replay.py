"""Many settings of a ring experiment's residual base, replayed behind recorded head traces in seconds each.

What ``ring_base_probe.py`` measures for one setting in minutes (the base driving alone, no layer, tuning
seed 3000 by default), this measures for hundreds: the head's speeds of every case are recorded once (with
the ``--set`` base, the reference), and each setting's base is re-driven behind them
(:mod:`mixed_traffic.evaluation.replay`; the env's actuator bounds, integration and metrics). Settings are
the reference plus ``--draws`` random draws of the ``--vary KEY=LO:HI`` ranges (uniform, seed ``--draw-seed``)
or the product of ``--grid KEY=A,B,...`` lists. Per case it gives the jerk against IDM-as-CAV's and against the
reference's on the same episodes, the smallest gap after the warm-up, the largest head gap, the steady RMSE
and the collisions (a gap at or below 0); not the return, which sums the humans' speeds.

``--cases`` defaults to the cases settings are searched on (those of ``ring_base_probe.py`` and the three of
``ring_generalization.py --cases tuning``); it also takes the fresh cases of ``ring_generalization.py --cases
fresh`` and ``fresh_2``, to look into a setting there, not to pick one.

With ``--classic MODEL`` (``idm``, ``soft`` or ``cacc``) the settings are a classical controller's instead
of the base's: ``--set``, ``--vary`` and ``--grid`` then name the model's parameters (``kv=0.3``, not Hydra
keys), the reference is the model's defaults with ``--set``, and the head's speeds are still recorded with the
experiment's base. That searches a classical opponent on the same tuning episodes as the base::

    python benchmarks/ring_base_replay.py --experiment ring_lagrangian_ppo_wide_band --classic cacc \
        --vary ka=0:1 kv=0.1:1.2 ks=0.01:0.3 h=0.4:2 s0=2:10 --draws 200 --out outputs/results/cacc_replay

A base whose ``transforms.residual.drive_off.gain`` is set is replayed under its drive-off cap (the deployed
chain's, with its memory), so the cap's settings can be searched the same way::

    python benchmarks/ring_base_replay.py --experiment ring_lagrangian_ppo_v2v \\
        --cases stop_and_go_15 stop_and_go brake_to_standstill brake_from_25 \\
        --grid transforms.residual.drive_off.gain=0.7,1.0,1.5 transforms.residual.drive_off.overspeed=0.05,0.1,0.15 \\
        'transforms.residual.drive_off.gaps=[32.0,38.0],[34.0,38.0]' transforms.residual.drive_off.accel=1.0,2.0 \\
        --out outputs/results/ring_base_replay_drive_off

Prints the settings on the frontier of (worst jerk excess over the reference across the cases, largest
head gap across the cases) that collide nowhere, and writes ``OUT/replay.jsonl`` (one line per setting) and
``OUT/replay.json``. Check a chosen setting in the env with ``ring_base_probe.py`` before training on it::

    python benchmarks/ring_base_replay.py --experiment ring_lagrangian_ppo_band_stop \\
        --set transforms.residual.catch_up.accel=2.9 'transforms.residual.catch_up.gaps=[33,39]' \\
        --vary transforms.residual.catch_up.horizon=0:4 transforms.residual.catch_up.dv=0.3:3 \\
        --draws 50 --out outputs/results/ring_base_replay
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import random
import sys
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from ring_base_probe import NAMES as PROBED  # noqa: E402
from ring_generalization import GROUPS  # noqa: E402

SEARCHED = PROBED + GROUPS["tuning"]  # the cases settings are searched on: --cases' default
# and the fresh ones, to look into them (no setting was picked on them)
NAMES = SEARCHED + GROUPS["fresh"] + GROUPS["fresh_2"]


def _pairs(items: list[str], flag: str, parse) -> dict:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise SystemExit(f"{flag}: {item!r} is not KEY=VALUE")
        try:
            out[key] = parse(value)
        except ValueError:
            raise SystemExit(f"{flag}: {item!r} has a bad value") from None
    return out


def _range(value: str) -> tuple[float, float]:
    lo, hi = (float(x) for x in value.split(":"))
    if not lo <= hi:
        raise ValueError
    return lo, hi


def _split(value: str) -> list[str]:
    """``A,B,...`` on the commas outside brackets: ``[1,2],[3,4]`` is two values."""
    out, depth, cur = [], 0, ""
    for ch in value:
        depth += (ch == "[") - (ch == "]")
        if ch == "," and depth == 0:
            out.append(cur)
            cur = ""
        else:
            cur += ch
    return [x for x in out + [cur] if x]


def settings(a) -> list[list[str]]:
    """The overrides of each setting beyond ``--set``: the reference (none) first."""
    vary = _pairs(a.vary, "--vary", _range)
    grid = _pairs(a.grid, "--grid", _split)
    if vary and grid:
        raise SystemExit("--vary and --grid: give one of them")
    if vary and a.draws < 1:
        raise SystemExit(f"--draws = {a.draws} is invalid with --vary; allowed: >= 1")
    rng = random.Random(a.draw_seed)
    out: list[list[str]] = [[]]
    for _ in range(a.draws if vary else 0):
        out.append([f"{k}={round(rng.uniform(lo, hi), 3)}" for k, (lo, hi) in vary.items()])
    for combo in itertools.product(*grid.values()) if grid else ():
        out.append([f"{k}={v}" for k, v in zip(grid, combo)])
    return out


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--experiment", required=True, help="a ring experiment with a residual base")
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="Hydra overrides of the reference")
    p.add_argument("--vary", nargs="*", default=[], metavar="KEY=LO:HI", help="ranges drawn uniformly")
    p.add_argument("--draws", type=int, default=20, help="settings drawn from --vary")
    p.add_argument("--draw-seed", type=int, default=0)
    p.add_argument("--grid", nargs="*", default=[], metavar="KEY=A,B,...", help="every combination of the lists")
    p.add_argument("--cases", nargs="+", default=list(SEARCHED),
                   help=f"subset of {list(NAMES)} (default: the first {len(SEARCHED)}, the ones settings are searched on)")
    p.add_argument("--seed", type=int, default=3000, help="evaluation seed (default 3000, a tuning seed)")
    p.add_argument("--episodes", type=int, default=4)
    p.add_argument("--classic", default=None, metavar="MODEL",
                   help="replay settings of this classical controller (idm, soft, cacc) instead of the base's")
    p.add_argument("--out", default="outputs/results/ring_base_replay")
    a = p.parse_args(argv)
    unknown = set(a.cases) - set(NAMES)
    if unknown:
        raise SystemExit(f"--cases: {sorted(unknown)} are not cases; allowed: {list(NAMES)}")
    todo = settings(a)

    import torch
    from omegaconf import open_dict
    from ring_generalization import named_config
    from tqdm import tqdm

    from mixed_traffic import make_env
    from mixed_traffic.config import compose
    from mixed_traffic.controllers.classic import make_classic_policy
    from mixed_traffic.evaluation.policies import residual_base_factory
    from mixed_traffic.evaluation.replay import (
        AnswerLaw,
        DriveOffLaw,
        record_head_traces,
        replay,
        replay_settings,
        stack_traces,
    )
    from mixed_traffic.training.builders import committed_answer, drive_off_cap, residual_base
    from mixed_traffic.validation import validate_config

    torch.set_num_threads(1)

    def config(extra):
        return validate_config(compose([f"experiment={a.experiment}", *([] if a.classic else a.set), *extra]))

    classic_set = {}
    if a.classic is not None:
        from mixed_traffic.controllers.classic import classic_parameters

        try:
            allowed = classic_parameters(a.classic)
        except ValueError as e:
            raise SystemExit(f"--classic: {e}") from None
        classic_set = _pairs(a.set, "--set", float)
        named = set(classic_set) | set(_pairs(a.vary, "--vary", _range)) | set(_pairs(a.grid, "--grid", _split))
        unknown = sorted(named - set(allowed))
        if unknown:
            raise SystemExit(f"--set/--vary/--grid: {unknown} are not {a.classic} parameters; allowed: {allowed}")

    def law(extra):
        """The setting's controller: the base of its Hydra overrides, or (``--classic``) the classical model."""
        if a.classic is None:
            rcfg = config(extra).transforms.residual
            base = residual_base(rcfg, env).module.double()
            answer = committed_answer(rcfg, env)  # the deployed chain's committed answer over the base, with its memory
            if answer is not None:
                base = AnswerLaw(base, answer.double())
            cap = drive_off_cap(rcfg, env)  # the deployed chain's drive-off cap over the base, with its memory
            return base if cap is None else DriveOffLaw(base, cap)
        params = {**classic_set, **{k: float(v) for k, v in (o.split("=", 1) for o in extra)}}
        return make_classic_policy(a.classic, env, **params).module.double()

    ref_cfg = config([])
    factory = residual_base_factory(ref_cfg)  # fails here, naming residual_idm, for a chain without a base
    t0 = time.perf_counter()
    traces, kw = [], None
    for name in a.cases:
        cfg, prof = named_config(ref_cfg, name, episodes=a.episodes, seconds=200.0, seed=a.seed)
        with open_dict(cfg):
            cfg.eval.seed = a.seed
        traces.append(record_head_traces(cfg, policy_factory=factory)[prof])
        here = replay_settings(cfg, prof)
        if kw is not None and here != kw:
            raise SystemExit(f"--cases: {name} runs with {here}, the others with {kw}; replay them apart")
        kw = here
    trace, rows = stack_traces(traces)
    record_s = time.perf_counter() - t0
    env = make_env("ring", batch_size=1, seed=0)

    def per_case(m):
        return {name: {"collisions": int(m["collision"][r].sum()), "min_gap": float(m["min_gap_after"][r].min()),
                       "max_head_gap": float(m["max_head_gap"][r].max()),
                       "steady_rmse": float(m["speed_rmse_steady"][r].mean()),
                       "jerk": float(m["mean_abs_jerk"][r].mean())} for name, r in zip(a.cases, rows)}

    idm = per_case(replay(make_classic_policy("idm", env).module.double(), trace, **kw))
    results = []
    t1 = time.perf_counter()
    for extra in tqdm(todo, desc="replay", unit="setting", disable=len(todo) < 2):
        try:
            base = law(extra)
        except ValueError as e:  # a drawn setting the base refuses (e.g. gaps[0] >= gaps[1])
            if not extra:
                raise SystemExit(f"--set: {e}") from None
            results.append({"overrides": extra, "error": str(e)})
            continue
        res = per_case(replay(base, trace, **kw))
        ref = results[0]["cases"] if results else res
        for name, r in res.items():
            r["jerk_vs_idm"] = r["jerk"] / idm[name]["jerk"] - 1.0
            r["jerk_vs_reference"] = r["jerk"] / ref[name]["jerk"] - 1.0
        results.append({"overrides": extra, "cases": res})
    per_setting = (time.perf_counter() - t1) / len(todo)

    ok = [r for r in results if "cases" in r and not any(c["collisions"] for c in r["cases"].values())]
    key = lambda r: (max(c["jerk_vs_reference"] for c in r["cases"].values()),  # noqa: E731
                     max(c["max_head_gap"] for c in r["cases"].values()))
    frontier = [r for r in ok if not any(key(q)[0] <= key(r)[0] and key(q)[1] <= key(r)[1] and key(q) != key(r)
                                         for q in ok)]
    print(f"{a.classic or a.experiment} {' '.join(a.set)}: {len(todo)} settings replayed on {a.cases} (seed {a.seed}, "
          f"{a.episodes} episodes a case); recording {record_s:.1f} s, {per_setting:.2f} s a setting")
    print("frontier (worst jerk over the reference's, largest head gap), collision-free:")
    for r in sorted(frontier, key=key):
        w, g = key(r)
        print(f"  {100 * w:+6.1f} %  {g:5.1f} m  {' '.join(r['overrides']) or '(reference)'}")
    out = {"experiment": a.experiment, "classic": a.classic, "set": a.set, "seed": a.seed, "episodes": a.episodes, "cases": a.cases,
           "idm_as_cav": idm, "settings": results, "record_seconds": record_s, "seconds_per_setting": per_setting}
    d = Path(a.out)
    d.mkdir(parents=True, exist_ok=True)
    (d / "replay.json").write_text(json.dumps(out, indent=1))
    with open(d / "replay.jsonl", "w") as f:
        for r in results:
            f.write(json.dumps(r) + "\n")
    return out


if __name__ == "__main__":
    main()
