"""The compiled formatter (deft_gym/record/_format_c.c) writes ``(template % args).encode()``
byte for byte - exact fixed-point rounding with ties to even, negative zero, every precision -
and leaves everything else to Python's ``%``; the compiled scene values (deft_gym/record/_scene_c.c)
are ``scene.scene_args``'s tuple or leave the state to it; the Foxglove scene they write is the
scene written entity by entity (deft_gym/record/scene.py)."""

from __future__ import annotations

import json
import math
import random
import struct

import pytest

from deft_gym.record import scene, textformat
from deft_gym.record.scene import COMPACT, SCENE_TOPIC, TF_TOPIC, expand
from tests.support.fixtures import SCENARIOS, same_values

kernel = getattr(textformat._format_c, "format_bytes", None)  # None: missing or stale (not loaded)
compiled = pytest.mark.skipif(kernel is None, reason="the compiled formatter is missing or stale")


def _doubles(rng: random.Random, n: int) -> list[float]:
    """Uniform values, exact ties at 3 and 6 decimals, arbitrary bit patterns, tiny and huge ones."""
    out = []
    for _ in range(n):
        k = rng.random()
        if k < 0.3:
            out.append(rng.uniform(-1000.0, 1000.0))
        elif k < 0.45:
            out.append(rng.randint(-10**6, 10**6) / 2000)  # x.xxx5: a tie at 3 decimals
        elif k < 0.55:
            out.append(rng.randint(-10**9, 10**9) / 2 / 10**6)  # a tie at 6 decimals
        elif k < 0.7:
            out.append(struct.unpack("<d", struct.pack("<Q", rng.getrandbits(64)))[0])
        elif k < 0.85:
            out.append(rng.uniform(-1e-3, 1e-3))
        else:
            out.append(rng.uniform(-1e13, 1e13))
    return [*out, 0.0, -0.0, 0.0005, -0.0005, 0.0015, 0.0625, 2.5e-7, 5e-324, 4.5e15, 9.9e15, math.inf, -math.inf,
            math.nan]


@compiled
def test_fixed_point_numbers_are_pythons_text_at_every_precision() -> None:
    values = _doubles(random.Random(7), 20000)
    taken = 0
    for nd in range(10):
        template = f"a%.{nd}f|"
        for x in values:
            data = kernel(template, (x,))
            if data is not NotImplemented:  # out of range or not finite: Python's % (below)
                assert data == (template % (x,)).encode(), (nd, x)
                taken += 1
            assert textformat.format_bytes(template, (x,)) == (template % (x,)).encode()
    assert taken > 0.8 * 10 * len(values)


@compiled
def test_ints_strings_and_percent_signs_and_what_is_left_to_python() -> None:
    template = '{"sec":%d,"id":%s,"x":%.3f,"p":"100%%"}'
    args = (-12345678901, '"npc_1"', -0.0004)
    assert kernel(template, args) == (template % args).encode() == b'{"sec":-12345678901,"id":"npc_1","x":-0.000,"p":"100%"}'
    for template, args in [("%d", (True,)), ("%d", (2**70,)), ("%.3f", (1,)), ("%s", ("\u00e9",)), ("%r", (1,)),
                           ("%5.1f", (1.0,)), ("%.10f", (1.0,)), ("%d %d", (1,)), ("%d", (1, 2)), ("%", ()),
                           ("\u00e9%d", (1,)), ("%.3f", (math.nan,)), ("%.3f", (1e300,))]:
        assert kernel(template, args) is NotImplemented, template
        try:
            want = (template % args).encode()
        except (TypeError, ValueError):
            with pytest.raises((TypeError, ValueError)):
                textformat.format_bytes(template, args)
        else:
            assert textformat.format_bytes(template, args) == want


