"""Ctrl-C for a command: one line `lgnn: interrupted` and exit 130, whenever it comes.

`run_interruptibly(command)` runs `command(interrupts_after_loading)` and returns its
exit status, or `EXIT_INTERRUPTED` after printing the one line. Ctrl-C at any moment,
while JAX loads or compiles included, ends so (one dropped inside a callback is
delivered again); `interrupts_after_loading()` is the context in which a command loads
numpy and JAX (`lgnn.runtime.configure`).

A Ctrl-C during an XLA compilation is held until that compilation ends. JAX waits
for a compilation interruptibly, but the compilation itself goes on in XLA's thread
pool, and nothing cancels or waits for it: leaving then destroyed the backend (its
devices) and LLVM's static state under the running compiler thread, a segmentation
fault after "lgnn: interrupted". "lgnn: interrupted" is printed at once; a second
Ctrl-C during the compilation leaves at once, without Python's shutdown.

`leave(code)` ends the process: a Ctrl-C after the command has returned, while the
interpreter ends, exits 130 with the one line too (the console script's `entry`).

`HeldWhileLoading` is the context an entry point's own imports run in: a Ctrl-C then
is remembered (`received`) and handed to `run_interruptibly`, not raised as a
traceback from an import. Nothing here is done at import: only the entry point
(`lgnn.cli`) takes SIGINT, and gives it back as it found it.
"""

from __future__ import annotations

import _thread
import contextlib
import os
import signal
import sys
import threading
from typing import Callable, ContextManager

EXIT_INTERRUPTED = 130  # Ctrl-C (128 + SIGINT, as shells report it)
_JAX_COMPILER = os.path.join("jax", "_src", "compiler.py")


def _holds_sigint() -> bool:
    # A SIGINT handler someone else set (or SIG_IGN, inherited) is left alone.
    return threading.current_thread() is threading.main_thread() and signal.getsignal(signal.SIGINT) is signal.default_int_handler


class HeldWhileLoading:
    """Context: a Ctrl-C inside it is appended to `received` instead of raised (where
    Python's own handler holds SIGINT; the handler is restored on leaving)."""

    def __init__(self):
        self.received: list[int] = []
        self.holds = False

    def __enter__(self) -> "HeldWhileLoading":
        self.holds = _holds_sigint()
        if self.holds:
            signal.signal(signal.SIGINT, lambda signum, frame: self.received.append(signum))
        return self

    def __exit__(self, *exc) -> bool:
        if self.holds:
            signal.signal(signal.SIGINT, signal.default_int_handler)
        return False

    def take(self) -> list[int]:
        """The Ctrl-Cs received so far, forgotten here."""
        received = self.received[:]
        self.received.clear()
        return received


def run_interruptibly(command: Callable[[Callable[[], ContextManager]], int], received: list[int] | None = None) -> int:
    """`command(interrupts_after_loading)`'s exit status, or `EXIT_INTERRUPTED` after one
    line on stderr (module docstring); `received`: Ctrl-Cs that came before (while the
    entry point loaded, `HeldWhileLoading.take`), which interrupt at once."""
    default_hook = sys.unraisablehook
    received, loading = list(received or ()), []  # Ctrl-Cs; a C extension loads
    owed, askers, announced, finished = [], [], [], threading.Event()

    def ask_again():
        # A Ctrl-C taken but not raised yet, delivered again a moment later from another
        # thread; we wait for these threads before SIGINT is given back.
        owed.append(True)
        askers.append(threading.Thread(target=_interrupt_main_later, args=(finished,), daemon=True))
        askers[-1].start()

    def redeliver_interrupts(unraisable):
        # Ctrl-C landing in a callback Python cannot raise from (JAX's garbage-collection
        # hook, a __del__) is printed and dropped: deliver it again once the main thread
        # is out of the callback.
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            ask_again()
        else:
            default_hook(unraisable)

    def on_interrupt(signum, frame):
        if owed:
            owed.pop()  # delivered again, not a new Ctrl-C
        else:
            received.append(signum)
        if finished.is_set():
            return
        if _inside_compilation(frame):
            if len(received) > 1:  # a second Ctrl-C: leave now, without Python's shutdown
                sys.stdout.flush()
                os._exit(EXIT_INTERRUPTED)
            if not announced:
                announced.append(_say_interrupted())
            ask_again()  # raised once the compilation has returned
            return
        if not loading:
            raise KeyboardInterrupt

    @contextlib.contextmanager
    def interrupts_after_loading():
        # numpy's and jaxlib's C initialisation print the traceback of an exception
        # raised inside it before failing the import: a Ctrl-C while they load is held
        # until they have (a second or two), then raised.
        loading.append(True)
        try:
            yield
        finally:
            loading.clear()
        if received:
            raise KeyboardInterrupt

    # Ctrl-C as Python takes it, but remembered: one inside a C extension's
    # initialisation comes out as the ImportError it caused.
    own_handler = _holds_sigint()
    if own_handler:
        signal.signal(signal.SIGINT, on_interrupt)
    sys.unraisablehook = redeliver_interrupts
    code = None  # None: interrupted
    try:
        if received:
            raise KeyboardInterrupt
        code = command(interrupts_after_loading)
    except KeyboardInterrupt:
        pass
    except Exception:
        if not received:
            raise  # a bug in lgnn, shown as one
    finally:
        finished.set()
        for asker in askers:  # signal.signal first runs what they asked for (quietly)
            asker.join()
        sys.unraisablehook = default_hook
        if own_handler:
            signal.signal(signal.SIGINT, signal.default_int_handler)
    if code is not None and not announced:
        return code
    if not announced:  # announced: a held Ctrl-C, which the command outran
        _say_interrupted()
    _forget_interrupted_source_text()
    return EXIT_INTERRUPTED


def leave(code: int):
    """End the process with exit status `code` (`sys.exit`), a Ctrl-C from here on, while
    the interpreter ends (atexit handlers: JAX shuts its backends down), leaving with the
    one line and `EXIT_INTERRUPTED`: Python's own handler would raise KeyboardInterrupt
    there, and Python then ends the process by the signal itself (a shell's -2, not 130)."""
    if _holds_sigint():
        signal.signal(signal.SIGINT, _leave_interrupted)
    sys.exit(code)


def _leave_interrupted(signum, frame) -> None:
    _say_interrupted()
    with contextlib.suppress(Exception):
        sys.stdout.flush()
    os._exit(EXIT_INTERRUPTED)


def _say_interrupted() -> bool:
    print("lgnn: interrupted", file=sys.stderr, flush=True)
    return True


def _forget_interrupted_source_text() -> None:
    # CPython remembers a KeyboardInterrupt that left an `exec` or `eval` of source text
    # (dataclasses and namedtuple build their methods so while modules import) and ends
    # the process by SIGINT at exit, whatever the command returned. Evaluating source
    # text again clears the memory.
    exec("pass")


def _inside_compilation(frame) -> bool:
    """Whether the Python frame `frame` waits on an XLA compilation (JAX's compiler)."""
    while frame is not None:
        code = frame.f_code
        if code.co_name.startswith("backend_compile") and code.co_filename.endswith(_JAX_COMPILER):
            return True
        frame = frame.f_back
    return False


def _interrupt_main_later(finished: threading.Event) -> None:
    if not finished.wait(0.05):
        _thread.interrupt_main()
