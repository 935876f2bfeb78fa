"""The compiled evaluation step of the lattice planner gives bit-identical results to numpy.

``deft_gym/planner/_lattice_c.c`` (built by ``pip install -e .``) replaces
``LatticePlanner._evaluate_numpy`` when it is available. Every seed scenario's live frames, and
the same frames with exceptional values planted in them, are planned by two planners - one
with the compiled step, one without - and must give the same bytes (or the same error).
"""

from __future__ import annotations

import copy
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from deft_gym.bus.codec import encode
from deft_gym.planner import lattice
from deft_gym.planner.base import Frame, load_planner
from deft_gym.scenarios.scenario import list_scenarios, load_scenario
from deft_gym.sim.simulation import Simulation

pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")  # odd values overflow on purpose
LATTICE = "deft_gym.planner.lattice:LatticePlanner"
ODD = [math.nan, math.inf, -math.inf, 1e300, -1e300, 0.0, -0.0, 5e-324, -3.0]


def _frames(path: Path, seed: int, duration: float) -> tuple[dict, list[Frame]]:
    scenario = load_scenario(path)
    scenario = scenario.model_copy(update={"duration": min(scenario.duration, duration)})
    sim = Simulation(scenario, jitter_seed=seed)
    frames: list[Frame] = []
    plan = sim.planner.plan

    def spy(frame: Frame) -> dict | None:
        frames.append(frame)
        return plan(frame)

    sim.planner.plan = spy  # type: ignore[method-assign]
    sim.run()
    return sim.scenario.map.model_dump(), frames


def _pair(map_spec: dict) -> tuple[lattice.LatticePlanner, lattice.LatticePlanner]:
    compiled = load_planner(LATTICE, map_spec, {})
    numpy_only = load_planner(LATTICE, map_spec, {})
    numpy_only.kernel = None
    return compiled, numpy_only


def _outcome(planner: lattice.LatticePlanner, frame: Frame) -> bytes | str:
    try:
        out = planner.plan(frame)
    except Exception as exc:  # the same error from both is a match too
        return f"{type(exc).__name__}: {exc}"
    return encode(out) if out is not None else b"None"


def _kernel():
    if lattice._lattice_c is None:
        pytest.fail("the compiled planner step is not built (pip install -e . needs a C compiler) "
                    "or DEFT_GYM_PURE_PYTHON is set")
    return lattice._lattice_c


def _proxy(**replaced) -> SimpleNamespace:
    """The compiled module with some functions replaced (to count or record calls)."""
    kernel = _kernel()
    return SimpleNamespace(**{**{k: getattr(kernel, k) for k in dir(kernel) if not k.startswith("_")}, **replaced})


@pytest.fixture(scope="module")
def recorded() -> list[tuple[str, dict, list[Frame]]]:
    _kernel()
    return [(p.stem, *_frames(p, seed=11, duration=25.0)) for p in list_scenarios()]


def test_compiled_step_matches_numpy_on_every_seed_scenario(recorded) -> None:
    checked = 0
    for name, map_spec, frames in recorded:
        compiled, numpy_only = _pair(map_spec)
        for i, frame in enumerate(frames):
            a, b = _outcome(compiled, frame), _outcome(numpy_only, frame)
            assert a == b, f"{name}: frame {i} at t={frame.time}"
            checked += isinstance(a, bytes) and a != b"None"
    assert checked > 1000


def _corrupt(frame: Frame, rng: np.random.Generator) -> Frame:
    """The frame with one to three numbers of localization or prediction replaced by odd values."""
    inputs = copy.deepcopy(dict(frame.inputs))
    slots: list[tuple[dict | list, str | int]] = []
    loc = inputs.get("localization")
    if loc:
        slots += [(loc, k) for k in ("x", "y", "heading", "v", "a") if k in loc]
    for ob in (inputs.get("prediction") or {}).get("obstacles", []):
        slots += [(ob, k) for k in ("length", "width", "v", "t0", "dt") if k in ob]
        for key in ("x", "y", "heading"):
            slots += [(ob[key], j) for j in range(len(ob[key]))]
    for j in rng.choice(len(slots), size=min(len(slots), int(rng.integers(1, 4))), replace=False):
        holder, key = slots[j]
        holder[key] = ODD[int(rng.integers(len(ODD)))]
    return Frame(frame.time, inputs)


