"""Results table (docs/results.md) from evaluated run directories.

    python -m mixed_traffic.evaluation.results outputs/results/*/      # prints a markdown table
    python -m mixed_traffic.evaluation.results --itself RUN... --baseline IDM_RUN   # with / without the layer
    python -m mixed_traffic.evaluation.results --paired RUN... --baseline IDM_RUN   # episode by episode
    python -m mixed_traffic.evaluation.results --generalization GEN_DIR...       # held-out cases over seeds

Each directory holds ``eval/report.json`` (from ``mt-main``, ``mt-train eval.after_train=true``
or ``mt-eval``) and, for trained policies, ``summary.json``; ``--itself`` and ``--paired`` also
take a directory holding ``report.json`` itself, or the file.
"""

from __future__ import annotations

import json
import math
import statistics
from pathlib import Path

COLUMNS = ("policy", "seed", "frames", "train wall (s)", "collisions / episodes", "min gap (m)",
           "max head gap (m)", "time outside (s/ep)", "steady RMSE (m/s)", "mean abs a (m/s2)", "jerk (m/s3)", "return", "override rate", "pass")


def row(run_dir: str | Path) -> dict:
    d = Path(run_dir)
    rep_path = d / "eval" / "report.json" if (d / "eval" / "report.json").is_file() else d / "report.json"
    rep = json.loads(rep_path.read_text())
    summ = json.loads((d / "summary.json").read_text()) if (d / "summary.json").is_file() else {}
    ov, acc = rep["overall"], rep["acceptance"]
    return {
        "policy": summ.get("name", rep.get("policy", d.name)), "seed": summ.get("seed", "–"),
        "frames": summ.get("frames", "–"),
        "train wall (s)": f"{summ['wall_seconds']:.0f}" if "wall_seconds" in summ else "–",
        "collisions / episodes": f"{ov['collisions']} / {ov['episodes']}",
        "min gap (m)": f"{ov['min_gap']:.2f}", "max head gap (m)": f"{ov['max_head_gap']:.2f}",
        "time outside (s/ep)": f"{ov['time_outside']:.2f}",
        "steady RMSE (m/s)": f"{acc['steady_speed_rmse']:.3f}",
        "mean abs a (m/s2)": f"{ov['mean_abs_accel']:.3f}", "jerk (m/s3)": f"{ov['mean_abs_jerk']:.2f}",
        "return": f"{ov['return']:.0f}", "pass": "yes" if acc["pass"] else "no",
        # share of steps SUMO's speed mode 95 changed the command (envs with sumo_safety only)
        "override rate": f"{ov['override_rate']:.3f}" if rep.get("sumo_safety") else "–",
        "_wall": summ.get("wall_seconds"),
    }


def table(run_dirs) -> str:
    rows = [row(d) for d in run_dirs]
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    lines += ["| " + " | ".join(str(r[c]) for c in COLUMNS) + " |" for r in rows]
    walls = [r["_wall"] for r in rows if r["_wall"] is not None]
    if walls:
        lines += ["", f"median training wall-clock: {statistics.median(walls):.0f} s over {len(walls)} runs"]
    return "\n".join(lines)


def profile_table(run_dirs) -> str:
    """Per seed and head profile: collisions, min gap, max head gap, time outside, steady RMSE."""
    lines = ["| run | profile | collisions / episodes | min gap (m) | max head gap (m) | time outside (s/ep) | "
             "steady RMSE (m/s) | mean abs a (m/s2) | safety clip rate |", "|" + "---|" * 9]
    for d in run_dirs:
        d = Path(d)
        rep = json.loads((d / "eval" / "report.json").read_text())
        for prof, r in rep["profiles"].items():
            m = r["metrics"]
            lines.append(f"| {d.name} | {prof} | {r['collisions']} / {len(r['per_episode']['collision'])} | "
                         f"{m['min_gap']['min']:.2f} | {m['max_head_gap']['max']:.2f} | "
                         f"{m['time_outside']['mean']:.2f} | {m['speed_rmse_steady']['mean']:.3f} ± "
                         f"{m['speed_rmse_steady']['std']:.3f} | {m['mean_abs_accel']['mean']:.3f} | "
                         f"{m['safety_clip_rate']['mean']:.2f} |")
    return "\n".join(lines)


