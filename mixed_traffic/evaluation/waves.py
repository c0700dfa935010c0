"""Stop-and-go wave report for rings without a head (``ring_wave``): metrics, runs and plots.

Every controller (the all-human ring, IDM-as-CAV, FollowerStopper, PI with saturation,
a learned policy with and without its safety layer) drives the CAVs of the same
episodes: one batched env per ring length and controller, seeded identically, so the
initial wave, the humans' parameters and their noise are the same for every controller
(the ``human`` controller's own noise comes from its own generator).

Metrics per episode, over the steps after ``warmup`` (:func:`wave_metrics`):

- ``mean_speed`` (m/s): all vehicles, all steps;
- ``speed_std`` (m/s): standard deviation of the speeds across vehicles at each step,
  averaged over the steps (0 in uniform flow; a stop-and-go wave gives a few m/s);
- ``hard_brakes_per_vkm``: hard-braking events (a vehicle's acceleration crossing below
  ``hard_brake``, counted once per crossing) per vehicle-km driven;
- ``fuel_ml_per_vkm``: fuel per vehicle-km from the instantaneous fuel model used by the
  DeeP-LCC reference (:func:`mixed_traffic.controllers.deeplcc.closed_loop.fuel_rate`,
  mL/s, after Bowyer, Akçelik and Biggs 1985), summed over all vehicles;
- ``throughput`` (veh/h): flow past a fixed point of the ring, ``n mean(v) / L * 3600``;
- ``min_gap`` (m, every vehicle, whole episode), ``cav_min_gap`` (m), ``collision`` (0/1),
  ``intervention`` (share of CAV steps the safety layer changed; 0 without a layer).

The reference speed is the uniform-flow speed of the ring (every car at gap
``L / n - l`` in IDM equilibrium, :func:`mixed_traffic.physics.idm_equilibrium_speed`).

>>> from mixed_traffic.config import compose
>>> from mixed_traffic.evaluation.waves import evaluate_waves
>>> cfg = compose(["env=ring_wave", "transforms.safety_layer.s_max=null", "eval.wave.episodes=2"])  # doctest: +SKIP
>>> report, traces = evaluate_waves(cfg)  # doctest: +SKIP
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from mixed_traffic.evaluation.harness import first_done_mask

WAVE_METRICS = ("mean_speed", "speed_std", "hard_brakes_per_vkm", "fuel_ml_per_vkm", "throughput", "min_gap",
                "cav_min_gap", "collision", "intervention")


def fuel_rate(v: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """Instantaneous fuel (mL/s) of the DeeP-LCC reference's model, on tensors."""
    from mixed_traffic.controllers.deeplcc.closed_loop import fuel_rate as _fuel

    return torch.as_tensor(_fuel(v.double().numpy(), a.double().numpy()))


def uniform_flow_speed(scenario, ring_length: float) -> float:
    """Speed of the ring's uniform flow from the humans' IDM at gap ``L / n - l`` (a float)."""
    from mixed_traffic.envs.traffic import uniform_flow_speed as per_row

    return float(per_row(scenario, float(ring_length)))


def hard_brake_events(accel: torch.Tensor, threshold: float, mask: torch.Tensor) -> torch.Tensor:
    """Number of crossings below ``threshold`` per episode: ``accel`` ``[E, T, n]``, ``mask`` ``[E, T]``."""
    below = (accel < threshold) & mask.unsqueeze(-1)
    prev = torch.zeros_like(below)
    prev[:, 1:] = below[:, :-1]
    return (below & ~prev).sum((1, 2))


