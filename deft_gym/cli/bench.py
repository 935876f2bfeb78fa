"""Speed benchmark: the full stack against bare highway-env, recording on and off.

    deft-gym bench [--scenario bench_highway] [--repeats 3]      # -> runs/bench.json
    deft-gym bench --metrics left_turn right_turn --repeats 2 --out runs/bench_metrics.json
    deft-gym bench --commonroad handwritten/stopped_bus left_turn --out runs/bench_commonroad.json
    deft-gym bench --recording-only --repeats 40 --out runs/bench_recording.json

Measures simulated seconds per wall second (one simulation process) of

1. the full DeFT-Gym stack (world + all ADS modules on the jittered bus) with MCAP recording,
   written by the recorder process (the default) and by the writer in the simulation's process,
   and with the recorder process but without the Foxglove scene topics (what they cost);
2. the same without recording;
3. highway-env's own ``highway-v0`` stepped with the same vehicle count and simulation
   frequency (its default observation and action types), as the reference;

and prints both, their ratio, the recording overhead and where the stack's time goes.

The headline of the recording overhead is CPU time: the simulation process's and the recorder
process's together over the unrecorded run's (median of the paired ratios, with a bootstrap 95 %
interval: single runs on a shared machine drift by several per cent, so use ``--repeats 15`` or
more to resolve a few points; a loaded machine stretches wall time more than CPU time), wall
time beside it, and the same with every topic JSON (``DEFT_GYM_LOG_ENCODING=json``, logs before
the binary payloads). The recorder process's start-up
(once per simulation process, not per episode) is measured at the end from the children's CPU
time and printed apart.
Each figure is the median over ``--repeats`` runs; the runs of the three kinds are interleaved.
``--metrics SCENARIO...`` measures instead what the driving-quality metrics (docs/metrics.md) cost
against the episodes' CPU. ``--commonroad SCENARIO...`` runs each scenario with CommonRoad's
reactive planner (configs/ads/commonroad.yaml) twice, with the adapter's vectorised kinematic check
and with the library's own loop (``vectorised_kinematics: false``), and prints both CPU times and
whether the two runs' planning outputs are identical.
"""

from __future__ import annotations

import json
import os
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from deft_gym.cli import common
from deft_gym.files import write_atomic
from deft_gym.record.recorder import LOG_ENCODING_ENV


def stack_speed(scenario: Any, recorder: str | None, seed: int, breakdown: bool = False,
                scene: bool = True, encoding: str | None = None) -> dict[str, Any]:
    """One full-stack run: sim seconds, wall and CPU seconds of this process and (optionally)
    per-node wall time. ``recorder``: None (no log), ``"process"`` (the recorder process),
    ``"inline"`` (the MCAP writer in this process) or ``"json"`` (no log: every payload only
    JSON-encoded - the floor of a JSON log); ``scene``: with the Foxglove scene topics;
    ``encoding``: the log's message encoding (default: binary where a topic has a layout;
    ``"json"``: every topic JSON, as logs were before).
    Wall time runs until the log is complete and in place, so a recorder process that lags is
    charged for it."""
    from deft_gym.bus.ads import load_ads_config
    from deft_gym.bus.bus import TimingSupervisor
    from deft_gym.execution.watchdog import apply_env
    from deft_gym.sim.simulation import Simulation

    ads = load_ads_config()
    # the run's settings, restored after: the log's encoding (None: the default), no scene topics
    changes = {LOG_ENCODING_ENV: encoding, **({} if scene else {"DEFT_GYM_SCENE_HZ": "0"})}
    saved = {k: os.environ.get(k) for k in changes}
    apply_env(changes)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            sim = Simulation(scenario, ads, jitter_seed=seed,
                             out_dir=tmp if recorder in ("process", "inline") else None,
                             keep_planning=False, recorder_process=recorder == "process")
            if recorder == "json":
                from deft_gym.bus.codec import encode

                sim.bus.taps.append(lambda msg: encode(msg.payload))
            sup = None
            if breakdown:
                sup = TimingSupervisor()
                sim.bus.supervisor = sup
            t0, c0 = time.perf_counter(), time.process_time()
            r = sim.run()
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    finally:
        apply_env(saved)
    out = {"sim": r.sim_time, "wall": wall, "cpu": cpu, "speed": r.sim_time / wall, "messages": r.messages,
           "recorder_cpu": sim.recorder.process_seconds if sim.recorder is not None else 0.0}
    if sup is not None:
        out["nodes"] = {k: v for k, v in sup.seconds.items()}
    return out


