"""Cross-entropy-method training (policy.cem): the update, the batched population, the score."""

import pytest
import torch
from tensordict import TensorDict
from torch.nn.utils import parameters_to_vector
from torchrl.envs.utils import ExplorationType, set_exploration_type

from mixed_traffic.config import compose
from mixed_traffic.training.builders import make_transformed_env
from mixed_traffic.training.cem import PopulationPolicy, cem_pretrain, cem_update, score
from mixed_traffic.training.on_policy import build_ppo

TINY = ["experiment=ring_wave_cem", "policy.cem.population=3", "policy.cem.episodes=2", "policy.cem.seconds=1.0",
        "policy.cem.score_after=0.0",
        "trainer.progress=false"]


def _actor(cfg, rows=6):
    env = make_transformed_env(cfg, num_envs=rows, seed=0)
    return build_ppo(cfg, env)[0], env


def test_cem_update_moves_to_the_elite_mean_and_floors_sigma():
    thetas = torch.tensor([[0.0, 0.0], [1.0, 3.0], [3.0, 5.0], [-4.0, 9.0]])
    F = torch.tensor([0.1, 0.9, 0.8, -1.0])
    mu, sigma = cem_update(thetas, F, 2, 0.05)
    assert torch.allclose(mu, torch.tensor([2.0, 4.0], dtype=torch.float64))
    assert torch.allclose(sigma, torch.tensor([1.0, 1.0], dtype=torch.float64))
    mu1, sigma1 = cem_update(thetas, F, 1, 0.05)
    assert torch.equal(mu1, thetas[1].double()) and torch.equal(sigma1, torch.full((2,), 0.05, dtype=torch.float64))


def test_population_rows_follow_their_own_candidate():
    cfg = compose(TINY)
    actor, env = _actor(cfg)
    td = env.reset()
    theta = parameters_to_vector(actor.module[0].parameters()).detach()
    thetas = torch.stack([theta, theta + 0.5 * torch.randn(theta.shape, generator=torch.Generator().manual_seed(0)),
                          theta])
    a = PopulationPolicy(actor, thetas, episodes=2)(td.clone())["action"]
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        ref = actor(td.clone())["action"]
    same = [0, 1, 4, 5]  # candidates 0 and 2 are the actor itself, candidate 1 (rows 2, 3) is perturbed
    assert torch.allclose(a[same], ref[same], atol=1e-6)
    assert not torch.allclose(a[2:4], ref[2:4], atol=1e-4)


def test_score_counts_the_first_episode_and_prices_a_collision():
    T = 4
    done = torch.zeros(2, T, 1, dtype=torch.bool)
    done[1, 1] = True  # row 1 collides at step 1; steps 2-3 belong to the next episode
    nxt = TensorDict({"reward": torch.ones(2, T, 1), "cost": torch.zeros(2, T, 1), "done": done,
                      "collision": done.clone()}, batch_size=[2, T])
    td = TensorDict({"next": nxt}, batch_size=[2, T])
    s = score(td, cost_coeff=10.0)
    assert float(s[0]) == pytest.approx(1.0)
    # reward 1 on 2 of 4 steps, the 2 missing steps as cost 1, and the collision
    assert float(s[1]) == pytest.approx(2 / 4 - 10.0 * (2 / 4 + 1.0))
    s2 = score(td, cost_coeff=10.0, start=2)  # steps 2-3 only: row 1 has none left, and its collision counts
    assert float(s2[0]) == pytest.approx(1.0) and float(s2[1]) == pytest.approx(0.0 - 10.0 * (1.0 + 1.0))


def test_score_spends_a_cost_budget_free():
    """cost_limit: the mean cost per step below it is not penalised, the excess is; a collision always is."""
    T = 4
    cost = torch.tensor([[0.0, 0.1, 0.1, 0.0], [0.4, 0.4, 0.4, 0.4]]).unsqueeze(-1)  # means 0.05 and 0.4
    nxt = TensorDict({"reward": torch.ones(2, T, 1), "cost": cost, "done": torch.zeros(2, T, 1, dtype=torch.bool),
                      "collision": torch.zeros(2, T, 1, dtype=torch.bool)}, batch_size=[2, T])
    td = TensorDict({"next": nxt}, batch_size=[2, T])
    s = score(td, cost_coeff=10.0, cost_limit=0.1)
    assert float(s[0]) == pytest.approx(1.0)  # within the budget
    assert float(s[1]) == pytest.approx(1.0 - 10.0 * (0.4 - 0.1))
    assert torch.allclose(score(td, cost_coeff=10.0), torch.tensor([1.0 - 0.5, 1.0 - 4.0], dtype=torch.float64))


