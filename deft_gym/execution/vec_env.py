"""Training on Ray: a stable-baselines3 ``VecEnv`` whose sub-environments are Ray actors.

SB3's PPO (its hyperparameters, checkpoints, callbacks, the evaluation's model loading) stays as
it is; only where the environments step changes: each actor holds one env (built by the same
thunk :class:`~stable_baselines3.common.vec_env.SubprocVecEnv` would run), ``step_async`` sends
the actions to all actors at once and ``step_wait`` collects them with ``ray.get``, resetting an
env whose episode ended exactly as ``SubprocVecEnv`` does. The actors can sit on any node of a
cluster. Why this rather than RLlib's PPO: docs/distributed.md.

Files the envs write into the run folder (episode journals, failing logs, extracted tests,
monitor CSVs) reach it through a shared path, or, from an actor that cannot see the run folder,
come back when the env closes (:mod:`deft_gym.execution.transfer`).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices, VecEnvStepReturn
from stable_baselines3.common.vec_env.subproc_vec_env import _stack_obs

from deft_gym.execution import transfer
from deft_gym.execution.watchdog import apply_env, carried_env


class EnvActor:
    """One environment in a Ray actor (the loop of SB3's ``SubprocVecEnv`` worker, as methods)."""

    def __init__(self, env_fn: Callable[[], Any], cwd: str, env: dict[str, str | None] | None = None) -> None:
        from stable_baselines3.common.vec_env.patch_gym import _patch_env

        apply_env(env)  # the driver's settings (e.g. --watchdog-s)
        if os.getcwd() != cwd:
            transfer.enter_working_dir(cwd)
        self.env = _patch_env(env_fn())

    def spaces(self) -> tuple[Any, Any]:
        return self.env.observation_space, self.env.action_space

    def step(self, action: Any) -> tuple[Any, Any, bool, dict[str, Any], dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        done = terminated or truncated
        info["TimeLimit.truncated"] = truncated and not terminated
        reset_info: dict[str, Any] = {}
        if done:
            info["terminal_observation"] = obs
            obs, reset_info = self.env.reset()
        return obs, reward, done, info, reset_info

    def reset(self, seed: int | None, options: dict[str, Any] | None) -> tuple[Any, dict[str, Any]]:
        return self.env.reset(seed=seed, **({"options": options} if options else {}))

    def render(self) -> Any:
        return self.env.render()

    def get_attr(self, name: str) -> Any:
        return self.env.get_wrapper_attr(name)

    def has_attr(self, name: str) -> bool:
        try:
            self.env.get_wrapper_attr(name)
            return True
        except AttributeError:
            return False

    def set_attr(self, name: str, value: Any) -> None:
        setattr(self.env, name, value)

    def env_method(self, name: str, args: tuple[Any, ...], kwargs: dict[str, Any]) -> Any:
        return self.env.get_wrapper_attr(name)(*args, **kwargs)

    def is_wrapped(self, wrapper_class: type) -> bool:
        from stable_baselines3.common.env_util import is_wrapped

        return is_wrapped(self.env, wrapper_class)

    def close(self, run_dir: str | None, token: str | None) -> bytes | None:
        """Close the env; the run folder's files as an archive when this node does not share it."""
        self.env.close()
        if run_dir and token and not os.path.exists(token):
            blob = transfer.pack([run_dir])
            transfer.remove([run_dir])
            return blob
        return None


class RayVecEnv(VecEnv):
    """``len(env_fns)`` envs, each in a Ray actor of ``num_cpus`` CPUs (Ray must be connected:
    :func:`deft_gym.execution.ray_backend.connect`)."""

    def __init__(self, env_fns: Sequence[Callable[[], Any]], run_dir: Path | str | None = None,
                 num_cpus: float = 1.0) -> None:
        import ray

        self.ray = ray
        actor = ray.remote(num_cpus=num_cpus)(EnvActor)
        self.actors = [actor.remote(fn, os.getcwd(), carried_env()) for fn in env_fns]
        self.run_dir = Path(run_dir).resolve() if run_dir is not None else None
        self.token = transfer.write_token(self.run_dir) if self.run_dir is not None else None
        self.waiting: list[Any] = []
        self.closed = False
        obs_space, act_space = ray.get(self.actors[0].spaces.remote())
        super().__init__(len(env_fns), obs_space, act_space)

    def step_async(self, actions: np.ndarray) -> None:
        self.waiting = [a.step.remote(act) for a, act in zip(self.actors, actions)]

    def step_wait(self) -> VecEnvStepReturn:
        results = self.ray.get(self.waiting)
        self.waiting = []
        obs, rews, dones, infos, self.reset_infos = zip(*results)
        return _stack_obs(obs, self.observation_space), np.stack(rews), np.stack(dones), infos  # type: ignore[return-value]

    def reset(self) -> Any:
        results = self.ray.get([a.reset.remote(self._seeds[i], self._options[i]) for i, a in enumerate(self.actors)])
        obs, self.reset_infos = zip(*results)
        self._reset_seeds()
        self._reset_options()
        return _stack_obs(obs, self.observation_space)

    def close(self) -> None:
        if self.closed:
            return
        if self.waiting:
            self.ray.get(self.waiting)
        token = str(self.token) if self.token else None
        blobs = self.ray.get([a.close.remote(str(self.run_dir) if self.run_dir else None, token) for a in self.actors])
        for blob in blobs:
            if blob:
                transfer.unpack(blob)
        for a in self.actors:
            self.ray.kill(a)
        if self.token is not None:
            self.token.unlink(missing_ok=True)
        self.closed = True

    def get_images(self) -> Sequence[np.ndarray | None]:
        return self.ray.get([a.render.remote() for a in self.actors])

    def _targets(self, indices: VecEnvIndices) -> list[Any]:
        return [self.actors[i] for i in self._get_indices(indices)]

    def has_attr(self, attr_name: str) -> bool:
        return all(self.ray.get([a.has_attr.remote(attr_name) for a in self.actors]))

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        return self.ray.get([a.get_attr.remote(attr_name) for a in self._targets(indices)])

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        self.ray.get([a.set_attr.remote(attr_name, value) for a in self._targets(indices)])

    def env_method(self, method_name: str, *method_args: Any, indices: VecEnvIndices = None,
                   **method_kwargs: Any) -> list[Any]:
        return self.ray.get([a.env_method.remote(method_name, method_args, method_kwargs)
                             for a in self._targets(indices)])

    def env_is_wrapped(self, wrapper_class: type, indices: VecEnvIndices = None) -> list[bool]:
        return self.ray.get([a.is_wrapped.remote(wrapper_class) for a in self._targets(indices)])
