"""Linear string stability of a car-following law at its equilibria, printed as a markdown table.

Linearised about the steady state at speed ``v`` (gap ``S(v)``, found by bisection on ``f(S, v, v) = 0``), a law
``a = f(s, v, v_leader)`` with ``ks = df/ds``, ``kv = df/dv_leader`` and the desired gap's slope
``S' = dS/dv = -(df/dv + df/dv_leader) / df/ds`` passes its leader's speed to its own through

    H(s) = (kv s + ks) / (s^2 + (kv + ks S') s + ks),

and ``|H(jw)| <= 1`` at every ``w`` (no oscillation of the leader's speed amplified) exactly when
``2 kv S' + ks S'^2 >= 2``. The partial derivatives are central differences of the project's own law
(:func:`mixed_traffic.physics.idm_accel`), or of a linear spring and damper on the gap ``s0 + h v``
(``--linear ks kv h s0``). TorchRL and the project have no such check; it is a few lines of algebra::

    python benchmarks/string_stability.py --speeds 3 5 10 16                 # IDM-as-CAV (IDMParams())
    python benchmarks/string_stability.py --speeds 10 16 --linear 0.4 0.55 1.3 0.5
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys

import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from mixed_traffic.physics import IDMParams, idm_accel  # noqa: E402


def law(args) -> tuple[str, callable]:
    """``(name, f(gap, v, v_leader))`` in float64."""
    if args.linear:
        ks, kv, h, s0 = args.linear
        return (f"linear ks {ks} kv {kv} h {h} s0 {s0}",
                lambda s, v, vl: ks * (s - s0 - h * v) + kv * (vl - v))
    p = dataclasses.asdict(IDMParams())
    for kv in args.idm:
        key, _, value = kv.partition("=")
        if key not in p:
            raise SystemExit(f"--idm: {key!r} is not an IDM parameter; allowed: {sorted(p)}")
        p[key] = float(value)
    return (f"IDM {p}", lambda s, v, vl: idm_accel(s, v, vl, **p))


def equilibrium_gap(f, v: float, hi: float = 1e4) -> float:
    """The gap where ``f(gap, v, v) = 0`` (``f`` falls as the gap shrinks), by bisection."""
    lo, v_t = 1e-3, torch.tensor(v, dtype=torch.float64)
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if f(torch.tensor(mid, dtype=torch.float64), v_t, v_t) > 0:
            hi = mid
        else:
            lo = mid
    return 0.5 * (lo + hi)


def linearise(f, v: float, eps: float = 1e-4) -> dict[str, float]:
    """``ks``, ``kv``, ``S'``, the criterion ``2 kv S' + ks S'^2`` and ``max |H(jw)|`` at speed ``v``."""
    s = equilibrium_gap(f, v)
    t = lambda x: torch.tensor(x, dtype=torch.float64)  # noqa: E731
    d = lambda g: float((g(+eps) - g(-eps)) / (2 * eps))  # noqa: E731
    fs = d(lambda e: f(t(s + e), t(v), t(v)))
    fv = d(lambda e: f(t(s), t(v + e), t(v)))
    fl = d(lambda e: f(t(s), t(v), t(v + e)))
    slope = -(fv + fl) / fs
    w = torch.logspace(-3, 2, 20000, dtype=torch.float64)
    jw = 1j * w
    h = (fl * jw + fs) / (jw**2 - fv * jw + fs)
    return {"gap": s, "ks": fs, "kv": fl, "slope": slope, "criterion": 2 * fl * slope + fs * slope**2,
            "max_h": float(h.abs().max())}


def main(argv=None) -> str:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--speeds", nargs="+", type=float, default=[3.0, 5.0, 10.0, 16.0])
    p.add_argument("--idm", nargs="*", default=[], metavar="KEY=VALUE", help="IDMParams fields to change")
    p.add_argument("--linear", nargs=4, type=float, metavar=("KS", "KV", "H", "S0"))
    args = p.parse_args(argv)
    if any(v <= 0 for v in args.speeds):
        raise SystemExit(f"--speeds must be > 0 m/s, got {args.speeds}")
    name, f = law(args)
    rows = [f"{name}\n", "| speed (m/s) | gap (m) | ks | kv | S' (s) | 2 kv S' + ks S'^2 | max abs H |",
            "|---|---|---|---|---|---|---|"]
    for v in args.speeds:
        r = linearise(f, v)
        rows.append(f"| {v:g} | {r['gap']:.2f} | {r['ks']:.3f} | {r['kv']:.3f} | {r['slope']:.3f} | "
                    f"{r['criterion']:.2f} | {r['max_h']:.3f} |")
    text = "\n".join(rows)
    print(text)
    return text


if __name__ == "__main__":
    main()