def wave_metrics(td: TensorDictBase, *, dt: float, warmup: float, hard_brake: float = -2.0,
                 cav_indices=(0,)) -> dict[str, torch.Tensor]:
    """Per-episode wave metrics of a ``[E, T]`` rollout of a ring without a head (module docstring)."""
    nxt = td.get("next")
    valid = first_done_mask(nxt.get("done").squeeze(-1))
    t = nxt.get(("traffic", "time")).squeeze(-1)
    after = valid & (t > warmup + 1e-9)
    v = nxt.get(("traffic", "speed"))
    a = nxt.get(("traffic", "accel"))
    gap = nxt.get(("traffic", "gap"))
    L = nxt.get(("traffic", "ring_length"))[:, 0, 0]
    n = v.shape[-1]
    w = after.float()
    steps = w.sum(1).clamp_min(1)
    out: dict[str, torch.Tensor] = {}
    out["mean_speed"] = (v.mean(-1) * w).sum(1) / steps
    out["speed_std"] = (v.std(-1, unbiased=False) * w).sum(1) / steps
    vkm = (v * w.unsqueeze(-1)).sum((1, 2)) * dt / 1000.0
    out["hard_brakes_per_vkm"] = hard_brake_events(a, hard_brake, after).float() / vkm.clamp_min(1e-9)
    fuel = (fuel_rate(v, a).float() * w.unsqueeze(-1)).sum((1, 2)) * dt
    out["fuel_ml_per_vkm"] = fuel / vkm.clamp_min(1e-9)
    out["throughput"] = n * out["mean_speed"] / L * 3600.0
    inf = torch.tensor(float("inf"))
    out["min_gap"] = torch.where(valid.unsqueeze(-1), gap, inf).amin((1, 2))
    out["cav_min_gap"] = torch.where(valid.unsqueeze(-1), gap[..., list(cav_indices)], inf).amin((1, 2))
    out["collision"] = (nxt.get("collision").squeeze(-1) & valid).any(1).float()
    clipped = nxt.get(("safety", "clipped"), None)
    if clipped is not None:
        out["intervention"] = (clipped.float().mean(-1) * valid).sum(1) / valid.sum(1).clamp_min(1)
    else:
        out["intervention"] = torch.zeros(v.shape[0])
    return out


# ----------------------------------------------------------------------------- runs
#: transforms that turn a policy's output into the CAV's command: a classical damper drives the CAV itself
POLICY_ONLY = ("residual_damper", "residual_idm", "set_point", "blend", "intervention_cost")


def _eval_cfg(cfg: DictConfig, *, safety_layer: bool, policy: bool = True) -> DictConfig:
    """The run's chain with the safety layer first (or removed); without ``policy`` also without
    the residual base (:data:`POLICY_ONLY`), so that a classical controller's command is executed
    as it is, not added to the learned policy's base controller."""
    c = OmegaConf.create(OmegaConf.to_container(cfg, resolve=False))
    drop = ("safety_layer",) + (() if policy else POLICY_ONLY)
    chain = [x for x in c.transforms.chain if x not in drop]
    # the layer goes nearest the env (first), so that it clips what is executed
    c.transforms.chain = (["safety_layer"] + chain) if safety_layer else chain
    return c


def run_controller(cfg: DictConfig, policy_factory, *, ring_length: float, episodes: int, seed: int,
                   seconds: float, warmup: float, safety_layer: bool, hard_brake: float, policy: bool = True):
    """One controller on ``episodes`` episodes of one ring length: (metrics, rollout positions/speeds).

    Torch backend: one batched env of ``episodes`` rows seeded ``seed``. SUMO backend
    (``cfg.env.backend=sumo``, one simulation per process): the episodes run one after
    the other, episode ``e`` in an env seeded ``seed + e`` (the same episode as a torch env
    with ``batch_size=1`` and that seed).
    """
    from mixed_traffic.training.builders import make_transformed_env

    c = _eval_cfg(cfg, safety_layer=safety_layer, policy=policy)
    kw = dict(ring_length=float(ring_length), ring_length_range=None, episode_seconds=float(seconds))
    runs = [(episodes, seed)] if c.env.backend != "sumo" else [(1, seed + e) for e in range(episodes)]
    tds = []
    for num_envs, s in runs:
        env = make_transformed_env(c, num_envs=num_envs, seed=s, **kw)
        sc = env.base_env.scenario
        policy = policy_factory(env)
        torch.manual_seed(s)
        try:
            with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
                tds.append(env.rollout(sc.max_steps, policy, break_when_any_done=False))
        finally:
            env.close()
    td = torch.cat(tds, 0) if len(tds) > 1 else tds[0]
    m = wave_metrics(td, dt=sc.dt, warmup=warmup, hard_brake=hard_brake, cav_indices=sc.cav_indices)
    trace = {"time": td["next", "traffic", "time"][0, :, 0].clone(), "pos": td["next", "traffic", "pos"][0].clone(),
             "speed": td["next", "traffic", "speed"][0].clone(), "ring_length": float(ring_length),
             "cav_indices": list(sc.cav_indices)}
    return m, trace, sc


