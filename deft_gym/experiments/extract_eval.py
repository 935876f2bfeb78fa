"""Reproduce the DeFT paper's research questions on this testbed.

    deft-gym extract-eval --out runs/extract/eval                      # all seed scenarios
    deft-gym extract-eval --scenarios left_turn u_turn --cut-ins 4 --reruns 10 --out DIR

Scenario pool: every seed scenario plus ``--variants`` perturbations and ``--cut-ins`` cut-in
variants of it (:mod:`deft_gym.scenarios.variants`), like the output of a test generator. Each scenario
is run once (S0, logged, planning outputs carrying their input headers so that all three modes
can be extracted from the same log; the heuristic and last modes never read them) and then
``--reruns - 1`` more times (S1..S9). Then:

- RQ1 (Table 3): planning outputs reproduced by the module tests of each mode vs by each
  system rerun (i-th output of S_k against the i-th of S0, lock-step), at theta = 0, 0.1, 0.23,
  1.62, 6.99, 17.15 m.
- RQ2 (Figure 7): for scenarios whose S0 collided, collisions reproduced by each rerun vs
  failure tests failing in each of ``--test-runs`` executions of the generated module tests.
- RQ3 (Tables 4-6): extraction ms/frame (planner vs overhead) per mode, module-test execution
  time vs system-test time, and time-to-reproduce-failure (TTRF) of system reruns vs module
  tests. System reruns and module-test executions are timed interleaved, in this process and
  in pytest subprocesses respectively, both after imports (warm), so that machine load hits
  both alike.

Writes ``DIR/report.md``, ``DIR/results.json`` and plots; intermediate results are appended to
``DIR/records/*.jsonl`` so an interrupted run resumes where it stopped. An S0 log that is not
intact (a chunk failing its CRC, missing messages) is named in the headline and in
``results.json`` (``damaged_logs``), and the exit status is 1.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib.util
import json
import os
import shutil
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from deft_gym.bus.ads import load_ads_config
from deft_gym.cli import common
from deft_gym.config import ConfigError
from deft_gym.execution import Backend, Executor, Record, add_backend_arguments, backend_from_args
from deft_gym.experiments.extract_report import write_report
from deft_gym.experiments.record import ads_overrides
from deft_gym.files import write_atomic
from deft_gym.planner.trajectory import lsed
from deft_gym.record.recorder import init_pool_worker
from extract.batch import extract_directory
from extract.runtime import load_frames, make_planner, replay
from extract.validator import distance

# the parser and the program are this one module; the scenarios and the simulation are imported
# where they are used, so that --help and bad input are answered before they load
MODES = ("heuristic", "last", "headers")  # extract.search.MODES (checked by tests/cli/test_cli.py)
RQ1_THETAS = (0.0, 0.1, 0.23, 1.62, 6.99, 17.15)
FAILURE_K = "does_not_plan_into_collision"


# -- scenario pool -------------------------------------------------------------------------------
def scenario_pool(seeds: list[str], variants: int, cut_ins: int, extra: int = 0
                  ) -> tuple[list[tuple[str, dict[str, Any]]], list[tuple[str, dict[str, Any]]]]:
    """``(group, scenario dict)`` lists: the pool (each seed scenario, its perturbations and its
    first ``cut_ins`` cut-ins) and ``extra`` further cut-ins per seed, which join the evaluation
    only when their S0 collides (as a test generator reports the failures it finds)."""
    from deft_gym.scenarios.scenario import load_scenario, scenario_to_dict
    from deft_gym.scenarios.variants import inject_cut_in, perturb
    from deft_gym.sim.simulation import reference_path

    pool, more = [], []
    for path in seeds:
        sc = load_scenario(path)
        group = sc.name
        items = [sc] + [perturb(sc, seed=v) for v in range(1, variants + 1)]
        ref = reference_path(sc) if cut_ins or extra else None
        items += [inject_cut_in(sc, ref, seed=c) for c in range(cut_ins)]
        pool += [(group, scenario_to_dict(v)) for v in items]
        more += [(group, scenario_to_dict(inject_cut_in(sc, ref, seed=c))) for c in range(cut_ins, cut_ins + extra)]
    return pool, more


def _dirname(name: str) -> str:
    return name.replace("~", "-")


def _plans(planning: list[dict[str, Any]]) -> list[dict[str, list[float]]]:
    return [{k: p["trajectory"][k] for k in ("t", "x", "y")} for p in planning]


def pin_planner(out: Path) -> tuple[str, str]:
    """Copy the default planner's source into ``out/pinned`` under a unique module name and make
    it importable here, in spawned workers and in pytest subprocesses (``PYTHONPATH`` and a
    ``conftest.py``): every run, extraction and test of one evaluation uses the same planner
    even while its source is being edited. Returns ``(class path, sha256)``."""
    pinned = out / "pinned"
    record = pinned / "planner.json"
    if record.exists():  # resuming: keep the planner the evaluation started with
        pin = json.loads(record.read_text())
        module, name, digest = pin["module"], pin["name"], pin["sha256"]
    else:
        cls_path = load_ads_config().planning.planner.cls
        mod, _, name = cls_path.partition(":")
        spec = importlib.util.find_spec(mod)
        if spec is None or spec.origin is None:
            raise SystemExit(f"cannot locate the planner module {mod!r}")
        src = Path(spec.origin).read_bytes()
        digest = hashlib.sha256(src).hexdigest()
        module = f"deft_eval_planner_{digest[:10]}"
        write_atomic(pinned / f"{module}.py", src)
        write_atomic(record, json.dumps({"module": module, "name": name, "sha256": digest, "source": spec.origin}))
    if str(pinned) not in sys.path:
        sys.path.insert(0, str(pinned))
    os.environ["PYTHONPATH"] = os.pathsep.join([str(pinned), *filter(None, [os.environ.get("PYTHONPATH")])])
    conftest = ("# makes the planner pinned by the evaluation importable for its generated tests\n"
                f"import sys\n\nsys.path.insert(0, {str(pinned)!r})\n")
    write_atomic(out / "conftest.py", conftest)
    return f"{module}:{name}", digest


def _timed_run(data: dict[str, Any], seed: int, out_dir: str | None, headers: bool,
               planner: str | None = None) -> tuple[Any, float]:
    """One system-level run, timed from construction to the end (log closed)."""
    from deft_gym.scenarios.scenario import scenario_from_dict
    from deft_gym.sim.simulation import Simulation

    sc = scenario_from_dict(data, source=data["name"])
    ads = load_ads_config(None, ads_overrides(headers=headers, planner_class=planner) or None)
    t0 = time.perf_counter()
    res = Simulation(sc, ads, jitter_seed=seed, out_dir=out_dir).run()
    return res, time.perf_counter() - t0


def _s0_job(args: tuple[str, dict[str, Any], int, str, str | None]) -> dict[str, Any]:
    group, data, seed, out_dir, planner = args
    res, wall = _timed_run(data, seed, out_dir, headers=True, planner=planner)
    s = res.summary()
    plans = _plans(res.planning)
    write_atomic(Path(out_dir) / "plans.json", json.dumps(plans))
    return {"name": data["name"], "group": group, "seed": seed, "outcome": s["outcome"],
            "collision": s["collision_detail"], "wall": wall, "sim_time": s["sim_time"],
            "outputs": len(plans), "log": s["log"]}


def _compare(ref: list[dict[str, Any]], plans: list[dict[str, Any]]) -> dict[str, Any]:
    """Lock-step LSED of a rerun's outputs against S0's: counts within each RQ1 threshold."""
    d = np.array([lsed(a, b) for a, b in zip(ref, plans)]) if ref and plans else np.zeros(0)
    q = np.percentile(d, [0, 25, 50, 75, 100]).tolist() if d.size else [None] * 5
    return {"pairs": int(d.size), "within": {f"{t:g}": int((d <= t).sum()) for t in RQ1_THETAS},
            "quantiles": q, "mean": float(d.mean()) if d.size else None}


def _rerun_job(args: tuple[str, dict[str, Any], int, int, str, str | None]) -> dict[str, Any]:
    name, data, k, seed, ref_path, planner = args
    res, wall = _timed_run(data, seed, None, headers=False, planner=planner)
    ref = json.loads(Path(ref_path).read_text())
    coll = res.outcome.collision
    return {"name": name, "k": k, "seed": seed, "outcome": res.outcome.outcome, "wall": wall,
            "sim_time": res.sim_time, "collision": coll.participant if coll else None,
            **_compare(ref, _plans(res.planning))}


# -- the evaluation ------------------------------------------------------------------------------
class _NoProgress:
    """What ``--no-progress`` gets in place of a rich Progress."""

    def __enter__(self) -> _NoProgress:
        return self

    def __exit__(self, *exc: Any) -> None:
        return None

    def add_task(self, *a: Any, **k: Any) -> int:
        return 0

    def advance(self, *a: Any, **k: Any) -> None:
        return None

    def update(self, *a: Any, **k: Any) -> None:
        return None


class Evaluation:
    """All phases; each skips what its records already hold."""

    def __init__(self, args: argparse.Namespace, console: Any, executor: Executor | None = None) -> None:
        self.args, self.console = args, console
        self.out = Path(args.out).resolve()
        self.out.mkdir(parents=True, exist_ok=True)
        # records (append-only, resumable): appended as work finishes, read on restart
        self.s0, self.reruns, self.rounds, self.full, self.replays = (
            Record(self.out / "records" / f"{name}.jsonl")
            for name in ("s0", "reruns", "module_rounds", "module_full", "replay_check"))
        self.planner, self.planner_sha = pin_planner(self.out) if args.pin_planner else (None, None)
        self.ex = executor or Executor(Backend("local", args.workers), initializer=init_pool_worker,
                                       initargs=(args.workers,), run_dir=self.out)

    def progress(self) -> Any:
        return common.rich_progress(self.console) if common.show_progress(self.args) else _NoProgress()

    def _pool_map(self, fn: Callable[[Any], dict[str, Any]], jobs: list[Any], desc: str,
                  sink: Callable[[dict[str, Any]], None], **files: Any) -> None:
        """``fn`` over ``jobs`` on the executor, rows to ``sink`` in job order (``files``:
        :meth:`deft_gym.execution.Executor.map`'s ``artifacts`` and ``inputs``)."""
        if not jobs:
            return
        with self.progress() as prog:
            task = prog.add_task(desc, total=len(jobs))
            for row in self.ex.map(fn, jobs, progress=lambda n: prog.advance(task, n), **files):
                sink(row)

    # phase 1: S0 of every scenario (logged, with input headers)
    def run_s0(self, pool: list[tuple[str, dict[str, Any]]], extra: bool = False) -> None:
        """S0 runs; with ``extra``, a run without a collision is dropped (its log deleted)."""
        done = self.s0.keys("name")
        jobs = [(g, d, self.args.jitter_seed, str(self.out / "runs" / _dirname(d["name"]) / "S0"), self.planner)
                for g, d in pool if (d["name"],) not in done]

        def keep(row: dict[str, Any]) -> None:
            if extra:
                row["extra"] = True
                if not row["collision"]:
                    row["dropped"] = True
                    shutil.rmtree(Path(row["log"]).parent.parent, ignore_errors=True)
            self.s0.add(row)

        self._pool_map(_s0_job, jobs, "S0 runs" + (" (extra cut-ins)" if extra else ""), keep,
                       artifacts=lambda j: [j[3]])

    def evaluated(self) -> set[str]:
        """Names of the scenarios in the evaluation (extra ones only when they collided)."""
        return {r["name"] for r in self.s0.rows if not r.get("dropped")}

    # phase 2: extraction in every mode
    def extract(self) -> None:
        for mode in self.args.modes:
            with self.progress() as prog:
                task = prog.add_task(f"extract ({mode})", total=len(self.s0.rows))

                def tick(_: Any, prog: Any = prog, task: Any = task) -> None:
                    prog.advance(task)

                extract_directory(self.out / "runs", self.out / "deft" / mode, mode=mode, workers=self.args.workers,
                                  on_episode=tick, executor=self.ex)

    def deft_dir(self, mode: str, name: str) -> Path:
        return self.out / "deft" / mode / _dirname(name) / "S0"

    def summary(self, mode: str, name: str) -> dict[str, Any]:
        return json.loads((self.deft_dir(mode, name) / "summary.json").read_text())

    # phase 3: reruns of scenarios without a collision in S0 (in parallel; RQ1 only)
    def rerun_others(self, pool: list[tuple[str, dict[str, Any]]]) -> None:
        done = self.reruns.keys("name", "k")
        colliding = {r["name"] for r in self.s0.rows if r["collision"]} | (
            {d["name"] for _, d in pool} - self.evaluated())
        jobs = [(d["name"], d, k, self.args.jitter_seed + k,
                 str(self.out / "runs" / _dirname(d["name"]) / "S0" / "plans.json"), self.planner)
                for _, d in pool if d["name"] not in colliding
                for k in range(1, self.args.reruns) if (d["name"], k) not in done]
        self._pool_map(_rerun_job, jobs, "reruns (no collision in S0)", self.reruns.add, inputs=lambda j: [j[4]])

    # phase 4: collision scenarios - reruns and module-test executions, interleaved and timed
    def collisions(self, pool: list[tuple[str, dict[str, Any]]]) -> None:
        data = {d["name"]: d for _, d in pool}
        names = self.evaluated()
        coll = [r["name"] for r in self.s0.rows if r["collision"] and r["name"] in names]
        done = self.reruns.keys("name", "k")
        n_rounds = max(self.args.test_runs, self.args.reruns - 1)
        dirs = [self.deft_dir(m, n) for m in self.args.modes for n in coll if (self.deft_dir(m, n)).exists()]
        covered: dict[int, set[str]] = defaultdict(set)
        for rec in self.rounds.rows:
            covered[rec["round"]].update(rec.get("dirs", []))
        with self.progress() as prog:
            task = prog.add_task("collision reruns + module-test runs", total=n_rounds)
            for k in range(1, n_rounds + 1):
                if k < self.args.reruns:
                    for name in coll:
                        if (name, k) not in done:
                            ref = self.out / "runs" / _dirname(name) / "S0" / "plans.json"
                            self.reruns.add(_rerun_job((name, data[name], k, self.args.jitter_seed + k, str(ref),
                                                        self.planner)))
                todo = [d for d in dirs if str(d) not in covered[k]]
                if k <= self.args.test_runs and todo:
                    self.rounds.add({"round": k, "dirs": list(map(str, todo)),
                                     **self._pytest(todo, f"round{k}-{len(covered[k])}", FAILURE_K)})
                prog.advance(task)
        done_full = {d for rec in self.full.rows for d in rec.get("dirs", [])}
        heur = [d for d in dirs if "/heuristic/" in str(d) and str(d) not in done_full]
        if heur:
            self.full.add({"dirs": list(map(str, heur)), **self._pytest(heur, f"full-{len(done_full)}", None)})

    def _pytest(self, dirs: list[Path], tag: str, keyword: str | None) -> dict[str, Any]:
        """Run the generated tests in a subprocess; per-test outcome and duration from JUnit XML."""
        xml = self.out / "records" / f"junit_{tag}.xml"
        cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-o", "addopts=",
               "--import-mode=importlib", f"--junitxml={xml}", *map(str, dirs)]
        if keyword:
            cmd += ["-k", keyword]
        # the tests import this extract (and deft_gym), not another installed copy
        root = str(Path(extract_directory.__code__.co_filename).resolve().parents[1])
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([root, *filter(None, [os.environ.get("PYTHONPATH")])])}
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True, cwd=self.out, env=env)
        wall = time.perf_counter() - t0
        cases = []
        root = ET.parse(xml).getroot() if xml.exists() else None
        for tc in (root.iter("testcase") if root is not None else []):
            status = "failed" if tc.find("failure") is not None or tc.find("error") is not None else (
                "skipped" if tc.find("skipped") is not None else "passed")
            cases.append({"file": tc.get("file") or tc.get("classname"), "name": tc.get("name"),
                          "time": float(tc.get("time") or 0.0), "status": status})
        return {"wall": wall, "returncode": proc.returncode, "cases": cases}

    # phase 5: replay every frames file through the runtime (what the tests do) and compare
    def replay_check(self) -> None:
        done = self.replays.keys("mode", "name")
        names = self.evaluated()
        for mode in self.args.modes:
            for r in self.s0.rows:
                if r["name"] not in names or (mode, r["name"]) in done or \
                        not (self.deft_dir(mode, r["name"]) / "frames.jsonl").exists():
                    continue
                header, frames = load_frames(self.deft_dir(mode, r["name"]) / "frames.jsonl")
                outs = replay(make_planner(header), frames)
                same = sum(1 for f, out in zip(frames, outs) if (f["distance"] if f["distance"] is not None else np.inf)
                           == distance(f["expected"], out, header["measure"]))
                self.replays.add({"mode": mode, "name": r["name"], "frames": len(frames), "same_distance": same})

    def cold_start(self) -> float:
        """Seconds a fresh interpreter needs to import the simulation stack (for 'cold' figures)."""
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-c", "import deft_gym.sim.simulation, deft_gym.planner.lattice, extract.runtime"],
                       check=True)
        return time.perf_counter() - t0