def _report_path(d) -> Path:
    """The report a run is given by: ``report.json`` itself, its ``eval/`` directory or the run directory."""
    d = Path(d)
    if d.is_file():
        return d
    if (d / "eval" / "report.json").is_file():
        return d / "eval" / "report.json"
    return d / "report.json"


def _report(d) -> dict:
    return json.loads(_report_path(d).read_text())


def _run_name(d) -> str:
    """The run directory's name, however the run is given (``run/``, ``run/eval/``, ``run/eval/report.json``)."""
    folder = _report_path(d).parent
    return folder.parent.name if folder.name == "eval" else folder.name


PAIRED_METRICS = ("return", "mean_abs_jerk_after", "mean_abs_jerk", "max_head_gap", "speed_rmse_steady")


def paired_differences(run: dict, baseline: dict, metric: str) -> dict[str, dict]:
    """Per profile, ``run - baseline`` of ``metric`` episode by episode (reports of the same episodes).

    Returns ``{profile: {"mean", "se", "n", "run", "baseline", "run_lower"}}``: the mean difference, its
    standard error (sample std / sqrt(n)), the two means and how many episodes the run is below the
    baseline. Refuses reports whose episodes differ (``episode_seeds``), e.g. one written before the
    harness seeded its episodes one by one.
    """
    seeds = run.get("episode_seeds"), baseline.get("episode_seeds")
    if seeds[0] is None or seeds[0] != seeds[1]:
        raise ValueError(f"paired comparison: episode_seeds {seeds[0]} and {seeds[1]} are invalid; allowed: the same "
                         "list in both reports (evaluate both with the same eval.seed and eval.episodes)")
    out = {}
    for prof, r in run["profiles"].items():
        if prof not in baseline["profiles"]:
            continue
        a = r["per_episode"][metric]
        b = baseline["profiles"][prof]["per_episode"][metric]
        d = [x - y for x, y in zip(a, b)]
        n = len(d)
        se = statistics.stdev(d) / math.sqrt(n) if n > 1 else math.nan
        out[prof] = {"mean": statistics.fmean(d), "se": se, "n": n, "run": statistics.fmean(a),
                     "baseline": statistics.fmean(b), "run_lower": sum(x < 0 for x in d)}
    return out


def paired_table(run_dirs, baseline_dir, metrics=PAIRED_METRICS) -> str:
    """Markdown: per run, profile and metric, the run's mean, the baseline's, and the paired difference ± its SE."""
    base = _report(baseline_dir)
    lines = [f"Paired with {base.get('policy', baseline_dir)} on the same episodes (difference = run − baseline, "
             "± standard error over episodes; 'below' = episodes where the run's value is lower).", "",
             "| run | profile | metric | run | baseline | difference | below |", "|" + "---|" * 7]
    for d in run_dirs:
        rep = _report(d)
        name = _run_name(d)
        for metric in metrics:
            for prof, x in paired_differences(rep, base, metric).items():
                lines.append(f"| {name} | {prof} | {metric} | {x['run']:.4f} | {x['baseline']:.4f} | "
                             f"{x['mean']:+.4f} ± {x['se']:.4f} | {x['run_lower']} / {x['n']} |")
    return "\n".join(lines)


def itself_table(run_dirs, baseline_dir=None) -> str:
    """Per profile and run: the policy with its safety layer, without it (each start), and a baseline.

    Columns: collisions, min gap (after the warm-up for the layer-free close starts), max
    head gap after the warm-up, steady RMSE, jerk, return, intervention rate, mean |Δa|.
    Return and jerk are compared with the baseline (e.g. IDM as the CAV, no layer) on the
    same episodes when one is given.
    """
    base = _report(baseline_dir) if baseline_dir is not None else None
    lines = ["| profile | run | layer | start | collisions | min gap (m) | max head gap (m) | steady RMSE (m/s) | "
             "jerk (m/s3) | jerk after warm-up (m/s3) | return | intervention rate | mean abs Δa (m/s2) |", "|" + "---|" * 13]

    def cells(r, after=False):
        m = r["metrics"]
        gap = m["min_gap_after"]["min"] if after and "min_gap_after" in m else m["min_gap"]["min"]
        return (f"{r['collisions']} / {len(r['per_episode']['collision'])} | {gap:.2f} | {m['max_head_gap']['max']:.2f} | "
                f"{m['speed_rmse_steady']['mean']:.3f} | {m['mean_abs_jerk']['mean']:.3f} | "
                f"{m.get('mean_abs_jerk_after', {'mean': math.nan})['mean']:.3f} | {m['return']['mean']:.1f}")

    runs = [(_run_name(d), _report(d)) for d in run_dirs]  # each report read once
    for prof in runs[0][1]["profiles"]:
        for name, rep in runs:
            r = rep["profiles"][prof]
            m = r["metrics"]
            lines.append(f"| {prof} | {name} | on | standard | {cells(r)} | {m['safety_clip_rate']['mean']:.3f} | "
                         f"{m['mean_abs_delta']['mean']:.3f} |")
            for label, q in rep.get("without_layer", {}).get(prof, {}).items():
                lines.append(f"| {prof} | {name} | off | {label} | {cells(q, after=True)} | – | – |")
        if base is not None:
            lines.append(f"| {prof} | {base.get('policy', 'baseline')} | off | standard | "
                         f"{cells(base['profiles'][prof])} | – | – |")
    return "\n".join(lines)


