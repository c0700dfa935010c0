"""The scorecard of trained ring policies on every case they never trained on, in one command.

Runs ``ring_generalization.py`` for each run (one per seed) on each group of cases at the group's own
evaluation seed (held_out 2000, fresh 5000, fresh_2 7000, fresh_3 8000, fresh_4 9000, random_stops 10000,
fresh_5 12000, fresh_6 13000, fresh_7 14000, fresh_8 15000, fresh_9 16000, fresh_10 17000, fresh_11 18000, fresh_12 19000,
fresh_13 20000, fresh_14 21000, fresh_15 22000, fresh_16 23000, fresh_17 24000, fresh_17_fast 25000,
fresh_18 26000, fresh_18_fast 27000, fresh_19 28000, fresh_19_fast 29000, fresh_20 30000, fresh_20_fast 31000, fresh_21 32000,
fresh_21_fast 33000, fresh_22 34000, fresh_22_fast 35000, fresh_23 36000, fresh_23_fast 37000),
IDM-as-CAV beside every run and the classical controllers of ``--classical`` beside the first run only (they do
not depend on the policy: the same episodes in every run; ``zero_residual``, the first run's deployed controller
with its learned residual at zero, stands for every run's when they share their config, as seeds of one experiment
do). Then prints and writes
``OUT/scorecard.md``: per group, the table of
``python -m mixed_traffic.evaluation.results --generalization ... --bars`` (which acceptance bars each case
misses and on how many runs, and what each controller meets alone), a line counting the clean cases over
all groups, one on what the learned residual adds (``results.residual_line``) and the count by kind of head
(``results.kinds_table``: stop-and-go, braking to a standstill, above the training speeds, ...), and draws
``OUT/scorecard.png`` (per case, the policy's jerk and return against the bars' reference over
the runs, beside the classical controllers'). A group whose output is already there is not run again (``--rerun``
to run it anyway) unless it lacks a classical controller now asked for. ``--backend sumo`` evaluates every run and
classical controller in SUMO instead (``ring_generalization.py --backend sumo``)::

    python benchmarks/ring_scorecard.py --runs outputs/results/ring_safety_net_seed{0,1,2,3,4} --jobs 2 \\
        --out outputs/results/scorecard
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

SEEDS = {"held_out": 2000, "fresh": 5000, "fresh_2": 7000, "fresh_3": 8000, "fresh_4": 9000, "random_stops": 10000,
         "fresh_5": 12000, "fresh_6": 13000, "fresh_7": 14000, "fresh_8": 15000, "fresh_9": 16000,
         "fresh_10": 17000, "fresh_11": 18000, "fresh_12": 19000, "fresh_13": 20000, "fresh_14": 21000,
         "fresh_15": 22000, "fresh_16": 23000, "fresh_17": 24000, "fresh_17_fast": 25000,
         "fresh_18": 26000, "fresh_18_fast": 27000,
         "fresh_19": 28000, "fresh_19_fast": 29000,
         "fresh_20": 30000, "fresh_20_fast": 31000,
         "fresh_21": 32000, "fresh_21_fast": 33000, "fresh_22": 34000, "fresh_22_fast": 35000,
         "fresh_23": 36000, "fresh_23_fast": 37000}
CLASSICAL = ("idm:s0=7.0;v0=40.0;b=2.0", "cacc", "zero_residual")  # IDM_cav (b = 2), the best classical; CACC. They
# stand in for a colliding IDM-as-CAV as the reference of the jerk and return bars (results.REFERENCE_FALLBACK, the same
# two). zero_residual: the run's deployed controller with its learned residual at zero (results.ZERO_RESIDUAL)


def jobs(runs: list[str], groups: list[str], out: Path, *, episodes: int, seconds: float, classical,
         settings=(), backend: str = "torch", workers: int = 2) -> list[tuple]:
    """``(output directory, ring_generalization.py arguments)`` of every run and group (``backend="sumo"``: in SUMO,
    ``workers`` SUMO processes a job)."""
    todo = []
    for i, run in enumerate(runs):
        for g in groups:
            d = out / f"run{i}" / g
            args = ["--checkpoint", run, "--episodes", str(episodes), "--seconds", str(seconds), "--seed",
                    str(SEEDS[g]), "--cases", g, "--baselines", "idm", *(classical if i == 0 else ()), "--out", str(d),
                    *(["--set", *settings] if settings else []),
                    *(["--backend", "sumo", "--workers", str(workers)] if backend == "sumo" else [])]
            todo.append((d, args))
    return todo


def classical_for(run: str, asked: list[str] | None, *, cfg=None) -> list[str]:
    """The classical controllers to run beside ``run``: ``asked``, or by default :data:`CLASSICAL` less
    ``zero_residual`` where the run has no learned residual (a policy that drives alone); ``base`` or
    ``zero_residual`` asked for such a run fails here. ``cfg``: the run's checkpoint config, where already read."""
    from mixed_traffic.evaluation.policies import checkpoint_config

    cfg = checkpoint_config(run)[0] if cfg is None else cfg
    has_residual = "residual_idm" in cfg.transforms.chain
    if asked is None:
        return [c for c in CLASSICAL if c != "zero_residual" or has_residual]
    wrong = [c for c in asked if c in ("base", "zero_residual")]
    if wrong and not has_residual:
        raise SystemExit(f"--classical: {wrong} drive the run's classical base without its learned residual, and {run} "
                         "has none (its transforms.chain lacks residual_idm); allowed: classical controllers (e.g. "
                         "idm, cacc, 'idm:s0=6')")
    return list(asked)


