"""Where episode logs go: failing episodes to the DeFT extractor, passing ones only as a sample.

Every episode that logs writes ``<root>/episodes/<tag>/episode.mcap``. When it ends,
:meth:`EpisodeSink.finish` appends one line to ``<root>/episodes-<worker>.jsonl`` (append-only,
one file per worker process, so parallel workers never interleave) and then:

- a failing episode (collision or non-optimal decision of a valid mutation, or a finding on the
  env's metric oracle: docs/metrics.md) keeps its log plus
  ``episode.json`` (verdict, equivalent scenario, seeds) and is passed to the DeFT extractor
  (``extract.extract_episode``), which writes the extracted frames and a pytest module into
  ``<episode>/extracted``;
- a failing episode whose ``(scenario, signature)`` (the root-cause signature the evaluation
  counts distinct failures by) this worker already kept is, with ``distinct``, not kept again: its
  journal line names the kept log (``duplicate_of``), and no log is replayed or test extracted
  for it (a long training run repeats its favourite failures: a third of the kept logs in the
  second half of the main run); with ``shared`` as well, a failure another worker of the same
  run folder kept at an earlier env step (its journal line has a smaller ``env_steps``) is not
  kept again either - deterministic only when the workers step in lockstep, as SB3's vec envs do
  (a worker's step ``n`` starts after every worker's step ``n - 1`` has ended, so those lines are
  written whatever the processes' timing);
- a passing episode is kept with probability ``keep_passing`` (seeded), otherwise deleted, so a
  long run does not fill the disk.

A sink on a folder that already holds episodes (a resumed run) continues their numbering and
never deletes a folder it did not create itself: :meth:`EpisodeSink.episode_dir` skips names
that exist, and :meth:`EpisodeSink.finish` removes only folders this sink made (numbers of
folders a resumed run set aside under ``<root>/rolled_back/episodes`` are not reused either).
Each journal line carries ``env_steps`` (the env's steps so far, :attr:`EpisodeSink.steps`), so
a resumed training run can tell which episodes came after its checkpoint.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from deft_gym.files import append_jsonl, read_jsonl, write_json_atomic

ROLLED_BACK = "rolled_back"  # where a resumed training run sets aside what came after its checkpoint


def extractor() -> Any | None:
    """``extract.extract_episode`` if the extractor package provides it, else None."""
    try:
        from extract import extract_episode  # type: ignore[attr-defined]
    except ImportError:
        return None
    return extract_episode


class EpisodeSink:
    """Decides what happens to each episode's log (see the module docstring)."""

    def __init__(self, root: Path | str, worker: int = 0, keep_passing: float = 0.02, extract: bool = True,
                 seed: int = 0, extract_kwargs: dict[str, Any] | None = None, distinct: bool = False,
                 shared: bool = False) -> None:
        self.root = Path(root)
        self.worker = worker
        self.keep_passing = keep_passing
        self.extract = extract
        self.distinct = distinct
        self.shared = shared
        # (scenario, signature) -> the kept log of that failure (a resumed run: those still in place)
        self.kept_failures: dict[tuple[str, str], str] = {}
        # the other workers' kept failures: (scenario, signature) -> (env_steps, log), the earliest
        self.others_kept: dict[tuple[str, str], tuple[int, str]] = {}
        self._read_to: dict[Path, int] = {}  # other workers' journals -> bytes read so far
        self.extract_kwargs = dict(extract_kwargs or {})
        self.rng = np.random.default_rng([seed, worker])
        self.journal = self.root / f"episodes-{worker}.jsonl"
        self.count = self._last_number()
        self.steps = 0  # the env's steps so far (set by the env; written to each journal line)
        self._made: set[Path] = set()

    def _last_number(self) -> int:
        """The highest episode number this worker already used in ``root`` (its folders, those
        set aside by a resume, and its journal lines), so a resumed run continues after it."""
        lines = read_jsonl(self.journal) if self.journal.exists() else []
        for r in lines:
            if _finding(r) and r.get("dir") and Path(r["dir"]).is_dir():
                self.kept_failures.setdefault(_failure_key(r), r["dir"])
        n = len(lines)
        pat = re.compile(rf"w{self.worker}-(\d+)-")
        for folder in (self.root / "episodes", self.root / ROLLED_BACK / "episodes"):
            if folder.is_dir():
                for d in folder.iterdir():
                    m = pat.match(d.name)
                    if m:
                        n = max(n, int(m.group(1)))
        return n

    def episode_dir(self, tag: str) -> Path:
        """A fresh directory for the next episode's log; a name that exists already (not made
        by this sink) is skipped, never reused or deleted."""
        while True:
            self.count += 1
            d = self.root / "episodes" / f"w{self.worker}-{self.count:06d}-{tag}"
            try:
                d.mkdir(parents=True)
            except FileExistsError:
                continue
            self._made.add(d)
            return d

    def keeps(self, record: dict[str, Any]) -> bool:
        """Whether the episode's log is kept: for a failure, always (with ``distinct``: unless
        it duplicates a kept one); with probability ``keep_passing`` otherwise (one draw of the
        sink's RNG)."""
        if _finding(record):
            return not (self.distinct and self.kept_log(record) is not None)
        return bool(self.rng.random() < self.keep_passing)

    def kept_log(self, record: dict[str, Any]) -> str | None:
        """The kept log of the failure ``record`` repeats: this worker's, else (``shared``) one
        another worker journalled at an env step before :attr:`steps`; None if there is none."""
        key = _failure_key(record)
        if key in self.kept_failures:
            return self.kept_failures[key]
        if not self.shared:
            return None
        self._read_others()
        steps, log = self.others_kept.get(key, (self.steps, ""))
        return log if steps < self.steps else None

    def _read_others(self) -> None:
        """Read the lines the other workers appended to their journals since the last call
        (whole lines only: one being written is read next time)."""
        for journal in self.root.glob("episodes-*.jsonl"):
            if journal == self.journal:
                continue
            start = self._read_to.get(journal, 0)
            with open(journal, "rb") as fh:
                fh.seek(start)
                chunk = fh.read()
            whole = chunk[:chunk.rfind(b"\n") + 1]
            self._read_to[journal] = start + len(whole)
            for line in whole.splitlines():
                try:
                    r = json.loads(line)
                except json.JSONDecodeError:
                    continue
                if _finding(r) and r.get("kept") and r.get("dir") and Path(r["dir"]).is_dir():
                    key, seen = _failure_key(r), (int(r.get("env_steps", 0)), str(r["dir"]))
                    self.others_kept[key] = min(self.others_kept.get(key, seen), seen)

    def finish(self, episode_dir: Path | None, record: dict[str, Any], details: dict[str, Any],
               keep: bool | None = None) -> dict[str, Any]:
        """Extract / keep / delete; returns what was done (also added to the journal line).
        ``keep``: decided earlier with :meth:`keeps` (a log recorded after the fact, by replay);
        ``episode_dir`` None: nothing was recorded."""
        failing = _finding(record)
        done: dict[str, Any] = {"kept": False, "extraction": None}
        if keep is None:
            keep = self.keeps(record)
        if keep and episode_dir is not None:
            done["kept"] = True
            write_json_atomic(episode_dir / "episode.json", {**record, **details})
            if failing:
                self.kept_failures.setdefault(_failure_key(record), str(episode_dir))
                if self.extract:
                    done["extraction"] = self._extract(episode_dir)
        elif episode_dir is not None and Path(episode_dir) in self._made:  # only what this sink made
            shutil.rmtree(episode_dir, ignore_errors=True)
        if episode_dir is not None:
            self._made.discard(Path(episode_dir))
        done["dir"] = str(episode_dir) if done["kept"] else None
        if failing and not done["kept"] and (kept := self.kept_log(record)) is not None:
            done["duplicate_of"] = kept
        append_jsonl(self.journal, {**record, **done, "env_steps": self.steps})
        return done

    def _extract(self, episode_dir: Path) -> dict[str, Any]:
        return extract_log(episode_dir, **{"test_suffix": episode_dir.name, **self.extract_kwargs})