def _slow(ns: int, seq: int, payload: dict, start_ns: int) -> list[tuple[str, int, bytes, int]]:
    """The scene as written before the one-format path: entity by entity."""
    rows, xs, ys, stamp, collision = payload[COMPACT]
    t = start_ns + ns
    ents = scene._entities(t, rows, xs, ys, stamp)
    if collision:
        ents.append(json.dumps(scene.collision_entity(t, collision)))
    text = scene._SCENE_HEAD % (t // 10**9, t % 10**9) + ",".join(ents) + "]}"
    x, y, h = rows[0][2:5]
    tf = (f'{{"timestamp":{{"sec":{t // 10**9},"nsec":{t % 10**9}}},"parent_frame_id":"map","child_frame_id":"ego",'
          f'"translation":{scene._position_text(x, y, 0.0)},"rotation":{scene._orientation_text(h)}}}')
    return [(SCENE_TOPIC, ns, text.encode(), seq), (TF_TOPIC, ns, tf.encode(), seq)]


@pytest.mark.parametrize("pure", [False, True])
def test_the_scene_is_the_scene_written_entity_by_entity(pure: bool, monkeypatch) -> None:
    """Random states - vehicles of every kind, plans of 0-17 points, odd values (non-finite,
    ints, strings), ids that need escapes, collisions - give the same bytes, compiled or not."""
    if not pure and kernel is None:
        pytest.skip("the compiled formatter is missing or stale")
    if pure:
        monkeypatch.setattr(textformat, "_kernel", None)
        monkeypatch.setattr(scene, "_scene_c", None)
    rng = random.Random(11)
    odd = [math.nan, math.inf, -math.inf, 3, True, "1.5", -0.0, 1e300]
    fast = 0
    for i in range(600):
        rows = [("ego", "ego", rng.uniform(-300, 300), rng.uniform(-50, 50), rng.uniform(-4, 4), rng.uniform(0, 30),
                 4.8, 2.0)]
        for k in range(rng.randint(0, 6)):
            kind = rng.choice(["reactive", "scripted", "static"])
            eid = rng.choice([f"npc_{k}", f"cone{k}", 'q"uote', "caf\u00e9"]) if rng.random() < 0.1 else f"v{k}"
            rows.append((eid, kind, rng.uniform(-300, 300), rng.uniform(-50, 50), rng.uniform(-4, 4),
                         rng.uniform(0, 30), rng.choice([0.5, 4.5, 5.0]), rng.choice([0.5, 2.0])))
        n = rng.randint(0, 17)
        xs, ys = [rng.uniform(-300, 300) for _ in range(n)], [rng.uniform(-50, 50) for _ in range(n)]
        if rng.random() < 0.1 and rows:
            r = list(rows[-1])
            r[rng.randint(2, 5)] = rng.choice(odd[:3])
            rows[-1] = tuple(r)
        if rng.random() < 0.1 and n:
            (xs if rng.random() < 0.5 else ys)[rng.randrange(n)] = rng.choice(odd)
        collision = {"x": 1.0, "y": 2.0, "participant": "v0", "time": 3.0} if rng.random() < 0.05 else None
        stamp = rng.choice(["4.9", 4.9, 'a"b', "\u00e9"])
        payload = {COMPACT: [rows, xs, ys, stamp, collision]}
        ns, start = rng.randint(0, 60 * 10**9), 1_700_000_000 * 10**9
        try:
            want = _slow(ns, i, payload, start)
        except (TypeError, ValueError):  # a plan point that is no number: both raise
            with pytest.raises((TypeError, ValueError)):
                expand(ns, i, payload, start)
            continue
        assert expand(ns, i, payload, start) == want, i
        fast += not collision and scene._scene_texts((start + ns) // 10**9, (start + ns) % 10**9, rows, xs, ys,
                                                    stamp) is not None
        for _, _, data, _ in want:
            json.loads(data)
    assert fast > 300  # most states take the one-format path


@pytest.mark.skipif(scene._scene_c is None, reason="the compiled scene values are missing or stale")
def test_compiled_scene_values_are_the_python_ones() -> None:
    """``_scene_c.scene_args`` gives ``scene.scene_args``'s tuple, every float with the same bits,
    or None where it does, for random states with odd values in every place (non-finite, huge,
    negative zero, subnormal, ints, strings, lists for tuples, short rows, stamps that need JSON
    escapes); where it returns NotImplemented the Python version decides. Every scene state of a
    recorded run is taken by it."""
    kern, rng = scene._scene_c.scene_args, random.Random(5)
    odd = [math.nan, math.inf, -math.inf, -0.0, 5e-324, 1e300, 1.7e308, 3, True, "1.5", None]
    stamps = [4.9, "4.9", 12, 'a"b', "back\\slash", "tab\t", "\u00e9", "\x7f", "", None, 1e300, math.nan]
    taken = none = 0
    for i in range(3000):
        rows = [(f"v{k}", "reactive", *(rng.uniform(-300, 300) for _ in range(4)), 4.8, 2.0)
                for k in range(rng.randint(0, 7))]
        n = rng.randint(0, 17)
        xs, ys = [rng.uniform(-300, 300) for _ in range(n)], [rng.uniform(-50, 50) for _ in range(n)]
        for _ in range(rng.choice([0, 0, 1, 2])):  # odd values anywhere
            where = rng.random()
            if where < 0.5 and rows:
                k = rng.randrange(len(rows))
                row = list(rows[k])
                row[rng.randint(2, 5)] = rng.choice(odd)
                rows[k] = tuple(row) if rng.random() < 0.9 else row
            elif n:
                (xs if where < 0.75 else ys)[rng.randrange(n)] = rng.choice(odd)
        if rng.random() < 0.03 and rows:
            rows[0] = rows[0][:7]
        if rng.random() < 0.03:
            ys = [*ys, 1.0]
        stamp, plan = rng.choice(stamps), rng.random() < 0.8
        sec, nsec = rng.randint(0, 2**40), rng.randint(0, 10**9 - 1)
        want = scene.scene_args(sec, nsec, rows, xs, ys, stamp, plan)
        got = kern(sec, nsec, rows, xs, ys, stamp, plan)
        if got is NotImplemented:
            continue
        assert same_values(got, want), (i, got, want)
        taken += 1
        none += got is None
    assert taken > 1000 and none > 100  # many states (half the stamps need escapes), many with a non-finite value
    # the states of a real run: all taken, all the same
    from deft_gym.sim.simulation import Simulation

    states = []
    sim = Simulation(SCENARIOS / "lane_follow_static.yaml", jitter_seed=7)
    scene.SceneWriter(sim, lambda m: states.append(m.payload[COMPACT]) if m.topic == SCENE_TOPIC else None, 0)
    sim.run()
    assert len(states) > 50
    for rows, xs, ys, stamp, _ in states:
        got = kern(1, 2, rows, xs, ys, stamp, len(xs) >= 2)
        assert got is not NotImplemented and same_values(got, scene.scene_args(1, 2, rows, xs, ys, stamp, len(xs) >= 2))
