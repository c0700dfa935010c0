"""V2VChannel: the leader's acceleration as a CAV receives it over an imperfect radio link.

The env writes each CAV's leader acceleration of the last step to ``("cav", "leader_accel")``: a perfect
V2V link. A controller that reads it (CACC, the residual base's ``brake_floor``) is only as good as the
link, so the evaluation can degrade it: every message arrives ``delay_steps`` steps late, and each is lost
with probability ``loss``, the receiver then holding the last message it got (zero-order hold, as a CAV
without a fresh packet would). What the CAV measures itself (gap, own speed, leader speed) is untouched.
The age of what the CAV holds (``("v2v", "age")``, in steps) travels with it, so a CAV can tell a silent link
from a live one (:class:`transforms.OnboardLeaderAccel` reads it). TorchRL has no transform that delays or drops
an entry, hence this one.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Composite, Unbounded
from torchrl.envs.transforms import Transform

from transforms.specs import kept_rows, state_entries

LEADER_ACCEL = ("cav", "leader_accel")


class V2VChannel(Transform):
    """Delay ``accel_key`` by ``delay_steps`` steps and drop each message with probability ``loss``.

    The entry is overwritten with what arrived; the sent values of the last ``delay_steps`` steps, the last
    received value and its age in steps since it was sent (``("v2v", "sent")``, ``("v2v", "held")``,
    ``("v2v", "age")``: ``delay_steps`` when this step's message arrived, one more for every step lost since,
    0 at reset) travel in the tensordict, so a row reset
    on its own starts its link afresh and a collector's rollouts carry the link's state. At reset the
    receiver holds the reset value, and the values still in flight are taken as that value. Losses are drawn
    per step and per CAV from the transform's own generator (``seed``), so two controllers evaluated on the
    same episodes with the same seed lose the same messages.

    Args:
        delay_steps: how many steps late each message arrives (>= 0; the env's entry is already the last
            step's acceleration, so 0 is the perfect link's one-step age).
        loss: probability that a message is lost (in [0, 1]; 1: nothing arrives after the reset).
        seed: seed of the loss draws.
        accel_key: the received entry (default ``("cav", "leader_accel")``).

    Example:
        >>> import torch
        >>> from torchrl.envs import TransformedEnv
        >>> from mixed_traffic import make_env
        >>> from transforms import V2VChannel
        >>> kw = dict(profile="sine", profile_kwargs={"v_star": 12.5, "amplitude": 5.0, "period": 10.0})
        >>> env = TransformedEnv(make_env("ring", batch_size=1, seed=0, **kw), V2VChannel(delay_steps=3))
        >>> plain = make_env("ring", batch_size=1, seed=0, **kw)
        >>> act = lambda td: td.set("action", torch.zeros(1, 1))
        >>> late = env.rollout(8, act)["next", "cav", "leader_accel"]
        >>> sent = plain.rollout(8, act)["next", "cav", "leader_accel"]
        >>> bool((late[:, 3:] == sent[:, :-3]).all()), bool((late[:, 3:] == sent[:, 3:]).all())
        (True, False)
    """

    def __init__(self, delay_steps: int = 0, loss: float = 0.0, *, seed: int = 0, accel_key: NestedKey = LEADER_ACCEL):
        if isinstance(delay_steps, bool) or not isinstance(delay_steps, int) or delay_steps < 0:
            raise ValueError(f"V2VChannel: delay_steps={delay_steps!r} is invalid; allowed: an integer >= 0")
        if not 0.0 <= float(loss) <= 1.0:
            raise ValueError(f"V2VChannel: loss={loss!r} is invalid; allowed: a probability in [0, 1]")
        super().__init__(in_keys=[accel_key], out_keys=[accel_key])
        self.delay_steps, self.loss, self.seed, self.accel_key = int(delay_steps), float(loss), int(seed), accel_key
        self._gen = torch.Generator().manual_seed(self.seed)
        self.sent_key, self.held_key, self.age_key = ("v2v", "sent"), ("v2v", "held"), ("v2v", "age")

    def _arrived(self, like: torch.Tensor) -> torch.Tensor:
        """Which messages of this step arrive (True), one draw per entry of ``like``."""
        if self.loss == 0.0:
            return torch.ones_like(like, dtype=torch.bool)
        draw = torch.rand(like.shape, generator=self._gen).to(like.device)
        return draw >= self.loss

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        now = tensordict_reset.get(self.accel_key)
        sent = now.unsqueeze(-1).expand(*now.shape, self.delay_steps).clone()
        held, age = now.clone(), torch.zeros_like(now)
        keep = kept_rows(tensordict, now, self.sent_key)
        if keep is not None:  # rows not reset keep their link
            sent = torch.where(keep.unsqueeze(-1), tensordict.get(self.sent_key), sent)
            held = torch.where(keep, tensordict.get(self.held_key), held)
            age = torch.where(keep, tensordict.get(self.age_key), age)
            tensordict_reset.set(self.accel_key, held)
        tensordict_reset.set(self.sent_key, sent)
        tensordict_reset.set(self.held_key, held)
        tensordict_reset.set(self.age_key, age)
        return tensordict_reset

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        now = next_tensordict.get(self.accel_key)
        sent, held, age = state_entries("V2VChannel", tensordict, "link", self.sent_key, self.held_key, self.age_key)
        if self.delay_steps:
            out = sent[..., 0]
            next_tensordict.set(self.sent_key, torch.cat([sent[..., 1:], now.unsqueeze(-1)], -1))
        else:
            out = now
            next_tensordict.set(self.sent_key, sent)
        arrived = self._arrived(out)
        held = torch.where(arrived, out, held)
        next_tensordict.set(self.age_key, torch.where(arrived, torch.full_like(age, self.delay_steps), age + 1))
        next_tensordict.set(self.held_key, held)
        next_tensordict.set(self.accel_key, held)
        return next_tensordict

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        return next_tensordict  # everything happens in _step / _reset (needs the link's state)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise RuntimeError("V2VChannel delays a live env's entry; use it inside an env")

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        leaf = observation_spec[self.accel_key]
        observation_spec["v2v"] = Composite(
            sent=Unbounded(shape=(*leaf.shape, self.delay_steps), dtype=leaf.dtype, device=leaf.device),
            held=Unbounded(shape=leaf.shape, dtype=leaf.dtype, device=leaf.device),
            age=Unbounded(shape=leaf.shape, dtype=leaf.dtype, device=leaf.device),
            shape=observation_spec.shape, device=observation_spec.device)
        return observation_spec

    def __repr__(self) -> str:
        return f"{type(self).__name__}(delay_steps={self.delay_steps}, loss={self.loss}, seed={self.seed})"
