"""A trained ring policy on the SUMO backend, side by side with the torch backend.

Loads a checkpoint (its own env and transform chain, e.g. the SafetyLayer it was trained
with), evaluates it on SUMO (speed mode 0 unless ``--sumo-safety``) with
:func:`mixed_traffic.evaluation.sumo.evaluate_on_sumo`, and on the torch backend on the
very same episodes (same profiles, same per-episode seeds ``seed + e``, same episode
length) with :func:`mixed_traffic.evaluation.sumo.evaluate_on_torch_seeds`. Writes

    OUT/report.json, OUT/report.md, OUT/<profile>.png, OUT/training_curves.png   (SUMO)
    OUT/torch/report.json, OUT/torch/report.md, OUT/torch/<profile>.png          (torch, same episodes)
    OUT/comparison.md, OUT/comparison.json                                        (key metrics, both)

and prints the comparison table.

    .venv/bin/python benchmarks/ring_policy_on_sumo.py \
        --checkpoint outputs/results/ring_lagrangian_ppo_seed0/final.pt \
        --episodes 4 --seconds 120 --out outputs/results/ring_lagrangian_ppo_seed0/eval_sumo

With the run's ``eval.without_layer`` (the default) each profile also runs without the safety layer from the
standard start and each ``eval.close_starts`` gap on both backends, so the reports hold the layer-free bars; that is
four times the episodes, which ``--with-layer-only`` skips.

``--set transforms.KEY=VALUE ...`` deploys the run with other settings of its transforms on both backends, as
``ring_generalization.py --set`` does (a bad key or value stops the script, naming it, before SUMO starts).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # ring_generalization's --set, loaded by path too


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--checkpoint", required=True, help="final.pt, checkpoints/latest.pt or a run directory")
    p.add_argument("--episodes", type=int, default=4, help="episodes per profile (default 4)")
    p.add_argument("--profiles", nargs="+", default=None, help="head profiles (default: the config's eval.profiles)")
    p.add_argument("--seconds", type=float, default=None,
                   help="episode length in s (default: eval.episode_seconds, else 120)")
    p.add_argument("--seed", type=int, default=None, help="evaluation seed; episode e uses seed + e (default eval.seed)")
    p.add_argument("--workers", type=int, default=2, help="SUMO processes (ParallelEnv workers, default 2)")
    p.add_argument("--sumo-safety", action="store_true", help="SUMO speed mode 95 instead of 0")
    p.add_argument("--no-torch", action="store_true", help="skip the torch comparison")
    p.add_argument("--with-layer-only", action="store_true",
                   help="skip the policy's runs without its layer (eval.without_layer=false): a quarter of the SUMO "
                        "time, and no layer-free bars in the reports")
    p.add_argument("--set", nargs="+", default=[], metavar="transforms.KEY=VALUE",
                   help="deploy-time settings of the run's transforms (e.g. transforms.residual.envelope_fade_slack=1.0):"
                        " a variant evaluated on both backends without retraining")
    p.add_argument("--out", required=True, help="output directory")
    return p.parse_args(argv)


def main(argv=None) -> dict:
    args = parse_args(argv)
    from ring_generalization import apply_set, parse_set

    settings_set = parse_set(args.set)  # a bad item stops here, before SUMO starts
    import torch

    from mixed_traffic.evaluation.policies import checkpoint_config, policy_factory_from_state
    from mixed_traffic.evaluation.report import write_report
    from mixed_traffic.evaluation.sumo import (
        comparison_markdown,
        comparison_rows,
        eval_config,
        evaluate_on_sumo,
        evaluate_on_torch_seeds,
    )

    torch.set_num_threads(1)
    cfg, state = checkpoint_config(args.checkpoint)
    cfg = eval_config(apply_set(cfg, settings_set), args.seconds)
    if args.with_layer_only:
        cfg.eval.without_layer = False
    factory = policy_factory_from_state(cfg, state)
    ck = Path(args.checkpoint)
    run_dir = ck if ck.is_dir() else (ck.parent.parent if ck.parent.name == "checkpoints" else ck.parent)
    out = Path(args.out)
    kw = dict(profiles=args.profiles, episodes=args.episodes, seed=args.seed)
    secs = float(cfg.eval.episode_seconds)
    mode = 95 if args.sumo_safety else 0

    t0 = time.perf_counter()
    rep_s, tr_s = evaluate_on_sumo(cfg, policy_factory=factory, workers=args.workers, sumo_safety=args.sumo_safety,
                                   **kw)
    wall_s = time.perf_counter() - t0
    rep_s.update(policy=str(args.checkpoint), transforms=list(cfg.transforms.chain), set=list(args.set),
                 wall_seconds=wall_s)
    title = f"{args.checkpoint} on SUMO (speed mode {mode}), {secs:g} s episodes"
    write_report(rep_s, out, tr_s, title=title, plot_episode=cfg.eval.plot_episode, s_min=cfg.eval.s_min,
                 s_max=cfg.eval.s_max, run_dir=run_dir)
    _note(out / "report.md", rep_s, wall_s)
    reports = {"sumo": rep_s}

    if not args.no_torch:
        t0 = time.perf_counter()
        rep_t, tr_t = evaluate_on_torch_seeds(cfg, policy_factory=factory, **kw)
        wall_t = time.perf_counter() - t0
        rep_t.update(policy=str(args.checkpoint), transforms=list(cfg.transforms.chain), set=list(args.set),
                     wall_seconds=wall_t)
        write_report(rep_t, out / "torch", tr_t, title=f"{args.checkpoint} on torch, {secs:g} s episodes",
                     plot_episode=cfg.eval.plot_episode, s_min=cfg.eval.s_min, s_max=cfg.eval.s_max)
        _note(out / "torch" / "report.md", rep_t, wall_t)
        reports = {"torch": rep_t, "sumo": rep_s}

    table = comparison_markdown(reports)
    deployed = f" with {' '.join(args.set)}" if args.set else ""
    head = (f"policy `{args.checkpoint}`{deployed}, profiles {list(rep_s['profiles'])}, {rep_s['episodes_per_profile']} "
            f"episodes each, seeds {rep_s['episode_seeds']}, {secs:g} s episodes, SUMO speed mode {mode}; "
            "min gap = min over episodes, max head gap = max, others = mean over episodes")
    (out / "comparison.md").write_text(head + "\n\n" + table + "\n")
    (out / "comparison.json").write_text(json.dumps(comparison_rows(reports), indent=2))
    print(head)
    print(table)
    for name, rep in reports.items():
        acc = rep["acceptance"]
        print(f"{name}: pass={acc['pass']} (zero_collisions={acc['zero_collisions']}, "
              f"gap_within_bounds={acc['gap_within_bounds']}, steady RMSE {acc['steady_speed_rmse']:.3f}), "
              f"wall {rep['wall_seconds']:.0f} s")
    print(f"reports: {out / 'report.md'}" + ("" if args.no_torch else f", {out / 'torch' / 'report.md'}"))
    return reports


def _note(md: Path, rep: dict, wall: float) -> None:
    extra = (f"\nBackend: {rep['backend']}"
             + (f" (speed mode {rep['speed_mode']}, {rep['workers']} SUMO processes)" if rep["backend"] == "sumo" else "")
             + f"; episode length {rep['episode_seconds']:g} s; episode seeds {rep['episode_seeds']}; "
             f"wall {wall:.0f} s.\n")
    md.write_text(md.read_text() + extra)


if __name__ == "__main__":
    main()
