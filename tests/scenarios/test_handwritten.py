"""The hand-written scenario group (``configs/scenarios/handwritten``): scenarios written as users
write them, an evaluation-only group beside the seeds and the generated scenarios."""

from __future__ import annotations

from pathlib import Path

import pytest

from agents.config import check_train_settings, load_train_config
from agents.evaluate import load_eval_config, parse_args
from deft_gym.config import CONFIG_DIR, ConfigError
from deft_gym.scenarios.generate import parse_spec
from deft_gym.scenarios.scenario import (
    SCENARIO_DIR,
    expand_groups,
    group_scenarios,
    is_group_scenario,
    list_scenarios,
    load_scenario,
)
from deft_gym.search.context import (
    SEED_SCENARIOS,
    parse_config_spec,
    resolve_scenario,
    robust,
    seed_context,
)

HANDWRITTEN = group_scenarios("handwritten")
FILES = sorted((SCENARIO_DIR / "handwritten").glob("*.yaml"))


def test_every_handwritten_scenario_loads_and_resolves() -> None:
    assert len(HANDWRITTEN) >= 12
    assert [f"handwritten/{p.stem}" for p in FILES] == HANDWRITTEN
    names = set()
    for spec, path in zip(HANDWRITTEN, FILES, strict=True):
        sc = resolve_scenario(spec)
        assert sc.model_dump() == load_scenario(path).model_dump()
        assert sc.name == path.stem and sc.description.startswith("Hand-written:")
        assert path.read_text().startswith("# "), f"{path.name}: expected a header comment"
        names.add(sc.name)
    assert len(names) == len(FILES)
    assert not names & {p.stem for p in list_scenarios()}  # no clash with a seed name


def test_a_bare_handwritten_name_is_answered_with_its_group_spelling() -> None:
    with pytest.raises(ConfigError, match="did you mean 'handwritten/stalled_car'"):
        resolve_scenario("stalled_car")
    with pytest.raises(ConfigError, match=r"not one of \[") as err:
        resolve_scenario("no_such_scenario")
    assert "did you mean" not in str(err.value)


def test_group_is_not_a_seed_and_expands_in_the_evaluation() -> None:
    assert all(p.parent == SCENARIO_DIR for p in list_scenarios())  # the seeds stay the top-level files
    assert expand_groups(["left_turn", "handwritten", "left_turn"]) == ["left_turn", *HANDWRITTEN]
    cfg = load_eval_config(parse_args(["--scenarios", "handwritten", "--methods", "random_delta",
                                       "--held-out", "0", "--workers", "1"]))
    assert cfg.scenarios == HANDWRITTEN
    with pytest.raises(ConfigError, match="does not resolve"):
        load_eval_config(parse_args(["--scenarios", "handwritten/no_such_scenario", "--methods", "random"]))


def _generated_with_config(spec: str) -> bool:
    """``gen:<seed>@<generator config>`` naming a shipped generator config."""
    parsed = parse_config_spec(spec)
    return parsed is not None and parsed[1].startswith("configs/generate/")


def test_training_never_uses_a_handwritten_scenario(tmp_path: Path) -> None:
    """Every shipped training config, the env's default list and the generated training seeds
    exclude the group; a training config that names one of them is refused."""
    hand = set(HANDWRITTEN) | {p.stem for p in FILES} | {str(p) for p in FILES}
    for path in sorted((CONFIG_DIR / "train").glob("*.yaml")):
        cfg = load_train_config(path)
        trained = set(cfg.env.scenarios)
        assert not trained & hand, path
        assert not any(is_group_scenario(s) for s in trained), path
        # seeds or generated scenarios (gen:<seed>, gen:<seed>@configs/generate/<config>.yaml)
        assert all(s in SEED_SCENARIOS or _generated_with_config(s) or parse_spec(s) is not None for s in trained), path
    assert not set(load_train_config().env.scenarios) & hand
    for spec in ("handwritten", HANDWRITTEN[0], f"{HANDWRITTEN[0]}~v3", str(FILES[0])):
        cfg = load_train_config(None, {"timesteps": 64})
        cfg = cfg.model_copy(update={"env": cfg.env.model_copy(update={"scenarios": ["left_turn", spec]})})
        with pytest.raises(ConfigError, match="evaluation-only"):
            check_train_settings(cfg, "train.yaml")


# the reference planner's own failure (docs/simulation.md): its lane change round the stopped bus
# begins too late and some jitter seeds brake into the bus's corner - the demo's flaky collision,
# so no optimal-decision seed
NOT_SEEDS = {"handwritten/stopped_bus"}


@pytest.mark.slow
@pytest.mark.parametrize("spec", [pytest.param(s, marks=pytest.mark.xfail(strict=True, reason="collides on some "
                                                 "jitter seeds: the reference planner's late lane change"))
                                  if s in NOT_SEEDS else s for s in HANDWRITTEN])
def test_handwritten_scenario_is_robust(spec: str) -> None:
    """What the evaluation demands of a held-out scenario: the reference run (medoid of five
    jitter seeds) completes without a lane change it gave up, and the unmutated runs with jitter
    seeds 1..8 complete consistently with it (:func:`deft_gym.search.context.robust`)."""
    ctx = seed_context(spec)
    assert ctx.ref.outcome == "completed"
    assert not ctx.ref.meta["not_completed"]
    assert robust(ctx, cache_dir=None)
