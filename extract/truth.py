"""Truth agreement: how often the chosen inputs are the ones the planner really consumed.

deft_gym writes ``truth.jsonl`` beside each log (per planning output, the sequence number of
every input it consumed). It is read only here, after the search, to measure extraction
accuracy; the search never sees it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from deft_gym.files import read_jsonl
from extract.io_filter import PlanningIOFilter
from extract.search import FrameChoice


def read_truth(path: Path) -> dict[int, dict[str, Any]]:
    """Truth records keyed by planning sequence number (unreadable lines are skipped)."""
    out: dict[int, dict[str, Any]] = {}
    for rec in read_jsonl(path):
        try:
            out[int(rec["planning_seq"])] = rec
        except (ValueError, KeyError, TypeError):
            continue
    return out


def truth_agreement(path: Path | None, choices: list[FrameChoice], pif: PlanningIOFilter) -> dict[str, Any] | None:
    """Share of frames whose chosen inputs all equal the truth, per-role shares, and the share
    of frame times that equal the truth's."""
    if path is None or not path.exists():
        return None
    truth = read_truth(path)
    topics = pif.mapping.topics
    same = compared = same_time = 0
    by_role = dict.fromkeys(pif.roles, 0)
    for fc in choices:
        rec = truth.get(fc.output.seq)
        if rec is None:
            continue
        compared += 1
        ok = True
        for role, j in fc.choice.items():
            chosen = int(pif.inputs[role].seq[j]) if j is not None else None
            if rec.get("inputs", {}).get(topics[role]) == chosen:
                by_role[role] += 1
            else:
                ok = False
        same += ok
        same_time += rec.get("frame_time") == fc.time
    if not compared:
        return None
    return {"file": str(path), "frames": compared, "share": same / compared,
            "by_role": {r: v / compared for r, v in by_role.items()}, "frame_time_share": same_time / compared}
