"""What every CAN node of the project keeps of the messages it receives, written
once: per message the counts, the intervals and the last accepted values
(``RxStats``), and the wait on a condition over them (``ReceivingNode``).

Used by ``can_dbc.peer.CanPeer`` (the contract's messages, either side) and
``tcu_stub.can_tcu.MappedPeer`` (a vehicle matrix's messages, the TCU's side).
A node holds its ``RxStats`` under its own lock, notifies its ``_changed``
condition (built on that lock) after every received frame, and reads them
through the methods below while holding the lock."""

import threading
import time

from . import codec

#: at most this many queued frames discarded per bus at a node's start (a bus
#: busier than the drain would never end)
DRAIN_MAX_FRAMES = 100_000


class RxStats:
    """Reception of one message: counts, intervals, the last accepted values."""

    __slots__ = ("received", "accepted", "rejected", "first_t", "last_t", "max_interval_s", "last",
                 "last_t_any", "rejects_in_row", "last_reject", "state")

    def __init__(self, state=None):
        self.received = 0
        self.accepted = 0
        self.rejected = {r: 0 for r in codec.REJECTS}
        self.first_t = None           # receive time of the first accepted frame
        self.last_t = None            # ... of the last one
        self.max_interval_s = 0.0
        self.last = None              # decoded values of the last accepted frame
        self.last_t_any = None        # receive time of the last frame, accepted or not
        self.rejects_in_row = 0       # frames rejected since the last accepted one
        self.last_reject = None       # why the last of them was (bad_length, bad_crc, bad_counter)
        self.state = state            # a codec's receive state (the last counter), if it keeps one

    def frame(self, t, status, values):
        """One frame received at monotonic time ``t``: ``status`` codec.OK
        (``values`` its decoded signals) or the reason it was rejected."""
        self.received += 1
        self.last_t_any = t
        if status == codec.OK:
            self.rejects_in_row = 0
            self.accepted += 1
            if self.last_t is not None:
                self.max_interval_s = max(self.max_interval_s, t - self.last_t)
            else:
                self.first_t = t
            self.last_t = t
            self.last = values
        else:
            self.rejects_in_row += 1
            self.rejected[status] += 1
            self.last_reject = status

    def snapshot(self):
        """(last values or None, their receive time or None, frames rejected
        since, why the last of those was or None)."""
        return self.last, self.last_t, self.rejects_in_row, self.last_reject

    def counts(self):
        """{received, accepted, bad_length, bad_crc, bad_counter}."""
        return {"received": self.received, "accepted": self.accepted, **self.rejected}

    def figures(self):
        """The counts, the mean and largest interval between accepted frames
        (ms; None before the second) and the last values, JSON-ready."""
        mean = None
        if self.accepted >= 2 and self.last_t is not None:
            mean = (self.last_t - self.first_t) / (self.accepted - 1) * 1000.0
        return {
            "received": self.received,
            "accepted": self.accepted,
            "rejected": dict(self.rejected),
            "mean_interval_ms": mean,
            "max_interval_ms": self.max_interval_s * 1000.0 if self.accepted >= 2 else None,
            "last": dict(self.last) if self.last is not None else None,
        }


class ReceivingNode:
    """The threads and the receiving side of a node: ``_rx_stats`` holds an
    RxStats per received message under ``_lock``; ``_changed`` is a
    threading.Condition the receive threads notify after every frame, ``_stop``
    a threading.Event they watch, ``_threads`` the list of them, ``started_at``
    and ``stopped_at`` monotonic times (None before)."""

    #: frames the buses had queued when the node started, discarded (``_drain``)
    drained_at_start = 0

    def _drain(self, *buses):
        """Discards the frames ``buses`` queued before the node starts (a bus opened
        long before, whose socket may have overflowed and cut the counters): they
        are of another time, and a burst of them would be judged as traffic now.
        Counted in ``drained_at_start``; at most DRAIN_MAX_FRAMES a bus."""
        for bus in buses:
            n = 0
            try:
                while n < DRAIN_MAX_FRAMES and bus.recv(timeout=0.0) is not None:
                    n += 1
            except Exception:  # a bus error: the receive thread meets and counts it
                pass
            self.drained_at_start += n

    def _start_threads(self, threads):
        """Starts ``threads`` ((target, args, name) each) as daemons; notes the start."""
        self.started_at = time.monotonic()
        for target, args, name in threads:
            t = threading.Thread(target=target, args=args, name=name, daemon=True)
            t.start()
            self._threads.append(t)

    def _stop_threads(self):
        """Stops and joins the node's threads; notes the stop (the first one)."""
        self._stop.set()
        for t in self._threads:
            t.join(timeout=5.0)
        self._threads = []
        if self.stopped_at is None and self.started_at is not None:
            self.stopped_at = time.monotonic()

    def _frames(self, bus):
        """(monotonic receive time, message) of each frame ``bus`` receives until
        the node stops; a receive error ends it while stopping (the bus going
        down) and is retried otherwise."""
        while not self._stop.is_set():
            try:
                msg = bus.recv(timeout=0.05)
            except Exception:  # any bus error: retried, or the end while stopping
                if self._stop.is_set():
                    return
                time.sleep(0.01)
                continue
            if msg is not None:
                yield time.monotonic(), msg

    node = "TCU"          # who receives (a node's name in the DBC), for the errors

    def _rx_key(self, message):
        """The key of ``message`` in ``_rx_stats``."""
        return message

    def _stats_of(self, message):
        """The RxStats of a received message (the caller holds ``_lock``)."""
        key = self._rx_key(message)
        st = self._rx_stats.get(key)
        if st is None:
            raise ValueError(f"{key} is not a message the {self.node} receives")
        return st

    def rx_snapshot(self):
        """{message: (decoded values of the last accepted frame or None,
        monotonic time it was received or None, frames rejected since then,
        why the last of those was rejected or None)} for every received
        message, in one consistent copy. The value dicts are the node's own
        (never changed after they were stored): read them, do not modify them."""
        with self._lock:
            return {key: st.snapshot() for key, st in self._rx_stats.items()}

    def last(self, message):
        """Decoded values of the last accepted frame of a received message (None before the first)."""
        with self._lock:
            st = self._stats_of(message)
            return dict(st.last) if st.last is not None else None

    def counts(self, message):
        """{received, accepted, bad_length, bad_crc, bad_counter} of a received message."""
        with self._lock:
            return self._stats_of(message).counts()

    def wait_for(self, predicate, timeout=5.0):
        """Waits until ``predicate(self)`` is true (checked after every received
        frame) or ``timeout`` seconds passed; returns the predicate's value."""
        deadline = time.monotonic() + timeout
        while True:
            ok = predicate(self)
            left = deadline - time.monotonic()
            if ok or left <= 0:
                return ok
            with self._changed:
                self._changed.wait(min(left, 0.05))
