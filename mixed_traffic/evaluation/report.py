"""report.json / report.md and the plots of an evaluation, plus the training-curves panel."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from mixed_traffic.evaluation.harness import Trace  # noqa: E402

MD_COLUMNS = (("collision", "collisions", "{:.0f}"), ("min_gap", "min gap (m)", "{:.2f}"),
              ("max_head_gap", "max head gap (m)", "{:.2f}"), ("time_outside", "time outside (s)", "{:.1f}"),
              ("speed_rmse_steady", "steady RMSE (m/s)", "{:.3f}"), ("speed_rmse", "RMSE (m/s)", "{:.3f}"),
              ("mean_abs_accel", "mean abs a (m/s2)", "{:.3f}"), ("mean_abs_jerk", "jerk (m/s3)", "{:.2f}"),
              ("mean_abs_jerk_after", "jerk after warm-up (m/s3)", "{:.3f}"),
              ("return", "return", "{:.1f}"), ("safety_clip_rate", "intervention rate", "{:.3f}"),
              ("mean_abs_delta", "mean abs Δa (m/s2)", "{:.3f}"), ("override_rate", "speed-mode-95 override rate", "{:.3f}"))
NO_LAYER_COLUMNS = (("collision", "collisions", "{:.0f}"), ("min_gap", "min gap (m)", "{:.2f}"),
                    ("min_gap_after", "min gap after warm-up (m)", "{:.2f}"),
                    ("max_head_gap", "max head gap (m)", "{:.2f}"), ("time_outside", "time outside (s)", "{:.1f}"),
                    ("speed_rmse_steady", "steady RMSE (m/s)", "{:.3f}"), ("mean_abs_jerk", "jerk (m/s3)", "{:.2f}"),
                    ("mean_abs_jerk_after", "jerk after warm-up (m/s3)", "{:.3f}"), ("return", "return", "{:.1f}"))


def write_report(report: dict, out_dir: str | Path, traces: dict[str, Trace] | None = None, *,
                 title: str = "Evaluation", plot_episode: int = 0, s_min: float = 5.0, s_max: float = 40.0,
                 run_dir: str | Path | None = None) -> dict[str, Path]:
    """Write report.json, report.md, per-profile plots and (if ``run_dir`` has CSV logs) the curves panel."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"json": out / "report.json", "md": out / "report.md"}
    plots = {}
    if traces:
        for prof, tr in traces.items():
            label = prof.replace("_without_layer_close", ": no safety layer, close start").replace(
                "_without_layer", ": no safety layer")
            plots[prof] = plot_trace(tr, out / f"{prof}.png", title=f"{title}: {label}", episode=plot_episode,
                                     s_min=s_min, s_max=s_max)
    if run_dir is not None:
        curves = plot_training_curves(run_dir, out / "training_curves.png", title=title)
        if curves is not None:
            plots["training_curves"] = curves
        lam = read_scalars(run_dir).get("lambda")
        if lam is not None and lam[1]:
            ys = lam[1]
            report = dict(report, lambda_over_training={"first": ys[0], "max": max(ys), "min": min(ys),
                                                        "last": ys[-1], "frames": lam[0][-1]})
    report = dict(report, plots={k: str(v) for k, v in plots.items()})
    paths["json"].write_text(json.dumps(report, indent=2))
    paths["md"].write_text(markdown(report, title))
    paths.update(plots)
    return paths