def _stats(x: torch.Tensor) -> dict:
    x = x.double()
    return {"mean": float(x.mean()), "std": float(x.std(unbiased=False)) if x.numel() > 1 else 0.0,
            "min": float(x.min()), "max": float(x.max())}


def parse_controller(name: str, field: str = "eval.wave.controllers") -> tuple[str, dict]:
    """``"follower_stopper:u_ratio=0.93;U=3"`` -> ``("follower_stopper", {"u_ratio": 0.93, "U": 3.0})``."""
    damper, _, args = name.partition(":")
    kwargs = {}
    for item in filter(None, args.split(";")):
        key, eq, value = item.partition("=")
        try:
            kwargs[key.strip()] = float(value)
        except ValueError:
            eq = ""
        if not eq or not key.strip():
            raise ValueError(f"{field}: {name!r} is invalid; allowed: name or name:key=number[;key=number]")
    return damper, kwargs


def controller_factories(cfg: DictConfig, names, *, policy_factory=None, seed: int = 0) -> dict:
    """``{label: (factory(env) -> policy, with_safety_layer)}`` for the wave comparison."""
    from mixed_traffic.controllers.dampers import DAMPERS, check_damper_arguments, make_damper

    out = {}
    for name in names:
        if name == "policy":
            continue
        damper, kwargs = parse_controller(name)
        if damper not in DAMPERS:
            raise ValueError(f"eval.wave.controllers: {name!r} is invalid; allowed: {list(DAMPERS)} (+ 'policy'), "
                             "optionally with arguments, e.g. 'follower_stopper:u_ratio=0.93'")
        try:  # before any controller runs, not when this one's turn comes
            check_damper_arguments(damper, kwargs)
        except ValueError as e:
            raise ValueError(f"eval.wave.controllers: {name!r} is invalid: {e}") from e
        factory = (lambda n, kw: (lambda env: make_damper(n, env, seed=seed, **kw)))(damper, kwargs)
        out[name] = (factory, False)
        if cfg.eval.wave.get("classical_with_layer", False) and damper != "human":
            out[f"{name} (layer)"] = (factory, True)
    if policy_factory is not None:
        if cfg.eval.wave.safety_layer:
            out["policy"] = (policy_factory, True)
        if cfg.eval.wave.get("without_layer", True):
            out["policy (no layer)"] = (policy_factory, False)
    return out


def evaluate_waves(cfg: DictConfig, *, policy_factory=None, controllers=None, ring_lengths=None,
                   episodes: int | None = None, seed: int | None = None) -> tuple[dict, dict]:
    """The wave report over ``ring_lengths`` x controllers; returns ``(report, traces)``.

    ``traces[ring_length][label]`` holds episode 0's positions and speeds (space-time plots).
    """
    w = cfg.eval.wave
    names = list(controllers if controllers is not None else w.controllers)
    lengths = [float(x) for x in (ring_lengths if ring_lengths is not None else w.ring_lengths)]
    episodes = int(episodes or w.episodes)
    seed = int(cfg.eval.seed if seed is None else seed)
    facts = controller_factories(cfg, names, policy_factory=policy_factory, seed=seed)
    report = {"episodes": episodes, "eval_seed": seed, "backend": str(cfg.env.backend),
              "episode_seconds": float(w.episode_seconds),
              "warmup_seconds": float(w.warmup_seconds), "hard_brake": float(w.hard_brake), "rings": {}}
    traces: dict = {}
    for L in lengths:
        entry = {"controllers": {}}
        traces[L] = {}
        for label, (factory, layer) in facts.items():
            m, trace, sc = run_controller(cfg, factory, ring_length=L, episodes=episodes, seed=seed,
                                          seconds=w.episode_seconds, warmup=w.warmup_seconds, safety_layer=layer,
                                          hard_brake=w.hard_brake, policy=label.startswith("policy"))
            entry["controllers"][label] = {"metrics": {k: _stats(v) for k, v in m.items()},
                                           "collisions": int(m["collision"].sum()),
                                           "per_episode": {k: [float(x) for x in v] for k, v in m.items()}}
            traces[L][label] = trace
        entry["uniform_flow_speed"] = uniform_flow_speed(sc, L)
        entry["comparison"] = compare(entry)
        report["rings"][f"{L:g}"] = entry
    return report, traces