def _finding(record: dict[str, Any]) -> bool:
    """A failure, a finding on the env's metric oracle (``oracle_signature``, docs/metrics.md),
    or under ``oracle: any`` any counted metric oracle's finding (``found_by_oracle``)."""
    return bool(record.get("failure") or record.get("oracle_signature") or _union_findings(record))


def _union_findings(record: dict[str, Any]) -> str:
    """Under ``oracle: any``, the episode's metric signatures joined (``""``: none or another oracle)."""
    found = record.get("found_by_oracle") if record.get("oracle") == "any" else None
    return "+".join(sorted(found.values())) if found else ""


def _failure_key(record: dict[str, Any]) -> tuple[str, str]:
    sig = record.get("oracle_signature") or (record.get("signature") if record.get("failure") else None)
    return str(record.get("scenario")), str(sig or _union_findings(record) or record.get("signature"))


def extract_log(episode_dir: Path, **kwargs: Any) -> dict[str, Any]:
    """Run the DeFT extractor on ``<episode_dir>/episode.mcap`` into ``<episode_dir>/extracted``
    (``kwargs``: the extractor's, e.g. a ``test_suffix`` that keeps module names unique). Never
    raises: what happened is the returned ``status`` (``ok``, ``error: ...``, unavailable)."""
    fn = extractor()
    if fn is None:
        return {"status": "extractor unavailable (extract.extract_episode not importable)"}
    try:
        res = fn(episode_dir / "episode.mcap", episode_dir / "extracted", **kwargs)
    except Exception as exc:  # an extractor bug must not kill a training or evaluation run
        return {"status": f"error: {type(exc).__name__}: {exc}"}
    return {"status": "ok", "test": str(getattr(res, "test_path", None) or ""),
            "frames": str(getattr(res, "frames_path", None) or ""),
            "faulty": getattr(res, "faulty", None), "summary": getattr(res, "summary", None)}
