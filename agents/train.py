"""Train the RL adversary on ``deft_gym/Adversary-v0`` with stable-baselines3.

    deft-gym train --config configs/train/adversary.yaml [--timesteps N] [--out runs/adversary/x]
    python -m agents.train --config ... --resume runs/adversary/x/checkpoints/ppo_20000_steps.zip
    python -m agents.train --config ... --ray [--ray-address ADDR]   # envs as Ray actors

The run folder holds ``config.yaml`` (the resolved configuration), ``tb/`` (TensorBoard),
``checkpoints/`` (every ``checkpoint_every`` steps), ``monitor/`` (per-env episode CSVs),
``episodes-<worker>.jsonl`` (one line per episode: verdict, scenario, seeds, what happened to the
log), ``episodes/`` (the logs of failing episodes with their extracted tests, plus a sample of
passing ones), ``progress.jsonl`` (failure counts as training goes) and, at the end, ``model.zip``
and ``summary.json``.

A run resumed from a checkpoint (after a crash or ``kill -9``) continues the model as it was
then, so what the envs did after that checkpoint is no part of the resumed model's history: it is
set aside, never deleted, under ``rolled_back/`` - the Monitor rows of those episodes
(``rolled_back/monitor/``), their kept logs and any log an unfinished episode left
(``rolled_back/episodes/``) and the ``progress.jsonl`` lines after the checkpoint. The journals
keep every line (a resume marker says where the rollback starts); ``summary.json`` counts the
episodes the model saw and reports ``rolled_back_episodes``. Checkpoints are taken between
rollouts, after the update, so a checkpoint's model has learned from every step before it.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import re
import signal
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

import yaml

from agents.config import ALGOS, TrainConfig, check_train_settings, load_train_config
from deft_gym.cli import common
from deft_gym.config import ConfigError
from deft_gym.envs.sink import ROLLED_BACK
from deft_gym.execution import Backend, add_backend_arguments, backend_from_args
from deft_gym.execution.watchdog import apply_env, carried_env
from deft_gym.files import (
    append_jsonl,
    atomic_path,
    first_line,
    read_jsonl,
    write_atomic,
    write_json_atomic,
)
from deft_gym.record.recorder import init_pool_worker


def build_parser() -> common.Parser:
    p = common.parser("train", "agents.train", __doc__)
    p.add_argument("--config", type=Path, default=None, help="training YAML (configs/train/*.yaml; default: "
                   "the built-in defaults)")
    p.add_argument("--timesteps", type=int, default=None, help="env steps to train (default: the config's)")
    common.add_out(p, None, help="run folder (default: runs/adversary/<config name>)")
    p.add_argument("--resume", type=Path, default=None, help="checkpoint .zip to continue from")
    common.add_seed(p, None, "seed of the learner and the envs (default: the config's)")
    p.add_argument("--n-envs", type=int, default=None, help="parallel envs (default: the config's)")
    p.add_argument("--algo", choices=ALGOS, default=None, help="algorithm (default: the config's)")
    common.add_ads_config(p, "the config's env.ads, else configs/ads/default.yaml")
    common.add_render(p)
    common.add_watchdog(p)
    common.add_output_flags(p)
    add_backend_arguments(p)  # --ray: the envs as Ray actors (deft_gym.execution.vec_env), PPO unchanged
    return p


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    args = build_parser().parse_args(argv)
    args.out = Path(args.out) if args.out else None
    return args


# -- environments --------------------------------------------------------------------------------
MONITOR_KEYS = ("failure", "scenario", "valid", "iou", "outcome", "env_steps")  # info columns of a Monitor CSV


def monitor_path(out: Path, rank: int) -> Path:
    return out / "monitor" / f"env{rank}.monitor.csv"


def monitor_keys(path: Path) -> tuple[str, ...]:
    """The info columns of an existing Monitor CSV (a resumed run appends rows of the same
    columns, even to a file an older version wrote), else :data:`MONITOR_KEYS`."""
    try:
        with path.open() as f:
            f.readline()
            cols = next(csv.reader([f.readline()]))
    except (OSError, StopIteration):
        return MONITOR_KEYS
    return tuple(cols[3:]) if cols[:3] == ["r", "l", "t"] else MONITOR_KEYS


def resume_seed(seed: int, timesteps0: int) -> int:
    """The seed of a session resumed at ``timesteps0`` steps (learner and envs): SB3 seeds a
    loaded model with the run's own seed, so every resumed session simulated the scenarios and
    jitter seeds of the run's start again."""
    import numpy as np

    return int(np.random.SeedSequence([seed, timesteps0]).generate_state(1)[0] >> 1)


