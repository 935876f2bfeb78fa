"""Scaling of a campaign over workers and backends (issue 21's figure).

    python -m deft_gym.cli.bench_scale --workers 1,2 --backends local,ray
    python -m deft_gym.cli.bench_scale --campaign calibrate --workers 1,2,4,8,16   # the 256-run calibration

Runs the same campaign - the adversary evaluation (``evaluate``, default) or the calibration
(``calibrate``: issue 21's 256 runs) - once per backend and worker count, each in a fresh
interpreter (start-up, Ray's included, is part of the figure), and prints wall time, throughput
[simulated scenarios/s], speed-up and efficiency against one worker of the same backend, the
time the items themselves took (wall and CPU, summed over items: when it grows with workers, the
cores are shared with something else), the load average, and the fit ``T = a + b/W`` (``a``:
what stays serial). It also checks that every run wrote the same records (timings aside: the
calibration gets fixed jitter seeds, ``--jitter-seed``) and measures the driver's cost per item
of each backend (an empty item).

The serial part from CPU times, which a loaded machine measures where wall times do not: a
run's CPU (``getrusage`` of its process tree) less the CPU of its items is the driver's and the
start-up's; its share of the run's CPU is the serial share ``s`` of Amdahl's law, and the
efficiency at ``W`` workers it implies is ``1 / (s W + 1 - s)``. Scaled to a campaign of
``--eval-minutes`` of item CPU (default 10): the start-up once, the driver's part per item.
Where a run's process tree shows less CPU than its items took (Ray's workers outside it), no
share is given. An item's CPU that grows with workers (cores that share caches, memory or an SMT
sibling) bounds the efficiency apart from Amdahl: the ratio at the most workers is printed, and
the prediction divided by it. Writes ``OUT/scale.json``.
"""

from __future__ import annotations

import argparse
import operator
import os
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from deft_gym.cli import common
from deft_gym.execution import Backend, Executor, ray_installed, without_timings
from deft_gym.files import read_jsonl, write_json_atomic

EVAL_SCENARIOS = "lane_follow_static,left_turn,take_exit,u_turn"
CAL_SCENARIOS = ["take_exit", "blocked_red_light", "lane_follow_static", "left_turn"]


def campaign_command(campaign: str, out: Path, workers: int, backend: str, a: argparse.Namespace) -> list[str]:
    """The command line of one run."""
    ray = ["--ray"] if backend == "ray" else []
    if campaign == "evaluate":
        return [sys.executable, "-m", "agents.evaluate", "--methods", "random,random_delta", "--budget", str(a.budget),
                "--repeats", str(a.repeats), "--scenarios", a.scenarios or EVAL_SCENARIOS, "--held-out", "0",
                "--placements", "closest", "--seed", "0", "--no-progress", "--workers", str(workers),
                "--out", str(out), *ray]
    scen = [f"configs/scenarios/{s}.yaml" for s in (a.scenarios.split(",") if a.scenarios else CAL_SCENARIOS)]
    return [sys.executable, "-m", "deft_gym.cli.calibrate", "--scenarios", *scen, "--variants", "2", "--cut-ins", "3",
            "--brakes", "3", "--reruns", str(a.reruns), "--jitter-seed", str(a.jitter_seed), "--workers", str(workers),
            "--out", str(out), *ray]


def driver_cost(backend: Backend, n: int) -> tuple[float, float]:
    """[ms] the driver's wall time and CPU time (its own and its workers') per item: ``n`` empty
    items, after start-up."""
    with Executor(backend) as ex:
        list(ex.map(operator.pos, range(4 * backend.workers)))  # start the workers
        t0, c0 = time.perf_counter(), _tree_cpu(children_running=True)
        list(ex.map(operator.pos, range(n)))
        return (time.perf_counter() - t0) / n * 1000, (_tree_cpu(children_running=True) - c0) / n * 1000


def _become_subreaper() -> bool:
    """Make this process the reaper of its orphaned descendants (Linux), so that the CPU of a
    run's whole process tree - a forkserver's workers outlive their parent's wait - reaches
    ``RUSAGE_CHILDREN`` once :func:`_reap_orphans` waits for them."""
    try:
        import ctypes

        return ctypes.CDLL(None, use_errno=True).prctl(36, 1, 0, 0, 0) == 0  # PR_SET_CHILD_SUBREAPER
    except (OSError, AttributeError):
        return False


