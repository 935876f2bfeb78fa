"""Log integrity: CRCs and the summary section written, verified by the reader, damage localised,
the reader resynchronised, every intact message extracted, counts checked against the statistics."""

from __future__ import annotations

import struct
import subprocess
import sys
import zlib
from pathlib import Path

import pytest
from mcap.reader import make_reader

from deft_gym.experiments.log_damage import KINDS, chunk_table, damage, evaluate
from extract.logs import read_log
from extract.verify import verify


@pytest.fixture(scope="module")
def log(lane_follow_log) -> Path:
    return Path(lane_follow_log.log_path)


def test_logs_carry_crcs_and_a_summary_the_mcap_library_reads(log) -> None:
    with open(log, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.chunk_count == len(summary.chunk_indexes) > 10
        n = sum(1 for _ in reader.iter_messages())
    assert n == summary.statistics.message_count
    v = verify(log)
    assert v.status == "complete" and v.integrity.crcs and v.integrity.summary
    assert v.integrity.chunks_ok == v.integrity.chunks == summary.statistics.chunk_count
    assert sum(v.integrity.found.values()) == n and v.integrity.expected == v.integrity.found


def test_every_kind_of_damage_is_detected_localised_and_only_it_is_lost(log, tmp_path) -> None:
    rows = evaluate(log, workdir=tmp_path)
    assert len(rows) == 3 * len(KINDS)
    for r in rows:
        assert r["detected"] and r["localised"] and r["intact_kept"] and r["loss_stated"], r
        assert r["damaged_kept"] == 0
    lost = {r["kind"]: r["lost"] for r in rows if r["chunk"] == "middle"}
    assert lost["record_type"] == lost["record_length"] == 0  # content verified by its CRC: kept
    assert lost["payload_digit"] > 0 and lost["truncation"] > lost["payload_digit"]


def test_resynchronises_after_a_garbled_record(log, tmp_path) -> None:
    """A chunk's header overwritten and no summary to find the next one: the reader finds the
    next record that verifies, and keeps every message around the garbled chunk; the messages
    the garbled chunk held are stated lost, found from the topics' sequence numbers."""
    buf = log.read_bytes()
    table = chunk_table(buf)
    k = len(table) // 2
    ch = table[k]
    (summary_start,) = struct.unpack_from("<Q", buf, len(buf) - 8 - 29 + 9)
    bad = bytearray(buf[:summary_start])
    bad[ch["offset"]:ch["offset"] + 48] = b"\xab" * 48
    path = tmp_path / "garbled.mcap"
    path.write_bytes(bytes(bad))
    got = verify(path)
    (d,) = [d for d in got.integrity.damage if d.kind not in ("truncated", "count")]
    assert d.offset == ch["offset"] and f"resynchronised at offset {table[k + 1]['offset']}" in d.detail
    intact = verify(log)
    n_chunk = len(ch["messages"])
    assert sum(got.integrity.found.values()) == sum(intact.integrity.found.values()) - n_chunk
    assert sum(got.integrity.lost().values()) == n_chunk  # it used to say none


def test_message_counts_are_checked_against_the_statistics(log, tmp_path) -> None:
    """A summary that counts more messages on a channel than the file holds (a writer that lost
    some): reported per topic."""
    buf = bytearray(log.read_bytes())
    foot = len(buf) - 8 - 29
    _, start, offsets, _ = struct.unpack_from("<QQQI", buf, foot + 1)
    pos = start
    while buf[pos] != 0x0B:  # the statistics record
        pos += 9 + struct.unpack_from("<Q", buf, pos + 1)[0]
    body = pos + 9
    n_counts = struct.unpack_from("<I", buf, body + 8 + 2 + 4 * 4 + 16)[0]
    cid, count = struct.unpack_from("<HQ", buf, body + 8 + 2 + 4 * 4 + 16 + 4)
    struct.pack_into("<HQ", buf, body + 8 + 2 + 4 * 4 + 16 + 4, cid, count + 5)
    crc = zlib.crc32(struct.pack("<BQQQ", 0x02, 20, start, offsets), zlib.crc32(bytes(buf[start:foot])))
    struct.pack_into("<I", buf, foot + 1 + 24, crc)
    path = tmp_path / "counts.mcap"
    path.write_bytes(bytes(buf))
    got = verify(path)
    assert n_counts > 0
    (d,) = got.integrity.damage
    assert d.kind == "count" and sum(got.integrity.lost().values()) == 5
    assert "5 message(s) lost" in got.status


def test_an_unreadable_summary_is_reported_and_chunks_still_verified(log, tmp_path) -> None:
    buf = bytearray(log.read_bytes())
    (start,) = struct.unpack_from("<Q", buf, len(buf) - 8 - 29 + 9)
    buf[start + 20] ^= 0xFF
    path = tmp_path / "summary.mcap"
    path.write_bytes(bytes(buf))
    got = verify(path)
    assert [d.kind for d in got.integrity.damage] == ["summary"] and got.integrity.expected is None
    assert got.integrity.chunks_ok == got.integrity.chunks and sum(got.integrity.found.values()) > 1000


def test_verify_cli(log, tmp_path) -> None:
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(damage(log.read_bytes(), "payload_digit", chunk_table(log.read_bytes())[3]))
    run = lambda *a: subprocess.run([sys.executable, "-m", "extract.verify", *map(str, a)],  # noqa: E731
                                    capture_output=True, text=True)
    ok, broken, missing = run(log), run(bad), run(tmp_path / "nope.mcap")
    assert ok.returncode == 0 and "complete" in ok.stdout and "chunks pass their CRC" in ok.stdout
    assert broken.returncode == 1 and "fails its CRC-32" in broken.stdout and "message(s) lost" in broken.stdout
    assert missing.returncode == 2 and missing.stderr.count("\n") == 1


def test_extraction_of_a_damaged_log_says_what_was_lost(log, tmp_path) -> None:
    from extract import extract_episode

    buf = log.read_bytes()
    table = chunk_table(buf)
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(damage(buf, "payload_digit", table[len(table) // 2]))
    s = extract_episode(bad, tmp_path / "out", truth=False).summary
    integ = s["log_integrity"]
    assert s["log_status"].startswith("damaged") and not integ["intact"]
    assert integ["messages_written"] - integ["messages_found"] == sum(integ["lost"].values()) > 0
    assert any("intact messages" in w and "lost:" in w for w in s["warnings"])
    assert read_log(bad, ["/apollo/planning"]).topics["/apollo/planning"].raw  # the rest is there


# -- campaign-side readers: a damaged log is reported as damaged, never summarised as good -----------
def _flipped(log: Path, tmp_path: Path, name: str = "episode.mcap") -> Path:
    """A copy of ``log`` with one bit flipped inside a middle chunk's records."""
    buf = bytearray(log.read_bytes())
    table = chunk_table(bytes(buf))
    ch = table[len(table) // 2]
    buf[ch["offset"] + ch["length"] // 2] ^= 0x01
    out = tmp_path / name
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(bytes(buf))
    return out


def test_the_offline_invariant_checker_refuses_a_log_with_a_flipped_bit(log, tmp_path, capsys) -> None:
    """``stress check`` read logs with the mcap library, which does not check CRCs: a flipped bit
    gave 'no invariant violated', exit 0. Now: one line saying what is damaged, exit 2."""
    from deft_gym.robustness import stress
    from deft_gym.robustness.offline import LogDamaged, check_log

    bad = _flipped(log, tmp_path)
    with pytest.raises(LogDamaged, match=r"damaged: 1 problem\(s\) \(crc\); \d+ message\(s\) lost"):
        check_log(bad)
    assert stress.main(["check", str(bad)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"error: {bad}: damaged") and "deft-gym verify" in err
    assert stress.main(["check", str(log)]) in (0, 1)  # the intact log is judged


def test_extracting_a_folder_with_a_damaged_log_marks_it_and_exits_1(log, tmp_path, capsys) -> None:
    import json

    from extract.__main__ import main as extract_main

    root = tmp_path / "runs"
    (root / "good").mkdir(parents=True)
    (root / "good" / "episode.mcap").write_bytes(log.read_bytes())
    bad = _flipped(log, root / "bad")
    out = tmp_path / "out"
    assert extract_main([str(root), "--out", str(out), "--workers", "1", "--no-tests", "--no-progress"]) == 1
    printed = " ".join(capsys.readouterr().out.split())
    assert f"damaged log: {bad}: damaged" in printed and "damaged log: " + str(root / "good") not in printed
    s = json.loads((out / "summary.json").read_text())
    assert [d["log"] for d in s["damaged_logs"]] == [str(bad)] and s["failed"] == 0
    status = {e["log"]: e["log_status"] for e in s["episodes_list"]}
    assert status[str(root / "good" / "episode.mcap")] == "complete" and status[str(bad)].startswith("damaged")
    # resumed (the extractions are up to date): still reported
    assert extract_main([str(root), "--out", str(out), "--workers", "1", "--no-tests", "--no-progress"]) == 1


def test_the_extraction_evaluation_names_a_damaged_s0_log_in_its_headline(log, tmp_path) -> None:
    from types import SimpleNamespace

    from deft_gym.experiments.extract_report import _markdown, collect
    from extract import extract_episode

    out = tmp_path / "eval"
    extract_episode(_flipped(log, tmp_path), out / "deft" / "heuristic" / "lfs" / "S0", truth=False, emit_tests=False)
    rows = lambda r: SimpleNamespace(rows=r)  # noqa: E731
    ev = SimpleNamespace(args=SimpleNamespace(modes=["heuristic"], reruns=2, test_runs=1), out=out,
                         s0=rows([{"name": "lfs", "outputs": 234, "collision": None, "group": "seed", "wall": 1.0}]),
                         reruns=rows([]), rounds=rows([]), full=rows([]), replays=rows([]),
                         deft_dir=lambda m, n: out / "deft" / m / n / "S0")
    res = collect(ev, {"lfs"}, 0.0)
    assert list(res["damaged_logs"]) == ["heuristic/lfs"] and res["damaged_logs"]["heuristic/lfs"].startswith("damaged")
    _, headline = _markdown({**res, "elapsed_s": 0.0, "provenance": {}, "plots": {}})
    assert headline.startswith("- **1 extraction(s) read a damaged S0 log**")


def test_pictures_of_a_log_with_a_flipped_bit_are_refused_in_one_line(log, tmp_path) -> None:
    """render and the HTML report read logs with the mcap library: a chunk failing its CRC is a
    one-line error naming the file (the report shows it as 'no picture: ...'), not a drawing of
    whatever the damaged bytes decode to."""
    from deft_gym.viz.episode import load_episode

    assert load_episode(log).ego.rows  # the intact log is drawn
    bad = _flipped(log, tmp_path)
    with pytest.raises(ValueError, match=r"damaged log \(crc validation failed") as err:
        load_episode(bad)
    assert str(bad) in str(err.value) and "\n" not in str(err.value)
