"""The CommonRoad adapter's vectorised kinematic check (deft_gym/planner/commonroad_kinematics.py)
is the library's ``ReactivePlanner._check_kinematics``, bit for bit: on every trajectory bundle
of hand-made frames (both velocity modes) and of whole episodes, both run on copies of the same
samples and every array, label and rejection count is compared. The bundles whose samples share
their lateral polynomials are the library's, sample by sample; the vectorised default cost gives
every sample the library's cost and the bundle its order. Skipped without the extra."""

from __future__ import annotations

import copy
from typing import Any

import numpy as np
import pytest

pytest.importorskip("commonroad_rp.reactive_planner", reason="CommonRoad's reactive planner is not installed: "
                    "pip install -e '.[commonroad]'")

from commonroad_rp.reactive_planner import ReactivePlanner

import deft_gym.planner.commonroad as adapter
from deft_gym.planner.commonroad import CommonRoadPlanner
from deft_gym.planner.commonroad_kinematics import (
    SharedLateralMixin,
    check_kinematics,
    default_costs,
    sort_bundle,
    to_cartesian,
)
from tests.planner.test_commonroad import ADS, TOGGLING, road_frames

SAMPLE_ARRAYS = {"cartesian": ("x", "y", "theta", "v", "a", "kappa", "kappa_dot"),
                 "curvilinear": ("s", "d", "theta", "s_dot", "s_ddot", "d_dot", "d_ddot")}


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


class _BothChecks(ReactivePlanner):
    """Runs the library's check and the vectorised one on copies of every bundle, asserts that
    they agree bit for bit and goes on with the library's result."""

    bundles: list[dict[str, Any]] = []

    def _check_kinematics(self, trajectories: list[Any], queue_1: Any = None, queue_2: Any = None) -> Any:
        copies = copy.deepcopy(trajectories)
        before = dict(self._infeasible_reason_dict)
        library, _ = ReactivePlanner._check_kinematics(self, trajectories)
        library_reasons = dict(self._infeasible_reason_dict)
        self._infeasible_reason_dict.clear()
        self._infeasible_reason_dict.update(before)
        fast, rest = check_kinematics(self, copies)
        assert rest == [] and self._infeasible_reason_dict == library_reasons
        index = {id(t): i for i, t in enumerate(trajectories)}
        index_copy = {id(t): i for i, t in enumerate(copies)}
        assert [index[id(t)] for t in library] == [index_copy[id(t)] for t in fast]
        assert [t.feasibility_label for t in trajectories] == [t.feasibility_label for t in copies]
        for a, b in zip(library, fast, strict=True):
            for part, names in SAMPLE_ARRAYS.items():
                pa, pb = getattr(a, part), getattr(b, part)
                assert pa.current_time_step == pb.current_time_step
                for name in names:
                    assert _same_bits(np.asarray(getattr(pa, name)), np.asarray(getattr(pb, name))), (part, name)
        _BothChecks.bundles.append({"samples": len(trajectories), "feasible": len(library),
                                    "low_vel": bool(self._low_vel_mode), "reasons": library_reasons})
        return library, []


def _plan_hand_made_frames() -> None:
    """One planner through frames in both velocity modes (the speed crosses 4 m/s both ways)."""
    planner = CommonRoadPlanner({})
    for fr in road_frames([*TOGGLING, 6.0, 8.0, 8.0]) + road_frames([0.0, 0.0, 0.3, 1.0]):
        planner.plan(fr)


@pytest.fixture
def both_checks(monkeypatch: pytest.MonkeyPatch) -> list[dict[str, Any]]:
    monkeypatch.setattr(adapter, "_FastReactivePlanner", _BothChecks)
    _BothChecks.bundles = []
    return _BothChecks.bundles


