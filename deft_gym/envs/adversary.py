"""``deft_gym/Adversary-v0``: an RL adversary places vehicles and obstacles around the ego.

One episode is one simulated scenario: a seed scenario (a perturbed variant, or a generated
scenario ``gen:<seed>``) runs on the full jittered ADS stack, and every ``dt`` seconds (2 s) the
adversary may add one participant or change the motion of one vehicle it added. Every placement
request is granted by the shared :class:`~deft_gym.search.placement.Placer` under the configured
placement rule (``closest`` or ``uniform``, the same rule the search baselines are evaluated
under) inside the non-invasive feasible area (:mod:`deft_gym.search.feasible`, Decictor eq.
3-4), so the action space only reaches placements that never come within 0.5 m of the ego's
reference motion, nor into the areas of the other participants - validity by construction. The
episode's log can be handed to the DeFT extractor (:class:`deft_gym.envs.sink.EpisodeSink`).

**Action** ``MultiDiscrete([5, 11, 9, 5, 5])``: operation (no-op, cone, static vehicle, vehicle,
change a vehicle), where along the reference path relative to the ego (``ALONG`` m, or relative
to the previous placement: ``AT_LAST``), lateral offset from the path (``LATERAL`` m, right +;
the request the placement rule grants: ``closest`` moves it outwards until it is feasible, so
+-1.5 means "as close as allowed"), speed (``SPEEDS`` x the lane speed limit) and manoeuvre for
the next window (keep lane, change towards / away from the ego's path, turn left / right at the
next junction).

**Observation** (``Box``, 119 floats): progress, the ego's state relative to the reference path
and to the reference timing, what the planner intends (read off its latest trajectory, for any planner), the lane structure, the curvature
of the path and the closest feasible obstacle offset at every ``ALONG`` anchor, the six nearest
participants in the path frame, and where the previous placement went.

**Reward**: per window, potential-based shaping - the growth of the ego's largest distance from the
reference path (objective ``nods``) and of its largest proximity (gap / time to collision) to an
added participant (``collision``); at the end a bonus for an ego-at-fault collision
(``collision``) or a non-optimal decision (``nods``) of a valid mutation (``both``: either) - a
fifth of it when the trigger stood inside the ego's lane, and divided by sqrt(1 + n) for a root
cause this env was rewarded for n times before (distinct root causes are the headline) - a
small penalty for a timeout/stuck ego (a task failure, no NoDS) or for a participant running into
the ego (not the ego's fault), and shaping by 1 - IoU.

**Oracle** (``oracle:``, default ``default``): a driving-quality metric oracle instead
(:mod:`deft_gym.metrics.oracle`): the end bonus goes to its finding on a valid mutation, novelty
by its signature, and a run without one earns ``iou_shaping`` x its severity. ``any``: the bonus
for the decision oracle's failure and for each counted metric oracle's finding, each with its own
novelty (the evaluation's "any oracle"); a run with none is rewarded as under ``default``.
``late_statics: from_start`` pays a bonus only for what comes back with the static objects placed
mid-run standing from t = 0 (one more simulation of such an episode: the evaluation's rule).

**info** (final step): ``metrics`` (docs/metrics.md), ``oracle``, ``oracle_signature``, ``found_by_oracle`` (every
counted metric oracle's finding, not re-checked), ``collision``, ``ego_at_fault``, ``nods``, ``failure``, ``iou``, ``f_p``, ``f_b``,
``valid``, ``invasive``, ``outcome``, ``signature``, ``scenario``, ``jitter_seed``, ``added``,
``env_steps`` (the env's steps so far, all episodes), ``from_start`` (None, or when ``late_statics:
from_start`` simulated the episode again, what came back: ``decision``, ``found`` (oracles),
``aimed``), and the log / extraction results when logging.
"""

from __future__ import annotations

import math
import os
import shutil
import time
from pathlib import Path
from typing import Any, Literal

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from pydantic import BaseModel, ConfigDict, Field

from deft_gym.config import load_mapping, validate
from deft_gym.envs.sink import EpisodeSink
from deft_gym.metrics.oracle import (
    COUNTED_ORACLES,
    ORACLES,
    findings_by_oracle,
    rerun,
    run_metrics,
    seed_finding,
    severity,
)
from deft_gym.scenarios.scenario import with_participants
from deft_gym.search.context import SEED_SCENARIOS, SeedContext, ads_config, robust, seed_context
from deft_gym.search.episode import (
    late_statics,
    replay_record,
    run_scenario,
    statics_from_start,
    write_optimal_path,
)
from deft_gym.search.feasible import FeasibleConfig, Layout
from deft_gym.search.nods import EGO_LENGTH, EGO_WIDTH, IN_LANE
from deft_gym.search.placement import ALONG, LATERAL, MANOEUVRES, SPEEDS, Placer, first_window
from deft_gym.search.trace import TraceRecorder
from deft_gym.search.vehicles import (
    LENGTH,
    WIDTH,
    Trajectory,
    complete,
    window_feasible,
)
from deft_gym.sim.simulation import Simulation
from deft_gym.world.geometry import box_gap, box_gap_point
from deft_gym.world.participants import SIZES

