"""All-human stop-and-go wave on the ``ring_wave`` ring: torch backend vs SUMO, same episodes.

Each episode runs in both simulators with the same seed (``batch_size=1``), i.e. the same ring
length, initial wave, human parameters and per-step human noise; the CAV slot (car 0) is
driven like the humans (the ``human`` damper, the same noise in both). Per episode, after the
warm-up, it measures:

- ``mean_speed`` (m/s), ``speed_std`` (m/s; across the cars at each step, averaged over time);
- ``amplitude`` (m/s): each car's speed standard deviation over time, averaged over cars;
- ``range`` (m/s): 95th minus 5th percentile of all the cars' speeds;
- ``period`` (s): first peak of the cars' mean speed autocorrelation (the time between two
  passages of the wave at one car);
- ``stopped``: share of car-steps below 0.5 m/s;
- ``diverge_s``: the first time the two simulators' speeds differ by more than 0.01 m/s.

    .venv/bin/python benchmarks/wave_agreement.py --ring-lengths 260 230 --episodes 4 --out outputs/wave_agreement.json
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from mixed_traffic import make_env
from mixed_traffic.controllers.dampers import make_damper


def run_episode(backend: str, seed: int, ring_length: float, seconds: float) -> np.ndarray:
    """Speeds ``[T, n]`` of one all-human episode (a lean loop over ``_step``: no rollout overhead)."""
    env = make_env("ring_wave", backend=backend, seed=seed, ring_length=float(ring_length),
                   episode_seconds=float(seconds))
    try:
        policy = make_damper("human", env, seed=seed)
        td = env.reset()
        out = []
        with torch.no_grad():
            for _ in range(env.scenario.max_steps):
                td = env._step(policy(td))
                out.append(td["traffic", "speed"][0].double().numpy().copy())
                if bool(td["done"].any()):
                    break
    finally:
        env.close()
    return np.stack(out)


def period(v: np.ndarray, dt: float) -> float:
    """First peak (after the first zero crossing) of the mean autocorrelation of the cars' speeds."""
    x = v - v.mean(0, keepdims=True)
    T = x.shape[0]
    f = np.fft.rfft(x, n=2 * T, axis=0)
    ac = np.fft.irfft(f * np.conj(f), axis=0)[:T].mean(1)
    ac = ac / max(ac[0], 1e-12)
    below = np.nonzero(ac < 0)[0]
    if below.size == 0:
        return float("nan")
    k0 = int(below[0])
    k = k0 + int(np.argmax(ac[k0:T // 2])) if k0 < T // 2 else k0
    return float(k * dt)


def metrics(v: np.ndarray, dt: float, warmup: float) -> dict:
    w = v[int(round(warmup / dt)):]
    return {"mean_speed": float(w.mean()), "speed_std": float(w.std(1).mean()),
            "amplitude": float(w.std(0).mean()),
            "range": float(np.percentile(w, 95) - np.percentile(w, 5)),
            "period": period(w, dt), "stopped": float((w < 0.5).mean())}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ring-lengths", type=float, nargs="+", default=[260.0, 230.0])
    ap.add_argument("--episodes", type=int, default=4)
    ap.add_argument("--seed", type=int, default=1000)
    ap.add_argument("--seconds", type=float, default=600.0)
    ap.add_argument("--warmup", type=float, default=300.0)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    dt = 0.1
    report = {"episodes": a.episodes, "seed": a.seed, "seconds": a.seconds, "warmup": a.warmup, "rings": {}}
    for L in a.ring_lengths:
        rows = []
        for e in range(a.episodes):
            t0 = time.time()
            vt = run_episode("torch", a.seed + e, L, a.seconds)
            t1 = time.time()
            vs = run_episode("sumo", a.seed + e, L, a.seconds)
            t2 = time.time()
            n = min(len(vt), len(vs))
            bad = np.nonzero(np.abs(vt[:n] - vs[:n]).max(1) > 0.01)[0]
            row = {"seed": a.seed + e, "torch": metrics(vt, dt, a.warmup), "sumo": metrics(vs, dt, a.warmup),
                   "diverge_s": float((bad[0] + 1) * dt) if bad.size else None,
                   "wall_s": {"torch": t1 - t0, "sumo": t2 - t1}}
            rows.append(row)
            print(f"L {L:g} seed {a.seed + e}: " + ", ".join(
                f"{k} {row['torch'][k]:.2f}/{row['sumo'][k]:.2f}" for k in row["torch"])
                + f" (torch/sumo), diverge {row['diverge_s']} s, wall {t1 - t0:.0f}/{t2 - t1:.0f} s", flush=True)
        mean = {b: {k: float(np.nanmean([r[b][k] for r in rows])) for k in rows[0]["torch"]} for b in ("torch", "sumo")}
        report["rings"][f"{L:g}"] = {"episodes": rows, "mean": mean}
        print(f"L {L:g} mean: " + ", ".join(f"{k} {mean['torch'][k]:.2f}/{mean['sumo'][k]:.2f}"
                                           for k in mean["torch"]), flush=True)
    if a.out:
        with open(a.out, "w") as f:
            json.dump(report, f, indent=2)
    return report


if __name__ == "__main__":
    main()
