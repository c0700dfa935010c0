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
              ("return", "return", "{:.1f}"), ("safety_clip_rate", "clip rate", "{:.3f}"))


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
            plots[prof] = plot_trace(tr, out / f"{prof}.png", title=f"{title}: {prof}", episode=plot_episode,
                                     s_min=s_min, s_max=s_max)
    if run_dir is not None:
        curves = plot_training_curves(run_dir, out / "training_curves.png", title=title)
        if curves is not None:
            plots["training_curves"] = curves
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
    lines.append("| profile | " + " | ".join(c[1] for c in MD_COLUMNS) + " |")
    lines.append("|---|" + "---|" * len(MD_COLUMNS))
    for prof, r in report["profiles"].items():
        cells = []
        for key, _, fmt in MD_COLUMNS:
            if key == "collision":
                cells.append(str(r["collisions"]))
                continue
            st = r["metrics"][key]
            if key == "min_gap":
                cells.append(fmt.format(st["min"]))
            elif key == "max_head_gap":
                cells.append(fmt.format(st["max"]))
            else:
                cells.append(f"{fmt.format(st['mean'])} ± {fmt.format(st['std'])}")
        lines.append(f"| {prof} | " + " | ".join(cells) + " |")
    acc = report.get("acceptance")
    if acc:
        lines += ["", "Acceptance: " + ", ".join(
            f"{k}={v:.3f}" if isinstance(v, float) else f"{k}={v}" for k, v in acc.items())]
    if report.get("plots"):
        lines += ["", "Plots: " + ", ".join(f"[{k}]({Path(v).name})" for k, v in report["plots"].items())]
    return "\n".join(lines) + "\n"


def plot_trace(tr: Trace, path: Path, *, title: str, episode: int = 0, s_min: float = 5.0,
               s_max: float = 40.0) -> Path:
    e = min(episode, tr.time.shape[0] - 1)
    m = tr.valid[e]
    t = tr.time[e][m].numpy()
    fig, ax = plt.subplots(3, 1, figsize=(10, 8), sharex=True)
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
    ax[2].set_xlabel("time (s)")
    ax[2].set_ylim(0, max(s_max * 1.5, float(tr.gap[e][m].max()) * 1.05 if m.any() else s_max))
    ax[2].legend(loc="upper right", fontsize=8)
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
              ("lambda", ["lambda"]), ("violation / safety clip rate", ["mean_violation", "safety_clip_rate"]),
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
