import gymnasium as gym
import numpy as np
import pytest
from torchrl.envs import GymEnv
from torchrl.envs.utils import check_env_specs

import mixed_traffic.envs.gym  # noqa: F401  (registers the ids)


@pytest.mark.parametrize("gym_id", ["MixedTraffic/Ring-v0", "MixedTraffic/DeePLCC-v0", "MixedTraffic/Intersection-v0"])
def test_gym_api_and_torchrl_roundtrip(gym_id):
    env = gym.make(gym_id)
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    obs, r, term, trunc, info = env.step(env.action_space.sample())
    assert np.isfinite(r) and "cost" in info
    check_env_specs(GymEnv(gym_id))


def test_gym_same_seed_same_observations():
    def run():
        env = gym.make("MixedTraffic/Ring-v0")
        env.reset(seed=5)
        return [env.step(np.array([0.5], dtype=np.float32))[0] for _ in range(50)]

    assert np.array_equal(np.stack(run()), np.stack(run()))
