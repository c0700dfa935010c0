"""On-policy loop: PPO and Lagrangian PPO (TorchRL Collector + GAE + ClipPPOLoss).

One iteration, CleanRL style::

    batch = collector.next()                        # [num_envs, rollout_len]
    penalty(batch)                                  # lagrangian_ppo, 1 critic: r <- r - lambda * c
    loss_module.update_lambda(batch)                # lagrangian_ppo, 2 critics: dual ascent on the batch cost
    gae(batch) for each critic                      # advantage(s), value target(s) (bootstrap on truncation)
    for epoch, minibatch in shuffled(batch):        # `epochs` passes
        loss = sum(loss_module(minibatch) terms)    # clipped surrogate + critic(s) - entropy
        loss += aux(minibatch)                      # optional BC on demonstrations / residual size
        loss.backward(); clip_grad_norm_; optim.step()
    penalty.update(batch)                           # 1 critic: dual ascent on lambda from the mean cost
"""

from __future__ import annotations

import functools
import time

import torch
from omegaconf import DictConfig
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from mixed_traffic.training import checkpoint as ck
from mixed_traffic.training.builders import (
    collector_rows,
    make_actor_critic,
    make_collector,
    make_transformed_env,
    make_value,
)
from mixed_traffic.training.metrics import batch_metrics
from mixed_traffic.training.run import Run


def build_ppo(cfg: DictConfig, env):
    """Actor, critic, loss, GAE estimators and (single-critic Lagrangian PPO) the reward penalty.

    * ``ppo``: ``ClipPPOLoss``, one GAE.
    * ``lagrangian_ppo`` with ``loss.critics=1`` (the ring seed's scheme): the batch reward is
      penalised in the main process by :class:`transforms.LagrangianPenalty` (``r - lambda c``)
      before GAE; :class:`losses.LagrangianPPOLoss` in its single-critic form shares the multiplier.
    * ``lagrangian_ppo`` with ``loss.critics=2``: a cost critic and a second GAE on the cost;
      :class:`losses.LagrangianPPOLoss` combines ``(A_R - lambda A_C) / (1 + lambda)`` and holds lambda.
    """
    lc = cfg.loss
    if lc.name not in ("ppo", "lagrangian_ppo"):
        raise ValueError(f"loss.name={lc.name!r} is invalid for trainer 'on_policy'; allowed: 'ppo', 'lagrangian_ppo'")
    actor, critic = make_actor_critic(cfg, env)
    kw = dict(clip_epsilon=lc.clip_epsilon, entropy_coeff=lc.entropy_coeff, critic_coeff=lc.critic_coeff,
              loss_critic_type=lc.loss_critic_type, normalize_advantage=lc.normalize_advantage,
              clip_value=lc.clip_value)
    lam = dict(lambda_init=lc.lambda_init, lambda_lr=lc.lambda_lr, lambda_max=lc.lambda_max,
               cost_limit=lc.violation_tolerance, lambda_method=lc.lambda_method)
    penalty = None
    gaes = [GAE(gamma=lc.gamma, lmbda=lc.gae_lambda, value_network=critic, average_gae=False)]
    if lc.name == "lagrangian_ppo" and lc.get("critics", 1) == 2:
        from losses import LagrangianPPOLoss

        cost_critic = make_value(cfg, env, "cost_value")
        loss = LagrangianPPOLoss(actor, critic, cost_critic, **lam, **kw)
        gaes.append(GAE(gamma=lc.gamma, lmbda=lc.gae_lambda, value_network=cost_critic, average_gae=False))
        gaes[-1].set_keys(reward="cost", value="cost_value", advantage="cost_advantage",
                          value_target="cost_value_target")
    elif lc.name == "lagrangian_ppo":
        from losses import LagrangianPPOLoss
        from transforms import LagrangianPenalty

        lam["cost_limit"], lam["method"] = lam.pop("cost_limit"), lam.pop("lambda_method")
        penalty = LagrangianPenalty(**lam, kp=lc.lambda_kp, kd=lc.lambda_kd)
        loss = LagrangianPPOLoss(actor, critic, None, multiplier=penalty.multiplier, **kw)
    else:
        loss = ClipPPOLoss(actor, critic, **kw)
    return actor, critic, loss, gaes, penalty


