"""The compiled parts of the control module give bit-identical results to the Python versions.

``deft_gym/modules/_control_c.c`` (built by ``pip install -e .``) converts a planned trajectory
(``float_lists``, for ``_trajectory_lists``) and finds the nearest trajectory point
(``nearest``, for ``_nearest``) when it is available. They are checked against the Python
functions on every seed scenario's plans, on planted inputs that the kernel must refuse (so the
Python and numpy path gives its own result or error), and over a full run of the control node.
"""

from __future__ import annotations

import copy
import math
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from deft_gym.bus.ads import load_ads_config
from deft_gym.bus.codec import encode
from deft_gym.modules import control
from deft_gym.modules.control import ControlNode, _nearest, _trajectory_lists
from deft_gym.scenarios.scenario import list_scenarios, load_scenario
from deft_gym.sim.simulation import Simulation
from tests.support.fixtures import float_bits

pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")  # odd values overflow on purpose
COLUMNS = ("t", "x", "y", "v", "a", "heading")


def _kernel() -> Any:
    if control._control_c is None:
        pytest.fail("the compiled control kernel is not built (pip install -e . needs a C compiler) "
                    "or DEFT_GYM_PURE_PYTHON is set")
    return control._control_c


def _assert_same_lists(got: dict[str, list[float]] | None, want: dict[str, list[float]] | None) -> None:
    assert (got is None) == (want is None)
    if want is not None:
        assert list(got) == list(want)  # same keys, same order
        for k in want:
            assert type(got[k]) is list and float_bits(got[k]) == float_bits(want[k]), k


def _plans(path: Path, seed: int, duration: float) -> list[dict[str, Any]]:
    scenario = load_scenario(path)
    scenario = scenario.model_copy(update={"duration": min(scenario.duration, duration)})
    return [p["trajectory"] for p in Simulation(scenario, jitter_seed=seed).run().planning]


@pytest.fixture(scope="module")
def recorded() -> list[tuple[str, list[dict[str, Any]]]]:
    _kernel()
    return [(p.stem, _plans(p, seed=11, duration=25.0)) for p in list_scenarios()]


def test_float_lists_matches_python_on_every_seed_scenario(recorded) -> None:
    kernel = _kernel()
    taken = 0
    for name, plans in recorded:
        for i, tr in enumerate(plans):
            want, got = _trajectory_lists(tr), kernel.float_lists(tr)
            if want is not None and got is None:  # only np.unwrap's case is left to Python
                assert any(abs(b - a) >= math.pi for a, b in zip(tr["heading"], tr["heading"][1:])), (name, i)
                continue
            _assert_same_lists(got, want)
            if got is not None:
                assert all(got[k] is tr[k] for k in ("t", "x", "y", "v", "a"))  # as _float_lists: not copied
                taken += 1
    assert taken > 500


def test_nearest_matches_python_on_every_seed_scenario(recorded) -> None:
    kernel = _kernel()
    rng = np.random.default_rng(4)
    checked = 0
    for _, plans in recorded:
        for tr in plans[::5]:
            xs, ys = tr["x"], tr["y"]
            points = [(xs[k] + d, ys[k] - d) for k in range(0, len(xs), 7) for d in (0.0, 0.3, -2.0)]
            points += [tuple(p) for p in rng.normal(size=(4, 2)) * 30 + [xs[0], ys[0]]]
            for x, y in points:
                assert kernel.nearest(xs, ys, float(x), float(y)) == _nearest(xs, ys, float(x), float(y))
                checked += 1
    assert checked > 1000


def test_nearest_matches_python_on_ties_and_nan() -> None:
    kernel = _kernel()
    rng = np.random.default_rng(5)
    for _ in range(3000):
        n = int(rng.integers(1, 12))
        xs, ys = rng.normal(size=n).round(1), rng.normal(size=n).round(1)  # ties happen
        for _ in range(int(rng.integers(0, 3))):
            (xs if rng.random() < 0.5 else ys)[int(rng.integers(n))] = rng.choice([np.nan, np.inf, -np.inf])
        x, y = (float(v) for v in rng.normal(size=2).round(1))
        if rng.random() < 0.05:
            x = math.nan
        assert kernel.nearest(xs.tolist(), ys.tolist(), x, y) == _nearest(xs.tolist(), ys.tolist(), x, y)


def test_nearest_leaves_other_values_to_python() -> None:
    kernel = _kernel()
    xs, ys = [0.0, 1.0, 2.0], [0.0, 0.0, 0.0]
    assert kernel.nearest(xs, ys, 1.2, 0.0) == 1
    for args in [(xs, ys, 1, 0.0), (xs, ys, 1.0, np.float64(0.0)), (xs, ys[:2], 1.0, 0.0),
                 ([0.0, 1, 2.0], ys, 1.0, 0.0), (tuple(xs), ys, 1.0, 0.0), (xs, np.array(ys), 1.0, 0.0)]:
        assert kernel.nearest(*args) is None, args


def _base() -> dict[str, list[float]]:
    """A well-formed trajectory: a curve with a -0.0 heading and a standing end."""
    t = [0.1 * k for k in range(12)]
    heading = [-0.0, *(0.2 * k - 1.0 for k in range(1, 12))]
    x = [5.0 * math.cos(h) + 1.5 * k for k, h in enumerate(heading)]
    y = [5.0 * math.sin(h) for h in heading]
    x[-1], y[-1] = x[-2], y[-2]
    return {"t": t, "x": x, "y": y, "v": [3.0] * 12, "a": [-0.0] * 12, "heading": heading}


class _F(float):
    pass


