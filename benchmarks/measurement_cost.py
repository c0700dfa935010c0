"""What the measurement transforms cost a rollout: the ring bare, behind SensorNoise, and behind SensorNoise and
MeasurementFilter (the evaluation's ``eval.sensor_noise_*`` and ``eval.sensor_filter``).

    python benchmarks/measurement_cost.py --batch-sizes 20 1024 --steps 200 --repeats 5

Frames per second of ``env.rollout(steps)`` with a constant command, median of ``repeats`` after one warm-up
rollout, one torch thread; also the time :class:`transforms.MeasurementFilter` takes to build (its gains).
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
from torchrl.envs import Compose, TransformedEnv

from mixed_traffic import make_env
from transforms import MeasurementFilter, SensorNoise


def chains(sc) -> dict:
    kw = dict(tau=1.0, dt=sc.dt, observation=sc.observation, s_max=sc.s_max)
    return {"bare": lambda: [],
            "noise": lambda: [SensorNoise(1.0, 0.3, seed=0, **kw)],
            "noise + filter": lambda: [SensorNoise(1.0, 0.3, seed=0, **kw), MeasurementFilter(1.0, 0.3, **kw)]}


def rate(batch: int, build, steps: int, repeats: int) -> float:
    base = make_env("ring", batch_size=batch, seed=0, observation="relative")
    env = TransformedEnv(base, Compose(*build()))
    act = torch.zeros(batch, 1)

    def run():
        with torch.no_grad():
            env.rollout(steps, lambda td: td.set("action", act), break_when_any_done=False)

    run()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        run()
        times.append(time.perf_counter() - t0)
    return batch * steps / statistics.median(times)


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batch-sizes", type=int, nargs="+", default=[20, 1024])
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--repeats", type=int, default=5)
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    sc = make_env("ring", batch_size=1, seed=0, observation="relative").scenario
    t0 = time.perf_counter()
    MeasurementFilter(1.0, 0.3, tau=1.0, dt=sc.dt, s_max=sc.s_max)
    build_s = time.perf_counter() - t0
    out = {"filter_build_s": build_s, "rates": {}}
    print(f"MeasurementFilter(1.0, 0.3, tau=1.0) builds in {build_s:.2f} s")
    print("| B | chain | frames/s | against bare |\n|---|---|---|---|")
    for b in a.batch_sizes:
        bare = None
        for name, build in chains(sc).items():
            r = rate(b, build, a.steps, a.repeats)
            bare = bare or r
            out["rates"][f"{b}/{name}"] = r
            print(f"| {b} | {name} | {r:,.0f} | {r / bare:.2f} |", flush=True)
    return out


if __name__ == "__main__":
    main()