def markdown(report: dict, title: str) -> str:
    lines = [f"# {title}", ""]
    if "policy" in report:
        lines += [f"policy: `{report['policy']}`", ""]
    lines += [f"{report['episodes_per_profile']} deterministic episodes per profile, evaluation seed "
              f"{report['eval_seed']}; mean ± std over episodes (collisions: total).", ""]
    layer = report.get("safety_layer")
    if layer:
        upper = ("no s_max: its s_min rule alone" if layer["s_max"] is None else
                 f"s_max {layer['s_max']:g} m ({layer['beyond_s_max']} beyond it"
                 + (f", after a {layer['hold_seconds']:g}-s hold" if layer.get("hold_seconds") else "") + ")")
        lines += [f"Safety layer as evaluated: s_min {layer['s_min']:g} m ({layer['mode']} rule); {upper}.", ""]
    v2v = report.get("v2v") or {}
    if v2v.get("delay") or v2v.get("loss"):
        lines += [f"V2V link: the leader's acceleration received {v2v['delay']:g} s late, {100 * v2v['loss']:g} % of "
                  "the messages lost (the last one received held).", ""]
    noise = report.get("sensor_noise") or {}
    if noise.get("gap") or noise.get("speed"):
        lines += [f"Measurement noise: every gap the CAV measures with a standard deviation of {noise['gap']:g} m, every "
                  f"speed {noise['speed']:g} m/s ("
                  + (f"correlated over {noise['tau']:g} s" if noise.get("tau") else "white, drawn each step")
                  + "); the simulation runs on the true state"
                  + (f"; the safety layer and the stopping envelope keep {noise['margin']:g} standard deviations of it as "
                     "margin" if noise.get("margin") else "")
                  + ("; a Kalman filter tracks the measurements and the controllers act on its estimates"
                     if noise.get("filter") else "")
                  + (" (it assumes errors of {gap:g} m and {speed:g} m/s over {tau:g} s)".format(**noise["filter_model"])
                     if noise.get("filter_model") else "") + ".", ""]
    # the speed-mode-95 override rate only where the env ran with sumo_safety
    cols = MD_COLUMNS if report.get("sumo_safety") else tuple(c for c in MD_COLUMNS if c[0] != "override_rate")
    lines.append("| profile | " + " | ".join(c[1] for c in cols) + " |")
    lines.append("|---|" + "---|" * len(cols))
    for prof, r in report["profiles"].items():
        lines.append(f"| {prof} | " + " | ".join(_cells(r, cols)) + " |")
    unsteady = _unsteady(report["profiles"])
    if unsteady:
        lines += ["", "Steady RMSE where the head never held its speed long enough to settle: " + "; ".join(unsteady)
                  + ". An episode without a steady state gives its whole-episode RMSE instead; the table gives the "
                  "mean over the episodes that settle (report.json: `steady_only_rmse`), or marks the whole-episode "
                  "figure where none did."]
    nl = report.get("without_layer")
    if nl:
        lines += ["", "Without the safety layer (the policy's own commands executed), per start spacing:", ""]
        lines.append("| profile | start | " + " | ".join(c[1] for c in NO_LAYER_COLUMNS) + " |")
        lines.append("|---|---|" + "---|" * len(NO_LAYER_COLUMNS))
        for prof, starts in nl.items():
            for label, r in starts.items():
                lines.append(f"| {prof} | {label} | " + " | ".join(_cells(r, NO_LAYER_COLUMNS)) + " |")
    ref = report.get("reference")
    if ref:
        labels = [k for k in next(iter(ref["profiles"].values())) if k != "reference"]
        lines += ["", f"Against {ref['controller']} on the same episodes (driving the CAV without a layer, under the "
                      "task's reward): the policy's mean |jerk| in % of its, and the policy's return less its.", ""]
        lines.append(f"| profile | {ref['controller']}: jerk (m/s3) | its return | "
                     + " | ".join(f"{k}: jerk − its | {k}: return − its" for k in labels) + " |")
        lines.append("|---|---|---|" + "---|---|" * len(labels))
        for prof, e in ref["profiles"].items():
            r = e["reference"]
            note = f" ({r['collisions']} collisions: not judged)" if r["collisions"] else ""
            lines.append(f"| {prof} | {r['jerk']:.4f}{note} | {r['return']:.1f} | "
                         + " | ".join(f"{e[k]['jerk_pct']:+.2f} % | {e[k]['return_diff']:+.1f}" for k in labels) + " |")
    lam = report.get("lambda_over_training")
    if lam:
        lines += ["", f"λ over training: first {lam['first']:.3f}, max {lam['max']:.3f}, min {lam['min']:.3f}, "
                      f"last {lam['last']:.3f} ({lam['frames']:.0f} frames; curve in training_curves.png)"]
    acc = report.get("acceptance")
    if acc:
        lines += ["", "Acceptance: " + ", ".join(
            f"{k}={v:.3f}" if isinstance(v, float) else f"{k}={v}" for k, v in acc.items())]
    if report.get("plots"):
        lines += ["", "Plots: " + ", ".join(f"[{k}]({Path(v).name})" for k, v in report["plots"].items())]
    return "\n".join(lines) + "\n"


