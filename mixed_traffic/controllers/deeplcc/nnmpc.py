"""NNMPC: an MLP surrogate of the DeeP-LCC QP, trained by behaviour cloning (BCLoss).

Network: ``[uini, yini, eini]`` (260) -> normalise (per-feature mean/std of the
training set, stored as buffers so they travel with the checkpoint) -> 256 -> ReLU
-> 128 -> ReLU -> 2 -> tanh -> affine map of [-1, 1] onto [a_min, a_max].

Training: :class:`losses.BCLoss` (MSE of the deterministic action to the expert
key ``u_opt``), Adam (lr 5e-4, weight decay 1e-5), 90/10 split, early stopping on
the validation loss. :func:`dagger` runs the network in closed loop, labels the
states it visits with the exact QP and retrains on the aggregate.

>>> import torch
>>> net = NNMPC()
>>> a = net(torch.zeros(4, 40), torch.zeros(4, 200), torch.zeros(4, 20))
>>> a.shape, bool((a >= -5).all() and (a <= 2).all())
(torch.Size([4, 2]), True)
"""

from __future__ import annotations

import copy
import dataclasses
import time
from dataclasses import dataclass

import numpy as np
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

WINDOW_KEYS = ["uini", "yini", "eini"]


class NNMPC(torch.nn.Module):
    """MLP ``(uini, yini, eini) -> action`` bounded to ``[a_min, a_max]`` by tanh.

    Variants that give the network what the QP knows (``gain = qp_gain(solver)``):
    the QP's equality-only first action as an extra input (``gain``), or as the
    base the network corrects (``residual=True``: ``clamp(gain @ x + MLP(x))``).
    """

    def __init__(self, in_features: int = 260, hidden: tuple[int, ...] = (256, 128), out_features: int = 2,
                 a_min: float = -5.0, a_max: float = 2.0, gain: torch.Tensor | np.ndarray | None = None,
                 residual: bool = False):
        super().__init__()
        if residual and gain is None:
            raise ValueError("NNMPC: residual=True needs gain (the QP's linear part, see qp_gain)")
        if not a_min < a_max:
            raise ValueError(f"NNMPC: a_min={a_min} and a_max={a_max} are invalid; allowed: a_min < a_max")
        if gain is not None and tuple(np.shape(gain)) != (out_features, in_features):
            raise ValueError(f"NNMPC: gain has shape {tuple(np.shape(gain))}; expected ({out_features}, {in_features})")
        self.config = {"in_features": in_features, "hidden": tuple(hidden), "out_features": out_features,
                       "a_min": a_min, "a_max": a_max, "gain": gain is not None, "residual": residual}
        self.residual = residual
        n_feat = in_features + (out_features if gain is not None else 0)
        layers, d = [], n_feat
        for h in hidden:
            layers += [torch.nn.Linear(d, h), torch.nn.ReLU()]
            d = h
        layers.append(torch.nn.Linear(d, out_features))
        self.net = torch.nn.Sequential(*layers)
        if residual:  # start as the clamped linear controller
            torch.nn.init.zeros_(layers[-1].weight)
            torch.nn.init.zeros_(layers[-1].bias)
        self.register_buffer("x_mean", torch.zeros(n_feat))
        self.register_buffer("x_std", torch.ones(n_feat))
        if gain is not None:
            self.register_buffer("gain", torch.as_tensor(np.asarray(gain), dtype=torch.float32))
        else:
            self.gain = None
        self.a_min, self.a_max = float(a_min), float(a_max)

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """The input, plus (with ``gain``) the QP's equality-only first action ``gain @ x``."""
        return x if self.gain is None else torch.cat([x, x @ self.gain.T], -1)

    def set_normalization(self, x: np.ndarray | torch.Tensor) -> None:
        f = self.features(torch.as_tensor(x, dtype=torch.float32))
        self.x_mean.copy_(f.mean(0))
        self.x_std.copy_(f.std(0).clamp_min(1e-6))

    def forward_flat(self, x: torch.Tensor) -> torch.Tensor:
        z = self.net((self.features(x) - self.x_mean) / self.x_std)
        if self.residual:  # the QP's unconstrained action plus a learned correction, within the bounds
            return (x @ self.gain.T + z).clamp(self.a_min, self.a_max)
        return self.a_min + 0.5 * (torch.tanh(z) + 1.0) * (self.a_max - self.a_min)

    def forward(self, uini: torch.Tensor, yini: torch.Tensor, eini: torch.Tensor) -> torch.Tensor:
        x = torch.cat([uini, yini, eini], -1).to(self.x_mean.dtype)
        return self.forward_flat(x).to(uini.dtype)

    # ------------------------------------------------------------ checkpoints
    def save(self, path, **extra) -> None:
        """Weights, normalisation (buffers) and constructor config in one file."""
        torch.save({"config": self.config, "state_dict": self.state_dict(), "extra": extra}, path)

    @classmethod
    def load(cls, path) -> NNMPC:
        ck = torch.load(path, map_location="cpu", weights_only=True)
        cfg = dict(ck["config"])
        if cfg.pop("gain", False):
            cfg["gain"] = torch.zeros(cfg["out_features"], cfg["in_features"])
        net = cls(**cfg)
        net.load_state_dict(ck["state_dict"])
        return net.eval()


