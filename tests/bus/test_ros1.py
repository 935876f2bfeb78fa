"""Binary payloads (deft_gym/bus/ros1.py): ROS 1 bytes laid out by the JSON schemas, read back to
the same values (every float bit), the compiled encoder byte for byte the Python one, a payload
that does not fit written as JSON on a second channel of its topic, and the logs readable by
genpy's ROS 1 decoder (mcap-ros1-support), as ROS tools and Foxglove read them."""

from __future__ import annotations

import math
import random
import struct
from pathlib import Path

import numpy as np
import orjson
import pytest
from mcap.reader import make_reader

from deft_gym.bus import ros1
from deft_gym.bus.codec import encode as encode_json
from deft_gym.bus.messages import DEFAULT_TOPICS, SCHEMAS, Message
from deft_gym.record.recorder import McapRecorder
from tests.support.fixtures import same_values

LAYOUTS = ros1.role_layouts(SCHEMAS)
ODD_FLOATS = [0.0, -0.0, 1e-310, -5e-324, 1.7976931348623157e308, math.nan, math.inf, -math.inf, 0.1, 1 / 3]


def _python(program: ros1.Program, payload) -> bytes | None:
    out = bytearray()
    try:
        return bytes(out) if ros1._put(program, payload, out) else None
    except (TypeError, UnicodeEncodeError, OverflowError, struct.error):
        return None




def _prediction(rng: random.Random, n: int) -> dict:
    obs = []
    for i in range(n):
        k = rng.randint(1, 31)
        ob = {"id": i, "type": rng.choice(["VEHICLE", "CONE", "Straße", ""]), "length": rng.random() * 5,
              "width": 2.0, "t0": rng.random(), "dt": 0.2, "v": rng.choice(ODD_FLOATS), "is_static": rng.random() < 0.5,
              "x": [rng.uniform(-1e3, 1e3) for _ in range(k)], "y": [rng.choice(ODD_FLOATS) for _ in range(k)],
              "heading": [rng.gauss(0, 3) for _ in range(k)]}
        if rng.random() < 0.3:
            ob["intent"] = rng.choice(["left", "right"])
        obs.append(ob)
    return {"header": {"seq": rng.randint(0, 2**63 - 1), "stamp": rng.random(), "module": "prediction"},
            "perception_stamp": rng.random(), "obstacles": obs}


def _misfits(p: dict) -> list[dict]:
    """Copies of a prediction payload that the layout must refuse."""
    import copy

    out = []
    for change in ("int_for_float", "bool_for_int", "numpy_float", "tuple_series", "missing", "extra_top", "order",
                   "big_int", "surrogate", "nan_in_rest", "none_in_rest", "float_for_int", "str_for_float"):
        q = copy.deepcopy(p)
        ob = q["obstacles"][0]
        if change == "int_for_float":
            ob["length"] = 4
        elif change == "bool_for_int":
            ob["id"] = True
        elif change == "numpy_float":
            ob["x"][0] = np.float64(1.0)
        elif change == "tuple_series":
            ob["y"] = tuple(ob["y"])
        elif change == "missing":
            del ob["dt"]
        elif change == "extra_top":
            q["unexpected"] = 1
        elif change == "order":
            q["obstacles"][0] = dict(reversed(list(ob.items())))
        elif change == "big_int":
            q["header"]["seq"] = 2**63
        elif change == "surrogate":
            ob["type"] = "\ud800"
        elif change == "nan_in_rest":
            ob["intent"] = math.nan
        elif change == "none_in_rest":
            ob["intent"] = None
        elif change == "float_for_int":
            q["header"]["seq"] = 1.0
        elif change == "str_for_float":
            q["perception_stamp"] = "0.1"
        out.append(q)
    return out


