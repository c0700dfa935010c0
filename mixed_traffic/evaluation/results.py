"""Results table (docs/results.md) from evaluated run directories.

    python -m mixed_traffic.evaluation.results outputs/results/*/      # prints a markdown table
    python -m mixed_traffic.evaluation.results --itself RUN... --baseline IDM_RUN   # with / without the layer
    python -m mixed_traffic.evaluation.results --paired RUN... --baseline IDM_RUN   # episode by episode
    python -m mixed_traffic.evaluation.results --generalization GEN_DIR...       # held-out cases over seeds
    python -m mixed_traffic.evaluation.results --generalization GEN_DIR... --bars   # ... and the bars each misses

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


BARS = ("collisions", "gaps", "jerk", "steady RMSE", "return", "layer's share")
GAP_TOLERANCE = 1e-3  # m: a stopping envelope that holds 5 m exactly ends 5e-5 m under it in the env's float32


def _steady_rmse(r: dict) -> float:
    """A row's steady RMSE as the tables give it: the mean over the episodes with a steady state where only some
    had one, else the row's own (the whole-episode RMSE where none had)."""
    k, n = r.get("steady_episodes"), r.get("episodes")
    return r["steady_only_rmse"] if k and k != n else r["steady_rmse"]


def _rmse_met(r: dict, rmse_bar: float) -> bool | None:
    """Whether a row's steady RMSE (:func:`_steady_rmse`) meets ``rmse_bar``; None (not judged) where no episode
    had a steady state."""
    return None if r.get("steady_episodes") == 0 else _steady_rmse(r) <= rmse_bar + 1e-9


def _gaps_met(r: dict, s_min: float, s_max: float) -> bool:
    return r["min_gap_after"] >= s_min - GAP_TOLERANCE and r["max_head_gap"] <= s_max + GAP_TOLERANCE


def _standard(x: dict) -> dict:
    """The policy's row without its layer from the standard start, of one case of a generalization run."""
    free = x["policy_without_layer"]
    return free[next(k for k in free if k.startswith("standard"))]


ZERO_RESIDUAL = "zero_residual"
"""The baseline name of a run's deployed controller with its learned residual at zero
(``benchmarks/ring_generalization.py --baselines zero_residual``): the base's laws, envelope and catch-up, and the
drive-off cap and join, all as deployed. Beside the policy on the same episodes it shows what the learned part adds
(:func:`residual_line`)."""

REFERENCE_FALLBACK = ("idm:s0=7.0;v0=40.0;b=2.0", "cacc")
"""The classical controllers that take IDM-as-CAV's place as the reference of the jerk and return bars, in this
order, on a case where IDM-as-CAV collides: IDM_cav (b = 2) and CACC (``benchmarks/ring_scorecard.py`` evaluates
them beside its first run)."""


def bar_reference(x: dict, others: dict | None = None) -> tuple[str | None, dict | None]:
    """``(name, row)`` of the reference of the jerk and return bars on one case (``x``: a run's ``results[case]`` of
    ``benchmarks/ring_generalization.py``; ``others``: rows of classical controllers on the same case's episodes
    from other runs, by name).

    IDM-as-CAV (``idm``) where it completes every episode without a collision. Where it collides, its jerk and
    return cover only the steps before its collision (the episode ends there), not the episode the policy drives,
    so the first of :data:`REFERENCE_FALLBACK` that completes every episode takes its place; ``(None, None)`` where
    none does or none was evaluated (the two bars are then not judged)."""
    if x["idm"]["collisions"] == 0:
        return "idm", x["idm"]
    pool = {**(others or {}), **{k: x[k] for k in REFERENCE_FALLBACK if k in x}}
    name = next((k for k in REFERENCE_FALLBACK if k in pool and pool[k]["collisions"] == 0), None)
    return name, pool.get(name)


