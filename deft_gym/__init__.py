"""DeFT-Gym: testing autonomous-driving planning - a jittered multi-module ADS on highway-env, an
RL adversary, DeFT test extraction and ASTAA robustness testing (see the README)."""

from deft_gym import envs as _envs  # noqa: F401  registers deft_gym/Adversary-v0 (env code loads on gymnasium.make)
