"""The jitter model's draws against their specification: ``random.Random``'s own ``gauss`` and
``random`` in the order the model has always drawn them (a log's jitter seed replays a run only
with the same sequence, ``JitterModel.VERSION``)."""

from __future__ import annotations

import math
import random

import pytest

from deft_gym.bus.ads import Duration, JitterConfig
from deft_gym.bus.jitter import JitterModel


class _Spec:
    """The draws as they were written before ``duration_ns`` inlined ``random.gauss``."""

    def __init__(self, config: JitterConfig, seed: int) -> None:
        self.config, self.rng, self.drops = config, random.Random(seed), 0

    def duration_ns(self, dist: Duration) -> int:
        if not self.config.enabled or dist.std_ms == 0.0:
            return round(dist.mean_ms * 1_000_000)
        var = math.log1p((dist.std_ms / dist.mean_ms) ** 2) if dist.mean_ms > 0 else 0.0
        mu, sigma = math.log(max(dist.mean_ms, 1e-9)) - var / 2, math.sqrt(var)
        ms = math.exp(self.rng.gauss(mu, sigma))
        if dist.spike_prob and self.rng.random() < dist.spike_prob:
            ms *= dist.spike_factor
        return round(max(ms, dist.min_ms) * 1_000_000)

    def delivery_ns(self, reliable: bool = False) -> int | None:
        if not self.config.enabled:
            return round(self.config.delivery.mean_ms * 1_000_000)
        if self.config.drop_prob and self.rng.random() < self.config.drop_prob and not reliable:
            self.drops += 1
            return None
        return self.duration_ns(self.config.delivery)

    def timer_lateness_ns(self) -> int:
        if not self.config.enabled or self.config.timer_ms == 0.0:
            return 0
        return round(abs(self.rng.gauss(0.0, self.config.timer_ms)) * 1_000_000)

    def order_key(self) -> float:
        if self.config.enabled and self.config.shuffle_simultaneous:
            return self.rng.random()
        return 0.0


CONFIGS = {
    "default": JitterConfig(),
    "spikes and a floor": JitterConfig(delivery=Duration(mean_ms=2.0, std_ms=3.0, min_ms=1.5, spike_prob=0.2,
                                                         spike_factor=4.0), drop_prob=0.3),
    "constant": JitterConfig(delivery=Duration(mean_ms=1.25), dispatch=Duration(mean_ms=0.0), timer_ms=0.0),
    "off": JitterConfig(enabled=False),
    "no shuffle": JitterConfig(shuffle_simultaneous=False),
}


@pytest.mark.parametrize("name", list(CONFIGS))
def test_draws_are_the_specified_sequence(name: str) -> None:
    """Every kind of draw, interleaved in a seeded random order as a run interleaves them (the
    cached second Box-Muller value crosses from one kind to the next): the same values, the same
    drops, and the generator left in the same state."""
    config = CONFIGS[name]
    dists = [config.delivery, config.dispatch, Duration(mean_ms=5.0, std_ms=1.0, spike_prob=1.0, spike_factor=2.5)]
    for seed in (0, 1, 2**31 - 1):
        model, spec = JitterModel(config, seed), _Spec(config, seed)
        order = random.Random(seed + 1)
        for _ in range(20_000):
            kind = order.randrange(5)
            if kind < 3:
                dist = order.choice(dists)
                assert model.duration_ns(dist) == spec.duration_ns(dist)
            elif kind == 3:
                reliable = order.random() < 0.2
                assert model.delivery_ns(reliable) == spec.delivery_ns(reliable)
            else:
                assert (model.timer_lateness_ns(), model.order_key()) == (spec.timer_lateness_ns(), spec.order_key())
        assert model.drops == spec.drops
        assert model._rng.getstate() == spec.rng.getstate()