def _shown_reference(x: dict, others: dict | None) -> tuple[str | None, dict]:
    """``(name, row)`` the tables and the figure compare with: :func:`bar_reference`'s, or IDM-as-CAV's own
    figures where no stand-in completes (the bars then are not judged, and the name is None)."""
    name, ref = bar_reference(x, others)
    return name, x["idm"] if ref is None else ref


def case_bars(x: dict, *, s_min: float = 5.0, s_max: float = 40.0, rmse_bar: float = 0.2,
              share_bar: float = 0.05, others: dict | None = None) -> dict[str, bool | None]:
    """Which of the ring's acceptance bars one run of ``benchmarks/ring_generalization.py`` meets on one case
    (``x``: its ``results[case]``). The policy with its layer and without it from every start: no collision;
    without it, the gaps after the warm-up within ``[s_min, s_max]`` (to :data:`GAP_TOLERANCE`); from the
    standard start, with the layer and without it, a jerk at or below IDM-as-CAV's, a return at or above it and
    a steady RMSE at most ``rmse_bar`` (None, not judged, where no episode had a steady state; on the episodes
    that had one where only some had); the layer's share of steps at most ``share_bar``. Where IDM-as-CAV
    collides, the jerk and return bars compare with :func:`bar_reference`'s controller (``others``: its rows
    from other runs on the same episodes)."""
    free, pol, std = x["policy_without_layer"], x["policy"], _standard(x)
    _, ref = bar_reference(x, others)
    return {"collisions": pol["collisions"] + sum(v["collisions"] for v in free.values()) == 0,
            "gaps": all(_gaps_met(v, s_min, s_max) for v in free.values()),
            "jerk": None if ref is None else std["jerk"] <= ref["jerk"] and pol["jerk"] <= ref["jerk"],
            "steady RMSE": _rmse_met(std, rmse_bar),
            "return": None if ref is None else std["return"] >= ref["return"] and pol["return"] >= ref["return"],
            "layer's share": pol["intervention_rate"] <= share_bar + 1e-9}


def row_bars(r: dict, ref: dict | None, *, s_min: float = 5.0, s_max: float = 40.0,
             rmse_bar: float = 0.2) -> dict[str, bool | None]:
    """The same bars for one controller's row of a case (``r``: a classical baseline's, or the policy's from one
    start) against the reference's row (``ref``: :func:`bar_reference`'s, IDM-as-CAV's where it completes; None:
    those two bars not judged), without a layer: what a reader holds the policy's against."""
    return {"collisions": r["collisions"] == 0, "gaps": _gaps_met(r, s_min, s_max),
            "jerk": None if ref is None else r["jerk"] <= ref["jerk"], "steady RMSE": _rmse_met(r, rmse_bar),
            "return": None if ref is None else r["return"] >= ref["return"], "layer's share": True}


def _classical_pool(runs, case: str) -> dict:
    """The rows of :data:`REFERENCE_FALLBACK`'s controllers on ``case`` from whichever run evaluated them (a
    classical controller drives the same episodes in every run)."""
    pool = {}
    for _, g in runs:
        pool.update({k: g["results"][case][k] for k in REFERENCE_FALLBACK if k in g["results"][case] and k not in pool})
    return pool


def classical_rows(runs, case: str, names, *, rmse_bar: float = 0.2) -> dict[str, tuple[dict, dict]]:
    """``{name: (row, bars)}`` of each controller of ``names`` (IDM-as-CAV ``idm`` and the other baselines) that
    some run evaluated on ``case`` without a layer (a classical controller drives the same episodes in every run,
    so the first run's row that has it stands for all), with :func:`row_bars` against the first run's bars'
    reference (:func:`bar_reference`): the bars each classical controller misses, beside the policy's misses."""
    pool = _classical_pool(runs, case)
    _, ref = bar_reference(runs[0][1]["results"][case], pool)
    out = {}
    for o in names:
        row = next((g["results"][case][o] for _, g in runs if o in g["results"][case]), None)
        if row is not None:
            out[o] = (row, row_bars(row, ref, rmse_bar=rmse_bar))
    return out


