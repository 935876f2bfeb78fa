"""Metric oracles wired into the search baselines and the adversary env (docs/metrics.md): the
records carry the metrics, a finding counts only on a valid mutation, re-checked on a second
jitter seed with the same signature."""

from __future__ import annotations

import numpy as np
import pytest

from deft_gym.metrics.oracle import ORACLES


@pytest.mark.parametrize("oracle", ["default", "ttc"])
def test_search_records_carry_the_metrics_and_the_oracle(oracle: str) -> None:
    from agents.search import search
    from deft_gym.search.context import seed_context

    ctx = seed_context("blocked_red_light")
    recs = list(search("random_delta", ctx, 3, seed=0, oracle=oracle))
    assert len(recs) == 3
    for r in recs:
        assert 0.0 <= r["metric_score"] <= 1.0
        assert set(r["metric_violations"]) <= set(ORACLES)
        if oracle == "default":
            assert "oracle" not in r
            continue
        assert r["oracle"] == "ttc"
        sig = r["oracle_signature"]
        if sig is None:  # no finding: nothing re-checked
            assert r["oracle_confirmed"] is None
        else:  # a finding: a valid mutation that violated the oracle, re-checked once more
            assert r["valid"] and "ttc" in r["metric_violations"] and sig.startswith("metric:ttc:")
            assert isinstance(r["oracle_confirmed"], bool) and r["sims"] >= 2


def test_the_env_rewards_its_metric_oracle() -> None:
    """An episode on blocked_red_light (its reference run closes on the parked blocker at a TTC
    of about 1.07 s < 1.5 s): with ``oracle: ttc`` and no-op actions the mutation (none) is valid
    and the TTC finding earns the failure bonus; with the default objective it earns nothing."""
    from deft_gym.envs.adversary import AdversaryEnv

    rewards = {}
    for oracle in ("ttc", "default"):
        env = AdversaryEnv("blocked_red_light", oracle=oracle)
        env.reset(seed=0, options={"jitter_seed": 0})
        done, total, info = False, 0.0, {}
        while not done:
            _, r, done, _, info = env.step(np.zeros(5, dtype=np.int64))  # no-op
            total += r
        env.close()
        assert info["valid"] and info["metrics"]["min_ttc"] < 1.5
        rewards[oracle] = total
        if oracle == "ttc":
            assert info["oracle_signature"] == "metric:ttc:seed:parked"
    assert rewards["ttc"] >= rewards["default"] + 9.0  # the failure bonus (10), less any shaping
