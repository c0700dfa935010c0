"""The DeeP-LCC QP on noise-free torch IDM Hankel data, in SUMO, on the comparison's episodes.

Separates what the SUMO-collected Hankel data bring (``compare`` controller ``qp_sumo``): the
same pre-collection (seed 12345) in the torch platoon with IDM humans and no acceleration
noise, then the QP in the SUMO platoon on the episodes of
``python -m mixed_traffic.controllers.deeplcc.compare --backend sumo`` (env seed 10,000 + the
scenario's index, 3 episodes, behind the safety layer).

    python benchmarks/deeplcc_noise_free_qp.py --scenarios random1 random5 brake
"""

from __future__ import annotations

import argparse
import os
import sys

import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from mixed_traffic.controllers.deeplcc.compare import SCENARIOS, build, rollout_metrics  # noqa: E402
from mixed_traffic.controllers.deeplcc.controller import deeplcc_policy  # noqa: E402
from mixed_traffic.controllers.deeplcc.platoon import PlatoonConfig  # noqa: E402
from mixed_traffic.controllers.deeplcc.precollect import precollect  # noqa: E402
from mixed_traffic.controllers.deeplcc.qp import DeepLCCSolver, QPParams  # noqa: E402


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenarios", nargs="*", default=["random1", "random5", "brake", "sine"], choices=list(SCENARIOS))
    ap.add_argument("--episodes", type=int, default=3)
    ap.add_argument("--seed", type=int, default=10_000)
    ap.add_argument("--qp-seed", type=int, default=12345)
    a = ap.parse_args(argv)
    cfg = PlatoonConfig(hdv_model="idm", accel_noise=0.0)
    [h] = precollect(cfg, T=2000, generator=torch.Generator().manual_seed(a.qp_seed))
    cache = {"qp_idm": deeplcc_policy(DeepLCCSolver(h, QPParams.preset("dataset")))}
    out = {}
    for gi, sc in enumerate(a.scenarios):  # the compare's SUMO seeding: seed + the scenario's index
        env, pol = build("qp_idm", scenarios=(sc,), mismatch="idm", episodes=a.episodes, seed=a.seed + gi,
                         safety=True, runs={}, nnmpc="", cache=cache, backend="sumo")
        try:
            out[sc] = rollout_metrics(env, pol, (sc,), a.episodes)[sc]
        finally:
            env.close()
        print(sc, out[sc], flush=True)
    return out


if __name__ == "__main__":
    main()
