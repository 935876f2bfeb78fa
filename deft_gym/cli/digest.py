"""Behaviour digests: a fingerprint of everything a run publishes, to prove a change neutral.

    deft-gym digest --out runs/digests.json          # record (all scenarios, jitter seeds 7 8)
    deft-gym digest --check runs/digests.json        # after a change: same bytes?

Each scenario runs once per jitter seed with recording on; the digest of a topic is the SHA-256
of its messages' JSON payloads and log times, read back from the MCAP file with the ``mcap``
reader (a binary message as the JSON a JSON channel holds: digests do not depend on the log's
encoding). Two versions of the code whose digests agree published byte-identical logs - the
check used to keep speed-ups from changing a single float. ``--check`` exits 1 and names every
run and topic that differs.
"""

from __future__ import annotations

import hashlib
import json
import sys
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

from deft_gym.cli import common
from deft_gym.files import write_atomic

if TYPE_CHECKING:
    from deft_gym.scenarios.scenario import Scenario

DEFAULT_SEEDS = [7, 8]  # the jitter seeds of tests/support/data/digests-numpy*.json


def run_digest(scenario: Scenario | str | Path, jitter_seed: int) -> dict[str, str]:
    """Per topic, the digest of one recorded run (plus its outcome and sim time)."""
    from deft_gym.sim.simulation import run_episode

    with tempfile.TemporaryDirectory() as tmp:
        r = run_episode(scenario, jitter_seed=jitter_seed, out_dir=tmp, keep_planning=False)
        hashes: dict[str, Any] = {}
        from mcap.reader import make_reader

        from deft_gym.bus.messages import VIEWER_TOPICS, log_start_ns
        from deft_gym.bus.ros1 import ChannelDecoders
        from deft_gym.record.recorder import EPISODE_METADATA

        with open(Path(tmp) / "episode.mcap", "rb") as f:
            reader = make_reader(f)
            episode = next((m.metadata for m in reader.iter_metadata() if m.name == EPISODE_METADATA), {})
        start = log_start_ns(episode)  # log_time = epoch start + sim time: the sim time is hashed
        with open(Path(tmp) / "episode.mcap", "rb") as f:
            decoders = ChannelDecoders()
            for schema, channel, msg in make_reader(f).iter_messages():
                if channel.topic in VIEWER_TOPICS:  # pictures of the world state, not bus messages
                    continue
                h = hashes.setdefault(channel.topic, hashlib.sha256())
                h.update(decoders.json(schema, channel, msg.data))  # binary messages as their JSON
                h.update((msg.log_time - start).to_bytes(8, "little"))
    out = {topic: h.hexdigest()[:16] for topic, h in sorted(hashes.items())}
    out["outcome"] = f"{r.outcome.outcome} at {r.sim_time:.2f} s"
    return out


def compute(scenarios: list[str | Path], seeds: list[int], progress: bool = True) -> dict[str, dict[str, str]]:
    """Digests of every (scenario, seed), keyed ``<scenario name>/<seed>``; scenarios are names
    or YAML paths (as :func:`deft_gym.scenarios.scenario.load_scenario` takes them)."""
    from deft_gym.scenarios.scenario import load_scenario

    jobs = [(sc, s) for sc in sorted((load_scenario(p) for p in scenarios), key=lambda sc: sc.name) for s in seeds]
    out = {}
    with common.Bar(len(jobs), "digests", progress) as bar:
        for sc, s in jobs:
            out[f"{sc.name}/{s}"] = run_digest(sc, s)
            bar.update()
    return out


def differences(old: dict[str, dict[str, str]], new: dict[str, dict[str, str]]) -> list[str]:
    """One line per run and topic whose digest differs (runs missing on one side included)."""
    lines = []
    for run in sorted(set(old) | set(new)):
        a, b = old.get(run), new.get(run)
        if a is None or b is None:
            lines.append(f"{run}: only in the {'new' if a is None else 'recorded'} digests")
            continue
        lines += [f"{run}: {key} differs ({a.get(key)} -> {b.get(key)})"
                  for key in sorted(set(a) | set(b)) if a.get(key) != b.get(key)]
    return lines


def build_parser() -> common.Parser:
    ap = common.parser("digest", "deft_gym.cli.digest", __doc__)
    common.add_scenarios(ap, help="scenario names or YAML paths (default: all in configs/scenarios)")
    ap.add_argument("--jitter-seeds", "--seeds", dest="seeds", nargs="+", action=common.ListAction,
                    default=[str(s) for s in DEFAULT_SEEDS], metavar="S", help="jitter seeds of the runs")
    ap.add_argument("--out", type=Path, default=None, metavar="FILE", help="write the digests to this JSON file")
    ap.add_argument("--check", type=Path, default=None, metavar="FILE", help="compare with digests recorded earlier")
    common.add_output_flags(ap)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    args.seeds = [int(s) for s in args.seeds]
    console = common.console(args, stderr=True)
    from deft_gym.config import ConfigError
    from deft_gym.scenarios.scenario import list_scenarios
    if args.check is not None and not args.check.exists():
        console.print(f"error: {args.check}: no such digest file")
        return 2
    try:
        digests = compute(args.scenarios or list_scenarios(), args.seeds,
                          progress=sys.stderr.isatty() and common.show_progress(args))
    except (ConfigError, OSError) as err:
        console.print(f"error: {err}")
        return 2
    if args.out is not None:
        write_atomic(args.out, json.dumps(digests, indent=1))
        console.print(f"{len(digests)} runs -> {args.out}")
    if args.check is not None:
        recorded = json.loads(args.check.read_text())
        if args.scenarios or args.seeds != DEFAULT_SEEDS:
            recorded = {k: v for k, v in recorded.items() if k in digests}
        diff = differences(recorded, digests)
        for line in diff:
            print(line)
        print(f"{len(digests)} runs: " + ("IDENTICAL to " if not diff else f"{len(diff)} differences from ")
              + str(args.check))
        return 1 if diff else 0
    if args.out is None:
        print(json.dumps(digests, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
