"""Gymnasium environments of DeFT-Gym. Importing this package registers them (the env modules
themselves are imported only by ``gymnasium.make``):

- ``deft_gym/Adversary-v0``: :class:`deft_gym.envs.adversary.AdversaryEnv`.
"""

from gymnasium.envs.registration import register, registry

if "deft_gym/Adversary-v0" not in registry:
    register(id="deft_gym/Adversary-v0", entry_point="deft_gym.envs.adversary:AdversaryEnv")
