"""Where in the episode a ring policy's jerk is, next to IDM driving the CAV on the same episodes.

The report's ``mean_abs_jerk`` is the mean of ``|a_t - a_{t-1}| / dt`` over a whole episode
(the first step, whose previous acceleration is unknown, not counted). This splits that mean
into the share of each time window (the shares add up to the whole-episode figure), for the
trained policy behind its layer and for IDM-as-CAV without one, on the evaluation profiles and
episodes of the run's config (``eval.seed``, ``eval.episodes``), and prints one table per
profile plus the mean from ``--from-seconds`` on; ``--plot`` draws the two commands over the
first ``--plot-seconds`` of each profile's first episode (the residual's engagement shaded)::

    python benchmarks/ring_jerk_by_time.py --checkpoint outputs/results/ring_smooth_seed0 \\
        --out outputs/results/ring_smooth_seed0/jerk_by_time.json --plot outputs/results/ring_smooth_seed0/start.png
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

EDGES = (0.0, 2.0, 5.0, 10.0, 15.0, 20.0, 30.0, 60.0, float("inf"))


def jerk_shares(trace, dt: float, edges=EDGES, from_seconds: float = 5.0) -> dict:
    """Per window ``[lo, hi)``: its steps' summed ``|jerk|`` over all valid steps (so the windows add
    up to the whole-episode mean), averaged over episodes; and the mean ``|jerk|`` from ``from_seconds`` on.
    The jerk and its steps are the report's (:func:`~mixed_traffic.evaluation.harness.abs_jerk`)."""
    from mixed_traffic.evaluation.harness import abs_jerk, jerk_shares_by

    jerk, valid = abs_jerk(trace.cav_accel, trace.valid, dt)
    t = trace.time
    n = valid.sum(1).clamp_min(1)
    shares = jerk_shares_by(trace.cav_accel, trace.valid, dt, t, edges)
    late = valid & (t >= from_seconds)
    after = (jerk * late).sum(1) / late.sum(1).clamp_min(1)
    return {"edges": list(edges), "shares": shares, "whole": float(((jerk * valid).sum(1) / n).mean()),
            "from_seconds": from_seconds, "after": float(after.mean()), "after_per_episode": after.tolist()}


def plot_starts(traces: dict, path, *, seconds: float, engage_seconds: float = 0.0) -> None:
    """One panel per profile: the CAV's command (m/s^2) over the first ``seconds`` of episode 0, one
    line per controller, and the head's speed on a second axis; ``engage_seconds`` > 0 is shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(traces), 1, figsize=(8, 2.4 * len(traces)), sharex=True, squeeze=False)
    for ax, (prof, rows) in zip(axes[:, 0], traces.items()):
        for name, tr in rows.items():
            k = tr.time[0] < seconds
            ax.plot(tr.time[0][k].numpy(), tr.cav_accel[0][k].numpy(), label=name)
        if engage_seconds > 0:
            ax.axvspan(0.0, engage_seconds, color="0.9", label=f"engaging ({engage_seconds:g} s)")
        tr = next(iter(rows.values()))
        k = tr.time[0] < seconds
        twin = ax.twinx()
        twin.plot(tr.time[0][k].numpy(), tr.head_speed[0][k].numpy(), color="0.5", ls=":", label="head speed")
        twin.set_ylabel("head m/s")
        ax.set_ylabel("CAV m/s²")
        ax.set_title(prof, fontsize=9)
        ax.legend(fontsize=7, loc="upper right")
    axes[-1, 0].set_xlabel("time (s)")
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--checkpoint", required=True, help="final.pt or a run directory")
    p.add_argument("--profiles", nargs="+", default=None, help="default: the run's eval.profiles")
    p.add_argument("--baseline", default="idm", help="classical controller run without a layer (default idm)")
    p.add_argument("--from-seconds", type=float, default=5.0, help="also report the mean |jerk| from here on")
    p.add_argument("--out", default=None, help="write the figures as JSON here")
    p.add_argument("--plot", default=None, help="draw the start of each profile's first episode into this PNG")
    p.add_argument("--plot-seconds", type=float, default=30.0, help="how much of the start --plot draws (s)")
    a = p.parse_args(argv)
    if not a.from_seconds >= 0:
        p.error(f"--from-seconds={a.from_seconds} is invalid; allowed: >= 0")
    if not a.plot_seconds > 0:
        p.error(f"--plot-seconds={a.plot_seconds} is invalid; allowed: > 0")

    import torch
    from omegaconf import OmegaConf, open_dict

    from mixed_traffic.evaluation import classical_chain
    from mixed_traffic.evaluation.harness import run_profile
    from mixed_traffic.evaluation.policies import checkpoint_config, classic_factory, policy_factory_from_state

    torch.set_num_threads(1)
    cfg, state = checkpoint_config(a.checkpoint)
    factory = policy_factory_from_state(cfg, state)
    base_cfg = cfg.copy()
    with open_dict(base_cfg):
        base_cfg.transforms.chain = classical_chain(cfg.transforms.chain)
    out = {"checkpoint": str(a.checkpoint), "baseline": a.baseline, "profiles": {}}
    traces = {}
    for prof in a.profiles or list(cfg.eval.profiles):
        rows, traces[prof] = {}, {}
        for name, c, fac in (("policy", cfg, factory), (a.baseline, base_cfg, classic_factory(a.baseline))):
            _, trace = run_profile(c, None, prof, episodes=int(cfg.eval.episodes), seed=int(cfg.eval.seed),
                                   policy_factory=fac)
            rows[name] = jerk_shares(trace, float(trace.time[0, 1] - trace.time[0, 0]), from_seconds=a.from_seconds)
            traces[prof][name] = trace
        out["profiles"][prof] = rows
        head = " | ".join(f"{lo:g}-{hi:g} s" for lo, hi in zip(EDGES[:-1], EDGES[1:]))
        print(f"\n{prof}\n| controller | whole | {head} | from {a.from_seconds:g} s |\n|" + "---|" * (len(EDGES) + 2))
        for name, r in rows.items():
            print(f"| {name} | {r['whole']:.4f} | " + " | ".join(f"{s:.4f}" for s in r["shares"]) + f" | {r['after']:.4f} |")
        pol, base = rows["policy"], rows[a.baseline]
        worse = sum(x > y for x, y in zip(pol["after_per_episode"], base["after_per_episode"]))
        print(f"from {a.from_seconds:g} s: policy {100 * (pol['after'] / base['after'] - 1):+.1f} % against "
              f"{a.baseline}; above it on {worse} of {len(pol['after_per_episode'])} episodes")
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps(out, indent=2))
    if a.plot:
        engage = float(OmegaConf.select(cfg, "transforms.residual.engage_seconds", default=0.0) or 0.0)
        plot_starts(traces, a.plot, seconds=a.plot_seconds, engage_seconds=engage)
        print(f"plot: {a.plot}")
    return out


if __name__ == "__main__":
    main()