def _unsteady(profiles: dict) -> list[str]:
    """The profiles some of whose episodes had no steady samples (``steady_seconds`` = 0), with how many."""
    out = []
    for prof, r in profiles.items():
        secs = (r.get("per_episode") or {}).get("steady_seconds")
        if secs is None:  # a report from before the metric
            continue
        none = sum(s == 0 for s in secs)
        if none:
            out.append(f"{prof}, {none} of {len(secs)} episodes" if none < len(secs) else f"{prof}, every episode")
    return out


def steady_rmse_cell(rmse: float, steady: int | None, episodes: int | None, steady_only: float | None,
                     fmt: str = "{:.3f}") -> str:
    """A steady RMSE as a table shows it: ``rmse`` (the mean over all episodes) marked where it is the whole-episode
    fallback on every episode (``steady`` 0 of ``episodes``), ``steady_only`` (the mean over the episodes that
    settle) marked where only some settle, ``rmse`` alone where all do or the counts were not recorded (None)."""
    if steady is None or episodes is None or steady == episodes:
        return fmt.format(rmse)
    if steady == 0:
        return f"{fmt.format(rmse)} (no steady state: whole episode)"
    return f"{fmt.format(steady_only)} (steady in {steady} of {episodes} episodes, on those)"


def _partly_steady(r: dict) -> bool:
    """Whether some of an entry's episodes had no steady samples (False for a report from before the metric)."""
    k = r.get("steady_episodes")
    return k is not None and k < len(r["per_episode"]["steady_seconds"])


def _cells(r: dict, columns) -> list[str]:
    cells = []
    for key, _, fmt in columns:
        if key == "collision":
            cells.append(str(r["collisions"]))
            continue
        st = r["metrics"].get(key)
        if st is None:
            cells.append("–")
        elif key == "speed_rmse_steady" and _partly_steady(r):
            cells.append(steady_rmse_cell(st["mean"], r["steady_episodes"], len(r["per_episode"]["steady_seconds"]),
                                          r["steady_only_rmse"], fmt))
        elif key in ("min_gap", "min_gap_after"):
            cells.append(fmt.format(st["min"]))
        elif key == "max_head_gap":
            cells.append(fmt.format(st["max"]))
        else:
            cells.append(f"{fmt.format(st['mean'])} ± {fmt.format(st['std'])}")
    return cells