def test_the_vectorised_check_is_the_librarys_on_hand_made_frames(both_checks) -> None:
    """Both velocity modes, feasible and rejected samples (the speed crosses 4 m/s both ways)."""
    _plan_hand_made_frames()
    assert len(both_checks) >= len(TOGGLING) + 7
    assert {b["low_vel"] for b in both_checks} == {True, False}
    assert sum(b["feasible"] for b in both_checks) > 0
    assert sum(b["samples"] - b["feasible"] for b in both_checks) > 0


def test_the_planner_uses_it_unless_told_not_to() -> None:
    fast, library = CommonRoadPlanner({}), CommonRoadPlanner({}, vectorised_kinematics=False)
    outputs = []
    for planner in (fast, library):
        outputs.append([planner.plan(fr) for fr in road_frames(TOGGLING)])
        model = next(iter(planner._models.values()))
        assert isinstance(model.planner, adapter._FastReactivePlanner) == (planner is fast)
    assert outputs[0] == outputs[1]


class _BothBundles(SharedLateralMixin, ReactivePlanner):
    """Builds every bundle the library's way and with shared lateral polynomials, asserts that
    they hold the same samples bit for bit, and goes on with the shared one."""

    bundles: list[tuple[bool, int, int]] = []

    def _create_trajectory_bundle(self, x_0_lon: Any, x_0_lat: Any, samp_level: int) -> Any:
        library = ReactivePlanner._create_trajectory_bundle(self, x_0_lon, x_0_lat, samp_level)
        shared = SharedLateralMixin._create_trajectory_bundle(self, x_0_lon, x_0_lat, samp_level)
        assert len(library.trajectories) == len(shared.trajectories)
        for a, b in zip(library.trajectories, shared.trajectories, strict=True):
            for pa, pb in ((a.trajectory_long, b.trajectory_long), (a.trajectory_lat, b.trajectory_lat)):
                assert type(pa) is type(pb) and type(pa.delta_tau) is type(pb.delta_tau)
                assert float(pa.delta_tau).hex() == float(pb.delta_tau).hex()
                for name in ("coeffs", "x_0", "x_d"):
                    assert _same_bits(np.asarray(getattr(pa, name)), np.asarray(getattr(pb, name))), name
        _BothBundles.bundles.append((bool(self._low_vel_mode), len(shared.trajectories),
                                     len({id(t.trajectory_lat) for t in shared.trajectories})))
        return shared


@pytest.fixture
def both_bundles(monkeypatch: pytest.MonkeyPatch) -> list[tuple[bool, int, int]]:
    monkeypatch.setattr(adapter, "_FastReactivePlanner", _BothBundles)
    _BothBundles.bundles = []
    return _BothBundles.bundles


def test_bundles_that_share_lateral_polynomials_are_the_librarys(both_bundles) -> None:
    """Both velocity modes; at high velocity the samples share a lateral trajectory several times
    over (at low velocity its length depends on the longitudinal sample: few are shared)."""
    planner = CommonRoadPlanner({})
    for fr in road_frames([*TOGGLING, 6.0, 8.0]) + road_frames([0.0, 0.3, 1.0]):
        planner.plan(fr)
    bundles = both_bundles
    assert len(bundles) >= len(TOGGLING) and {low for low, _, _ in bundles} == {True, False}
    samples, lateral = (sum(b[i] for b in bundles if not b[0]) for i in (1, 2))
    assert samples >= 3 * lateral > 0


class _BothSorts(ReactivePlanner):
    """Costs every sorted bundle the library's way (``DefaultCostFunction.evaluate`` per sample)
    and with :func:`default_costs`, asserts the same floats, sorts with :func:`sort_bundle` and
    asserts the library's order."""

    bundles: list[tuple[int, bool]] = []

    def _create_trajectory_bundle(self, x_0_lon: Any, x_0_lat: Any, samp_level: int) -> Any:
        bundle = ReactivePlanner._create_trajectory_bundle(self, x_0_lon, x_0_lat, samp_level)

        def both() -> None:
            samples, cost_function = list(bundle.trajectories), bundle._cost_function
            if samples:
                library = [cost_function.evaluate(t) for t in samples]
                fast = default_costs(cost_function, samples)
                assert fast is not None and len(fast) == len(library)
                for a, b in zip(library, fast, strict=True):
                    assert type(a) is type(b) and np.float64(a).tobytes() == np.float64(b).tobytes()
                order = sorted(range(len(samples)), key=lambda i: library[i])
            sort_bundle(bundle)
            if samples:
                assert [id(t) for t in bundle.trajectories] == [id(samples[i]) for i in order]
                assert [t.cost for t in bundle.trajectories] == [library[i] for i in order]
                _BothSorts.bundles.append((len(samples), cost_function.desired_s is not None))

        bundle.sort = both
        return bundle


