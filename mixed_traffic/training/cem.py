"""Cross-entropy method (CEM): black-box search over the actor's parameters on whole-episode returns.

A population of parameter vectors drawn around a mean is scored by running each one's
deterministic action for whole episodes; the mean moves to the best of them::

    mu, sigma <- the actor's parameters (or its output layer zeroed: init=zero_action), policy.cem.sigma
    kept <- mu
    for g in range(generations):
        theta_k ~ N(mu, sigma^2), k = 2..P-1;  theta_0 = mu;  theta_1 = kept
        F_k = mean over candidate k's episodes of  mean_t r_t - cost_coeff * max(mean_t c_t - cost_limit, 0)
              (t >= score_after; a collision costs cost_coeff more)
        if F_0 > F_1: kept <- mu
        elite = the ceil(elite * P) best F_k
        mu <- mean(elite);  sigma <- max(std(elite), sigma_min)
    actor <- kept

The mean kept is the one that beat the previous keeper on the same episodes: a mean of elite
parameter vectors can be worse than its elites, and scores of different generations come
from different episodes, so neither the last mean nor the best-scoring one is taken blindly.

All ``P x episodes`` episodes run as one batched rollout of the run's env (row ``i`` driven by
candidate ``i // episodes``; the network is evaluated for every candidate at once with
``torch.func.vmap``), so a generation costs about one rollout. On the torch rings every
candidate drives the same ``episodes`` starts (ring length, positions, the humans'
parameters: ``TrafficEnv.share_starts``; only the humans' per-step noise differs), so
candidates are compared on common episodes; each generation draws new ones.

Why this exists beside TorchRL's losses: TorchRL has no evolution-strategy or CEM trainer, and
its objectives all assign credit step by step (likelihood ratios over a critic's advantage). A
wave damper's set point acts over minutes: raising it pays now and brings the stop-and-go wave
back a minute later, below what a discounted per-step advantage resolves from the humans'
noise (``docs/wave.md``, "What did not work"). Scoring whole episodes needs no credit
assignment. It needs no gradient, so any batched env of the pipeline serves (the torch
backends; the SUMO backend runs one row and refuses the batch), and the policy it leaves is
the actor itself (PPO may train it further: ``trainer.total_frames`` after it).

>>> from mixed_traffic.config import compose
>>> from mixed_traffic.training.builders import make_transformed_env
>>> from mixed_traffic.training.on_policy import build_ppo
>>> cfg = compose(["experiment=ring_wave_cem", "policy.cem.generations=1", "policy.cem.population=2",
...                "policy.cem.episodes=1", "policy.cem.seconds=1.0", "policy.cem.score_after=0",
...                "trainer.progress=false"])
>>> actor = build_ppo(cfg, make_transformed_env(cfg, num_envs=2, seed=0))[0]
>>> cem_pretrain(actor, cfg, log=None)["generations"]
1
"""

from __future__ import annotations

import math
import time

import torch
from omegaconf import DictConfig
from torch import nn
from torch.func import functional_call, vmap
from torch.nn.utils import parameters_to_vector, vector_to_parameters
from tqdm.auto import tqdm

from mixed_traffic.training.plain_actor import PlainSequence


class PopulationPolicy(nn.Module):
    """``td -> td`` with the deterministic action of candidate ``i // episodes`` on row ``i``.

    Args:
        actor: a ``ProbabilisticActor`` whose first module writes ``loc`` and ``scale`` (the
            pipeline's actor); its parameters are left untouched.
        thetas: ``[P, n]`` flat parameter vectors (the order of ``actor.module[0].parameters()``).
        episodes: rows per candidate; the env has ``P * episodes`` rows.
    """

    def __init__(self, actor, thetas: torch.Tensor, episodes: int):
        super().__init__()
        self.actor, self.episodes = actor, int(episodes)
        self.net = PlainSequence(actor.module[0])
        names = [n for n, _ in self.net.named_parameters()]
        shapes = [p.shape for _, p in self.net.named_parameters()]
        P, out, i = thetas.shape[0], {}, 0
        for name, shape in zip(names, shapes):
            k = math.prod(shape)
            out[name] = thetas[:, i:i + k].reshape(P, *shape)
            i += k
        self.params, self.P = out, P

    def forward(self, td):
        ins = [td.get(k) for k in self.net.in_keys]
        shaped = [x.reshape(self.P, self.episodes, *x.shape[1:]) for x in ins]
        loc, scale = vmap(lambda p, *x: functional_call(self.net, p, x))(self.params, *shaped)
        td.set("loc", loc.reshape(-1, *loc.shape[2:]))
        td.set("scale", scale.reshape(-1, *scale.shape[2:]))
        dist = self.actor.module[1].get_dist(td)
        return td.set(self.actor.module[1].out_keys[0], dist.deterministic_sample)