OPS = ("noop", "cone", "static_vehicle", "vehicle", "change")
AT_LAST = ("last", "last+8")  # anchors relative to the previous placement (gates, walls)
# ALONG, LATERAL, SPEEDS, MANOEUVRES: the request grid every method asks from (placement.py)
N_NEAR = 6
OBS_DIM = 6 + 8 + 8 + 3 * len(ALONG) + 2 * len(ALONG) + 8 * N_NEAR + 4


class RewardConfig(BaseModel):
    """Reward weights."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    failure_bonus: float = 10.0
    in_lane_share: float = Field(0.2, ge=0.0, le=1.0, description="share of failure_bonus for a failure whose "
                                 "trigger stood inside the ego's own lane (< 0.75 m from the optimal path: the "
                                 "headline leaves those root causes out)")
    novelty: bool = Field(True, description="scale failure_bonus by 1 / sqrt(1 + n), n: how often this env has "
                          "already been rewarded for the same root cause (count-based novelty: distinct root "
                          "causes are the headline)")
    task_failure: float = -2.0
    invalid: float = -5.0
    deviation: float = 2.0
    proximity: float = 1.0
    iou_shaping: float = 2.0
    placement_cost: float = 0.0


class AdversaryConfig(BaseModel):
    """Everything that shapes the adversary env (``configs/train/*.yaml``: key ``env``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    scenarios: list[str] = Field(default_factory=lambda: list(SEED_SCENARIOS), min_length=1)
    ads: str | None = Field(None, description="ADS config YAML the scenarios run on (default: "
                            "configs/ads/default.yaml); configs/ads/commonroad.yaml puts CommonRoad's reactive "
                            "planner under test")
    objective: Literal["collision", "nods", "both"] = "both"
    oracle: Literal[ORACLES] = Field("default", description="what the end-of-episode bonus rewards: default "  # type: ignore[valid-type]
                                     "(the objective's failures: NoDS, at-fault collisions), any (those and every "
                                     "counted metric oracle's findings) or a driving-quality metric oracle "
                                     "(deft_gym.metrics.oracle, docs/metrics.md): its finding on a valid mutation, "
                                     "novelty by its signature; the shaping stays the objective's")
    variant_prob: float = Field(0.0, ge=0.0, le=1.0, description="share of episodes on a training variant")
    variant_seeds: int = Field(200, ge=1, description="training variants use seeds [0, variant_seeds)")
    feasible: FeasibleConfig = FeasibleConfig()
    placement: Literal["closest", "uniform"] = Field("closest", description="how a requested placement is "
                                                      "granted (deft_gym.search.placement; the same rule the "
                                                      "search baselines are evaluated under)")
    max_added: int = Field(8, ge=1, le=40)
    respect_plan: bool = Field(True, description="never place into the ego's current planned trajectory")
    plan_margin: float = Field(0.3, ge=0.0, le=5.0)
    reward: RewardConfig = RewardConfig()
    late_statics: Literal["from_start", "as_placed"] = Field(
        "as_placed", description="from_start: the end bonus pays for a failure or finding only when it comes "
        "back with the static objects this episode placed mid-run standing from t = 0 (one more simulation, on "
        "the same jitter seed, of an episode that has both) - the evaluation's rule for counting it "
        "(docs/search.md, Validity); as_placed: as the episode ran")
    grid: Literal["lane", "world"] = "lane"
    threshold: float = Field(0.6, gt=0.0, lt=1.0)
    reference_seed: int = 0
    log_dir: str | None = None
    record: Literal["all", "failures"] = Field("failures", description="with log_dir: record every episode "
                                               "as it runs (all), or only the kept ones (failures and a "
                                               "keep_passing sample) by replaying them exactly afterwards")
    keep_passing: float = Field(0.02, ge=0.0, le=1.0)
    keep_duplicates: bool = Field(False, description="with log_dir: also keep the log (and extract a test) "
                                  "of a failure whose (scenario, signature) this worker already kept; off: "
                                  "its journal line names the kept log (duplicate_of)")
    distinct_across_workers: bool = Field(False, description="without keep_duplicates: also skip a failure "
                                          "another worker on the same log_dir kept at an earlier env step "
                                          "(deterministic for workers in lockstep: SB3 vec envs; "
                                          "deft_gym.envs.sink)")
    extract: bool = True
    worker: int = 0

    def context(self, scenario: str | Path) -> SeedContext:
        """The :class:`SeedContext` of a scenario under this config's feasible areas, reference
        seed and decision oracle (memoised per process by name: resolving a name reads files)."""
        key = (str(scenario), self.ads, self.feasible, self.reference_seed, self.grid, self.threshold)
        ctx = _CONTEXTS.get(key)
        if ctx is None:
            if len(_CONTEXTS) > 512:
                _CONTEXTS.clear()
            ctx = _CONTEXTS[key] = seed_context(scenario, self.feasible, ads_config(self.ads),
                                                reference_seed=self.reference_seed, grid=self.grid,
                                                threshold=self.threshold)
        return ctx


_CONTEXTS: dict[tuple[Any, ...], SeedContext] = {}


def load_env_config(source: dict[str, Any] | str | Path | AdversaryConfig | None = None,
                    **overrides: Any) -> AdversaryConfig:
    """Validate an env config (dict, YAML path or object) with keyword overrides."""
    name = "env config"
    if isinstance(source, AdversaryConfig):
        data = source.model_dump()
    elif isinstance(source, str | Path):
        name = str(source)
        data = load_mapping(source)
    else:
        data = dict(source or {})
    data.update({k: v for k, v in overrides.items() if v is not None})
    return validate(AdversaryConfig, data, name)


class AdversaryEnv(gym.Env):
    """See the module docstring."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 2}

    def __init__(self, scenario: str | list[str] | None = None,
                 objective: Literal["collision", "nods", "both"] | None = None,
                 config: dict[str, Any] | str | Path | AdversaryConfig | None = None,
                 render_mode: str | None = None, **overrides: Any) -> None:
        if isinstance(scenario, str):
            overrides["scenarios"] = [scenario]
        elif scenario is not None:
            overrides["scenarios"] = list(scenario)
        self.cfg = load_env_config(config, objective=objective, **overrides)
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode {render_mode!r} not in {self.metadata['render_modes']}")
        self.render_mode = render_mode
        self.action_space = spaces.MultiDiscrete([len(OPS), len(ALONG) + len(AT_LAST), len(LATERAL), len(SPEEDS),
                                                  len(MANOEUVRES)])
        self.observation_space = spaces.Box(-10.0, 10.0, shape=(OBS_DIM,), dtype=np.float32)
        self.sink = (EpisodeSink(self.cfg.log_dir, self.cfg.worker, self.cfg.keep_passing, self.cfg.extract,
                                 distinct=not self.cfg.keep_duplicates, shared=self.cfg.distinct_across_workers)
                     if self.cfg.log_dir else None)
        self._bad: set[str] = set()
        self._rewarded: dict[str, int] = {}  # root cause -> failures rewarded so far (novelty)
        self.sim: Simulation | None = None
        self._finished = False
        self.ctx: SeedContext | None = None
        self.episodes = 0
        self.env_steps = 0  # steps over all episodes (a resumed training run sets where it starts)
        self._cpu0 = time.process_time()

    # -- episode ------------------------------------------------------------------------------
    def _context(self) -> SeedContext:
        cfg, rng = self.cfg, self.np_random
        for _ in range(20):
            name = cfg.scenarios[int(rng.integers(len(cfg.scenarios)))]
            if cfg.variant_prob > 0 and "~v" not in name and rng.random() < cfg.variant_prob:
                name = f"{name}~v{int(rng.integers(cfg.variant_seeds))}"
            if name in self._bad:
                continue
            try:
                ctx = cfg.context(name)
            except ValueError:  # a variant whose reference run fails is no optimal seed
                if "~v" not in name:
                    raise
                self._bad.add(name)
                continue
            if "~v" in name and not robust(ctx):  # flaky under timing noise: failures for free
                self._bad.add(name)
                continue
            return ctx
        raise RuntimeError("no usable scenario among " + ", ".join(cfg.scenarios))

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        self._close_sim()
        options = options or {}
        if "scenario" in options:
            self.ctx = self.cfg.context(options["scenario"])
        else:
            self.ctx = self._context()
        ctx = self.ctx
        self.jitter_seed = int(options.get("jitter_seed", self.np_random.integers(2**31 - 1)))
        self.log_dir = (self.sink.episode_dir(self._tag()) if self.sink is not None and self.cfg.record == "all"
                        else None)
        self.sim = Simulation(ctx.scenario, ctx.ads, jitter_seed=self.jitter_seed, out_dir=self.log_dir)
        if self.sim.recorder is not None:  # what the run is judged against, for the extracted NoDS test
            write_optimal_path(self.sim.recorder, ctx)
        self.added_ids: set[str] = set()
        self.added_at: dict[str, float] = {}
        self._until = 0.0
        self.recorder = TraceRecorder(self.sim, self.added_ids)
        self.layout = Layout(ctx.areas)
        self.placer = Placer(ctx, self.cfg.placement, self.np_random)
        self.driver = self.placer.driver
        self.k = 0
        self.n_placed = 0
        self._last_sigma: float | None = None
        self.ops: list[dict[str, Any]] = []
        self._hint = 0
        self._seen = 1  # ego rows of the recorder already rewarded
        self._max_dev = 0.0
        self._max_close = 0.0
        self.sim.start()
        self._finished = False
        self.episodes += 1
        return self._obs(), {"scenario": ctx.name, "jitter_seed": self.jitter_seed}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self.sim is None:
            raise RuntimeError("call reset() before step()")
        sim, dt = self.sim, self.ctx.feasible.dt
        op_info = self._apply(np.asarray(action, dtype=np.int64))
        self.k += 1
        self.env_steps += 1
        if self.sink is not None:
            self.sink.steps = self.env_steps  # in the journal (a resumed run's rollback)
        self._until = self.k * dt + 1e-6
        done = sim.advance(self._until)
        reward = self._shaping() + (self.cfg.reward.placement_cost if op_info.get("placed") else 0.0)
        info: dict[str, Any] = {"t": round(sim.world.time, 3), **op_info}
        if done:
            r_end, end_info = self._finish()
            reward += r_end
            info.update(end_info, env_steps=self.env_steps)  # where the episode ended (Monitor CSV)
        obs = self._obs()
        return obs, float(reward), bool(done), False, info

    def close(self) -> None:
        self._close_sim()

    def _close_sim(self) -> None:
        """Close an episode; one abandoned before its end leaves no log behind."""
        if self.sim is not None and not self._finished:
            self.sim.finish()
            if self.sink is not None and self.log_dir is not None:
                shutil.rmtree(self.log_dir, ignore_errors=True)
        self.sim = None

    # -- actions ------------------------------------------------------------------------------
    def _apply(self, a: np.ndarray) -> dict[str, Any]:
        op = OPS[int(a[0])]
        info: dict[str, Any] = {"op": op, "placed": False}
        if op == "noop":
            return info
        if op != "change" and len(self.layout.placed) >= self.cfg.max_added:
            info["rejected"] = "max_added"
            return info
        along, lateral = self._along(int(a[1])), LATERAL[int(a[2])]
        speed, man = SPEEDS[int(a[3])], MANOEUVRES[int(a[4])]
        if op in ("cone", "static_vehicle"):
            placed = self._place_static("CONE" if op == "cone" else "STATIC_VEHICLE", along, lateral)
        elif op == "vehicle":
            placed = self._place_vehicle(along, lateral, speed, man)
        else:
            placed = self._change_vehicle(along, lateral, speed, man)
        if placed is not None:
            if "sigma" in placed:
                self._last_sigma = self._ego_sigma()[0] + placed["sigma"]
            info.update(placed=True, **placed)
            self.ops.append({"t": round(self.sim.world.time, 3), "op": op, **placed})
        else:
            info["rejected"] = "infeasible"
        return info

    def _along(self, i: int) -> float:
        """Anchor [m] ahead of the ego's projection on the reference path."""
        if i < len(ALONG):
            return ALONG[i]
        sigma_e = self._ego_sigma()[0]
        base = (self._last_sigma if self._last_sigma is not None else sigma_e + 30.0) - sigma_e
        return base + (8.0 if AT_LAST[i - len(ALONG)] == "last+8" else 0.0)

    def _ego(self) -> tuple[float, float, float, float]:
        e = self.sim.world.ego
        return float(e.position[0]), float(e.position[1]), float(e.heading), float(e.speed)

    def _ego_sigma(self) -> tuple[float, float]:
        x, y, _, _ = self._ego()
        sigma, lat, self._hint = self.ctx.path.project(np.array([x, y]), self._hint)
        return sigma, lat

    def _plan(self) -> dict[str, np.ndarray] | None:
        outs = self.sim.planning_outputs
        if not outs:
            return None
        tr = outs[-1]["trajectory"]
        return {k: np.asarray(tr[k], dtype=float) for k in ("t", "x", "y", "heading", "v")}

    def _new_id(self, kind: str) -> str:
        self.n_placed += 1
        return f"adv_{kind}_{self.n_placed}"

    def _place_static(self, obstacle: str, along: float, lateral: float) -> dict[str, Any] | None:
        cfg = self.cfg
        sigma_e, _ = self._ego_sigma()
        length, width = SIZES[obstacle]
        plan = self._plan() if cfg.respect_plan else None

        def off_plan(x: np.ndarray, y: np.ndarray, h: np.ndarray) -> np.ndarray:
            g = box_gap(plan["x"][None, :], plan["y"][None, :], plan["heading"][None, :],
                        EGO_LENGTH + 2 * cfg.plan_margin, EGO_WIDTH + 2 * cfg.plan_margin,
                        x[:, None], y[:, None], h[:, None], length, width)
            return (g > 0.0).all(axis=1)

        ex, ey, _, _ = self._ego()
        pose = self.placer.static(self.layout, obstacle, sigma_e + along, lateral, ego_xy=np.array([ex, ey]),
                                  extra_ok=off_plan if plan is not None else None)
        if pose is None:
            return None
        pid = self._new_id("cone" if obstacle == "CONE" else "static")
        spec = self.placer.add_static(self.layout, pid, obstacle, pose)
        self._add(spec)
        return {"id": pid, "x": pose.x, "y": pose.y, "sigma": pose.sigma - sigma_e, "lateral": pose.lateral,
                "moved": abs(pose.sigma - sigma_e - along) + abs(pose.lateral - lateral)}

    def _add(self, spec: dict[str, Any]) -> None:
        self.added_ids.add(spec["id"])
        self.added_at[spec["id"]] = self._until  # replay: advance(until), then add
        self.sim.add_participant(spec)

    def _plan_ok(self, traj: Trajectory) -> bool:
        if not self.cfg.respect_plan:
            return True
        plan = self._plan()
        x, y, h, _ = self._ego()
        pt = np.array([self.sim.world.time])
        px, py, ph = np.array([x]), np.array([y]), np.array([h])
        if plan is not None:
            keep = plan["t"] >= self.sim.world.time - 1e-6
            pt = np.concatenate([pt, plan["t"][keep]])
            px, py = np.concatenate([px, plan["x"][keep]]), np.concatenate([py, plan["y"][keep]])
            ph = np.concatenate([ph, plan["heading"][keep]])
        inside = (pt >= traj.t[0]) & (pt <= traj.t[-1])
        if not inside.any():
            return True
        pt, px, py, ph = pt[inside], px[inside], py[inside], ph[inside]
        vx, vy = np.interp(pt, traj.t, traj.x), np.interp(pt, traj.t, traj.y)
        vh = np.interp(pt, traj.t, np.unwrap(traj.h))
        m = self.cfg.plan_margin
        return bool((box_gap(px, py, ph, EGO_LENGTH + 2 * m, EGO_WIDTH + 2 * m, vx, vy, vh, LENGTH, WIDTH) > 0).all())

    def _place_vehicle(self, along: float, lateral: float, speed: float, man: str) -> dict[str, Any] | None:
        t0 = round(self.sim.world.time, 6)
        sigma_e, _ = self._ego_sigma()
        ex, ey, _, _ = self._ego()
        traj = self.placer.vehicle(self.layout, t0, sigma_e + along, lateral, speed, man, ego_xy=np.array([ex, ey]),
                                   trajectory_ok=self._plan_ok)
        if traj is None:
            return None
        pid = self._new_id("veh")
        spec = self.placer.add_vehicle(self.layout, pid, traj)
        self._add(spec)
        sig, lat, _ = self.ctx.path.project(np.array([traj.x[0], traj.y[0]]))
        return {"id": pid, "x": float(traj.x[0]), "y": float(traj.y[0]), "sigma": along, "lateral": float(lat),
                "speed": float(traj.states[0].v), "manoeuvre": man,
                "moved": abs(sig - sigma_e - along) + abs(lat - lateral)}

    def _change_vehicle(self, along: float, lateral: float, speed: float, man: str) -> dict[str, Any] | None:
        ctx = self.ctx
        vehicles = [p for p in self.layout.placed if p.kind == "scripted"]
        if not vehicles:
            return None
        t0 = round(self.sim.world.time, 6)
        sigma_e, _ = self._ego_sigma()
        target, _ = ctx.path.offset(np.array([sigma_e + along]), np.array([lateral]))
        pos = [(p, p.traj.state_at(t0), p.traj.index(t0)) for p in vehicles]
        p, st, i = min(pos, key=lambda q: math.hypot(q[0].traj.x[q[2]] - target[0, 0], q[0].traj.y[q[2]] - target[0, 1]))
        if p.traj.t[i] > t0 + 1e-6 or p.traj.t[-1] < t0:
            return None
        v = speed * self.driver.v_max(st.lane) / self.driver.v_max_factor
        first = first_window(self.driver, ctx, st, t0, v, man)
        if first is None or not window_feasible(self.layout, first, p.id) or not self._plan_ok(first):
            return None
        new = complete(self.driver, self.layout, first, ctx.scenario.duration, ctx.path.xy, skip=p.id)
        if new is None or not self._plan_ok(new):
            return None
        traj = p.traj.until(t0).extend(new)
        spec = self.placer.add_vehicle(self.layout, p.id, traj)
        _retarget(self.sim, p.id, spec)
        return {"id": p.id, "speed": float(v), "manoeuvre": man}

    # -- reward / end -------------------------------------------------------------------------
    def _shaping(self) -> float:
        """Potential-based shaping (it telescopes: no reward for merely keeping the ego near
        something): the increase of the largest deviation from the reference path so far and of
        the largest closeness to an added participant so far."""
        cfg, ctx = self.cfg.reward, self.ctx
        ego = self.recorder.ego_rows(self._seen)  # this window's ego states
        self._seen = len(self.recorder)
        if not len(ego):
            return 0.0
        r = 0.0
        if self.cfg.objective in ("nods", "both"):
            lane_w = ctx.roadmap.spec.lane_width
            dev = ctx.oracle.distances(ego[:, :2])
            new = max(self._max_dev, min(float(dev.max()), lane_w))
            r += cfg.deviation * (new - self._max_dev) / lane_w
            self._max_dev = new
        if self.cfg.objective in ("collision", "both") and self.added_ids:
            close = max(self._max_close, self._proximity())
            r += cfg.proximity * (close - self._max_close)
            self._max_close = close
        return r

    def _proximity(self) -> float:
        """exp(-gap / 2 m) or exp(-TTC / 2 s) to the closest added participant, now."""
        w = self.sim.world
        ex, ey, eh, ev = self._ego()
        best = 0.0
        for p in w.present_participants():
            if p.id not in self.added_ids:
                continue
            o = p.obj
            gap = box_gap_point(ex, ey, eh, EGO_LENGTH, EGO_WIDTH, float(o.position[0]), float(o.position[1]),
                                float(o.heading), o.LENGTH, o.WIDTH)
            rel = np.array([o.position[0] - ex, o.position[1] - ey])
            dist = max(float(np.hypot(*rel)), 1e-3)
            vrel = np.array([o.speed * math.cos(o.heading) - ev * math.cos(eh),
                             o.speed * math.sin(o.heading) - ev * math.sin(eh)])
            closing = -float(rel[0] * vrel[0] + rel[1] * vrel[1]) / dist
            ttc = max(gap, 0.0) / closing if closing > 0.1 else math.inf
            best = max(best, math.exp(-max(gap, 0.0) / 2.0), math.exp(-ttc / 2.0))
        return best

    def _finish(self) -> tuple[float, dict[str, Any]]:
        sim, ctx, cfg = self.sim, self.ctx, self.cfg
        result = sim.finish()
        self._finished = True
        o = result.outcome
        trace = self.recorder.trace(o.outcome, o.sim_time)
        verdict = ctx.oracle.judge(trace, o.collision.as_dict() if o.collision else None)
        self.last_verdict = verdict
        metrics = self.last_metrics = run_metrics(ctx, trace, o.collision.as_dict() if o.collision else None)
        found = findings_by_oracle(ctx, verdict.valid, metrics, COUNTED_ORACLES)  # every metric's, unchecked
        aimed = seed_finding(ctx, verdict.valid, metrics, cfg.oracle)  # the aimed metric oracle's (None: default, any)
        decision = self._objective_failure(verdict)
        paid = self._paid_from_start(verdict, decision, found, aimed)
        rw = cfg.reward
        r = 0.0
        if not verdict.valid:
            r += rw.invalid
        elif cfg.oracle == "any":  # the union: each decision and metric finding, novelty by signature
            r += self._union_bonus(verdict, found, o.outcome, paid)
        elif cfg.oracle != "default":  # a metric oracle: its finding, novelty by its signature
            if aimed is None:
                r += rw.iou_shaping * severity(metrics, cfg.oracle)
            elif paid[2] is not None:
                r += self._failure_bonus(verdict, aimed)
        else:
            if paid[0]:
                r += self._failure_bonus(verdict)
            r += self._spent_or_shaping(verdict, o.outcome)
        info = {**verdict.as_dict(), "metrics": metrics.as_dict(),
                "oracle_signature": aimed,
                "oracle": cfg.oracle, "found_by_oracle": found,
                "scenario": ctx.name, "jitter_seed": self.jitter_seed,
                "pid": os.getpid(), "process_cpu": round(time.process_time() - self._cpu0, 3),
                "added": len(self.layout.placed), "sim_time": round(o.sim_time, 3),
                "wall_time": round(result.wall_time, 3), "from_start": self._from_start}
        if self.sink is not None:
            details = {"scenario_equivalent": self.equivalent_scenario(), "ops": self.ops,
                       "reference_seed": cfg.reference_seed}
            record = {k: info[k] for k in info if k != "collision_detail"} | {"collision_detail": verdict.collision_detail}
            if self.log_dir is not None:  # recorded as it ran
                done = self.sink.finish(Path(self.log_dir), record, details)
            else:
                done = self._replay_into_sink(record, details, verdict)
            info["log"] = done.get("dir")
            info["extraction"] = done.get("extraction")
        return r, info

    def _paid_from_start(self, verdict: Any, decision: bool, found: dict[str, str],
                         aimed: str | None) -> tuple[bool, dict[str, str], str | None]:
        """What of this run's findings the end bonus may pay for: ``(decision failure, metric
        findings, aimed oracle's finding)``. Under ``late_statics: from_start`` an episode with a
        finding and a static object placed after t = 0 is simulated once more on its jitter seed
        with those objects there from the start, and only what comes back with the same root
        cause (signature) is paid; otherwise all of it."""
        self._from_start: dict[str, Any] | None = None
        if self.cfg.late_statics == "as_placed" or not verdict.valid or not (decision or found or aimed):
            return decision, found, aimed
        eq = self.equivalent_scenario()
        specs = eq["scenario"]["participants"][len(self.ctx.scenario.participants):]
        if not late_statics(specs, eq["added_at"]):
            return decision, found, aimed
        again, m = rerun(self.ctx, specs, self.jitter_seed, statics_from_start(specs, eq["added_at"]))
        v = again.verdict
        paid = (decision and v.failure == verdict.failure and v.signature == verdict.signature,
                {o: sig for o, sig in found.items() if seed_finding(self.ctx, v.valid, m, o) == sig},
                aimed if aimed is not None and seed_finding(self.ctx, v.valid, m, self.cfg.oracle) == aimed else None)
        self._from_start = {"decision": paid[0], "found": sorted(paid[1]), "aimed": paid[2] is not None}
        return paid

    def _union_bonus(self, verdict: Any, found: dict[str, str], outcome: str,
                     paid: tuple[bool, dict[str, str], str | None] | None = None) -> float:
        """The end reward of ``oracle: any``: :meth:`_failure_bonus` for the decision oracle's
        failure (the objective's) and for each metric finding in ``found`` (``{oracle:
        signature}``; an at-fault collision once), each with its own novelty, of those ``paid``
        (:meth:`_paid_from_start`; default: all); without any found, the task-failure penalty or the objective's
        IoU shaping, as ``default``."""
        decision = self._objective_failure(verdict)
        if decision and verdict.failure == "collision":
            found = {o: sig for o, sig in found.items() if o != "collision"}
        paid = paid or (decision, found, None)
        r = (self._failure_bonus(verdict) if paid[0] else 0.0) + sum(self._failure_bonus(verdict, sig)
                                                                       for o, sig in found.items() if o in paid[1])
        return r if decision or found else self._spent_or_shaping(verdict, outcome)

    def _spent_or_shaping(self, verdict: Any, outcome: str) -> float:
        """The end reward of the decision oracle besides its failure bonus: ``task_failure`` for a
        run that failed without the ADS failing (timeout, standstill, a collision not the ego's
        fault: the scenario is spent), the objective's IoU shaping for a completed run without NoDS."""
        rw = self.cfg.reward
        r = 0.0
        if outcome in ("timeout", "stuck") or (verdict.collision and not verdict.ego_at_fault):
            r += rw.task_failure
        if outcome == "completed" and not verdict.nods and self.cfg.objective in ("nods", "both"):
            r += rw.iou_shaping * (1.0 - verdict.iou)
        return r

    def _objective_failure(self, verdict: Any) -> bool:
        """Whether the run is a failure the ``objective`` rewards: an at-fault collision
        (``collision``, ``both``) or a NoDS (``nods``, ``both``)."""
        objective = self.cfg.objective
        return bool((verdict.failure == "collision" and objective in ("collision", "both"))
                    or (verdict.nods and objective in ("nods", "both")))

    def _failure_bonus(self, verdict: Any, sig: str | None = None) -> float:
        """``failure_bonus`` for a failure, less for a trigger inside the ego's lane and for a
        root cause this env was rewarded for before (:class:`RewardConfig`); ``sig``: a metric
        oracle's signature (then the novelty counts it, and the lane band does not apply)."""
        rw = self.cfg.reward
        inside = sig is None and verdict.finding and verdict.finding.band == IN_LANE
        bonus = rw.failure_bonus * (rw.in_lane_share if inside else 1.0)
        key = verdict.signature if sig is None else sig
        if rw.novelty:
            n = self._rewarded.get(key, 0)
            self._rewarded[key] = n + 1
            bonus /= math.sqrt(1.0 + n)
        return bonus

    def _tag(self) -> str:
        return self.ctx.name.replace("~", "_").replace(":", "_")

    def _replay_into_sink(self, record: dict[str, Any], details: dict[str, Any], verdict: Any) -> dict[str, Any]:
        """Record a kept episode by replaying it exactly (same scenario, additions at the same
        times, same jitter seed) into a fresh episode folder; the rest only reach the journal."""
        keep = self.sink.keeps(record)
        if not keep:
            return self.sink.finish(None, record, details, keep=False)
        d = self.sink.episode_dir(self._tag())
        eq = details["scenario_equivalent"]
        specs = eq["scenario"]["participants"][len(self.ctx.scenario.participants):]
        again = run_scenario(self.ctx, specs, eq["jitter_seed"], out_dir=d, added_at=eq["added_at"]).verdict
        if again.failure != verdict.failure or abs(again.iou - verdict.iou) > 1e-9:
            details = {**details, "replay_differs": {"failure": again.failure, "iou": again.iou}}
        return self.sink.finish(d, record, details, keep=True)

    def equivalent_scenario(self) -> dict[str, Any]:
        """This episode in the one shape of a failure's scenario
        (:func:`deft_gym.search.episode.replay_record`): the seed scenario plus every added
        participant with its final motion, when each was added, and the jitter seed;
        ``deft_gym.search.episode.replay`` (``deft-gym run`` of it) replays this episode exactly."""
        data = with_participants(self.ctx.scenario, f"{self.ctx.name}+adv", [p.spec for p in self.layout.placed])
        return replay_record(data, self.jitter_seed, self.added_at)

    # -- observation --------------------------------------------------------------------------
    def _obs(self) -> np.ndarray:
        ctx, sim, cfg = self.ctx, self.sim, self.cfg
        path = ctx.path
        w = sim.world
        t = w.time
        x, y, h, v = self._ego()
        sigma_e, lat_e = self._ego_sigma()
        L = max(path.length, 1.0)
        sig_ref = path.sigma_at_time(t)
        n_win = ctx.areas.n_windows
        f: list[float] = [t / ctx.scenario.duration, sigma_e / L, sig_ref / L, (sigma_e - sig_ref) / 30.0,
                          len(self.layout.placed) / cfg.max_added, (n_win - self.k) / n_win]
        _, hp = path.at(sigma_e)
        dh = float((h - hp[0] + math.pi) % (2 * math.pi) - math.pi)
        f += [lat_e / 3.5, v / 15.0, (v - path.speed_at(sigma_e)) / 10.0, math.sin(dh), math.cos(dh) - 1.0,
              float(w.ego.accel) / 5.0, self._max_dev / 3.5, 1.0 if w.collision else 0.0]
        f += self._plan_features(sigma_e)
        grid, left, right = path.lanes_beside
        anchors = sigma_e + np.array(ALONG)
        gi = np.clip(np.searchsorted(grid, anchors), 0, len(grid) - 1)
        f += (left[gi] / 2.0).tolist() + (right[gi] / 2.0).tolist()
        _, h0 = path.at(anchors)
        _, h1 = path.at(anchors + 10.0)
        f += np.clip((h1 - h0) * 2.0, -3.0, 3.0).tolist()  # heading change over the next 10 m (curves)
        f += self._closest_static(anchors)
        f += self._nearest(x, y, sigma_e)
        n_veh = sum(1 for p in self.layout.placed if p.kind == "scripted")
        f += [n_veh / cfg.max_added, (len(self.layout.placed) - n_veh) / cfg.max_added]
        last = self._last_sigma
        f += [0.0, 0.0] if last is None else [1.0, (last - sigma_e) / 50.0]
        return np.clip(np.asarray(f, dtype=np.float32), -10.0, 10.0)

    def _plan_features(self, sigma_e: float) -> list[float]:
        """What the planner intends, from its latest trajectory alone (any planner): its offset
        from the optimal path at a third, two thirds and the end of the plan [lanes], how far
        along the path it gets [m / 50], its end and lowest speed [/ 15 m/s], whether it stops,
        whether there is a plan."""
        plan = self._plan()
        if plan is None or not len(plan["x"]):
            return [0.0] * 7 + [1.0]
        n = len(plan["x"])
        lats, sig_end = [], sigma_e
        hint = self._hint
        for i in (n // 3, (2 * n) // 3, n - 1):
            sig, lat, hint = self.ctx.path.project(np.array([plan["x"][i], plan["y"][i]]), hint)
            lats.append(float(np.clip(lat / 3.5, -3.0, 3.0)))
            sig_end = sig
        v = plan["v"]
        return [*lats, (sig_end - sigma_e) / 50.0, float(v[-1]) / 15.0, float(v.min()) / 15.0,
                1.0 if v[-1] < 0.5 else 0.0, 0.0]

    def _closest_static(self, anchors: np.ndarray) -> list[float]:
        """Per anchor and side: smallest feasible |lateral| of a cone, normalised (1.5: none)."""
        lats = np.arange(1.2, 6.01, 0.6)
        sig = np.repeat(anchors, 2)  # (anchor, side) pairs
        side = np.tile([-1.0, 1.0], len(anchors))
        first = np.full(len(sig), 7.5)  # 7.5: none
        todo = np.arange(len(sig))
        # the nearest laterals first, the rest only where none of them is feasible (each box is
        # judged alone, so the answer is the same as testing them all at once, at a third the cost)
        for part in (lats[:3], lats[3:]):
            s_k, lat_k = np.repeat(sig[todo], len(part)), (side[todo, None] * part).ravel()
            xy, h = self.ctx.path.offset(s_k, lat_k)
            ok = self.layout.static_ok(xy[:, 0], xy[:, 1], h, 0.6, 0.6).reshape(len(todo), len(part))
            hit = ok.any(axis=1)
            first[todo[hit]] = part[np.argmax(ok[hit], axis=1)]
            todo = todo[~hit]
            if not len(todo):
                break
        return ((first - 1.2) / 4.0).tolist()  # 7.5 (none) -> 1.575

    def _nearest(self, x: float, y: float, sigma_e: float) -> list[float]:
        parts = self.sim.world.present_participants()
        out = np.zeros((N_NEAR, 8))
        if parts:
            pos = np.array([p.obj.position for p in parts], dtype=float)
            dist = np.hypot(pos[:, 0] - x, pos[:, 1] - y)
            order = np.argsort(dist)[:N_NEAR]
            path = self.ctx.path
            for r, i in enumerate(order):
                p = parts[int(i)]
                sig, lat, _ = path.project(pos[i])
                _, hp = path.at(sig)
                dh = float(p.obj.heading - hp[0])
                out[r] = [1.0, (sig - sigma_e) / 50.0, lat / 10.0, float(p.obj.speed) / 15.0, math.sin(dh),
                          math.cos(dh), 1.0 if p.kind == "static" else 0.0, 1.0 if p.id in self.added_ids else 0.0]
        return out.ravel().tolist()

    # -- rendering ----------------------------------------------------------------------------
    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array" or self.sim is None:
            return None
        from deft_gym.envs.render import render_state

        return render_state(self)


def _retarget(sim: Simulation, pid: str, spec: dict[str, Any]) -> None:
    """Give a scripted vehicle already in the world new waypoints (its past is unchanged)."""
    wp = np.array([[w["t"], w["x"], w["y"]] for w in spec["waypoints"]])
    for p in sim.world.participants:
        if p.id == pid:
            p.obj.set_waypoints(wp, float(p.obj.heading))
            break
    for entry in sim.added:
        if entry.get("id") == pid:
            entry["waypoints"] = spec["waypoints"]
            entry.setdefault("changed_at", []).append(round(sim.world.time, 6))