def _git_state() -> dict[str, Any]:
    """Commit and a digest of the uncommitted changes (provenance of the results)."""
    def git(*a: str) -> str:
        try:
            return subprocess.run(["git", *a], capture_output=True, text=True, check=True).stdout
        except (OSError, subprocess.CalledProcessError):
            return ""
    return {"commit": git("rev-parse", "HEAD").strip() or None,
            "diff_sha256": hashlib.sha256(git("diff").encode()).hexdigest()}


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = common.parser("extract-eval", "deft_gym.experiments.extract_eval", __doc__,
                       epilog="\n\n".join(__doc__.split("\n\n")[1:3]))
    common.add_scenarios(ap, help="seed scenarios (default: all in configs/scenarios except bench_*)")
    ap.add_argument("--variants", type=common.int_range(0, 10_000), default=1, help="perturbed variants per seed")
    ap.add_argument("--cut-ins", type=common.int_range(0, 10_000), default=8, help="cut-in variants per seed")
    ap.add_argument("--extra-cut-ins", type=common.int_range(0, 10_000), default=0,
                    help="further cut-ins per seed that join only when their S0 collides (default 0)")
    ap.add_argument("--reruns", type=common.int_range(2, 10_000), default=10, help="system runs per scenario incl. S0")
    ap.add_argument("--test-runs", type=common.int_range(1, 10_000), default=10,
                    help="executions of the generated tests")
    ap.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES), help="input-search modes")
    common.add_jitter_seed(ap, "S_k uses jitter seed S+k (a resumed evaluation keeps its seeds)")
    common.add_workers(ap, "parallel processes for S0, extraction, reruns")
    common.add_out(ap, common.RUNS / "extract" / "eval")
    ap.add_argument("--report-only", action="store_true", help="re-render report.md, results.json and plots "
                    "from the records of OUT")
    ap.add_argument("--no-pin-planner", dest="pin_planner", action="store_false",
                    help="use the planner module in place instead of a copy pinned at the start")
    add_backend_arguments(ap)
    common.add_watchdog(ap)
    common.add_output_flags(ap)
    args = ap.parse_args(argv)
    if args.reruns < 2:
        ap.error("--reruns must be at least 2 (S0 and one rerun)")
    if args.jitter_seed is None:  # resuming: the seed recorded there; else a fresh one
        try:
            args.jitter_seed = int(json.loads((Path(args.out) / "options.json").read_text())["jitter_seed"])
        except (OSError, ValueError, KeyError, TypeError):
            args.jitter_seed = common.fresh_seed()
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)  # --help and bad input answered here, before the simulation loads
    with common.watchdog_env(args), common.locked_out(args.out):
        return _main(args)


