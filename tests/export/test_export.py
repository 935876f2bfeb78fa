"""The export checked by independent tools (the ``export`` extra; ``make test`` installs it):

- every ``.xodr`` and ``.xosc`` passes ASAM's schema and quality checkers with 0 errors (and the
  checkers do find errors in a damaged file, so a pass means something);
- the CommonRoad file validates against CommonRoad's XSD and reads back with commonroad-io, and
  CommonRoad's drivability checker finds the logged collision within one step;
- parsed back, every trajectory matches the log's ground truth within 1 cm and 0.01 rad;
- the round trip (import, rerun on the jitter seed) reproduces the logged outcome;
- ``deft-gym export`` / ``deft-gym import`` do it from the command line, and the report links it.

One colliding episode of a left turn with a vehicle cutting in (tests/support/data/left_turn_cut_in.yaml
on the legacy testbed, jitter seed 1000: collision with cut_in_7)
and one lane-following episode with a cone and a parked vehicle added mid-run are recorded once
per module; each costs about a second to simulate.
"""

from __future__ import annotations

import json
import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("scenariogeneration")
pytest.importorskip("commonroad")
pytest.importorskip("commonroad_dc")
pytest.importorskip("qc_opendrive")
pytest.importorskip("qc_openscenario")

from deft_gym.config import CONFIG_DIR
from deft_gym.export.checks import errors, qc_issues
from deft_gym.export.episode import from_log, read_log
from deft_gym.export.failures import (
    check_export,
    commonroad_schema_errors,
    export_paths,
    reproduces,
    rerun,
    trajectory_errors,
    write_exports,
)
from deft_gym.export.opendrive import write_xodr
from deft_gym.world.roadmap import RoadMap

FLAKY = Path(__file__).resolve().parents[1] / "support" / "data" / "left_turn_cut_in.yaml"
LEGACY = CONFIG_DIR / "ads" / "legacy.yaml"  # where FLAKY collides (pure pursuit cuts the turn)


@pytest.fixture(scope="module")
def collision(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Path]]:
    """The left turn with a cut-in on the legacy testbed, jitter seed 1000 (it collides), exported
    in both formats."""
    from deft_gym.bus.ads import load_ads_config
    from deft_gym.sim.simulation import run_episode

    out = tmp_path_factory.mktemp("flaky") / "0"
    res = run_episode(FLAKY, load_ads_config(LEGACY), jitter_seed=1000, out_dir=out)
    assert res.outcome.collision is not None, "the left turn with a cut-in no longer collides on jitter seed 1000"
    log = Path(res.log_path)
    return log, write_exports(from_log(log), export_paths(log))


@pytest.fixture(scope="module")
def late(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Path]]:
    """Lane following with a parked vehicle and a cone added mid-run (as the RL adversary adds
    them), exported."""
    from deft_gym.sim.simulation import Simulation

    out = tmp_path_factory.mktemp("late")
    sim = Simulation(CONFIG_DIR / "scenarios" / "lane_follow_static.yaml", jitter_seed=3, out_dir=out)
    sim.start()
    sim.advance(2.0)
    sim.add_participant({"id": "late_parked", "type": "static", "obstacle": "STATIC_VEHICLE", "lane": ["a", "b", 1],
                         "s": 140.0})
    sim.advance(3.5)
    sim.add_participant({"id": "late_cone", "type": "static", "obstacle": "CONE", "lane": ["b", "c", 1], "s": 30.0,
                         "d": 1.2})
    sim.advance(40.0)
    log = Path(sim.finish().log_path)
    return log, write_exports(from_log(log), export_paths(log))


@pytest.mark.parametrize("spec", [{"type": "intersection", "lanes": 3, "turn_lanes": 2, "right_turn_lanes": 2},
                                  {"type": "highway", "lanes": 3}, {"type": "uturn", "turn_lanes": 2}],
                         ids=["intersection", "highway", "uturn"])