def compare(entry: dict) -> dict:
    """Each controller relative to the all-human ring and the uniform-flow speed (acceptance figures)."""
    ctrl = entry["controllers"]
    if "human" not in ctrl:
        return {}
    h = {k: ctrl["human"]["metrics"][k]["mean"] for k in WAVE_METRICS}
    v_u = entry["uniform_flow_speed"]
    out = {}
    for label, r in ctrl.items():
        m = {k: r["metrics"][k]["mean"] for k in WAVE_METRICS}

        def drop(k, m=m):
            return 1.0 - m[k] / h[k] if h[k] > 0 else float("nan")

        out[label] = {"speed_std_reduction": drop("speed_std"), "hard_brake_reduction": drop("hard_brakes_per_vkm"),
                      "fuel_reduction": drop("fuel_ml_per_vkm"), "mean_speed_vs_uniform": m["mean_speed"] / v_u,
                      "collisions": r["collisions"], "intervention": m["intervention"]}
    return out


def acceptance(report: dict, label: str = "policy") -> dict:
    """The learned damper's bars on every ring length (std -50%, hard braking -75%, fuel -20%,
    mean speed within 10% of uniform flow and above every classical damper, 0 collisions,
    intervention <= 5%)."""
    out = {}
    for L, entry in report["rings"].items():
        cmp = entry["comparison"].get(label)
        if cmp is None:
            continue
        ctrl = entry["controllers"]
        v = ctrl[label]["metrics"]["mean_speed"]["mean"]
        others = {k: r["metrics"]["mean_speed"]["mean"] for k, r in ctrl.items() if not k.startswith("policy")}
        out[L] = {
            "speed_std_-50%": cmp["speed_std_reduction"] >= 0.5,
            "hard_brake_-75%": cmp["hard_brake_reduction"] >= 0.75,
            "fuel_-20%": cmp["fuel_reduction"] >= 0.2,
            "mean_speed_within_10%_of_uniform": abs(cmp["mean_speed_vs_uniform"] - 1.0) <= 0.1,
            "mean_speed_above_classical": all(v > x for x in others.values()),
            "zero_collisions": cmp["collisions"] == 0,
            "intervention_<=5%": cmp["intervention"] <= 0.05,
        }
    return out


# ----------------------------------------------------------------------------- report
COLUMNS = (("mean_speed", "mean speed (m/s)", "{:.2f}"), ("speed_std", "speed std (m/s)", "{:.2f}"),
           ("hard_brakes_per_vkm", "hard brakes / veh-km", "{:.2f}"), ("fuel_ml_per_vkm", "fuel (mL/veh-km)", "{:.1f}"),
           ("throughput", "throughput (veh/h)", "{:.0f}"), ("min_gap", "min gap (m)", "{:.2f}"),
           ("collision", "collisions", "{:.0f}"), ("intervention", "intervention", "{:.3f}"))