def median_interval(values: list[float], confidence: float = 0.95) -> tuple[float, float] | None:
    """A bootstrap confidence interval of the median of ``values`` (scipy.stats.bootstrap,
    percentile method, seeded); None for fewer than 3 values."""
    if len(values) < 3:
        return None
    from scipy.stats import bootstrap

    ci = bootstrap((values,), statistics.median, confidence_level=confidence, method="percentile",
                   random_state=0, vectorized=False).confidence_interval
    return float(ci.low), float(ci.high)


def paired_overhead(values: list[float], base: list[float]) -> dict[str, Any]:
    """Of runs paired with the unrecorded ones (same jitter seed): the overhead ``value / base - 1``
    of each pair, their median and its bootstrap 95 % interval (:func:`median_interval`)."""
    ratios = [v / b - 1.0 for v, b in zip(values, base, strict=True)]
    return {"median": statistics.median(ratios), "ci95": median_interval(ratios)}


def _interval_text(ci: tuple[float, float] | None, n: int) -> str:
    return f"(95 % CI of the median of {n} paired runs: n/a)" if ci is None else \
        f"(95 % CI {100 * ci[0]:+.1f} to {100 * ci[1]:+.1f} %, {n} paired runs)"


def highway_speed(vehicles: int, frequency: float, sim_seconds: float, seed: int) -> dict[str, Any]:
    """highway-v0 stepped for ``sim_seconds`` with ``vehicles`` other vehicles at ``frequency`` Hz."""
    import gymnasium as gym
    import highway_env  # noqa: F401 - registers the envs

    env = gym.make("highway-v0", config={"vehicles_count": vehicles, "simulation_frequency": int(frequency),
                                         "duration": 10_000})
    env.reset(seed=seed)
    policy_hz = env.unwrapped.config["policy_frequency"]
    steps = int(sim_seconds * policy_hz)
    t0 = time.perf_counter()
    for _ in range(steps):
        _, _, term, trunc, _ = env.step(1)  # IDLE
        if term or trunc:
            env.reset()
    wall = time.perf_counter() - t0
    env.close()
    return {"sim": steps / policy_hz, "wall": wall, "speed": steps / policy_hz / wall}


def metrics_cost(scenarios: list[str], seeds: int) -> dict[str, Any]:
    """What the driving-quality metrics (docs/metrics.md) cost per episode: process CPU [s] of
    the episode without a trace recorder, with one, and of computing the metrics from its trace
    (the map's drivable area built beforehand, as every campaign after its first episode has it);
    their sums over ``scenarios`` x ``seeds`` unrecorded episodes and the shares."""
    from deft_gym.metrics.episode import MetricsContext, episode_metrics
    from deft_gym.scenarios.scenario import load_scenario
    from deft_gym.search.trace import TraceRecorder
    from deft_gym.sim.simulation import Simulation

    rows = []
    for name in scenarios:
        sc = load_scenario(name)
        for seed in range(seeds):
            c0 = time.process_time()
            Simulation(sc, jitter_seed=seed, keep_planning=False).run()
            bare = time.process_time() - c0
            sim = Simulation(sc, jitter_seed=seed, keep_planning=False)
            c0 = time.process_time()
            rec = TraceRecorder(sim)
            res = sim.run()
            traced = time.process_time() - c0
            ctx = MetricsContext.of_scenario(sc, sim.roadmap)
            ctx.area  # noqa: B018 - the map's drivable area: built once per map and process
            c0 = time.process_time()
            o = res.outcome
            m = episode_metrics(rec.trace(o.outcome, o.sim_time), ctx, o.collision.as_dict() if o.collision else None)
            rows.append({"scenario": sc.name, "jitter_seed": seed, "outcome": o.outcome, "sim_time": o.sim_time,
                         "episode_cpu": bare, "traced_cpu": traced, "metrics_cpu": time.process_time() - c0,
                         "score": round(m.score, 4)})
    tot = {k: sum(r[k] for r in rows) for k in ("episode_cpu", "traced_cpu", "metrics_cpu")}
    return {"episodes": rows, **tot, "metrics_share": tot["metrics_cpu"] / tot["episode_cpu"],
            "metrics_and_trace_share": (tot["traced_cpu"] - tot["episode_cpu"] + tot["metrics_cpu"]) / tot["episode_cpu"],
            "max_episode_share": max(r["metrics_cpu"] / r["episode_cpu"] for r in rows)}


