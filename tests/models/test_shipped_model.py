"""The adversary shipped in the package: it loads, it fits the env its training config describes,
and it acts (one episode of the adversary env driven by its policy)."""

from __future__ import annotations

import json

import numpy as np
from stable_baselines3 import PPO

from agents.evaluate import check_model, model_env_config
from deft_gym.envs.adversary import AdversaryEnv, load_env_config
from deft_gym.models import default_model, resolve_model


def test_shipped_model_files_and_provenance():
    model = default_model()
    assert model.is_file() and 100_000 < model.stat().st_size < 10_000_000  # a few MB
    check_model(str(model), "deft_gym/models/adversary/model.zip")  # a readable SB3 model with a policy
    prov = json.loads((model.parent / "provenance.json").read_text())
    assert len(prov["commit"]) == 40 and "configs/train/adversary.yaml" in prov["command"]
    summary = json.loads((model.parent / "summary.json").read_text())
    assert summary["timesteps"] >= 150_000  # the full budget of configs/train/adversary.yaml
    assert resolve_model("default") == str(model)


def test_shipped_model_acts_in_its_env():
    model = PPO.load(default_model(), device="cpu")
    cfg = load_env_config(model_env_config(str(default_model())))
    cfg = cfg.model_copy(update={"scenarios": ["take_exit"], "variant_prob": 0.0, "log_dir": None})
    env = AdversaryEnv(config=cfg)
    try:
        assert env.observation_space.shape == model.observation_space.shape
        assert env.action_space == model.action_space
        obs, _ = env.reset(seed=3)
        done, steps, info = False, 0, {}
        while not done:
            action, _ = model.predict(obs, deterministic=True)
            assert env.action_space.contains(np.asarray(action))
            obs, _, done, _, info = env.step(action)
            steps += 1
        assert steps >= 1 and env.last_verdict is not None
        assert int(info["added"]) >= 1  # the trained policy places something rather than doing nothing
    finally:
        env.close()


def test_tempered_actions_sample_the_policy_flattened():
    """``evaluate --temperature``: at 1 the sampled actions are ``predict``'s (the same draws of
    torch's generator); higher temperatures spread the choices towards uniform, lower ones
    concentrate them on the greedy action."""
    import torch

    from agents.evaluate import tempered_action

    model = PPO.load(default_model(), device="cpu")
    obs = np.zeros(model.observation_space.shape, dtype=np.float32)
    for seed in range(20):
        torch.manual_seed(seed)
        a = model.predict(obs, deterministic=False)[0]
        torch.manual_seed(seed)
        assert np.array_equal(tempered_action(model, obs, 1.0), a)
    greedy = model.predict(obs, deterministic=True)[0]
    torch.manual_seed(0)
    share = {}
    for t in (0.01, 1.0, 8.0):
        acts = np.array([tempered_action(model, obs, t) for _ in range(400)])
        assert all(model.action_space.contains(x) for x in acts[:5])
        share[t] = float((acts == greedy).mean())  # how often each dimension takes the greedy choice
    assert share[0.01] > 0.98
    assert share[0.01] > share[1.0] > share[8.0]
    assert share[8.0] < 0.5