def _planted() -> list[tuple[str, Any]]:
    """Inputs the kernel must leave to Python: (what, trajectory)."""
    out: list[tuple[str, Any]] = []

    def put(what: str, col: str, k: int, value: Any) -> None:
        tr = _base()
        tr[col][k] = value
        out.append((what, tr))

    for col in COLUMNS:
        for value in (1, True, _F(1.0), np.float64(1.0), None, "1.0"):
            put(f"{col} holds {type(value).__name__}", col, 3, value)
        tr = _base()
        tr[col] = tr[col][:-1]
        out.append((f"{col} shorter", tr))
        for kind in (tuple, np.array):
            tr = _base()
            tr[col] = kind(tr[col])
            out.append((f"{col} as {kind.__name__}", tr))
        tr = _base()
        del tr[col]
        out.append((f"no {col}", tr))
    tr = _base()
    for col in COLUMNS:
        tr[col] = []
    out.append(("empty", tr))
    for value in (math.nan, math.inf, -math.inf):
        put(f"t {value}", "t", 5, value)
        put(f"x {value}", "x", 5, value)
        put(f"heading {value}", "heading", 5, value)
    put("t backwards", "t", 5, 0.35)
    put("t backwards at the end", "t", 11, 0.0)
    put("heading step of pi", "heading", 4, _base()["heading"][3] + math.pi)
    put("heading step beyond pi", "heading", 4, _base()["heading"][3] - 4.0)
    put("arc length overflows", "x", 6, 1e308)
    tr = _base()
    tr["x"][3], tr["x"][4] = -1e308, 1e308
    out.append(("step overflows", tr))
    out.append(("not a dict", SimpleNamespace(**_base())))
    out.append(("a dict subclass", type("D", (dict,), {})(_base())))
    return out


def _traj(node: ControlNode, tr: Any) -> tuple[bool, dict[str, bytes]] | str:
    """What the control node makes of a plan: its columns' bits and whether it is the fast
    path, or the error it raises."""
    node._cache_seq = -1
    try:
        out = node._traj(SimpleNamespace(seq=1, payload={"trajectory": tr}))
    except Exception as exc:  # the same error with and without the kernel is a match too
        return f"{type(exc).__name__}: {exc}"
    return node._fast, {k: float_bits(v) for k, v in out.items()}


def test_float_lists_leaves_planted_inputs_to_python() -> None:
    kernel = _kernel()
    ads = load_ads_config()
    compiled, python = ControlNode(ads.control, ads.topics), ControlNode(ads.control, ads.topics)
    python.kernel = None
    base = _base()
    _assert_same_lists(kernel.float_lists(base), _trajectory_lists(base))
    assert kernel.float_lists(base) is not None and kernel.float_lists(base)["heading"][0] is base["heading"][0]
    for what, tr in _planted():
        assert kernel.float_lists(tr) is None, what
        before = copy.deepcopy(tr)
        assert _traj(compiled, tr) == _traj(python, tr), what
        assert repr(tr) == repr(before), what  # nothing changed in the plan


@pytest.mark.parametrize("seed", range(3))
def test_float_lists_matches_python_on_random_trajectories(seed: int) -> None:
    kernel = _kernel()
    rng = np.random.default_rng(seed)
    taken = 0
    for _ in range(2000):
        n = int(rng.integers(1, 70))
        scale = rng.choice([1e-300, 1e-3, 1.0, 1e3, 1e150, 1e300])
        tr = {k: (rng.normal(size=n) * scale).tolist() for k in ("x", "y", "v", "a")}
        tr["t"] = np.cumsum(rng.uniform(0.0, 0.2, size=n)).tolist()
        h = np.cumsum(rng.normal(size=n) * rng.choice([0.05, 0.5, 4.0]))
        tr["heading"] = ((h + np.pi) % (2 * np.pi) - np.pi).tolist()
        if rng.random() < 0.3:
            tr["heading"][int(rng.integers(n))] = -0.0
        if rng.random() < 0.1:
            tr[str(rng.choice(["x", "y", "t"]))][int(rng.integers(n))] = float(rng.choice([np.nan, np.inf]))
        want, got = _trajectory_lists(tr), kernel.float_lists(tr)
        if got is None and want is not None:  # np.unwrap's case
            assert any(abs(b - a) >= math.pi for a, b in zip(tr["heading"], tr["heading"][1:]))
            continue
        _assert_same_lists(got, want)
        taken += got is not None
    assert taken > 500


def _control_outputs(path: Path, kernel: Any) -> tuple[list[bytes], int]:
    """The control node's messages over a full run, and how many plans the kernel converted."""
    sim = Simulation(path, jitter_seed=5)
    node = next(n for n in sim.bus.nodes if isinstance(n, ControlNode))
    converted = 0

    def float_lists(tr: Any) -> Any:
        nonlocal converted
        out = kernel.float_lists(tr)
        converted += out is not None
        return out

    node.kernel = None if kernel is None else SimpleNamespace(float_lists=float_lists, nearest=kernel.nearest)
    topic, outputs = node.out_topic, []
    sim.bus.taps.append(lambda m: outputs.append(encode(m.payload)) if m.topic == topic else None)
    sim.run()
    return outputs, converted


def test_control_outputs_are_the_same_without_the_kernel() -> None:
    path = next(p for p in list_scenarios() if p.stem == "u_turn")
    with_kernel, converted = _control_outputs(path, _kernel())
    without, _ = _control_outputs(path, None)
    assert converted > 100 and len(with_kernel) > 400  # 27 s at 20 Hz
    assert with_kernel == without
