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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from deft_gym.bus.ads import AdsConfig, load_ads_config
from deft_gym.config import cache_dir
from deft_gym.files import write_atomic
from deft_gym.scenarios.scenario import Scenario, scenario_to_dict

CACHE_DIR = cache_dir() / "reference"
TRACE_FORMAT = 2  # bump when the recorded content changes (invalidates the cache)


@dataclass
class Actor:
    """Static description of one participant of a trace."""

    id: str
    kind: str  # static | scripted | reactive
    obstacle_type: str
    length: float
    width: float
    added: bool = False  # added by an adversary / mutation (not in the seed scenario)


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

    def _actor(self, p: Any) -> int:
        key = id(p)
        i = self._index.get(key)
        if i is None:
            o = p.obj
            i = self._index[key] = len(self.actors)
            self.actors.append(Actor(p.id, p.kind, str(p.obstacle_type), float(o.LENGTH), float(o.WIDTH),
                                     p.id in self.added))
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
                     list(self.actors), parts, outcome, sim_time, {**(meta or {}), "decisions": dict(self.decisions)})


# ---------------------------------------------------------------------------------------------
# not part of what a run computes: this package's own modules, tools and the log writer
_NOT_SIMULATION_PACKAGES = ("envs", "search", "robustness", "cli", "viz", "execution", "experiments",
                            "metrics", "export")  # the last two: planned (issues 33, 37)
_NOT_SIMULATION_FILES = ("__init__.py", "record/recorder.py", "scenarios/variants.py")
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
    out = h.hexdigest()[:16]
    if root is None:
        _FINGERPRINT.append(out)
    return out


def content_key(sc: Scenario, ads: AdsConfig, jitter_seed: int) -> str:
    """Hash of everything a reference run depends on (scenario, ADS config, seed, code)."""
    blob = json.dumps({"scenario": scenario_to_dict(sc), "ads": ads.model_dump(mode="json", by_alias=True),
                       "jitter_seed": jitter_seed, "format": TRACE_FORMAT, "code": code_fingerprint()},
                      sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def record_run(sc: Scenario, ads: AdsConfig | None = None, jitter_seed: int = 0) -> Trace:
    """Run ``sc`` once and return its trace."""
    from deft_gym.sim.simulation import Simulation

    sim = Simulation(sc, ads, jitter_seed=jitter_seed, keep_planning=False)
    rec = TraceRecorder(sim)
    res = sim.run()
    return rec.trace(res.outcome.outcome, res.sim_time, {"scenario": sc.name, "jitter_seed": jitter_seed})


_MEMO: dict[str, Trace] = {}


def reference_run(sc: Scenario, ads: AdsConfig | None = None, jitter_seed: int = 0,
                  cache_dir: Path | str | None = CACHE_DIR) -> Trace:
    """The reference run of a seed scenario (memoised per process, cached on disk).

    Raises ``ValueError`` if the reference does not complete its task: a seed scenario must be
    an optimal-decision scenario, so its run has to reach the destination without collision."""
    ads = ads or load_ads_config()
    key = f"{sc.name}-{content_key(sc, ads, jitter_seed)}"
    tr = _MEMO.get(key)
    if tr is not None:
        return tr
    path = Path(cache_dir) / key if cache_dir else None
    if path is not None and path.with_suffix(".json").exists() and path.with_suffix(".npz").exists():
        try:
            tr = Trace.load(path)
        except (OSError, ValueError, KeyError):
            tr = None
    if tr is None:
        tr = record_run(sc, ads, jitter_seed)
        if tr.outcome != "completed":
            raise ValueError(f"scenario {sc.name!r}: the reference run ended '{tr.outcome}' at "
                             f"{tr.sim_time:.1f} s; a seed scenario must complete its task")
        if path is not None:
            tr.save(path)
    _MEMO[key] = tr
    return tr