def commonroad_cost(scenarios: list[str], seeds: int) -> dict[str, Any]:
    """CPU seconds of episodes with CommonRoad's planner, its kinematic check vectorised and the
    library's, on the same jitter seeds, and whether their planning outputs are identical."""
    from deft_gym.bus.ads import load_ads_config
    from deft_gym.config import CONFIG_DIR
    from deft_gym.sim.simulation import Simulation

    fast = load_ads_config(CONFIG_DIR / "ads" / "commonroad.yaml")
    planner = fast.planning.planner
    slow_planner = planner.model_copy(update={"params": {**planner.params, "vectorised_kinematics": False}})
    library = fast.model_copy(update={"planning": fast.planning.model_copy(update={"planner": slow_planner})})
    rows = []
    for name in scenarios:
        for seed in range(seeds):
            cpu, outputs = {}, {}
            for label, ads in (("vectorised", fast), ("library", library)):
                c0 = time.process_time()
                res = Simulation(name, ads, jitter_seed=seed).run()
                cpu[label] = time.process_time() - c0
                outputs[label] = [{k: p[k] for k in ("trajectory", "decision")} for p in res.planning]
            rows.append({"scenario": name, "jitter_seed": seed, "plans": len(outputs["library"]),
                         "cpu_vectorised": round(cpu["vectorised"], 3), "cpu_library": round(cpu["library"], 3),
                         "identical": outputs["vectorised"] == outputs["library"]})
    tot = {k: sum(r[k] for r in rows) for k in ("cpu_vectorised", "cpu_library", "plans")}
    return {"episodes": rows, **tot, "speedup": tot["cpu_library"] / tot["cpu_vectorised"],
            "all_identical": all(r["identical"] for r in rows)}