def test_compiled_step_matches_numpy_on_exceptional_values(recorded) -> None:
    rng = np.random.default_rng(3)
    outcomes = {"planned": 0, "error": 0}
    for name, map_spec, frames in recorded:
        compiled, numpy_only = _pair(map_spec)
        for i, frame in enumerate(frames):
            if i % 3 == 0:
                frame = _corrupt(frame, rng)
            a, b = _outcome(compiled, frame), _outcome(numpy_only, frame)
            assert a == b, f"{name}: frame {i} at t={frame.time}"
            outcomes["planned" if isinstance(a, bytes) else "error"] += 1
    assert outcomes["planned"] > 500 and outcomes["error"] > 0, outcomes


def test_compiled_step_rejects_arrays_of_the_wrong_shape() -> None:
    kernel = _kernel()
    with pytest.raises(TypeError, match="takes 20 arguments"):
        kernel.evaluate()
    z = np.zeros(4)
    args = [z] * 6 + [np.zeros((3, 2, 3)), np.zeros(2), np.zeros((3, 2, 4))]
    with pytest.raises(ValueError, match="lat_d: dimension 2 is 4, expected 3"):
        kernel.evaluate(*args, *([None] * 11))
    with pytest.raises(TypeError, match="ref_x: expected a C-contiguous float64 array"):
        kernel.evaluate(z, z.astype(np.float32), *([None] * 18))


@pytest.mark.parametrize("batch", [1, 64])
def test_judging_batch_size_changes_no_result(recorded, monkeypatch, batch: int) -> None:
    """Pairs are judged lazily in batches; the batch size (read per call by both paths) may
    change the speed only, never the plan."""
    for name, map_spec, frames in recorded[:4]:
        compiled, numpy_only = _pair(map_spec)
        default = load_planner(LATTICE, map_spec, {})
        reference = [_outcome(default, f) for f in frames]
        monkeypatch.setattr(lattice.LatticePlanner, "BATCH", batch)
        for planner in (compiled, numpy_only):
            got = [_outcome(planner, f) for f in frames]
            assert got == reference, f"{name}: batch {batch}, {'numpy' if planner.kernel is None else 'C'}"
        monkeypatch.undo()


ODD_TYPES = [1, True, None, "1.0", [1.0], (1.0, 2.0)]


def _odd_type(frame: Frame, rng: np.random.Generator) -> Frame | None:
    """The frame with one prediction value of another type than a float (or a point list of
    another length, or a key gone), or None without moving obstacles."""
    inputs = copy.deepcopy(dict(frame.inputs))
    moving = [ob for ob in (inputs.get("prediction") or {}).get("obstacles", []) if len(ob["x"]) > 1]
    if not moving:
        return None
    ob = moving[int(rng.integers(len(moving)))]
    key = ("x", "y", "heading", "length", "width", "v", "t0")[int(rng.integers(7))]
    kind = int(rng.integers(4))
    if kind == 0 and key in ("x", "y", "heading"):
        ob[key] = ob[key][:-1] if rng.integers(2) else tuple(ob[key])  # shorter, or a tuple
    elif kind == 1:
        ob.pop(key, None)
    elif key in ("x", "y", "heading"):
        ob[key][int(rng.integers(len(ob[key])))] = ODD_TYPES[int(rng.integers(len(ODD_TYPES)))]
    else:
        ob[key] = ODD_TYPES[int(rng.integers(len(ODD_TYPES)))]
    return Frame(frame.time, inputs)


