"""Batch extraction: every log under a folder of runs, resumable, optionally in parallel.

Each log ``ROOT/<rel>/episode.mcap`` is extracted into ``OUT/<rel>/`` (other ``*.mcap`` names
into ``OUT/<rel>/<stem>/``; two logs that would share a folder get distinct ones,
:func:`episode_out_dirs`), with a test module named after the scenario and ``<rel>`` so that
``pytest OUT`` collects them all. An episode whose ``summary.json`` is newer than its log and was
made with the same options is skipped (``force`` redoes it). ``OUT/summary.json`` totals them.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from deft_gym.execution import Backend, Executor
from deft_gym.files import write_atomic
from extract.emit import slug
from extract.episode import ExtractionResult, extract_episode
from extract.logs import LogError
from extract.mapping import MappingError, load_mapping
from extract.validator import SUMMARY_THETAS, Tolerances, theta_key

BATCH_FORMAT = "deft_gym.extraction-batch/1"


def find_logs(root: Path | str) -> list[Path]:
    """The MCAP logs under ``root`` (or ``root`` itself), in path order."""
    root = Path(root)
    if root.is_file():
        return [root]
    if not root.is_dir():
        raise LogError(f"{root}: no such file or folder; expected an .mcap log or a folder of runs")
    return sorted(p for p in root.rglob("*.mcap") if p.is_file())


def episode_out_dir(log: Path, root: Path, out_root: Path) -> Path:
    """Where the extraction of ``log`` goes."""
    rel = log.parent.relative_to(root) if root.is_dir() else Path()
    base = out_root / rel
    return base if log.name == "episode.mcap" and rel != Path() else base / log.stem


def episode_out_dirs(logs: list[Path], root: Path, out_root: Path) -> list[Path]:
    """:func:`episode_out_dir` of each log, made distinct: a log whose folder another log already
    has (``lfs/episode.mcap`` and ``lfs.mcap`` both give ``OUT/lfs``) goes to ``OUT/<rel>/<name>``
    (``OUT/lfs.mcap``), then ``-2``, ``-3``... so no extraction overwrites another's."""
    taken: set[Path] = set()
    dirs = []
    for log in logs:
        out = episode_out_dir(log, root, out_root)
        if out in taken:
            rel = log.parent.relative_to(root) if root.is_dir() else Path()
            cand, k = out_root / rel / log.name, 2
            while cand in taken:
                cand, k = out_root / rel / f"{log.name}-{k}", k + 1
            out = cand
        taken.add(out)
        dirs.append(out)
    return dirs


def _options(kwargs: dict[str, Any]) -> dict[str, Any]:
    theta = float(kwargs.get("theta", 0.0))
    tol = kwargs.get("tolerances")
    tol = tol if isinstance(tol, Tolerances) else Tolerances.from_dict(tol, theta)
    return {"mode": kwargs.get("mode", "heuristic"), "theta": theta, "measure": kwargs.get("measure", "lsed"),
            "mapping": load_mapping(kwargs.get("mapping")).name, "tolerances": tol.as_dict()}


def _up_to_date(log: Path, out: Path, options: dict[str, Any]) -> dict[str, Any] | None:
    path = out / "summary.json"
    try:
        if path.stat().st_mtime < log.stat().st_mtime:
            return None
        s = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    same = all(s.get(k) == v for k, v in options.items()) and s.get("log") == str(log)
    return s if same and "error" not in s else None


def _job(args: tuple[str, str, str, dict[str, Any]]) -> ExtractionResult:
    log, out, suffix, kwargs = args
    try:
        res = extract_episode(log, out, test_suffix=suffix, **kwargs)
        res.choices = []  # keep what crosses process boundaries small
        return res
    except (LogError, MappingError, ValueError, OSError) as exc:
        return ExtractionResult({"log": log, "error": str(exc), "frames": 0}, None, None, None)


def _job_files(job: tuple[str, str, str, dict[str, Any]]) -> list[str]:
    """What one episode's extraction writes: its output folder."""
    return [job[1]]


def _job_inputs(job: tuple[str, str, str, dict[str, Any]]) -> list[str]:
    """What it reads: the log and the truth file beside it (if any)."""
    return [job[0], str(Path(job[0]).with_name("truth.jsonl"))]