def test_the_layouts_follow_the_schemas() -> None:
    """Every bus role with a fixed shape has a layout; routing and the map (lane ids mix strings
    and an int) stay JSON; optional keys (a plan's decision and debug, a predicted obstacle's
    intent) travel as JSON inside; the schema text parses back to the same layout."""
    assert set(LAYOUTS) == set(SCHEMAS) - {"routing", "map"}
    assert LAYOUTS["planning"].rest and not LAYOUTS["localization"].rest
    assert [k for k, *_ in LAYOUTS["planning"].fields] == ["header", "trajectory"]
    obstacle = LAYOUTS["prediction"].fields[2][2]
    assert obstacle.rest and "intent" not in [k for k, *_ in obstacle.fields]
    for layout in LAYOUTS.values():
        text = layout.definition()
        assert b"float64 stamp  # [s] " in text  # units and descriptions in the comments
        assert ros1.parse_definition(text).program == layout.program


def test_random_payloads_round_trip_bit_exactly_and_c_matches_python() -> None:
    rng = random.Random(5)
    program = LAYOUTS["prediction"].program
    decode = ros1.decoder(LAYOUTS["prediction"].definition())
    for i in range(300):
        p = _prediction(rng, rng.randint(0, 6))
        data = ros1.encode(program, p)
        assert data is not None and data == _python(program, p)
        back = decode(data)
        assert same_values(back, p)
        assert ros1.json_bytes(decode, data) == encode_json(p)  # what a JSON log holds, NaN tags included
        if p["obstacles"]:
            for q in _misfits(p):
                assert ros1.encode(program, q) is None and _python(program, q) is None, i


def test_the_compiled_decoder_gives_the_python_values_and_refuses_what_python_refuses() -> None:
    """Random payloads, then every prefix of some and 2,000 single-byte corruptions: the compiled
    decoder and the Python one give the same values (floats bit for bit) or both ValueError."""
    rng = random.Random(11)
    layout = LAYOUTS["prediction"]
    compiled, python = ros1.decoder(layout.definition()), ros1.python_decoder(layout)
    assert compiled is not python

    def outcome(decode, data):
        try:
            return decode(data)
        except ValueError:
            return ValueError

    for i in range(200):
        data = ros1.encode(layout.program, _prediction(rng, rng.randint(0, 4)))
        assert same_values(compiled(data), python(data))
        cuts = range(len(data)) if i < 3 else [rng.randrange(len(data))]
        for k in cuts:
            got = outcome(compiled, data[:k])
            assert got is ValueError and outcome(python, data[:k]) is ValueError
        for _ in range(10):
            bad = bytearray(data)
            bad[rng.randrange(len(bad))] = rng.randrange(256)
            a, b = outcome(compiled, bytes(bad)), outcome(python, bytes(bad))
            assert (a is ValueError and b is ValueError) or same_values(a, b)
        assert outcome(compiled, data + b"\0") is ValueError


def test_the_compiled_encoder_is_the_one_in_use() -> None:
    """The kernel is built and current (make test builds it): otherwise this file tests Python alone.
    (Skipped only where it could not be built at all: the build is optional.)"""
    pytest.importorskip("deft_gym.bus._ros1_c")
    assert ros1._kernel is not None and ros1.encode_fast is ros1._ros1_c.encode


@pytest.mark.parametrize("bad", [b"", b"\x00" * 7, None])
def test_bytes_that_are_not_a_message_raise_value_error(bad) -> None:
    decode = ros1.decoder(LAYOUTS["localization"].definition())
    good = ros1.encode(LAYOUTS["localization"].program, {"header": {"seq": 1, "stamp": 0.5, "module": "m"}, "x": 1.0,
                                                         "y": 2.0, "heading": 0.0, "v": 3.0, "a": 0.0, "yaw_rate": 0.0})
    assert decode(good)["v"] == 3.0
    with pytest.raises(ValueError, match="ros1 schema"):
        decode(good + b"\x00" if bad is None else bad)
    with pytest.raises(ValueError, match="expected 'json', or 'ros1'"):
        ros1.payload_decoder("protobuf")


