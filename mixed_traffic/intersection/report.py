"""Collect the intersection results: one table per test set with every method, plus GIFs.

Reads ``<run>/eval/eval.json`` of each run directory given (written by ``mt-train
experiment=intersection_<method>`` with ``eval.after_train=true``, or by ``mt-eval``), prints
the markdown tables and, with ``--gifs DIR``, re-runs chosen standard test episodes (the
first of each behaviour plus the first failures of each method) and writes one GIF each.

    python -m mixed_traffic.intersection.report outputs/runs/intersection_*/* --gifs docs/intersection_gifs

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

from mixed_traffic.envs.intersection_agents import make_test_set
from mixed_traffic.intersection.evaluate import evaluate_policy, load_policy, write_gifs


def load_eval(run_dir: str | Path) -> dict | None:
    """The evaluation report of a run directory (``eval/eval.json``), or None if it has none."""
    p = Path(run_dir) / "eval" / "eval.json"
    return json.loads(p.read_text()) if p.exists() else None


def summary_table(results: dict[str, dict], test_set: str = "standard") -> str:
    """One row per method on one test set: success, collisions, timeouts, crossing time, return, per behaviour."""
    lines = ["| method | success | collision | timeout | crossing time (s) | return | success per behaviour |",
             "|---|---|---|---|---|---|---|"]
    for m, data in results.items():
        if test_set not in data["sets"]:
            continue
        t = data["sets"][test_set]["table"]
        o = t["overall"]
        per = " / ".join(f"{b} {r['success_rate']:.1%}" for b, r in t.items() if b != "overall")
        lines.append(f"| {m} | {o['success_rate']:.1%} | {o['collision_rate']:.1%} | {o['timeout_rate']:.1%} | "
                     f"{o['crossing_time_s']:.2f} | {o['return']:.1f} | {per} |")
    return "\n".join(lines)


def main(argv=None) -> str:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", help="run directories (each with eval/eval.json)")
    ap.add_argument("--gifs", default=None, help="directory for GIFs (omit to skip)")
    ap.add_argument("--episodes", type=int, nargs="*", default=[0, 1, 2, 3], help="standard test episodes to draw")
    ap.add_argument("--per-behaviour", type=int, default=80)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    results = {}
    for run in map(Path, args.runs):
        data = load_eval(run)
        if data is not None:
            results[data.get("name", run.name).removeprefix("intersection_")] = dict(data, run=run)
    sets = sorted({s for d in results.values() for s in d["sets"]}, key=lambda s: (s != "standard", s))
    text = []
    for s in sets:
        text += [f"**{s}**", "", summary_table(results, s), ""]
    if args.gifs:
        test_set = make_test_set(args.per_behaviour)
        for m, data in results.items():
            codes = data["sets"]["standard"]["outcomes"]["codes"]
            eps = sorted(set(args.episodes) | set([i for i, c in enumerate(codes) if c != "S"][:2]))
            if m == "nmpc":
                from mixed_traffic.intersection.nmpc import make_nmpc_policy

                policy, transform = make_nmpc_policy(), None
            else:
                policy, make_transform, _ = load_policy(data["run"] / "final.pt")
                transform = make_transform()
            res = evaluate_policy(policy, test_set=test_set.subset(torch.tensor(eps)), transform=transform,
                                  record=list(range(len(eps))))
            res.frames = {eps[i]: fr for i, fr in res.frames.items()}
            for key in ("success", "collision", "timeout", "out_of_bounds"):  # outcomes at the test-set indices
                full = np.zeros(len(test_set), dtype=bool)
                full[eps] = getattr(res, key)
                setattr(res, key, full)
            text.append(f"{m}: " + ", ".join(str(p) for p in write_gifs(res, args.gifs, prefix=m)))
    out = "\n".join(text)
    print(out)
    return out


if __name__ == "__main__":
    main()
