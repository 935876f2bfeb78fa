"""Ground-truth traces of episodes, and the cached reference run of a seed scenario.

:class:`TraceRecorder` hooks into a :class:`~deft_gym.sim.simulation.Simulation` (``on_step``) and
keeps, for every world step, the ego state and the pose of every present participant. A
:class:`Trace` is what the oracles (:mod:`deft_gym.search.nods`) and the feasible areas
(:mod:`deft_gym.search.feasible`) read.

:func:`reference_run` runs a seed scenario once with a fixed jitter seed - the ego's optimal
path tau(s*) and its observation O(s*) in Decictor's terms - and caches it on disk under
``runs/cache/reference``, keyed by the scenario content, the ADS configuration and the seed.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from deft_gym.bus.ads import AdsConfig, PlannerSpec, load_ads_config
from deft_gym.config import cache_dir
from deft_gym.files import write_atomic
from deft_gym.planner.base import planner_fingerprint
from deft_gym.scenarios.scenario import Scenario, scenario_to_dict

CACHE_DIR = cache_dir() / "reference"
TRACE_FORMAT = 3  # bump when the recorded content changes (invalidates the cache)


@dataclass
class Actor:
    """Static description of one participant of a trace."""

    id: str
    kind: str  # static | scripted | reactive
    obstacle_type: str
    length: float
    width: float
    added: bool = False  # added by an adversary / mutation (not in the seed scenario)
    num: int = -1  # the perception id the ADS knows it by (-1: unknown)


@dataclass
class Trace:
    """What happened in one episode, per world step (``ticks`` are world step numbers; time is
    ``tick * world_dt``).

    ``ego`` columns: x, y, heading [rad], speed [m/s], acceleration [m/s^2].
    ``parts`` rows: tick, actor index, x, y, heading - one row per present participant and step.
    """

    world_dt: float
    ticks: np.ndarray
    ego: np.ndarray
    actors: list[Actor]
    parts: np.ndarray
    outcome: str = ""
    sim_time: float = 0.0
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def t(self) -> np.ndarray:
        return self.ticks * self.world_dt

    @property
    def xy(self) -> np.ndarray:
        return self.ego[:, :2]

    def actor_index(self, pid: str) -> int:
        return next(i for i, a in enumerate(self.actors) if a.id == pid)

    def track(self, index: int) -> np.ndarray:
        """Rows ``(tick, x, y, heading)`` of one actor."""
        rows = self.parts[self.parts[:, 1] == index]
        return rows[:, [0, 2, 3, 4]]

    # -- persistence ------------------------------------------------------------------------
    def save(self, path: Path) -> Path:
        """Write ``<path>.npz`` + ``<path>.json`` atomically."""
        path = Path(path)
        buf = io.BytesIO()
        np.savez(buf, ticks=self.ticks, ego=self.ego, parts=self.parts)
        write_atomic(path.with_suffix(".npz"), buf.getvalue())
        meta = {"world_dt": self.world_dt, "outcome": self.outcome, "sim_time": self.sim_time,
                "actors": [a.__dict__ for a in self.actors], "meta": self.meta}
        write_atomic(path.with_suffix(".json"), json.dumps(meta))
        return path

    @classmethod
    def load(cls, path: Path) -> Trace:
        path = Path(path)
        meta = json.loads(path.with_suffix(".json").read_text())
        arr = np.load(path.with_suffix(".npz"))
        return cls(meta["world_dt"], arr["ticks"], arr["ego"], [Actor(**a) for a in meta["actors"]],
                   arr["parts"], meta["outcome"], meta["sim_time"], meta.get("meta", {}))


class TraceRecorder:
    """Records a :class:`Trace` of a running simulation (attach before ``start``)."""

    def __init__(self, sim: Any, added: set[str] | None = None) -> None:
        self.sim = sim
        self.world_dt = 1.0 / sim.ads.world_hz
        self._ticks: list[int] = []
        self._ego: list[tuple[float, ...]] = []
        self._parts: list[tuple[float, ...]] = []
        self._index: dict[int, int] = {}  # id(Participant) -> actor index
        self.actors: list[Actor] = []
        self.added = added if added is not None else set()
        #: planning decisions seen (``reason:<r>``, ``blocked``, ``tight``, ``refused:<why>``) and
        #: when each was first seen [s]
        self.decisions: dict[str, float] = {}
        #: the decision each plan published, an entry per change (:func:`decision_entry`)
        self.timeline: list[dict[str, Any]] = []
        self._planning = sim.ads.topic("planning")
        sim.on_step.append(self._on_step)
        sim.bus.taps.append(self._on_message)
        self._on_step(sim, initial=True)

    def _on_message(self, msg: Any) -> None:
        if msg.topic != self._planning:
            return
        d = msg.payload.get("decision") or {}
        kinds = [f"reason:{d.get('reason') or d.get('behavior', '')}"]
        if d.get("blocked"):
            kinds.append("blocked")
        if d.get("tight"):
            kinds.append("tight")
        kinds += [f"refused:{why}" for why in (d.get("refused") or {}).values()]
        t = float(msg.payload["header"]["stamp"])
        for k in kinds:
            self.decisions.setdefault(k, t)
        entry = decision_entry(d)
        if not self.timeline or {k: v for k, v in self.timeline[-1].items() if k != "t"} != entry:
            self.timeline.append({"t": t, **entry})

    def _actor(self, p: Any) -> int:
        key = id(p)
        i = self._index.get(key)
        if i is None:
            o = p.obj
            i = self._index[key] = len(self.actors)
            self.actors.append(Actor(p.id, p.kind, str(p.obstacle_type), float(o.LENGTH), float(o.WIDTH),
                                     p.id in self.added, int(p.num)))
        return i

    def _on_step(self, sim: Any, initial: bool = False) -> None:
        w = sim.world
        tick = w.ticks
        e = w.ego
        self._ticks.append(tick)
        self._ego.append((float(e.position[0]), float(e.position[1]), float(e.heading), float(e.speed),
                          float(getattr(e, "accel", 0.0))))
        t = w.time
        app = self._parts.append
        for p in w.participants:
            if p.kind == "scripted" and t < p.obj.spawn_time:
                continue
            pos = p.obj.position
            app((tick, self._actor(p), float(pos[0]), float(pos[1]), float(p.obj.heading)))

    def ego_rows(self, start: int = 0) -> np.ndarray:
        """Ego rows (x, y, heading, speed, acceleration) recorded from index ``start`` on."""
        return np.array(self._ego[start:], dtype=float).reshape(-1, 5)

    def __len__(self) -> int:
        return len(self._ego)

    def trace(self, outcome: str = "", sim_time: float = 0.0, meta: dict[str, Any] | None = None) -> Trace:
        parts = np.array(self._parts, dtype=float).reshape(-1, 5)
        return Trace(self.world_dt, np.array(self._ticks, dtype=np.int64), np.array(self._ego, dtype=float),
                     list(self.actors), parts, outcome, sim_time,
                     {**(meta or {}), "decisions": dict(self.decisions), "timeline": list(self.timeline)})


def decision_entry(d: dict[str, Any]) -> dict[str, Any]:
    """What a trace keeps of a published planning decision: the ``reason``, the ego's ``lane``,
    the ``target`` lane, the ``home`` lane (ids as lists), the ``blocked`` and ``tight`` lanes,
    the ``refused`` lane changes (lane -> why) and their ``causes`` (perception ids; see
    :meth:`deft_gym.planner.decision.LaneDecider.published`). A planner that publishes none of
    these gives empty fields."""
    return {"reason": d.get("reason") or d.get("behavior", ""), "lane": list(d.get("lane") or []),
            "target": list(d.get("target_lane") or []), "home": list(d.get("home") or []),
            "blocked": list(d.get("blocked") or []), "tight": list(d.get("tight") or []),
            "refused": dict(d.get("refused") or {}), "causes": dict(d.get("causes") or {})}


# ---------------------------------------------------------------------------------------------
# not part of what a run computes: this package's own modules, tools and the log writer
_NOT_SIMULATION_PACKAGES = ("envs", "search", "robustness", "cli", "viz", "execution", "experiments",
                            "metrics", "export", "models")  # metrics: driving quality from traces; models: data
# planner/commonroad.py (and its commonroad_kinematics.py): a third-party planner's adapter that no run uses unless its ADS config
# names it; such a run's cache keys hash its source instead (content_key), so that adding or
# changing it leaves every other run's fingerprint and caches alone
_NOT_SIMULATION_FILES = ("__init__.py", "record/recorder.py", "scenarios/variants.py", "planner/commonroad.py",
                         "planner/commonroad_kinematics.py")
_FINGERPRINT: list[str] = []


def code_fingerprint(root: Path | None = None, read: Any = None) -> str:
    """Hash of the simulation's source (world, participants, modules, planner, scenario loading,
    and the variant generator ``perturb``): a changed planner makes cached reference runs and
    evaluation records stale. ``root``/``read`` let it hash another checkout (e.g. a git revision)."""
    if root is None and _FINGERPRINT:
        return _FINGERPRINT[0]
    pkg = root or Path(__file__).resolve().parent.parent
    read = read or (lambda f: f.read_bytes())
    h = hashlib.sha256()
    for f in sorted(pkg.rglob("*.py")):
        rel = f.relative_to(pkg).as_posix()
        if rel.split("/")[0] in _NOT_SIMULATION_PACKAGES or rel in _NOT_SIMULATION_FILES:
            continue
        h.update(rel.encode())
        h.update(read(f))
    import ast

    tree = ast.parse(read(pkg / "scenarios" / "variants.py"))  # only perturb() makes the held-out variants
    fn = next(n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "perturb")
    h.update(ast.unparse(fn).encode())
    import numpy

    h.update(f"numpy {numpy.__version__}".encode())  # numpy 1.x and 2.x round some results differently
    out = h.hexdigest()[:16]
    if root is None:
        _FINGERPRINT.append(out)
    return out


def content_key(sc: Scenario, ads: AdsConfig, jitter_seed: int) -> str:
    """Hash of everything a reference run depends on (scenario, ADS config, seed, code; and the
    source of the configured planner when it is not the default, whose code
    :func:`code_fingerprint` may not hash: a third-party adapter, a user's planner)."""
    data = {"scenario": scenario_to_dict(sc), "ads": ads.model_dump(mode="json", by_alias=True),
            "jitter_seed": jitter_seed, "format": TRACE_FORMAT, "code": code_fingerprint()}
    planner = planner_source(ads)
    if planner is not None:
        data["planner_source"] = planner
    blob = json.dumps(data, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def planner_source(ads: AdsConfig) -> str | None:
    """The SHA-256 of the source file of the ADS config's planner class, or None for the default
    planner (hashed with the simulation code) - so that the default's keys stay what they were."""
    cls = ads.planning.planner.cls
    if cls == PlannerSpec.model_fields["cls"].default:
        return None
    return _PLANNER_SOURCES.get(cls) or _PLANNER_SOURCES.setdefault(cls, planner_fingerprint(cls))


_PLANNER_SOURCES: dict[str, str] = {}


def record_run(sc: Scenario, ads: AdsConfig | None = None, jitter_seed: int = 0) -> Trace:
    """Run ``sc`` once and return its trace."""
    from deft_gym.sim.simulation import Simulation

    sim = Simulation(sc, ads, jitter_seed=jitter_seed, keep_planning=False)
    rec = TraceRecorder(sim)
    res = sim.run()
    return rec.trace(res.outcome.outcome, res.sim_time, {"scenario": sc.name, "jitter_seed": jitter_seed})


_MEMO: dict[str, Trace] = {}
REFERENCE_RUNS = 5  # jitter seeds the reference path is chosen from


def path_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Mean distance [m] of the points of path ``a`` to the polyline ``b`` (both (n, 2))."""
    import shapely

    return float(shapely.distance(shapely.points(a), shapely.LineString(b)).mean())


def medoid(paths: list[np.ndarray]) -> int:
    """Index of the most typical of ``paths``: the one with the smallest summed symmetric mean
    distance to the others (the first on a tie)."""
    n = len(paths)
    d = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1, n):
            d[i, j] = d[j, i] = 0.5 * (path_distance(paths[i], paths[j]) + path_distance(paths[j], paths[i]))
    return int(np.argmin(d.sum(axis=1)))


def _failed_reference(path: Path | None) -> str | None:
    """The cached error of a reference run none of whose runs completed, or None (none cached, or
    the file is damaged: the runs are simulated again)."""
    if path is None or not path.exists():
        return None
    try:
        return str(json.loads(path.read_text())["error"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def reference_run(sc: Scenario, ads: AdsConfig | None = None, jitter_seed: int = 0,
                  cache_dir: Path | str | None = CACHE_DIR, runs: int = REFERENCE_RUNS) -> Trace:
    """The reference run of a seed scenario (memoised per process, cached on disk): of its runs
    with jitter seeds ``jitter_seed`` .. ``jitter_seed + runs - 1`` that complete, the most
    typical path (:func:`medoid`), so that one jittered run with, say, a half lane change it
    gave up does not become the optimal path. ``meta`` names the seeds tried and the one chosen.

    Raises ``ValueError`` if no run completes its task: a seed scenario must be an
    optimal-decision scenario, so its run has to reach the destination without collision."""
    ads = ads or load_ads_config()
    key = f"{sc.name}-{content_key(sc, ads, jitter_seed)}-of{runs}"
    tr = _MEMO.get(key)
    if tr is not None:
        return tr
    path = Path(cache_dir) / key if cache_dir else None
    failed = Path(cache_dir) / f"{key}.failed.json" if cache_dir else None
    error = _failed_reference(failed)
    if error:  # no run completed last time: the verdict is cached too
        raise ValueError(error)
    if path is not None and path.with_suffix(".json").exists() and path.with_suffix(".npz").exists():
        try:
            tr = Trace.load(path)
        except (OSError, ValueError, KeyError):
            tr = None
    if tr is None:
        tries = [record_run(sc, ads, jitter_seed + i) for i in range(max(runs, 1))]
        done = [t for t in tries if t.outcome == "completed"]
        if not done:
            first = tries[0]
            error = (f"scenario {sc.name!r}: the reference run ended '{first.outcome}' at "
                     f"{first.sim_time:.1f} s; a seed scenario must complete its task")
            if failed is not None:
                from deft_gym.files import write_json_atomic

                write_json_atomic(failed, {"error": error, "runs": len(tries)})
            raise ValueError(error)
        tr = done[medoid([t.xy for t in done])]
        tr.meta["reference_of"] = [int(t.meta["jitter_seed"]) for t in done]
        tr.meta["not_completed"] = [int(t.meta["jitter_seed"]) for t in tries if t.outcome != "completed"]
        if path is not None:
            tr.save(path)
    _MEMO[key] = tr
    return tr


#: [s] how long a run must want its own lane back, still in it, for a lane change to count as
#: given up: one or two planning cycles (10 Hz) of another choice that the next cycles take back
#: are no decision
GIVE_UP_S = 0.5


def aborted_changes(trace: Trace, hold: float = GIVE_UP_S) -> list[dict[str, Any]]:
    """Lane changes the run began and gave up (from the planning decisions in ``trace.meta``):
    ``{"t": start [s], "lane", "target"}`` for each change towards a lane of the same road that
    ended with the ego still in its lane, wanting it again for ``hold`` [s] or more. Emergency
    stops (reason ``estop``: no plan, so no lane decision) are skipped: a change resumed after one
    was not given up. A planner that publishes no lanes gives none."""
    out: list[dict[str, Any]] = []
    change: dict[str, Any] | None = None
    back: float | None = None  # when the run began wanting its own lane back, mid-change
    for e in trace.meta.get("timeline") or []:
        lane, target = e["lane"], e["target"]
        if not lane or not target or e.get("reason") == "estop":
            continue
        if change is not None:
            if lane == change["target"] or lane[:2] != change["lane"][:2]:
                change, back = None, None  # reached, or the road ended (a junction): not given up here
            elif target == change["lane"] and lane == change["lane"]:
                back = e["t"] if back is None else back
                if e["t"] - back >= hold - 1e-9:
                    out.append(change)
                    change, back = None, None
                continue
            elif target == change["target"]:
                back = None  # taken back: the change goes on
                continue
        if change is None and target != lane and target[:2] == lane[:2]:
            change, back = {"t": e["t"], "lane": lane, "target": target}, None
    end = float(trace.t[-1]) if len(trace.t) else -math.inf
    if change is not None and back is not None and end - back >= hold - 1e-9:
        out.append(change)  # the run ended wanting its own lane back, for hold or more
    return out
