"""Independent checks of exported files: ASAM's quality checkers (``asam-qc-opendrive``,
``asam-qc-openscenarioxml``; their first check is the schema of the file's version, shipped with
them), run in this process.

:func:`qc_issues` returns every issue a checker bundle raised (rule, level, description); an
export passes when none of them is an error (:func:`errors`). A checker that could not run (it
raised, or its preconditions failed) is reported as an error too, so a silent skip never passes.
"""

from __future__ import annotations

import contextlib
import io
import logging
from pathlib import Path
from typing import Any

#: checkers that are skipped for a reason that is no fault of the file: they apply only to
#: other versions, or to features the file does not use (none so far)
_SKIP_OK = ("Version", "is lower than definition setting", "is not valid according to", "applicable version")


def qc_issues(path: Path | str) -> list[dict[str, Any]]:
    """Run the ASAM quality checker bundle for ``path`` (``.xodr`` or ``.xosc``): every issue
    as ``{"checker", "rule", "level", "description"}``, levels ``error``, ``warning``, ``info``;
    a checker that ended in an error or was skipped for failed preconditions is an ``error``."""
    from qc_baselib import Configuration, Result, StatusType

    path = Path(path)
    if path.suffix == ".xodr":
        from qc_opendrive import constants
        from qc_opendrive.main import run_checks
    elif path.suffix == ".xosc":
        from qc_openscenario import constants
        from qc_openscenario.main import run_checks
    else:
        raise ValueError(f"{path}: not an .xodr or .xosc file")
    config = Configuration()
    config.set_config_param(name="InputFile", value=str(path))
    config.register_checker_bundle(checker_bundle_name=constants.BUNDLE_NAME)
    result = Result()
    result.register_checker_bundle(name=constants.BUNDLE_NAME, description="", version="", summary="")
    result.set_result_version(version="1.0.0")
    log = logging.getLogger()
    level = log.level
    log.setLevel(logging.WARNING)  # the checkers log every step at INFO
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            run_checks(config, result)
    finally:
        log.setLevel(level)
    out: list[dict[str, Any]] = []
    names = {0: "unknown", 1: "error", 2: "warning", 3: "info"}
    bundle = result.get_checker_bundle_result(constants.BUNDLE_NAME)
    for checker in bundle.checkers:
        status = checker.status
        summary = getattr(checker, "summary", "") or ""
        if status == StatusType.ERROR or (status == StatusType.SKIPPED and not any(k in summary for k in _SKIP_OK)):
            out.append({"checker": checker.checker_id, "rule": "", "level": "error",
                        "description": f"checker {status.name.lower()}: {summary}"})
        for issue in checker.issues:
            lvl = int(getattr(issue.level, "value", issue.level))
            out.append({"checker": checker.checker_id, "rule": issue.rule_uid, "level": names.get(lvl, str(lvl)),
                        "description": issue.description})
    return out


def errors(issues: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [i for i in issues if i["level"] == "error"]


def checker_status(path: Path | str) -> dict[str, str]:
    """Each checker of the bundle for ``path`` and how it ended (completed, skipped, error)."""
    from qc_baselib import Configuration, Result

    path = Path(path)
    if path.suffix == ".xodr":
        from qc_opendrive import constants
        from qc_opendrive.main import run_checks
    else:
        from qc_openscenario import constants
        from qc_openscenario.main import run_checks
    config = Configuration()
    config.set_config_param(name="InputFile", value=str(path))
    config.register_checker_bundle(checker_bundle_name=constants.BUNDLE_NAME)
    result = Result()
    result.register_checker_bundle(name=constants.BUNDLE_NAME, description="", version="", summary="")
    result.set_result_version(version="1.0.0")
    with contextlib.redirect_stdout(io.StringIO()):
        run_checks(config, result)
    bundle = result.get_checker_bundle_result(constants.BUNDLE_NAME)
    return {c.checker_id: f"{c.status.name.lower()}: {c.summary}" for c in bundle.checkers}