def test_every_map_family_passes_asam_opendrive_checks(spec: dict, tmp_path: Path) -> None:
    path = write_xodr(RoadMap(spec), tmp_path / "map.xodr")
    assert errors(qc_issues(path)) == []


def test_the_checkers_find_errors_in_damaged_files(collision, tmp_path: Path) -> None:
    _, files = collision
    xodr = ET.parse(files["xodr"])
    root = xodr.getroot()
    root.remove(root.find("road"))  # a junction now connects a road that is not there
    bad_xodr = tmp_path / "bad.xodr"
    xodr.write(bad_xodr)
    assert errors(qc_issues(bad_xodr))
    xosc = ET.parse(files["xosc"])
    next(xosc.getroot().iter("EntityRef")).set("entityRef", "nobody")  # an actor that is not an entity
    xosc.getroot().find("RoadNetwork/LogicFile").set("filepath", str(files["xodr"]))
    bad_xosc = tmp_path / "bad.xosc"
    xosc.write(bad_xosc)
    assert errors(qc_issues(bad_xosc))
    xosc.getroot().find("RoadNetwork/LogicFile").set("filepath", str(tmp_path / "missing.xodr"))
    xosc.write(bad_xosc)  # a checker that cannot run (no road network to resolve signals) is an error too
    assert any("skipped" in e["description"] for e in errors(qc_issues(bad_xosc)))


def test_the_episode_is_simulated_again_and_agrees_with_its_log(collision) -> None:
    log, _ = collision
    e = from_log(log)
    check = e.source["check"]
    assert check["outcome_agrees"] and check["missing_count"] == 0 and check["samples"] > 300
    assert check["max_position_error"] < 0.002 and check["max_heading_error"] < 1e-5  # the log keeps millimetres
    assert e.source["trajectories"].startswith("simulated again at every world step")
    assert np.allclose(np.diff(e.ego.rows[:, 0]), 0.05) and e.ego.rows[0, 0] == 0.0
    assert e.ego.rows[-1, 0] == pytest.approx(e.collision["time"])


def test_openscenario_and_opendrive_pass_asam_checks(collision) -> None:
    _, files = collision
    for key in ("xodr", "xosc"):
        assert errors(qc_issues(files[key])) == [], key
    root = ET.parse(files["xosc"]).getroot()
    assert root.find("FileHeader").get("revMajor") == "1" and root.find("FileHeader").get("revMinor") == "2"
    assert ET.parse(files["xodr"]).getroot().find("header").get("revMinor") == "7"
    assert len(list(root.iter("FollowTrajectoryAction"))) == 4  # the ego and the three vehicles
    assert root.find(".//TimeReference/Timing").get("domainAbsoluteRelative") == "absolute"
    stop = root.find("Storyboard/StopTrigger//SimulationTimeCondition")
    props = {p.get("name"): p.get("value") for p in root.iterfind("FileHeader/Properties/Property")}
    assert float(stop.get("value")) == pytest.approx(float(props["deft_gym:collision.time"]))
    assert props["deft_gym:collision.participant"] == "cut_in_7" and props["deft_gym:failure"] == "collision"
    assert len(list(root.iter("Phase"))) >= 6 and len(list(ET.parse(files["xodr"]).getroot().iter("signal"))) == 8


def test_commonroad_reads_back_and_the_drivability_checker_finds_the_collision(collision) -> None:
    from deft_gym.export.commonroad import first_collision_step, read_commonroad
    from deft_gym.export.openscenario import read_xosc

    log, files = collision
    assert commonroad_schema_errors(files["commonroad"]) == []
    got = read_commonroad(files["commonroad"])
    sc, problems = got["scenario"], got["problems"]
    roadmap = from_log(log, resimulate=False).roadmap
    assert len(sc.lanelet_network.lanelets) == len(roadmap.lane_ids) == 32
    assert len(sc.lanelet_network.traffic_lights) == 4 and len(sc.lanelet_network.intersections) == 1
    assert len(sc.dynamic_obstacles) == 3 and len(sc.static_obstacles) == 1
    assert len(problems.planning_problem_dict) == 1
    _, oc, _ = read_log(log)
    ego = next(a for a in read_xosc(files["xosc"])["actors"] if a.kind == "ego")
    step = first_collision_step(sc, ego.rows, ego.length, ego.width, sc.dt)
    assert step is not None and abs(step - round(oc["collision"]["time"] / sc.dt)) <= 1
    # and before the logged collision the ego is clear of every obstacle
    assert first_collision_step(sc, ego.rows[:-2], ego.length, ego.width, sc.dt) is None


