"""Tabular Q-learning (TD(0)) as a LossModule, with an epsilon-greedy table policy.

TorchRL's Q-learning losses (``DQNLoss``, ``DistributionalDQNLoss``) regress a
network by gradient descent; a table updated by the TD(0) rule has no counterpart
there, hence :class:`TabularQLearning`. States are the integer index written by
:class:`transforms.StateDiscretizer`; actions are ``n_bins`` accelerations per CAV
(``n_bins ** n_cav`` joint actions). The table grows on demand (a dict from state
index to row), so only visited states take memory.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.objectives import LossModule


def action_levels(low: float, high: float, n_bins: int) -> torch.Tensor:
    """``n_bins`` evenly spaced accelerations from ``low`` to ``high`` (both included)."""
    if not (isinstance(n_bins, int) and n_bins >= 2):
        raise ValueError(f"n_bins={n_bins!r} is invalid; allowed: an integer >= 2")
    return torch.linspace(float(low), float(high), n_bins)


class QTable(nn.Module):
    """A growable Q-table: ``rows[state] -> Tensor[n_actions]`` (unvisited states read 0)."""

    def __init__(self, n_actions: int, capacity: int = 1024):
        super().__init__()
        if not (isinstance(n_actions, int) and n_actions >= 1):
            raise ValueError(f"QTable: n_actions={n_actions!r} is invalid; allowed: an integer >= 1")
        self.n_actions = n_actions
        self.register_buffer("values", torch.zeros(capacity, n_actions))
        self.index: dict[int, int] = {}

    def __len__(self) -> int:
        return len(self.index)

    def rows(self, states: torch.Tensor, create: bool) -> torch.Tensor:
        """Row of each state (``-1`` for unseen states when ``create=False``)."""
        out = []
        for s in states.reshape(-1).tolist():
            r = self.index.get(s)
            if r is None and create:
                r = len(self.index)
                if r >= self.values.shape[0]:
                    grown = torch.zeros(2 * self.values.shape[0], self.n_actions, dtype=self.values.dtype)
                    grown[: self.values.shape[0]] = self.values
                    self.values = grown
                self.index[s] = r
            out.append(-1 if r is None else r)
        return torch.tensor(out, dtype=torch.long)

    def q(self, states: torch.Tensor) -> torch.Tensor:
        """Q-values ``[N, n_actions]`` (zeros for unseen states)."""
        rows = self.rows(states, create=False)
        q = torch.zeros(rows.shape[0], self.n_actions, dtype=self.values.dtype)
        seen = rows >= 0
        q[seen] = self.values[rows[seen]]
        return q

    def get_extra_state(self):
        return {"index": dict(self.index)}

    def set_extra_state(self, state):
        self.index = dict(state["index"])

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        key = prefix + "values"
        if key in state_dict:
            self.values = torch.zeros_like(state_dict[key])
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)


class TabularQLearning(LossModule):
    """TD(0) on a Q-table: ``Q(s,a) <- Q(s,a) + alpha [r + gamma (1 - term) max_a' Q(s',a') - Q(s,a)]``.

    ``forward(batch)`` applies the update for every transition of the batch in order
    (so repeated states see the earlier updates) and returns ``loss_td`` (mean squared
    TD error, for logging: there is nothing to back-propagate) and ``table_size``.
    :meth:`policy` gives the matching epsilon-greedy actor.

    Args:
        n_actions: joint actions (``n_bins ** n_cav``).
        alpha: learning rate (default 0.2, in ``(0, 1]``).
        gamma: discount (default 0.98, in ``[0, 1]``).

    Keys (``set_keys``): ``state`` (``"state_index"``), ``action_index``
    (``"action_index"``), ``reward``, ``terminated``.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> q = TabularQLearning(n_actions=3, alpha=0.5, gamma=0.9)
        >>> batch = TensorDict({"state_index": torch.tensor([[7]]), "action_index": torch.tensor([[2]]),
        ...     "next": {"state_index": torch.tensor([[8]]), "reward": torch.tensor([[1.0]]),
        ...              "terminated": torch.tensor([[False]])}}, [1])
        >>> _ = q(batch)
        >>> q.table.q(torch.tensor([7])).tolist()
        [[0.0, 0.0, 0.5]]
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable keys.

        Attributes:
            state: integer state index, default ``"state_index"``.
            action_index: index of the joint discrete action, default ``"action_index"``.
            reward: default ``"reward"`` (read under ``"next"``).
            terminated: default ``"terminated"`` (read under ``"next"``).
        """

        state: NestedKey = "state_index"
        action_index: NestedKey = "action_index"
        reward: NestedKey = "reward"
        terminated: NestedKey = "terminated"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys

    def __init__(self, n_actions: int, alpha: float = 0.2, gamma: float = 0.98):
        if not 0 < alpha <= 1:
            raise ValueError(f"TabularQLearning: alpha={alpha!r} is invalid; allowed: (0, 1]")
        if not 0 <= gamma <= 1:
            raise ValueError(f"TabularQLearning: gamma={gamma!r} is invalid; allowed: [0, 1]")
        super().__init__()
        self.table = QTable(n_actions)
        self.alpha, self.gamma = float(alpha), float(gamma)

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    @property
    def n_actions(self) -> int:
        return self.table.n_actions

    @torch.no_grad()
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        k = self.tensor_keys
        td = tensordict.reshape(-1)
        s = td.get(k.state).reshape(-1)
        a = td.get(k.action_index).reshape(-1).long()
        nxt = td.get("next")
        s2 = nxt.get(k.state).reshape(-1)
        r = nxt.get(k.reward).reshape(-1).float()
        term = nxt.get(k.terminated).reshape(-1).bool()
        if bool(((a < 0) | (a >= self.n_actions)).any()):
            raise ValueError(f"TabularQLearning: action_index out of range; allowed: [0, {self.n_actions - 1}]")
        rows = self.table.rows(s, create=True)
        rows2 = self.table.rows(s2, create=True)
        vals = self.table.values
        errors = torch.empty(len(rows))
        for i in range(len(rows)):  # in order: a repeated state sees the earlier updates
            target = r[i] + (0.0 if term[i] else self.gamma * vals[rows2[i]].max())
            err = target - vals[rows[i], a[i]]
            vals[rows[i], a[i]] += self.alpha * err
            errors[i] = err
        return TensorDict({"loss_td": errors.pow(2).mean(), "table_size": torch.tensor(float(len(self.table)))}, [])

    def policy(self, levels: torch.Tensor, n_cav: int = 1, *, eps_init: float = 1.0, eps_end: float = 0.05,
               annealing_num_steps: int = 100_000) -> EpsilonGreedyTablePolicy:
        """An epsilon-greedy actor over this table (see :class:`EpsilonGreedyTablePolicy`)."""
        return EpsilonGreedyTablePolicy(self.table, levels, n_cav, eps_init=eps_init, eps_end=eps_end,
                                        annealing_num_steps=annealing_num_steps,
                                        state_key=self.tensor_keys.state, index_key=self.tensor_keys.action_index)


class EpsilonGreedyTablePolicy(TensorDictModuleBase):
    """Reads ``state_index``, writes ``action_index`` and the continuous ``action``.

    Greedy with random tie-breaking, random with probability ``eps``; ``eps`` decays
    linearly from ``eps_init`` to ``eps_end`` over ``annealing_num_steps`` calls of
    :meth:`step` (one call per env frame, as TorchRL's ``EGreedyModule.step``).
    ``greedy=True`` (or ``eps = 0``) for evaluation.
    """

    def __init__(self, table: QTable, levels: torch.Tensor, n_cav: int = 1, *, eps_init: float = 1.0,
                 eps_end: float = 0.05, annealing_num_steps: int = 100_000, state_key: NestedKey = "state_index",
                 index_key: NestedKey = "action_index", action_key: NestedKey = "action", seed: int | None = None):
        super().__init__()
        n_bins = len(levels)
        if table.n_actions != n_bins ** n_cav:
            raise ValueError(f"EpsilonGreedyTablePolicy: the table has {table.n_actions} actions; "
                             f"allowed: len(levels) ** n_cav = {n_bins ** n_cav}")
        if not 0 <= eps_end <= eps_init <= 1:
            raise ValueError(f"EpsilonGreedyTablePolicy: eps_init={eps_init}, eps_end={eps_end} are invalid; "
                             "allowed: 0 <= eps_end <= eps_init <= 1")
        self.table, self.n_cav, self.n_bins = table, n_cav, n_bins
        self.register_buffer("levels", torch.as_tensor(levels, dtype=torch.float32))
        self.eps_init, self.eps_end, self.annealing_num_steps = eps_init, eps_end, max(1, int(annealing_num_steps))
        self.eps = eps_init
        self.greedy = False
        self.in_keys = [state_key]
        self.out_keys = [index_key, action_key]
        self.state_key, self.index_key, self.action_key = state_key, index_key, action_key
        self._gen = torch.Generator()
        if seed is not None:
            self._gen.manual_seed(seed)

    def step(self, frames: int = 1) -> None:
        frac = min(1.0, frames / self.annealing_num_steps)
        self.eps = max(self.eps_end, self.eps - frac * (self.eps_init - self.eps_end))

    def decode(self, index: torch.Tensor) -> torch.Tensor:
        """Joint index -> one acceleration per CAV (``[..., n_cav]``)."""
        digits = [(index // self.n_bins**i) % self.n_bins for i in range(self.n_cav)]
        return self.levels[torch.stack(digits, -1)]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        s = tensordict.get(self.state_key)
        batch = s.shape[:-1] if s.ndim > 1 else s.shape
        q = self.table.q(s.reshape(-1))
        best = q == q.max(-1, keepdim=True).values
        idx = (torch.rand(q.shape, generator=self._gen) * best).argmax(-1)  # random tie-breaking
        eps = 0.0 if self.greedy else self.eps
        if eps > 0:
            explore = torch.rand(idx.shape, generator=self._gen) < eps
            rand = torch.randint(self.table.n_actions, idx.shape, generator=self._gen)
            idx = torch.where(explore, rand, idx)
        idx = idx.reshape(*batch, 1)
        tensordict.set(self.index_key, idx)
        tensordict.set(self.action_key, self.decode(idx.squeeze(-1)).to(torch.float32))
        return tensordict