def build_parser() -> common.Parser:
    ap = common.parser("bench", "deft_gym.cli.bench", __doc__)
    ap.add_argument("--scenario", default="bench_highway",
                    help="scenario with the participants to benchmark (default: bench_highway, 5 reactive vehicles)")
    ap.add_argument("--repeats", type=common.positive_int, default=3, help="runs per measurement; the median is shown")
    ap.add_argument("--metrics", nargs="+", default=None, metavar="SCENARIO",
                    help="instead: what the driving-quality metrics cost on these scenarios (e.g. the seven seeds), "
                    "--repeats jitter seeds each, against the episodes' CPU (target <= 5 %%)")
    ap.add_argument("--commonroad", nargs="+", default=None, metavar="SCENARIO",
                    help="instead: CPU of CommonRoad's planner on these scenarios, its kinematic check vectorised "
                    "and the library's loop, --repeats jitter seeds each, and whether the outputs are identical")
    ap.add_argument("--recording-only", action="store_true",
                    help="instead: only the recording overhead, binary and all-JSON logs (recorder process) and binary "
                    "logs written in the simulation's process against unrecorded runs, --repeats interleaved "
                    "quadruplets (about 2x faster per repeat: use --repeats 40 on a noisy machine)")
    common.add_out(ap, common.RUNS / "bench.json", help="JSON file for the figures", folder=False)
    common.add_output_flags(ap)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    console = common.console(args, width=110)
    from rich.table import Table

    from deft_gym.bus.ads import load_ads_config
    from deft_gym.planner import lattice
    from deft_gym.scenarios.scenario import load_scenario

    if args.metrics:
        cost = metrics_cost(common.split_list(args.metrics), args.repeats)
        n = len(cost["episodes"])
        console.print(f"driving-quality metrics on {n} episodes: {1e3 * cost['metrics_cpu'] / n:.1f} ms CPU per "
                      f"episode, {100 * cost['metrics_share']:.2f} % of the episodes' CPU ({cost['episode_cpu']:.2f} s; "
                      f"worst episode {100 * cost['max_episode_share']:.2f} %); with the trace recorder's hooks "
                      f"{100 * cost['metrics_and_trace_share']:.2f} %; target <= 5 %", highlight=False)
        if args.out:
            write_atomic(Path(args.out), json.dumps(cost, indent=2))
            console.print(f"wrote {args.out}")
        return 0
    if args.commonroad:
        cost = commonroad_cost(common.split_list(args.commonroad), args.repeats)
        for r in cost["episodes"]:
            console.print(f"{r['scenario']} (jitter seed {r['jitter_seed']}, {r['plans']} plans): vectorised "
                          f"{r['cpu_vectorised']:.1f} CPU-s, library {r['cpu_library']:.1f} CPU-s, outputs "
                          f"{'identical' if r['identical'] else 'DIFFERENT'}", highlight=False)
        console.print(f"CommonRoad planner: {cost['speedup']:.2f}x less CPU vectorised ("
                      f"{1e3 * cost['cpu_vectorised'] / cost['plans']:.0f} vs {1e3 * cost['cpu_library'] / cost['plans']:.0f}"
                      f" ms per plan, simulation included); outputs identical in "
                      f"{sum(r['identical'] for r in cost['episodes'])} of {len(cost['episodes'])} episodes",
                      highlight=False)
        if args.out:
            write_atomic(Path(args.out), json.dumps(cost, indent=2))
            console.print(f"wrote {args.out}")
        return 0 if cost["all_identical"] else 1
    sc = load_scenario(args.scenario)
    if args.recording_only:
        return _recording_only(sc, args, console)
    ads = load_ads_config()
    n_part = len(sc.participants)
    evaluation = "numpy" if lattice._lattice_c is None else "compiled (C)"
    console.print(f"scenario {sc.name}: {n_part} participants, world {ads.world_hz:g} Hz, "
                  f"{sc.duration:g} s simulated per run, {args.repeats} runs each; "
                  f"lattice planner evaluation step: {evaluation}")
    # the per-module breakdown times every callback, which costs time itself: it is a run of
    # its own (also warming up caches), not one of the timed runs
    first = stack_speed(sc, "process", seed=0, breakdown=True)
    # interleaved (one of each per repeat), so drifting machine load biases no measurement
    rec, inline, noscene, norec, hw, json_only, json_log = [], [], [], [], [], [], []
    with common.bar(args, args.repeats, "benchmark") as bar:
        for i in range(args.repeats):
            rec.append(stack_speed(sc, "process", seed=i))
            inline.append(stack_speed(sc, "inline", seed=i))
            noscene.append(stack_speed(sc, "process", seed=i, scene=False))
            norec.append(stack_speed(sc, None, seed=i))
            json_only.append(stack_speed(sc, "json", seed=i))
            json_log.append(stack_speed(sc, "process", seed=i, encoding="json"))
            hw.append(highway_speed(n_part, ads.world_hz, sc.duration, seed=i))
            bar.update()
    runs = {"stack_recording": rec, "stack_recording_inline": inline, "stack_recording_no_scene": noscene,
            "stack_no_recording": norec, "stack_json_only": json_only, "stack_recording_json_log": json_log,
            "highway_v0": hw}
    med = {name: statistics.median(r["speed"] for r in rs) for name, rs in runs.items()}
    # recording on and off of one repeat share the jitter seed (the same messages): the median
    # of their wall-time ratios is robust to load that drifts between repeats
    overhead = {
        "wall": statistics.median(r["wall"] / n["wall"] for r, n in zip(rec, norec, strict=True)) - 1.0,
        "wall_inline": statistics.median(r["wall"] / n["wall"] for r, n in zip(inline, norec, strict=True)) - 1.0,
        "wall_no_scene": statistics.median(r["wall"] / n["wall"] for r, n in zip(noscene, norec, strict=True)) - 1.0,
        "cpu_sim_process": statistics.median(r["cpu"] / n["cpu"] for r, n in zip(rec, norec, strict=True)) - 1.0,
        "cpu_sim_process_no_scene": statistics.median(r["cpu"] / n["cpu"] for r, n in zip(noscene, norec,
                                                                                         strict=True)) - 1.0,
        "cpu_inline": statistics.median(r["cpu"] / n["cpu"] for r, n in zip(inline, norec, strict=True)) - 1.0,
        "cpu_json_only": statistics.median(r["cpu"] / n["cpu"] for r, n in zip(json_only, norec, strict=True)) - 1.0,
    }
    # CPU of both processes: what recording costs (the headline), and the same with every topic
    # JSON (logs before the binary payloads); with how sure it is - a bootstrap interval of the
    # median (single runs on a shared machine drift by several per cent; more --repeats narrow it)
    both = {name: paired_overhead([r["cpu"] + r["recorder_cpu"] for r in rs], [n["cpu"] for n in norec])
            for name, rs in (("cpu_both", rec), ("cpu_both_json_log", json_log))}
    overhead.update({name: b["median"] for name, b in both.items()})
    ci = {name: b["ci95"] for name, b in both.items()}
    recorder_ms = statistics.median(1e3 * r["recorder_cpu"] / r["sim"] for r in rec)
    ratio = med["stack_recording"] / med["highway_v0"]
    t = Table(title="simulated seconds per wall second (median)", title_justify="left")
    t.add_column("what")
    t.add_column("x real time", justify="right")
    t.add_row("DeFT-Gym full stack, recording on (recorder process)", f"{med['stack_recording']:.1f}")
    t.add_row("DeFT-Gym full stack, recording on (in-process writer)", f"{med['stack_recording_inline']:.1f}")
    t.add_row("DeFT-Gym full stack, recording on, no scene topics", f"{med['stack_recording_no_scene']:.1f}")
    t.add_row("DeFT-Gym full stack, recording off", f"{med['stack_no_recording']:.1f}")
    t.add_row(f"highway-v0, {n_part} vehicles, {ads.world_hz:g} Hz", f"{med['highway_v0']:.1f}")
    # the recorder process's own start-up and idle CPU: all its CPU (it ends here) less the logs'
    from deft_gym.record.recorder import RecorderProcess

    proc = RecorderProcess._current
    startup_s = None
    if proc is not None and proc.pid == os.getpid():
        proc.stop()
        RecorderProcess._current = None
        logs_s = sum(r["recorder_cpu"] for r in (first, *rec, *noscene, *json_log))
        children = resource.getrusage(resource.RUSAGE_CHILDREN)
        startup_s = children.ru_utime + children.ru_stime - logs_s
    sim_ms = statistics.median(1e3 * n["cpu"] / n["sim"] for n in norec)
    common.print_table(console, t)
    console.print(f"[bold]recording overhead: CPU {100 * overhead['cpu_both']:+.1f} %[/bold] "
                  f"{_interval_text(ci['cpu_both'], args.repeats)} (simulation process "
                  f"{100 * overhead['cpu_sim_process']:+.1f} %, recorder process {recorder_ms:.2f} ms CPU per sim s "
                  f"against {sim_ms:.2f} ms unrecorded); wall {100 * overhead['wall']:+.1f} %   "
                  f"targets: <= 10 % CPU; the stack recorded >= 3.0x highway-v0")
    console.print(f"full stack / highway-v0 = {ratio:.2f}x; in-process writer: CPU {100 * overhead['cpu_inline']:+.1f} %, "
                  f"wall {100 * overhead['wall_inline']:+.1f} %"
                  + ("" if startup_s is None else f"; the recorder process's start-up and idle CPU "
                                                  f"{startup_s:.2f} s once per simulation process"))
    console.print(f"the Foxglove scene topics: overhead {100 * overhead['wall_no_scene']:.1f} % without them "
                  f"(wall); the simulation process's CPU {100 * overhead['cpu_sim_process']:.1f} % over an unrecorded "
                  f"run with them, {100 * overhead['cpu_sim_process_no_scene']:.1f} % without")
    console.print(f"every topic JSON (logs before the binary payloads, DEFT_GYM_LOG_ENCODING=json): CPU "
                  f"{100 * overhead['cpu_both_json_log']:+.1f} % {_interval_text(ci['cpu_both_json_log'], args.repeats)} "
                  f"(both processes); JSON encoding alone (every payload "
                  f"JSON-encoded, nothing written: the floor of a JSON log): CPU {100 * overhead['cpu_json_only']:+.1f} %")
    nodes = first["nodes"]
    wall0, sim0 = first["wall"], first["sim"]
    bt = Table(title="where the time goes (a recorded run with per-module timing)", title_justify="left")
    for c in ("module", "ms per sim s", "share"):
        bt.add_column(c, justify="right" if c != "module" else "left")
    for name, sec in sorted(nodes.items(), key=lambda kv: -kv[1]):
        bt.add_row(name, f"{1e3 * sec / sim0:.2f}", f"{100 * sec / wall0:.0f} %")
    rest = wall0 - sum(nodes.values())
    bt.add_row("bus, jitter, recording", f"{1e3 * rest / sim0:.2f}", f"{100 * rest / wall0:.0f} %")
    common.print_table(console, bt)
    if args.out:
        console.print(f"wrote {args.out}")
        write_atomic(Path(args.out), json.dumps({"median_speed": med, "ratio_vs_highway": ratio,
                                                 "recording_overhead": overhead,
                                                 "recording_overhead_95ci": ci,
                                                 "recorder_process_ms_per_sim_s": recorder_ms,
                                                 "unrecorded_ms_per_sim_s": sim_ms,
                                                 "recorder_process_startup_cpu_s": startup_s,
                                                 "planner_evaluation": evaluation,
                                                 "runs": {**runs, "breakdown": first}},
                                                indent=2))
    return 0


