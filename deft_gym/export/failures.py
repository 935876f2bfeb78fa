"""The failures of a log, an episode folder or a whole run / evaluation / training folder, their
export in both formats next to their other files, and the checks of an export.

A failure is an episode whose folder's ``episode.json`` names a failure or a task failure (an
adversary's or a search's verdict), or, without one, whose log records a collision, a crash, a
hang or a missing plan. An episode ``DIR/episode.mcap`` is written as ``DIR/episode.xosc`` +
``DIR/episode.xodr`` (OpenSCENARIO + OpenDRIVE) and ``DIR/episode.cr.xml`` (CommonRoad); a log
``DIR/NAME.mcap`` as ``DIR/NAME.xosc`` and so on.

:func:`check_export` runs the independent checks on one export: ASAM's schema and quality
checkers on the ``.xosc`` and ``.xodr``, CommonRoad's schema and reader, the drivability
checker's first collision (against the logged one), every parsed-back trajectory against the
log's ground truth, and the round trip - each file imported back to a scenario and run on the
episode's jitter seed - against the logged outcome.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

FORMATS = ("xosc", "commonroad")
ROUNDTRIP_POSITION_TOL = 0.01  #: [m] the rerun ego's path must stay this close to the logged one


def export_paths(log: Path | str) -> dict[str, Path]:
    """Where the exports of ``log`` go (see the module docstring)."""
    log = Path(log)
    stem = log.stem
    return {"xosc": log.with_name(f"{stem}.xosc"), "xodr": log.with_name(f"{stem}.xodr"),
            "commonroad": log.with_name(f"{stem}.cr.xml")}


def existing_exports(log: Path | str) -> dict[str, Path]:
    """The exports of ``log`` that exist (what the report links)."""
    return {k: p for k, p in export_paths(log).items() if p.exists()}


def failure_of_log(log: Path) -> str | None:
    """What failed in the episode of ``log`` (see the module docstring), None if nothing did."""
    from deft_gym.export.episode import failure_of

    verdict = None
    vpath = log.with_name("episode.json")
    if vpath.exists():
        try:
            verdict = json.loads(vpath.read_text())
        except ValueError:
            verdict = None
    if verdict is not None:
        return failure_of("", None, verdict)
    from deft_gym.record import read_metadata
    from deft_gym.viz.episode import OUTCOME_META

    try:
        meta = read_metadata(log)
    except Exception:
        return None
    oc = meta.get(OUTCOME_META, {})
    collision = oc.get("collision")
    coll = json.loads(collision) if collision else None
    return failure_of(str(oc.get("outcome", "")), coll if isinstance(coll, dict) else None, None)


def find_logs(path: Path | str, all_episodes: bool = False) -> list[Path]:
    """The failing episode logs a path names: a log, the log beside an ``episode.json``, or every
    log under a folder (sorted); with ``all_episodes`` the passing ones too. ValueError when the
    path names none."""
    path = Path(path)
    if path.is_file() and path.suffix == ".mcap":
        logs = [path]
    elif path.is_file() and path.name.endswith(".json"):
        logs = [path.with_name("episode.mcap")]
        if not logs[0].exists():
            raise ValueError(f"{path}: no episode.mcap beside it")
    elif path.is_dir():
        logs = sorted(p for p in path.rglob("*.mcap") if p.is_file())
        if not logs:
            raise ValueError(f"{path}: no .mcap logs under it")
    else:
        raise ValueError(f"{path}: not an episode log (.mcap), an episode.json, a folder or a scenario")
    return logs if all_episodes else [p for p in logs if failure_of_log(p)]


def write_exports(e: Any, paths: dict[str, Path], formats: tuple[str, ...] = FORMATS) -> dict[str, Path]:
    """Write ``e`` in ``formats`` to ``paths`` (:func:`export_paths`' keys); what was written."""
    from deft_gym.export.commonroad import write_commonroad
    from deft_gym.export.opendrive import write_xodr
    from deft_gym.export.openscenario import write_xosc

    out: dict[str, Path] = {}
    if "xosc" in formats:
        out["xodr"] = write_xodr(e.roadmap, paths["xodr"], name=e.name)
        out["xosc"] = write_xosc(e, paths["xosc"], paths["xodr"])
    if "commonroad" in formats:
        out["commonroad"] = write_commonroad(e, paths["commonroad"])
    return out


# -- checks ----------------------------------------------------------------------------------------------
def _track_errors(rows: np.ndarray, truth: np.ndarray) -> tuple[float, float, int]:
    """Largest position and heading differences of ``rows`` against ``truth`` (both ``(t, x, y,
    h, ...)``) at the truth's times that ``rows`` covers; and how many were compared."""
    worst_p = worst_h = 0.0
    n = 0
    for t, x, y, h, *_ in truth:
        i = int(np.searchsorted(rows[:, 0], t - 1e-6))
        if i >= len(rows) or abs(rows[i, 0] - t) > 1e-6:
            continue
        worst_p = max(worst_p, math.hypot(rows[i, 1] - x, rows[i, 2] - y))
        worst_h = max(worst_h, abs(math.remainder(rows[i, 3] - h, math.tau)))
        n += 1
    return worst_p, worst_h, n


def trajectory_errors(actors: list[Any], scene: dict[str, Any]) -> dict[str, Any]:
    """Parsed-back actors against the log's ground-truth samples: the largest errors over every
    sample an actor's rows cover, and the samples no row covers."""
    by = {a.id: a for a in actors}
    worst_p = worst_h = 0.0
    n = uncovered = 0
    for pid, (_, _, _, truth) in scene.items():
        a = by.get(pid)
        if a is None or not len(a.rows):
            uncovered += len(truth)
            continue
        if len(a.rows) == 1:  # a static object, or the ego of a CommonRoad file: its one pose at every sample
            rows = np.repeat(a.rows, len(truth), axis=0)
            rows[:, 0] = truth[:, 0]
            keep = truth[:, 0] >= a.rows[0, 0] - 1e-9
            if a.kind == "ego":
                keep &= truth[:, 0] <= a.rows[0, 0] + 1e-9
            rows, tr = rows[keep], truth[keep]
        else:
            rows, tr = a.rows, truth
        p, h, k = _track_errors(rows, tr)
        worst_p, worst_h, n = max(worst_p, p), max(worst_h, h), n + k
        uncovered += len(tr) - k
    return {"samples": n, "uncovered": uncovered, "max_position_error": worst_p, "max_heading_error": worst_h}


def rerun(data: dict[str, Any], jitter_seed: int | None, ads: Any = None) -> tuple[dict[str, Any], np.ndarray]:
    """Run an imported scenario (plain data) once on ``jitter_seed``: its outcome record and the
    ego's rows at every world step."""
    from deft_gym.export.episode import simulate

    outcome, ego, _, _ = simulate(data, ads, jitter_seed, source=f"{data.get('name')} (imported)")
    return outcome.as_dict(), ego.rows


def reproduces(meta: dict[str, Any], outcome: dict[str, Any], ego_recorded: np.ndarray | None,
               ego_rerun: np.ndarray) -> dict[str, Any]:
    """Whether a rerun reproduces the logged episode: the same outcome (and collision: participant
    and time); and, where the recorded ego path is known, whether the ego also stays within
    :data:`ROUNDTRIP_POSITION_TOL` of it at every step both have (``same_path``)."""
    from deft_gym.export.episode import same_outcome

    same = same_outcome(outcome, {"outcome": meta.get("outcome"), "collision": meta.get("collision")})
    dev = None
    if ego_recorded is not None and len(ego_recorded):
        dev, _, _ = _track_errors(ego_rerun, ego_recorded)
    return {"reproduced": same, "same_path": dev is not None and dev <= ROUNDTRIP_POSITION_TOL,
            "ego_max_deviation": dev, "outcome": outcome.get("outcome"),
            "collision": (outcome.get("collision") or {}).get("participant"),
            "collision_time": (outcome.get("collision") or {}).get("time")}


def check_export(log: Path, written: dict[str, Path], roundtrip: bool = True) -> dict[str, Any]:
    """The independent checks of one export (see the module docstring); plain data."""
    from deft_gym.export.checks import errors, qc_issues
    from deft_gym.export.episode import log_ads, read_log

    ep, oc, scene = read_log(log)
    ads = log_ads(ep)  # the round trips rerun on the ADS the log was recorded with
    out: dict[str, Any] = {}
    ego_xosc = None
    if "xosc" in written:
        from deft_gym.export.openscenario import read_xosc
        from deft_gym.export.roundtrip import import_file

        for key in ("xodr", "xosc"):
            issues = qc_issues(written[key])
            out[f"{key}_errors"] = len(errors(issues))
            out[f"{key}_issues"] = [f"{i['level']}: {i['description']}" for i in issues][:5]
        got = read_xosc(written["xosc"])
        out["xosc_trajectories"] = trajectory_errors(got["actors"], scene)
        ego_xosc = next(a for a in got["actors"] if a.kind == "ego").rows
        if roundtrip:
            for key, reactive in (("xosc_roundtrip", False), ("xosc_roundtrip_reactive", True)):
                data, meta = import_file(written["xosc"], reactive=reactive)
                t0 = time.perf_counter()
                o, ego = rerun(data, meta.get("jitter_seed"), ads)
                out[key] = reproduces(meta, o, ego_xosc, ego) | {"seconds": time.perf_counter() - t0}
    if "commonroad" in written:
        from deft_gym.export.commonroad import first_collision_step, read_commonroad
        from deft_gym.export.roundtrip import import_file

        out["commonroad_schema"] = commonroad_schema_errors(written["commonroad"])
        got = read_commonroad(written["commonroad"])
        out["commonroad_trajectories"] = trajectory_errors(got["actors"], scene)
        coll = oc.get("collision") if isinstance(oc.get("collision"), dict) else None
        if coll is not None:
            dt = float(got["meta"].get("dt") or got["scenario"].dt)
            ego_rows = ego_xosc if ego_xosc is not None else scene["ego"][3]
            size = got["meta"].get("ego_size") or {"length": 4.8, "width": 2.0}
            k = first_collision_step(got["scenario"], ego_rows, float(size["length"]), float(size["width"]), dt)
            logged = round(float(coll["time"]) / dt)
            out["commonroad_collision"] = {"step": k, "logged_step": logged,
                                           "confirmed": k is not None and abs(k - logged) <= 1}
        if roundtrip:
            data, meta = import_file(written["commonroad"])
            o, ego = rerun(data, meta.get("jitter_seed"), ads)
            out["commonroad_roundtrip"] = reproduces(meta, o, ego_xosc, ego)
    return out


def commonroad_schema_errors(path: Path | str) -> list[str]:
    """CommonRoad's own XSD (shipped with commonroad-io) against the file: its errors."""
    import commonroad
    from lxml import etree

    xsd = Path(commonroad.__file__).parent / "scenario_definition" / "xml_definition_files" / "XML_commonRoad_XSD.xsd"
    schema = etree.XMLSchema(etree.parse(str(xsd)))
    ok = schema.validate(etree.parse(str(path)))
    return [] if ok else [str(e) for e in schema.error_log][:5]