def make_env(cfg: TrainConfig, rank: int, out: Path | None, workers: int = 1, step0: int = 0) -> Any:
    """A thunk building env ``rank`` (own worker id, own episode journal, Monitor-wrapped) in one
    of ``workers`` env processes (:func:`deft_gym.record.recorder.init_pool_worker`; 1 when the envs
    share this process). ``step0``: the env's steps before this session (a resumed run: its
    episode numbers, step count and journal continue, its Monitor file is appended to). The env
    process follows this one's watchdog setting (``--watchdog-s``)."""
    settings = carried_env()

    def thunk() -> Any:
        from stable_baselines3.common.monitor import Monitor

        apply_env(settings)
        if workers > 1:
            init_pool_worker(workers)

        from deft_gym.envs.adversary import AdversaryEnv

        env_cfg = cfg.env.model_copy(update={
            "worker": rank, "distinct_across_workers": cfg.n_envs > 1,  # the vec env steps them in lockstep
            "log_dir": str(out) if (out is not None and cfg.log_episodes) else cfg.env.log_dir})
        env = AdversaryEnv(config=env_cfg)
        env.env_steps = step0  # (each step hands it on to the episode sink's journal)
        env.reset(seed=cfg.seed * 1000 + rank)
        monitor, keys, fresh = None, MONITOR_KEYS, True
        if out is not None:
            path = monitor_path(out, rank)
            path.parent.mkdir(parents=True, exist_ok=True)
            monitor = str(path)
            fresh = not (path.exists() and step0 > 0)  # resumed: append
            keys = MONITOR_KEYS if fresh else monitor_keys(path)
        return Monitor(env, monitor, info_keywords=keys, override_existing=fresh)

    return thunk


def make_vec_env(cfg: TrainConfig, out: Path | None, backend: Backend | None = None, step0: int = 0) -> Any:
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    if backend is not None and backend.kind == "ray":
        from deft_gym.execution.vec_env import RayVecEnv

        return RayVecEnv([make_env(cfg, i, out, cfg.n_envs, step0) for i in range(cfg.n_envs)], run_dir=out)
    if cfg.vec_env == "subproc" and cfg.n_envs > 1:
        return SubprocVecEnv([make_env(cfg, i, out, cfg.n_envs, step0) for i in range(cfg.n_envs)],
                             start_method="forkserver")
    return DummyVecEnv([make_env(cfg, i, out, step0=step0) for i in range(cfg.n_envs)])


def checkpoint_callback(every: int, path: Path, prefix: str) -> Any:
    """``<prefix>_<steps>_steps.zip`` in ``path`` at the first rollout boundary after every
    ``every`` env steps (all envs), written to a temporary file and renamed, so a kill never
    leaves a truncated one. Between rollouts, after the update: SB3's CheckpointCallback saves in
    the middle of a rollout, before the update, and a run resumed from it lost that rollout's
    learning while its episodes were counted."""
    from stable_baselines3.common.callbacks import BaseCallback

    class AtomicCheckpoint(BaseCallback):
        def _on_training_start(self) -> None:
            self.saved = self.num_timesteps

        def _on_rollout_start(self) -> None:
            if self.num_timesteps // every > self.saved // every:
                with atomic_path(path / f"{prefix}_{self.num_timesteps}_steps.zip") as tmp:
                    self.model.save(tmp)
                self.saved = self.num_timesteps

        def _on_step(self) -> bool:
            return True

    return AtomicCheckpoint()