def recording_overhead(scenario: Any, repeats: int, progress: Any = None) -> dict[str, Any]:
    """CPU of both processes over the unrecorded run's, for binary and all-JSON logs written by
    the recorder process and for binary logs written in the simulation's process (``inline``,
    what a pool of simulation processes that fills the CPUs does): ``repeats`` quadruplets
    paired by jitter seed, their order rotated from one repeat to the next; per kind of log the
    median paired ratio and its bootstrap 95 % interval."""
    modes = [("unrecorded", None, None), ("binary", "process", None), ("json", "process", "json"),
             ("inline", "inline", None)]
    cpu: dict[str, list[float]] = {m: [] for m, _, _ in modes}
    stack_speed(scenario, "process", seed=repeats)  # warm-up (caches, the recorder process), not timed
    for i in range(repeats):
        for name, recorder, encoding in modes[i % len(modes):] + modes[:i % len(modes)]:
            r = stack_speed(scenario, recorder, seed=i, encoding=encoding)
            cpu[name].append(r["cpu"] + r["recorder_cpu"])
        if progress is not None:
            progress()
    out: dict[str, Any] = {"repeats": repeats, "cpu_s": cpu}
    for name in ("binary", "json", "inline"):
        out[name] = paired_overhead(cpu[name], cpu["unrecorded"])
    out["binary_lower_in"] = sum(b < j for b, j in zip(cpu["binary"], cpu["json"], strict=True))
    return out


def _recording_only(sc: Any, args: Any, console: Any) -> int:
    with common.bar(args, args.repeats, "recording quadruplets") as bar:
        res = recording_overhead(sc, args.repeats, bar.update)
    for name, what in (("binary", "binary payloads (the default), recorder process"),
                       ("json", "every topic JSON, recorder process"),
                       ("inline", "binary payloads, written in the simulation's process (a pool filling the CPUs)")):
        console.print(f"[bold]recording CPU, {what}: {100 * res[name]['median']:+.1f} %[/bold] "
                      f"{_interval_text(res[name]['ci95'], args.repeats)}", highlight=False)
    console.print(f"binary below JSON in {res['binary_lower_in']} of {args.repeats} pairs; target <= 10 % CPU",
                  highlight=False)
    if args.out:
        write_atomic(Path(args.out), json.dumps(res, indent=2))
        console.print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
