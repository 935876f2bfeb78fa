"""Objects run in a child process of their own, so that nothing they do can end the program.

:class:`Hosted` builds an object in a forked child process and calls its methods there; what
the object does becomes an exception in the caller, never the caller's end:

- it raises anything, ``BaseException`` included (``SystemExit``, ``KeyboardInterrupt``,
  ``GeneratorExit``): :class:`HostedError`, an ``Exception`` carrying the type name, the message
  and where it was raised;
- it ends its process (``os._exit``, ``sys.exit`` from a thread, ``abort()``), is killed by a
  signal (``SIGSEGV``, ``SIGKILL``, ``SIGTERM`` it sent itself) or its process is gone for any
  other reason: :class:`HostDied`, naming the exit status or the signal and the call;
- it blocks: the caller waits in a system call that a signal interrupts, so the wall-clock
  watchdog (:mod:`deft_gym.execution.watchdog`) raises its ``ModuleHang`` there as it would in
  an in-process call; the child is then killed (its state is unknown) and every later call is a
  :class:`HostDied`.

The child is a ``fork`` of the caller: it starts in about a millisecond with every module the
caller imported (no import, no pickling of the object), closes every file descriptor but its
channel and the standard streams (it never holds the caller's logs, pipes or locks), ignores
Ctrl-C (the caller decides) and dies with the caller (``PR_SET_PDEATHSIG``). Arguments and
results cross as pickles (floats and arrays bit for bit); a call costs a few tens of
microseconds plus the pickling.

Layer 0: the standard library only.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import traceback
from collections.abc import Callable
from multiprocessing.connection import Connection, Pipe
from typing import Any


class HostedError(Exception):
    """The hosted object raised: ``type_name``, ``message`` and ``location`` (innermost frame,
    ``path:function``) of what it raised; ``str()`` is the message."""

    def __init__(self, type_name: str, message: str, location: str = "", frames: list[str] | None = None) -> None:
        super().__init__(message)
        self.type_name, self.message, self.location = type_name, message, location
        self.frames = frames or []

    def describe(self) -> str:
        return f"{self.type_name}: {self.message}" if self.message else self.type_name


class HostDied(Exception):
    """The hosted object's process ended (or was ended) while it was called or before;
    ``location``: ``path:method`` of the call (the object's source file, when known)."""

    def __init__(self, message: str, location: str = "") -> None:
        super().__init__(message)
        self.location = location


def _signal_name(sig: int) -> str:
    try:
        return signal.Signals(sig).name
    except ValueError:
        return f"signal {sig}"


def describe_status(status: int) -> str:
    """How a child process ended, from its ``waitpid`` status."""
    if os.WIFSIGNALED(status):
        sig = os.WTERMSIG(status)
        return f"killed by {_signal_name(sig)}" + (" (a segmentation fault)" if sig == signal.SIGSEGV else "")
    if os.WIFEXITED(status):
        return f"exited with status {os.WEXITSTATUS(status)} (os._exit or an exit of its process)"
    return f"ended (status {status})"


def _set_pdeathsig(parent: int) -> None:
    """Linux: this process gets SIGKILL when its parent dies (no orphan planner left running)."""
    with contextlib.suppress(Exception):
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    if os.getppid() != parent:  # the parent died before that
        os._exit(1)


def _close_other_fds(keep: int) -> None:
    try:
        fds = [int(n) for n in os.listdir("/proc/self/fd")]
    except OSError:
        fds = list(range(3, 1024))
    for fd in fds:
        if fd > 2 and fd != keep:
            with contextlib.suppress(OSError):
                os.close(fd)


def _where(tb: Any) -> tuple[str, list[str]]:
    frames = traceback.extract_tb(tb)
    if not frames:
        return "", []
    f = frames[-1]
    return f"{f.filename}:{f.name}", [f"{g.filename}:{g.lineno}:{g.name}" for g in frames[-8:]]


def _serve(conn: Connection, factory: Callable[[], Any]) -> None:
    """The child: build the object, then answer calls until the channel closes."""
    try:
        obj = factory()
        conn.send(("ok", None))
    except BaseException as exc:  # reported to the caller
        conn.send(("raised", (type(exc).__name__, str(exc), *_where(exc.__traceback__))))
        return
    while True:
        try:
            request = conn.recv()
        except (EOFError, OSError):
            return
        if request is None:
            return
        method, args = request
        try:
            result = getattr(obj, method)(*args)
        except BaseException as exc:  # whatever the object raises is the caller's to judge
            reply: tuple[str, Any] = ("raised", (type(exc).__name__, str(exc)[:2000], *_where(exc.__traceback__)))
        else:
            reply = ("ok", result)
        try:
            conn.send(reply)
        except Exception as exc:  # a result that cannot be pickled
            conn.send(("raised", (type(exc).__name__, f"cannot send the result of {method}(): {exc}"[:2000], "", [])))


class Hosted:
    """An object built by ``factory()`` in a child process; :meth:`call` runs its methods there.

    ``what`` names it in messages (``"the planner"``). Construction errors are raised as
    :class:`HostedError` from the constructor."""

    def __init__(self, factory: Callable[[], Any], what: str = "the hosted object", source: str = "") -> None:
        self.what = what
        self.source = source  # the hosted object's source file (where a death is located)
        self.pid = 0
        self.owner = os.getpid()
        self.ended: str | None = None  # how the child ended, once it did
        parent, child = Pipe(duplex=True)
        me = os.getpid()
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:  # the child
            code = 0
            try:
                parent.close()
                _close_other_fds(child.fileno())
                signal.signal(signal.SIGINT, signal.SIG_IGN)
                # a fault ends the child with its own signal (no library's crash handler, no dump)
                for sig in (signal.SIGALRM, signal.SIGPROF, signal.SIGTERM, signal.SIGSEGV, signal.SIGBUS,
                            signal.SIGFPE, signal.SIGILL, signal.SIGABRT):
                    with contextlib.suppress(OSError, ValueError):
                        signal.signal(sig, signal.SIG_DFL)
                with contextlib.suppress(Exception):
                    import faulthandler

                    faulthandler.disable()
                _set_pdeathsig(me)
                _serve(child, factory)
            except BaseException:  # never return into the caller's code
                code = 1
            finally:
                os._exit(code)
        self.pid = pid
        child.close()
        self.conn = parent
        self._answer("construction")

    def call(self, method: str, *args: Any) -> Any:
        """``obj.method(*args)`` in the child; :class:`HostedError` when it raised,
        :class:`HostDied` when its process is gone. Anything raised in the caller while it
        waits (the watchdog's hang, Ctrl-C) kills the child and propagates."""
        if self.ended is not None:
            raise HostDied(f"{self.what}: its process had ended ({self.ended}); {method}() not run",
                           f"{self.source}:{method}" if self.source else "")
        try:
            self.conn.send((method, args))
        except (OSError, ValueError):
            self._died(method)
        return self._answer(f"{method}()")

    def _answer(self, during: str) -> Any:
        try:
            status, value = self.conn.recv()
        except (EOFError, OSError):
            self._died(during)
        except BaseException:
            self.kill("it was interrupted (a hang, or the program's own interrupt)")
            raise
        if status == "raised":
            raise HostedError(*value)
        return value

    def _died(self, during: str) -> None:
        self.ended = self._reap(block=True)
        method = during.removesuffix("()")
        raise HostDied(f"{self.what}: its process {self.ended} during {during}",
                       f"{self.source}:{method}" if self.source else "")

    def _reap(self, block: bool) -> str:
        try:
            pid, status = os.waitpid(self.pid, 0 if block else os.WNOHANG)
        except ChildProcessError:
            return "ended"
        return describe_status(status) if pid else "still running"

    def kill(self, why: str = "killed") -> None:
        """End the child now (it hangs, or is no longer wanted)."""
        if self.ended is None and self.pid:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, signal.SIGKILL)
            self._reap(block=True)
            self.ended = why
        with contextlib.suppress(Exception):
            self.conn.close()

    def close(self) -> None:
        """Let the child end (end of input) and reap it."""
        if self.ended is None and self.pid:
            with contextlib.suppress(Exception):
                self.conn.send(None)
            with contextlib.suppress(Exception):
                self.conn.close()
            # a child busy elsewhere (it should not be) is not waited for
            if self._reap(block=False) == "still running":
                with contextlib.suppress(ProcessLookupError):
                    os.kill(self.pid, signal.SIGKILL)
                self._reap(block=True)
            self.ended = "closed"

    def __del__(self) -> None:
        if getattr(self, "pid", 0) and os.getpid() == getattr(self, "owner", None):
            with contextlib.suppress(Exception):
                self.close()


__all__ = ["HostDied", "Hosted", "HostedError", "describe_status"]