def checkpoint_steps(path: Path) -> int:
    """The timesteps stored in a checkpoint; ConfigError (one line) if it is missing or unreadable."""
    if not path.is_file():
        raise ConfigError(f"--resume {path}: no such checkpoint file; expected a .zip written by agents.train "
                          "(checkpoints/<algo>_<steps>_steps.zip or model.zip)")
    from stable_baselines3.common.save_util import load_from_zip_file

    try:
        data, _, _ = load_from_zip_file(path, device="cpu", load_data=True)
        return int(data["num_timesteps"])
    except Exception as exc:  # a truncated or foreign file: name it, no traceback
        raise ConfigError(f"--resume {path}: not a readable SB3 checkpoint ({type(exc).__name__}: "
                          f"{first_line(exc, '')})") from None


def mark_resume(out: Path, n_envs: int, step0: int, checkpoint: Path) -> None:
    """Append to every env's journal where this session starts: the episodes journalled after
    ``step0`` env steps were rolled back with the checkpoint and are not counted again."""
    for rank in range(n_envs):
        append_jsonl(out / f"episodes-{rank}.jsonl", {"resume_at_env_steps": step0, "checkpoint": str(checkpoint)})


def journal_records(path: Path) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """The episode records of one env's journal that count and those rolled back by a later
    resume."""
    recs: list[dict[str, Any]] = []
    rolled: list[dict[str, Any]] = []
    for r in read_jsonl(path):
        if "resume_at_env_steps" in r:
            keep: list[dict[str, Any]] = []
            for x in recs:
                (keep if x.get("env_steps") is None or x["env_steps"] <= r["resume_at_env_steps"] else rolled).append(x)
            recs = keep
        else:
            recs.append(r)
    return recs, rolled


def roll_back(out: Path, n_envs: int, step0: int, timesteps0: int, checkpoint: Path) -> None:
    """Resuming from ``checkpoint`` (``step0`` steps per env, ``timesteps0`` in all): set aside
    under ``out/rolled_back/`` what came after it (module docstring) - Monitor rows of episodes
    that ended later or were cut by a kill, the kept logs of rolled-back or unfinished episodes,
    later ``progress.jsonl`` lines - and mark the journals. Nothing is deleted; a rollback cut
    short by another kill is completed by the next resume without duplicating anything."""
    mark_resume(out, n_envs, step0, checkpoint)
    aside = out / ROLLED_BACK
    for rank in range(n_envs):
        src = monitor_path(out, rank)
        _move_lines(src, aside / "monitor" / src.name, 2, lambda rows: _monitor_counts(rows, step0))
        _move_logs(out, rank)
    _move_lines(out / "progress.jsonl", aside / "progress.jsonl", 0,
                lambda rows: [_progress_counts(r, timesteps0) for r in rows])


def _monitor_counts(rows: list[str], step0: int) -> list[bool]:
    """Which Monitor CSV rows (lines with their header: the columns) stay: episodes that ended by
    ``step0`` env steps (column ``env_steps``; the sum of ``l`` in a file without it)."""
    cols = next(csv.reader([rows[0]]), [])
    keep, end = [True], 0
    for line in rows[1:]:
        try:
            row = dict(zip(cols, next(csv.reader([line]))))
            end = int(float(row["env_steps"])) if "env_steps" in cols else end + int(row["l"])
            keep.append(line.endswith("\n") and end <= step0)
        except (KeyError, ValueError, StopIteration):  # a row cut by the kill
            keep.append(False)
    return keep


