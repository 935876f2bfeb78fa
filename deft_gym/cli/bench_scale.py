"""Scaling of a campaign over workers and backends (issue 21's figure).

    python -m deft_gym.cli.bench_scale --workers 1,2 --backends local,ray
    python -m deft_gym.cli.bench_scale --campaign calibrate --workers 1,2,4,8,16   # the 256-run calibration

Runs the same campaign - the adversary evaluation (``evaluate``, default) or the calibration
(``calibrate``: issue 21's 256 runs) - once per backend and worker count, each in a fresh
interpreter (start-up, Ray's included, is part of the figure), and prints wall time, throughput
[simulated scenarios/s], speed-up and efficiency against one worker of the same backend, the
time the items themselves took (wall and, for the evaluation, CPU, summed over items: when it
grows with workers, the cores are shared with something else), the load average, and the fit
``T = a + b/W`` (``a``: what stays serial). It also checks that every run wrote the same
records (timings aside) and measures the driver's cost per item of each backend (an empty item).
Writes ``OUT/scale.json``.
"""

from __future__ import annotations

import argparse
import operator
import os
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
            "--brakes", "3", "--reruns", str(a.reruns), "--workers", str(workers), "--out", str(out), *ray]


def driver_cost(backend: Backend, n: int) -> float:
    """[ms] the driver's time per item: ``n`` empty items, after start-up."""
    with Executor(backend) as ex:
        list(ex.map(operator.pos, range(4 * backend.workers)))  # start the workers
        t0 = time.perf_counter()
        list(ex.map(operator.pos, range(n)))
        return (time.perf_counter() - t0) / n * 1000


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
    env = {**os.environ, "RAY_DEDUP_LOGS": "1"}
    print(f"{a.campaign}: {os.cpu_count()} CPUs here; each run in a fresh interpreter")
    print(f"{'backend':8s} {'workers':>7s} {'wall [s]':>9s} {'items':>6s} {'items/s':>8s} {'speed-up':>8s} "
          f"{'efficiency':>10s} {'items [s]':>10s} {'CPU [s]':>9s} {'load':>5s}")
    for backend in backends:
        for w in counts:
            out = a.out / f"{a.campaign}-{backend}-{w}"
            if out.exists():
                import shutil

                shutil.rmtree(out)
            t0 = time.perf_counter()
            proc = subprocess.run(campaign_command(a.campaign, out, w, backend, a), capture_output=True, text=True,
                                  env=env)
            wall = time.perf_counter() - t0
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
            row = {"backend": backend, "workers": w, "wall_s": round(wall, 2), "items": len(recs),
                   "items_per_s": round(len(recs) / wall, 3), "same_records": recs == reference,
                   "item_wall_s": round(item_wall, 2), "item_cpu_s": round(item_cpu, 2) if item_cpu else None,
                   "load_average": os.getloadavg()[0]}
            if base is not None:
                row["speedup"] = round(base["wall_s"] / wall, 3)
                row["efficiency"] = round(base["wall_s"] / (w * wall), 3)
            rows.append(row)
            print(f"{backend:8s} {w:7d} {wall:9.1f} {len(recs):6d} {row['items_per_s']:8.2f} "
                  f"{row.get('speedup', 1.0):8.2f} {row.get('efficiency', 1.0):10.0%} {item_wall:10.1f} "
                  f"{item_cpu or float('nan'):9.1f} {row['load_average']:5.1f}", flush=True)
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
    costs = {}
    for backend in backends:
        costs[backend] = round(driver_cost(Backend(backend, max(2, max(counts))), 400), 3)
        print(f"{backend}: the driver's cost per item {costs[backend]:.2f} ms (400 empty items, after start-up)")
    same = all(r["same_records"] for r in rows)
    print(f"records identical on every backend and worker count (timings aside): {'yes' if same else 'NO'}")
    write_json_atomic(a.out / "scale.json", {"campaign": a.campaign, "cpus": os.cpu_count(), "runs": rows,
                                             "fit": fits, "driver_ms_per_item": costs, "same_records": same,
                                             "command": " ".join(sys.argv)})
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