def qp_gain(solver) -> np.ndarray:
    """The linear map ``[uini, yini, eini] -> first action`` of the QP when no inequality binds (m, 260)."""
    m, p, t = solver.m, solver.qp.p, solver.qp.t_ini
    G = solver.G[:m]  # a0 = G @ [yini; uini; eini; 0]
    return np.concatenate([G[:, p * t: p * t + m * t], G[:, : p * t], G[:, p * t + m * t: p * t + m * t + t]], 1)


def nnmpc_policy(net: NNMPC) -> TensorDictModule:
    """The network as a policy module (``uini, yini, eini -> action``)."""
    return TensorDictModule(net, in_keys=list(WINDOW_KEYS), out_keys=["action"])


def numpy_controller(net: NNMPC):
    """``controller(uini, yini, eini) -> u`` on numpy arrays (for :func:`.closed_loop.run_closed_loop`)."""

    @torch.no_grad()
    def ctrl(uini, yini, eini):
        x = torch.as_tensor(np.concatenate([uini, yini, eini], -1), dtype=torch.float32)
        return net.forward_flat(x).double().numpy()

    return ctrl


@dataclass
class TrainConfig:
    lr: float = 5e-4
    weight_decay: float = 1e-5
    batch_size: int = 256
    max_epochs: int = 200
    patience: int = 20
    val_fraction: float = 0.1
    seed: int = 0
    max_seconds: float | None = None  # wall-clock budget (early stop), None: unlimited

    def validate(self) -> TrainConfig:
        for name, ok, allowed in (("lr", self.lr > 0, "> 0"), ("weight_decay", self.weight_decay >= 0, ">= 0"),
                                  ("batch_size", self.batch_size >= 1, ">= 1"), ("max_epochs", self.max_epochs >= 1, ">= 1"),
                                  ("patience", self.patience >= 1, ">= 1"),
                                  ("val_fraction", 0 < self.val_fraction < 1, "(0, 1)")):
            if not ok:
                raise ValueError(f"TrainConfig: {name}={getattr(self, name)!r} is invalid; allowed: {allowed}")
        return self


def _td(x: torch.Tensor, y: torch.Tensor | None = None) -> TensorDict:
    d = {"uini": x[:, :40], "yini": x[:, 40:240], "eini": x[:, 240:]}
    if y is not None:
        d["u_opt"] = y
    return TensorDict(d, batch_size=[x.shape[0]])


