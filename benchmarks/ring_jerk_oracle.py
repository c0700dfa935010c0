"""A ring policy's jerk next to IDM-as-CAV's and the least jerk a clairvoyant CAV could have on the same episodes.

For every case (the held-out cases of ``ring_generalization.py`` by default) this runs, on the same
episodes (evaluation seed 2000), the policy without its layer and with it, and IDM-as-CAV without a
layer (the reference of the jerk bar), then solves per episode the least whole-episode mean
|jerk| of any command sequence that knows the head's future
(:func:`mixed_traffic.evaluation.oracle.least_jerk`):

- ``band``: the gap in ``[s_min, s_max]`` after the warm-up (the evaluation's 5-40 m), above 0.05 m before;
- ``band + rmse (l1)``: also mean |v - v_head| <= ``eval.rmse_bar`` on the steady samples, a lower
  bound of the least jerk under the steady-RMSE bar;
- ``band + rmse (linf)``: |v - v_head| <= ``eval.rmse_bar`` on every steady sample, a sequence that
  meets both bars (an upper bound of that least jerk).

The gap between a causal controller and the clairvoyant figure is what not knowing the head's
future costs; a bar that even the clairvoyant figure misses cannot be met by any controller.
``--profiles random_steps ...`` runs the run's own evaluation profiles instead (its ``eval.seed``, its
episode length). Writes ``OUT/jerk_oracle.json`` and ``OUT/jerk_oracle.md`` and prints the table::

    python benchmarks/ring_jerk_oracle.py --checkpoint outputs/results/ring_eng5_seed0 \\
        --out outputs/results/ring_eng5_seed0/jerk_oracle
    python benchmarks/ring_jerk_oracle.py --checkpoint outputs/results/ring_eng5_seed0 --cases fast_steps stop_and_go \\
        --out /tmp/jerk_oracle --plot docs/img/ring_jerk_oracle.png
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--checkpoint", required=True, help="final.pt or a run directory")
    p.add_argument("--episodes", type=int, default=4)
    p.add_argument("--seconds", type=float, default=200.0)
    p.add_argument("--seed", type=int, default=2000)
    p.add_argument("--cases", nargs="+", default=None, help="subset of ring_generalization's cases")
    p.add_argument("--profiles", nargs="+", default=(),
                   help="evaluation profiles of the run (e.g. random_steps), on its own episodes (eval.seed) "
                        "instead of the held-out cases")
    p.add_argument("--out", required=True)
    p.add_argument("--plot", default=None,
                   help="PNG: episode 0 of each case, speed, gap and command of the policy without its layer, "
                        "IDM-as-CAV and the clairvoyant band + RMSE (linf) sequence")
    p.add_argument("--stop-gap", type=float, default=None, metavar="G",
                   help="also the column 'band + stopping (G m)': every step in the stopping-safe set of the "
                        "head's braking bound (a lower bound of the jerk of any controller that no head within "
                        "that bound can bring below G m)")
    p.add_argument("--plot-seconds", type=float, nargs=2, default=(20.0, 110.0), help="time window of --plot")
    p.add_argument("--preview", type=float, nargs="+", default=(), metavar="S",
                   help="also the columns 'preview S s': a causal CAV that sees S seconds of the head's coming "
                        "speeds and drives by least-jerk plans inside the band and the stopping-safe set of the run's "
                        "stop_gap or --stop-gap (oracle.preview_least_jerk; 0: it only measures the head's present "
                        "speed), with its gaps after the warm-up and its steady RMSE")
    p.add_argument("--preview-horizon", type=float, default=15.0, metavar="H",
                   help="the plans' horizon with --preview: the larger of H and S + 5 s (default 15)")
    p.add_argument("--preview-plot", default=None, metavar="PNG",
                   help="with --preview: each case's jerk against the preview's length, beside IDM-as-CAV's, the "
                        "policy's without its layer and the clairvoyant band's (hollow: the gap left the band)")
    p.add_argument("--track-weight", type=float, default=None, metavar="W",
                   help="with --preview: also price each m/s of speed error on a step at W m/s^2 of command change "
                        "(default: none; the plans then price jerk and the band only)")
    p.add_argument("--band-weight", type=float, default=20.0, metavar="W",
                   help="with --preview: the price of a metre outside the band for a step, in command change "
                        "(m/s^2; default 20: the plans leave the band only where they must)")
    a = p.parse_args(argv)
    if (any(not s_ >= 0 for s_ in a.preview) or not a.preview_horizon > 0 or not a.band_weight > 0
            or (a.track_weight is not None and not a.track_weight > 0)):
        raise SystemExit(f"--preview {list(a.preview)} / --preview-horizon {a.preview_horizon} / --band-weight "
                         f"{a.band_weight} / --track-weight {a.track_weight} are invalid; allowed: previews >= 0, a "
                         "horizon > 0 (s), weights > 0")

    import torch
    from omegaconf import open_dict
    from ring_generalization import cases, named_config

    from mixed_traffic.evaluation import classical_chain
    from mixed_traffic.evaluation.harness import eval_scenario, evaluate, follower_metrics
    from mixed_traffic.evaluation.oracle import least_jerk_of_trace, preview_least_jerk, start_of_trace, steady_mask
    from mixed_traffic.evaluation.policies import checkpoint_config, classic_factory, policy_factory_from_state

    torch.set_num_threads(1)
    run_cfg, state = checkpoint_config(a.checkpoint)
    factory = policy_factory_from_state(run_cfg, state)
    all_cases = cases(a.seconds)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    results, plotted, preview_gaps = {}, {}, {}

    for name in list(a.profiles) or a.cases or list(all_cases):
        traces = {}
        row = {}
        for label, chain, fac in (("policy + layer", None, factory), ("policy, no layer", "no_layer", factory),
                                  ("IDM-as-CAV", classical_chain(run_cfg.transforms.chain), classic_factory("idm"))):
            cfg, prof = named_config(run_cfg, name, episodes=a.episodes, seconds=a.seconds, seed=a.seed)
            with open_dict(cfg):
                cfg.eval.without_layer = False
                if chain == "no_layer":
                    cfg.transforms.chain = [t for t in cfg.transforms.chain if t != "safety_layer"]
                elif chain is not None:
                    cfg.transforms.chain = chain
            rep, tr = evaluate(cfg, policy_factory=fac)
            traces[label] = tr[prof]
            row[label] = rep["profiles"][prof]["per_episode"]["mean_abs_jerk"]
        e = cfg.eval
        dt = round(float(traces["IDM-as-CAV"].time[0, 0]), 6)  # the trace's float32 time
        scenario = eval_scenario(cfg, prof)
        lo, hi = scenario.cav_accel_bounds
        steady = steady_mask(traces["IDM-as-CAV"], dt=dt, warmup=e.warmup_seconds, settle=e.settle_seconds)
        programs = [("clairvoyant: band", {}),
                    ("clairvoyant: band + rmse (l1)", {"steady": steady, "rmse": e.rmse_bar, "norm": "l1"}),
                    ("clairvoyant: band + rmse (linf)", {"steady": steady, "rmse": e.rmse_bar, "norm": "linf"})]
        if a.stop_gap is not None:
            programs.append((f"clairvoyant: band + stopping ({a.stop_gap:g} m)",
                             {"stop_gap": a.stop_gap, "leader_brake": -float(scenario.head_accel_bounds[0])}))
        for label, kw in programs:
            vals = []
            for r in range(a.episodes):
                try:
                    sol = least_jerk_of_trace(traces["IDM-as-CAV"], r, dt=dt, warmup=e.warmup_seconds,
                                              s_min=e.s_min, s_max=e.s_max, accel_bounds=(lo, hi), **kw)
                    vals.append(sol.jerk)
                    if r == 0 and kw.get("norm") == "linf":
                        plotted[name] = (traces, sol)
                except ValueError:
                    vals.append(float("nan"))
            row[label] = vals
        # the plans keep the stopping-safe set of the run's own stopping envelope (transforms.residual.stop_gap),
        # or of --stop-gap, so that a head's stop cannot make them collide
        preview_stop = a.stop_gap if a.stop_gap is not None else run_cfg.transforms.get("residual", {}).get("stop_gap")
        ref_tr = traces["IDM-as-CAV"]
        for s_ in a.preview:
            label, vals, lows, highs, braked, rmses = preview_label(s_), [], [], [], [], []
            for r in range(a.episodes):
                vh, v0, g0, vh0 = start_of_trace(ref_tr, r, dt=dt)
                sol = preview_least_jerk(vh, preview=s_, horizon=max(a.preview_horizon, s_ + 5.0), v_start=v0,
                                         gap_start=g0, head_start=vh0, dt=dt, warmup=e.warmup_seconds, s_min=e.s_min,
                                         s_max=e.s_max, accel_bounds=(lo, hi), stop_gap=preview_stop,
                                         band_weight=a.band_weight, track_weight=a.track_weight,
                                         leader_brake=-float(scenario.head_accel_bounds[0]))
                n = len(vh)  # the report's own gap and steady-RMSE figures of the driven sequence
                valid = ref_tr.valid[r:r + 1, :n]
                m = follower_metrics(gap=sol.gap[None], head_gap=sol.gap[None], speed=sol.speed[None],
                                     head_speed=vh[None], accel=sol.accel[None],
                                     head_accel=ref_tr.head_accel[r:r + 1, :n].double(), valid=valid,
                                     after=valid & (ref_tr.time[r:r + 1, :n] >= e.warmup_seconds), dt=dt,
                                     settle=e.settle_seconds)
                vals.append(sol.jerk), braked.append(sol.braked)
                lows.append(float(m["min_gap_after"])), highs.append(float(m["max_head_gap"]))
                rmses.append(float(m["speed_rmse_steady"]))
            row[label] = vals
            preview_gaps.setdefault(name, {})[label] = [min(lows), max(highs), sum(braked), sum(rmses) / len(rmses)]
        results[name] = row
        print(name, json.dumps({k: round(sum(v) / len(v), 4) for k, v in row.items()}), flush=True)
    labels = list(next(iter(results.values())))
    md = ["| case | " + " | ".join(labels) + " |", "|---" * (len(labels) + 1) + "|"]
    for name, row in results.items():
        ref = sum(row["IDM-as-CAV"]) / len(row["IDM-as-CAV"])
        cells = []
        for k in labels:
            m = sum(row[k]) / len(row[k])
            cells.append(f"{m:.4f}" if k == "IDM-as-CAV" else f"{m:.4f} ({100 * (m / ref - 1):+.1f} %)")
            if k in preview_gaps.get(name, {}):
                low_, high_, braked_, rmse_ = preview_gaps[name][k]
                cells[-1] += f"; {low_:.1f}–{high_:.1f} m; RMSE {rmse_:.2f}"
                cells[-1] += f"; {braked_} steps braked without a plan" if braked_ else ""
        md.append(f"| {name} | " + " | ".join(cells) + " |")
    table = "\n".join(md)
    own = bool(a.profiles)  # the run's own evaluation episodes
    (out / "jerk_oracle.json").write_text(json.dumps({"checkpoint": str(a.checkpoint), "episodes": a.episodes,
                                                      "seconds": run_cfg.eval.episode_seconds if own else a.seconds,
                                                      "seed": run_cfg.eval.seed if own else a.seed, "results": results,
                                                      "preview_gaps_after_warmup": preview_gaps},
                                                     indent=1))
    (out / "jerk_oracle.md").write_text(table + "\n")
    print(table)
    if a.preview_plot and a.preview:
        plot_preview(results, preview_gaps, a.preview, a.preview_plot, s_band=(cfg.eval.s_min, cfg.eval.s_max))
    if a.plot:
        plot_episodes(plotted, a.plot, window=a.plot_seconds, s_band=(cfg.eval.s_min, cfg.eval.s_max))
    return results


def preview_label(seconds: float) -> str:
    """The column of the preview controller that sees ``seconds`` of the head's coming speeds."""
    return f"preview {seconds:g} s: band"