def kinds_of_cases(run_cfg, groups: list[str], seconds: float) -> tuple[dict[str, tuple[str, ...]], str]:
    """``(case -> its kinds of head, the kind of the heads above the training speeds)``: ``ring_generalization``'s
    ``case_kinds`` at each case's group's evaluation seed, against the top speed of the training profile of the run
    whose checkpoint config is ``run_cfg``, and its ``KINDS`` entry for those heads; ``{}`` for the first where that
    profile has no top speed."""
    import importlib.util

    from mixed_traffic.profiles import make_profile

    env = run_cfg.env
    v_train = getattr(make_profile(env.profile, **(env.profile_kwargs or {})), "v_high", None)
    spec = importlib.util.spec_from_file_location("ring_generalization", Path(__file__).with_name("ring_generalization.py"))
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)
    if v_train is None:
        return {}, gen.ABOVE
    every = gen.cases(seconds)
    return ({c: gen.case_kinds(every[c], seed=SEEDS[g], v_train=float(v_train)) for g in groups for c in gen.GROUPS[g]},
            gen.ABOVE)


def main(argv=None) -> str:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--runs", nargs="+", required=True, help="run directories (one per seed) or final.pt files")
    p.add_argument("--groups", nargs="+", default=list(SEEDS), help=f"groups of cases (default: all of {list(SEEDS)})")
    p.add_argument("--episodes", type=int, default=4)
    p.add_argument("--seconds", type=float, default=200.0)
    p.add_argument("--classical", nargs="*", default=None,
                   help="classical controllers run beside the first run (default: IDM_cav (b = 2), CACC and "
                        "zero_residual, the run's deployed controller with its learned residual at zero, where the run "
                        "has one)")
    p.add_argument("--jobs", type=int, default=1, help="groups evaluated at once (processes)")
    p.add_argument("--rerun", action="store_true", help="run every group again, even where its output is there")
    p.add_argument("--rmse-bar", type=float, default=0.2)
    p.add_argument("--set", nargs="+", default=[], metavar="transforms.KEY=VALUE",
                   help="deploy-time settings of the runs' transforms, passed to ring_generalization.py --set (a "
                        "variant scored without retraining; use a new --out)")
    p.add_argument("--backend", choices=("torch", "sumo"), default="torch",
                   help="the simulator of every evaluation (default torch; sumo: ring_generalization.py --backend sumo, "
                        "about 15 times slower; use a new --out)")
    p.add_argument("--sumo-workers", type=int, default=2, help="with --backend sumo: SUMO processes a job (default 2)")
    p.add_argument("--out", required=True)
    a = p.parse_args(argv)
    unknown = sorted(set(a.groups) - set(SEEDS))
    if unknown:
        raise SystemExit(f"--groups: {unknown} are not groups; allowed: {list(SEEDS)}")
    missing = [r for r in a.runs if not Path(r).exists()]
    if missing:
        raise SystemExit(f"--runs: {missing} do not exist; allowed: run directories or final.pt files")
    if a.jobs < 1:
        raise SystemExit(f"--jobs: {a.jobs} is invalid; allowed: >= 1")
    if a.sumo_workers < 0:
        raise SystemExit(f"--sumo-workers: {a.sumo_workers} is invalid; allowed: >= 0 (0: SUMO in the job's process)")
    from mixed_traffic.evaluation.policies import checkpoint_config

    first_cfg = checkpoint_config(a.runs[0])[0]  # read once: the classical controllers and the kinds of head need it
    a.classical = classical_for(a.runs[0], a.classical, cfg=first_cfg)
    from mixed_traffic.evaluation.results import (
        beaten_line,
        generalization_table,
        kinds_table,
        residual_line,
        scorecard_margins,
        scorecard_plot,
    )

    out = Path(a.out)
    todo = jobs(a.runs, a.groups, out, episodes=a.episodes, seconds=a.seconds, classical=a.classical, settings=a.set,
                backend=a.backend, workers=a.sumo_workers)
    script = str(Path(__file__).with_name("ring_generalization.py"))
    if not a.rerun:  # a group already there must have been run with the same --set, or it would be scored as this one
        import json

        for d, _ in todo:
            f = d / "generalization.json"
            done = json.loads(f.read_text()) if f.is_file() else {"set": list(a.set), "backend": a.backend}
            if done.get("set", []) != list(a.set):
                raise SystemExit(f"--set: {d} was evaluated with --set {done.get('set', [])}, not {list(a.set)}; "
                                 "allowed: a new --out for another variant, or --rerun")
            if done.get("backend", "torch") != a.backend:  # written before --backend existed: torch
                raise SystemExit(f"--backend: {d} was evaluated on {done.get('backend', 'torch')}, not {a.backend}; "
                                 "allowed: a new --out for another simulator, or --rerun")

    def lacking(d: Path, args: list[str]) -> list[str]:
        """The baselines of ``args`` that the group's output in ``d`` lacks (evaluated before they were asked for)."""
        import json

        results = json.loads((d / "generalization.json").read_text())["results"]
        wanted = args[args.index("--baselines") + 1:args.index("--out")]
        return [b for b in wanted if any(b not in r for r in results.values())]

    def run(job):
        d, args = job
        if (d / "generalization.json").is_file() and not a.rerun:
            missing = lacking(d, args)
            if not missing:
                return d, 0
            sys.stdout.write(f"{d}: evaluated without {missing}; running it again\n")  # one write: jobs run at once
        d.mkdir(parents=True, exist_ok=True)
        with open(d / "log.txt", "w") as log:
            rc = subprocess.run([sys.executable, script, *args], stdout=log, stderr=subprocess.STDOUT).returncode
        return d, rc

    with ThreadPoolExecutor(max_workers=a.jobs) as pool:
        failed = [str(d) for d, rc in pool.map(run, todo) if rc != 0]
    if failed:
        raise SystemExit(f"ring_generalization.py failed for {failed}; see log.txt there")
    parts, margins = [], {}
    for g in a.groups:  # each group's runs judged once for the count and the figure, and tabled
        dirs = [out / f"run{i}" / g for i in range(len(a.runs))]
        margins[g] = scorecard_margins(dirs, rmse_bar=a.rmse_bar)
        parts += [f"## {g} (evaluation seed {SEEDS[g]})", "", generalization_table(dirs, bars=True, rmse_bar=a.rmse_bar), ""]
    clean = sum(e["clean"] for m in margins.values() for e in m)
    total = sum(len(m) for m in margins.values())
    beaten = [f"{e['case']} ({', '.join(e['classical_clean'])})" for m in margins.values() for e in m
              if not e["clean"] and e["classical_clean"]]
    residual = residual_line([e for m in margins.values() for e in m])
    kinds, above = kinds_of_cases(first_cfg, a.groups, a.seconds)
    by_kind = (["By the kind of head (those the acceptance names; a case may be of several kinds, or of none): the cases "
                "that meet every bar, the policy's on every run, each classical controller's without a layer on the "
                "same episodes.", "", kinds_table([e for m in margins.values() for e in m], kinds,
                                                  above=above), ""] if kinds else [])
    head = [f"# Scorecard: {len(a.runs)} run(s), {a.episodes} episodes of {a.seconds:g} s a case"
            + (" (every controller in SUMO)" if a.backend == "sumo" else ""), "",
            f"{clean} of {total} cases meet every bar on every run."
            + (" " + beaten_line(total - clean, beaten, "each table's last column: the bars each classical "
                                  "controller misses") if clean < total else ""), "", *([residual, ""] if residual else []),
            *by_kind]
    md = "\n".join(head + parts)
    (out / "scorecard.md").write_text(md)
    scorecard_plot(margins, out / "scorecard.png", title=f"Scorecard: {len(a.runs)} run(s), {clean} of {total} cases "
                                                          "meet every bar on every run; jerk and return against "
                                                          "IDM-as-CAV († its stand-in)")
    print(md)
    return md


if __name__ == "__main__":
    main()