def demo_agent_mix(cfg: DictConfig) -> dict | None:
    """The agent shares of the BC demonstrations' bank: None (``loss.bc.agents: mixed``) or the env's."""
    agents = cfg.loss.bc.get("agents", "mixed")
    if agents not in ("mixed", "training"):
        raise ValueError(f"loss.bc.agents={agents!r} is invalid; allowed: 'mixed' or 'training'")
    if agents == "mixed":
        return None
    from mixed_traffic.intersection.demos import MIX_FIELDS

    ov = cfg.env.get("overrides") or {}
    mix = {k: float(ov.get(k, 0.0)) for k in MIX_FIELDS}
    if "hard_start_x" in ov:
        mix["hard_start_x"] = tuple(ov["hard_start_x"])
    return mix


class AuxiliaryLosses:
    """The optional terms added to the PPO loss of every minibatch (``loss.bc``, ``loss.residual_coeff``).

    * behaviour cloning: :class:`losses.BCLoss` on a random batch of the cached demonstrations,
      weight going linearly from ``bc.coeff`` to ``bc.final_coeff`` over the run (after
      ``bc.pretrain_steps`` steps of BC alone);
    * residual size: the same :class:`losses.BCLoss` towards a zero action (the base
      controller's), i.e. ``residual_coeff * mean(a_det^2)`` as in :class:`losses.ResidualMPCLoss`.
    """

    def __init__(self, cfg: DictConfig, actor, pretrain: bool):
        from losses import BCLoss

        lc, self.minibatch = cfg.loss, int(cfg.trainer.minibatch_size)
        self.bc = self.demo = self.residual = None
        b = lc.get("bc")
        if b is not None and b.coeff > 0:
            from mixed_traffic.intersection.demos import load_or_make

            self.demo = load_or_make(b.demos, expert=b.expert, episodes=b.episodes, seed=int(cfg.seed),
                                     mix=demo_agent_mix(cfg), expert_overrides=dict(b.get("expert_overrides") or {}))
            self.c0, self.c1 = float(b.coeff), float(b.coeff if b.final_coeff is None else b.final_coeff)
            self.bc = BCLoss(actor)
            if pretrain and b.pretrain_steps:
                opt = torch.optim.Adam(actor.parameters(), lr=b.pretrain_lr)
                for _ in range(int(b.pretrain_steps)):
                    opt.zero_grad()
                    self.bc(self.sample(512))["loss_bc"].backward()
                    opt.step()
        if lc.get("residual_coeff", 0.0) > 0:
            self.residual = BCLoss(actor, coeff=lc.residual_coeff)

    def sample(self, n: int):
        return self.demo[torch.randint(self.demo.shape[0], (min(n, self.demo.shape[0]),))]

    def bc_coeff(self, frac: float) -> float:
        return 0.0 if self.bc is None else self.c0 + (self.c1 - self.c0) * frac

    def __call__(self, mb, frac: float) -> dict:
        out = {}
        if self.bc is not None:
            out["loss_bc"] = self.bc_coeff(frac) * self.bc(self.sample(self.minibatch))["loss_bc"]
        if self.residual is not None:
            out["loss_residual"] = self.residual(mb.select(*self.residual.actor.in_keys, strict=False).set(
                "expert_action", torch.zeros_like(mb["action"])))["loss_bc"]
        return out


