"""Build the pieces of a run from its config: env + transform chain, networks, losses.

Everything here is plain TorchRL: ``TransformedEnv(make_env(...), Compose(...))``,
``ProbabilisticActor`` + ``ValueOperator``, ``ClipPPOLoss``, ``QValueActor`` + ``DQNLoss``.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.data import OneHot
from torchrl.envs import Compose, EnvBase, RewardSum, StepCounter, TransformedEnv
from torchrl.modules import MLP, ProbabilisticActor, QValueActor, TanhNormal, ValueOperator

from mixed_traffic.envs import make_env

ENV_FIELDS = ("observation", "profile", "profile_kwargs", "episode_seconds", "weight_v", "weight_s", "weight_u",
              "s_min", "s_max", "hdv_param_noise")


# ----------------------------------------------------------------------------- env
def env_kwargs(env_cfg: DictConfig | dict, **extra) -> dict:
    """Scenario overrides from an env config: the named fields that are set, then ``overrides``."""
    cfg = OmegaConf.to_container(env_cfg, resolve=True) if isinstance(env_cfg, DictConfig) else dict(env_cfg)
    kw = {k: cfg[k] for k in ENV_FIELDS if cfg.get(k) is not None}
    kw.update(cfg.get("overrides") or {})
    kw.update(extra)
    return kw


def _non_negative_reward(tcfg, env):
    from transforms import NonNegativeReward

    return NonNegativeReward(collision_reward=tcfg.non_negative_reward.collision_reward)


def _safety_layer(tcfg, env):
    from transforms import SafetyLayer

    s = tcfg.safety_layer
    return SafetyLayer(s_min=s.s_min, s_max=s.s_max, mode=s.mode)


def _residual_damper(tcfg, env):
    from mixed_traffic.controllers.dampers import make_damper
    from transforms import ResidualAction

    r = tcfg.residual_damper
    return ResidualAction(make_damper(r.base, env), weight=r.weight)


def _intervention_cost(tcfg, env):
    from transforms import InterventionCost

    c = tcfg.intervention_cost
    return InterventionCost(coef=c.coef, mode=c.mode)


def _jerk_penalty(tcfg, env):
    from transforms import JerkPenalty

    return JerkPenalty(weight=tcfg.jerk_penalty.weight)


def _residual_idm(tcfg, env):
    from mixed_traffic.controllers.classic import make_classic_policy
    from transforms import ResidualAction

    r = tcfg.residual
    return ResidualAction(make_classic_policy(r.base, env), weight=r.weight)


def _state_discretizer(tcfg, env):
    from transforms import StateDiscretizer

    return StateDiscretizer(n_bins=tcfg.discretizer.state_bins)


# name -> factory(transforms_cfg, base_env) -> Transform.  Order comes from the config's `chain`.
TRANSFORMS: dict[str, Callable] = {
    "non_negative_reward": _non_negative_reward,
    "safety_layer": _safety_layer,
    "residual_damper": _residual_damper,
    "intervention_cost": _intervention_cost,
    "residual_idm": _residual_idm,
    "jerk_penalty": _jerk_penalty,
    "state_discretizer": _state_discretizer,
}


def check_chain(chain) -> None:
    unknown = [c for c in chain if c not in TRANSFORMS]
    if unknown:
        raise ValueError(f"transforms.chain: unknown transform(s) {unknown}; allowed: {sorted(TRANSFORMS)}")


def make_transformed_env(cfg: DictConfig, *, num_envs: int, seed: int, without: tuple[str, ...] = (),
                         **env_overrides) -> TransformedEnv:
    """The base env of ``cfg.env`` wrapped in ``cfg.transforms.chain`` (+ episode bookkeeping).

    ``without`` drops named transforms from the chain (the evaluation removes
    ``safety_layer`` and ``intervention_cost`` to run the policy's raw actions).

    ``RewardSum`` (``episode_reward``: the task reward summed over the episode, before any
    Lagrangian penalty) and ``StepCounter`` come last so logs see the transformed reward.
    """
    check_chain(cfg.transforms.chain)
    base: EnvBase = make_env(cfg.env.scenario, backend=cfg.env.backend, batch_size=num_envs, seed=seed,
                             device=cfg.device, **env_kwargs(cfg.env, **env_overrides))
    ts = [TRANSFORMS[name](cfg.transforms, base) for name in cfg.transforms.chain if name not in without]
    ts += [RewardSum(in_keys=["reward"], out_keys=["episode_reward"]), StepCounter()]
    return TransformedEnv(base, Compose(*ts))


def desynchronize(env: EnvBase, seed: int) -> bool:
    """Put each row of a freshly reset car-following env at a random time of its episode.

    All rows start at t = 0 after the first reset, so without this every row of a batch
    is at the same episode phase (the random-steps head changes speed at the same
    instants in every row, every row truncates at once). Here each row's clock jumps to
    a uniform time in [0, episode); its rolling v_eq window is filled with the current
    head speed, so the reward stays consistent. Later episodes start at t = 0 as usual.
    Returns False (and does nothing) for envs without that clock.
    """
    base = env
    while isinstance(base, TransformedEnv):
        base = base.base_env
    needed = ("step_count", "head_hist", "head_sum", "vel", "scenario")
    if not all(hasattr(base, a) for a in needed):
        return False
    g = torch.Generator().manual_seed(int(seed) + 7919)
    B, window = base.head_hist.shape
    start = torch.randint(0, base.scenario.max_steps, (B,), generator=g).to(base.step_count)
    base.step_count = start
    v0 = base.vel[:, 0]
    base.head_hist = v0[:, None].expand(B, window).clone()
    base.head_sum = v0 * (start + 1).clamp(max=window).to(v0.dtype)
    return True


# ----------------------------------------------------------------------------- networks
def _activation(name: str) -> type[nn.Module]:
    table = {"tanh": nn.Tanh, "relu": nn.ReLU, "elu": nn.ELU, "silu": nn.SiLU}
    if name not in table:
        raise ValueError(f"policy.activation={name!r} is invalid; allowed: {sorted(table)}")
    return table[name]


def _ortho(layer: nn.Linear, gain: float) -> nn.Linear:
    nn.init.orthogonal_(layer.weight, gain)
    nn.init.zeros_(layer.bias)
    return layer


class Trunk(nn.Sequential):
    """Linear/activation stack with orthogonal init (gain sqrt 2)."""

    def __init__(self, in_dim: int, hidden: list[int], activation: str):
        layers, d = [], in_dim
        for h in hidden:
            layers += [_ortho(nn.Linear(d, h), math.sqrt(2.0)), _activation(activation)()]
            d = h
        super().__init__(*layers)
        self.out_dim = d


class GaussianHead(nn.Module):
    """Mean from a linear head (orthogonal, gain 0.01) and a state-independent log-std, clamped."""

    def __init__(self, in_dim: int, act_dim: int, log_std_init: float, log_std_min: float, log_std_max: float):
        super().__init__()
        self.mean = _ortho(nn.Linear(in_dim, act_dim), 0.01)
        self.log_std = nn.Parameter(torch.full((act_dim,), float(log_std_init)))
        self.log_std_min, self.log_std_max = float(log_std_min), float(log_std_max)

    def forward(self, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        loc = self.mean(h)
        scale = self.log_std.clamp(self.log_std_min, self.log_std_max).exp().expand_as(loc)
        return loc, scale


def make_actor_critic(cfg: DictConfig, env: EnvBase) -> tuple[ProbabilisticActor, ValueOperator]:
    """PPO actor (TanhNormal to the action bounds) and critic sharing one trunk module."""
    p = cfg.policy
    if p.kind != "actor_critic":
        raise ValueError(f"policy.kind={p.kind!r} is invalid for loss {cfg.loss.name!r}; allowed: 'actor_critic'")
    obs_dim = env.observation_spec["observation"].shape[-1]
    spec = env.action_spec_unbatched
    act_dim = spec.shape[-1]
    trunk = Trunk(obs_dim, list(p.hidden), p.activation)
    trunk_mod = TensorDictModule(trunk, in_keys=["observation"], out_keys=["hidden"])
    if p.shared_trunk:
        critic_trunk = trunk_mod
    else:
        critic_trunk = TensorDictModule(Trunk(obs_dim, list(p.hidden), p.activation), in_keys=["observation"],
                                        out_keys=["hidden_v"])
    head = TensorDictModule(GaussianHead(trunk.out_dim, act_dim, p.log_std_init, p.log_std_min, p.log_std_max),
                            in_keys=["hidden"], out_keys=["loc", "scale"])
    actor = ProbabilisticActor(
        TensorDictSequential(trunk_mod, head), in_keys=["loc", "scale"], spec=spec,
        distribution_class=TanhNormal,
        distribution_kwargs={"low": spec.space.low, "high": spec.space.high},
        return_log_prob=True,
    )
    v_in = "hidden" if p.shared_trunk else "hidden_v"
    v_lin = _ortho(nn.Linear(trunk.out_dim, 1), 1.0)
    nn.init.constant_(v_lin.bias, float(p.get("value_bias_init", 0.0)))
    value_head = TensorDictModule(v_lin, in_keys=[v_in], out_keys=["state_value"])
    critic = TensorDictSequential(critic_trunk, value_head)
    return actor, critic


class DiscreteToContinuous(nn.Module):
    """Maps a one-hot over ``levels`` (per CAV) to the acceleration command."""

    def __init__(self, levels: torch.Tensor):
        super().__init__()
        self.register_buffer("levels", levels)

    def forward(self, onehot: torch.Tensor) -> torch.Tensor:
        return (onehot.to(self.levels.dtype) * self.levels).sum(-1, keepdim=True)


def action_levels(env: EnvBase, n_bins: int) -> torch.Tensor:
    spec = env.action_spec_unbatched
    if spec.shape[-1] != 1:
        raise ValueError(f"discrete policies support one CAV (action dim 1), got {spec.shape[-1]}")
    lo, hi = float(spec.space.low.flatten()[0]), float(spec.space.high.flatten()[0])
    return torch.linspace(lo, hi, n_bins)


def make_qnet_policy(cfg: DictConfig, env: EnvBase) -> tuple[QValueActor, TensorDictModule]:
    """DQN Q-network over ``action_bins`` accelerations; the actor writes ``action_onehot``."""
    p = cfg.policy
    n_bins = cfg.transforms.discretizer.action_bins
    obs_dim = env.observation_spec["observation"].shape[-1]
    net = MLP(in_features=obs_dim, out_features=n_bins, num_cells=list(p.hidden), activation_class=_activation(p.activation))
    qactor = QValueActor(net, in_keys=["observation"], spec=OneHot(n_bins), action_space=None,
                         action_value_key="action_value")
    # QValueActor writes "action"; rename to "action_onehot" so the env receives the acceleration
    qactor.module[-1].out_keys = ["action_onehot", "action_value", "chosen_action_value"]
    qactor.module[-1].action_key = "action_onehot"
    to_accel = TensorDictModule(DiscreteToContinuous(action_levels(env, n_bins)), in_keys=["action_onehot"],
                                out_keys=["action"])
    return qactor, to_accel


def make_collector(cfg: DictConfig, env: EnvBase, policy, *, resume: dict | None = None):
    """The TorchRL ``Collector`` of a training loop and its batch arithmetic.

    ``trainer.num_envs x trainer.rollout_len`` frames a batch, enough batches to reach
    ``trainer.total_frames``; with ``trainer.desync_start`` (and not resuming) the rows
    start at spread-out points of their episode clock. Returns
    ``(collector, frames_per_batch, n_iterations)``.
    """
    from torchrl.collectors import Collector

    tc = cfg.trainer
    fpb = tc.num_envs * tc.rollout_len
    n_iters = max(1, math.ceil(tc.total_frames / fpb))
    collector = Collector(env, policy, frames_per_batch=fpb, total_frames=-1, device=cfg.device,
                          auto_register_policy_transforms=False)
    if tc.get("desync_start", False) and resume is None:
        desynchronize(env, cfg.seed)
    return collector, fpb, n_iters
