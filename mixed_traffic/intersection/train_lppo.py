"""Training of the intersection learners: LPPO, LPPO+BC, LPPO+BFF and residual MPC.

Built on TorchRL: ``Collector`` on the batched :class:`IntersectionEnv` (wrapped in the
method's transform: :class:`transforms.barrier_force.BarrierForce` or
:class:`mixed_traffic.intersection.residual.ResidualNMPC`), two ``GAE`` estimators (reward
and cost critics), :class:`losses.LagrangianPPOLoss` (``A = (A_R - lambda A_C)/(1 + lambda)``,
lambda by dual ascent on the mean step cost) and, for LPPO+BC, :class:`losses.BCLoss`
towards NMPC actions on demonstrations generated here (the NMPC drives training episodes).
The residual method trains with :class:`losses.ResidualMPCLoss` (clipped PPO plus a penalty
on the deterministic residual's size, so it stays near the NMPC unless the returns say
otherwise) on the same Lagrangian advantage.

Methods and their fixed knobs live in :data:`METHODS`; the rest (budget, PPO and Lagrangian
hyperparameters, network) comes from the project's Hydra config (``experiment=intersection_*``).

Command line (a Hydra app on the project's config)::

    python -m mixed_traffic.intersection.train_lppo experiment=intersection_lppo trainer.total_frames=200000

>>> from mixed_traffic.intersection.train_lppo import TrainConfig, train
>>> out = train(TrainConfig(method="lppo", total_frames=512, num_envs=64, rollout_len=8, epochs=1,
...                         minibatch_size=256, eval_per_behaviour=0))
>>> sorted(out)[:3]
['actor', 'config', 'history']
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.envs import Compose, TransformedEnv
from torchrl.modules import ProbabilisticActor, TanhNormal
from torchrl.objectives.value import GAE

from losses import BCLoss, LagrangianPPOLoss
from mixed_traffic.envs.intersection import IntersectionEnv
from mixed_traffic.intersection.agent_model import sample_agent_trajectories
from mixed_traffic.intersection.nmpc import NMPCConfig, NMPCController, make_nmpc_policy
from mixed_traffic.intersection.residual import BASE_KEY, ResidualNMPC

METHODS = {
    # name: fixed knobs of the method
    # hard_fraction / hard_start_x: share of close-start agents in the training bank (hard_start_bank);
    # anticipation: weight of the training-only predicted-separation cost (anticipation_cost);
    # oob_cost: training-only cost of leaving the road (so reversing out is no escape from the cost)
    "lppo": {"hard_fraction": 0.5, "hard_start_x": (2.2, 2.6), "anticipation": 1.0, "oob_cost": 150.0},
    "lppo_bc": {"bc_coeff": 2.0, "bc_final_coeff": 1.0, "bc_episodes": 384, "bc_pretrain_steps": 600,
                "hard_fraction": 0.5, "hard_start_x": (2.2, 2.6), "anticipation": 1.0, "oob_cost": 150.0},
    "lppo_bff": {"bff_rho": 0.2, "bff_K": 0.5},
    "residual_mpc": {"residual_weight": 1.0, "residual_l2": 0.5},
}

OBS_SCALE = torch.tensor([1.5, 1.0, 2.0, 1.0, 1.0, 1.0, 0.1, 0.1])
OBS_SHIFT = torch.tensor([0.0, 0.8, 0.5, 0.3, -0.5, 0.0, 0.1, 0.1])


@dataclass
class TrainConfig:
    """Everything one intersection training run needs (see :func:`from_hydra`).

    >>> TrainConfig(method="lppo_bff").method
    'lppo_bff'
    """

    method: str = "lppo"
    seed: int = 0
    total_frames: int = 300_000
    num_envs: int = 256
    rollout_len: int = 32
    epochs: int = 4
    minibatch_size: int = 2048
    lr: float = 3e-4
    max_grad_norm: float = 0.5
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_epsilon: float = 0.2
    entropy_coeff: float = 0.0
    critic_coeff: float = 0.5
    hidden: list = field(default_factory=lambda: [64, 64])
    log_std_init: float = -0.5
    lambda_init: float = 1.0
    lambda_lr: float = 0.05
    lambda_max: float = 10.0
    cost_limit: float = 0.05  # tolerated mean cost per step
    reward_scale: float = 0.01  # rewards and costs are scaled alike for the critics
    start_noise: float = 0.15
    max_minutes: float | None = None
    eval_per_behaviour: int = 80
    eval_seed: int = 2024
    out_dir: str | None = None
    env_overrides: dict = field(default_factory=dict)  # further IntersectionEnv arguments
    demo_cache: str | None = "outputs/intersection/demos"  # where NMPC demonstrations are kept (None: regenerate)
    verbose: int = 0  # print a progress line every `verbose` iterations (0: silent)
    knobs: dict = field(default_factory=dict)

    def validate(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"method={self.method!r} is invalid; allowed: {sorted(METHODS)}")
        for name in ("total_frames", "num_envs", "rollout_len", "epochs", "minibatch_size"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 1):
                raise ValueError(f"{name}={v!r} is invalid; allowed: an integer >= 1")
        unknown = set(self.knobs) - set(METHODS[self.method])
        if unknown:
            raise ValueError(f"knobs {sorted(unknown)} are invalid for method {self.method!r}; "
                             f"allowed: {sorted(METHODS[self.method])}")

    def knob(self, name):
        return self.knobs.get(name, METHODS[self.method][name])


# ----------------------------------------------------------------------------- networks
N_FEATURES = 5


def relational_features(obs: torch.Tensor) -> torch.Tensor:
    """Ego-agent features an MLP finds hard to compute from raw coordinates (all O(1)).

    Relative position, distance, the agent's time to reach the ego's line and the ego's time
    to reach the agent's ``y`` (both clipped to [-5, 5] s).
    """
    y, v, xa, ya, vxa = obs[..., 0:1], obs[..., 1:2], obs[..., 2:3], obs[..., 3:4], obs[..., 4:5]
    dx, dy = xa - 0.5, ya - y
    d = torch.sqrt(dx**2 + dy**2)
    t_agent = (dx / (-vxa).clamp(min=0.05)).clamp(-5, 5)
    t_ego = (dy / v.clamp(min=0.1)).clamp(-5, 5)
    return torch.cat([dx / 2, dy / 2, d / 2, t_agent / 2, t_ego / 2], dim=-1)


class _Net(nn.Module):
    """MLP on the normalised observation (plus, for the residual, the NMPC action)."""

    def __init__(self, in_dim: int, out_dim: int, hidden, out_gain: float):
        super().__init__()
        layers, d = [], in_dim + N_FEATURES
        for h in hidden:
            lin = nn.Linear(d, h)
            nn.init.orthogonal_(lin.weight, math.sqrt(2))
            nn.init.zeros_(lin.bias)
            layers += [lin, nn.Tanh()]
            d = h
        out = nn.Linear(d, out_dim)
        nn.init.orthogonal_(out.weight, out_gain)
        nn.init.zeros_(out.bias)
        self.body = nn.Sequential(*layers, out)
        self.register_buffer("shift", OBS_SHIFT.clone())
        self.register_buffer("scale", OBS_SCALE.clone())

    def forward(self, obs, *extra):
        x = torch.cat([((obs - self.shift) / self.scale).clamp(-10, 10), relational_features(obs)], dim=-1)
        if extra:
            x = torch.cat([x, *[e / 3.2 for e in extra]], dim=-1)
        return self.body(x)


class _Gaussian(nn.Module):
    def __init__(self, net: _Net, log_std_init: float):
        super().__init__()
        self.net = net
        self.log_std = nn.Parameter(torch.tensor([float(log_std_init)]))

    def forward(self, *inputs):
        loc = self.net(*inputs)
        return loc, self.log_std.clamp(-3.0, 0.5).exp().expand_as(loc)


def make_networks(cfg: TrainConfig, env):
    """Actor (TanhNormal to the action bounds), reward critic and cost critic."""
    in_keys = ["observation"] + ([BASE_KEY] if cfg.method == "residual_mpc" else [])
    in_dim = 8 + (1 if cfg.method == "residual_mpc" else 0)
    spec = env.action_spec_unbatched
    actor = ProbabilisticActor(
        TensorDictModule(_Gaussian(_Net(in_dim, 1, cfg.hidden, 0.01), cfg.log_std_init), in_keys=in_keys,
                         out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"], spec=spec, distribution_class=TanhNormal,
        distribution_kwargs={"low": spec.space.low, "high": spec.space.high}, return_log_prob=True)
    critic = TensorDictModule(_Net(in_dim, 1, cfg.hidden, 1.0), in_keys=in_keys, out_keys=["state_value"])
    cost_critic = TensorDictModule(_Net(in_dim, 1, cfg.hidden, 1.0), in_keys=in_keys, out_keys=["cost_value"])
    return actor, critic, cost_critic


def method_transform(cfg: TrainConfig):
    """The env-side transform of the method (``None`` for LPPO and LPPO+BC)."""
    if cfg.method == "lppo_bff":
        from transforms.barrier_force import BarrierForce

        return BarrierForce(rho=cfg.knob("bff_rho"), K=cfg.knob("bff_K"))
    if cfg.method == "residual_mpc":
        return ResidualNMPC(weight=cfg.knob("residual_weight"), nmpc=NMPCController(NMPCConfig()))
    return None


def hard_start_bank(cfg: TrainConfig, bank_size: int = 2048):
    """The training agent bank with close-start agents oversampled (``None`` if the method has none).

    A fraction ``hard_fraction`` of the bank is replaced by agents (same training split and
    behaviours, an independent seed stream) whose start ``x`` is drawn from ``hard_start_x``,
    the near end of the start range: such an agent reaches the crossing ~1.5 s after the start,
    so going at once collides and the policy must learn to wait. The test set is untouched.
    """
    frac = float(cfg.knobs.get("hard_fraction", METHODS[cfg.method].get("hard_fraction", 0.0)))
    if frac <= 0.0:
        return None
    from mixed_traffic.intersection.agent_model import AgentModelParams, AgentTrajectories

    n_hard = max(1, int(round(frac * bank_size)))
    lo, hi = cfg.knobs.get("hard_start_x", METHODS[cfg.method].get("hard_start_x", (2.2, 2.8)))
    normal = sample_agent_trajectories(bank_size - n_hard, seed=cfg.seed, split="train")
    hard = sample_agent_trajectories(n_hard, seed=cfg.seed + 7919, split="train",
                                     params=AgentModelParams(start_x=(float(lo), float(hi))))
    return AgentTrajectories.cat([normal, hard])


def make_train_env(cfg: TrainConfig, num_envs: int | None = None):
    kw = {"agent_split": "train", **cfg.env_overrides, "start_noise": cfg.start_noise}
    bank = hard_start_bank(cfg)
    if bank is not None:
        kw["agent_trajectories"] = bank
    base = IntersectionEnv(batch_size=num_envs or cfg.num_envs, seed=cfg.seed, **kw)
    t = method_transform(cfg)
    return TransformedEnv(base, Compose(t)) if t is not None else TransformedEnv(base, Compose())


def anticipation_cost(obs: torch.Tensor, *, horizon_s: float = 1.5, dt: float = 0.1, radius: float = 0.3328,
                      mu: float = 200.0) -> torch.Tensor:
    """Training-only cost on the *predicted* separation: ``mu max(0, (2R + |sigma|)^2 - d_min^2)``.

    ``d_min`` is the smallest distance over the next ``horizon_s`` seconds when ego and perceived
    agent both keep their current velocities; it charges driving towards a conflict before the
    env's distance cost (which only sees the current separation) does. ``obs`` ``[..., 8]``.

    >>> o = torch.tensor([[-0.5, 2.0, 1.5, 0.5, -1.0, 0.0, 0.05, 0.05]])
    >>> bool(anticipation_cost(o) > 0), bool(anticipation_cost(o.index_fill(-1, torch.tensor([1]), 0.0)) == 0)
    (True, True)
    """
    tau = torch.arange(0.0, horizon_s + 1e-9, dt, dtype=obs.dtype, device=obs.device)
    y, v = obs[..., 0:1], obs[..., 1:2]
    xa, ya, vxa, vya = obs[..., 2:3], obs[..., 3:4], obs[..., 4:5], obs[..., 5:6]
    d2 = (0.5 - (xa + vxa * tau)) ** 2 + ((y + v * tau) - (ya + vya * tau)) ** 2
    sig = obs[..., 6:8].norm(dim=-1, keepdim=True)
    return mu * torch.clamp((2 * radius + sig) ** 2 - d2.min(dim=-1, keepdim=True).values, min=0.0)


# ----------------------------------------------------------------------------- demonstrations
@torch.no_grad()
def nmpc_demonstrations(n_episodes: int, *, seed: int, batch: int = 32, start_noise: float = 0.15) -> TensorDict:
    """``(observation, expert_action)`` pairs from the NMPC driving ``n_episodes`` training episodes.

    >>> demo = nmpc_demonstrations(2, seed=0, batch=2)
    >>> demo["expert_action"].shape[-1]
    1
    """
    obs_all, act_all = [], []
    policy = make_nmpc_policy()
    ctrl = policy.module
    bank = sample_agent_trajectories(n_episodes, seed=seed + 10_000, split="train")
    for start in range(0, n_episodes, batch):
        sub = bank.subset(torch.arange(start, min(n_episodes, start + batch)))
        env = IntersectionEnv(batch_size=len(sub), agent_trajectories=sub, agent_sampling="sequential",
                              start_noise=start_noise, seed=seed + start)
        ctrl.reset()
        td = env.reset()
        done = torch.zeros(len(sub), dtype=torch.bool)
        for _ in range(env.max_steps):
            alive = torch.nonzero(~done).squeeze(-1)
            ctrl.set_rows(alive.tolist())
            a = ctrl(td["observation"][alive])
            obs_all.append(td["observation"][alive].clone())
            act_all.append(a.clone())
            action = torch.zeros(len(sub), 1)
            action[alive] = a
            td["action"] = action
            td = env.step(td)
            done = done | td["next", "done"].squeeze(-1)
            if done.all():
                break
            td = td["next"]
        ctrl.set_rows(None)
    obs, act = torch.cat(obs_all), torch.cat(act_all)
    return TensorDict({"observation": obs, "expert_action": act}, batch_size=[obs.shape[0]])


# ----------------------------------------------------------------------------- training
def train(cfg: TrainConfig) -> dict:
    """Train one method; returns ``{"actor", "transform", "history", "eval", "config"}``.

    Writes ``final.pt`` (actor state), ``history.json`` and ``eval.json`` under ``out_dir`` if set.
    """
    cfg.validate()
    torch.manual_seed(cfg.seed)
    t0 = time.perf_counter()
    env = make_train_env(cfg)
    actor, critic, cost_critic = make_networks(cfg, env)
    loss = LagrangianPPOLoss(actor, critic, cost_critic, lambda_init=cfg.lambda_init, lambda_lr=cfg.lambda_lr,
                             lambda_max=cfg.lambda_max, cost_limit=cfg.cost_limit, clip_epsilon=cfg.clip_epsilon,
                             entropy_coeff=cfg.entropy_coeff, critic_coeff=cfg.critic_coeff,
                             normalize_advantage=True)
    res_loss = None
    if cfg.method == "residual_mpc":
        from losses import ResidualMPCLoss

        res_loss = ResidualMPCLoss(actor, critic, residual_coeff=cfg.knob("residual_l2"), clip_epsilon=cfg.clip_epsilon,
                                   entropy_coeff=cfg.entropy_coeff, critic_coeff=cfg.critic_coeff,
                                   normalize_advantage=True)
    gae_r = GAE(gamma=cfg.gamma, lmbda=cfg.gae_lambda, value_network=critic, average_gae=False)
    gae_c = GAE(gamma=cfg.gamma, lmbda=cfg.gae_lambda, value_network=cost_critic, average_gae=False)
    gae_c.set_keys(reward="cost", value="cost_value", advantage="cost_advantage", value_target="cost_value_target")
    params = list(actor.parameters()) + list(critic.parameters()) + list(cost_critic.parameters())
    optim = torch.optim.Adam(params, lr=cfg.lr)
    history: list[dict] = []

    bc = demo = None
    if cfg.method == "lppo_bc":
        cache = Path(cfg.demo_cache) / f"nmpc_demos_seed{cfg.seed}_n{cfg.knob('bc_episodes')}.pt" if cfg.demo_cache else None
        if cache is not None and cache.exists():
            demo = torch.load(cache, weights_only=False)
        else:
            demo = nmpc_demonstrations(cfg.knob("bc_episodes"), seed=cfg.seed)
            if cache is not None:
                cache.parent.mkdir(parents=True, exist_ok=True)
                torch.save(demo, cache)
        bc = BCLoss(actor, coeff=1.0)
        _bc_pretrain(actor, bc, demo, steps=cfg.knob("bc_pretrain_steps"), lr=1e-3)
        history.append({"bc_pretrain_mse": float(bc(demo[:4096])["bc_mse"]), "demo_samples": demo.shape[0]})

    fpb = cfg.num_envs * cfg.rollout_len
    n_iters = max(1, math.ceil(cfg.total_frames / fpb))
    collector = Collector(env, actor, frames_per_batch=fpb, total_frames=n_iters * fpb,
                          auto_register_policy_transforms=False)
    frames = 0
    for it, batch in enumerate(collector):
        frames += batch.numel()
        nxt = batch["next"]
        done = nxt["done"].squeeze(-1)
        n_done = int(done.sum())
        row = {"iter": it, "frames": frames,
               "reward_step": float(nxt["reward"].mean()), "cost_step": float(nxt["cost"].mean()),
               "episodes": n_done,
               "success": float(nxt["success"].squeeze(-1)[done].float().mean()) if n_done else float("nan"),
               "collision": float(nxt["collision"].squeeze(-1)[done].float().mean()) if n_done else float("nan"),
               "lambda": float(loss.lagrange_multiplier)}
        w_ant = float(cfg.knobs.get("anticipation", METHODS[cfg.method].get("anticipation", 0.0)))
        if w_ant > 0:  # training-only cost on the predicted separation (see anticipation_cost)
            alive = ~nxt["done"]
            extra = w_ant * anticipation_cost(nxt["observation"]) * alive
            batch.set(("next", "cost"), nxt["cost"] + extra)
            nxt = batch["next"]
        oob_cost = float(cfg.knobs.get("oob_cost", METHODS[cfg.method].get("oob_cost", 0.0)))
        if oob_cost > 0:  # leaving the road backwards must not be a cheap escape from the cost
            batch.set(("next", "cost"), nxt["cost"] + oob_cost * nxt["out_of_bounds"].to(nxt["cost"].dtype))
            nxt = batch["next"]
        lam = loss.update_lambda(batch)
        row["lambda_new"] = float(lam)
        batch.set(("next", "reward"), nxt["reward"] * cfg.reward_scale)
        batch.set(("next", "cost"), nxt["cost"] * cfg.reward_scale)
        with torch.no_grad():
            gae_r(batch)
            gae_c(batch)
        flat = batch.reshape(-1)
        frac = min(1.0, frames / max(cfg.total_frames, 1))
        for g in optim.param_groups:
            g["lr"] = cfg.lr * (1.0 - 0.9 * frac)
        bc_coeff = 0.0
        if bc is not None:
            c0, c1 = cfg.knob("bc_coeff"), cfg.knob("bc_final_coeff")
            bc_coeff = c0 + (c1 - c0) * frac
        stats = []
        for _ in range(cfg.epochs):
            perm = torch.randperm(flat.shape[0])
            for s in range(0, flat.shape[0], cfg.minibatch_size):
                mb = flat[perm[s:s + cfg.minibatch_size]]
                if res_loss is None:
                    out = loss(mb)
                    total = out["loss_objective"] + out["loss_critic"] + out["loss_entropy"] + out["loss_cost_critic"]
                else:
                    # residual MPC: ResidualMPCLoss on the Lagrangian advantage, cost critic from the LPPO loss
                    lam_t = loss.lagrange_multiplier.to(mb["advantage"])
                    mb = mb.clone(False)
                    mb.set("advantage", (mb["advantage"] - lam_t * mb["cost_advantage"]) / (1.0 + lam_t))
                    out = res_loss(mb)
                    out.set("loss_cost_critic", loss.loss_cost_critic(mb))
                    total = (out["loss_objective"] + out["loss_critic"] + out["loss_entropy"] + out["loss_residual"]
                             + out["loss_cost_critic"])
                if bc is not None:
                    d = demo[torch.randint(demo.shape[0], (min(cfg.minibatch_size, demo.shape[0]),))]
                    total = total + bc_coeff * bc(d)["loss_bc"]
                optim.zero_grad()
                total.backward()
                nn.utils.clip_grad_norm_(params, cfg.max_grad_norm)
                optim.step()
                stats.append([float(out["loss_objective"].detach()), float(out["loss_critic"].detach()),
                              float(out["loss_cost_critic"].detach())])
        s = np.mean(stats, 0)
        row.update(loss_objective=s[0], loss_critic=s[1], loss_cost_critic=s[2], bc_coeff=bc_coeff,
                   wall_s=time.perf_counter() - t0)
        history.append(row)
        if cfg.verbose and it % cfg.verbose == 0:
            print({k: (round(v, 4) if isinstance(v, float) else v) for k, v in row.items()
                   if k in ("iter", "frames", "episodes", "success", "collision", "lambda", "reward_step", "cost_step",
                            "wall_s")}, flush=True)
        if cfg.max_minutes is not None and (time.perf_counter() - t0) > 60 * cfg.max_minutes:
            break
    collector.shutdown()
    result = {"actor": actor, "transform": method_transform(cfg), "history": history, "config": asdict(cfg),
              "train_seconds": time.perf_counter() - t0}
    if cfg.eval_per_behaviour > 0:
        from mixed_traffic.intersection.evaluate import evaluate_policy

        res = evaluate_policy(actor, n_per_behaviour=cfg.eval_per_behaviour, seed=cfg.eval_seed,
                              transform=result["transform"])
        result["eval"] = res.table
        result["eval_result"] = res
        result["outcomes"] = outcomes(res)
    if cfg.out_dir:
        out = Path(cfg.out_dir)
        out.mkdir(parents=True, exist_ok=True)
        torch.save({"actor": actor.state_dict(), "config": asdict(cfg)}, out / "final.pt")
        (out / "history.json").write_text(json.dumps(history, indent=1))
        if "eval" in result:
            (out / "eval.json").write_text(json.dumps({"eval": result["eval"], "outcomes": result["outcomes"],
                                                       "train_seconds": result["train_seconds"],
                                                       "frames": history[-1].get("frames") if history else 0},
                                                      indent=2))
    return result


def outcomes(res) -> dict:
    """Per-episode outcome codes of an evaluation: ``S`` success, ``C`` collision, ``T`` timeout, ``O`` out of bounds."""
    codes = np.where(res.success, "S", np.where(res.collision, "C", np.where(res.timeout, "T", "O")))
    return {"codes": "".join(codes.tolist()), "steps": res.steps.astype(int).tolist()}


def _bc_pretrain(actor, bc: BCLoss, demo: TensorDict, *, steps: int, lr: float, batch: int = 512):
    opt = torch.optim.Adam(actor.parameters(), lr=lr)
    for _ in range(steps):
        d = demo[torch.randint(demo.shape[0], (min(batch, demo.shape[0]),))]
        loss = bc(d)["loss_bc"]
        opt.zero_grad()
        loss.backward()
        opt.step()


def load_actor(path: str | Path):
    """Rebuild a trained actor (and its method transform) from ``final.pt``.

    Returns ``(actor, transform, config)``.
    """
    ck = torch.load(path, map_location="cpu", weights_only=False)
    cfg = TrainConfig(**ck["config"])
    env = make_train_env(TrainConfig(**{**ck["config"], "method": "lppo"}), num_envs=1)
    actor, _, _ = make_networks(cfg, env)
    actor.load_state_dict(ck["actor"])
    return actor, method_transform(cfg), cfg


# ----------------------------------------------------------------------------- Hydra
def from_hydra(hcfg) -> TrainConfig:
    """Map the project's composed config (``experiment=intersection_*``) to a :class:`TrainConfig`."""
    name = str(hcfg.name)
    method = name.removeprefix("intersection_")
    if method not in METHODS:
        raise ValueError(f"name={name!r} is invalid for intersection training; allowed: "
                         f"{['intersection_' + m for m in METHODS]}")
    tc, lc, pc = hcfg.trainer, hcfg.loss, hcfg.policy
    overrides = dict(hcfg.env.get("overrides") or {})
    return TrainConfig(
        method=method, seed=int(hcfg.seed), total_frames=int(tc.total_frames), num_envs=int(tc.num_envs),
        rollout_len=int(tc.rollout_len), epochs=int(tc.epochs), minibatch_size=int(tc.minibatch_size), lr=float(tc.lr),
        max_grad_norm=float(tc.max_grad_norm), gamma=float(lc.gamma), gae_lambda=float(lc.gae_lambda),
        clip_epsilon=float(lc.clip_epsilon), entropy_coeff=float(lc.entropy_coeff), critic_coeff=float(lc.critic_coeff),
        hidden=list(pc.hidden), log_std_init=float(pc.log_std_init), lambda_init=float(lc.lambda_init),
        lambda_lr=float(lc.lambda_lr), lambda_max=float(lc.lambda_max), cost_limit=float(lc.violation_tolerance),
        start_noise=float(overrides.pop("start_noise", 0.15)), env_overrides=overrides,
        max_minutes=None if tc.max_minutes is None else float(tc.max_minutes),
        eval_per_behaviour=int(hcfg.eval.episodes), eval_seed=int(hcfg.eval.seed))