def restore_collection(cfg: DictConfig, env, collector, resume: dict) -> None:
    """Put the collection side of a checkpoint back, as far as it can be; say what cannot.

    The torch backend in one process (``trainer.collector=single``) restores exactly: the
    simulator tensors and the collector's carrier, so episodes in flight continue. A SUMO
    simulation's state lives inside SUMO and is not saved, and past one process the envs
    live in the workers: then the episodes in flight are lost and collection restarts
    from fresh episodes (the workers are seeded from the run seed and the iteration).
    """
    sumo = cfg.env.get("backend") == "sumo"
    single = cfg.trainer.get("collector", "single") == "single"
    if single and not sumo and resume.get("env") is not None and resume.get("collector") is not None:
        ck.load_env_runtime_state(env, resume["env"])
        ck.load_collector_state(collector, resume["collector"])
        return
    if single and sumo and resume.get("env"):  # its random generator: the next episodes draw as they would have
        ck.load_env_runtime_state(env, {k: v for k, v in resume["env"].items()
                                        if isinstance(v, tuple) and v and v[0] == "generator"})
    why = ("a SUMO simulation's state (vehicles, SUMO's clock) cannot be saved" if sumo else
           f"trainer.collector={cfg.trainer.collector}: the envs live in the collector's workers"
           if not single else "the checkpoint was written by a multi-process collector")
    print(f"resume: restored the learner, optimiser, Lagrange multiplier, counters and RNG; not the episodes in "
          f"flight ({why}): collection restarts from fresh episodes")


