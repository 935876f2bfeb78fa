"""Stopping training (Ctrl-C, ``kill PID``) between two env replies still closes the env
processes: SB3's ``SubprocVecEnv.close`` would wait for replies already read and hang."""

from __future__ import annotations

import threading

import gymnasium as gym
import numpy as np


def test_envs_close_after_an_interrupt_between_two_replies() -> None:
    from stable_baselines3.common.vec_env import SubprocVecEnv

    from agents.train import close_envs

    vec = SubprocVecEnv([lambda: gym.make("CartPole-v1") for _ in range(2)], start_method="fork")
    vec.reset()
    vec.step_async(np.zeros(2, dtype=np.int64))
    vec.remotes[0].recv()  # the first reply read, then the interrupt: the second is still in its pipe
    vec.remotes[1].recv()  # ... or read too: close must not wait for either again
    assert vec.waiting
    done = threading.Thread(target=close_envs, args=(vec, True), daemon=True)
    done.start()
    done.join(30)
    assert not done.is_alive(), "closing the envs after an interrupt hung"
    assert vec.closed and not any(p.is_alive() for p in vec.processes)


def test_a_second_sigterm_cannot_break_off_the_save() -> None:
    """GNU ``timeout`` sends SIGTERM to the training process and then to its process group: the
    first stops training, the second once reached ``model.save`` and the model was lost (seen on a
    lent 16-core machine). After the first, SIGTERM is ignored."""
    import os
    import signal

    from agents.train import _interrupt

    before = signal.signal(signal.SIGTERM, _interrupt)
    try:
        stopped = False
        try:
            os.kill(os.getpid(), signal.SIGTERM)
        except KeyboardInterrupt:
            stopped = True
        assert stopped, "the first SIGTERM did not stop training"
        saved = False
        os.kill(os.getpid(), signal.SIGTERM)  # while saving: must not raise
        saved = True
        assert saved and signal.getsignal(signal.SIGTERM) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGTERM, before)