def run_nmpc_experiment(hcfg, out_dir: str | Path | None = None) -> dict:
    """``experiment=intersection_nmpc``: no training; evaluate the NMPC on the test set."""
    from mixed_traffic.intersection.evaluate import evaluate_policy

    res = evaluate_policy(make_nmpc_policy(), n_per_behaviour=int(hcfg.eval.episodes), seed=int(hcfg.eval.seed))
    out = {"eval": res.table, "nmpc": res.extra.get("nmpc"), "outcomes": outcomes(res)}
    if out_dir:
        Path(out_dir).mkdir(parents=True, exist_ok=True)
        (Path(out_dir) / "eval.json").write_text(json.dumps(out, indent=2))
    return out


def main(argv: list[str] | None = None) -> dict:
    """Compose ``hydra_configs`` with the command-line overrides and run the experiment."""
    import sys

    from mixed_traffic.config import compose

    args = list(sys.argv[1:] if argv is None else argv)
    out_dir = None
    for a in list(args):
        if a.startswith("out_dir="):
            out_dir = a.split("=", 1)[1]
            args.remove(a)
    hcfg = compose(args)
    out_dir = out_dir or f"outputs/intersection/{hcfg.name}_seed{hcfg.seed}"
    return run_experiment(hcfg, out_dir)


def run_experiment(hcfg, out_dir: str | Path) -> dict:
    """Run one composed intersection experiment (``mt-train experiment=intersection_*`` calls this)."""
    from mixed_traffic.intersection.evaluate import format_table

    torch.set_num_threads(max(1, int(hcfg.threads)))
    name = str(hcfg.name)
    if name == "intersection_nmpc":
        out = run_nmpc_experiment(hcfg, out_dir)
    else:
        cfg = from_hydra(hcfg)
        cfg.out_dir = str(out_dir)
        cfg.verbose = 3
        out = train(cfg)
    if "eval" in out:
        print(format_table(out["eval"], title=name))
    print(f"outputs: {out_dir}")
    return out


if __name__ == "__main__":
    main()