def _baselines(runs, cases) -> list[str]:
    """The baselines other than IDM-as-CAV that some run evaluated on every case, in the order first met (a
    classical controller drives the same episodes in every run)."""
    skip = ("seconds", "policy", "policy_without_layer", "idm", "jerk_by_speed", "jerk_by_time")
    return list(dict.fromkeys(k for _, g in runs for k in g["results"][cases[0]] if k not in skip
                              and all(k in g["results"][c] for c in cases)))


def _meets_every_bar(bars: dict) -> bool:
    return not any(v is False for v in bars.values())


def _classical_cell(rows: dict[str, tuple[dict, dict]]) -> str:
    """``idm: gaps 25.5–51.0 m, steady RMSE; cacc: jerk``: the bars each classical controller misses (``–``: none),
    the gaps with their span where they leave the band."""
    def missed(r, bars):
        return [f"gaps {r['min_gap_after']:.1f}–{r['max_head_gap']:.1f} m" if b == "gaps" else b
                for b in BARS if bars.get(b) is False]
    return "; ".join(f"{o}: {', '.join(missed(r, bars)) or '–'}" for o, (r, bars) in rows.items())


def beaten_line(missed: int, beaten: list[str], where: str) -> str:
    """The sentence on the policy's ``missed`` cases that a classical controller meets every bar of (``beaten``:
    ``case (controllers)``)."""
    if not beaten:
        return (f"Where the policy misses a bar ({missed} of the cases), no classical controller meets every bar on "
                f"the same episodes either ({where}).")
    rest = missed - len(beaten)
    return (f"Where the policy misses a bar ({missed} of the cases), a classical controller meets every bar on the "
            f"same episodes on {len(beaten)}: {', '.join(beaten)}"
            + (f"; on the other {rest}, none does ({where})." if rest else f" ({where})."))


def _missed(per_run: list[dict]) -> str:
    """The bars some run misses, each with on how many runs (``jerk 3 of 5``); ``–`` where every run meets every
    bar it is judged on (a steady RMSE bar that does not apply is not a miss)."""
    n = len(per_run)
    out = [f"{bar} {m} of {n}" for bar in BARS if (m := sum(r[bar] is False for r in per_run))]
    return "; ".join(out) if out else "–"


def _load_runs(dirs) -> tuple[list[tuple[str, dict]], list[str]]:
    """``([(dir, generalization.json)], cases in common)`` of runs of ``benchmarks/ring_generalization.py``;
    refuses runs evaluated on other episodes, over another V2V link or with other measurement noise."""
    runs = [(str(d), _generalization(d)) for d in dirs]
    for _, g in runs:  # written before the link was an option: the perfect link
        g.setdefault("v2v", {"delay": 0.0, "loss": 0.0})
        g.setdefault("sensor_noise", {"gap": 0.0, "speed": 0.0, "tau": 0.0, "margin": 0.0})  # and exact measurements
        g["sensor_noise"].setdefault("filter", False)  # and no filter
        g.setdefault("set", [])  # and the run's own transforms
    ref_dir, ref = runs[0]
    for d, g in runs[1:]:
        for key in ("seed", "episodes", "seconds", "v2v", "sensor_noise", "set"):
            if g.get(key) != ref.get(key):
                raise ValueError(f"--generalization: {key} {g.get(key)!r} of {d!r} differs from {ref.get(key)!r} of "
                                 f"{ref_dir!r}; allowed: runs evaluated on the same episodes, link and noise, with "
                                 "the same --set")
    cases = [c for c in ref["results"] if all(c in g["results"] for _, g in runs)]
    if not cases:
        raise ValueError("--generalization: the runs have no case in common")
    return runs, cases


