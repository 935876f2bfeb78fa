"""Writing the extraction: the frames file and the pytest module that replays it.

Frame lines splice the log's raw payload bytes in, so what the tests feed the planner is
byte-for-byte what the log holds. Both files are written to a temporary name and renamed.
"""

from __future__ import annotations

import textwrap
from pathlib import Path
from typing import Any

from deft_gym.bus.codec import encode
from deft_gym.files import write_atomic
from extract.io_filter import PlanningIOFilter
from extract.runtime import finite_or_none
from extract.search import FrameChoice


def frame_line(fc: FrameChoice, pif: PlanningIOFilter) -> bytes:
    """One frame as a JSON line (inputs and expected output are the log's bytes)."""
    o = fc.output
    inputs, seqs = [], []
    for role, j in fc.choice.items():
        tm = pif.inputs[role]
        key = encode(role)
        inputs.append(key + b":" + (tm.raw[j] if j is not None else b"null"))
        seqs.append(key + b":" + (str(int(tm.seq[j])).encode() if j is not None else b"null"))
    d = finite_or_none(fc.distance)
    return b"".join([
        b'{"index":', str(o.index).encode(), b',"time":', encode(fc.time),
        b',"planning_seq":', str(o.seq).encode(), b',"publish_ns":', str(o.publish_ns).encode(),
        b',"distance":', b"null" if d is None else encode(d), b',"stage":', encode(fc.stage),
        b',"input_seqs":{', b",".join(seqs), b'},"inputs":{', b",".join(inputs),
        b'},"expected":', pif.planning.raw[o.msg], b"}\n"])


def write_frames(path: Path, header: dict[str, Any], choices: list[FrameChoice], pif: PlanningIOFilter) -> Path:
    """``frames.jsonl``: the header line, then one line per frame."""
    body = [encode(header) + b"\n"]
    body.extend(frame_line(fc, pif) for fc in choices)
    return write_atomic(path, b"".join(body))


def slug(text: str) -> str:
    """A Python-identifier-safe version of a scenario name (``left_turn~cut3`` -> ``left_turn_cut3``)."""
    out = "".join(c if c.isalnum() else "_" for c in str(text)).strip("_").lower()
    while "__" in out:
        out = out.replace("__", "_")
    if not out or out[0].isdigit():
        out = "s_" + out
    return out