def score(td, cost_coeff: float, start: int = 0, cost_limit: float = 0.0) -> torch.Tensor:
    """Per row of a ``[rows, T]`` rollout: ``mean_t reward - cost_coeff * max(mean_t cost - cost_limit, 0)`` over its first episode.

    ``cost_limit`` is a budget of mean cost per step that is free (as a Lagrangian's cost
    limit): the safety layer's work below it is not traded against reward.

    Steps ``start ..`` count (the first ``start`` are a warm-up that is not scored, save for
    a collision in it). The steps after a row's first ``done`` (the next episode, started by
    the rollout) do not count; an episode that ends early in a collision scores its missing
    steps as reward 0 and cost 1, and the collision itself as cost 1 per step.
    """
    from mixed_traffic.evaluation.harness import first_done_mask

    nxt = td.get("next")
    valid = first_done_mask(nxt.get("done").reshape(td.shape)).double()
    collided = (nxt.get("collision").reshape(td.shape) & valid.bool()).any(1).double()
    valid = valid[:, start:]
    T = valid.shape[1]
    r = (nxt.get("reward").reshape(td.shape)[:, start:].double() * valid).sum(1) / T
    c = (nxt.get("cost").reshape(td.shape)[:, start:].double() * valid).sum(1) + (T - valid.sum(1))
    return r - cost_coeff * ((c / T - cost_limit).clamp_min(0.0) + collided)


