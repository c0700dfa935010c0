"""Collect the intersection results: one table for every method on the same test episodes, plus GIFs.

Reads ``<runs>/intersection_<method>_seed<seed>/eval.json`` (written by
``python -m mixed_traffic.intersection.train_lppo experiment=intersection_<method>``), prints the
markdown tables and, with ``--gifs DIR``, re-runs chosen test episodes (default: the first of
each behaviour, plus the first failure of each method when the run recorded its outcomes) and
writes one GIF each.

    python -m mixed_traffic.intersection.report --runs outputs/intersection --gifs docs/intersection_gifs

>>> from mixed_traffic.intersection.report import load_eval
>>> load_eval("does/not/exist") is None
True
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from mixed_traffic.intersection.agent_model import make_test_set
from mixed_traffic.intersection.evaluate import evaluate_policy, format_table, write_gifs

METHOD_ORDER = ["lppo", "lppo_bc", "lppo_bff", "nmpc", "residual_mpc"]


def load_eval(run_dir: str | Path) -> dict | None:
    """``{"eval": table, "outcomes": ...}`` of a run directory, or None if it has no ``eval.json``."""
    p = Path(run_dir) / "eval.json"
    if not p.exists():
        return None
    data = json.loads(p.read_text())
    if "eval" not in data:  # a bare table
        data = {"eval": data}
    return data


def policy_for(method: str, run_dir: Path):
    """``(policy, transform)`` of a method: the NMPC, or the trained actor of ``run_dir``."""
    if method == "nmpc":
        from mixed_traffic.intersection.nmpc import make_nmpc_policy

        return make_nmpc_policy(), None
    from mixed_traffic.intersection.train_lppo import load_actor

    actor, transform, _ = load_actor(run_dir / "final.pt")
    return actor, transform


def summary_table(results: dict[str, dict]) -> str:
    """One row per method: overall success, collisions, timeouts, crossing time, return; zig-zag success."""
    lines = ["| method | success | collision | timeout | crossing time (s) | return | straight / left / right success | zig-zag (held out) success |",
             "|---|---|---|---|---|---|---|---|"]
    for m, data in results.items():
        t = data["eval"]
        o = t["overall"]
        slr = " / ".join(f"{t[b]['success_rate']:.1%}" for b in ("straight", "left", "right") if b in t)
        zz = f"{t['zigzag']['success_rate']:.1%}" if "zigzag" in t else "-"
        lines.append(f"| {m} | {o['success_rate']:.1%} | {o['collision_rate']:.1%} | {o['timeout_rate']:.1%} | "
                     f"{o['crossing_time_s']:.2f} | {o['return']:.1f} | {slr} | {zz} |")
    return "\n".join(lines)


def main(argv=None) -> str:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", default="outputs/intersection")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--gifs", default=None, help="directory for GIFs (omit to skip)")
    ap.add_argument("--episodes", type=int, nargs="*", default=[0, 1, 2, 3], help="test-episode indices for GIFs")
    ap.add_argument("--per-behaviour", type=int, default=80)
    ap.add_argument("--methods", nargs="*", default=METHOD_ORDER, help="subset of methods for the GIFs")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    runs = Path(args.runs)
    results = {}
    for m in METHOD_ORDER:
        data = load_eval(runs / f"intersection_{m}_seed{args.seed}")
        if data is not None:
            results[m] = data
    text = [summary_table(results), ""]
    for m, data in results.items():
        text += [format_table(data["eval"], title=m), ""]
    if args.gifs:
        test_set = make_test_set(args.per_behaviour)
        for m, data in results.items():
            if m not in args.methods:
                continue
            eps = list(args.episodes)
            codes = data.get("outcomes", {}).get("codes")
            if codes:
                fails = [i for i, c in enumerate(codes) if c != "S"]
                eps += fails[:2]
            eps = sorted(set(eps))
            policy, transform = policy_for(m, runs / f"intersection_{m}_seed{args.seed}")
            sub = test_set.subset(torch.tensor(eps))
            res = evaluate_policy(policy, test_set=sub, transform=transform, record=list(range(len(eps))))
            res.frames = {eps[i]: fr for i, fr in res.frames.items()}
            # map outcomes back to the test-set indices for the file names
            for key in ("success", "collision", "timeout", "out_of_bounds"):
                full = np.zeros(len(test_set), dtype=bool)
                full[eps] = getattr(res, key)
                setattr(res, key, full)
            paths = write_gifs(res, args.gifs, prefix=m)
            text.append(f"{m}: " + ", ".join(str(p) for p in paths))
    out = "\n".join(text)
    print(out)
    return out


if __name__ == "__main__":
    main()
