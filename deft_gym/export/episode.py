"""What an export needs of an episode, from its log, its episode folder or a scenario YAML.

A log holds the scenario it ran (as simulated), the jitter seed, the ADS configuration, the
outcome and, at :data:`~deft_gym.record.scene.SCENE_HZ` Hz, the ground truth of the ego and of
every participant (the scene topic: positions to the millimetre). An export wants every world
step, so :func:`from_log` simulates the episode again - the same scenario (with the participants
an adversary added mid-run at their times, from the folder's ``episode.json``), the same ADS
configuration and jitter seed: the simulation is deterministic - records every actor at every
world step, and keeps that only when it agrees with the log: the same outcome (and collision),
every scene sample within :data:`POSITION_TOL` and :data:`HEADING_TOL`. Otherwise (a log made by
other simulation code) the log's own samples are the trajectories, and the export says so.

:func:`from_scenario` simulates a scenario YAML once (a jitter seed) and exports that episode.
Positions here are in the world frame (highway-env's); the writers mirror them
(:mod:`.network`).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

POSITION_TOL = 0.01  #: [m] a re-simulated trajectory must match the log's samples this closely
HEADING_TOL = 0.01  #: [rad]
TIME_TOL = 1e-6  #: [s] two sample times are the same world step


@dataclass
class Actor:
    """The ego or a participant: its kind (``ego``, ``static``, ``scripted``, ``reactive``), what
    perception calls it (``EGO``, ``CONE``, ``STATIC_VEHICLE``, ``VEHICLE``), its size [m] and
    ``rows`` ``(t [s], x, y [m], heading [rad], speed [m/s])`` while it is in the world."""

    id: str
    kind: str
    obstacle: str
    length: float
    width: float
    rows: np.ndarray
    added: float | None = None  #: sim time [s] it was added mid-run (None: in the scenario from the start)

    @property
    def appear(self) -> float:
        return float(self.rows[0, 0]) if len(self.rows) else 0.0

    @property
    def moves(self) -> bool:
        r = self.rows
        return bool(len(r) > 1 and (np.ptp(r[:, 1]) > 1e-9 or np.ptp(r[:, 2]) > 1e-9))


@dataclass
class ExportEpisode:
    """One episode, ready to be written (see the module docstring)."""

    name: str
    scenario: dict[str, Any]  #: the scenario as simulated (plain data), participants added mid-run not in it
    dt: float  #: world step [s]
    ego: Actor
    participants: list[Actor]  #: in the world's order (perception ids 1, 2, ...)
    outcome: str
    sim_time: float
    collision: dict[str, Any] | None
    failure: str | None  #: collision, nods, a task failure (timeout, stuck), crash, ... or None
    jitter_seed: int | None
    verdict: dict[str, Any] | None = None  #: an adversary's or a search's episode.json
    source: dict[str, Any] = field(default_factory=dict)  #: log, scenario file, where the trajectories came from

    @property
    def map(self) -> dict[str, Any]:
        return self.scenario["map"]

    @property
    def roadmap(self) -> Any:
        from deft_gym.world.roadmap import shared_roadmap

        return shared_roadmap(self.map)

    @property
    def lights(self) -> dict[str, Any] | None:
        """The light plan (the scenario's, or the default one on a map with lights)."""
        from deft_gym.world.traffic_lights import LightPlan

        if not self.roadmap.stop_lines:
            return None
        return LightPlan.model_validate(self.scenario.get("lights") or {}).model_dump()

    def actor(self, pid: str) -> Actor:
        return self.ego if pid == "ego" else next(p for p in self.participants if p.id == pid)

    def summary(self) -> str:
        """One line: scenario, failure, collision, seed."""
        what = self.failure or self.outcome
        if self.collision:
            what = f"collision with {self.collision.get('participant')} at {float(self.collision['time']):.2f} s"
        elif self.failure and self.failure != self.outcome:
            what = f"{self.failure} ({self.outcome} at {self.sim_time:.2f} s)"
        seed = f", jitter seed {self.jitter_seed}" if self.jitter_seed is not None else ""
        return f"{self.name}: {what}{seed}"

    def meta(self) -> dict[str, Any]:
        """What the exported files carry about the episode beyond the standard's elements (the
        way back needs it: :mod:`.roundtrip`), as plain data."""
        sc = self.scenario
        ego = dict(sc["ego"])
        specs = {p["id"]: p for p in sc.get("participants", [])}
        out: dict[str, Any] = {
            "format": "deft_gym.export/1", "scenario_name": self.name, "scenario_seed": int(sc.get("seed", 0)),
            "duration": float(sc.get("duration", 40.0)), "stuck_time": float(sc.get("stuck_time", 30.0)),
            "map": self.map, "lights": sc.get("lights"), "ego": ego, "dt": self.dt,
            "ego_size": {"length": self.ego.length, "width": self.ego.width},
            "jitter_seed": self.jitter_seed, "outcome": self.outcome, "sim_time": self.sim_time,
            "collision": self.collision, "failure": self.failure,
            "participants": [{"id": p.id, "kind": p.kind, "obstacle": p.obstacle, "added": p.added, "appear": p.appear,
                              **({"spec": specs[p.id]} if p.kind == "reactive" and p.id in specs else {})}
                             for p in self.participants],
            "trajectories": self.source.get("trajectories"),
        }
        if self.verdict:
            out["verdict"] = {k: self.verdict[k] for k in ("failure", "task_failure", "signature", "mechanism",
                                                          "trigger", "band", "clearance", "iou", "method")
                              if k in self.verdict}
        for k in ("log", "scenario_file"):
            if self.source.get(k):
                out[k] = str(self.source[k])
        return out


# -- simulation ----------------------------------------------------------------------------------------
class _Tracks:
    """Every actor's state at every world step of a simulation (and at t = 0)."""

    def __init__(self, sim: Any) -> None:
        self.sim = sim
        self.rows: dict[str, list[tuple[float, float, float, float, float]]] = {"ego": []}
        self.info: dict[str, tuple[str, str, float, float]] = {}
        self.added: dict[str, float] = {}
        world = sim.world
        step = world.step

        def first_step(*args: Any, **kwargs: Any) -> None:
            if world.ticks == 0:
                self.grab(world)  # t = 0, with what was added at t = 0
            step(*args, **kwargs)

        world.step = first_step  # an instance attribute that reads the world, nothing else
        sim.on_step.append(lambda s: self.grab(s.world))

    def grab(self, world: Any) -> None:
        t = world.time
        e = world.ego
        self.rows["ego"].append((t, float(e.position[0]), float(e.position[1]), float(e.heading), float(e.speed)))
        for p in world.participants:
            if p.present(t):
                self.grab_one(p, t)

    def grab_one(self, p: Any, t: float) -> None:
        o = p.obj
        if p.id not in self.info:
            self.info[p.id] = (p.kind, p.obstacle_type, float(o.LENGTH), float(o.WIDTH))
            self.rows[p.id] = []
        rows = self.rows[p.id]
        if rows and abs(rows[-1][0] - t) < 1e-12:
            return
        rows.append((t, float(o.position[0]), float(o.position[1]), float(o.heading), float(o.speed)))

    def actors(self, world: Any) -> tuple[Actor, list[Actor]]:
        e = world.ego
        ego = Actor("ego", "ego", "EGO", float(e.LENGTH), float(e.WIDTH), np.array(self.rows["ego"], float))
        parts = []
        for p in world.participants:
            if p.id not in self.info:
                continue  # added but never present (a vehicle due after the end)
            kind, obstacle, length, width = self.info[p.id]
            parts.append(Actor(p.id, kind, obstacle, length, width, np.array(self.rows[p.id], float),
                               self.added.get(p.id)))
        return ego, parts


def simulate(scenario: dict[str, Any], ads: Any, jitter_seed: int | None,
             added: list[tuple[float, dict[str, Any]]] | None = None,
             source: str = "<export>") -> tuple[Any, Actor, list[Actor], float]:
    """Run ``scenario`` (plain data) with ``ads`` and ``jitter_seed``, adding each ``(time,
    spec)`` of ``added`` at its time as the adversary env did
    (:func:`deft_gym.search.episode.run_scenario`); ``(outcome, ego, participants, dt)``."""
    from deft_gym.scenarios.scenario import scenario_from_dict
    from deft_gym.sim.simulation import Simulation

    sc = scenario_from_dict(scenario, source=source)
    sim = Simulation(sc, ads, jitter_seed=jitter_seed, keep_planning=False)
    tracks = _Tracks(sim)
    try:
        sim.start()
        for t, spec in added or []:
            if t > 0.0 and sim.advance(t):
                break
            part = sim.add_participant(spec)
            tracks.added[spec["id"]] = sim.world.time
            if part.kind == "static":  # in the world from now on (world time: the last step's)
                tracks.grab_one(part, sim.world.time)
        sim.advance(sc.duration)
    finally:
        res = sim.finish()
    ego, parts = tracks.actors(sim.world)
    return res.outcome, ego, parts, 1.0 / sim.ads.world_hz


# -- logs ----------------------------------------------------------------------------------------------
def read_log(log: Path | str) -> tuple[dict[str, Any], dict[str, Any], dict[str, Any]]:
    """``(episode metadata, outcome record, scene tracks)`` of a log; the scene tracks are
    ``{id: (kind, length, width, rows)}`` with ``ego`` among them (ground truth, world frame)."""
    from mcap.reader import make_reader

    from deft_gym.bus.codec import decode
    from deft_gym.bus.messages import NS_PER_S, SCENE_TOPIC, log_start_ns
    from deft_gym.record import read_metadata
    from deft_gym.viz.episode import EPISODE_META, OUTCOME_META, _scene

    log = Path(log)
    try:
        meta = read_metadata(log)
    except Exception as exc:
        raise ValueError(f"{log}: cannot read the log: {type(exc).__name__}: {exc}") from None
    ep = {k: _json(v) for k, v in meta.get(EPISODE_META, {}).items()}
    oc = {k: _json(v) for k, v in meta.get(OUTCOME_META, {}).items()}
    if not oc:
        raise ValueError(f"{log}: no outcome record (the episode did not finish writing its log)")
    start = log_start_ns(ep)
    ego_rows: list[Any] = []
    parts: dict[str, Any] = {}
    with open(log, "rb") as f:
        for _, _, msg in make_reader(f).iter_messages(topics=[SCENE_TOPIC]):
            try:
                p = decode(msg.data)
            except ValueError:
                continue
            _scene(p, (msg.log_time - start) / NS_PER_S, ego_rows, parts)
    size = ep.get("ego") or {}
    scene = {"ego": ("ego", float(size.get("length", 4.8)), float(size.get("width", 2.0)), np.array(ego_rows, float))}
    for pid, tr in parts.items():
        scene[pid] = (tr.kind, tr.length, tr.width, tr.array())
    return ep, oc, scene


def _no_nulls(d: Any) -> Any:
    """A dumped configuration without its None values (the defaults they stand for)."""
    if isinstance(d, dict):
        return {k: _no_nulls(v) for k, v in d.items() if v is not None}
    return d


def _json(v: str) -> Any:
    try:
        return json.loads(v)
    except ValueError:
        return v


def failure_of(outcome: str, collision: dict[str, Any] | None, verdict: dict[str, Any] | None) -> str | None:
    """What failed: the verdict's failure (collision, nods) or task failure, else a collision or
    a crash, hang or missing plan; None for a passing episode."""
    if verdict:
        if verdict.get("failure"):
            return str(verdict["failure"])
        if verdict.get("task_failure"):
            return str(verdict["task_failure"])
    if collision:
        return "collision"
    if outcome in ("crash", "hang", "no_plan"):
        return outcome
    return None


def _replay_plan(ep: dict[str, Any], oc: dict[str, Any], verdict: dict[str, Any] | None
                 ) -> tuple[dict[str, Any], list[tuple[float, dict[str, Any]]]]:
    """The scenario to simulate and the participants to add mid-run: an adversary episode's
    equivalent scenario (``episode.json``), else the log's scenario plus the participants its
    outcome record says were added."""
    eq = (verdict or {}).get("scenario_equivalent")
    if isinstance(eq, str):
        import ast

        try:
            eq = ast.literal_eval(eq)
        except (ValueError, SyntaxError):
            eq = None
    from deft_gym.search.episode import read_replay

    rep = read_replay(eq, 0)  # the one shape of a failure's scenario (or a search's record from before it)
    if rep is not None:
        data, added_at = dict(rep["scenario"]), rep["added_at"]
        later = [p for p in data.get("participants", []) if p["id"] in added_at]
        data["participants"] = [p for p in data.get("participants", []) if p["id"] not in added_at]
        return data, [(float(added_at[p["id"]]), p) for p in later]
    data = ep.get("scenario")
    if not isinstance(data, dict):
        raise ValueError("the log's metadata holds no scenario")
    added = []
    for a in oc.get("participants_added") or []:
        spec = {k: v for k, v in a.items() if k != "time"}
        added.append((float(a.get("time", 0.0)), spec))
    return data, added


def _compare(ego: Actor, parts: list[Actor], scene: dict[str, Any]) -> dict[str, Any]:
    """The largest position and heading differences between simulated tracks and the log's scene
    samples, over every sample (each sample time must be a simulated step)."""
    mine = {"ego": ego.rows, **{p.id: p.rows for p in parts}}
    worst_p = worst_h = 0.0
    n = 0
    missing = []
    for pid, (_, _, _, rows) in scene.items():
        a = mine.get(pid)
        if a is None or not len(a):
            missing.append(pid)
            continue
        for t, x, y, h, _v in rows:
            i = int(np.searchsorted(a[:, 0], t - TIME_TOL))
            if i >= len(a) or abs(a[i, 0] - t) > TIME_TOL:
                missing.append(f"{pid}@{t:.3f}")
                continue
            worst_p = max(worst_p, math.hypot(a[i, 1] - x, a[i, 2] - y))
            worst_h = max(worst_h, abs(math.atan2(math.sin(a[i, 3] - h), math.cos(a[i, 3] - h))))
            n += 1
    return {"samples": n, "max_position_error": worst_p, "max_heading_error": worst_h, "missing": missing[:5],
            "missing_count": len(missing)}


def same_outcome(a: dict[str, Any], b: dict[str, Any]) -> bool:
    """Two outcome records agree: the outcome, and the collision's participant and time."""
    if a.get("outcome") != b.get("outcome"):
        return False
    ca, cb = a.get("collision"), b.get("collision")
    if bool(ca) != bool(cb):
        return False
    if ca and cb:
        return ca.get("participant") == cb.get("participant") and abs(float(ca["time"]) - float(cb["time"])) < TIME_TOL
    return True


def log_ads(ep: dict[str, Any]) -> Any:
    """The ADS config a log was recorded with (its episode metadata's ``ads_config``), or None
    (the default ADS) for a log without one."""
    from deft_gym.bus.ads import AdsConfig

    return AdsConfig.model_validate(_no_nulls(ep["ads_config"])) if isinstance(ep.get("ads_config"), dict) else None


def from_log(log: Path | str, resimulate: bool = True) -> ExportEpisode:
    """The episode of ``log`` (an ``episode.mcap``; its folder's ``episode.json`` when there is
    one). See the module docstring."""
    log = Path(log)
    ep, oc, scene = read_log(log)
    verdict = None
    vpath = log.with_name("episode.json")
    if vpath.exists():
        try:
            verdict = json.loads(vpath.read_text())
        except ValueError:
            verdict = None
    data, added = _replay_plan(ep, oc, verdict)
    jitter_seed = ep.get("jitter_seed") if isinstance(ep.get("jitter_seed"), int) else None
    collision = oc.get("collision") if isinstance(oc.get("collision"), dict) else None
    outcome, sim_time = str(oc.get("outcome", "unknown")), float(oc.get("sim_time", 0.0))
    source: dict[str, Any] = {"log": str(log), "scenario_file": ep.get("scenario_source") or None}
    result = None
    if resimulate:
        try:
            o, ego, parts, dt = simulate(data, log_ads(ep), jitter_seed, added, source=f"{log} (scenario)")
            check = _compare(ego, parts, {k: v for k, v in scene.items()})
            agree = same_outcome(o.as_dict(), oc)
            check["outcome_agrees"] = agree
            ok = agree and check["missing_count"] == 0 and check["max_position_error"] <= POSITION_TOL \
                and check["max_heading_error"] <= HEADING_TOL
            source["check"] = check
            if ok:
                result = (ego, parts, dt)
                source["trajectories"] = (f"simulated again at every world step ({1 / dt:g} Hz) with the log's "
                                          f"scenario, ADS config and jitter seed; matches the log's "
                                          f"{check['samples']} ground-truth samples within "
                                          f"{check['max_position_error'] * 1000:.2f} mm and "
                                          f"{check['max_heading_error']:.2g} rad, and its outcome")
        except Exception as exc:  # another simulation version, a scenario that no longer loads
            source["check"] = {"error": f"{type(exc).__name__}: {exc}"[:300]}
    if result is None:
        hz = float((ep.get("ads_config") or {}).get("world_hz") or 20.0)
        result = _from_scene(scene, data, added, 1.0 / hz)
        source["trajectories"] = (f"the log's ground-truth samples (scene topic), linear between them at every "
                                  f"world step ({hz:g} Hz)")
    ego, parts, dt = result
    name = str(ep.get("scenario_name") or data.get("name") or log.parent.name)
    data = dict(data)
    data["participants"] = list(data.get("participants", []))
    return ExportEpisode(name, data, dt, ego, parts, outcome, sim_time, collision,
                         failure_of(outcome, collision, verdict), jitter_seed, verdict, source)


def _from_scene(scene: dict[str, Any], data: dict[str, Any], added: list[tuple[float, dict[str, Any]]],
                dt: float) -> tuple[Actor, list[Actor], float]:
    """Tracks from the log's scene samples (obstacle types from the scenario, by id), resampled
    linearly to every world step ``dt`` between an actor's first and last sample (the samples
    fall on world steps, so they are kept exactly)."""
    specs = {p["id"]: p for p in data.get("participants", [])} | {s["id"]: s for _, s in added}
    when = {s["id"]: t for t, s in added}

    def resample(rows: np.ndarray) -> np.ndarray:
        if len(rows) < 2:
            return rows
        k0, k1 = round(rows[0, 0] / dt), round(rows[-1, 0] / dt)
        t = np.arange(k0, k1 + 1) * dt
        h = np.interp(t, rows[:, 0], np.unwrap(rows[:, 3]))
        return np.column_stack([t, *(np.interp(t, rows[:, 0], rows[:, c]) for c in (1, 2)), h,
                                np.interp(t, rows[:, 0], rows[:, 4])])

    kind, length, width, rows = scene["ego"]
    ego = Actor("ego", "ego", "EGO", length, width, resample(rows))
    parts = []
    for pid, (kind, length, width, rows) in scene.items():
        if pid == "ego":
            continue
        spec = specs.get(pid, {})
        obstacle = spec.get("obstacle", "CONE" if length < 1.0 else "STATIC_VEHICLE") if kind == "static" else "VEHICLE"
        parts.append(Actor(pid, kind, obstacle, length, width, resample(rows), when.get(pid)))
    order = [p["id"] for p in data.get("participants", [])] + [s["id"] for _, s in added]
    parts.sort(key=lambda p: order.index(p.id) if p.id in order else len(order))
    return ego, parts, dt


def from_scenario(scenario: Path | str, jitter_seed: int = 0, ads: Any = None) -> ExportEpisode:
    """Simulate a scenario (YAML path, name or ``gen:<seed>``) once and return that episode."""
    from deft_gym.scenarios.scenario import scenario_to_dict
    from deft_gym.search.context import resolve_scenario

    sc = resolve_scenario(str(scenario))
    data = scenario_to_dict(sc)
    outcome, ego, parts, dt = simulate(data, ads, jitter_seed, source=str(scenario))
    o = outcome.as_dict()
    src = {"scenario_file": sc.source or str(scenario),
           "trajectories": f"simulated at every world step ({1 / dt:g} Hz), jitter seed {jitter_seed}"}
    return ExportEpisode(sc.name, data, dt, ego, parts, o["outcome"], float(o["sim_time"]), o["collision"],
                         failure_of(o["outcome"], o["collision"], None), jitter_seed, None, src)