def _progress_counts(line: str, timesteps0: int) -> bool:
    try:
        return line.endswith("\n") and int(json.loads(line)["timesteps"]) <= timesteps0
    except (ValueError, KeyError, TypeError):
        return False


def _move_lines(path: Path, dest: Path, head: int, counts: Any) -> int:
    """Move the lines of ``path`` that ``counts`` rejects (it gets the lines from the last of
    the ``head`` header lines on; one flag each) to the end of ``dest`` (created with the same
    header lines), then rewrite ``path`` without them, atomically. A line already in ``dest``
    (a move cut short by a kill) is not appended again. The number of lines moved."""
    if not path.exists():
        return 0
    lines = path.read_text().splitlines(keepends=True)
    if len(lines) <= head:
        return 0
    start = max(head - 1, 0)  # counts sees the last header line (a CSV's columns) first
    flags = [True] * start + counts(lines[start:])
    moved = [x if x.endswith("\n") else x + "\n" for x, ok in zip(lines, flags) if not ok]
    if not moved:
        return 0
    dest.parent.mkdir(parents=True, exist_ok=True)
    have = set(dest.read_text().splitlines(keepends=True)) if dest.exists() else set()
    with dest.open("a") as f:
        if not have:
            f.writelines(lines[:head])
        f.writelines(x for x in moved if x not in have)
        f.flush()
        os.fsync(f.fileno())
    write_atomic(path, "".join(x for x, ok in zip(lines, flags) if ok))
    return len(moved)


def _move_logs(out: Path, rank: int) -> int:
    """Move env ``rank``'s episode folders that no longer count - kept logs of rolled-back
    episodes, and what an episode cut by the kill left (no journal line; numbered after the last
    counted one) - from ``episodes/`` to ``rolled_back/episodes/``. The number moved."""
    folder = out / "episodes"
    if not folder.is_dir():
        return 0
    kept, rolled = journal_records(out / f"episodes-{rank}.jsonl")
    counted = {Path(r["dir"]).name for r in kept if r.get("dir")}
    aside = {Path(r["dir"]).name for r in rolled if r.get("dir")}
    pat = re.compile(rf"w{rank}-(\d+)-")
    last = max((int(m.group(1)) for name in counted if (m := pat.match(name))), default=0)
    moved = 0
    for d in sorted(folder.iterdir()):
        m = pat.match(d.name)
        if not m or d.name in counted or (d.name not in aside and int(m.group(1)) <= last):
            continue
        dest = out / ROLLED_BACK / "episodes" / d.name
        if dest.exists():  # numbers are never reused: not ours to merge
            continue
        dest.parent.mkdir(parents=True, exist_ok=True)
        os.replace(d, dest)
        moved += 1
    return moved


def monitor_totals(out: Path) -> Counter[str]:
    """Episodes, outcomes, valid mutations and failures in a run's Monitor CSVs (where a resumed
    session's ``progress.jsonl`` counts continue from)."""
    c: Counter[str] = Counter()
    for path in sorted((out / "monitor").glob("*.monitor.csv")):
        lines = path.read_text().splitlines()[1:]
        for row in csv.DictReader(lines):
            c["episodes"] += 1
            if row.get("outcome"):
                c[f"outcome_{row['outcome']}"] += 1
            c["valid"] += int(row.get("valid") == "True")
            if row.get("failure"):
                c[row["failure"]] += 1
    return c


