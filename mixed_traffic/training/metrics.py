"""Per-batch training metrics read from a collected batch (keys of docs/architecture.md)."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase


def batch_metrics(batch: TensorDictBase) -> dict:
    """Reward, episode returns, collisions, violation and safety-clip rate of one batch.

    Read before any Lagrangian penalty is applied, so ``reward_per_step`` and
    ``episode_return`` are the task reward.
    """
    nxt = batch.get("next")
    m = {"reward_per_step": float(nxt.get("reward").float().mean())}
    cost = nxt.get("cost", None)
    m["mean_violation"] = float(cost.float().mean()) if cost is not None else 0.0
    coll = nxt.get("collision", None)
    m["collisions"] = int(coll.sum()) if coll is not None else 0
    done = nxt.get("done").reshape(nxt.batch_size)
    if done.any() and "episode_reward" in nxt.keys():
        ep = nxt.get("episode_reward").reshape(*nxt.batch_size, -1).sum(-1)[done]
        m["episode_return"] = float(ep.mean())
        m["episodes"] = int(done.sum())
        if "step_count" in nxt.keys():
            length = nxt.get("step_count").reshape(nxt.batch_size)[done].float()
            m["episode_length"] = float(length.mean())
            # comparable across episode lengths (the first episodes are shortened by desync_start)
            m["episode_reward_per_step"] = float((ep / length.clamp_min(1)).mean())
    clipped = nxt.get(("safety", "clipped"), None)
    if clipped is not None:
        m["safety_clip_rate"] = float(clipped.float().mean())
        m["safety_delta_abs"] = float(nxt.get(("safety", "delta")).abs().mean())
    ic = nxt.get(("safety", "intervention_cost"), None)
    if ic is not None:
        m["intervention_cost"] = float(ic.float().mean())
    gap = nxt.get(("cav", "gap"), None)
    hg = None
    if gap is not None:
        m["gap_min"] = float(gap.min())
        hg = nxt.get(("cav", "head_gap"), None)
        if hg is not None:  # rings without a head have no head gap
            m["head_gap_mean"] = float(hg.mean())
            sp, hs = nxt.get(("cav", "speed")), nxt.get(("cav", "head_speed"))
            m["speed_err_abs"] = float((sp - hs).abs().mean())
    speed = nxt.get(("traffic", "speed"), None)
    if speed is not None and hg is None:
        m["speed_mean"] = float(speed.mean())
        m["speed_std"] = float(speed.std(-1, unbiased=False).mean())  # spread across vehicles (waves)
    return {k: v for k, v in m.items() if v is not None and not (isinstance(v, float) and torch.isnan(torch.tensor(v)))}