def _payloads() -> dict[str, list[dict]]:
    from deft_gym.bus.ads import load_ads_config
    from deft_gym.scenarios.scenario import load_scenario
    from deft_gym.sim.simulation import Simulation

    role_of = {t: r for r, t in DEFAULT_TOPICS.items()}
    out: dict[str, list[dict]] = {}
    sim = Simulation(load_scenario("left_turn"), load_ads_config(), jitter_seed=7, out_dir=None, keep_planning=False)
    sim.bus.taps.append(lambda m: out.setdefault(role_of.get(m.topic, m.topic), []).append(m.payload))
    sim.run()
    return out


def test_every_message_of_a_run_fits_its_layout_and_reads_back_as_its_json() -> None:
    payloads = _payloads()
    for role, layout in LAYOUTS.items():
        decode = ros1.decoder(layout.definition())
        assert payloads[role], role
        for p in payloads[role]:
            data = ros1.encode(layout.program, p)
            assert data is not None, role  # the modules write their schema's shape
            assert data == _python(layout.program, p)
            assert orjson.dumps(decode(data)) == encode_json(p)


def test_a_message_that_does_not_fit_goes_as_json_on_a_second_channel(tmp_path: Path) -> None:
    """An injected exceptional value (a string for a float) cannot be ROS 1 bytes: that message is
    JSON on a JSON channel of the same topic (with the role's JSON schema), in publish order with
    the rest; the extractor's reader gives every message as the JSON a JSON log holds, and a log
    written with encoding json holds those very bytes."""
    from extract.logs import read_log

    topic = DEFAULT_TOPICS["localization"]
    good = {"header": {"seq": 0, "stamp": 0.0, "module": "localization"}, "x": 1.0, "y": 2.0, "heading": 0.5,
            "v": 3.0, "a": 0.0, "yaw_rate": -0.0}
    odd = {**good, "header": {**good["header"], "seq": 1}, "v": "fast"}
    nan = {**good, "header": {**good["header"], "seq": 2}, "x": math.nan}
    raws = {}
    for encoding in ("ros1", "json"):
        path = tmp_path / f"{encoding}.mcap"
        rec = McapRecorder(path, DEFAULT_TOPICS, {}, background=False, encoding=encoding)
        for seq, p in enumerate([good, odd, nan, good]):
            rec(Message(topic, seq, seq * 10_000_000, p))
        rec.close()
        with open(path, "rb") as f:
            chans = [(sc.encoding if sc else "", ch.message_encoding) for sc, ch, _ in make_reader(f).iter_messages()]
        expect = [("ros1msg", "ros1"), ("jsonschema", "json"), ("ros1msg", "ros1"), ("ros1msg", "ros1")]
        assert chans == (expect if encoding == "ros1" else [("jsonschema", "json")] * 4)
        tm = read_log(path, [topic]).topics[topic]
        raws[encoding] = tm.raw
        assert tm.seq.tolist() == [0, 1, 2, 3] and tm.payload(1)["v"] == "fast" and math.isnan(tm.payload(2)["x"])
    assert raws["ros1"] == raws["json"]


def test_a_recorded_log_reads_the_same_with_genpy(lane_follow_log) -> None:
    """genpy's decoder (mcap-ros1-support, the ROS 1 reference implementation) reads every binary
    message of a recorded run to the values deft_gym's decoder gives."""
    from mcap_ros1.decoder import DecoderFactory

    from deft_gym.bus.ros1 import ChannelDecoders

    factory, ours, n = DecoderFactory(), ChannelDecoders(), 0

    def plain(m):
        if hasattr(m, "__slots__"):
            out = {k: plain(getattr(m, k)) for k in m.__slots__}
            extra = out.pop(ros1.REST_FIELD, None)
            return {**out, **orjson.loads(extra)} if extra else out
        return [plain(x) for x in m] if isinstance(m, list | tuple) else m

    with open(lane_follow_log.log_path, "rb") as f:
        for sc, ch, m in make_reader(f).iter_messages():
            if ch.message_encoding != "ros1":
                continue
            assert same_values(plain(factory.decoder_for("ros1", sc)(m.data)), ours(sc, ch, m.data)), ch.topic
            n += 1
    assert n > 1000