def test_obstacle_resampling_matches_numpy_on_odd_types(recorded) -> None:
    """The compiled resampling takes only lists of Python floats; anything else goes to the
    numpy lines, so both planners give the same plan or the same error."""
    rng = np.random.default_rng(5)
    outcomes = {"planned": 0, "error": 0}
    taken = []

    def resample(*args):
        taken.append(_kernel().resample(*args))
        return taken[-1]

    for name, map_spec, frames in recorded:
        compiled, numpy_only = _pair(map_spec)
        compiled.kernel = _proxy(resample=resample)  # counting the groups it resampled
        for i, frame in enumerate(frames):
            odd = _odd_type(frame, rng) if i % 2 == 0 else None
            frame = odd or frame
            a, b = _outcome(compiled, frame), _outcome(numpy_only, frame)
            assert a == b, f"{name}: frame {i} at t={frame.time}"
            outcomes["planned" if isinstance(a, bytes) else "error"] += 1
    assert outcomes["planned"] > 500 and outcomes["error"] > 0, outcomes
    assert taken.count(True) > 500 and taken.count(False) > 50  # both ways were taken


def test_resample_takes_only_well_formed_obstacles() -> None:
    kernel = _kernel()
    tq = np.array([0.0, 0.05, 0.25, 0.5, 10.0])
    ob = {"x": [0.0, 1.0, 2.0], "y": [5.0, 5.5, 6.0], "heading": [0.0, 0.25, 0.5], "length": 4.0, "width": 2.0,
          "v": 3.0}

    def run(o: dict) -> tuple[bool, np.ndarray, np.ndarray, np.ndarray]:
        oxy, oh, dims = np.zeros((2, 2, 5)), np.zeros((2, 5)), np.zeros((2, 3))
        ok = kernel.resample([o], tq, 0.0, 1.0 / 0.2, 3, 1, oxy, oh, dims)
        return ok, oxy[:, 1], oh[1], dims[1]

    ok, xy, h, d = run(ob)
    assert ok
    f = np.minimum(np.maximum(tq / 0.2, 0.0), 2.0)  # 0, 0.25, 1.25, 2, 2
    np.testing.assert_array_equal(xy[0], [0.0, 0.25, 1.25, 2.0, 2.0])
    np.testing.assert_array_equal(xy[1], [5.0, 5.125, 5.625, 6.0, 6.0])
    np.testing.assert_array_equal(h, np.array([0.0, 0.25, 0.5])[np.rint(f).astype(int)])  # 1.25 -> 1, 2.5 -> 2
    np.testing.assert_array_equal(d, [2.0, 1.0, 3.0])
    ok, _, _, d = run({k: v for k, v in ob.items() if k != "v"})
    assert ok and d[2] == 0.0  # no speed: 0, as ob.get("v", 0.0)
    for odd in ({**ob, "x": [0, 1.0, 2.0]}, {**ob, "y": [5.0, 5.5]}, {**ob, "heading": (0.0, 0.25, 0.5)},
                {**ob, "length": 4}, {**ob, "v": None}, {k: v for k, v in ob.items() if k != "width"}):
        assert not run(odd)[0], odd
    oxy, oh, dims = np.zeros((2, 2, 5)), np.zeros((2, 5)), np.zeros((2, 3))
    assert not kernel.resample([ob], tq, math.nan, 5.0, 3, 0, oxy, oh, dims)  # NaN time: the numpy lines decide
    with pytest.raises(ValueError, match="rows out of range"):
        kernel.resample([ob, ob], tq, 0.0, 5.0, 3, 1, oxy, oh, dims)
    with pytest.raises(ValueError, match="oh: dimension 1 is 4, expected 5"):
        kernel.resample([ob], tq, 0.0, 5.0, 3, 0, oxy, np.zeros((2, 4)), dims)


def _bits(a: np.ndarray) -> bytes:
    """The array's bytes with every NaN made the same NaN (payloads may differ, values may not)."""
    return np.where(np.isnan(a), math.nan, a).tobytes()


