"""Zenoh's runtime as dyknow runs it: the layout of its threads, callbacks on them, its errors in words.

Zenoh runs its network on tokio runtimes of its own, laid out by ``ZENOH_RUNTIME`` (see
:data:`ZENOH_RUNTIME`), and calls back into Python on their threads: :func:`inline_handler`
runs a callback right there, keeping the thread's Python state between calls. Zenoh's errors
carry the Rust source location they were raised at: :func:`error_text` trims it off.
"""

from __future__ import annotations

import ctypes
import os
import re
import threading
from collections.abc import Callable
from typing import Any, Final

import zenoh

from dyknow.errors import TransportError

__all__ = ["ZENOH_RUNTIME", "error_text", "inline_handler", "inline_handler_with_end", "keep_thread_state", "lay_out_runtimes", "panic_error", "pinned", "wait_for_handlers"]

# --------------------------------------------------------------------------- Zenoh's runtimes

#: How dyknow has Zenoh lay out its network threads, unless the process sets ``ZENOH_RUNTIME``
#: itself (Zenoh's syntax; ``ZENOH_RUNTIME='()'`` gives Zenoh's own defaults). By default Zenoh
#: reads sockets on its ``net`` and ``acc`` runtimes' threads and hands every message over to
#: the ``rx`` runtime, another thread, and tokio then often wakes rx's second worker as well.
#: Handing ``net`` and ``acc`` over to ``rx`` makes the thread that is woken by the socket the one
#: that handles the message (``benchmarks/chain.py``: raw Zenoh with this layout,
#: ``zenoh-process-tuned``, against Zenoh's own, ``zenoh-process``). The ``tx`` runtime stays apart on purpose: a put with congestion
#: control BLOCK from a receive callback waits for the tx task, which must not need the waiting
#: thread (Zenoh's source warns that receiving on TX deadlocks). ``rx`` keeps its two workers, so
#: one slow callback does not stop every link.
ZENOH_RUNTIME: Final = "(net: (handover: rx), acc: (handover: rx))"


def lay_out_runtimes() -> None:
    """Set ``ZENOH_RUNTIME`` to :data:`ZENOH_RUNTIME` unless the process chose its own. Zenoh reads
    it once, when it first starts a runtime: from then on it no longer has any effect."""
    os.environ.setdefault("ZENOH_RUNTIME", ZENOH_RUNTIME)


def panic_error(exc: BaseException) -> TransportError | None:
    """A clear error for a Zenoh panic while opening a session (it escapes ``except Exception``),
    else None. The usual cause is a ``ZENOH_RUNTIME`` Zenoh cannot parse; once Zenoh panicked
    so, every later open in the process panics too ("Once panicked")."""
    if type(exc).__name__ != "PanicException":
        return None
    text = str(exc)[:300]
    chosen = os.environ.get("ZENOH_RUNTIME")
    if chosen is None or chosen == ZENOH_RUNTIME:
        return TransportError(f"Zenoh failed while opening a session: {text}")
    return TransportError(
        f"Zenoh cannot start with ZENOH_RUNTIME={chosen!r}: {text}",
        where="environment variable ZENOH_RUNTIME",
        expected=f"Zenoh's runtime syntax, e.g. {ZENOH_RUNTIME!r} (dyknow's default) or '()' (Zenoh's own); "
        "or unset it, and start the process again",
    )


# --------------------------------------------------------------------------- Zenoh's threads

# Zenoh runs an inline callback on its own (Rust) threads and takes the GIL through
# PyGILState_Ensure. On a thread Python does not know, that builds a thread state and frees it
# again when the callback returns: per message, an mmap and a munmap of the 16 kB frame stack, a
# gettid, and cold caches (measured with strace: one of each per message on a relay). Taking the
# GIL once more and never giving it back keeps the thread state for the life of Zenoh's thread,
# so later callbacks reuse it.
# Every callback checks that its thread was seen, in a thread-local attribute: exact, since it
# lives in the thread's own state. (An earlier check by the thread's ident in a set cost half as
# much on a cold cache, 4 vs 8 µs on a relay at 50 Hz, but was not exact: once a pinned thread
# ends, a new thread can get its ident and pass as pinned, and then builds and frees a thread
# state per message again; the test suite twice caught a Zenoh thread losing its state, most
# likely that way.) Only threads Python did not start are
# pinned: a callback can also run on a Python thread (a call or a declaration from this very
# session), which has a state of its own.
pinned: Final = threading.local()  # seen: set once the thread was looked at (and pinned if foreign)
_gil_ensure: Final[Callable[[], int] | None] = getattr(getattr(ctypes, "pythonapi", None), "PyGILState_Ensure", None)


def keep_thread_state() -> None:
    """Keep this thread's Python state past the current callback (see above) if Python did not
    start the thread (it then shows as a "dummy" thread to ``threading``); once per thread."""
    if type(threading.current_thread()).__name__ == "_DummyThread" and _gil_ensure is not None:
        _gil_ensure()
    pinned.seen = True


# The inline handlers Zenoh holds: it lets go of one (calling its drop) on a thread of its own,
# when its entity is undeclared or its request ends, which may come a moment after the session
# closed. One let go while the interpreter is torn down calls into Python then, and the process
# aborts ("FATAL: exception not rethrown", exit -6, after it had done its work): at exit, once
# the sessions are closed, :func:`wait_for_handlers` waits for them (dyknow.transport.session).
_held: Final = threading.Condition()
_held_count: Final[list[int]] = [0]


def _hold() -> Callable[[], None]:
    """Count a handler handed to Zenoh; the function Zenoh calls as it lets go of it."""
    with _held:
        _held_count[0] += 1

    def let_go() -> None:
        with _held:
            _held_count[0] -= 1
            _held.notify_all()

    return let_go


def wait_for_handlers(timeout_s: float) -> bool:
    """Wait until Zenoh has let go of every inline handler (at most ``timeout_s``); whether it has."""
    with _held:
        return _held.wait_for(lambda: _held_count[0] <= 0, timeout_s)


def inline_handler(callback: Callable[[Any], None]) -> Any:
    """A Zenoh handler that runs ``callback`` on the thread delivering the sample, keeping that
    thread's Python state between calls."""

    def run(arg: Any) -> None:
        if not getattr(pinned, "seen", False):
            keep_thread_state()
        callback(arg)

    return zenoh.handlers.Callback(run, _hold(), indirect=False)


def inline_handler_with_end(callback: Callable[[Any], None], end: Callable[[], None]) -> Any:
    """:func:`inline_handler`, and ``end()`` once Zenoh lets go of the handler (a request ended)."""

    def run(arg: Any) -> None:
        if not getattr(pinned, "seen", False):
            keep_thread_state()
        callback(arg)

    let_go = _hold()

    def ended() -> None:
        try:
            end()
        finally:
            let_go()

    return zenoh.handlers.Callback(run, ended, indirect=False)


def error_text(exc: BaseException) -> str:
    """Zenoh's message without the Rust source locations it appends."""
    text = str(exc)
    text = re.sub(r" at /\S+\.rs:\d+\.?", "", text)
    return text.strip().rstrip(".")