def split(n: int, val_fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    perm = np.random.default_rng(seed).permutation(n)
    n_val = max(1, int(round(n * val_fraction)))
    return perm[n_val:], perm[:n_val]


def train_nnmpc(x: np.ndarray, y: np.ndarray, cfg: TrainConfig | None = None, net: NNMPC | None = None,
                log=None, gain=None, residual: bool = False) -> tuple[NNMPC, dict]:
    """Fit ``net`` (new if None; normalisation from ``x``) on ``(x (N,260), y (N,2))`` with BCLoss + Adam.

    ``gain`` (only for a new network): see :func:`qp_gain` (the QP's linear part as an extra input);
    ``residual``: the output is ``clamp(gain @ x + MLP, a_min, a_max)`` instead of the tanh map.

    Returns the best-validation network and a history dict (train/val loss per epoch, epochs, seconds).
    """
    from losses.bc import BCLoss

    cfg = (cfg or TrainConfig()).validate()
    torch.manual_seed(cfg.seed)
    x = torch.as_tensor(x, dtype=torch.float32)
    y = torch.as_tensor(y, dtype=torch.float32)
    if x.ndim != 2 or y.ndim != 2 or x.shape[0] != y.shape[0]:
        raise ValueError(f"train_nnmpc: x {tuple(x.shape)} and y {tuple(y.shape)} must be (N, 260) and (N, 2)")
    if net is None:
        net = NNMPC(in_features=x.shape[1], out_features=y.shape[1], gain=gain, residual=residual)
        net.set_normalization(x)
    tr, va = split(len(x), cfg.val_fraction, cfg.seed)
    actor = nnmpc_policy(net)
    loss_fn = BCLoss(actor, expert_action_key="u_opt")
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    best, best_state, bad_epochs = float("inf"), copy.deepcopy(net.state_dict()), 0
    hist = {"train": [], "val": []}
    gen = torch.Generator().manual_seed(cfg.seed)
    t0 = time.perf_counter()
    tr_t = torch.as_tensor(tr)
    for epoch in range(cfg.max_epochs):
        net.train()
        order = tr_t[torch.randperm(len(tr_t), generator=gen)]
        tot = 0.0
        for i in range(0, len(order), cfg.batch_size):
            idx = order[i:i + cfg.batch_size]
            loss = loss_fn(_td(x[idx], y[idx]))["loss_bc"]
            opt.zero_grad()
            loss.backward()
            opt.step()
            tot += float(loss.detach()) * len(idx)
        net.eval()
        with torch.no_grad():
            val = float(((net.forward_flat(x[va]) - y[va]) ** 2).mean())
        hist["train"].append(tot / len(tr))
        hist["val"].append(val)
        if log:
            log(epoch, hist["train"][-1], val)
        if val < best - 1e-9:
            best, best_state, bad_epochs = val, copy.deepcopy(net.state_dict()), 0
        else:
            bad_epochs += 1
            if bad_epochs >= cfg.patience:
                break
        if cfg.max_seconds is not None and time.perf_counter() - t0 > cfg.max_seconds:
            break
    net.load_state_dict(best_state)
    net.eval()
    hist.update(epochs=len(hist["val"]), seconds=time.perf_counter() - t0, best_val=best, val_index=va)
    return net, hist


@torch.no_grad()
def offline_metrics(net: NNMPC, x: np.ndarray, y: np.ndarray) -> dict[str, float]:
    """MSE, MAE and max absolute error of the network against labels."""
    pred = net.forward_flat(torch.as_tensor(x, dtype=torch.float32)).double().numpy()
    err = pred - np.asarray(y, dtype=np.float64)
    return {"mse": float((err**2).mean()), "mae": float(np.abs(err).mean()), "max_error": float(np.abs(err).max())}


def dagger(net: NNMPC, solver, x: np.ndarray, y: np.ndarray, cfg, scenarios, rounds: int = 2,
           episodes_per_round: int = 4, beta: float = 0.0, seconds: float = 40.0, t_ini: int = 20,
           train_cfg: TrainConfig | None = None, seed: int = 0, log=print) -> tuple[NNMPC, np.ndarray, np.ndarray, list]:
    """DAgger: run the network in closed loop, label the visited states with ``solver``, retrain.

    Args:
        net: initial network (trained on ``(x, y)``).
        solver: the :class:`~.qp.DeepLCCSolver` the network imitates (expert labels).
        cfg: :class:`~.platoon.PlatoonConfig` of the closed loop.
        scenarios: list of :class:`~.closed_loop.ScenarioSpec` cycled over the episodes.
        beta: probability that the expert's action is executed at a step (0: the network drives).

    Returns the retrained network, the aggregated data and a per-round log.
    """
    from mixed_traffic.controllers.deeplcc.closed_loop import run_closed_loop

    rng = np.random.default_rng(seed)
    train_cfg = train_cfg or TrainConfig(max_epochs=60, patience=10)
    history = []
    ctrl_nn = numpy_controller(net)
    for r in range(rounds):
        new_x, new_y = [], []
        for e in range(episodes_per_round):
            spec = scenarios[(r * episodes_per_round + e) % len(scenarios)]
            gen = torch.Generator().manual_seed(seed * 7919 + r * 101 + e)
            v = spec.head_speed(cfg.dt, 1, gen)
            labels = []

            def ctrl(uini, yini, eini, ctrl_nn=ctrl_nn, labels=labels):
                a_nn = ctrl_nn(uini, yini, eini)
                a_qp = np.stack([solver.solve(uini[b], yini[b], eini[b]).u for b in range(len(uini))])
                labels.append(a_qp)
                return a_qp if rng.random() < beta else a_nn

            out = run_closed_loop(ctrl, v, cfg, t_ini, adaptive_v_star=spec.adaptive_v_star, generator=gen, record=True)
            new_x.append(np.concatenate([out["uini"][0], out["yini"][0], out["eini"][0]], -1).astype(np.float32))
            new_y.append(np.concatenate(labels))
        x = np.concatenate([x, *new_x])
        y = np.concatenate([y, *new_y])
        net, hist = train_nnmpc(x, y, dataclasses.replace(train_cfg, seed=train_cfg.seed + r + 1), net=net)
        ctrl_nn = numpy_controller(net)
        history.append({"round": r, "samples": len(x), "epochs": hist["epochs"], "best_val": hist["best_val"]})
        if log:
            log(f"dagger round {r}: {len(x)} samples, val MSE {hist['best_val']:.2e}")
    return net, x, y, history
