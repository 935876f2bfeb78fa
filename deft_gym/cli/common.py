"""The command-line conventions every DeFT-Gym program shares, defined once.

Every program (``deft-gym <command>`` or its ``python -m`` module) builds its parser with
:func:`parser` and takes its shared options from the ``add_*`` functions here, so that one
flag means one thing everywhere:

========================  ==================================================================
``--scenarios A B``       scenario names (``configs/scenarios``), YAML paths or specs such as
                          ``gen:7``; space-separated (commas also accepted: ``A,B``)
``--out DIR``             output folder; every program has a default under ``runs/``
``--workers N``           parallel processes; default: the CPUs this process may use
``--seed S``              seed of the program's own randomness (tests, adversary); default 0
``--jitter-seed S``       jitter seed of the first run (run *i* uses S+i); default: fresh seeds
                          from the OS, printed and recorded, as in a real system
``--no-progress``         no progress bar (rich, one style everywhere)
``--quiet``               print only errors and the final line (implies ``--no-progress``)
``--render WHAT``         pictures of episodes: ``failures`` (default), ``all`` or ``none``
``--watchdog-s SECONDS``  wall-clock seconds one module call (a module computation, a planner's
                          ``plan()``) may take before it is reported as a hang; default the
                          ``DEFT_GYM_WATCHDOG_S`` environment variable, else 10 s
``--ray``                 (execution layer) run jobs on Ray instead of local processes
``--ray-address ADDR``    (execution layer) the Ray cluster to join
``--version``             the package version
========================  ==================================================================

Bad input is one line naming the flag or field, exit status 2 (:class:`Parser`). Help lists
every option with its default. Nothing here imports more than the standard library and rich
(lazily), so ``--help`` stays fast.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

RUNS = Path("runs")
RENDER_CHOICES = ("failures", "all", "none")
# set by the ``deft-gym`` console script: programs then name themselves ``deft-gym <command>``
INVOKED_AS: str | None = None


def version() -> str:
    """The installed package version (the source tree's when not installed)."""
    try:
        from importlib.metadata import PackageNotFoundError
        from importlib.metadata import version as _version

        return _version("deft-gym")
    except PackageNotFoundError:  # pragma: no cover - a source tree never installed
        return "0.1.0"


def cpus() -> int:
    """How many CPUs this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Keeps the description's layout and appends ``(default: X)`` to every option's help that
    does not state its default itself."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        if "default" in text or action.default is argparse.SUPPRESS or not action.option_strings:
            return text
        if isinstance(action, argparse._StoreTrueAction | argparse._StoreFalseAction):
            return f"{text} (default: {'on' if action.default else 'off'})".strip()
        if action.default is None:
            return f"{text} (default: none)".strip()
        shown = " ".join(map(str, action.default)) if isinstance(action.default, list | tuple) else action.default
        return f"{text} (default: {shown})".strip()


class Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line naming the flag, exit status 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def parser(name: str, module: str, doc: str | None, epilog: str | None = None) -> Parser:
    """The parser of program ``name`` (``deft-gym name``, or ``python -m module``): its
    description is the first paragraph of ``doc``; ``--version`` included."""
    prog = f"{INVOKED_AS} {name}" if INVOKED_AS else f"python -m {module}"
    description = (doc or "").strip().split("\n\n")[0] or None
    p = Parser(prog=prog, description=description, epilog=epilog, formatter_class=HelpFormatter)
    p.add_argument("--version", action="version", version=f"deft-gym {version()}",
                   help="print the version and exit")
    return p


def cli_error(message: str) -> int:
    """Print a one-line error to stderr; returns exit status 2 (bad input)."""
    print(f"error: {message}", file=sys.stderr)
    return 2


# -- the shared options ----------------------------------------------------------------------------
class ListAction(argparse.Action):
    """Space- and comma-separated values, flattened."""

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any,
                 option_string: str | None = None) -> None:
        items = [v.strip() for s in (values if isinstance(values, list) else [values]) for v in str(s).split(",")]
        setattr(namespace, self.dest, [v for v in items if v])


def split_list(value: str | Sequence[str] | None) -> list[str] | None:
    """``"a,b c"`` or ``["a,b", "c"]`` -> ``["a", "b", "c"]`` (None stays None)."""
    if value is None:
        return None
    parts = [value] if isinstance(value, str) else list(value)
    return [v.strip() for s in parts for v in s.replace(",", " ").split() if v.strip()]


def add_scenarios(p: argparse.ArgumentParser, default: Sequence[str] | None = None, help: str | None = None,
                  flags: Sequence[str] = ("--scenarios",)) -> None:
    """``--scenarios A B`` (or ``A,B``): scenario names, YAML paths or specs."""
    p.add_argument(*flags, dest="scenarios", nargs="+", action=ListAction, metavar="SCENARIO",
                   default=list(default) if default is not None else None,
                   help=help or "scenario names (configs/scenarios), YAML paths or gen:<seed> specs; "
                                "space- or comma-separated")


def out_folder(text: str) -> str:
    """``--out`` of a program that writes a folder: a path that is an existing file is refused
    before any work starts (one line, exit 2)."""
    if Path(text).exists() and not Path(text).is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a file; expected a folder (new or existing)")
    return text


def add_out(p: argparse.ArgumentParser, default: str | Path | None, help: str = "output folder",
            folder: bool = True) -> None:
    """``--out DIR`` with a default under ``runs/`` (a string default may name a placeholder
    the program fills in, e.g. ``runs/run/<scenario>``); ``folder=False`` for a file."""
    p.add_argument("--out", default=str(default) if default is not None else None, metavar="DIR" if folder else "FILE",
                   type=out_folder if folder else str, help=help)


def add_workers(p: argparse.ArgumentParser, help: str = "parallel processes") -> None:
    """``--workers N``, default the CPUs this process may use."""
    p.add_argument("--workers", type=positive_int, default=cpus(), metavar="N",
                   help=f"{help} (default: the CPUs, {cpus()} here)")


def add_seed(p: argparse.ArgumentParser, default: int | None = 0,
             help: str = "seed of this program's own randomness") -> None:
    """``--seed S``."""
    p.add_argument("--seed", type=int, default=default, metavar="S", help=help)


def add_jitter_seed(p: argparse.ArgumentParser, help: str = "jitter seed of the first run; run i uses S+i") -> None:
    """``--jitter-seed S``, default fresh seeds from the OS."""
    p.add_argument("--jitter-seed", type=int, default=None, metavar="S",
                   help=f"{help} (default: fresh seeds from the OS, recorded in the output)")


def add_ads_config(p: argparse.ArgumentParser, default: str = "configs/ads/default.yaml") -> None:
    """``--ads-config YAML``: the ADS the campaign runs on, its planner included (e.g.
    ``configs/ads/commonroad.yaml``: CommonRoad's reactive planner)."""
    p.add_argument("--ads-config", type=Path, default=None, metavar="YAML",
                   help=f"ADS config, the planner under test included, e.g. configs/ads/commonroad.yaml "
                        f"(default: {default})")


def add_output_flags(p: argparse.ArgumentParser) -> None:
    """``--no-progress`` and ``--quiet``."""
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--quiet", action="store_true", help="print only errors and the final line (no progress bar)")


def add_render(p: argparse.ArgumentParser, default: str = "failures") -> None:
    """``--render failures|all|none`` (pictures of episodes: plot and video)."""
    p.add_argument("--render", choices=RENDER_CHOICES, default=default,
                   help="draw a plot and a video of these episodes (deft-gym render)")


WATCHDOG_ENV = "DEFT_GYM_WATCHDOG_S"  # deft_gym.execution.watchdog.ENV (not imported: --help stays fast)


def positive_seconds(text: str) -> float:
    """argparse type: finite seconds > 0."""
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds (a number > 0), got {text!r}") from None
    if not (x > 0 and x < float("inf")):
        raise argparse.ArgumentTypeError(f"expected finite seconds > 0, got {text!r}")
    return x


RUN_WALL_ENV = "DEFT_GYM_RUN_WALL_S"  # deft_gym.execution.watchdog.RUN_ENV


def add_watchdog(p: argparse.ArgumentParser) -> None:
    """``--watchdog-s SECONDS`` and ``--run-wall-s SECONDS`` (read by :func:`watchdog_env`)."""
    p.add_argument("--watchdog-s", type=positive_seconds, default=None, metavar="SECONDS",
                   help="wall-clock seconds one module call (a module computation, a planner's plan()) may take "
                        f"before it is reported as a hang instead of hanging the program (default: {WATCHDOG_ENV} "
                        "from the environment, else 10)")
    p.add_argument("--run-wall-s", type=positive_seconds, default=None, metavar="SECONDS",
                   help="wall-clock seconds all the module calls of one episode (or all the plan() calls of one "
                        "extraction) may take together before the run is a hang (default: "
                        f"{RUN_WALL_ENV} from the environment, else 600)")


@contextmanager
def watchdog_env(args: argparse.Namespace) -> Iterator[None]:
    """While the block runs, ``--watchdog-s`` and ``--run-wall-s`` (when given) are
    ``DEFT_GYM_WATCHDOG_S`` and ``DEFT_GYM_RUN_WALL_S`` of this process, and of the worker
    processes it starts (the execution layer carries them); restored after. A variable that is
    not seconds >= 0 is one line, exit 2, before any work."""
    from deft_gym.execution.watchdog import run_wall_seconds, watchdog_seconds

    with _seconds_env(args, "run_wall_s", RUN_WALL_ENV, run_wall_seconds), \
            _seconds_env(args, "watchdog_s", WATCHDOG_ENV, watchdog_seconds):
        yield


@contextmanager
def _seconds_env(args: argparse.Namespace, attr: str, env: str, check: Callable[[], float]) -> Iterator[None]:
    """The flag ``args.<attr>`` as the environment variable ``env`` while the block runs (restored
    after); without the flag, ``check()`` - the check every watched run makes - runs here, before
    any work, and a bad variable is one line, exit 2."""
    value = getattr(args, attr, None)
    old = os.environ.get(env)
    if value is None:
        try:
            check()
        except ValueError as err:
            raise SystemExit(cli_error(f"{err}; or give --{attr.replace('_', '-')} SECONDS")) from None
        yield
        return
    os.environ[env] = repr(float(value))
    try:
        yield
    finally:
        if old is None:
            os.environ.pop(env, None)
        else:
            os.environ[env] = old


# the errors of a disk that cannot take the output: one line naming the file, never a traceback
DISK_ERRNOS = frozenset({"ENOSPC", "EDQUOT", "EROFS", "EACCES", "EPERM", "EIO", "EFBIG", "ENAMETOOLONG"})


@contextmanager
def locked_out(folder: str | Path, what: str | None = None) -> Iterator[Path]:
    """Hold the output folder ``folder`` (created if needed) while the block runs: every program
    that writes an ``--out`` folder does its work inside this block (:func:`deft_gym.files.folder_lock`).

    - another process already writing the folder: one line naming the folder and that process
      (pid, command, start time), exit 2, nothing written;
    - a folder that cannot be created or written (read-only, no permission) before or while the
      block runs, or a disk that fills up while it runs: one line naming the file and the reason,
      exit 1 (what is already on disk stays; the append-only records resume where they stopped).

    The lock goes with the process that holds it (``kill -9`` included): a killed run never
    blocks the next one."""
    import errno

    from deft_gym.files import FolderBusy, folder_lock

    try:
        cm = folder_lock(folder, what)
        path = cm.__enter__()
    except FolderBusy as err:
        raise SystemExit(cli_error(str(err))) from None
    except OSError as err:
        raise SystemExit(cli_error(f"{err.filename or folder}: cannot write the output folder: "
                                   f"{err.strerror or err}")) from None
    try:
        yield path
    except OSError as err:
        if errno.errorcode.get(err.errno or -1) not in DISK_ERRNOS:
            cm.__exit__(type(err), err, err.__traceback__)
            raise
        cm.__exit__(None, None, None)
        print(f"error: {err.filename or folder}: cannot write: {err.strerror or err}", file=sys.stderr)
        raise SystemExit(1) from None
    except BaseException as err:
        cm.__exit__(type(err), err, err.__traceback__)
        raise
    else:
        cm.__exit__(None, None, None)


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {n}")
    return n


def int_range(lo: int, hi: int) -> Any:
    """argparse type: an integer in ``lo..hi`` (a count bounded before any work starts)."""

    def parse(text: str) -> int:
        try:
            n = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if not lo <= n <= hi:
            raise argparse.ArgumentTypeError(f"expected an integer in {lo}..{hi:,}, got {n:,}")
        return n

    parse.__name__ = "integer"
    return parse


def finite_float(lo: float = float("-inf"), hi: float = float("inf")) -> Any:
    """argparse type: a finite number in ``lo..hi`` (NaN and infinities refused)."""
    import math

    def parse(text: str) -> float:
        try:
            x = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not math.isfinite(x) or not lo <= x <= hi:
            raise argparse.ArgumentTypeError(f"expected a finite number in {lo:g}..{hi:g}, got {text!r}")
        return x

    parse.__name__ = "number"
    return parse


def fresh_seed() -> int:
    """A jitter seed from the OS (as :func:`deft_gym.bus.jitter.os_seed`, without its imports)."""
    return int.from_bytes(os.urandom(4), "little") & 0x7FFFFFFF


# -- console and progress --------------------------------------------------------------------------
def console(args: argparse.Namespace | None = None, stderr: bool = False, width: int = 120) -> Any:
    """The rich console of a program (silent with ``--quiet``)."""
    from rich.console import Console

    stream = sys.stderr if stderr else sys.stdout
    return Console(stderr=stderr, width=None if stream.isatty() else width, highlight=False,
                   quiet=bool(getattr(args, "quiet", False)))


def show_progress(args: argparse.Namespace | None) -> bool:
    """Whether a progress bar is wanted (not ``--no-progress`` nor ``--quiet``)."""
    return not (getattr(args, "no_progress", False) or getattr(args, "quiet", False))


def rich_progress(con: Any = None, info: bool = False) -> Any:
    """A rich ``Progress`` in the one style (for programs that run several tasks at once)."""
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    cols = [TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
            TextColumn("eta"), TimeRemainingColumn()]
    if info:
        cols.append(TextColumn("{task.fields[info]}"))
    return Progress(*cols, console=con or console(stderr=True), transient=True)


class Bar:
    """The one progress-bar style (rich): description, bar, done/total, elapsed, remaining.

    ``update(n)`` advances like tqdm's; ``set(done, total)`` sets; ``close()`` ends it. Disabled
    bars cost nothing. Use as a context manager or call :meth:`close`."""

    def __init__(self, total: int | None, description: str, enabled: bool = True, con: Any = None,
                 info: bool = False) -> None:
        self._progress = None
        if not enabled:
            return
        self._progress = rich_progress(con, info)
        self._progress.start()
        self._task = self._progress.add_task(description, total=total, info="")

    def update(self, n: int = 1) -> None:
        """Advance by ``n``."""
        if self._progress is not None:
            self._progress.advance(self._task, n)

    def set(self, done: int, total: int | None = None, info: str | None = None) -> None:
        """Set the count (and the total, and the info text)."""
        if self._progress is not None:
            kw: dict[str, Any] = {"completed": done}
            if total is not None:
                kw["total"] = total
            if info is not None:
                kw["info"] = info
            self._progress.update(self._task, **kw)

    def close(self) -> None:
        """End the bar (it disappears; what was printed stays)."""
        if self._progress is not None:
            self._progress.stop()
            self._progress = None

    def __enter__(self) -> Bar:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


@contextmanager
def bar(args: argparse.Namespace | None, total: int | None, description: str, con: Any = None) -> Iterator[Bar]:
    """A :class:`Bar` that honours ``--no-progress``/``--quiet``."""
    b = Bar(total, description, show_progress(args), con)
    try:
        yield b
    finally:
        b.close()


# -- tables ----------------------------------------------------------------------------------------
def table(title: str | None = None, caption: str | None = None, **kw: Any) -> Any:
    """A rich ``Table`` in the one style (left-justified title and caption, simple head rule);
    print it with :func:`print_table` so that no value is cut."""
    from rich import box
    from rich.table import Table

    opts: dict[str, Any] = {"title_justify": "left", "caption_justify": "left", "box": box.SIMPLE_HEAD,
                            "pad_edge": False, "padding": (0, 1)}
    return Table(title=title, caption=caption, **{**opts, **kw})


def fit_table(con: Any, t: Any) -> int:
    """Set the column widths of rich table ``t`` so that no value is ever cut; returns the width
    [characters] the table needs.

    Piped (not a terminal: a file, a CI log) every column gets its full natural width, headers
    included. On a terminal the table fits the console's width where the values allow it: each
    column is first as wide as its widest value (values on one line) and headers wrap, at words
    where there is room, else folded; when the values alone are too wide, values of several
    words wrap at their spaces. No value ever loses a character (``…``): a word longer than the
    room keeps its width and the terminal wraps the line."""
    from rich.cells import cell_len
    from rich.measure import Measurement
    from rich.text import Text

    opts = con.options.update_width(1_000_000)
    vmax, vmin, heads, words = [], [], [], []
    for col in t.columns:
        sizes = [Measurement.get(con, opts, c) for c in col.cells]
        head = col.header.copy() if isinstance(col.header, Text) else Text(str(col.header))  # plain: "[s]" stays
        head.no_wrap, head.overflow = False, "fold"
        col.header = head
        col.no_wrap, col.overflow, col.min_width, col.max_width = True, "fold", None, None
        lines = head.plain.splitlines() or [""]
        vmax.append(max([m.maximum for m in sizes] + [1]))
        vmin.append(max([m.minimum for m in sizes] + [1]))
        heads.append(max(cell_len(x) for x in lines))
        words.append(max((cell_len(w) for x in lines for w in x.split()), default=0))
    def overhead() -> int:  # borders, dividers and padding [characters]
        return t._extra_width + sum(t._get_padding_width(i) for i in range(len(t.columns)))

    fixed = overhead()
    widths = [max(v, h) for v, h in zip(vmax, heads)]
    if con.is_terminal and sum(widths) + fixed > con.width:
        # tighter first: no outer edge, one character between columns (the divider, else padding)
        t.show_edge, t.padding = False, ((0, 0) if t.box is not None else (0, 1, 0, 0))
        fixed = overhead()
        targets = [words, heads]
        widths = list(vmax)
        if sum(widths) + fixed > con.width:  # values of several words wrap at their spaces
            widths, targets = list(vmin), [words, vmax, heads]
            for col in t.columns:
                col.no_wrap = False
        room = con.width - fixed - sum(widths)
        for target in targets:
            while room > 0:
                short = [i for i, w in enumerate(widths) if w < target[i]]
                if not short:
                    break
                i = max(short, key=lambda k: target[k] - widths[k])
                widths[i] += 1
                room -= 1
    for col, w in zip(t.columns, widths):
        col.width = w
    return sum(widths) + fixed


def _one_line(con: Any, t: Any) -> int:
    """The width [characters] of table ``t`` with every value on one line, one character between
    columns and headers no wider than their values."""
    from rich.measure import Measurement

    opts = con.options.update_width(1_000_000)
    return sum(max([Measurement.get(con, opts, c).maximum for c in col.cells] + [1]) for col in t.columns) \
        + len(t.columns) - 1


def transposed(t: Any) -> Any:
    """Table ``t`` turned by 90 degrees: a row per column (its header first), a column per row
    (headed by the row's first value) - what a table of many columns and few rows prints as on a
    narrow terminal."""
    from rich.text import Text

    first = t.columns[0]
    out = table(title=t.title, caption=t.caption)
    out.add_column(first.header if isinstance(first.header, Text) else Text(str(first.header)))
    for cell in first.cells:
        out.add_column(cell if isinstance(cell, Text) else Text.from_markup(str(cell)), justify="right")
    for col in t.columns[1:]:
        out.add_row(col.header if isinstance(col.header, Text) else Text(str(col.header)), *col.cells)
    return out


def print_table(con: Any, t: Any) -> None:
    """Print rich table ``t`` on console ``con`` with :func:`fit_table`: fitted to a terminal,
    full values when piped; never a cut value. On a terminal too narrow for its values on one
    line, a table of more columns than rows prints :func:`transposed` when that fits."""
    if con.is_terminal and t.columns and t.row_count < len(t.columns) and _one_line(con, t) > con.width:
        turned = transposed(t)
        if _one_line(con, turned) <= con.width:
            t = turned
    need = fit_table(con, t)
    if need <= con.width:
        con.print(t)
        return
    old = con.width
    con.width = need
    try:
        con.print(t)
    finally:
        con.width = old


def print_markdown(con: Any, text: str) -> None:
    """Print the little markdown of the project's reports (paragraphs, ``- `` items, headings,
    ``|`` tables) on console ``con``: tables through :func:`print_table`, the rest soft-wrapped,
    with no rich markup (a ``[s]`` stays)."""
    from rich.text import Text

    rows: list[list[str]] = []

    def flush() -> None:
        if rows:
            t = table()
            for h in rows[0]:
                t.add_column(Text(h), justify="left" if not t.columns else "right")
            for r in rows[1:]:
                t.add_row(*(Text(c) for c in r))
            print_table(con, t)
            rows.clear()

    for line in text.splitlines():
        s = line.strip()
        if s.startswith("|"):
            cells = [c.strip().replace("**", "") for c in s.strip("|").split("|")]
            if not set("".join(cells)) <= set("-: "):
                rows.append(cells)
            continue
        flush()
        if s in ("<details>", "</details>") or s.startswith("<details><summary>"):
            continue
        con.print(Text(s.lstrip("#").strip().replace("**", ""), style="bold" if s.startswith("#") else ""),
                  soft_wrap=True)
    flush()


# -- paths and commands shown to users -----------------------------------------------------------
def shown(path: str | Path) -> str:
    """A path as shown to users (in commands to paste, in reports): relative to the working
    directory when it is inside it (normally the checkout's root), else absolute."""
    p = Path(os.path.abspath(path))
    cwd = Path.cwd()
    for a, b in ((p, cwd), (p.resolve(), cwd.resolve())):
        try:
            rel = a.relative_to(b).as_posix()
            return rel or "."
        except ValueError:
            continue
    return str(p)


def tool(name: str) -> str:
    """How to call the console script ``name`` (``deft-gym``, ``pytest``, ``tensorboard``) from
    the working directory: the bare name inside this program's activated virtual environment,
    else its path in that environment (``.venv/bin/deft-gym``), so the command works as pasted."""
    bindir = Path(sys.executable).parent
    active = os.environ.get("VIRTUAL_ENV")
    if sys.prefix == sys.base_prefix or (active and os.path.abspath(active) == os.path.abspath(sys.prefix)):
        return name  # no virtual environment, or the activated one
    script = bindir / name
    return shown(script) if script.exists() else name