@pytest.mark.parametrize("fixture", ["collision", "late"])
def test_parsed_back_trajectories_match_the_log(fixture: str, request) -> None:
    from deft_gym.export.commonroad import read_commonroad
    from deft_gym.export.openscenario import read_xosc

    log, files = request.getfixturevalue(fixture)
    _, _, scene = read_log(log)
    for got in (read_xosc(files["xosc"]), read_commonroad(files["commonroad"])):
        err = trajectory_errors(got["actors"], scene)
        assert err["samples"] > 100 and err["uncovered"] == 0
        assert err["max_position_error"] <= 0.01 and err["max_heading_error"] <= 0.01


def test_the_round_trip_reproduces_the_collision(collision) -> None:
    from deft_gym.bus.ads import load_ads_config
    from deft_gym.export.openscenario import read_xosc
    from deft_gym.export.roundtrip import import_file

    _, files = collision
    ego = next(a for a in read_xosc(files["xosc"])["actors"] if a.kind == "ego").rows
    for path in (files["xosc"], files["commonroad"]):
        data, meta = import_file(path)
        kinds = {p["id"]: p["type"] for p in data["participants"]}
        assert kinds == {"oncoming": "scripted", "waiting_west": "scripted", "cone_exit": "static",
                         "cut_in_7": "scripted"}  # the reactive vehicles replay their trajectories
        outcome, ego_rerun = rerun(data, meta["jitter_seed"], load_ads_config(LEGACY))
        r = reproduces(meta, outcome, ego, ego_rerun)
        assert r["reproduced"] and r["collision"] == "cut_in_7", (path, r)
        assert r["same_path"], (path, r)


def test_objects_added_mid_run_appear_when_they_did(late) -> None:
    from deft_gym.export.commonroad import read_commonroad
    from deft_gym.export.openscenario import read_xosc
    from deft_gym.export.roundtrip import import_file

    _, files = late
    root = ET.parse(files["xosc"]).getroot()
    adds = {ev.find(".//AddEntityAction/..").get("entityRef"): float(ev.find(".//SimulationTimeCondition").get("value"))
            for ev in root.iter("Event") if ev.find(".//AddEntityAction") is not None}
    assert adds == {"late_parked": 2.0, "late_cone": 3.5}
    assert errors(qc_issues(files["xosc"])) == [] and commonroad_schema_errors(files["commonroad"]) == []
    cr = {a.id: a for a in read_commonroad(files["commonroad"])["actors"]}
    assert cr["late_parked"].rows[0, 0] == pytest.approx(2.0) and cr["late_cone"].rows[0, 0] == pytest.approx(3.5)
    assert {a.id: a.added for a in read_xosc(files["xosc"])["actors"] if a.added} == {"late_parked": 2.0,
                                                                                     "late_cone": 3.5}
    data, meta = import_file(files["xosc"])
    spec = {p["id"]: p for p in data["participants"]}
    assert spec["late_parked"]["type"] == "scripted" and spec["late_parked"]["waypoints"][0]["t"] == 2.0
    outcome, _ = rerun(data, meta["jitter_seed"])
    assert outcome["outcome"] == meta["outcome"]


