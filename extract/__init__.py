"""DeFT: deterministic planning-module tests extracted from episode logs.

>>> from extract import extract_episode
>>> result = extract_episode("runs/x/0/episode.mcap", "runs/x/0/deft")
>>> result.summary["reproduced"]["0"], result.test_path

See :mod:`extract.episode` (one log), :mod:`extract.batch` (a folder of runs),
:mod:`extract.runtime` (what the generated tests import) and ``python -m extract --help``.
"""

from extract.batch import extract_directory
from extract.episode import ExtractionResult, extract_episode
from extract.logs import LogError
from extract.mapping import MappingError, load_mapping
from extract.runtime import FramesError, load_frames, make_planner, replay
from extract.search import MODES, SearchConfig

__all__ = ["MODES", "ExtractionResult", "FramesError", "LogError", "MappingError", "SearchConfig",
           "extract_directory", "extract_episode", "load_frames", "load_mapping", "make_planner", "replay"]