def test_module(header: dict[str, Any], summary: dict[str, Any], frames_name: str, name: str,
                xfail_failures: bool = False) -> str:
    """Source of the pytest module for one episode. ``xfail_failures``: the failure oracle is a
    strict xfail (CI stays green while the failure reproduces; XPASS, a failure, once fixed)."""
    oracles = header.get("oracle") or {}
    faulty, departure, wrong_way, stall, off_road, near_miss, red_light, yellow = (
        oracles.get(key) for key in ("faulty", "departure", "wrong_way", "stall", "off_road", "near_miss",
                                     "red_light", "yellow"))
    coll = summary.get("collision")
    outcome = summary.get("outcome") or "unknown"
    if coll:
        outcome += f" with {coll.get('participant')} at {coll.get('time', 0.0):.2f} s"
    repro = summary["reproduced_at_theta"]
    lines = [
        f"scenario : {summary.get('scenario')}",
        f"log      : {summary.get('log')}" + (f" (jitter seed {summary['jitter_seed']})"
                                               if summary.get("jitter_seed") is not None else ""),
        f"outcome  : {outcome}",
        f"frames   : {summary['frames']} in {frames_name} (mode {summary['mode']}, measure "
        f"{summary['measure']}, theta {summary['theta']:g} m; {repro} reproduced at extraction)",
    ]
    if departure:
        d = departure
        lines.append(f"P_departure: frame {d['index']} (t={d['time']:.3f} s) plans the ego {d['distance']:.2f} m "
                     f"off the optimal path (limit {d['limit']:.2f} m); the ego left it at t={d['left_at']:.2f} s")
    if wrong_way:
        w = wrong_way
        lines.append(f"P_wrong_way: frame {w['index']} (t={w['time']:.3f} s) plans {w['length']:.2f} m of path against "
                     f"the lane direction (limit {w['limit']:.2f} m); the ego was there at t={w['entered_at']:.2f} s")
    if off_road:
        o = off_road
        lines.append(f"P_off_road: frame {o['index']} (t={o['time']:.3f} s) plans the ego's box {o['depth']:.2f} m outside "
                     f"the drivable area (limit {o['limit']:.2f} m) where the ego left it at t={o['left_at']:.2f} s")
    if near_miss:
        n = near_miss
        lines.append(f"P_near_miss: frame {n['index']} (t={n['time']:.3f} s) plans the ego's box {n['gap']:.2f} m from "
                     f"{n['participant']} at t={n['point_time']:.2f} s (clearance {n['clearance']:.2f} m); the ego "
                     f"passed it {n['close_gap']:.2f} m away at t={n['close_at']:.2f} s")
    if red_light:
        r = red_light
        lines.append(f"P_red_light: frame {r['index']} (t={r['time']:.3f} s, light {r['light']} {r['colour']}) plans the "
                     f"ego's front over its stop line at t={r['point_time']:.2f} s, at red; the ego crossed it at "
                     f"t={r['crossed_at']:.2f} s")
    if yellow:
        y = yellow
        lines.append(f"P_yellow: frame {y['index']} (t={y['time']:.3f} s, light {y['light']} yellow) starts {y['ahead']:.1f} m "
                     f"before the line at {y['v0']:.1f} m/s (a stop within {y['decel']:g} m/s^2) and plans on; the ego "
                     f"crossed it at red at t={y['crossed_at']:.2f} s")
    if stall:
        lines.append(f"P_stall : frame {stall['index']} (t={stall['time']:.3f} s) plans {stall['travel']:.3f} m of path "
                     f"(limit {stall['limit']:.2f} m), the first of the {stall['standing_plans']} standing plans that "
                     + ("end the run (timed out), no light holding the ego" if stall.get("timed_out") else
                        "end the run (stuck)"))
    if faulty:
        lines.append(f"P_faulty : frame {faulty['index']} (t={faulty['time']:.3f} s) plans the ego into "
                     f"{faulty['participant']} at t={faulty['point_time']:.2f} s")
    doc = "\n".join(lines)
    src = f'''\
        """DeFT planning-module tests extracted from one system-level run.

        {textwrap.indent(doc, "        ").lstrip()}

        Generated by `python -m extract`; run with `pytest {{this folder}}`. The frames replay in
        order through one fresh planner, so its state carries over as in the live run. Set
        DEFT_PLANNER=module:Class or DEFT_PLANNER_PARAMS='{{"name": value}}' to test another planner.
        """

        from pathlib import Path

        import pytest

        from extract.runtime import EpisodeReplay

        EPISODE = EpisodeReplay(Path(__file__).with_name({frames_name!r}))
        THETA = EPISODE.theta


        @pytest.mark.parametrize("index", EPISODE.reproduction_cases())
        def test_{name}_reproduces(index: int) -> None:
            """The planner's whole output for this frame is the recorded one: positions within
            THETA m, every other trajectory field and the decision within their tolerances. The
            first frame that differs fails; the frames right after it that differ too xfail as its
            consequences; a frame that replays equal passes, and a difference after it fails again."""
            EPISODE.check(index)
        '''
    if faulty:
        mark = ""
        if xfail_failures:
            why = (f"known failure: plans the ego into {faulty['participant']} (frame {faulty['index']}); "
                   "strict: passes (XPASS, a failure) once the planner is fixed")
            mark = f"@pytest.mark.xfail(strict=True, reason={why!r})\n        "
        src += f'''

        {mark}@pytest.mark.parametrize("index", EPISODE.failure_cases())
        def test_{name}_does_not_plan_into_collision(index: int) -> None:
            """Oracle transformation: fails while the planner still plans the ego into the
            participant it hit in the system-level run (P_faulty); passes once it stops."""
            problem = EPISODE.faulty_hit(index)
            assert problem is None, problem
        '''
    for oracle, test, doc in _more_failure_tests(oracles):
        src += f'''

        @pytest.mark.parametrize("index", EPISODE.{oracle}_cases())
        def test_{name}_{test}(index: int) -> None:
            """{doc}"""
            problem = EPISODE.{oracle}_problem(index)
            assert problem is None, problem
        '''
    return textwrap.dedent(src)