def test_export_and_import_commands(collision, tmp_path: Path, capsys) -> None:
    import shutil

    from deft_gym.cli.export import main as export_main
    from deft_gym.cli.import_scenario import main as import_main
    from deft_gym.cli.report import write_report

    log, _ = collision
    run = tmp_path / "run"
    shutil.copytree(log.parent, run / "0")
    (run / "1").mkdir()  # a passing episode is no failure: nothing to export
    assert export_main([str(run), "--check", "--quiet"]) == 0
    assert "1 of 1 episode(s) exported" in capsys.readouterr().out
    for name in ("episode.xosc", "episode.xodr", "episode.cr.xml", "episode.export.json"):
        assert (run / "0" / name).exists(), name
    rec = json.loads((run / "0" / "episode.export.json").read_text())
    c = rec["check"]
    assert c["xosc_errors"] == 0 and c["xodr_errors"] == 0 and c["commonroad_collision"]["confirmed"]
    assert c["xosc_roundtrip"]["reproduced"] and c["commonroad_roundtrip"]["reproduced"]
    assert import_main([str(run / "0" / "episode.cr.xml"), "--rerun", "--ads-config", str(LEGACY)]) == 0
    text = capsys.readouterr().out
    assert "reproduced" in text and "--jitter-seed 1000" in text and (run / "0" / "episode.cr.yaml").exists()
    from deft_gym.scenarios.scenario import load_scenario

    assert load_scenario(run / "0" / "episode.cr.yaml").name == "left_turn_cut_in-import"
    assert import_main([str(tmp_path / "nothing.xosc")]) == 2
    (tmp_path / "not.xml").write_text("<a/>")
    assert import_main([str(tmp_path / "not.xml")]) == 2
    # the report's failure card links the exports (a run folder needs its summary)
    (run / "summary.json").write_text(json.dumps({"scenario": "left_turn_cut_in", "scenario_file": str(FLAKY),
                                                  "reruns": [_rerun_row(log, run)]}))
    html = write_report(run, draw=False).read_text()
    assert 'href="0/episode.xosc"' in html and 'href="0/episode.cr.xml"' in html


def _rerun_row(log: Path, run: Path) -> dict:
    _, oc, _ = read_log(log)
    return {"rerun": 0, "outcome": oc["outcome"], "collision": True, "collision_detail": oc["collision"],
            "jitter_seed": 1000, "sim_time": oc["sim_time"], "log": str(run / "0" / "episode.mcap"),
            "divergence": {"identical": 0, "paired": 0}}


def test_a_scenario_exports_after_one_run(tmp_path: Path, capsys) -> None:
    from deft_gym.cli.export import main as export_main

    out = tmp_path / "x"
    assert export_main(["u_turn", "--jitter-seed", "2", "--out", str(out), "--format", "xosc", "--quiet"]) == 0
    assert (out / "episode.xosc").exists() and not (out / "episode.cr.xml").exists()
    assert errors(qc_issues(out / "episode.xosc")) == [] and errors(qc_issues(out / "episode.xodr")) == []


@pytest.mark.slow
def test_every_seed_scenario_exports_clean_and_round_trips(tmp_path: Path) -> None:
    """Every seed scenario, one run each: 0 checker errors, trajectories within 1 cm / 0.01 rad,
    the drivability checker's collision, the round trip's outcome."""
    from deft_gym.scenarios.scenario import list_scenarios
    from deft_gym.sim.simulation import run_episode

    for sc in list_scenarios():
        log = Path(run_episode(sc, jitter_seed=11, out_dir=tmp_path / sc.stem).log_path)
        c = check_export(log, write_exports(from_log(log), export_paths(log)))
        assert c["xosc_errors"] == 0 and c["xodr_errors"] == 0 and c["commonroad_schema"] == [], sc.stem
        for key in ("xosc_trajectories", "commonroad_trajectories"):
            assert c[key]["max_position_error"] <= 0.01 and c[key]["max_heading_error"] <= 0.01, (sc.stem, key)
        assert c.get("commonroad_collision", {"confirmed": True})["confirmed"], sc.stem
        assert c["xosc_roundtrip"]["reproduced"] and c["commonroad_roundtrip"]["reproduced"], sc.stem
        assert math.isfinite(c["xosc_roundtrip"]["ego_max_deviation"])
