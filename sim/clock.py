"""Simulated time: virtual (``sleep`` advances ``now``) or following the wall clock."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable


class SimClock:
    """The :class:`xmalign.roles.Clock` of the simulator.

    In virtual mode (the default) ``sleep(dt)`` returns at once and advances
    ``now()`` by ``dt``, so hours of simulated calibration take seconds of CPU;
    devices evaluate their state analytically at ``now()``. With
    ``real_time=True`` (served devices) ``now()`` follows the wall clock from
    ``start_s`` on and ``sleep`` really sleeps. Thread-safe.
    """

    def __init__(self, start_s: float = 0.0, real_time: bool = False) -> None:
        self.real_time = real_time
        self._lock = threading.Lock()
        self._now_s = start_s
        self._wall_origin_s = time.monotonic() - start_s

    def now(self) -> float:
        if self.real_time:
            return time.monotonic() - self._wall_origin_s
        with self._lock:
            return self._now_s

    def follow_wall_clock(self) -> None:
        """Go on in real time from the current ``now()`` (a setup prepared in virtual time,
        then served)."""
        with self._lock:
            self._wall_origin_s = time.monotonic() - self._now_s
            self.real_time = True

    def sleep(self, seconds: float) -> None:
        if self.real_time:
            time.sleep(max(0.0, seconds))
            return
        with self._lock:
            self._now_s += max(0.0, seconds)

    def await_stream(self) -> None:
        """Nothing to do: in-process devices are read, not streamed."""


class Follower:
    """A thread of a :class:`LockstepClock` that runs only when the clock lets it.

    ``wake_s`` is when its ``sleep`` ends (None: it waits for :meth:`LockstepClock.resume`).
    """

    def __init__(self, name: str) -> None:
        self.name = name
        self.wake_s: float | None = None
        self.running = True
        self.done = False
        self.released = False
        self.error: BaseException | None = None


class _Timer:
    def __init__(self, next_s: float, period_s: float, callback: Callable[[], None]) -> None:
        self.next_s = next_s
        self.period_s = period_s
        self.callback = callback
        self.cancelled = False


class LockstepClock(SimClock):
    """Virtual time shared by a host and served devices in threads of one process.

    Time advances only when a *driving* thread (the host; a streaming
    instrument) calls :meth:`sleep`. Threads started with
    :meth:`start_follower` (a served CNC running its program) instead block in
    ``sleep`` until virtual time reaches their wake time: the driving thread's
    ``sleep`` stops at every wake time and timer on its way, sets the time
    there, lets that follower or timer run until it blocks again, and goes on.
    So every device acts at its own virtual time, whatever the wall clock does,
    and a served world behaves as the same world in-process does. Listeners
    (:meth:`on_advance`) are called after every advance, in the driving thread.

    A host that waits for a streamed sample says so first (:meth:`await_stream`,
    the ``Clock`` role); a served stream sends one sample per such wait
    (:meth:`wait_for_stream_request`), so which samples the host sees, and at
    which virtual time, does not depend on how the threads are scheduled.
    """

    def __init__(self, start_s: float = 0.0) -> None:
        super().__init__(start_s)
        self._state = threading.Condition()
        self._advancing = threading.RLock()
        self._followers: dict[int, Follower] = {}
        self._timers: list[_Timer] = []
        self._listeners: list[Callable[[], None]] = []
        #: How often the host has waited for a streamed sample (:meth:`await_stream`).
        self._stream_waits = 0

    def await_stream(self) -> None:
        """The host is about to wait for the next streamed sample: a served stream may
        send it (advancing the time to it)."""
        with self._state:
            self._stream_waits += 1
            self._state.notify_all()

    def stream_waits(self) -> int:
        """How many waits for a streamed sample the host has announced so far."""
        with self._state:
            return self._stream_waits

    def wait_for_stream_request(self, answered: int, timeout_s: float) -> bool:
        """In a served stream: whether the host has announced more than ``answered`` waits,
        waiting up to ``timeout_s`` of wall time for one."""
        with self._state:
            return self._state.wait_for(lambda: self._stream_waits > answered, timeout_s)

    def _set_now(self, time_s: float) -> None:
        with self._lock:
            self._now_s = max(self._now_s, time_s)

    def on_advance(self, listener: Callable[[], None]) -> Callable[[], None]:
        """Call ``listener()`` after every advance; returns the function that removes it."""
        self._listeners.append(listener)
        return lambda: self._listeners.remove(listener)

    def call_every(self, period_s: float, callback: Callable[[], None]) -> Callable[[], None]:
        """Call ``callback()`` every ``period_s`` of virtual time; returns the cancel function."""
        timer = _Timer(self.now() + period_s, period_s, callback)
        with self._state:
            self._timers.append(timer)

        def cancel() -> None:
            with self._state:
                timer.cancelled = True
                if timer in self._timers:
                    self._timers.remove(timer)

        return cancel

    def start_follower(self, target: Callable[[], None], name: str) -> Follower:
        """Run ``target`` in a new follower thread until it first blocks; returns its handle."""
        follower = Follower(name)

        def run() -> None:
            with self._state:
                self._followers[threading.get_ident()] = follower
            try:
                target()
            except BaseException as error:  # kept for the thread that stops it
                follower.error = error
            finally:
                with self._state:
                    self._followers.pop(threading.get_ident(), None)
                    follower.running = False
                    follower.done = True
                    self._state.notify_all()

        threading.Thread(target=run, name=name, daemon=True).start()
        self._wait_blocked(follower)
        return follower

    def _wait_blocked(self, follower: Follower) -> None:
        with self._state:
            self._state.wait_for(lambda: not follower.running)

    def wait_for_resume(self) -> None:
        """In a follower: block until a driving thread calls :meth:`resume`."""
        follower = self._followers[threading.get_ident()]
        if follower.released:
            return
        with self._state:
            follower.wake_s = None
            follower.running = False
            self._state.notify_all()
            self._state.wait_for(lambda: follower.running)

    def release(self, follower: Follower, timeout_s: float = 5.0) -> None:
        """Let a follower run freely from now on (its waits return at once) until it ends."""
        with self._state:
            follower.released = True
            follower.running = True
            self._state.notify_all()
            self._state.wait_for(lambda: follower.done, timeout_s)

    def resume(self, follower: Follower) -> None:
        """Let a follower that waits for a resume run now, until it blocks again."""
        with self._state:
            if follower.done or follower.running or follower.wake_s is not None:
                return
            follower.running = True
            self._state.notify_all()
        self._wait_blocked(follower)

    def wake(self, follower: Follower) -> None:
        """Let a follower run now, whether it sleeps or waits for a resume, until it blocks
        again (its ``sleep`` ends early, at the current time: a feed hold, an abort)."""
        with self._advancing:
            with self._state:
                if follower.done or follower.running:
                    return
                follower.wake_s = None
                follower.running = True
                self._state.notify_all()
            self._wait_blocked(follower)

    def sleep(self, seconds: float) -> None:
        follower = self._followers.get(threading.get_ident())
        if follower is None:
            self._advance(max(0.0, seconds))
            return
        if seconds <= 0.0 or follower.released:
            return
        with self._state:
            follower.wake_s = self.now() + seconds
            follower.running = False
            self._state.notify_all()
            self._state.wait_for(lambda: follower.running)

    def _next_due(self, until_s: float) -> Follower | _Timer | None:
        with self._state:
            due: list[tuple[float, Follower | _Timer]] = [
                (f.wake_s, f)
                for f in self._followers.values()
                if f.wake_s is not None and f.wake_s <= until_s
            ]
            due += [(t.next_s, t) for t in self._timers if t.next_s <= until_s]
        return min(due, key=lambda entry: entry[0])[1] if due else None

    def _advance(self, seconds: float) -> None:
        with self._advancing:
            until_s = self.now() + seconds
            while (due := self._next_due(until_s)) is not None:
                if isinstance(due, Follower):
                    assert due.wake_s is not None
                    self._set_now(due.wake_s)
                    with self._state:
                        due.wake_s = None
                        due.running = True
                        self._state.notify_all()
                    self._wait_blocked(due)
                else:
                    self._set_now(due.next_s)
                    due.next_s += due.period_s
                    due.callback()
            self._set_now(until_s)
            for listener in list(self._listeners):
                listener()