def _more_failure_tests(oracles: dict[str, Any]) -> list[tuple[str, str, str]]:
    """``(oracle, test name, docstring)`` of each failure test but P_faulty's that the episode's
    oracle data (a frames header's ``oracle``) holds (its ``EpisodeReplay`` methods are
    ``<oracle>_cases`` and ``<oracle>_problem``)."""
    departure, stall, wrong_way, off_road, near_miss, red_light, yellow = (
        oracles.get(key) for key in ("departure", "stall", "wrong_way", "off_road", "near_miss", "red_light", "yellow"))
    tests = []
    if departure:
        tests.append(("departure", "keeps_to_the_optimal_path",
                      "Non-optimal decision: fails while the planner still plans the ego off the optimal\n"
                      "            path the run was judged against (P_departure, the plan that took it off); passes\n"
                      "            once it keeps within half a lane of it."))
    if stall:
        tests.append(("stall", "plans_progress",
                      "Stuck: fails while the planner still leaves the ego standing where the\n"
                      "            system-level run stood stuck to its end, no light holding it (P_stall, the first of\n"
                      f"            those plans: a path shorter than {stall['limit']:g} m); passes once it plans on.\n"
                      "            Whether standing there was wrong is the reader's call."))
    if wrong_way:
        tests.append(("wrong_way", "keeps_to_its_side_of_the_road",
                      "Driving direction: fails while the planner still plans the ego into lanes that all\n"
                      f"            point against it for {wrong_way['limit']:g} m or more (P_wrong_way, the plan that\n"
                      "            took it there); passes once it keeps to lanes of its own direction."))
    if off_road:
        tests.append(("off_road", "keeps_on_the_road",
                      "Drivable area: fails while the planner still plans the ego's box more than\n"
                      f"            {off_road['limit']:g} m outside the road where the system-level run left it (P_off_road, the\n"
                      f"            plan that took it there; points within {off_road['radius']:g} m of that place); passes once\n"
                      "            the plan keeps on the road there."))
    if near_miss:
        tests.append(("near_miss", "keeps_its_distance",
                      "Near miss: fails while the planner still plans the ego's box within\n"
                      f"            {near_miss['clearance']:g} m of the participant the system-level run passed that close, faster\n"
                      f"            than {near_miss['speed']:g} m/s relative to it (P_near_miss, the first plan of the run that\n"
                      "            put it there; the participant at its recorded positions); passes once the plan keeps\n"
                      "            its distance. Whether the ego could have kept it is the reader's call."))
    if red_light:
        tests.append(("red_light", "stops_at_red",
                      "Red light: fails while the planner still plans the ego's front over the stop line that\n"
                      "            the system-level run crossed at red, at a planned time when the light was red (P_red_light,\n"
                      "            the first plan of the run that did, made after the light turned); passes once it\n"
                      "            stops before the line or is over it before red."))
    if yellow:
        tests.append(("yellow", "stops_for_a_stoppable_yellow",
                      "Yellow light: fails while the planner, at a yellow light it could still stop for within\n"
                      f"            {yellow['decel']:g} m/s^2, plans on to where that stop is no longer possible (P_yellow, the\n"
                      "            first such plan of a run that then crossed the line at red); passes once it keeps\n"
                      "            the stop possible."))
    return tests
