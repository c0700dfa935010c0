"""Gymnasium registration of the project's scenarios (single-env API).

The Gymnasium env wraps a ``batch_size=1`` TorchRL env: observations are the
``observation`` vector as float32 numpy arrays, actions the CAV accelerations, and
``info`` carries the constraint ``cost`` and ``collision`` flag.

>>> import gymnasium as gym
>>> import mixed_traffic.envs.gym  # registers the ids
>>> env = gym.make("MixedTraffic/Ring-v0")
>>> obs, info = env.reset(seed=0)
>>> obs.shape
(8,)
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch

GYM_IDS = {
    "MixedTraffic/Ring-v0": "ring",
    "MixedTraffic/DeePLCC-v0": "deeplcc",
    "MixedTraffic/Intersection-v0": "intersection",
}


class MixedTrafficGymEnv(gym.Env):
    """A single scenario of the project behind the Gymnasium API."""

    metadata = {"render_modes": []}

    def __init__(self, scenario: str = "ring", frameskip: int | None = None, **overrides):
        from mixed_traffic.envs import make_env

        if frameskip not in (None, 1):
            raise ValueError(f"frameskip={frameskip!r} is invalid; allowed: 1 (wrap the env to repeat actions)")

        self._env = make_env(scenario, batch_size=1, **overrides)
        obs_spec = self._env.observation_spec["observation"]
        act_spec = self._env.action_spec
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=obs_spec.shape[1:], dtype=np.float32)
        self.action_space = gym.spaces.Box(act_spec.space.low[0].numpy(), act_spec.space.high[0].numpy(),
                                           dtype=np.float32)
        self._td = None

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None:
            self._env.set_seed(seed)
        self._td = self._env.reset()
        return self._td["observation"][0].numpy().astype(np.float32), {}

    def step(self, action):
        if self._td is None:
            raise RuntimeError("call reset() before step()")
        act = torch.as_tensor(np.asarray(action, dtype=np.float32)).reshape(self._env.action_spec.shape)
        td = self._td.clone(False).set("action", act)
        nxt = self._env.step(td)["next"]
        self._td = nxt
        obs = nxt["observation"][0].numpy().astype(np.float32)
        info = {"cost": float(nxt["cost"][0, 0]), "collision": bool(nxt.get("collision", torch.zeros(1, 1, dtype=torch.bool))[0, 0])}
        return obs, float(nxt["reward"][0, 0]), bool(nxt["terminated"][0, 0]), bool(nxt["truncated"][0, 0]), info

    def close(self):
        self._env.close()


def register() -> None:
    for gym_id, scenario in GYM_IDS.items():
        if gym_id not in gym.registry:
            gym.register(id=gym_id, entry_point=MixedTrafficGymEnv, kwargs={"scenario": scenario})


register()
