"""A model trained under one numpy major version evaluates under the other: its pickled spaces
(numpy 2's ``numpy._core`` paths do not exist under numpy 1.26, which the export extra pins) are
taken from the env, its training state is not read, and its parameters must still fit."""

from __future__ import annotations

import base64
import json
import zipfile
from pathlib import Path

import gymnasium as gym
import pytest
import torch

# a pickle of a global from a module that does not exist: what numpy 2's spaces are under numpy 1
FOREIGN = base64.b64encode(b"cnumpy._no_such_module\nthing\n.").decode()


def _saved(tmp_path: Path, env_id: str) -> tuple[Path, object]:
    from stable_baselines3 import PPO

    model = PPO("MlpPolicy", gym.make(env_id), n_steps=64, batch_size=64, device="cpu", seed=0)
    path = tmp_path / f"{env_id}.zip"
    model.save(path)
    return path, model


def _foreign_spaces(path: Path) -> Path:
    """The same model.zip with its spaces and last observation pickled under a foreign numpy."""
    out = path.with_name("foreign_" + path.name)
    with zipfile.ZipFile(path) as src, zipfile.ZipFile(out, "w") as dst:
        for item in src.infolist():
            raw = src.read(item.filename)
            if item.filename == "data":
                data = json.loads(raw)
                for key in ("observation_space", "action_space", "_last_obs"):
                    data[key] = {":type:": "<class 'numpy.ndarray'>", ":serialized:": FOREIGN}
                raw = json.dumps(data).encode()
            dst.writestr(item, raw)
    return out


def test_a_model_whose_spaces_do_not_unpickle_loads_with_the_envs(tmp_path: Path) -> None:
    from stable_baselines3 import PPO

    from agents.evaluate import check_model, load_policy

    path, trained = _saved(tmp_path, "CartPole-v1")
    foreign = _foreign_spaces(path)
    with pytest.raises(ModuleNotFoundError):
        PPO.load(foreign, device="cpu")  # what evaluate did before
    env = gym.make("CartPole-v1")
    check_model(str(foreign), "--model")  # readable: no ConfigError
    model = load_policy(str(foreign), env)
    assert model.observation_space == env.observation_space and model.action_space == env.action_space
    got, want = model.policy.state_dict(), trained.policy.state_dict()
    assert got.keys() == want.keys() and all(torch.equal(got[k], want[k]) for k in want)
    obs, _ = env.reset(seed=3)
    assert model.predict(obs, deterministic=True)[0] == trained.predict(obs, deterministic=True)[0]


def test_a_model_whose_parameters_do_not_fit_the_env_is_refused(tmp_path: Path) -> None:
    from agents.evaluate import load_policy

    path, _ = _saved(tmp_path, "Pendulum-v1")  # 3 observations, a continuous action
    with pytest.raises(RuntimeError, match="cannot load model"):
        load_policy(str(_foreign_spaces(path)), gym.make("CartPole-v1"))
