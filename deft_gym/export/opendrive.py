"""ASAM OpenDRIVE 1.7 of a road map (``scenariogeneration``'s ``xodr``).

The roads, lanes and junctions of :mod:`.network`: each road's reference line (a line or an arc)
with its right lanes (width, road marks from the map's line types, lane links), its type with
the speed limit, the connecting roads of each junction with their lane links, and every
intersection approach's traffic light (type ``1000001``, dynamic) and stop line (type ``294``)
at its stop line. The map's own description (its family and options: what rebuilds it exactly)
is the header's ``userData`` (code ``deft_gym.map``), which :mod:`.roundtrip` reads back.
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

from deft_gym.export.network import Network, Road, build_network
from deft_gym.world.roadmap import RoadMap

MAP_CODE = "deft_gym.map"  #: header userData code of the map's description (MapSpec)
XODR_REV = ("1", "7")


def _road(r: Road, net: Network, rule: str) -> Any:
    from scenariogeneration import xodr

    pv = xodr.PlanView(r.ref.x, r.ref.y, r.ref.hdg)
    pv.add_geometry(xodr.Line(r.ref.length) if r.ref.curvature == 0.0 else xodr.Arc(r.ref.curvature, r.ref.length))
    mark = {"solid": xodr.RoadMarkType.solid, "broken": xodr.RoadMarkType.broken}
    center = xodr.Lane(lane_type=xodr.LaneType.none)
    if r.marks[0] in mark:
        center.add_roadmark(xodr.RoadMark(mark[r.marks[0]], 0.12))
    section = xodr.LaneSection(0, center)
    for k in range(r.n):
        lane = xodr.Lane(lane_type=xodr.LaneType.driving, a=r.width)
        if r.marks[k + 1] in mark:
            lane.add_roadmark(xodr.RoadMark(mark[r.marks[k + 1]], 0.12))
        oid = -(k + 1)
        pred, succ = _lane_links(r, net, oid)
        if pred is not None:
            lane.add_link("predecessor", pred)
        if succ is not None:
            lane.add_link("successor", succ)
        section.add_right_lane(lane)
    lanes = xodr.Lanes()
    lanes.add_lanesection(section)
    road = xodr.Road(r.id, pv, lanes, road_type=r.junction, name=r.name,
                     rule=xodr.TrafficRule.RHT if rule == "RHT" else xodr.TrafficRule.LHT)
    kind = xodr.RoadType.motorway if net.roadmap.spec.type == "highway" else xodr.RoadType.town
    road.add_type(kind, 0, speed=r.speed_limit, speed_unit="m/s")
    # road links: a road into (or out of) a junction links to the junction; a connecting road and a
    # road after a plain road link to the road
    for side, others in (("predecessor", r.predecessors), ("successor", r.successors)):
        if not others:
            continue
        add = road.add_predecessor if side == "predecessor" else road.add_successor
        other = net.road(others[0])
        if r.junction < 0 and (len(others) > 1 or other.junction >= 0):
            add(xodr.ElementType.junction, other.junction)
        else:
            cp = xodr.ContactPoint.end if side == "predecessor" else xodr.ContactPoint.start
            add(xodr.ElementType.road, other.id, cp)
    for sig in net.signals:
        if sig.road != r.id:
            continue
        if sig.kind == "light":
            s = xodr.Signal(sig.s, sig.t, "DE", "1000001", "-1", id=str(sig.id), name=sig.light_id,
                            dynamic=xodr.Dynamic.yes, orientation=xodr.Orientation.positive, zOffset=2.0,
                            height=0.9, width=0.3)
        else:
            s = xodr.Signal(sig.s, sig.t, "DE", "294", "-1", id=str(sig.id), name=f"stop line {sig.light_id}",
                            dynamic=xodr.Dynamic.no, orientation=xodr.Orientation.positive, zOffset=0.0)
        s.add_validity(min(sig.lanes), max(sig.lanes))
        road.add_signal(s)
    return road


def _lane_links(r: Road, net: Network, lane: int) -> tuple[int | None, int | None]:
    """The lane's predecessor and successor lane ids where the road links to a road (links into a
    junction are the junction's)."""
    out: list[int | None] = []
    for links, others in ((r.lane_pred, r.predecessors), (r.lane_succ, r.successors)):
        if not others or (r.junction < 0 and (len(others) > 1 or net.road(others[0]).junction >= 0)):
            out.append(None)
            continue
        ids = [lid for rid, lid in links.get(lane, []) if rid == others[0]]
        out.append(ids[0] if ids else None)
    return out[0], out[1]