@pytest.fixture
def both_sorts(monkeypatch: pytest.MonkeyPatch) -> list[tuple[int, bool]]:
    monkeypatch.setattr(adapter, "_FastReactivePlanner", _BothSorts)
    _BothSorts.bundles = []
    return _BothSorts.bundles


def test_the_vectorised_default_cost_is_the_librarys(both_sorts) -> None:
    """Both velocity modes; bundles of many feasible samples."""
    _plan_hand_made_frames()
    assert len(both_sorts) >= len(TOGGLING) and max(n for n, _ in both_sorts) > 50


@pytest.mark.slow
@pytest.mark.parametrize("scenario", ["blocked_red_light", "handwritten/stalled_car"])
def test_the_vectorised_default_cost_is_the_librarys_through_whole_episodes(both_sorts, scenario) -> None:
    _compared_through_an_episode(scenario, both_sorts)


@pytest.mark.slow
@pytest.mark.parametrize("scenario", ["lane_follow_static", "blocked_red_light", "handwritten/stopped_bus",
                                      "handwritten/unprotected_left"])
def test_the_vectorised_check_is_the_librarys_through_whole_episodes(both_checks, scenario) -> None:
    _compared_through_an_episode(scenario, both_checks)


@pytest.mark.slow
@pytest.mark.parametrize("scenario", ["left_turn", "handwritten/stopped_bus"])
def test_bundles_that_share_lateral_polynomials_are_the_librarys_through_whole_episodes(both_bundles,
                                                                                     scenario) -> None:
    _compared_through_an_episode(scenario, both_bundles)


def _compared_through_an_episode(scenario: str, compared: list[Any]) -> None:
    """Runs ``scenario`` on jitter seed 5 and checks that at least every other plan compared a bundle."""
    from deft_gym.bus.ads import load_ads_config
    from deft_gym.sim.simulation import Simulation

    res = Simulation(scenario, load_ads_config(ADS), jitter_seed=5).run()
    assert res.planning and len(compared) >= len(res.planning) // 2


def test_rows_to_cartesian_are_the_point_by_point_conversion() -> None:
    """:func:`to_cartesian` gives each point's ``convert_to_cartesian_coords`` and drops a row at its
    first point outside the projection domain, as the library's loop does."""
    planner = CommonRoadPlanner({})
    planner.plan(road_frames([8.0])[0])
    (model,) = planner._models.values()
    (co,) = model.coords.values()
    rng = np.random.default_rng(3)
    s = rng.uniform(5.0, 60.0, (40, 21))
    d = rng.uniform(-3.0, 3.0, (40, 21))
    s[3, 7] = 1e6  # beyond the reference's end
    d[11, 0] = 1e4  # far beside it
    s[12, 20] = -1e6
    x, y, inside = to_cartesian(co, s, d, 31)
    assert inside.tolist() == [r not in (3, 11, 12) for r in range(40)]
    for r in np.flatnonzero(inside):
        points = np.array([co.convert_to_cartesian_coords(a, b) for a, b in zip(s[r], d[r])])
        assert _same_bits(x[r, :21], points[:, 0]) and _same_bits(y[r, :21], points[:, 1])
        assert not x[r, 21:].any() and not y[r, 21:].any()
    assert co.convert_to_cartesian_coords(1e6, 0.0) is None