def extract_directory(root: Path | str, out_root: Path | str, *, workers: int = 1, force: bool = False,
                      on_episode: Callable[[ExtractionResult], None] | None = None,
                      executor: Executor | None = None, **kwargs: Any) -> list[ExtractionResult]:
    """Extract every log under ``root`` into ``out_root`` (keyword arguments as
    :func:`extract.extract_episode`); a log that fails gives a result whose summary has
    ``error`` instead of stopping the batch. Episodes run on ``executor`` (default: ``workers``
    local processes; :mod:`deft_gym.execution`), results in log order. Writes
    ``out_root/summary.json``."""
    root, out_root = Path(root), Path(out_root)
    logs = find_logs(root)
    if not logs:
        raise LogError(f"{root}: no .mcap logs found")
    options = _options(kwargs)
    results: list[ExtractionResult | None] = [None] * len(logs)
    jobs: list[tuple[int, tuple[str, str, str, dict[str, Any]]]] = []
    for i, (log, out) in enumerate(zip(logs, episode_out_dirs(logs, root, out_root))):
        done = None if force else _up_to_date(log, out, options)
        if done is not None:
            results[i] = ExtractionResult(done, Path(done["frames_path"]) if done.get("frames_path") else None,
                                          Path(done["test_path"]) if done.get("test_path") else None,
                                          done.get("faulty_trajectory"))
            results[i].summary["skipped"] = True
            if on_episode is not None:
                on_episode(results[i])
            continue
        rel = out.relative_to(out_root) if out != out_root else Path(log.stem)
        jobs.append((i, (str(log), str(out), slug(str(rel)), kwargs)))
    own = executor is None
    ex = executor or Executor(Backend("local", max(1, min(workers, len(jobs)))), run_dir=out_root)
    try:
        # the logs travel to a node that does not share them; the extraction comes back
        for (i, _), res in zip(jobs, ex.map(_job, [a for _, a in jobs], artifacts=_job_files,
                                            inputs=_job_inputs)):
            results[i] = res
            if on_episode is not None:
                on_episode(res)
    finally:
        if own:
            ex.close()
    final = [r for r in results if r is not None]
    write_atomic(out_root / "summary.json", json.dumps(batch_summary(final, options), indent=2))
    return final


def damaged_log(summary: dict[str, Any]) -> bool:
    """Whether an episode's extraction read a log that is not intact (damaged or cut short)."""
    return summary.get("log_status", "complete") != "complete"


def batch_summary(results: list[ExtractionResult], options: dict[str, Any]) -> dict[str, Any]:
    """Totals over episodes (shares and per-frame times weighted by frames); ``damaged_logs``
    lists the logs that are not intact (extracted as far as they are)."""
    ok = [r.summary for r in results if r.ok]
    frames = sum(s["frames"] for s in ok)
    keys = [theta_key(t) for t in SUMMARY_THETAS]
    reproduced = {k: sum(s["reproduced"][k] for s in ok) for k in keys}
    whole = {k: sum(s.get("reproduced_all_fields", {}).get(k, 0) for s in ok) for k in keys}

    def weighted(key: str) -> float | None:
        vals = [(s[key], s["frames"]) for s in ok if s.get(key) is not None]
        n = sum(f for _, f in vals)
        return sum(v * f for v, f in vals) / n if n else None

    return {
        "format": BATCH_FORMAT, **options, "episodes": len(results), "failed": len(results) - len(ok),
        "damaged_logs": [{"log": s["log"], "log_status": s["log_status"]} for s in ok if damaged_log(s)],
        "frames": frames, "reproduced": reproduced,
        "reproduced_share": {k: (v / frames if frames else None) for k, v in reproduced.items()},
        "reproduced_all_fields": whole, "reproduced_at_theta": sum(s.get("reproduced_at_theta", 0) for s in ok),
        "ms_per_frame": weighted("ms_per_frame"), "planner_ms_per_frame": weighted("planner_ms_per_frame"),
        "overhead_ms_per_frame": weighted("overhead_ms_per_frame"), "truth_agreement": weighted("truth_agreement"),
        "collisions": sum(1 for s in ok if s.get("collision")),
        "faulty_trajectories": sum(1 for s in ok if s.get("faulty_trajectory")),
        "episodes_list": [{k: s.get(k) for k in ("log", "log_status", "scenario", "frames", "reproduced",
                                                 "ms_per_frame", "truth_agreement", "faulty_trajectory", "test_path",
                                                 "error", "skipped")}
                          for s in (r.summary for r in results)],
    }

