"""deft_gym/Adversary-v0: env checkers, seeding, validity by construction, replay, SB3."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import deft_gym  # noqa: F401  (registers the env)
from deft_gym.envs.adversary import ALONG, LATERAL, MANOEUVRES, OPS, AdversaryEnv
from deft_gym.search.context import seed_context
from deft_gym.search.episode import run_scenario

SCN = "lane_follow_static"  # no reactive participants: every mutation must be valid


def act(op: str, along: float, lateral: float, speed: int = 2, man: str = "keep") -> np.ndarray:
    return np.array([OPS.index(op), ALONG.index(along), LATERAL.index(lateral), speed, MANOEUVRES.index(man)])


def rollout(env: AdversaryEnv, seed: int, actions: list[np.ndarray] | None = None) -> tuple[list, dict]:
    env.action_space.seed(seed)
    obs, _ = env.reset(seed=seed)
    out, done, k, info = [obs], False, 0, {}
    while not done:
        a = actions[k] if actions and k < len(actions) else env.action_space.sample()
        obs, r, done, _trunc, info = env.step(a)
        out.append((obs, r))
        k += 1
    return out, info


def test_both_env_checkers_pass():
    from gymnasium.utils.env_checker import check_env as gym_check
    from stable_baselines3.common.env_checker import check_env as sb3_check

    env = gym.make("deft_gym/Adversary-v0", scenario=SCN, objective="both", render_mode="rgb_array")
    gym_check(env.unwrapped)
    sb3_check(env.unwrapped, warn=True)
    env.close()


def test_same_seed_same_episode():
    env = AdversaryEnv(scenario=SCN)
    a, ia = rollout(env, 5)
    b, ib = rollout(env, 5)
    assert len(a) == len(b)
    assert all(np.array_equal(x[0], y[0]) and x[1] == y[1] for x, y in zip(a[1:], b[1:]))
    assert ia["iou"] == ib["iou"] and ia["outcome"] == ib["outcome"]


def test_placements_are_valid_by_construction_and_replay_exactly():
    env = AdversaryEnv(scenario=SCN, objective="nods")
    plan = [act("cone", 30.0, -1.5), act("static_vehicle", 45.0, 3.5), act("vehicle", -20.0, 3.5, 3, "toward"),
            act("cone", 20.0, 1.5), act("change", -10.0, 3.5, 4, "away")]
    for seed in (0, 1):
        _, info = rollout(env, seed, plan)
        assert info["valid"] and info["invasive"] == []
        assert info["added"] >= 2
        assert set(info) >= {"collision", "nods", "iou", "f_p", "f_b", "valid", "outcome", "failure"}
    eq = env.equivalent_scenario()
    ctx = seed_context(SCN)
    specs = eq["scenario"]["participants"][len(ctx.scenario.participants):]
    run = run_scenario(ctx, specs, eq["jitter_seed"], added_at=eq["added_at"])
    trace = env.recorder.trace()
    assert np.array_equal(run.trace.ego, trace.ego)  # bit-identical replay of the episode


def test_noop_episode_matches_the_seed_and_renders():
    env = AdversaryEnv(scenario=SCN, render_mode="rgb_array")
    env.reset(seed=2)
    img = env.render()
    assert img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.uint8
    done, info = False, {}
    while not done:
        _, _, done, _, info = env.step(act("noop", 0.0, 0.0))
    assert info["outcome"] == "completed" and info["failure"] is None and info["iou"] > 0.9


def test_bad_config_is_one_clear_line(tmp_path):
    from deft_gym.config import ConfigError

    with pytest.raises(ConfigError, match="objective"):
        AdversaryEnv(scenario=SCN, objective="crash")
    bad = tmp_path / "bad.yaml"
    bad.write_text("max_added: 0\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml: max_added"):
        AdversaryEnv(config=bad)
    bad.write_text("- max_added\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml: expected a mapping"):
        AdversaryEnv(config=bad)


def test_tiny_ppo_learns_without_error(tmp_path):
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_vec_env

    venv = make_vec_env(lambda: AdversaryEnv(scenario=SCN, log_dir=str(tmp_path), keep_passing=1.0, extract=False),
                        n_envs=1)
    model = PPO("MlpPolicy", venv, n_steps=64, batch_size=32, n_epochs=1, seed=0, device="cpu")
    model.learn(total_timesteps=128)
    assert model.num_timesteps >= 128
    journal = list(tmp_path.glob("episodes-*.jsonl"))
    assert journal and journal[0].read_text().count("\n") >= 1
    venv.close()


def test_training_refuses_to_mix_a_new_run_into_an_old_one(tmp_path, capsys):
    """A fresh training run into a folder with another run's episode journals would mix their
    statistics: it is refused (continue with --resume, or use another folder)."""
    from agents import train

    (tmp_path / "episodes-0.jsonl").write_text('{"scenario": "take_exit", "valid": true}\n')
    assert train.main(["--config", "configs/train/demo.yaml", "--out", str(tmp_path), "--timesteps", "8"]) == 2
    assert "--resume" in capsys.readouterr().err
    assert (tmp_path / "episodes-0.jsonl").read_text().count("\n") == 1  # untouched


def test_evaluation_config_errors_name_the_file_and_field(tmp_path):
    from agents.evaluate import load_eval_config, parse_args
    from deft_gym.config import ConfigError

    cfg = tmp_path / "eval.yaml"
    cfg.write_text("- random\n")
    with pytest.raises(ConfigError, match=r"eval\.yaml: expected a mapping"):
        load_eval_config(parse_args(["--config", str(cfg), "--out", str(tmp_path)]))
    cfg.write_text("methods: [random, genetic]\n")
    with pytest.raises(ConfigError, match=r"eval\.yaml: methods: unknown \['genetic'\]"):
        load_eval_config(parse_args(["--config", str(cfg), "--out", str(tmp_path)]))
    assert load_eval_config(parse_args(["--methods", "random", "--budget", "3", "--out", str(tmp_path)])).budget == 3


def test_bench_env_profile_prints_both_profiles_and_restores_the_timed_methods(capsys) -> None:
    """deft-gym bench-env --profile: the cProfile shares, the shares timed around each call, the
    throughput; the timed methods are the originals again afterwards."""
    from deft_gym.cli import bench_env
    from deft_gym.envs.adversary import AdversaryEnv

    before = AdversaryEnv.__dict__["_obs"]
    assert bench_env.main(["--profile", "--config", "configs/train/demo.yaml", "--episodes", "2", "--generated", "0",
                           "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "CPU shares under cProfile" in out and "timed around each call" in out
    assert "scenarios per CPU-hour" in out and "closest-cone probe" in out
    assert AdversaryEnv.__dict__["_obs"] is before


def test_bench_env_without_profile_writes_its_figures_and_times_no_parts(tmp_path, capsys) -> None:
    """deft-gym bench-env: steps/s, scenarios per hour and per CPU-hour, to the console and to
    --out; no cProfile and no timed parts unless --profile asks."""
    import json

    from deft_gym.cli import bench_env

    out = tmp_path / "bench.json"
    assert bench_env.main(["--episodes", "2", "--scenarios", SCN, "--policy", "noop", "--out", str(out),
                           "--no-progress"]) == 0
    figures = json.loads(out.read_text())
    assert figures["episodes"] == 2 and figures["steps"] > 0 and figures["scenarios"] == [SCN]
    assert figures["scenarios_per_cpu_hour"] > 0 and "profile" not in figures
    text = capsys.readouterr().out
    assert "scenarios per CPU-hour" in text and "cProfile" not in text