def test_cem_trains_the_actor_in_place_and_runs_from_mt_train(tmp_path):
    cfg = compose(TINY + ["policy.cem.generations=3", "policy.cem.population=4", "policy.cem.sigma=1.0",
                          "policy.cem.seconds=5.0", "policy.cem.init=actor"])
    actor, _ = _actor(cfg, rows=8)
    before = parameters_to_vector(actor.module[0].parameters()).detach().clone()
    out = cem_pretrain(actor, cfg, log=None)
    assert out["generations"] == 3 and len(out["score_of_mean"]) == 3
    kept = out["kept_generation"]
    assert out["kept_score"] == out["score_of_mean"][kept - 1]
    after = parameters_to_vector(actor.module[0].parameters())
    # generation 1's mean is the initial actor; a later one is a move of the search
    assert torch.allclose(after, before) == (kept == 1)
    from mixed_traffic.training import train

    summary = train(compose(TINY + ["policy.cem.generations=1"]), out_dir=tmp_path)
    assert (tmp_path / "final.pt").exists() and summary["summary"]["frames"] == 0
    import json

    saved = json.loads((tmp_path / "summary.json").read_text())
    assert saved["cem"]["generations"] == 1 and saved["cem"]["seconds"] > 0  # the CEM's own record


def test_cem_stops_within_trainer_max_minutes():
    """trainer.max_minutes bounds the search: it stops before a generation that would end past it."""
    cfg = compose(TINY + ["policy.cem.generations=4", "policy.cem.seconds=3.0", "trainer.max_minutes=0.00001"])
    actor, _ = _actor(cfg)
    logged = []
    out = cem_pretrain(actor, cfg, log=logged.append)
    assert out["generations"] == 1 and len(out["score_of_mean"]) == 1  # the first always runs, then the budget is spent
    assert "trainer.max_minutes" in out["stopped"] and "stopping before generation 2/4" in logged[-2]
    out = cem_pretrain(actor, compose(TINY + ["policy.cem.generations=2", "policy.cem.seconds=3.0"]), log=None)
    assert out["generations"] == 2 and out["stopped"] is None  # no budget: every generation


@pytest.mark.parametrize("override, field", [
    ("policy.cem.population=1", "policy.cem.population"),
    ("policy.cem.episodes=0", "policy.cem.episodes"),
    ("policy.cem.elite=0.0", "elite"),
    ("policy.cem.sigma_min=1.0", "sigma_min"),
    ("policy.cem.seconds=0.0", "policy.cem.seconds"),
    ("policy.cem.score_after=1.0", "policy.cem.score_after"),  # the episode (policy.cem.seconds) is 1 s
    ("policy.cem.init=zeros", "policy.cem.init"),
    ("policy.cem.cost_limit=-0.1", "policy.cem.cost_limit"),
])
def test_bad_cem_settings_name_the_field(override, field):
    cfg = compose(TINY + ["policy.cem.generations=1", override])
    actor, _ = _actor(cfg)
    before = parameters_to_vector(actor.module[0].parameters()).detach().clone()
    with pytest.raises(ValueError, match=field):
        cem_pretrain(actor, cfg, log=None)
    assert torch.equal(parameters_to_vector(actor.module[0].parameters()), before)  # nothing touched


def test_share_starts_gives_row_blocks_the_same_episodes():
    from mixed_traffic import make_env

    env = make_env("ring_wave", batch_size=6, seed=0, ring_length_range=[220.0, 270.0])
    env.share_starts(2)
    td = env.reset()
    L = td["traffic", "ring_length"][:, 0]
    assert torch.equal(L[0::2], L[0].expand(3)) and torch.equal(L[1::2], L[1].expand(3)) and L[0] != L[1]
    assert torch.equal(td["traffic", "pos"][0], td["traffic", "pos"][4])
    assert torch.equal(env.hdv_params["T"][1], env.hdv_params["T"][5])
    with pytest.raises(ValueError, match="period"):
        env.share_starts(4)  # not a divisor of 6


def test_cem_is_deterministic_under_a_seed():
    def run(seed):
        cfg = compose(TINY + ["policy.cem.generations=2", "policy.cem.sigma=1.0", "policy.cem.seconds=3.0",
                              f"seed={seed}"])
        torch.manual_seed(0)  # the same initial actor
        actor, _ = _actor(cfg)
        out = cem_pretrain(actor, cfg, log=None)
        return parameters_to_vector(actor.module[0].parameters()).detach(), out["score_of_mean"]

    (p0, s0), (p1, s1), (_, s2) = run(0), run(0), run(1)
    assert torch.equal(p0, p1) and s0 == s1
    assert s2 != s0  # another seed: other candidates and other episodes


def test_zero_action_init_starts_the_search_at_the_set_point_schedule():
    """init=zero_action: the first mean acts 0, i.e. the ramped FollowerStopper that the set point corrects."""
    cfg = compose(TINY + ["policy.cem.generations=1", "policy.cem.init=zero_action"])  # the experiment's ramp 0.87 -> 1.0
    actor, env = _actor(cfg)
    cem_pretrain(actor, cfg, log=None)  # one generation: the kept mean is the first one
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        a = actor(env.reset())["action"]
    assert torch.equal(a, torch.zeros_like(a))