def test_the_foxglove_layout_reads_fields_the_log_has(lane_follow_log) -> None:
    """Every topic path of configs/foxglove/layout.json names a topic of a recorded log and a field
    its messages have as Foxglove sees them (ROS 1 fields by genpy; the planner's decision is in
    the planning message's json_rest since the payloads are binary)."""
    import json
    import re

    from mcap_ros1.decoder import DecoderFactory

    from deft_gym.config import CONFIG_DIR

    layout = json.loads((CONFIG_DIR / "foxglove" / "layout.json").read_text())
    paths: set[str] = set()

    def walk(o):
        if isinstance(o, dict):
            for k, v in o.items():
                if k in ("topicPath", "value") and isinstance(v, str) and v.startswith("/apollo"):
                    paths.add(v)
                walk(v)
        elif isinstance(o, list):
            for v in o:
                walk(v)

    walk(layout)
    assert "/apollo/planning.json_rest" in paths and len(paths) >= 3
    first: dict[str, object] = {}
    factory = DecoderFactory()
    with open(lane_follow_log.log_path, "rb") as f:
        for sc, ch, m in make_reader(f).iter_messages():
            if ch.topic not in first:
                first[ch.topic] = (factory.decoder_for("ros1", sc)(m.data) if ch.message_encoding == "ros1"
                                   else orjson.loads(m.data))
    for path in paths:
        topic, *fields = path.split(".")
        value = first[topic]
        for f in fields:
            name, index = re.fullmatch(r"(\w+)(?:\[(\d+)\])?", f).groups()
            value = value[name] if isinstance(value, dict) else getattr(value, name)
            if index is not None:
                value = value[int(index)]
        assert value is not None, path


FOXGLOVE_JS = Path(__file__).resolve().parents[1] / "support" / "foxglove_ros1.js"
FOXGLOVE_MODULES = Path(__file__).resolve().parents[2] / ".foxglove" / "node_modules"


@pytest.mark.slow
def test_foxglove_reads_every_binary_message_as_deft_gym_does(tmp_path: Path) -> None:
    """Foxglove's own ROS 1 parser and reader (@foxglove/rosmsg, @foxglove/rosmsg-serialization:
    `make foxglove` installs them) read every binary message of a recorded run to deft_gym's
    values. Slow and needs Node.js: `make test-foxglove`."""
    import base64
    import json
    import shutil
    import subprocess

    from deft_gym.bus.ros1 import ChannelDecoders
    from deft_gym.sim.simulation import run_episode

    node = shutil.which("node")
    if node is None or not (FOXGLOVE_MODULES / "@foxglove" / "rosmsg-serialization").is_dir():
        pytest.skip("Node.js and Foxglove's ROS 1 libraries are not installed (make foxglove)")
    run_episode("left_turn", jitter_seed=7, out_dir=tmp_path, keep_planning=False)
    out: dict = {"schemas": {}, "messages": []}
    decoders = ChannelDecoders()
    with open(tmp_path / "episode.mcap", "rb") as f:
        for sc, ch, m in make_reader(f).iter_messages():
            if ch.message_encoding == "ros1":
                out["schemas"][sc.name] = sc.data.decode()
                out["messages"].append({"schema": sc.name, "data": base64.b64encode(m.data).decode(),
                                        "ours": base64.b64encode(decoders.json(sc, ch, m.data)).decode()})
    (tmp_path / "messages.json").write_text(json.dumps(out))
    run = subprocess.run([node, str(FOXGLOVE_JS), str(tmp_path / "messages.json")], capture_output=True, text=True,
                         env={"NODE_PATH": str(FOXGLOVE_MODULES), "PATH": ""}, timeout=120)
    assert run.returncode == 0, run.stdout + run.stderr
    assert f"{len(out['messages'])} of {len(out['messages'])} messages" in run.stdout and len(out["schemas"]) == 7