def opendrive(roadmap: RoadMap, name: str = "deft_gym", net: Network | None = None) -> Any:
    """The ``xodr.OpenDrive`` of ``roadmap``."""
    from scenariogeneration import xodr

    net = net or build_network(roadmap)
    # scenariogeneration keeps the signal ids it has seen in a class-wide registry and renames a
    # repeated id: every document starts afresh, so that the ids are the network's
    for registry in (xodr.Signal._usedIDs, xodr.Signal._IDCounter):
        registry.pop("Signal", None)
    odr = xodr.OpenDrive(name, *XODR_REV)
    for r in net.roads:
        odr.add_road(_road(r, net, "RHT"))
    for jid, members in net.junctions.items():
        j = xodr.Junction(f"junction {jid}", jid)
        for rid in members:
            cr = net.road(rid)
            for iid in cr.predecessors:
                inc = net.road(iid)
                conn = xodr.Connection(iid, rid, xodr.ContactPoint.start)
                for lane, targets in sorted(inc.lane_succ.items(), reverse=True):
                    for tr, tl in targets:
                        if tr == rid:
                            conn.add_lanelink(lane, tl)
                j.add_connection(conn)
        odr.add_junction(j)
    for road in odr.roads.values():
        road.planview.adjust_geometries()
    got = sorted(str(s.id) for road in odr.roads.values() for s in road.signals)
    if got != sorted(str(s.id) for s in net.signals):
        raise RuntimeError(f"signal ids changed while building the OpenDRIVE document: {got}")
    return odr


def xodr_element(roadmap: RoadMap, name: str = "deft_gym") -> ET.Element:
    """The OpenDRIVE document of ``roadmap`` as an element tree, with the map's description in
    the header's ``userData`` and the header's bounds."""
    root = opendrive(roadmap, name).get_element()
    header = root.find("header")
    assert header is not None
    x0, y0, x1, y1 = roadmap.bounds  # world frame: y flips
    pad = max(g.width for g in roadmap.geoms.values())
    header.set("north", repr(-y0 + pad))
    header.set("south", repr(-y1 - pad))
    header.set("east", repr(x1 + pad))
    header.set("west", repr(x0 - pad))
    header.set("vendor", "DeFT-Gym")
    header.set("date", header.get("date", "").replace(" ", "T").split(".")[0])
    ud = ET.SubElement(header, "userData", {"code": MAP_CODE,
                                             "value": json.dumps(roadmap.spec.model_dump(mode="json"), sort_keys=True)})
    ud.tail = None
    return root


def write_xodr(roadmap: RoadMap, path: Path | str, name: str = "deft_gym") -> Path:
    """Write the OpenDRIVE file of ``roadmap`` to ``path``."""
    from deft_gym.files import write_atomic

    root = xodr_element(roadmap, name)
    ET.indent(root)
    data = b'<?xml version="1.0" encoding="utf-8"?>\n' + ET.tostring(root, encoding="utf-8")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, data)
    return path


def read_map_spec(path: Path | str) -> dict[str, Any] | None:
    """The map description an exported ``.xodr`` carries (None when it has none)."""
    root = ET.parse(path).getroot()
    for ud in root.iter("userData"):
        if ud.get("code") == MAP_CODE and ud.get("value"):
            return json.loads(ud.get("value") or "{}")
    return None