def cem_update(thetas: torch.Tensor, F: torch.Tensor, n_elite: int, sigma_min: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The new ``(mu, sigma)``: mean and std (floored at ``sigma_min``) of the ``n_elite`` best rows of ``thetas``."""
    elite = thetas[torch.topk(F, n_elite).indices].double()
    sigma = elite.std(0, unbiased=False) if n_elite > 1 else torch.zeros_like(elite[0])
    return elite.mean(0), sigma.clamp_min(float(sigma_min))


def cem_pretrain(actor, cfg: DictConfig, *, log=print) -> dict:
    """Fit ``actor``'s deterministic action by CEM on the run's env (``cfg.policy.cem``).

    Returns ``{"generations", "stopped", "best_first", "best_last", "mean_last", "score_of_mean",
    "kept_generation", "kept_score", "seconds"}`` (``generations``: how many ran; ``stopped``: why
    fewer than ``policy.cem.generations``, else None; scores: the best and the population mean of :func:`score` per
    generation, and each generation's mean's). The actor ends at the kept mean: each generation
    scores its mean (candidate 0) and the keeper (candidate 1) on the same episodes, and the mean
    replaces the keeper when it scores higher.

    ``trainer.max_minutes`` bounds the search on its own clock: it stops before a generation
    that would end past the budget (at the slowest generation's pace so far); the first
    generation always runs.
    """
    from mixed_traffic.training.builders import TRAINING_ONLY, make_transformed_env

    c = cfg.policy.cem
    for name in ("generations", "population", "episodes"):
        v = c[name]
        if not (isinstance(v, int) and v >= (2 if name == "population" else 1)):
            raise ValueError(f"policy.cem.{name}={v!r} is invalid; allowed: an integer >= "
                             f"{2 if name == 'population' else 1}")
    if not (0 < c.elite <= 1 and c.sigma > 0 and 0 <= c.sigma_min <= c.sigma and c.cost_coeff >= 0):
        raise ValueError(f"policy.cem: elite={c.elite}, sigma={c.sigma}, sigma_min={c.sigma_min}, "
                         f"cost_coeff={c.cost_coeff} are invalid; allowed: 0 < elite <= 1, sigma > 0, "
                         "0 <= sigma_min <= sigma, cost_coeff >= 0")
    seconds = c.get("seconds")
    if seconds is not None and not float(seconds) > 0:
        raise ValueError(f"policy.cem.seconds={seconds!r} is invalid; allowed: null (the scenario's episode) or > 0 (s)")
    if not hasattr(actor, "module") or len(actor.module) != 2 or not hasattr(actor.module[1], "get_dist"):
        raise ValueError("policy.cem needs the pipeline's ProbabilisticActor (policy.kind=actor_critic)")
    limit = float(c.get("cost_limit") or 0.0)
    if not limit >= 0:
        raise ValueError(f"policy.cem.cost_limit={limit!r} is invalid; allowed: >= 0 (mean cost per step)")
    init = c.get("init", "actor")
    if init not in ("actor", "zero_action"):
        raise ValueError(f"policy.cem.init={init!r} is invalid; allowed: 'actor', 'zero_action'")
    P, E = int(c.population), int(c.episodes)
    n_elite = max(1, math.ceil(float(c.elite) * P))
    env = make_transformed_env(cfg, num_envs=P * E, seed=int(cfg.seed) + 104_729, without=TRAINING_ONLY)
    if hasattr(env.base_env, "share_starts"):  # every candidate drives the same E episodes (its rows p*E .. p*E+E-1)
        env.base_env.share_starts(E)
    dt = float(env.base_env.scenario.dt)
    steps = env.base_env.scenario.max_steps if seconds is None else max(1, int(round(float(seconds) / dt)))
    after = float(c.get("score_after") or 0.0)
    if not 0 <= after < steps * dt:
        env.close()
        raise ValueError(f"policy.cem.score_after={after!r} is invalid; allowed: 0 <= score_after < the episode "
                         f"({steps * dt:g} s)")
    start = int(round(after / dt))
    params = list(actor.module[0].parameters())
    if init == "zero_action":  # the output layer zeroed: the first mean acts 0 (e.g. a residual's base controller)
        with torch.no_grad():
            last = [m for m in actor.module[0].modules() if isinstance(m, nn.Linear)][-1]
            last.weight.zero_()
            last.bias.zero_()
    mu = parameters_to_vector(params).detach().double()
    sigma = torch.full_like(mu, float(c.sigma))
    g = torch.Generator().manual_seed(int(cfg.seed) + 15_485_863)
    budget = cfg.trainer.get("max_minutes")
    budget_s = None if budget is None else 60.0 * float(budget)
    t0, best_hist, mean_hist, of_mean = time.perf_counter(), [], [], []
    kept = [mu.to(params[0].dtype).clone(), 0, None]  # parameters, generation whose mean they are, its score
    stopped, gen_s = None, 0.0
    bar = tqdm(range(c.generations), desc="CEM", unit="generation",
               disable=not bool(cfg.trainer.get("progress", True)))
    try:
        for gen in bar:
            elapsed = time.perf_counter() - t0
            if gen and budget_s is not None and elapsed + gen_s > budget_s:  # the next one would end past the budget
                stopped = (f"trainer.max_minutes={budget}: {gen} generations took {elapsed:.0f} s; another takes "
                           f"about {gen_s:.0f} s")
                if log:
                    log(f"cem: stopping before generation {gen + 1}/{c.generations} ({stopped})")
                break
            g0 = time.perf_counter()
            eps = torch.randn(P, mu.numel(), generator=g, dtype=torch.float64)
            eps[0] = 0.0  # the current mean is always scored
            thetas = (mu + sigma * eps).to(params[0].dtype)
            thetas[1] = kept[0]  # and the keeper, on the same episodes
            policy = PopulationPolicy(actor, thetas, E)
            with torch.no_grad():
                td = env.rollout(steps, policy, break_when_any_done=False, auto_reset=True)
            F = score(td, float(c.cost_coeff), start, limit).reshape(P, E).mean(1)
            of_mean.append(float(F[0]))
            keeper = f"the keeper, generation {kept[1]}: {float(F[1]):.4f}" if gen else "the first mean"
            if gen == 0 or float(F[0]) > float(F[1]):
                kept = [thetas[0].clone(), gen + 1, float(F[0])]
            mu, sigma = cem_update(thetas, F, n_elite, float(c.sigma_min))
            best_hist.append(float(F.max()))
            mean_hist.append(float(F.mean()))
            bar.set_postfix(best=f"{best_hist[-1]:.4f}", mean_policy=f"{float(F[0]):.4f}", refresh=False)
            if log:
                log(f"cem: generation {gen + 1}/{c.generations}, score of the mean {float(F[0]):.4f} ({keeper}), "
                    f"best {best_hist[-1]:.4f}, population mean {mean_hist[-1]:.4f}")
            gen_s = max(gen_s, time.perf_counter() - g0)
    finally:
        env.close()
    with torch.no_grad():
        vector_to_parameters(kept[0], params)
    if log:
        log(f"cem: the actor is the mean of generation {kept[1]} (its score {kept[2]:.4f}; no later mean beat it "
            "on common episodes)")
    return {"generations": len(best_hist), "stopped": stopped, "best_first": best_hist[0], "best_last": best_hist[-1],
            "mean_last": mean_hist[-1], "score_of_mean": of_mean, "kept_generation": kept[1],
            "kept_score": kept[2],
            "seconds": time.perf_counter() - t0}