def clean_cases(dirs, *, rmse_bar: float = 0.2) -> tuple[int, int]:
    """``(cases that meet every bar on every run, cases)`` of runs of ``benchmarks/ring_generalization.py``
    (:func:`case_bars`, as :func:`scorecard_margins` judges them): the count the ``bars`` table of
    :func:`generalization_table` ends with."""
    margins = scorecard_margins(dirs, rmse_bar=rmse_bar)
    return sum(e["clean"] for e in margins), len(margins)


def generalization_table(dirs, *, bars: bool = False, rmse_bar: float = 0.2) -> str:
    """Per case, over several runs (seeds) of ``benchmarks/ring_generalization.py`` on the same episodes.

    Columns, the policy without its layer: the gaps after the warm-up over every start and run (smallest gap,
    largest head gap); collisions with and without the layer; its jerk and return against IDM-as-CAV's (the
    ``idm`` baseline) from the standard start, and its steady RMSE, each as the range over the runs (marked where
    some or all episodes had no steady state, whose figure is then the whole-episode RMSE); its jerk
    against IDM-as-CAV's with the layer, and the layer's largest share of steps; then the jerk against
    IDM-as-CAV's of every other baseline the runs evaluated (e.g. ``cacc``, ``base``): a classical controller
    drives the same episodes in every run, so one run that evaluated it on every case is enough, and its range is
    over the runs that did. Where IDM-as-CAV collides on a case (its figures then cover only the steps before its
    collision), that row's columns against IDM's are against :func:`bar_reference`'s stand-in instead, marked
    with a note under the table. With ``bars``, a column names the acceptance bars missed and on how many runs
    (:func:`case_bars`, the steady RMSE at most ``rmse_bar``), a last one the bars each classical controller misses
    on the same episodes (:func:`classical_rows`: IDM-as-CAV's own gaps, say, where it leaves the band), and lines
    after the table count the cases that meet every bar on every run, and those of the policy's misses where a
    classical controller meets every bar. Refuses runs whose cases were evaluated on other episodes, over another V2V
    link or with other measurement noise.
    """
    runs, cases = _load_runs(dirs)
    ref = runs[0][1]
    others = _baselines(runs, cases)
    link, noise = ref["v2v"], ref["sensor_noise"]
    head = ["case", "collisions", "gaps (m)", "jerk − IDM's", "steady RMSE", "return − IDM's",
            "with the layer: jerk − IDM's", "layer's share", *(f"{o}: jerk − IDM's" for o in others),
            *([f"bars missed (of {len(runs)} runs)", "classical controllers: bars missed"] if bars else [])]
    lines = [f"{len(runs)} run(s); {ref['episodes']} episodes of {ref['seconds']:g} s a case, evaluation seed "
             f"{ref['seed']}" + (f"; V2V {link['delay']:g} s late, {100 * link['loss']:g} % lost"
                                 if link["delay"] or link["loss"] else "")
             + (f"; measured with noise of {noise['gap']:g} m and {noise['speed']:g} m/s"
                + (f" correlated over {noise['tau']:g} s" if noise.get("tau") else "")
                + (", filtered" if noise.get("filter") else "")
                + (f", the layer's and envelope's margin {noise['margin']:g} standard deviations" if noise.get("margin") else "")
                if noise["gap"] or noise["speed"] else "")
             + (f"; deployed with {' '.join(ref['set'])}" if ref["set"] else "") + ".", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    clean, notes, beaten, missed_cases = 0, [], [], 0
    for c in cases:
        pool = _classical_pool(runs, c)
        coll, gmin, gmax, jerk, rmse, ret, layered, layer = 0, math.inf, -math.inf, [], [], [], [], []
        crashed = set()  # the references that stood in for a colliding IDM-as-CAV, or None where none could
        met = []
        steady_in = []  # (episodes with a steady state, episodes) per run; None: not recorded
        other = {o: [] for o in others}
        for _, g in runs:
            x = g["results"][c]
            if "idm" not in x:
                raise ValueError(f"--generalization: case {c!r} has no idm baseline; allowed: runs made with "
                                 "--baselines idm (IDM-as-CAV, the reference of the bars)")
            free, std = x["policy_without_layer"], _standard(x)
            name, idm = _shown_reference(x, pool)
            if name != "idm":
                crashed.add(name)
            coll += x["policy"]["collisions"] + sum(v["collisions"] for v in free.values())
            gmin = min(gmin, *(v["min_gap_after"] for v in free.values()))
            gmax = max(gmax, *(v["max_head_gap"] for v in free.values()))
            jerk.append(100.0 * (std["jerk"] / idm["jerk"] - 1.0))
            k, n = std.get("steady_episodes"), std.get("episodes")
            steady_in.append(None if k is None or n is None else (k, n))
            rmse.append(_steady_rmse(std))
            ret.append(std["return"] - idm["return"])
            layered.append(100.0 * (x["policy"]["jerk"] / idm["jerk"] - 1.0))
            layer.append(100.0 * x["policy"]["intervention_rate"])
            for o in others:
                if o in x:
                    other[o].append(100.0 * (x[o]["jerk"] / idm["jerk"] - 1.0))
            met.append(case_bars(x, rmse_bar=rmse_bar, others=pool))
        if crashed:
            n_idm = x["idm"]
            stand_in = ", ".join(sorted(k for k in crashed if k))
            notes.append(f"† {c}: IDM-as-CAV collided on {n_idm['collisions']} of {n_idm.get('episodes', '?')} "
                         "episodes; its jerk and return cover only the steps before its collision, so this row's "
                         "columns against IDM's, and the jerk and return bars, are against "
                         + (f"{stand_in} (the first classical controller that completes every episode)" if stand_in
                            else "IDM's all the same: no classical controller completed every episode (those two "
                                 "bars not judged)") + ".")
        cells = [c + (" †" if crashed else ""), str(coll), f"{gmin:.2f}–{gmax:.1f}", _span(jerk, "+.1f", " %"), _span(rmse, ".3f") + _steadiness(steady_in),
                 _span(ret, "+.1f"), _span(layered, "+.1f", " %"), f"{max(layer):.1f} %",
                 *(_span(v, "+.1f", " %") for v in other.values())]
        if bars:
            cells.append(_missed(met))
            clean += cells[-1] == "–"
            crows = classical_rows(runs, c, ["idm", *others], rmse_bar=rmse_bar)
            cells.append(_classical_cell(crows))
            if cells[-2] != "–":
                missed_cases += 1
                winners = [o for o, (_, b) in crows.items() if _meets_every_bar(b)]
                if winners:
                    beaten.append(f"{c} ({', '.join(winners)})")
        lines.append("| " + " | ".join(cells) + " |")
    lines += [""] + notes if notes else []
    if bars:
        lines += ["", f"{clean} of {len(cases)} cases meet every bar on every run (the steady RMSE at most "
                      f"{rmse_bar:g} m/s where the head settles; the gaps within [5, 40] m after the warm-up)."]
        first = runs[0][1]["results"]

        def clean_on(rows) -> int:  # cases where a controller's rows meet every bar (rows: (row, reference's))
            return sum(_meets_every_bar(row_bars(r, i, rmse_bar=rmse_bar)) for r, i in rows)

        refs = {c: bar_reference(first[c], _classical_pool(runs, c))[1] for c in cases}
        counts = [f"the policy (the first run) {clean_on((_standard(first[c]), refs[c]) for c in cases)}"]
        for o in ["idm", *others]:
            g = next((g["results"] for _, g in runs if all(o in g["results"][c] for c in cases)), None)
            if g is not None:
                counts.append(f"{o} {clean_on((g[c][o], refs[c]) for c in cases)}")
        lines.append(f"From the standard start, without a layer, on the same episodes, the controllers meet every bar "
                     f"on: {', '.join(counts)} of the {len(cases)} cases.")
        if missed_cases:
            lines.append(beaten_line(missed_cases, beaten, "the last column"))
    return "\n".join(lines)


def scorecard_margins(dirs, *, rmse_bar: float = 0.2) -> list[dict]:
    """Per case of runs of ``benchmarks/ring_generalization.py`` on the same episodes (one per seed): the policy's
    jerk and return against the reference of the bars (:func:`bar_reference`) from the standard start without its
    layer, one value per run, and each classical controller's on the same episodes; what :func:`scorecard_plot`
    draws. Each entry: ``case``, ``reference`` (its name), ``clean`` (every bar met on every run, :func:`case_bars`),
    ``jerk`` / ``return`` (the policy's, % of the reference's, per run), ``classical`` (name -> ``(jerk %,
    return %)``, each that completes every episode), ``baselines`` (every classical controller evaluated on the case)
    and ``classical_clean`` (the classical controllers that meet
    every bar on the case without a layer, :func:`row_bars`): IDM-as-CAV, :data:`REFERENCE_FALLBACK`'s and every
    other baseline the runs evaluated, such as :data:`ZERO_RESIDUAL`."""
    runs, cases = _load_runs(dirs)
    others = _baselines(runs, cases)
    out = []
    for c in cases:
        pool = _classical_pool(runs, c)
        jerk, ret, met = [], [], []
        name = None
        for _, g in runs:
            x = g["results"][c]
            name, ref = _shown_reference(x, pool)
            std = _standard(x)
            jerk.append(100.0 * (std["jerk"] / ref["jerk"] - 1.0))
            ret.append(100.0 * (std["return"] - ref["return"]) / abs(ref["return"]))
            met.append(case_bars(x, rmse_bar=rmse_bar, others=pool))
        first = runs[0][1]["results"][c]
        _, ref = _shown_reference(first, pool)
        crows = classical_rows(runs, c, ["idm", *pool, *(o for o in others if o not in pool)], rmse_bar=rmse_bar)
        classical = {k: (100.0 * (r["jerk"] / ref["jerk"] - 1.0), 100.0 * (r["return"] - ref["return"]) / abs(ref["return"]))
                     for k, (r, _) in crows.items() if r["collisions"] == 0 and r is not ref}
        out.append({"case": c, "reference": name, "clean": all(v is not False for m in met for v in m.values()),
                    "jerk": jerk, "return": ret, "classical": classical, "baselines": list(crows),
                    "classical_clean": [k for k, (_, bars) in crows.items() if _meets_every_bar(bars)]})
    return out


def residual_line(margins: list[dict]) -> str:
    """The sentence on what the learned residual adds (``margins``: :func:`scorecard_margins`'s entries, of every
    group): beside the deployed controller with the residual at zero (:data:`ZERO_RESIDUAL`, on the same episodes
    without a layer), the cases where the policy meets every bar on every run and that controller misses one, the
    reverse, and on how many the policy's jerk is below its jerk on every run; ``""`` where it was not evaluated."""
    with_zero = [e for e in margins if ZERO_RESIDUAL in e.get("baselines", ())]
    if not with_zero:
        return ""
    zero_clean = [e["case"] for e in with_zero if ZERO_RESIDUAL in e["classical_clean"]]
    only_policy = [e["case"] for e in with_zero if e["clean"] and e["case"] not in zero_clean]
    only_zero = [e["case"] for e in with_zero if not e["clean"] and e["case"] in zero_clean]
    jerks = [(e["case"], e["jerk"], e["classical"][ZERO_RESIDUAL][0]) for e in with_zero
             if ZERO_RESIDUAL in e["classical"]]
    lower = sum(max(j) < z for _, j, z in jerks)
    higher = [c for c, j, z in jerks if min(j) > z]
    return (f"Beside its learned residual at zero ({ZERO_RESIDUAL}: the deployed laws, envelope, drive-off cap and join "
            f"alone, on the same episodes, no layer), the policy meets every bar on every run on {len(only_policy)} "
            f"cases where that controller misses one, and that controller on {len(only_zero)} where the policy misses "
            "one" + (f" ({', '.join(only_zero)})" if only_zero else "")
            + f"; both meet every bar on {len(zero_clean) - len(only_zero)}. The policy's jerk is below its residual-free "
            f"jerk on every run on {lower} of {len(jerks)} cases"
            + (f", above it on every run on {len(higher)} ({', '.join(higher)})" if higher else "") + ".")


def kinds_table(margins: list[dict], kinds: dict[str, tuple[str, ...]], *, above: str) -> str:
    """The scorecard's count by kind of head (``margins``: :func:`scorecard_margins`'s entries, of every group;
    ``kinds``: case -> the kinds it is, a case may be of several or of none; ``above``: the kind of the heads faster
    than the training's, whose complement is the table's "within the training speeds" row). Per kind, a markdown row
    of how many of its cases meet every bar on every run (the policy) and without a layer on the same episodes (each
    classical controller evaluated on all of them: IDM-as-CAV, the stand-ins, :data:`ZERO_RESIDUAL`), then the rows
    "within the training speeds", "other heads within the training speeds" (of no kind) and "every case". A case
    missing from ``kinds`` raises ``KeyError`` naming it."""
    missing = [e["case"] for e in margins if e["case"] not in kinds]
    if missing:
        raise KeyError(f"kinds_table: no kinds for the cases {missing}")
    controllers = [c for c in dict.fromkeys(b for e in margins for b in e.get("baselines", ()))
                   if all(c in e.get("baselines", ()) for e in margins)]
    names = list(dict.fromkeys(k for e in margins for k in kinds[e["case"]]))
    rows = [(k, [e for e in margins if k in kinds[e["case"]]]) for k in names]
    rows += [("within the training speeds", [e for e in margins if above not in kinds[e["case"]]]),
             ("other heads within the training speeds", [e for e in margins if not kinds[e["case"]]]),
             ("every case", list(margins))]

    def cell(entries, clean) -> str:
        return f"{sum(map(clean, entries))} of {len(entries)}"

    lines = ["| kind of head | cases | the policy (every run) | " + " | ".join(controllers) + " |",
             "|---|---|---|" + "---|" * len(controllers)]
    for kind, entries in rows:
        if entries:
            lines.append(f"| {kind} | {len(entries)} | {cell(entries, lambda e: e['clean'])} | "
                         + " | ".join(cell(entries, lambda e, c=c: c in e["classical_clean"]) for c in controllers)
                         + " |")
    return "\n".join(lines)


def scorecard_plot(groups: dict, path, *, title: str = "") -> None:
    """One figure of the scorecard (``groups``: group name -> that group's :func:`scorecard_margins`): per case, the
    policy's jerk and return against the bars' reference (IDM-as-CAV, or its stand-in where it collides, marked †)
    as the span over the runs, green where the case meets every bar on every run, red where it does not, and each
    classical controller that completes every episode as a marker. A bar is met below 0 % (jerk) or above it
    (return). A case the policy misses where a classical controller meets every bar (``classical_clean``) is marked
    ‡ in bold."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    entries, bounds = [], []
    for g, margins in groups.items():
        start = len(entries)
        entries += margins
        bounds.append((g, start, len(entries)))
    n = len(entries)
    fig, axes = plt.subplots(2, 1, figsize=(max(10.0, 0.42 * n + 2.0), 8.0), sharex=True)
    markers = {"idm": ("x", "black", "IDM-as-CAV"), "idm:s0=7.0;v0=40.0;b=2.0": ("^", "tab:blue", "IDM_cav (b = 2)"),
               "cacc": ("s", "tab:purple", "CACC"), ZERO_RESIDUAL: ("D", "tab:orange", "the learned residual at zero")}
    for ax, key, label in ((axes[0], "jerk", "jerk − reference's (%)"), (axes[1], "return", "return − reference's (%)")):
        for i, e in enumerate(entries):
            lo, hi = min(e[key]), max(e[key])
            color = "tab:green" if e["clean"] else "tab:red"
            ax.plot([i, i], [lo, hi], color=color, lw=5, solid_capstyle="butt")
            ax.plot([i] * len(e[key]), e[key], "_", color=color, ms=13, mew=2.5)  # each run, visible on a narrow span
            for k, (j, r) in e["classical"].items():
                m, col, _ = markers.get(k, ("o", "grey", k))
                ax.plot(i, j if key == "jerk" else r, m, color=col, ms=6, mfc="none" if m == "s" else col)
        ax.axhline(0.0, color="black", lw=0.8)
        ax.set_ylabel(label)
        ax.grid(axis="y", alpha=0.3)
        for g, a, b in bounds:
            ax.axvline(b - 0.5, color="grey", lw=0.6, ls=":")
            if key == "jerk":
                ax.text((a + b - 1) / 2, 1.01, g, transform=ax.get_xaxis_transform(), ha="center", va="bottom", fontsize=9)
    handles = [plt.Line2D([], [], color="tab:green", lw=5, label="the policy (each run, and their span): every bar met"),
               plt.Line2D([], [], color="tab:red", lw=5, label="the policy: some bar missed")]
    seen = {k for e in entries for k in e["classical"]}
    handles += [plt.Line2D([], [], marker=m, color=c, ls="", mfc="none" if m == "s" else c, label=lab)
                for k, (m, c, lab) in markers.items() if k in seen]
    fig.legend(handles=handles, fontsize=8, loc="upper center", ncol=len(handles), bbox_to_anchor=(0.5, 0.955),
               frameon=False)
    axes[1].set_xticks(range(n))
    lost = [not e["clean"] and bool(e.get("classical_clean")) for e in entries]  # a classical controller met them all
    axes[1].set_xticklabels([e["case"] + (" †" if e["reference"] != "idm" else "") + (" ‡" if x else "")
                             for e, x in zip(entries, lost)], rotation=70, ha="right", fontsize=8)
    for label, x in zip(axes[1].get_xticklabels(), lost):
        if x:
            label.set_fontweight("bold")
    if any(lost):
        fig.text(0.995, 0.005, "‡ the policy misses a bar where a classical controller meets every bar on the same "
                 "episodes", ha="right", va="bottom", fontsize=8)
    fig.suptitle(title or "Scorecard: jerk and return against IDM-as-CAV († against its stand-in, where it collides)",
                 fontsize=11)
    fig.tight_layout(rect=(0, 0, 1, 0.93))
    fig.savefig(path, dpi=110)
    plt.close(fig)


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
    p.add_argument("--bars", action="store_true",
                   help="with --generalization: a column naming the acceptance bars each case misses, on how many runs")
    p.add_argument("--rmse-bar", type=float, default=0.2, help="with --bars: the steady RMSE bar (m/s)")
    a = p.parse_args(argv)
    if a.paired and a.baseline is None:
        p.error("--paired needs --baseline DIR (the report the runs are compared with, episode by episode)")
    if a.bars and not a.generalization:
        p.error("--bars needs --generalization (the bars are judged on ring_generalization.py's cases)")
    if not a.rmse_bar > 0:
        p.error(f"--rmse-bar {a.rmse_bar} is invalid; allowed: > 0 (m/s)")
    if a.itself:
        out = itself_table(a.runs, a.baseline)
    elif a.paired:
        out = paired_table(a.runs, a.baseline)
    elif a.generalization:
        try:
            out = generalization_table(a.runs, bars=a.bars, rmse_bar=a.rmse_bar)
        except (ValueError, FileNotFoundError) as e:
            p.error(str(e))
    else:
        out = profile_table(a.runs) if a.profiles else table(a.runs)
    print(out)
    return out


if __name__ == "__main__":
    main()