# -- callbacks ------------------------------------------------------------------------------------
def failure_callback(out: Path | None, counts: Counter[str] | None = None) -> Any:
    """Logs failures per episode to TensorBoard and appends ``progress.jsonl`` (its counts
    continue from ``counts``: a resumed run's episodes so far)."""
    from stable_baselines3.common.callbacks import BaseCallback

    class FailureStats(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.counts: Counter[str] = Counter(counts or {})
            self.session = 0  # episodes of this session
            self.t0 = time.time()
            self.cpu0 = time.process_time()
            self.worker_cpu: dict[int, float] = {}  # env process id -> its CPU seconds so far

        def cpu_seconds(self) -> float:
            """CPU seconds of training so far: this process (updates) plus every env process."""
            own = time.process_time() - self.cpu0
            return own + sum(v for pid, v in self.worker_cpu.items() if pid != os.getpid())

        def _on_step(self) -> bool:
            for info, done in zip(self.locals["infos"], self.locals["dones"]):
                if not done or "outcome" not in info:
                    continue
                if "pid" in info:
                    self.worker_cpu[int(info["pid"])] = float(info["process_cpu"])
                c = self.counts
                c["episodes"] += 1
                self.session += 1
                c[f"outcome_{info['outcome']}"] += 1
                c["valid"] += int(bool(info.get("valid")))
                fail = info.get("failure")
                if fail:
                    c[fail] += 1
                self.logger.record_mean("adversary/failure", float(bool(fail)))
                self.logger.record_mean("adversary/collision", float(fail == "collision"))
                self.logger.record_mean("adversary/nods", float(fail == "nods"))
                self.logger.record_mean("adversary/valid", float(bool(info.get("valid"))))
                self.logger.record_mean("adversary/iou", float(info.get("iou", 1.0)))
                if isinstance(info.get("metrics"), dict):  # driving quality (docs/metrics.md)
                    self.logger.record_mean("adversary/driving_score", float(info["metrics"]["score"]))
                if info.get("oracle_signature"):  # a finding on the configured metric oracle
                    c["oracle_findings"] += 1
                found = info.get("found_by_oracle") or {}
                for oracle in found:  # every metric oracle's finding (not re-checked): oracle any's curve
                    c[f"found_{oracle}"] += 1
                c["any_findings"] += int(bool(fail or found))  # episodes with a failure or a metric finding
                self.logger.record_mean("adversary/any_finding", float(bool(fail or found)))
                if out is not None and c["episodes"] % 50 == 0:
                    self._write()
            return True

        def _write(self) -> None:
            assert out is not None
            append_jsonl(out / "progress.jsonl", {"timesteps": self.num_timesteps,
                                                  "seconds": round(time.time() - self.t0, 1),
                                                  "cpu_seconds": round(self.cpu_seconds(), 1), **self.counts})
            self.written = self.counts["episodes"]

        def _on_training_end(self) -> None:
            """The last line: the curves reach the end of training, not the last 50th episode."""
            if out is not None and self.counts["episodes"] != getattr(self, "written", None):
                self._write()

    return FailureStats()


def close_envs(vec_env: Any, interrupted: bool) -> None:
    """Close the envs; after an interrupt, without waiting for the step replies SB3's
    ``SubprocVecEnv`` still expects: interrupted between two of them, its ``close`` waits for
    replies that were already read and never comes back (a worker finishing its step still
    sends into its pipe, then reads ``close`` and exits)."""
    if interrupted and getattr(vec_env, "waiting", False):
        vec_env.waiting = False
    vec_env.close()


# -- summary --------------------------------------------------------------------------------------
def summarize_run(out: Path) -> dict[str, Any]:
    """Aggregate the episode journals of a run folder (what ``summary.json`` holds, besides the
    training figures)."""
    parts = [journal_records(f) for f in sorted(out.glob("episodes-*.jsonl"))]
    recs = [r for rs, _ in parts for r in rs]
    by_scn: dict[str, Counter[str]] = {}
    tests, extraction = [], Counter()
    for r in recs:
        c = by_scn.setdefault(r.get("scenario", "?"), Counter())
        c["episodes"] += 1
        c["valid"] += int(bool(r.get("valid")))
        if r.get("failure"):
            c[r["failure"]] += 1
        ex = r.get("extraction")
        if ex:
            extraction[ex.get("status", "?").split(":")[0]] += 1
            if ex.get("test"):
                tests.append(ex["test"])
    total: Counter[str] = Counter()
    for c in by_scn.values():
        total.update(c)
    summary = {"episodes": total["episodes"], "collisions": total["collision"], "nods": total["nods"],
               "valid": total["valid"], "validity": round(total["valid"] / max(total["episodes"], 1), 4),
               "failure_rate": round((total["collision"] + total["nods"]) / max(total["episodes"], 1), 4),
               "per_scenario": {k: dict(v) for k, v in sorted(by_scn.items())},
               "extraction": dict(extraction), "extracted_tests": tests,
               "kept_logs": sum(1 for r in recs if r.get("kept")),
               "duplicate_failures": sum(1 for r in recs if r.get("duplicate_of")),
               "rolled_back_episodes": sum(len(rolled) for _, rolled in parts)}
    return summary


def usable_cores(n_envs: int) -> int:
    """The cores a run of ``n_envs`` env processes can keep busy: one per env, at most the CPUs
    this process may use (the learner runs between the envs' steps)."""
    return max(1, min(n_envs, common.cpus()))


def cores_busy(cpu_seconds: float, wall_seconds: float, cores: int) -> float:
    """The share of ``cores`` busy over a run: its CPU [s] (learner and envs) over wall [s] x cores.
    Low with many envs when they wait for each other: a vectorised env steps them together, so
    every step waits for the slowest env, and every update for the learner."""
    return cpu_seconds / max(wall_seconds * cores, 1e-9)


# -- main -----------------------------------------------------------------------------------------
def _interrupt(signum: int, frame: Any) -> None:
    """SIGTERM stops training like Ctrl-C; a second SIGTERM is ignored from then on, so that it
    cannot break off the model's save (GNU ``timeout`` signals the process, then its group)."""
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    with common.watchdog_env(args):
        return _main(args)


def _main(args: argparse.Namespace) -> int:
    try:
        cfg = load_train_config(args.config, {"timesteps": args.timesteps, "seed": args.seed,
                                              "n_envs": args.n_envs, "algo": args.algo})
        if args.ads_config is not None:  # the planner under test (and the rest of the ADS)
            cfg = cfg.model_copy(update={"env": cfg.env.model_copy(update={"ads": str(args.ads_config)})})
        backend = backend_from_args(args, cfg.n_envs)
        check_train_settings(cfg, args.config)
    except ConfigError as err:
        return common.cli_error(str(err))
    con = common.console(args)
    if cfg.generated:
        from deft_gym.search.context import ads_config, robust_generated

        con.print(f"choosing {cfg.generated} robust generated training scenario(s) ...")
        names = robust_generated(cfg.generated, 0, ads=ads_config(cfg.env.ads))
        cfg = cfg.model_copy(update={"env": cfg.env.model_copy(update={"scenarios": list(cfg.env.scenarios) + names}),
                                     "generated": 0})
        con.print(f"training on {len(cfg.env.scenarios)} scenarios ({len(names)} generated)")
    out = args.out or Path("runs/adversary") / cfg.name
    step0 = timesteps0 = 0
    if args.resume is not None:
        try:
            timesteps0 = checkpoint_steps(args.resume)
            step0 = timesteps0 // cfg.n_envs
        except ConfigError as err:
            print(f"error: {err}", file=sys.stderr)
            return 2
    if out.exists() and not out.is_dir():
        print(f"error: --out {out}: is a file; expected a folder for the run", file=sys.stderr)
        return 2
    if args.resume is None and any(out.glob("episodes-*.jsonl")):
        print(f"error: {out} already holds a training run (episodes-*.jsonl); continue it with --resume "
              f"{out}/checkpoints/<checkpoint>.zip or train into another --out", file=sys.stderr)
        return 2
    with common.locked_out(out):
        if args.resume is None and any(out.glob("episodes-*.jsonl")):  # (another run began meanwhile)
            print(f"error: {out} already holds a training run (episodes-*.jsonl)", file=sys.stderr)
            return 2
        return _train(args, con, cfg, backend, out, step0, timesteps0)


def _train(args: argparse.Namespace, con: Any, cfg: Any, backend: Any, out: Path, step0: int, timesteps0: int) -> int:
    out.mkdir(parents=True, exist_ok=True)
    write_atomic(out / "config.yaml", yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False))

    import torch
    from stable_baselines3 import A2C, PPO
    from stable_baselines3.common.callbacks import CallbackList

    torch.set_num_threads(1)  # the cores belong to the simulation workers
    # SB3 builds a distribution per step; checking its arguments was 15 % of the learner's CPU per step
    torch.distributions.Distribution.set_default_validate_args(False)
    algo_cls = {"ppo": PPO, "a2c": A2C}[cfg.algo]
    if args.resume is not None:
        roll_back(out, cfg.n_envs, step0, timesteps0, args.resume)
    vec_env = make_vec_env(cfg, out, backend, step0)
    if args.resume is not None:
        model = algo_cls.load(args.resume, env=vec_env, tensorboard_log=str(out / "tb"), device="cpu")
        model.set_random_seed(resume_seed(cfg.seed, timesteps0))
        con.print(f"resumed from {args.resume} at {model.num_timesteps} steps")
    else:
        model = algo_cls(cfg.policy, vec_env, seed=cfg.seed, tensorboard_log=str(out / "tb"), device="cpu",
                         policy_kwargs=cfg.policy_kwargs, verbose=0, **cfg.algo_kwargs)
        if cfg.init_model:  # fine-tuning: the trained policy, this run's steps and schedule
            from deft_gym.models import resolve_model

            model.set_parameters(resolve_model(cfg.init_model), exact_match=True, device="cpu")
            con.print(f"started from the policy of {resolve_model(cfg.init_model)}")
    remaining = max(cfg.timesteps - (model.num_timesteps if args.resume else 0), 0)
    stats = failure_callback(out, monitor_totals(out) if args.resume is not None else None)
    callbacks = CallbackList([
        checkpoint_callback(cfg.checkpoint_every, out / "checkpoints", cfg.algo),
        stats,
    ])
    signal.signal(signal.SIGTERM, _interrupt)  # `kill PID` stops training like Ctrl-C: model saved
    t0 = time.time()
    steps0 = model.num_timesteps
    episodes0 = summarize_run(out)["episodes"]  # a resumed run's earlier episodes
    interrupted = False
    try:
        if common.show_progress(args):
            callbacks.callbacks.append(progress_callback(remaining))
        model.learn(total_timesteps=remaining, callback=callbacks, progress_bar=False,
                    reset_num_timesteps=args.resume is None, tb_log_name=cfg.algo)
    except KeyboardInterrupt:
        interrupted = True
        print("interrupted: saving the model", file=sys.stderr)
    finally:
        with atomic_path(out / "model.zip") as tmp:
            model.save(tmp)
        close_envs(vec_env, interrupted)
    seconds = time.time() - t0
    summary = summarize_run(out)
    if not summary["episodes"]:  # no episode journals (log_episodes: false): the envs' own counts
        c = stats.counts
        summary.update({"episodes": c["episodes"], "collisions": c["collision"], "nods": c["nods"],
                        "valid": c["valid"], "validity": round(c["valid"] / max(c["episodes"], 1), 4),
                        "failure_rate": round((c["collision"] + c["nods"]) / max(c["episodes"], 1), 4)})
    summary["findings"] = {k: v for k, v in sorted(stats.counts.items()) if k.startswith("found_") or k.endswith("findings")}
    cores = usable_cores(cfg.n_envs)
    summary.update({"timesteps": int(model.num_timesteps), "train_seconds": round(seconds, 1),
                    "interrupted": interrupted,
                    "env_steps_per_second": round((model.num_timesteps - steps0) / max(seconds, 1e-9), 2),
                    "episodes_this_session": summary["episodes"] - episodes0,
                    "episodes_per_hour": round((summary["episodes"] - episodes0) / max(seconds, 1e-9) * 3600, 1),
                    "cpu_seconds": round(stats.cpu_seconds(), 1),
                    "scenarios_per_cpu_hour": round(stats.session / max(stats.cpu_seconds(), 1e-9) * 3600, 1),
                    "cores": cores,
                    "cores_busy": round(cores_busy(stats.cpu_seconds(), seconds, cores), 3)})
    write_json_atomic(out / "summary.json", summary)
    pictures = render_failures(out, args) if args.render != "none" else []
    print_summary(con, summary, out, len(pictures))
    if args.quiet:
        print(f"model: {out / 'model.zip'}")
    return 0


