"""The timing-noise model: processing times, delivery delays, drops and event ordering.

All draws come from one private RNG. By default it is seeded from the OS, like a real system
whose timing nobody controls; a fixed seed (``--jitter-seed``) replays a run exactly. The seed
actually used is always known (:attr:`JitterModel.seed`) and recorded, so any run can be
replayed afterwards.
"""

from __future__ import annotations

import math
import random
import secrets
from math import cos as _cos
from math import exp as _exp
from math import log as _log
from math import sin as _sin
from math import sqrt as _sqrt

from deft_gym.bus.ads import Duration, JitterConfig

_NS_PER_MS = 1_000_000
_TWOPI = 2.0 * math.pi  # random.TWOPI


def os_seed() -> int:
    """A fresh 32-bit seed from the OS entropy pool."""
    return secrets.randbits(32)


class JitterModel:
    """Draws every timing quantity of a run from its own seeded RNG.

    ``VERSION`` names the sequence of draws; a log records it, since the same seed replays a run
    only with the same version."""

    VERSION = "deft_gym.bus.jitter/2"  # 2: lognormal via random.gauss

    def __init__(self, config: JitterConfig, seed: int | None = None) -> None:
        self.config = config
        self.seed = os_seed() if seed is None else int(seed)
        self._rng = random.Random(self.seed)
        # per distribution object: (the object, mu, sigma, spike_prob, spike_factor, min_ms)
        self._lognormal_params: dict[int, tuple[Duration, float, float | None, float, float, float]] = {}
        self.drops = 0
        # the config is frozen: what each draw reads of it, read once
        self._enabled = config.enabled
        self._drop_prob = config.drop_prob
        self._shuffle = config.enabled and config.shuffle_simultaneous

    def duration_ns(self, dist: Duration) -> int:
        """A processing (or dispatch) time [ns] drawn from ``dist``."""
        # per distribution object, its lognormal parameters (looked up by identity: hashing a
        # pydantic model hashes every field, on every draw; the entry keeps the object alive, so
        # its id is not reused)
        params = self._lognormal_params.get(id(dist))
        if params is None:
            params = self._lognormal_params[id(dist)] = (dist, *self._lognormal(dist), dist.spike_prob,
                                                         dist.spike_factor, dist.min_ms)
        _, mu, sigma, spike_prob, spike_factor, min_ms = params
        if sigma is None:
            return round(dist.mean_ms * _NS_PER_MS)
        rng = self._rng
        # rng.gauss(mu, sigma) written out (CPython's random.gauss: the same draws, the same
        # operations, its cached second Box-Muller value in rng.gauss_next), without its call
        z = rng.gauss_next
        rng.gauss_next = None
        if z is None:
            uniform = rng.random
            x2pi = uniform() * _TWOPI
            g2rad = _sqrt(-2.0 * _log(1.0 - uniform()))
            z = _cos(x2pi) * g2rad
            rng.gauss_next = _sin(x2pi) * g2rad
        ms = _exp(mu + z * sigma)  # lognormal
        if spike_prob and rng.random() < spike_prob:
            ms *= spike_factor
        return round((min_ms if min_ms > ms else ms) * _NS_PER_MS)  # max(ms, min_ms), its choices

    def _lognormal(self, dist: Duration) -> tuple[float, float | None]:
        """``(mu, sigma)`` of the lognormal with ``dist``'s mean and std; sigma None when the
        duration is constant (jitter off, or no spread)."""
        if not self._enabled or dist.std_ms == 0.0:
            return 0.0, None
        var = math.log1p((dist.std_ms / dist.mean_ms) ** 2) if dist.mean_ms > 0 else 0.0
        return math.log(max(dist.mean_ms, 1e-9)) - var / 2, math.sqrt(var)

    def delivery_ns(self, reliable: bool = False) -> int | None:
        """Delivery delay [ns] of one message to one subscriber, or None if it is dropped; a
        ``reliable`` delivery that draws a loss is redelivered (its delay drawn after the loss)."""
        if not self._enabled:
            return round(self.config.delivery.mean_ms * _NS_PER_MS)
        # a loss is drawn for every delivery; a reliable one is redelivered after it
        if self._drop_prob and self._rng.random() < self._drop_prob and not reliable:
            self.drops += 1
            return None
        return self.duration_ns(self.config.delivery)

    def timer_lateness_ns(self) -> int:
        """How late a periodic timer wakes up [ns] (half-normal)."""
        if not self._enabled or self.config.timer_ms == 0.0:
            return 0
        return round(abs(self._rng.gauss(0.0, self.config.timer_ms)) * _NS_PER_MS)

    def order_key(self) -> float:
        """Tie-break among events scheduled for the same instant (0 keeps FIFO order)."""
        return self._rng.random() if self._shuffle else 0.0