def _reap_orphans(timeout: float = 30.0) -> None:
    """Wait for the descendants left over from a run (reparented here): their CPU then counts."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            pid, _ = os.waitpid(-1, os.WNOHANG)
        except ChildProcessError:
            return
        if pid == 0:
            time.sleep(0.05)


def _tree_cpu(children_running: bool = False) -> float:
    """[s] CPU time of this process and of its children that have ended (with
    ``children_running``: this process only, the workers' share read from /proc where it can be)."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    total = own.ru_utime + own.ru_stime
    if not children_running:
        kids = resource.getrusage(resource.RUSAGE_CHILDREN)
        return total + kids.ru_utime + kids.ru_stime
    tick = os.sysconf("SC_CLK_TCK")
    for pid in _child_pids(os.getpid()):
        try:
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
            total += (int(fields[11]) + int(fields[12])) / tick
        except (OSError, IndexError, ValueError):
            continue
    return total


def _child_pids(pid: int) -> list[int]:
    """This process's children (Linux /proc; none elsewhere)."""
    try:
        return [int(c) for t in Path(f"/proc/{pid}/task").iterdir()
                for c in (t / "children").read_text().split()]
    except OSError:
        return []


UNSEEN_CPU = 0.98  # a run's process tree below this share of its items' CPU did not see all of it


def cpu_growth(rows: list[dict[str, Any]]) -> tuple[int, float] | None:
    """``(W, ratio)``: an item's CPU at the most workers ``W`` over its CPU at the fewest (rows of
    one backend with item CPU); None with fewer than two worker counts. Above 1 where the workers
    share cores (caches, memory bandwidth, SMT siblings): efficiency is then at most 1 / ratio."""
    if len({r["workers"] for r in rows}) < 2:
        return None
    lo, hi = min(rows, key=lambda r: r["workers"]), max(rows, key=lambda r: r["workers"])
    per_item = [r["item_cpu_s"] / max(1, r["items"]) for r in (lo, hi)]
    return hi["workers"], per_item[1] / per_item[0]


def amdahl(serial_share: float, workers: int) -> float:
    """Efficiency at ``workers`` workers of a campaign whose serial share is ``serial_share``."""
    return 1.0 / (serial_share * workers + 1.0 - serial_share)


def main(argv: list[str] | None = None) -> int:
    ap = common.parser("bench-scale", "deft_gym.cli.bench_scale", __doc__)
    ap.add_argument("--campaign", choices=("evaluate", "calibrate"), default="evaluate", help="campaign to scale")
    ap.add_argument("--workers", default="1,2", help="comma-separated worker counts")
    ap.add_argument("--backends", default="local,ray", help="comma-separated, of local,ray")
    ap.add_argument("--budget", type=common.int_range(1, 100_000), default=4, help="evaluate: scenarios per job")
    ap.add_argument("--repeats", type=common.int_range(1, 1000), default=2, help="evaluate: repeats")
    ap.add_argument("--reruns", type=common.int_range(1, 10_000), default=8,
                    help="calibrate: reruns per variant (8: 256 runs)")
    ap.add_argument("--scenarios", default=None, help="comma-separated seed scenarios (default: four)")
    ap.add_argument("--jitter-seed", type=common.int_range(0, 2**63 - 1), default=1000,
                    help="calibrate: jitter seed of each scenario's first run (default: 1000; the same for every run, "
                         "so the records can be compared)")
    ap.add_argument("--eval-minutes", type=common.finite_float(0.1, 1e6), default=10.0,
                    help="the campaign size [min of item CPU] the serial share is scaled to (default: 10)")
    common.add_out(ap, common.RUNS / "bench_scale")
    common.add_output_flags(ap)
    a = ap.parse_args(argv)
    a.out = Path(a.out)
    try:
        counts = [int(w) for w in a.workers.split(",")]
        assert counts and min(counts) >= 1
    except (ValueError, AssertionError):
        print(f"error: --workers: expected comma-separated counts >= 1, got {a.workers!r}", file=sys.stderr)
        return 2
    backends = [b.strip() for b in a.backends.split(",") if b.strip()]
    if not backends or any(b not in ("local", "ray") for b in backends):
        print(f"error: --backends: expected some of local,ray, got {a.backends!r}", file=sys.stderr)
        return 2
    if "ray" in backends and not ray_installed():
        print("error: --backends: ray needs Ray: pip install 'deft-gym[ray]'", file=sys.stderr)
        return 2
    with common.locked_out(a.out):
        return _scale(a, counts, backends)


def _scale(a: Any, counts: list[int], backends: list[str]) -> int:
    rows: list[dict[str, Any]] = []
    reference = None
    if not _become_subreaper():
        print("note: not a subreaper here (not Linux?): the CPU of workers that outlive their parent is missed")
    env = {**os.environ, "RAY_DEDUP_LOGS": "1"}
    print(f"{a.campaign}: {os.cpu_count()} CPUs here; each run in a fresh interpreter")
    print(f"{'backend':8s} {'workers':>7s} {'wall [s]':>9s} {'items':>6s} {'items/s':>8s} {'speed-up':>8s} "
          f"{'efficiency':>10s} {'items [s]':>10s} {'items CPU':>9s} {'run CPU':>8s} {'serial':>7s} {'load':>5s}")
    for backend in backends:
        for w in counts:
            out = a.out / f"{a.campaign}-{backend}-{w}"
            if out.exists():
                import shutil

                shutil.rmtree(out)
            t0, c0 = time.perf_counter(), _tree_cpu()
            proc = subprocess.run(campaign_command(a.campaign, out, w, backend, a), capture_output=True, text=True,
                                  env=env)
            wall = time.perf_counter() - t0
            _reap_orphans()
            run_cpu = _tree_cpu() - c0  # the run's process tree, all of it
            if proc.returncode != 0:
                print(proc.stdout[-2000:], proc.stderr[-3000:], file=sys.stderr)
                print(f"error: the {backend} run with {w} workers failed", file=sys.stderr)
                return 1
            raw = read_jsonl(out / ("records.jsonl" if a.campaign == "evaluate" else "runs.jsonl"))
            recs = without_timings(raw)
            reference = recs if reference is None else reference
            # [s] what the items themselves took: CPU (evaluate records it) and wall, summed over items
            item_cpu = sum(r.get("cpu_seconds", 0.0) for r in raw)
            item_wall = sum(r.get("seconds", r.get("wall_time", 0.0)) for r in raw)
            base = next((r for r in rows if r["backend"] == backend and r["workers"] == 1), None)
            # the serial part: the run's CPU that no item took (driver, start-up of the program, the
            # workers and their recorder processes), as a share of the run's CPU
            serial_cpu = max(0.0, run_cpu - item_cpu)
            # a tree that shows less CPU than its items took did not see all of its processes (Ray's
            # raylet starts the workers, outside it on some machines): no serial share from it
            seen = run_cpu >= UNSEEN_CPU * item_cpu
            row = {"backend": backend, "workers": w, "wall_s": round(wall, 2), "items": len(recs),
                   "items_per_s": round(len(recs) / wall, 3), "same_records": recs == reference,
                   "item_wall_s": round(item_wall, 2), "item_cpu_s": round(item_cpu, 2) if item_cpu else None,
                   "run_cpu_s": round(run_cpu, 2), "serial_cpu_s": round(serial_cpu, 2) if seen else None,
                   "serial_share": round(serial_cpu / run_cpu, 4) if run_cpu > 0 and item_cpu and seen else None,
                   "load_average": os.getloadavg()[0]}
            if base is not None:
                row["speedup"] = round(base["wall_s"] / wall, 3)
                row["efficiency"] = round(base["wall_s"] / (w * wall), 3)
            rows.append(row)
            print(f"{backend:8s} {w:7d} {wall:9.1f} {len(recs):6d} {row['items_per_s']:8.2f} "
                  f"{row.get('speedup', 1.0):8.2f} {row.get('efficiency', 1.0):10.0%} {item_wall:10.1f} "
                  f"{item_cpu:9.1f} {run_cpu:8.1f} "
                  f"{format(row['serial_share'], '7.1%') if row['serial_share'] is not None else '    n/a'} "
                  f"{row['load_average']:5.1f}", flush=True)
    fits = {}
    for backend in backends:
        pts = [(r["workers"], r["wall_s"]) for r in rows if r["backend"] == backend]
        if len(pts) >= 2:  # least squares of T = a + b / W
            import numpy as np

            x = np.array([[1.0, 1.0 / w] for w, _ in pts])
            (ser, par), *_ = np.linalg.lstsq(x, np.array([t for _, t in pts]), rcond=None)
            fits[backend] = {"serial_s": round(float(ser), 2), "parallel_s": round(float(par), 2)}
            if par <= 0:  # more workers were not faster: no serial share to speak of
                fits[backend]["note"] = "wall time did not fall with workers"
                print(f"{backend}: no fit of T = a + b / W: the wall time did not fall with workers (where the "
                      f"items' wall time grows and their CPU time does not, the cores are shared: see the load)")
                continue
            print(f"{backend}: T = {ser:.1f} s + {par:.1f} s / W  (serial share {ser / (ser + par):.0%} at W = 1)")
    costs, amdahl_fits = {}, {}
    for backend in backends:
        wall_ms, cpu_ms = driver_cost(Backend(backend, max(2, max(counts))), 400)
        costs[backend] = {"wall_ms": round(wall_ms, 3), "cpu_ms": round(cpu_ms, 3)}
        print(f"{backend}: the driver's cost per item {wall_ms:.2f} ms wall, {cpu_ms:.2f} ms CPU (400 empty items, "
              f"after start-up)")
        # Amdahl from CPU times: the serial CPU of the one-worker run (or the fewest workers) is
        # start-up (once) + the driver's CPU per item; scaled to --eval-minutes of item CPU
        mine = [r for r in rows if r["backend"] == backend and r["item_cpu_s"]]
        growth = cpu_growth(mine)
        one = min((r for r in mine if r["serial_share"] is not None), key=lambda r: r["workers"], default=None)
        if one is None:
            if mine:
                first = min(mine, key=lambda r: r["workers"])
                amdahl_fits[backend] = {"note": "serial share not measured: the run's process tree showed less "
                                                "CPU than its items took"}
                print(f"{backend}: serial share from CPU not measured: the run's process tree showed "
                      f"{first['run_cpu_s']:.1f} CPU s, its items {first['item_cpu_s']:.1f} (the workers ran "
                      f"outside it: Ray's raylet starts them); the wall-time fit above stands")
            continue
        per_item_cpu = one["item_cpu_s"] / max(1, one["items"])
        startup = max(0.0, one["serial_cpu_s"] - cpu_ms / 1000 * one["items"])
        items_eval = 60.0 * a.eval_minutes / per_item_cpu
        serial_eval = startup + cpu_ms / 1000 * items_eval
        share_eval = serial_eval / (serial_eval + 60.0 * a.eval_minutes)
        # each worker's start-up (parallel, but CPU no item gets): the growth of the serial CPU
        # from the fewest workers to the next count
        two = sorted((r for r in mine if r["serial_share"] is not None), key=lambda r: r["workers"])[:2]
        per_worker = (max(0.0, (two[1]["serial_cpu_s"] - two[0]["serial_cpu_s"]) / (two[1]["workers"] - two[0]["workers"]))
                      if len(two) == 2 else 0.0)
        total_eval = serial_eval + 60.0 * a.eval_minutes

        def with_workers(n: int, total: float = total_eval, serial: float = serial_eval, pw: float = per_worker) -> float:
            return total / (n * (serial + (total - serial) / n + pw))

        amdahl_fits[backend] = {
            "worker_startup_cpu_s": round(per_worker, 2),
            "efficiency_with_worker_startup": {str(n): round(with_workers(n), 4) for n in (16, 64)},
            "measured_serial_share": one["serial_share"], "workers_of_measurement": one["workers"],
            "startup_cpu_s": round(startup, 2), "driver_cpu_ms_per_item": round(cpu_ms, 3),
            "item_cpu_s": round(per_item_cpu, 3), "eval_minutes": a.eval_minutes,
            "serial_share_eval": round(share_eval, 5),
            "efficiency": {str(n): round(amdahl(share_eval, n), 4) for n in (2, 4, 8, 16, 32, 64)},
            "efficiency_measured_share": {str(n): round(amdahl(one["serial_share"], n), 4) for n in (16, 64)}}
        print(f"{backend}: serial share from CPU {one['serial_share']:.1%} of this run ({one['serial_cpu_s']:.1f} of "
              f"{one['run_cpu_s']:.1f} CPU s at {one['workers']} worker(s): start-up {startup:.1f} s, driver "
              f"{cpu_ms:.2f} ms per item); for {a.eval_minutes:g} min of item CPU ({items_eval:.0f} items of "
              f"{per_item_cpu:.2f} s) {share_eval:.2%}: Amdahl efficiency {amdahl(share_eval, 16):.0%} at 16 workers, "
              f"{amdahl(share_eval, 64):.0%} at 64 (this run's share: {amdahl(one['serial_share'], 16):.0%}, "
              f"{amdahl(one['serial_share'], 64):.0%}); with each worker's start-up ({per_worker:.1f} CPU s) "
              f"{with_workers(16):.0%} at 16, {with_workers(64):.0%} at 64")
        if growth is not None:
            top, ratio = growth
            eval_top = amdahl(share_eval, top) / ratio
            amdahl_fits[backend]["item_cpu_growth"] = {"workers": top, "ratio": round(ratio, 4),
                                                      "efficiency_eval": round(eval_top, 4)}
            measured = next(r.get("efficiency") for r in mine if r["workers"] == top)  # None without a 1-worker run
            print(f"{backend}: an item's CPU at {top} workers is {ratio - 1:+.0%} of its CPU at "
                  f"{min(r['workers'] for r in mine)} (cores shared: caches, memory, SMT): at {top} workers this run "
                  f"measured {'-' if measured is None else format(measured, '.0%')}, its share and that growth predict "
                  f"{amdahl(one['serial_share'], top) / ratio:.0%}; {a.eval_minutes:g} min of item CPU at {top} "
                  f"workers: {eval_top:.0%}")
    same = all(r["same_records"] for r in rows)
    print(f"records identical on every backend and worker count (timings aside): {'yes' if same else 'NO'}")
    write_json_atomic(a.out / "scale.json", {"campaign": a.campaign, "cpus": os.cpu_count(), "runs": rows,
                                             "fit": fits, "driver_per_item": costs, "amdahl": amdahl_fits,
                                             "same_records": same,
                                             "command": " ".join(sys.argv)})
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