def plot_preview(results: dict, preview_gaps: dict, previews, path, *, s_band, tol: float = 0.5) -> None:
    """One panel per case: the preview controller's mean jerk against its preview (s), hollow where its gap
    left ``s_band`` by more than ``tol`` m after the warm-up, with IDM-as-CAV's, the policy's without its layer
    and the clairvoyant band's jerk as horizontal lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    mean = lambda xs: sum(xs) / len(xs)  # noqa: E731
    cols = min(3, len(results))
    rows_ = -(-len(results) // cols)
    fig, axes = plt.subplots(rows_, cols, figsize=(4.2 * cols, 3.3 * rows_), squeeze=False)
    for ax in axes.flat[len(results):]:
        ax.set_visible(False)
    for ax, (name, row) in zip(axes.flat, results.items()):
        labels = [preview_label(s_) for s_ in previews]
        ys = [mean(row[k]) for k in labels]
        inside = [low >= s_band[0] - tol and high <= s_band[1] + tol for low, high, *_ in
                  (preview_gaps[name][k] for k in labels)]
        ax.plot(previews, ys, "k-", lw=1)
        for x, y, ok in zip(previews, ys, inside):
            ax.plot(x, y, "o", color="k", mfc="k" if ok else "white")
        for label, color in (("IDM-as-CAV", "C1"), ("policy, no layer", "C0"), ("clairvoyant: band", "C2")):
            ax.axhline(mean(row[label]), color=color, ls="--", lw=1, label=label)
        ax.set_title(name, fontsize=10)
        ax.set_xlabel("preview of the head (s)")
        ax.set_ylabel("mean |jerk| (m/s³)")
        ax.set_ylim(bottom=0)
    axes[0, 0].legend(fontsize=7)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_episodes(plotted: dict, path, *, window, s_band) -> None:
    """One column per case: speed (with the head's), gap (with the band) and command over ``window`` s of
    episode 0, for the policy without its layer, IDM-as-CAV and the clairvoyant sequence."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, len(plotted), figsize=(5.5 * len(plotted), 7), sharex="col", squeeze=False)
    for j, (name, (traces, sol)) in enumerate(plotted.items()):
        ref = traces["IDM-as-CAV"]
        t = ref.time[0]
        k = (t >= window[0]) & (t <= window[1])
        series = {"policy, no layer": traces["policy, no layer"], "IDM-as-CAV": ref}
        axes[0, j].plot(t[k], ref.head_speed[0][k], color="0.6", lw=2.5, label="head")
        for label, tr in series.items():
            axes[0, j].plot(t[k], tr.cav_speed[0][k], label=label)
            axes[1, j].plot(t[k], tr.gap[0][k], label=label)
            axes[2, j].plot(t[k], tr.cav_accel[0][k], label=label)
        axes[0, j].plot(t[k], sol.speed[k], "k--", label="clairvoyant (band + RMSE)")
        axes[1, j].plot(t[k], sol.gap[k], "k--")
        axes[2, j].plot(t[k], sol.accel[k], "k--")
        for s in s_band:
            axes[1, j].axhline(s, color="r", lw=0.8, ls=":")
        axes[0, j].set_title(name)
        axes[0, j].set_ylabel("speed (m/s)")
        axes[1, j].set_ylabel("gap (m)")
        axes[2, j].set_ylabel("command (m/s²)")
        axes[2, j].set_xlabel("time (s)")
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