def _generalization(d) -> dict:
    p = Path(d)
    if p.is_dir():
        p = p / "generalization.json"
    if not p.is_file():
        raise FileNotFoundError(f"--generalization: {str(d)!r} holds no generalization.json; allowed: the --out "
                                "directory of benchmarks/ring_generalization.py, or the file")
    return json.loads(p.read_text())


def _span(values, fmt: str, unit: str = "") -> str:
    lo, hi = min(values), max(values)
    return f"{lo:{fmt}}{unit}" if f"{lo:{fmt}}" == f"{hi:{fmt}}" else f"{lo:{fmt}}..{hi:{fmt}}{unit}"


def _steadiness(steady_in: list) -> str:
    """How the steady RMSE cell qualifies its figures: nothing where every episode had a steady state (or it was not
    recorded); else how many did, and that the figures are the whole-episode RMSE where none did."""
    known = [x for x in steady_in if x is not None]
    if not known or all(k == n for k, n in known):
        return ""
    if all(k == 0 for k, _ in known):
        return " (no steady state: whole episode)"
    counts = sorted(set(known))  # the same episodes in every run: one count, unless the runs differ
    return " (on the episodes with a steady state, " + ", ".join(f"{k} of {n}" for k, n in counts) + ")"


def generalization_table(dirs) -> str:
    """Per case, over several runs (seeds) of ``benchmarks/ring_generalization.py`` on the same episodes.

    Columns, the policy without its layer: the gaps after the warm-up over every start and run (smallest gap,
    largest head gap); collisions with and without the layer; its jerk and return against IDM-as-CAV's (the
    ``idm`` baseline) from the standard start, and its steady RMSE, each as the range over the runs (marked where
    some or all episodes had no steady state, whose figure is then the whole-episode RMSE); its jerk
    against IDM-as-CAV's with the layer, and the layer's largest share of steps; then the jerk against
    IDM-as-CAV's of every other baseline all the runs evaluated (e.g. ``cacc``, ``base``). Refuses runs whose
    cases were evaluated on other episodes, over another V2V link or with other measurement noise.
    """
    runs = [(str(d), _generalization(d)) for d in dirs]
    for _, g in runs:  # written before the link was an option: the perfect link
        g.setdefault("v2v", {"delay": 0.0, "loss": 0.0})
        g.setdefault("sensor_noise", {"gap": 0.0, "speed": 0.0, "tau": 0.0, "margin": 0.0})  # and exact measurements
        g["sensor_noise"].setdefault("filter", False)  # and no filter
    ref_dir, ref = runs[0]
    for d, g in runs[1:]:
        for key in ("seed", "episodes", "seconds", "v2v", "sensor_noise"):
            if g.get(key) != ref.get(key):
                raise ValueError(f"--generalization: {key} {g.get(key)!r} of {d!r} differs from {ref.get(key)!r} of "
                                 f"{ref_dir!r}; allowed: runs evaluated on the same episodes, link and noise")
    cases = [c for c in ref["results"] if all(c in g["results"] for _, g in runs)]
    if not cases:
        raise ValueError("--generalization: the runs have no case in common")
    skip = ("seconds", "policy", "policy_without_layer", "idm", "jerk_by_speed")
    # the other baselines every run evaluated (e.g. cacc on one seed only: left out)
    others = [k for k in ref["results"][cases[0]] if k not in skip
              and all(k in g["results"][c] for _, g in runs for c in cases)]
    link, noise = ref["v2v"], ref["sensor_noise"]
    head = ["case", "collisions", "gaps (m)", "jerk − IDM's", "steady RMSE", "return − IDM's",
            "with the layer: jerk − IDM's", "layer's share", *(f"{o}: jerk − IDM's" for o in others)]
    lines = [f"{len(runs)} run(s); {ref['episodes']} episodes of {ref['seconds']:g} s a case, evaluation seed "
             f"{ref['seed']}" + (f"; V2V {link['delay']:g} s late, {100 * link['loss']:g} % lost"
                                 if link["delay"] or link["loss"] else "")
             + (f"; measured with noise of {noise['gap']:g} m and {noise['speed']:g} m/s"
                + (f" correlated over {noise['tau']:g} s" if noise.get("tau") else "")
                + (", filtered" if noise.get("filter") else "")
                + (f", the layer's and envelope's margin {noise['margin']:g} standard deviations" if noise.get("margin") else "")
                if noise["gap"] or noise["speed"] else "") + ".", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for c in cases:
        coll, gmin, gmax, jerk, rmse, ret, layered, layer = 0, math.inf, -math.inf, [], [], [], [], []
        steady_in = []  # (episodes with a steady state, episodes) per run; None: not recorded
        other = {o: [] for o in others}
        for _, g in runs:
            x = g["results"][c]
            if "idm" not in x:
                raise ValueError(f"--generalization: case {c!r} has no idm baseline; allowed: runs made with "
                                 "--baselines idm (IDM-as-CAV, the reference of the bars)")
            free = x["policy_without_layer"]
            std = next(k for k in free if k.startswith("standard"))
            coll += x["policy"]["collisions"] + sum(v["collisions"] for v in free.values())
            gmin = min(gmin, *(v["min_gap_after"] for v in free.values()))
            gmax = max(gmax, *(v["max_head_gap"] for v in free.values()))
            idm = x["idm"]
            jerk.append(100.0 * (free[std]["jerk"] / idm["jerk"] - 1.0))
            k, n = free[std].get("steady_episodes"), free[std].get("episodes")
            steady_in.append(None if k is None or n is None else (k, n))
            rmse.append(free[std]["steady_only_rmse"] if k and k != n else free[std]["steady_rmse"])
            ret.append(free[std]["return"] - idm["return"])
            layered.append(100.0 * (x["policy"]["jerk"] / idm["jerk"] - 1.0))
            layer.append(100.0 * x["policy"]["intervention_rate"])
            for o in others:
                other[o].append(100.0 * (x[o]["jerk"] / idm["jerk"] - 1.0))
        cells = [c, str(coll), f"{gmin:.2f}–{gmax:.1f}", _span(jerk, "+.1f", " %"), _span(rmse, ".3f") + _steadiness(steady_in),
                 _span(ret, "+.1f"), _span(layered, "+.1f", " %"), f"{max(layer):.1f} %",
                 *(_span(v, "+.1f", " %") for v in other.values())]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> str:
    """Print a table of run directories' reports (``python -m mixed_traffic.evaluation.results -h``)."""
    import argparse

    p = argparse.ArgumentParser(prog="python -m mixed_traffic.evaluation.results",
                                description="Tables of evaluation reports (a run directory, its eval/ or report.json).")
    p.add_argument("runs", nargs="+", help="run directories")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--profiles", action="store_true", help="one row per run and head profile")
    mode.add_argument("--itself", action="store_true",
                      help="the policy with and without its layer, per profile and start")
    mode.add_argument("--paired", action="store_true",
                      help="episode-by-episode differences against --baseline, +- standard error")
    mode.add_argument("--generalization", action="store_true",
                      help="runs are --out directories of benchmarks/ring_generalization.py (one per seed): per case, "
                           "the ranges over them")
    p.add_argument("--baseline", default=None, help="a report to compare with (e.g. IDM-as-CAV's run directory)")
    a = p.parse_args(argv)
    if a.paired and a.baseline is None:
        p.error("--paired needs --baseline DIR (the report the runs are compared with, episode by episode)")
    if a.itself:
        out = itself_table(a.runs, a.baseline)
    elif a.paired:
        out = paired_table(a.runs, a.baseline)
    elif a.generalization:
        try:
            out = generalization_table(a.runs)
        except (ValueError, FileNotFoundError) as e:
            p.error(str(e))
    else:
        out = profile_table(a.runs) if a.profiles else table(a.runs)
    print(out)
    return out


if __name__ == "__main__":
    main()
