"""The covering order of a stress campaign: every field meets its first exceptional value, and every
role a stale duplicate, within the first (number of entries) tests; the planted faults are found early."""

from __future__ import annotations

import random

import pytest

from deft_gym.robustness.generate import (
    STALE,
    GenerationConfig,
    covered,
    covering_fields,
    generate_policies,
)
from deft_gym.robustness.spec import TestSpecification


def test_the_first_tests_cover_every_field_with_nan_first_and_every_role_with_a_stale_duplicate():
    spec, cfg = TestSpecification.from_schemas(), GenerationConfig(order="covering")
    entries = covering_fields(spec, cfg)
    fields = spec.select(cfg.roles, brittle=cfg.brittle)
    assert len(entries) == len(fields) + len({f.role for f in fields})
    seen = {(role, f.path if f else None): value for role, f, value in (covered(spec, cfg, i) for i in range(len(entries)))}
    assert len(seen) == len(entries)  # each entry once
    assert seen[("localization", "v")] == "float.nan" and seen[("localization", None)] == STALE
    for i in range(3 * len(entries)):  # the test's one policy is the covered entry
        role, f, value = covered(spec, cfg, i)
        policies = generate_policies(spec, cfg, random.Random(f"0:{i}"), i)
        first = policies[0]
        assert len(policies) == 1 and first.topic == role
        if f is None:
            assert first.mode == "inject" and first.set == []
        else:
            assert first.mode == "intercept" and [(a.path, a.value) for a in first.set] == [(f.path, value)]
    # a field's next visit takes its next value
    role, f, value = covered(spec, cfg, len(entries) + entries.index(("localization", f_v := next(
        f for r, f in entries if r == "localization" and f is not None and f.path == "v"))))
    assert (role, f, value) == ("localization", f_v, "float.inf")


@pytest.mark.slow
def test_a_covering_campaign_finds_the_four_planted_faults_within_110_tests(tmp_path):
    from deft_gym.robustness.campaign import Campaign, load_campaign_config, run_campaign

    cfg = load_campaign_config(None, {"generation": {"order": "covering"}})
    overlay = "configs/ads/faults/all.yaml"
    from deft_gym.config import load_mapping

    campaign = Campaign(cfg, seed=1, ads_overrides=load_mapping(overlay))
    summary = run_campaign(campaign, tmp_path / "c", 110, workers=2, minimise_findings="none", until_found=True)
    found = {k for k, v in summary["planted"].items() if v.get("found")}
    assert found == {"nan_speed", "empty_trajectory", "stale_stamp", "angle_wrap"}, summary["planted"]