def _main(args: argparse.Namespace) -> int:
    from deft_gym.scenarios.scenario import list_scenarios

    console = common.console(args)
    Path(args.out).mkdir(parents=True, exist_ok=True)
    write_atomic(Path(args.out) / "options.json", json.dumps({"jitter_seed": args.jitter_seed}))
    seeds = args.scenarios or [str(p) for p in list_scenarios() if not p.name.startswith("bench")]
    t0 = time.perf_counter()
    ev = Evaluation(args, console)  # pins the planner first: Ray's workers import it from there
    try:
        backend = backend_from_args(args, args.workers)
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    with Executor(backend, initializer=init_pool_worker, initargs=(args.workers,), run_dir=ev.out) as ev.ex:
        return _run(args, console, ev, seeds, t0)


def _run(args: argparse.Namespace, console: Any, ev: Evaluation, seeds: list[str], t0: float) -> int:
    if args.report_only:
        previous = ev.out / "results.json"
        old = json.loads(previous.read_text()) if previous.exists() else {}
        results = write_report(ev, ev.evaluated(), old.get("cold_start_s") or ev.cold_start(),
                               old.get("elapsed_s", 0.0), old.get("provenance"))
        console.print(f"wrote {ev.out / 'report.md'} and {ev.out / 'results.json'} from the records")
        return 0
    console.print(f"building the scenario pool from {len(seeds)} seed scenario(s) ...")
    pool, more = scenario_pool(seeds, args.variants, args.cut_ins, args.extra_cut_ins)
    console.print(f"{len(pool)} scenarios (+{len(more)} candidates kept if they collide); S0 runs ...")
    ev.run_s0(pool)
    ev.run_s0(more, extra=True)
    pool += more
    names = ev.evaluated() & {d["name"] for _, d in pool}
    n_coll = sum(1 for r in ev.s0.rows if r["collision"] and r["name"] in names)
    console.print(f"{n_coll} of {len(names)} scenarios collided in S0; extracting ({', '.join(args.modes)}) ...")
    ev.extract()
    ev.rerun_others(pool)
    ev.collisions(pool)
    ev.replay_check()
    cold = ev.cold_start()
    previous = ev.out / "results.json"
    before = json.loads(previous.read_text()).get("elapsed_s", 0.0) if previous.exists() else 0.0
    results = write_report(ev, names, cold, before + time.perf_counter() - t0,
                           {"planner": ev.planner, "planner_sha256": ev.planner_sha, "git": _git_state()})
    console.print(results["headline_text"])
    console.print(f"wrote {ev.out / 'report.md'} and {ev.out / 'results.json'}")
    if results["damaged_logs"]:
        console.print(f"[red]{len(results['damaged_logs'])} extraction(s) read a damaged S0 log[/red] "
                      "(results.json damaged_logs)", soft_wrap=True)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
