"""Stop signals: SIGINT (Ctrl-C) and SIGTERM (``kill``, Slurm time limits, container stops) end a run
the same way, with the frames written so far kept and marked incomplete.

``handle_stop_signals()`` (installed by the CLI around every run, and by each sweep job) turns both
signals into :class:`RunInterrupted`, a ``KeyboardInterrupt``, so every ``except BaseException`` /
``finally`` that closes a writer runs. Python drops an exception raised while it runs a finaliser or
a weakref callback ("Exception ignored in ..."): a Ctrl-C landing there would be lost and the run
would go on. The signal is therefore also remembered, and :func:`check` (called by the rollout and
fit loops between chunks) raises it again: one signal always stops a run.

A second signal while the first is being handled (outputs being closed) is reported and otherwise
ignored, so the files being finished are not cut in half; a third one kills the process at once.
The process that runs a parallel sweep instead passes the first signal on to its job processes
(:func:`forward_to`) and waits for them to close their files; a second signal stops it at once.

A job of a submitit (Slurm) sweep also stops this way on submitit's warning signal (SIGUSR2, sent
``signal_delay_s`` before the time limit or on a preemption; :func:`submitit_warning_signal`).
"""
from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from typing import Callable

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)

_pending: int | None = None   # the signal received and not yet handled to the end
_count = 0


class RunInterrupted(KeyboardInterrupt):
    """The run was stopped by a signal (``signum``: SIGINT or SIGTERM)."""

    def __init__(self, signum: int = signal.SIGINT):
        self.signum = int(signum)
        super().__init__(self.reason)

    @property
    def signal_name(self) -> str:
        return signal.Signals(self.signum).name

    @property
    def reason(self) -> str:
        if self.signum == submitit_warning_signal():
            return (f"stopped by {self.signal_name} (the scheduler's warning before the job's time limit, or a "
                    f"preemption; sent by submitit)")
        return {signal.SIGINT: "interrupted by SIGINT (Ctrl-C)",
                signal.SIGTERM: "terminated by SIGTERM (kill, a scheduler's time limit or a container stop)"
                }.get(self.signum, f"stopped by {self.signal_name}")

    @property
    def exit_code(self) -> int:
        return 128 + self.signum   # the shell's convention: 130 for SIGINT, 143 for SIGTERM

    def __reduce__(self):          # crosses a sweep launcher's process boundary
        return (RunInterrupted, (self.signum,))


def submitit_warning_signal() -> int | None:
    """The signal submitit sends a job before its time limit and on a preemption: SIGUSR2, or the one
    named by ``SUBMITIT_PREEMPT_SIGNAL`` (submitit's own setting). Submitit's handler for it checkpoints
    and requeues the job to start over, which an mpmlab run cannot resume: a sweep job stops on it
    instead, its frames kept and marked, like on SIGTERM."""
    return getattr(signal, "SIG" + os.environ.get("SUBMITIT_PREEMPT_SIGNAL", "USR2"), None)


def stop_reason(exc: BaseException) -> str:
    """How an exception that ended a run reads in a log or a file attribute."""
    if isinstance(exc, RunInterrupted):
        return exc.reason
    if isinstance(exc, KeyboardInterrupt):
        return "interrupted by SIGINT (Ctrl-C)"
    return f"{type(exc).__name__}: {exc}"


_forward: "Callable[[int], None] | None" = None   # a sweep's parent: stop the jobs instead of raising


def forward_to(on_stop: "Callable[[int], None] | None") -> None:
    """Make the first stop signal call ``on_stop(signum)`` instead of raising (the process that runs a
    parallel sweep tells its job processes to stop, each keeping its frames, and waits for them; a
    second signal raises)."""
    global _forward
    _forward = on_stop


_deferring = 0   # > 0 inside deferred(): a signal is remembered and raised when the block ends


@contextlib.contextmanager
def deferred():
    """Run the block whole: a stop signal arriving inside it is raised when it ends. Keeps the outputs
    of one frame in step (the trajectory, the metrics, the summary's frame count)."""
    global _deferring
    _deferring += 1
    try:
        yield
    finally:
        _deferring -= 1
    if _deferring == 0:
        check()


def _handler(signum, frame):
    global _pending, _count
    _count += 1
    if _count == 1:
        _pending = signum
        if _forward is not None:
            _forward(signum)
            return
        if _deferring:
            return
        raise RunInterrupted(signum)
    if _count == 2 and _forward is not None:
        raise RunInterrupted(signum)
    if _count == 2:
        print(f"mpmlab: {signal.Signals(signum).name} again: still closing the outputs written so far "
              f"(send it once more to kill at once, losing them).", file=sys.stderr, flush=True)
        return
    signal.signal(signum, signal.SIG_DFL)
    os.kill(os.getpid(), signum)


def pending() -> int | None:
    """The stop signal received during this run, or None."""
    return _pending


def check() -> None:
    """Raise :class:`RunInterrupted` if a stop signal arrived (also when its first raise was lost)."""
    if _pending is not None:
        raise RunInterrupted(_pending)


def reset() -> None:
    global _pending, _count, _forward
    _pending, _count, _forward = None, 0, None


@contextlib.contextmanager
def handle_stop_signals(extra: tuple[int, ...] = ()):
    """Within the block, SIGINT, SIGTERM and the ``extra`` signals raise :class:`RunInterrupted` (main
    thread only; elsewhere the block runs with the handlers it found)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    signals = STOP_SIGNALS + tuple(s for s in extra if s not in STOP_SIGNALS)
    previous = {s: signal.getsignal(s) for s in signals}
    reset()
    for s in signals:
        signal.signal(s, _handler)
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h if h is not None else signal.SIG_DFL)
        reset()
