"""One system-level scenario test: world + ADS modules on the jittered bus, recorded and judged.

>>> from deft_gym.sim.simulation import run_episode
>>> result = run_episode("configs/scenarios/left_turn.yaml", jitter_seed=1, out_dir="runs/x")

:class:`Simulation` wires everything: the simulator node (steps the world at ``world_hz``,
applies the latest control command it received, publishes chassis), routing, localization,
perception, traffic-light perception, prediction, planning and control. Hooks let other tools
attach without touching the core: ``bus.taps``/``bus.interceptors``/``bus.supervisor`` (see
:mod:`deft_gym.bus.bus`) and ``on_step`` callbacks called after every world step.

The default supervisor (:class:`WatchedSupervisor`) turns a module that raises, or publishes a NaN
or an infinity on the planning or control topic (reason ``non-finite output``), into the outcome
``crash`` and a module call that runs past ``watchdog_s`` seconds of wall clock (default
:data:`DEFAULT_WATCHDOG_S`, or the ``DEFT_GYM_WATCHDOG_S`` environment variable; 0 switches it
off) into ``hang``: module, exception and sim time go into the log's outcome record and the
result's summary, and the episode ends there.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from deft_gym.bus.ads import AdsConfig, load_ads_config
from deft_gym.bus.bus import Bus, Node, header
from deft_gym.bus.jitter import JitterModel
from deft_gym.bus.messages import LOG_START_KEY, NS_PER_S, non_finite_field, to_ns
from deft_gym.config import ConfigError
from deft_gym.execution.watchdog import (
    DEFAULT_WATCHDOG_S,
    ModuleHang,
    Watchdog,
    describe_exception,
    interrupts,
    module_fault,
    watchdog_seconds,
)
from deft_gym.files import first_line, write_atomic
from deft_gym.modules.control import ControlNode
from deft_gym.modules.planning import PlanningNode
from deft_gym.modules.prediction import PredictionNode
from deft_gym.modules.routing import RoutingNode
from deft_gym.modules.sensors import LocalizationNode, PerceptionNode, TrafficLightNode
from deft_gym.planner.base import import_object, load_planner, planner_fingerprint
from deft_gym.record.recorder import McapRecorder, write_truth
from deft_gym.record.scene import SceneWriter, scene_hz, viewer_channels
from deft_gym.scenarios.scenario import (
    Scenario,
    build_world,
    destination_xy,
    load_scenario,
    scenario_to_dict,
)
from deft_gym.sim.oracles import EpisodeOracle, Outcome
from deft_gym.world.roadmap import shared_roadmap
from deft_gym.world.world import World

PACKAGE_VERSION = "0.1.0"


class WatchedSupervisor:
    """The simulation's default bus supervisor: a module call that raises - anything, a
    ``BaseException`` such as ``SystemExit`` or a ``KeyboardInterrupt`` the module raised itself
    included; only the user's Ctrl-C ends the program - ends the episode as a ``crash``, one that
    runs ``seconds`` of wall clock past its start as a ``hang``, and so does the call in progress
    once the episode's calls took ``run_wall_s`` in all (reason ``run wall-clock cap``; the
    wall-clock :class:`~deft_gym.execution.watchdog.Watchdog`, armed while the bus runs; main
    thread only). Per call it only notes the start time, so valid runs cost nothing measurable
    and behave exactly as before. A module that publishes a NaN or an infinity on one of
    ``finite_topics`` (the simulation's: planning and control, what drives the vehicle) ends it
    as a ``crash`` too, reason ``non-finite output``, once the message is out (so the log holds
    it); otherwise a NaN plan was tracked as full throttle and full lock, and the run timed out."""

    def __init__(self, bus: Bus, seconds: float, finite_topics: frozenset[str] = frozenset(),
                 run_wall_s: float | None = None) -> None:
        self.bus = bus
        self.dog = Watchdog(seconds, run_wall_s)
        self.failure: dict[str, Any] | None = None
        self.finite_topics = finite_topics

    def run(self, node: Node, fn: Callable[..., Any], *args: Any) -> Any:
        before = interrupts()
        try:
            out = self.dog.call(fn, *args)
        except ModuleHang:
            self._fail("hang", node, self.dog.message(), "run wall-clock cap" if self.dog.expired else None)
            return None
        except BaseException as exc:  # SystemExit, KeyboardInterrupt... a module raised: a crash
            if not module_fault(exc, before):
                raise  # the user's Ctrl-C ends the program (the log says interrupted)
            self._fail("crash", node, describe_exception(exc))
            return None
        if self.finite_topics and getattr(fn, "__name__", "") == "_publish":
            for topic, payload in args[0]:
                if topic in self.finite_topics and (path := non_finite_field(payload)) is not None:
                    self._fail("crash", node, f"NonFiniteOutput: {path} is not finite on {topic}",
                               "non-finite output")
                    break
        return out

    def _fail(self, kind: str, node: Node, what: str, reason: str | None = None) -> None:
        if self.failure is None:
            self.failure = {"kind": kind, "module": node.name, "exception": what, "time": self.bus.now,
                            **({"reason": reason} if reason else {})}
        node.alive = False
        self.bus.stop()

    def armed(self) -> Any:
        """A context manager running the watchdog's heartbeat while the bus runs (no-op when
        off, or off the main thread)."""
        return self.dog.armed()


def build_planner(ads: AdsConfig, sc: Scenario) -> Any:
    """The planner the ADS config names, built for the scenario's map; ConfigError (one line,
    naming the ADS config file and ``planning.planner``) when the class cannot be imported or
    rejects its parameters - checked by the CLIs before any run."""
    spec = ads.planning.planner
    try:
        return load_planner(spec.cls, sc.map.model_dump(), dict(spec.params))
    except (ImportError, AttributeError, TypeError, ValueError) as exc:  # unknown class, bad params
        errors = getattr(exc, "errors", None)
        if callable(errors):  # a pydantic ValidationError: its fields, one line
            first = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in errors())
        else:
            first = first_line(exc)
        shown = repr(dict(spec.params))
        shown = shown if len(shown) <= 200 else shown[:200] + "...}"
        raise ConfigError(f"{getattr(ads, '_source', 'ADS config')}: planning.planner: cannot build "
                          f"{spec.cls!r} with params {shown}: {first[:300]}") from None


class SimulatorNode(Node):
    """The simulator: steps the world on a precise timer and publishes chassis."""

    def __init__(self, sim: Simulation) -> None:
        ads = sim.ads
        self.t_control = ads.topic("control")
        super().__init__("simulator", [self.t_control], period_ns=round(NS_PER_S / ads.world_hz))
        self.sim = sim
        self.dt = 1.0 / ads.world_hz
        self.t_chassis = ads.topic("chassis")
        self.chassis_every = max(1, round(ads.world_hz / ads.chassis_hz))
        self.ticks = 0

    def _tick(self, nominal_ns: int) -> None:
        self.bus.schedule(nominal_ns + self.period_ns, self._tick, nominal_ns + self.period_ns)
        if self.ticks > 0 and self.alive:
            self.bus.supervisor.run(self, self.step)
        self.ticks += 1

    def step(self) -> None:
        sim, world = self.sim, self.sim.world
        cmd = self.latest.get(self.t_control)
        steer, acc = (cmd.payload["steering"], cmd.payload["acceleration"]) if cmd else (0.0, 0.0)
        world.step(self.dt, steer, acc)
        for cb in sim.on_step:
            cb(sim)
        if self.ticks % self.chassis_every == 0:
            e = world.ego
            self.bus.publish(self.t_chassis, {"header": header(self.bus.now, self.name),
                                              "speed": float(e.speed),
                                              "steering": float(e.action["steering"]),
                                              "acceleration": float(e.accel)})
        if sim.oracle.check() is not None:
            self.bus.stop()


@dataclass
class EpisodeResult:
    """What one run produced."""

    scenario: str
    outcome: Outcome
    wall_time: float
    jitter_seed: int
    planning: list[dict[str, Any]] = field(default_factory=list)
    log_path: str | None = None
    truth_path: str | None = None
    messages: int = 0
    drops: int = 0

    @property
    def sim_time(self) -> float:
        return self.outcome.sim_time

    def summary(self) -> dict[str, Any]:
        o = self.outcome
        return {"outcome": o.outcome, "collision": o.collision is not None,
                "collision_detail": o.collision.as_dict() if o.collision else None,
                "task_completed": o.task_completed, "sim_time": round(o.sim_time, 6),
                "wall_time": round(self.wall_time, 6), "jitter_seed": self.jitter_seed,
                "min_distance": None if o.min_distance == float("inf") else round(o.min_distance, 4),
                "planning_outputs": len(self.planning), "messages": self.messages,
                "dropped_deliveries": self.drops, "log": self.log_path, "truth": self.truth_path,
                **({"failure": o.failure} if o.failure is not None else {}),
                **({"arrival": o.arrival} if o.arrival == "a lane over" else {})}


class Simulation:
    """A scenario, an ADS configuration and a jitter seed, ready to run once."""

    def __init__(self, scenario: Scenario | str | Path, ads: AdsConfig | None = None,
                 jitter_seed: int | None = None, out_dir: Path | str | None = None,
                 keep_planning: bool = True, compress: bool = False,
                 recorder_process: bool | None = None, watchdog_s: float | None = None,
                 log_start_ns: int | None = None, run_wall_s: float | None = None) -> None:
        self.scenario = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
        self.ads = ads or load_ads_config()
        sc, ads = self.scenario, self.ads
        self.roadmap = shared_roadmap(sc.map.model_dump())
        self.world: World = build_world(sc, self.roadmap)
        self.world.ego.MAX_STEERING = math.radians(ads.max_steering_deg)
        self.jitter = JitterModel(ads.jitter, jitter_seed)
        self.bus = Bus(self.jitter)
        self.watch = WatchedSupervisor(self.bus, watchdog_seconds(watchdog_s),
                                       frozenset({ads.topic("planning"), ads.topic("control")}), run_wall_s)
        self.bus.supervisor = self.watch
        self.bus.reliable = {ads.topic(role) for role in ads.jitter.reliable}
        self.on_step: list[Callable[[Simulation], None]] = []
        topics = ads.topics
        dest_xy, dest_s = destination_xy(self.roadmap, sc.ego.destination)
        self.oracle = EpisodeOracle(self.world, dest_xy, sc.duration, stuck_time=sc.stuck_time,
                                    destination_lane=self.roadmap.geom(tuple(sc.ego.destination.lane)),
                                    destination_s=dest_s)
        self.planner = build_planner(ads, sc)
        start_lane = tuple(sc.ego.lane) if sc.ego.lane else self.roadmap.locate(
            self.world.ego.position, self.world.ego.heading)[0]
        self.simulator = SimulatorNode(self)
        self.planning = _node(PlanningNode, ads.planning, self.planner, ads.planning, topics)
        nodes: list[Node] = [
            self.simulator,
            _node(RoutingNode, ads.routing, self.roadmap, start_lane, tuple(sc.ego.destination.lane), dest_s,
                  sc.ego.cruise_speed, ads.routing, topics["routing"], topics["map"]),
            _node(LocalizationNode, ads.localization, self.world, ads.localization, topics["localization"], sc.seed),
            _node(PerceptionNode, ads.perception, self.world, ads.perception, topics["perception_obstacles"]),
            _node(PredictionNode, ads.prediction, self.roadmap, ads.prediction, topics["perception_obstacles"],
                  topics["prediction"]),
            self.planning,
            _node(ControlNode, ads.control, ads.control, topics),
        ]
        # traffic-light perception runs on every map (an empty detection where there are no
        # lights, as Apollo's does), so every log holds every topic
        nodes.insert(4, _node(TrafficLightNode, ads.traffic_light, self.world, ads.traffic_light,
                              topics["traffic_light"]))
        for n in nodes:
            self.bus.add(n)
        self.out_dir = Path(out_dir) if out_dir else None
        self.recorder: McapRecorder | None = None
        self.scene: SceneWriter | None = None
        # the log's time base: a real epoch time (whole seconds) + sim time, so viewers show a date
        self.log_start_ns = int(time.time()) * NS_PER_S if log_start_ns is None else int(log_start_ns)
        if self.out_dir is not None:
            hz = scene_hz()
            self.recorder = McapRecorder(self.out_dir / "episode.mcap", topics, self.metadata(), compress=compress,
                                         background=recorder_process, extra_channels=viewer_channels() if hz else ())
            self.bus.taps.append(self.recorder.tap)
            if hz:
                self.scene = SceneWriter(self, self.recorder.tap, self.log_start_ns, hz)
        self.added: list[dict[str, Any]] = []
        self._wall = 0.0
        self._started = False
        self._result: EpisodeResult | None = None
        self._interrupted: dict[str, Any] | None = None
        self.planning_outputs: list[dict[str, Any]] = []
        if keep_planning:
            t_plan = topics["planning"]
            keep = self.planning_outputs.append
            self.bus.taps.append(lambda m: keep(m.payload) if m.topic == t_plan else None)

    def metadata(self) -> dict[str, Any]:
        """What the log's episode record says about this run."""
        ads = self.ads
        return {
            "format": "deft_gym.episode/1",
            "deft_gym_version": PACKAGE_VERSION,
            LOG_START_KEY: self.log_start_ns,
            "scenario_name": self.scenario.name,
            "scenario_source": self.scenario.source or "",
            "scenario": scenario_to_dict(self.scenario),
            "jitter_seed": self.jitter.seed,
            "jitter_model": JitterModel.VERSION,
            "scenario_seed": self.scenario.seed,
            "map": self.scenario.map.model_dump(),
            "ego": {"length": float(self.world.ego.LENGTH), "width": float(self.world.ego.WIDTH)},
            "planner": {"class": ads.planning.planner.cls, "params": dict(ads.planning.planner.params),
                        "subscribe": list(self.planning.roles), "trigger": ads.planning.trigger,
                        "source_sha256": planner_fingerprint(ads.planning.planner.cls)},
            "topics": dict(ads.topics),
            "ads_config": ads.model_dump(mode="json", by_alias=True),
        }

    # -- running ----------------------------------------------------------------------------
    def start(self) -> None:
        """Start the modules (idempotent)."""
        if not self._started:
            self._started = True
            self.bus.start()

    @property
    def done(self) -> bool:
        """An oracle ended the episode, or its duration is over."""
        return self.bus.stopped or self.bus.now_ns >= to_ns(self.scenario.duration)

    def advance(self, until: float) -> bool:
        """Run to sim time ``until`` [s] (capped at the duration); True when the episode is over."""
        self.start()
        wall0 = time.perf_counter()
        try:
            if self.bus.supervisor is self.watch:
                with self.watch.armed():
                    self.bus.run(min(to_ns(until), to_ns(self.scenario.duration) + 1))
            else:
                self.bus.run(min(to_ns(until), to_ns(self.scenario.duration) + 1))
        finally:
            self._wall += time.perf_counter() - wall0
        return self.done

    def add_participant(self, spec: dict[str, Any]) -> Any:
        """Add a participant now (same schema as a scenario's ``participants`` entries). A scripted
        vehicle appears at its first waypoint time; it is recorded in the log's outcome record."""
        from deft_gym.scenarios.scenario import add_participant, parse_participant

        p = parse_participant(spec, self.roadmap, source=f"participant {spec.get('id', '?')!r}")
        if any(q.id == p.id for q in self.world.participants):
            raise ValueError(f"participant id {p.id!r} already exists")
        part = add_participant(self.world, p)
        self.added.append({"time": self.world.time, **p.model_dump(mode="json", exclude_none=True)})
        return part

    def finish(self) -> EpisodeResult:
        """Close the log and return the result (idempotent)."""
        if self._result is not None:
            return self._result
        outcome = self.oracle.outcome()
        failure = self.watch.failure if self.bus.supervisor is self.watch else None
        if self._interrupted is not None:  # the program was interrupted: the log must not say timeout
            outcome = Outcome("interrupted", outcome.sim_time, outcome.collision, outcome.min_distance,
                              {**self._interrupted, "time": outcome.sim_time})
        elif failure is not None:
            outcome = Outcome(failure["kind"], outcome.sim_time, outcome.collision, outcome.min_distance, failure)
        elif outcome.outcome == "completed" and self.bus.published_on(self.ads.topic("planning")) == 0:
            outcome = Outcome("no_plan", outcome.sim_time, outcome.collision, outcome.min_distance,
                              {"kind": "no_plan", "module": "planning",
                               "exception": "the ego reached its destination without ever receiving a plan",
                               "time": outcome.sim_time})
        bus = self.bus
        result = EpisodeResult(self.scenario.name, outcome, self._wall, self.jitter.seed,
                               self.planning_outputs, messages=bus.published, drops=self.jitter.drops)
        if self.recorder is not None:
            if self.scene is not None:
                self.scene.finish(outcome.collision.as_dict() if outcome.collision else None)
            self.recorder.flush()  # the last messages are written while the truth file is
            result.truth_path = str(write_truth(self.out_dir / "truth.jsonl", self.planning.truth, self.ads.topics))
            result.log_path = str(self.recorder.close({**outcome.as_dict(), "wall_time": self._wall,
                                                       "jitter_seed": self.jitter.seed,
                                                       "participants_added": self.added}))
        self._result = result
        close = getattr(self.planner, "close", None)  # a planner in a process of its own ends it
        if callable(close):
            close()
        return result

    def run(self) -> EpisodeResult:
        """Run until an oracle ends the episode or the duration is over. Interrupted (Ctrl-C, or
        an error of the tool itself), the log is closed with the outcome ``interrupted``."""
        try:
            self.advance(self.scenario.duration)
        except BaseException as exc:
            self._interrupted = {"kind": "interrupted", "module": None, "exception": describe_exception(exc)}
            raise
        finally:
            result = self.finish()
        return result


