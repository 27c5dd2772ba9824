"""The event-loop guard of the test suite: times every event-loop callback (CPU and blocked wall time) so a test
fails when the loop computes or blocks for too long, and when a test that ran an event loop leaves a thread
running. ``tests/conftest.py`` runs it around every test (:func:`guard`, autouse), so no test that runs a loop
(``asyncio.run``, a service, a client) can run it unguarded.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import gc
import logging
import resource
import sys
import threading
import time
from collections.abc import Callable, Iterator

import pytest

# --- the event-loop guard: no blocking call inside the loop, no leaked thread ------------------------------

# A loop callback (a task step included) that computes on the loop thread for longer than this (s, CPU time)
# fails the test: work that belongs in a thread. Half asyncio's own slow_callback_duration (0.1 s, wall). Not
# lower: on the virtual machines that run this suite (here and CI), memory a process has not touched for
# half a second costs 8-26 us a 4 KiB page to touch again, against 0.3 us warm (scripts/cold_memory), so a
# callback that wakes an idle loop and walks ~600 pages of the service's objects (a fault published to every
# face, the health check) shows 10-23 ms of CPU for ~1 ms of work.
SLOW_CALLBACK_S = 0.05
# A callback that keeps the loop for longer than this (s, wall time less the time the thread waited for a
# CPU and for another thread's interpreter lock, :data:`LOCK_WAIT_S`) fails the test: a blocking call (sleep,
# connect, a wait for a thread, I/O). Larger than the CPU limit: short waits for the lock still count here.
BLOCKED_CALLBACK_S = 0.25
# Time a callback spent off its CPU without a wait in a system call and without waiting for a CPU is not held:
# blocking is a wait (see the rule in :func:`slow_callbacks`).
# Threads started by a test get this long (s) to end after it before they count as leaked.
THREAD_GRACE_S = 5.0
# A garbage collection that the interpreter happens to start inside a callback is the heap's cost, not the
# callback's (in the test process the heap holds every module and fixture of the whole suite, gigabytes):
# its time is taken out of the callback's figures. Young collections (generations 0 and 1: the objects made
# lately) inside one callback longer than this (s, wall) still fail; a full collection walks the whole
# process's heap, partly cold, and took 2.6-4.7 s in the full suite's process: the suite's size, not the
# callback's.
GC_PAUSE_S = 0.25
# While another thread holds the interpreter lock without letting go (C code that does not release it: LLVM,
# some numpy calls), the loop waits however little its callback does. That wait is measured (:class:`_LockWatch`)
# and taken out of the held time; it fails on its own only beyond this (s, in one callback): a worker stalling the
# service's loop this long is a product problem, not a blocking call in the loop. 4 s, not 2: three full-suite runs
# on a slow day charged two-camera Scanner.scan steps 2.2-2.8 s of it (340-460 waits, no CPU, no held time), each
# time with a decoder thread seen in a garbage-collection callback of the suite's 6.8 GB heap that the collection
# clock did not catch (cause not pinned); a scan's own lock waits stay under 1 s in the service's runs.
LOCK_WAIT_S = 4.0
# Where several threads run Python in turns (a two-camera scan's decoders and cameras), none holds the lock long
# enough for the watch to see a gap, yet the loop thread can lose the hand-over again and again: each attempt is a
# timed wait of the switch interval (5 ms). In a callback with at least this many waits, up to CONVOY_WAIT_FACTOR
# switch intervals a wait (less what the watch saw) counts with the lock waits (:data:`LOCK_WAIT_S`), not as a
# blocking call. A sleep, a connect or a read is one long wait and still counts; what this can hide is a blocking
# call no longer than that allowance inside a callback that lost the lock that often. Seen in full-suite runs on
# a slow day: Scanner.scan's step held 0.3-0.9 s with 0 ms CPU in 60-180 waits of 5.0-5.1 ms, no gap seen.
CONVOY_MIN_WAITS = 10
CONVOY_WAIT_FACTOR = 1.2


class _LockWatch:
    """Spans of time in which some thread held the interpreter lock without letting go.

    A daemon thread sleeps :data:`TICK_S` at a time; every wake-up needs the lock, so a gap between two wake-ups
    much longer than the tick is a span in which another thread held it (a thread blocked in a system call, the
    loop's own ``time.sleep`` included, lets go of it, and the watch runs on). Each gap longer than
    :data:`GAP_S` is kept with the names and frames of the other threads right after it.
    """

    TICK_S = 0.002
    GAP_S = 0.03

    def __init__(self) -> None:
        self.gaps: collections.deque[tuple[float, float, str]] = collections.deque(maxlen=256)
        self.thread = threading.Thread(target=self._run, name="loopguard-lock-watch", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        last = time.perf_counter()
        me = threading.get_ident()
        while True:
            time.sleep(self.TICK_S)
            now = time.perf_counter()
            if now - last > self.GAP_S + self.TICK_S:
                self.gaps.append((last + self.TICK_S, now, self._who(me)))
            last = now

    @staticmethod
    def _who(me: int) -> str:
        names = {t.ident: t.name for t in threading.enumerate()}
        where = []
        for tid, frame in sys._current_frames().items():
            if tid == me or frame is None:
                continue
            where.append(f"{names.get(tid, tid)} at {frame.f_code.co_filename.rsplit('/', 1)[-1]}:{frame.f_lineno} "
                         f"({frame.f_code.co_name})")
        return "; ".join(where[:6])

    def waited(self, t0: float, t1: float) -> tuple[float, str]:
        """Seconds of [t0, t1] inside such spans, and the threads seen after the longest of them."""
        total, longest, who = 0.0, 0.0, ""
        for a, b, w in list(self.gaps):
            part = min(b, t1) - max(a, t0)
            if part > 0:
                total += part
                if part > longest:
                    longest, who = part, w
        return total, who


_LOCKS = _LockWatch()


class _ThreadClock:
    """Time spent on something, per thread: running totals (s of CPU, s of wall)."""

    def __init__(self) -> None:
        self._totals: dict[int, tuple[float, float]] = {}
        self.wall_all = 0.0  # s of wall on every thread together

    def add(self, tid: int, cpu: float, wall: float) -> None:
        c, w = self._totals.get(tid, (0.0, 0.0))
        self._totals[tid] = (c + cpu, w + wall)
        self.wall_all += wall

    def totals(self, tid: int) -> tuple[float, float]:
        """(CPU, wall) seconds counted so far on thread ``tid``; an interval's share is the difference."""
        return self._totals.get(tid, (0.0, 0.0))

    def since(self, tid: int, mark: tuple[float, float]) -> tuple[float, float]:
        """(CPU, wall) seconds counted on thread ``tid`` since :meth:`totals` gave ``mark``."""
        cpu, wall = self.totals(tid)
        return cpu - mark[0], wall - mark[1]


class _GcClock(_ThreadClock):
    """Time the interpreter spent collecting garbage, per thread (s of CPU and of wall), from ``gc.callbacks``."""

    def __init__(self) -> None:
        super().__init__()
        self._start: dict[int, tuple[float, float]] = {}
        self.young = _ThreadClock()  # generations 0 and 1 only

    def __call__(self, phase: str, info: dict[str, int]) -> None:
        tid = threading.get_ident()
        if phase == "start":
            self._start[tid] = (time.thread_time(), time.perf_counter())
            return
        begun = self._start.pop(tid, None)
        if begun is None:
            return
        cpu, wall = time.thread_time() - begun[0], time.perf_counter() - begun[1]
        self.add(tid, cpu, wall)
        if info.get("generation", 2) < 2:
            self.young.add(tid, cpu, wall)

    def running_elsewhere(self, tid: int, since: float) -> float:
        """Wall seconds since ``since`` of the collections still running on threads other than ``tid``: one
        that holds the interpreter lock past the end of a callback is not in :attr:`wall_all` yet (its stop
        callback runs after the loop thread took the lock back)."""
        now = time.perf_counter()
        return sum(max(0.0, now - max(w, since)) for t, (_, w) in list(self._start.items()) if t != tid)


class _HarnessLogClock(_ThreadClock):
    """Time pytest's own log handlers spent on each thread (s of CPU and of wall, garbage collections left out).

    Under pytest every record goes through its capture handlers (the report section, ``caplog``, live logging),
    which in a process that holds the whole suite cost up to ~30 ms for the first traceback logged: the
    harness's cost, not the service's (which writes a line to stderr). Handlers of any other module are not
    timed here, so the service's own logging still counts.
    """

    def __init__(self, gc_clock: _GcClock) -> None:
        super().__init__()
        self._gc = gc_clock

    def wrap(self, real: Callable[[logging.Handler, logging.LogRecord], bool]) -> Callable[..., bool]:
        def handle(handler: logging.Handler, record: logging.LogRecord) -> bool:
            if not type(handler).__module__.startswith("_pytest"):
                return real(handler, record)
            tid = threading.get_ident()
            c0, w0, gc0 = time.thread_time(), time.perf_counter(), self._gc.totals(tid)
            try:
                return real(handler, record)
            finally:
                gc_cpu, gc_wall = self._gc.since(tid, gc0)
                self.add(tid, time.thread_time() - c0 - gc_cpu, time.perf_counter() - w0 - gc_wall)

        return handle


# The originals, taken at import: a guard opened inside another (the guard's own tests) replaces the outer one
# for its block instead of timing each callback twice.
_REAL_HANDLE_RUN = asyncio.events.Handle._run
_REAL_LOG_HANDLE = logging.Handler.handle


class _NumbaCompiles:
    """Whether numba compiled or loaded anything (on any thread) since a mark: a kernel compiled for the first
    time (a cold cache, as on a fresh clone in CI), or loaded from the disk cache, holds the interpreter lock in
    LLVM for up to seconds, which the loop then waits for. That wait is the cold cache's, not the code's: a
    callback during which a compilation or a load ran is still held to the CPU limit, not to the blocking one.
    The service itself warms every kernel before it reports ready."""

    def __init__(self) -> None:
        self.active = 0
        self.events = 0
        try:
            from numba.core import event
        except ImportError:  # pragma: no cover - numba is a dependency
            return
        outer = self

        class _Listener(event.Listener):  # type: ignore[misc]
            def on_start(self, ev: object) -> None:
                outer.active += 1
                outer.events += 1

            def on_end(self, ev: object) -> None:
                outer.active -= 1
                outer.events += 1

        event.install_listener("numba:compile", _Listener())
        # a kernel loaded from numba's on-disk cache (compiled earlier by another process of the suite, a
        # subprocess test) holds the lock in LLVM too, for up to a second, and raises no compile event
        from numba.core import caching

        real_load = caching.Cache.load_overload

        def load_overload(cache: object, *args: object, **kwargs: object) -> object:
            outer.active += 1
            outer.events += 1
            try:
                return real_load(cache, *args, **kwargs)
            finally:
                outer.active -= 1
                outer.events += 1

        caching.Cache.load_overload = load_overload  # type: ignore[method-assign,assignment]

    def mark(self) -> int:
        return self.events

    def since(self, mark: int) -> bool:
        return self.active > 0 or self.events != mark


_COMPILES = _NumbaCompiles()


def _blocked_count() -> int:
    """How many times this thread has given up its CPU of its own accord so far: each wait in a system call (a
    sleep, I/O, a lock, the interpreter lock) counts; being preempted does not (``getrusage(RUSAGE_THREAD)``'s
    voluntary context switches; 0.3 us a call here). The guard's message says how many a slow callback made."""
    return resource.getrusage(resource.RUSAGE_THREAD).ru_nvcsw


def _run_delay_s() -> float:
    """Time this thread has spent runnable but waiting for a CPU (s), from the scheduler's statistics."""
    try:
        with open("/proc/thread-self/schedstat", "rb") as f:
            return int(f.read().split()[1]) / 1e9
    except (OSError, ValueError, IndexError):
        return 0.0  # no schedstat: plain wall time


@contextlib.contextmanager
def slow_callbacks(
    monkeypatch: pytest.MonkeyPatch,
    ran: list[int] | None = None,
    *,
    cpu_s: float | None = None,
    held_s: float | None = None,
) -> Iterator[list[str]]:
    """Within the block, every event-loop callback (a task step included) that computes on the loop for more
    than :data:`SLOW_CALLBACK_S` or blocks it for more than :data:`BLOCKED_CALLBACK_S` is described in the list
    it gives; ``ran[0]``, where given, counts the callbacks run.

    Computing is the loop thread's CPU time; blocking is wall time less the time the thread waited for a CPU
    (other processes on a busy machine), both less the garbage collections run meanwhile on the loop thread
    (:class:`_GcClock`; more than :data:`GC_PAUSE_S` of young ones in one callback counts on its own) and less the
    time pytest's own log handlers took (:class:`_HarnessLogClock`). asyncio's debug mode would measure plain
    wall time and add its own bookkeeping to every callback, which alone pushes task steps past 20 ms on a
    loaded machine.
    """
    slow: list[str] = []
    cpu_limit = SLOW_CALLBACK_S if cpu_s is None else cpu_s
    held_limit = BLOCKED_CALLBACK_S if held_s is None else held_s
    real_run = _REAL_HANDLE_RUN
    counter = ran if ran is not None else [0]
    gc_clock = _GcClock()
    log_clock = _HarnessLogClock(gc_clock)

    def timed_run(handle: asyncio.events.Handle) -> None:
        counter[0] += 1
        tid = threading.get_ident()
        t0, c0, d0, v0 = time.perf_counter(), time.thread_time(), _run_delay_s(), _blocked_count()
        gc0, young0, log0 = gc_clock.totals(tid), gc_clock.young.totals(tid), log_clock.totals(tid)
        compiles0 = _COMPILES.mark()
        gc_all0 = gc_clock.wall_all
        try:
            real_run(handle)
        finally:
            gc_cpu, gc_wall = gc_clock.since(tid, gc0)
            # a collection on another thread holds the interpreter lock as well: the loop waited for the
            # suite's heap, not for the callback (a test's full collection in a worker thread, 1 s here)
            other_gc_wall = max(0.0, gc_clock.wall_all - gc_all0 - gc_wall) + gc_clock.running_elsewhere(tid, t0)
            young_wall = gc_clock.young.since(tid, young0)[1]
            log_cpu, log_wall = log_clock.since(tid, log0)
            cpu = time.thread_time() - c0 - gc_cpu - log_cpu
            delay = _run_delay_s() - d0
            held = time.perf_counter() - t0 - delay - gc_wall - log_wall - other_gc_wall
            compiled = _COMPILES.since(compiles0)
            # the spans another thread held the interpreter lock, less what the loop thread computed itself (its
            # own long C call shows as CPU) and the other threads' collections already taken out. Where the loop
            # thread was preempted holding the lock, the watch's gap and the wait for a CPU are the same time and
            # both are taken out: on a crowded CPU a short blocking call can hide there. Taking out only what
            # exceeds the wait for a CPU instead failed 11 service tests of the full suite (0 ms CPU, 0.3-0.9 s
            # left as held in 60-180 waits: the loop waited for the lock while the decoders' threads took turns)
            locked, who = _LOCKS.waited(t0, time.perf_counter())
            lock_wait = max(0.0, locked - cpu - other_gc_wall)
            held -= lock_wait
            waits = _blocked_count() - v0  # said in the message: 0 means it never blocked, only waited for a CPU
            # no wait in a system call: the thread never blocked (a sleep, a read, a lock, the interpreter lock: each
            # is at least one), so time it spent off its CPU without a wait for a CPU is the machine's, not the
            # callback's (seen twice in full runs: 0.3-0.75 s with 1-2 ms CPU and no lock gap)
            unaccounted = max(held, 0.0) if waits == 0 else 0.0
            held -= unaccounted
            if waits >= CONVOY_MIN_WAITS:  # the lock's hand-over lost again and again (see CONVOY_MIN_WAITS)
                convoy = min(max(held, 0.0),
                             max(0.0, waits * CONVOY_WAIT_FACTOR * sys.getswitchinterval() - lock_wait))
                held -= convoy
                lock_wait += convoy
            if (cpu > cpu_limit or (held > held_limit and not compiled) or young_wall > GC_PAUSE_S
                    or lock_wait > LOCK_WAIT_S):
                slow.append(
                    f"{cpu * 1e3:.0f} ms CPU, {held * 1e3:.0f} ms held (garbage collection {gc_wall * 1e3:.0f} ms, "
                    f"{gc_cpu * 1e3:.0f} ms CPU, not counted; {young_wall * 1e3:.0f} ms of it young; "
                    f"{other_gc_wall * 1e3:.0f} ms on other threads, not counted; {lock_wait * 1e3:.0f} ms waiting "
                    f"for another thread's interpreter lock, counted on its own{f' ({who})' if who else ''}; "
                    f"{waits} wait(s) in system calls; {unaccounted * 1e3:.0f} ms off the CPU with no wait, not "
                    f"counted), in {_describe(handle)}"
                )

    with monkeypatch.context() as patch:
        patch.setattr(asyncio.events.Handle, "_run", timed_run)
        patch.setattr(logging.Handler, "handle", log_clock.wrap(_REAL_LOG_HANDLE))
        gc.callbacks.append(gc_clock)
        try:
            yield slow
        finally:
            gc.callbacks.remove(gc_clock)


def _describe(handle: asyncio.events.Handle) -> str:
    cb = getattr(handle, "_callback", None)
    task = getattr(cb, "__self__", None)
    if isinstance(task, asyncio.Task):
        coro = task.get_coro()
        frame = getattr(coro, "cr_frame", None)
        where = f" at {frame.f_code.co_filename.rsplit('/', 1)[-1]}:{frame.f_lineno}" if frame is not None else ""
        inner: list[str] = []  # where the step ended, innermost last: the await chain below the task
        awaited = getattr(coro, "cr_await", None)
        while awaited is not None and getattr(awaited, "cr_frame", None) is not None and len(inner) < 6:
            f = awaited.cr_frame
            inner.append(f"{f.f_code.co_qualname} at {f.f_code.co_filename.rsplit('/', 1)[-1]}:{f.f_lineno}")
            awaited = getattr(awaited, "cr_await", None)
        chain = f", awaiting {' > '.join(inner)}" if inner else ""
        return f"task {task.get_name()} ({getattr(coro, '__qualname__', coro)}{where}{chain})"
    return repr(handle)[:200]


@contextlib.contextmanager
def guard(
    monkeypatch: pytest.MonkeyPatch,
    *,
    check_threads: bool = False,
    cpu_s: float | None = None,
    held_s: float | None = None,
) -> Iterator[None]:
    """Run the block under the loop guard; on leaving, fail (``AssertionError``) when a loop callback in it was
    slow (:func:`slow_callbacks`), or when it ran an event loop (or ``check_threads``) and a thread it started
    is still running :data:`THREAD_GRACE_S` later. A block that runs no event loop is not held to the thread
    rule: thread pools of sync code are not this guard's business. ``cpu_s`` / ``held_s`` replace the limits
    (:data:`SLOW_CALLBACK_S`, :data:`BLOCKED_CALLBACK_S`) for a test marked ``loop_guard_limits`` with a reason.
    """
    before = set(threading.enumerate())
    ran = [0]
    with slow_callbacks(monkeypatch, ran, cpu_s=cpu_s, held_s=held_s) as slow:
        yield
    assert not slow, "the event loop was blocked: " + "; ".join(slow[:5])
    if not (ran[0] or check_threads):
        return
    end = time.monotonic() + THREAD_GRACE_S
    leaked = [t for t in threading.enumerate() if t not in before and t.is_alive()]
    while leaked and time.monotonic() < end:
        time.sleep(0.05)
        leaked = [t for t in leaked if t.is_alive()]
    assert not leaked, f"threads left running after the test: {[t.name for t in leaked]}"