def markdown(report: dict, title: str = "Stop-and-go waves") -> str:
    lines = [f"# {title}", "",
             f"Backend: {report.get('backend', 'torch')}. "
             f"{report['episodes']} episodes per ring length and controller (evaluation seed {report['eval_seed']}), "
             f"{report['episode_seconds']:g} s each, metrics after {report['warmup_seconds']:g} s; "
             f"hard braking: a < {report['hard_brake']:g} m/s². Mean ± std over episodes; min gap: smallest; "
             "collisions: total.", ""]
    for L, entry in report["rings"].items():
        lines += [f"## Ring {L} m (uniform-flow speed {entry['uniform_flow_speed']:.2f} m/s)", "",
                  "| controller | " + " | ".join(c[1] for c in COLUMNS) + " |", "|---|" + "---|" * len(COLUMNS)]
        for label, r in entry["controllers"].items():
            cells = []
            for key, _, fmt in COLUMNS:
                st = r["metrics"][key]
                if key == "collision":
                    cells.append(str(r["collisions"]))
                elif key == "min_gap":
                    cells.append(fmt.format(st["min"]))
                else:
                    cells.append(f"{fmt.format(st['mean'])} ± {fmt.format(st['std'])}")
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
        cmp = entry.get("comparison") or {}
        if cmp:
            lines += ["", "| controller | speed std vs human | hard braking vs human | fuel vs human | "
                      "mean speed / uniform flow |", "|---|---|---|---|---|"]
            for label, c in cmp.items():
                lines.append(f"| {label} | {-c['speed_std_reduction']:+.0%} | {-c['hard_brake_reduction']:+.0%} | "
                             f"{-c['fuel_reduction']:+.0%} | {c['mean_speed_vs_uniform']:.3f} |")
        lines.append("")
    acc = report.get("acceptance")
    if acc:
        lines += ["## Learned damper: acceptance", ""]
        for L, bars in acc.items():
            lines.append(f"- ring {L} m: " + ", ".join(f"{k} {'yes' if v else 'NO'}" for k, v in bars.items()))
        lines.append("")
    if report.get("plots"):
        lines += ["Plots: " + ", ".join(f"[{k}]({Path(v).name})" for k, v in report["plots"].items()), ""]
    return "\n".join(lines)


def plot_space_time(traces: dict, path: str | Path, *, title: str = "", every: int = 5,
                    last_seconds: float | None = 150.0) -> Path:
    """Position (along the ring) vs time, coloured by speed, one panel per controller.

    ``last_seconds`` keeps the end of the episode (the state the metrics measure) so single
    vehicles stay visible; ``None`` draws the whole episode.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = list(traces)
    fig, axes = plt.subplots(1, len(labels), figsize=(4.2 * len(labels), 4.2), sharey=True, squeeze=False)
    vmax = max(float(tr["speed"].max()) for tr in traces.values())
    sc = None
    for ax, label in zip(axes[0], labels, strict=True):
        tr = traces[label]
        keep = slice(None)
        if last_seconds is not None:
            keep = tr["time"] >= float(tr["time"][-1]) - last_seconds
        t = tr["time"][keep][::every].numpy()
        pos = tr["pos"][keep][::every].numpy()
        v = tr["speed"][keep][::every].numpy()
        tt = np.repeat(t[:, None], pos.shape[1], axis=1)
        sc = ax.scatter(tt.ravel(), pos.ravel(), c=v.ravel(), s=0.4, cmap="RdYlGn", vmin=0.0, vmax=vmax,
                        rasterized=True)
        for i in tr["cav_indices"]:
            ax.plot(t, pos[:, i], ".", color="black", ms=0.6)
        ax.set_title(label)
        ax.set_xlabel("time (s)")
    axes[0][0].set_ylabel("position on the ring (m)")
    fig.colorbar(sc, ax=axes[0].tolist(), label="speed (m/s)", shrink=0.9)
    if title:
        fig.suptitle(title)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return Path(path)


def write_wave_report(report: dict, traces: dict, out_dir: str | Path, *, title: str = "Stop-and-go waves") -> dict:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    plots = {}
    for L, by_ctrl in traces.items():
        plots[f"space_time_{L:g}m"] = plot_space_time(by_ctrl, out / f"space_time_{L:g}m.png",
                                                      title=f"{title}: ring {L:g} m (black: CAV)")
    report = dict(report, plots={k: str(v) for k, v in plots.items()})
    (out / "report.json").write_text(json.dumps(report, indent=2, default=lambda x: None if math.isnan(x) else x))
    (out / "report.md").write_text(markdown(report, title))
    return {"json": out / "report.json", "md": out / "report.md", **plots}


__all__ = ["wave_metrics", "evaluate_waves", "write_wave_report", "acceptance", "uniform_flow_speed", "fuel_rate",
           "hard_brake_events", "plot_space_time", "WAVE_METRICS"]