def _node(default: type, cfg: Any, *args: Any) -> Node:
    """The module's bus node: the built-in class or the one named in its config (``node``)."""
    cls = import_object(cfg.node) if getattr(cfg, "node", None) else default
    return cls(*args)


def run_episode(scenario: Scenario | str | Path, ads: AdsConfig | None = None, jitter_seed: int | None = None,
                out_dir: Path | str | None = None, keep_planning: bool = True, compress: bool = False) -> EpisodeResult:
    """Build and run one episode (see :class:`Simulation`)."""
    return Simulation(scenario, ads, jitter_seed, out_dir, keep_planning, compress).run()


__all__ = ["DEFAULT_WATCHDOG_S", "EpisodeResult", "Simulation", "WatchedSupervisor", "run_episode", "write_atomic"]


def reference_path(sc: Scenario, jitter_seed: int = 0) -> np.ndarray:
    """The ego's path in one run of ``sc``: rows ``(t, x, y, heading, speed)`` at every step."""
    sim = Simulation(sc, jitter_seed=jitter_seed, keep_planning=False)
    rows: list[tuple[float, float, float, float, float]] = []

    def grab(s: Any) -> None:
        e = s.world.ego
        rows.append((s.world.time, float(e.position[0]), float(e.position[1]), float(e.heading), float(e.speed)))

    sim.on_step.append(grab)
    sim.run()
    return np.array(rows)