def test_profiles_match_numpy_bitwise(recorded) -> None:
    """The compiled longitudinal profiles equal ``_profiles_numpy`` bit for bit, on the calls of
    every seed scenario's frames and on the same calls with odd start states and targets."""
    kernel = _kernel()
    rng = np.random.default_rng(7)
    calls = []

    def profiles(*args):
        calls.append(copy.deepcopy(args))
        return kernel.profiles(*args)

    planner = None
    for _, map_spec, frames in recorded:
        planner = load_planner(LATTICE, map_spec, {})
        planner.kernel = _proxy(profiles=profiles)  # keeping the arguments of each call
        for frame in frames[::4]:
            _outcome(planner, frame)
    assert len(calls) > 200 and any(c[3] for c in calls)  # some with reach rows
    compared = 0
    for args in calls:
        sva, cruise, reach, ti, ds, rv, s0, v0, a0, v_des, decel, tk = args
        variants = [(ds, rv, s0, v0, a0, v_des)]
        for _ in range(2):  # odd values in the start state and the targets
            odd = [float(x) for x in rng.choice(ODD, size=4)]
            ds2 = [float(rng.choice(ODD)) if rng.random() < 0.3 else x for x in ds]
            variants.append((ds2, list(rv), *odd))
        for ds_, rv_, s0_, v0_, a0_, vd_ in variants:
            got, want = np.full(sva.shape, 7.0), np.full(sva.shape, 7.0)
            assert kernel.profiles(got, cruise, reach, ti, ds_, rv_, s0_, v0_, a0_, vd_, decel, tk)
            planner._profiles_numpy(want, ti, ds_, rv_, s0_, v0_, a0_, vd_)
            assert _bits(got) == _bits(want), (ds_, rv_, s0_, v0_, a0_, vd_)
            compared += 1
    assert compared > 600


def test_profiles_take_only_plain_ints_and_floats() -> None:
    kernel = _kernel()
    planner = load_planner(LATTICE, load_scenario(list_scenarios()[0]).map.model_dump(), {})
    K, C, T = planner.K, planner._n_cruise, len(planner._reach_T)

    def run(ti, ds, rv) -> bool:
        sva = np.zeros((3, C + len(ti) + 1, K))
        return kernel.profiles(sva, planner._cruise_stack, planner._reach_basis, ti, ds, rv, 1.0, 2.0, 0.5,
                               10.0, 6.0, planner.tk)

    assert run([0, T - 1], [5.0, 6.0], [0.0, 1.0]) and run([], [], [])
    for ti, ds, rv in (([T], [5.0], [0.0]), ([-1], [5.0], [0.0]), ([True], [5.0], [0.0]),
                       ([np.int64(2)], [5.0], [0.0]), ([2], [5], [0.0]), ([2], [5.0], [np.float64(0.0)]),
                       ((2,), [5.0], [0.0]), ([2], [5.0, 6.0], [0.0]), ([2, 2**70], [5.0, 6.0], [0.0, 0.0])):
        assert not run(ti, ds, rv), (ti, ds, rv)  # the numpy lines decide (index error, conversion)
    with pytest.raises(ValueError, match="cruise: dimension 3"):
        kernel.profiles(np.zeros((3, C + 1, K)), np.zeros((3, 3, C, K + 1)), planner._reach_basis, [], [], [],
                        0.0, 0.0, 0.0, 0.0, 1.0, planner.tk)
    with pytest.raises(ValueError, match="fewer rows"):
        kernel.profiles(np.zeros((3, C, K)), planner._cruise_stack, planner._reach_basis, [], [], [],
                        0.0, 0.0, 0.0, 0.0, 1.0, planner.tk)


def test_near_matches_numpy() -> None:
    kernel = _kernel()
    rng = np.random.default_rng(2)
    for _ in range(300):
        n, K = int(rng.integers(0, 6)), int(rng.integers(1, 40))
        oxy = rng.normal(size=(2, n, K)) * 60.0
        mask = rng.random(oxy.shape) < 0.02
        oxy[mask] = rng.choice(ODD, size=int(mask.sum()))
        ex, ey, reach2 = float(rng.normal() * 20), float(rng.normal() * 20), float(rng.uniform(0, 5000))
        gx, gy = oxy[0] - ex, oxy[1] - ey
        want = ((gx * gx + gy * gy).min(axis=1) < reach2).tolist() if n else []
        assert kernel.near(oxy, ex, ey, reach2) == want
    with pytest.raises(ValueError, match="oxy: dimension 0 is 3, expected 2"):
        kernel.near(np.zeros((3, 1, 4)), 0.0, 0.0, 1.0)