def plot_trace(tr: Trace, path: Path, *, title: str, episode: int = 0, s_min: float = 5.0,
               s_max: float = 40.0) -> Path:
    e = min(episode, tr.time.shape[0] - 1)
    m = tr.valid[e]
    t = tr.time[e][m].numpy()
    raw = getattr(tr, "raw_accel", None)
    who = raw is not None and bool((raw[e][m] != tr.cav_accel[e][m]).any())
    fig, ax = plt.subplots(4 if who else 3, 1, figsize=(10, 10.5 if who else 8), sharex=True)
    ax[0].plot(t, tr.head_speed[e][m].numpy(), label="head", color="tab:blue")
    ax[0].plot(t, tr.cav_speed[e][m].numpy(), label="CAV", color="tab:orange")
    ax[0].set_ylabel("speed (m/s)")
    ax[0].legend(loc="upper right")
    ax[1].plot(t, tr.head_accel[e][m].numpy(), label="head", color="tab:blue", lw=0.8)
    ax[1].plot(t, tr.cav_accel[e][m].numpy(), label="CAV", color="tab:orange", lw=0.8)
    ax[1].set_ylabel("acceleration (m/s²)")
    ax[1].legend(loc="upper right")
    ax[2].plot(t, tr.gap[e][m].numpy(), label="gap to leader", color="tab:green")
    ax[2].plot(t, tr.head_gap[e][m].numpy(), label="gap to head", color="tab:purple", ls="--", lw=0.8)
    ax[2].axhline(s_min, color="red", ls=":", label=f"s_min = {s_min:g} m")
    ax[2].axhline(s_max, color="red", ls="-.", label=f"s_max = {s_max:g} m")
    ax[2].set_ylabel("gap (m)")
    ax[2].set_ylim(0, max(s_max * 1.5, float(tr.gap[e][m].max()) * 1.05 if m.any() else s_max))
    ax[2].legend(loc="upper right", fontsize=8)
    if who:  # who brakes: the policy's command vs what the safety layer let through
        r, x = raw[e][m].numpy(), tr.cav_accel[e][m].numpy()
        ax[3].plot(t, r, label="commanded (policy)", color="tab:gray", lw=0.8)
        ax[3].plot(t, x, label="executed (after the safety layer)", color="tab:orange", lw=0.8)
        ax[3].fill_between(t, r, x, where=(x < r), color="tab:red", alpha=0.4, label="layer brakes")
        ax[3].fill_between(t, r, x, where=(x > r), color="tab:green", alpha=0.4, label="layer pushes")
        ax[3].set_ylabel("CAV accel (m/s²)")
        ax[3].legend(loc="upper right", fontsize=8)
    ax[-1].set_xlabel("time (s)")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def read_scalars(run_dir: str | Path) -> dict[str, tuple[list[float], list[float]]]:
    """CSV scalars of a run (``logs/<name>/scalars/*.csv``); repeated steps (after a resume) keep the last."""
    out = {}
    for d in sorted(Path(run_dir).glob("logs/*/scalars")):
        for f in sorted(d.glob("*.csv")):
            rows = {}
            with f.open() as fh:
                for row in csv.reader(fh):
                    if len(row) == 2:
                        rows[float(row[0])] = float(row[1])
            steps = sorted(rows)
            out[f.stem] = (steps, [rows[s] for s in steps])
    return out


def plot_training_curves(run_dir: str | Path, path: str | Path, *, title: str = "") -> Path | None:
    """The training panel: return, policy/value loss, entropy, clip fraction, lambda, violation and clip rate."""
    sc = read_scalars(run_dir)
    if not sc:
        return None
    panels = [("reward per step (task): batch / finished episodes", ["reward_per_step", "episode_reward_per_step"]),
              ("finished-episode return (desync: lengths vary)", ["episode_return"]),
              ("policy loss", ["loss_objective", "loss"]), ("value loss", ["loss_critic"]),
              ("entropy", ["entropy"]), ("clip fraction", ["clip_fraction"]),
              ("lambda", ["lambda"]), ("cost / intervention", ["mean_violation", "safety_clip_rate", "intervention_cost"]),
              ("epsilon", ["epsilon"])]
    panels = [(t, [k for k in keys if k in sc]) for t, keys in panels]
    panels = [(t, keys) for t, keys in panels if keys]
    n = len(panels)
    cols = 2
    rows = (n + 1) // 2
    fig, axes = plt.subplots(rows, cols, figsize=(11, 2.6 * rows), squeeze=False)
    for i, (t, keys) in enumerate(panels):
        ax = axes[i // cols][i % cols]
        for k in keys:
            xs, ys = sc[k]
            ax.plot(xs, ys, label=k, lw=1.0)
        ax.set_title(t, fontsize=10)
        ax.set_xlabel("frames")
        ax.ticklabel_format(axis="x", style="sci", scilimits=(0, 0))
        if len(keys) > 1:
            ax.legend(fontsize=8)
    for j in range(n, rows * cols):
        axes[j // cols][j % cols].axis("off")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path)