def progress_callback(total: int) -> Any:
    """The training progress bar (:class:`deft_gym.cli.common.Bar`, env steps)."""
    from stable_baselines3.common.callbacks import BaseCallback

    class Progress(BaseCallback):
        def _on_training_start(self) -> None:
            self.bar = common.Bar(total, "training (env steps)")
            self.start = self.num_timesteps

        def _on_step(self) -> bool:
            self.bar.set(self.num_timesteps - self.start)
            return True

        def _on_training_end(self) -> None:
            self.bar.close()

    return Progress()


def render_failures(out: Path, args: argparse.Namespace) -> list[dict[str, Any]]:
    """Plot and video of every failing episode kept in the run folder (``--render``)."""
    from deft_gym.viz.episode import render_failures as draw

    with common.bar(args, None, "pictures of failures") as bar:
        return draw(out / "episodes", progress=lambda done, total: bar.set(done, total))


def print_summary(con: Any, s: dict[str, Any], out: Path, pictures: int) -> None:
    """The run's figures as a table, then where things are."""
    from rich import box
    from rich.table import Table

    t = Table(title=f"training run {out}", title_justify="left", box=box.SIMPLE_HEAD, show_header=False)
    t.add_column("what")
    t.add_column("value", justify="right")
    rows = [("env steps", f"{s['timesteps']:,}" + (" (interrupted)" if s.get("interrupted") else "")),
            ("episodes (simulated scenarios)", f"{s['episodes']:,}"),
            ("collisions (ego at fault)", str(s["collisions"])), ("non-optimal decisions (NoDS)", str(s["nods"])),
            ("valid mutations", f"{100 * s['validity']:.1f} %"), ("failure rate", f"{100 * s['failure_rate']:.1f} %"),
            ("extracted test modules", str(len(s.get("extracted_tests") or []))
             + (f" (+{s['duplicate_failures']} failures repeating a kept one's signature)"
                if s.get("duplicate_failures") else "")),
            *([("rolled back by resuming (in rolled_back/)", str(s["rolled_back_episodes"]))]
              if s.get("rolled_back_episodes") else []),
            ("training time", f"{s['train_seconds']:.0f} s ({s['episodes_per_hour']:.0f} episodes/h)"),
            ("scenarios per CPU-hour", f"{s['scenarios_per_cpu_hour']:.0f}"),
            *([("cores busy", f"{100 * s['cores_busy']:.0f} % of {s['cores']}")] if "cores_busy" in s else [])]
    for k, v in rows:
        t.add_row(k, v)
    common.print_table(con, t)
    con.print(f"model: {common.shown(out / 'model.zip')}   curves: {common.tool('tensorboard')} --logdir "
              f"{common.shown(out / 'tb')}   "
              f"report: {common.tool('deft-gym')} report {common.shown(out)}"
              + (f"   pictures of {pictures} failure(s) under {common.shown(out / 'episodes')}" if pictures else ""),
              soft_wrap=True)


if __name__ == "__main__":
    raise SystemExit(main())