# -- a compiled kernel never overrides an edited source ---------------------------------------------
KERNELS = [("deft_gym.planner._lattice_c", "deft_gym/planner/_lattice_c.c", "deft_gym/planner/lattice.py"),
           ("deft_gym.modules._control_c", "deft_gym/modules/_control_c.c", "deft_gym/modules/control.py"),
           ("deft_gym.record._snapshot_c", "deft_gym/record/_snapshot_c.c", "deft_gym/record/worker.py"),
           ("deft_gym.record._tap_c", "deft_gym/record/_tap_c.c", "deft_gym/record/recorder.py"),
           ("deft_gym.record._format_c", "deft_gym/record/_format_c.c", "deft_gym/record/textformat.py"),
           ("deft_gym.record._scene_c", "deft_gym/record/_scene_c.c", "deft_gym/record/scene.py"),
           ("deft_gym.bus._ros1_c", "deft_gym/bus/_ros1_c.c", "deft_gym/bus/ros1.py")]
ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("name, c_source, mirrors", KERNELS)
def test_a_kernel_built_before_an_edit_of_its_sources_is_not_used(name, c_source, mirrors, tmp_path) -> None:
    """Each kernel records the digests of its C source and of the Python file it stands in for
    (setup.py): the build here matches the files beside it; a copy of either file with one edit
    makes it stale (an edit of lattice.py used to have no effect while the old kernel ran), and
    checked_kernel then gives None (the Python version) with a warning saying to rebuild."""
    import importlib

    from deft_gym.files import checked_kernel, stale_kernel

    kernel = importlib.import_module(name)
    assert stale_kernel(kernel, ROOT / c_source, ROOT / mirrors) is None  # this build is current
    for edited in (c_source, mirrors):
        copies = {p: tmp_path / Path(p).name for p in (c_source, mirrors)}
        for p, q in copies.items():
            q.write_bytes((ROOT / p).read_bytes() + (b"\n# an edit\n" if p == edited else b""))
        why = stale_kernel(kernel, copies[c_source], copies[mirrors])
        assert why is not None and Path(edited).name in why
        with pytest.warns(RuntimeWarning, match="using the Python version"):
            assert checked_kernel(kernel, copies[c_source], copies[mirrors]) is None
    old = SimpleNamespace(__name__=name)  # a build from before the digests were recorded
    assert "records no digests" in stale_kernel(old, ROOT / c_source, ROOT / mirrors)


def test_the_planner_fingerprint_covers_every_source_the_planner_runs(tmp_path) -> None:
    """The fingerprint a log records of its planner (source_sha256) is the digest of the class's
    file, the modules of its package and of deft_gym it imports (decision.py for the lattice
    planner) and the C sources of its kernels: it used to cover lattice.py only, so an edit of
    decision.py went unseen by the generated tests."""
    from deft_gym.planner.base import _digest_of, planner_sources, source_digest
    from deft_gym.planner.lattice import LatticePlanner
    from tests.support.fault_planners import FaultyPlanner

    names = {p.name for p in planner_sources(LatticePlanner)}
    assert {"lattice.py", "decision.py", "base.py", "_lattice_c.c", "geometry.py", "roadmap.py"} <= names
    assert not any("site-packages" in str(p) for p in planner_sources(LatticePlanner))
    assert {"fault_planners.py", "lattice.py", "decision.py"} <= {p.name for p in planner_sources(FaultyPlanner)}
    files = planner_sources(LatticePlanner)
    copies = []
    for p in files:
        q = tmp_path / p.name
        q.write_bytes(p.read_bytes())
        copies.append(q)
    key = lambda fs: tuple((str(f), 0, 0) for f in fs)  # noqa: E731
    assert _digest_of(key(copies)) == source_digest(LatticePlanner)
    decision = next(q for q in copies if q.name == "decision.py")
    decision.write_bytes(decision.read_bytes() + b"\n# an edit\n")
    _digest_of.cache_clear()
    assert _digest_of(key(copies)) != source_digest(LatticePlanner)