def train_on_policy(cfg: DictConfig, out_dir, resume: dict | None = None) -> dict:
    tc = cfg.trainer
    torch.manual_seed(cfg.seed)
    single = tc.get("collector", "single") == "single"
    # past one process the workers build their own envs; this one gives the specs
    env = make_transformed_env(cfg, num_envs=collector_rows(cfg), seed=cfg.seed)
    actor, critic, loss_module, gaes, penalty = build_ppo(cfg, env)
    ws = cfg.policy.get("warm_start")
    if ws is not None and ws.nnmpc and resume is None:  # Warm Start RL: the actor starts as the NNMPC
        from mixed_traffic.controllers.deeplcc.rlmpc import warm_start_actor

        warm_start_actor(actor, env, ws.nnmpc, frames=ws.frames, epochs=ws.epochs, lr=ws.lr, seed=cfg.seed)
    pretrained = {}  # what the trainers before PPO report, kept in summary.json
    if cfg.policy.get("apg") is not None and cfg.policy.apg.iterations and resume is None:
        from mixed_traffic.training.apg import apg_pretrain

        pretrained["apg"] = apg_pretrain(actor, cfg)
    if cfg.policy.get("cem") is not None and cfg.policy.cem.generations and resume is None:
        from mixed_traffic.training.cem import cem_pretrain

        pretrained["cem"] = cem_pretrain(actor, cfg)
    aux = AuxiliaryLosses(cfg, actor, pretrain=resume is None)  # before the run's clock starts
    two_critics = hasattr(loss_module, "update_lambda") and loss_module.cost_critic_network is not None
    scale = float(cfg.loss.get("reward_scale", 1.0))
    optim = torch.optim.Adam(loss_module.parameters(), lr=tc.lr)
    collector, fpb, n_iters = make_collector(cfg, env, actor, resume=resume)
    if tc.total_frames == 0:  # no PPO batches: e.g. a policy trained by policy.apg or policy.cem alone
        n_iters = 0
    if not single:
        env.close()  # only its specs were needed; a SUMO one would hold this process's libsumo
    run = Run.start(cfg, out_dir, n_iters, fpb)
    start_iter, frames = 0, 0
    if resume is not None:
        loss_module.load_state_dict(resume["model"])
        optim.load_state_dict(resume["optim"])
        if penalty is not None:
            penalty.multiplier.load_state_dict(resume["lagrange"])
        restore_collection(cfg, env, collector, resume)
        ck.load_rng_state(resume["rng"])
        start_iter, frames = resume["iteration"], resume["frames"]
        run.elapsed_before = resume["wall_seconds"]

    def payload(it):
        return {"model": loss_module.state_dict(), "optim": optim.state_dict(),
                "lagrange": penalty.multiplier.state_dict() if penalty is not None else None,
                "env": ck.env_runtime_state(env) if single else None,
                "collector": ck.collector_state(collector) if single else None,
                "rng": ck.rng_state(), "frames": frames, "kind": "ppo"}

    run.open_bar(start_iter)
    data = iter(collector)
    t_start, frames_start, it = time.perf_counter(), frames, start_iter
    stopped_early = False
    last, last_ret = {}, float("nan")
    try:
        for it in range(start_iter, n_iters):
            if tc.anneal_lr:
                for g in optim.param_groups:
                    g["lr"] = tc.lr * (1.0 - it / n_iters)
            batch = next(data)
            if batch.ndim > 2:  # multi_sync / ray: [workers, rows, T] -> [num_envs, T]
                batch = batch.reshape(-1, batch.shape[-1])
            frames += batch.numel()
            m = batch_metrics(batch)
            if penalty is not None:
                m["lambda"] = penalty.lam
                penalty(batch)  # r <- r - lambda * c (the multiplier of this batch)
            if two_critics:
                m["lambda"] = float(loss_module.lagrange_multiplier)
                m["lambda_next"] = loss_module.update_lambda(batch)  # on the batch's own mean cost
            if scale != 1.0:
                for k in ("reward", "cost"):
                    if ("next", k) in batch.keys(True):
                        batch.set(("next", k), batch.get(("next", k)) * scale)
            with torch.no_grad():
                for gae in gaes:
                    gae(batch)
            flat = batch.reshape(-1)
            n = flat.numel()
            mb = min(tc.minibatch_size, n)
            sums = {}
            n_updates = 0
            for _ in range(tc.epochs):
                perm = torch.randperm(n)
                for s in range(0, n - mb + 1, mb):
                    batch_mb = flat[perm[s:s + mb]]
                    out = loss_module(batch_mb)
                    out.update(aux(batch_mb, it / n_iters))
                    loss = out["loss_objective"] + out["loss_critic"] + out["loss_entropy"]
                    for k in ("loss_cost_critic", "loss_bc", "loss_residual"):
                        if k in out.keys():
                            loss = loss + out[k]
                    optim.zero_grad(set_to_none=True)
                    loss.backward()
                    gn = torch.nn.utils.clip_grad_norm_(loss_module.parameters(), tc.max_grad_norm)
                    optim.step()
                    n_updates += 1
                    for k in ("loss_objective", "loss_critic", "loss_entropy", "loss_cost_critic", "loss_bc",
                              "loss_residual", "entropy", "clip_fraction", "kl_approx"):
                        if k in out.keys():
                            sums[k] = sums.get(k, 0.0) + float(out[k].detach().mean())
                    sums["grad_norm"] = sums.get("grad_norm", 0.0) + float(gn)
            if not single:  # the workers' policy copies change only through TorchRL's weight sync
                collector.update_policy_weights_(actor)
            m.update({k: v / max(n_updates, 1) for k, v in sums.items()})
            if penalty is not None:
                m["lambda_next"] = penalty.update(m["mean_violation"])
            m["lr"] = optim.param_groups[0]["lr"]
            m["fps"] = (frames - frames_start) / max(time.perf_counter() - t_start, 1e-9)
            m["wall_seconds"] = run.wall()
            last = m
            if (it + 1) % tc.log_every == 0 or it + 1 == n_iters:
                run.log(m, frames, {"R/step": m["reward_per_step"], "return": m.get("episode_return", last_ret),
                                    "lam": m.get("lambda", 0.0), "coll": m["collisions"]})
            last_ret = m.get("episode_return", last_ret)
            done_iters = it + 1
            if run.end_iteration(done_iters, start_iter, functools.partial(payload, done_iters)):
                stopped_early = True
                break
    except KeyboardInterrupt:
        print(f"\ninterrupted: the last checkpoint is in {run.ckpt_dir}; resume with resume={run.out_dir}")
        raise
    finally:
        collector.shutdown()
        run.close()
    summary = {"name": cfg.name, "seed": cfg.seed, "algo": cfg.loss.name, "frames": frames,
               "iterations": it + 1 if n_iters else 0, "wall_seconds": run.wall(), "completed": not stopped_early,
               "final": {k: float(v) for k, v in last.items() if v is not None}, **pretrained}
    if not stopped_early:
        run.save_final({"model": loss_module.state_dict(), "actor": actor.state_dict(), "kind": "ppo",
                        "lagrange": penalty.lam if penalty is not None else None, "frames": frames}, summary)
    return {"summary": summary, "actor": actor, "env": env, "out_dir": run.out_dir, "stopped_early": stopped_early,
            "model": loss_module}
