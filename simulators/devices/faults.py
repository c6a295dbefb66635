"""Run-time switchable faults of one simulated device.

Every device server owns a :class:`Faults` (``device.faults``). Tests and the demo flip its fields from
any thread while the device runs; the device consults them on every answer or transmission. What a
fault means on the wire depends on the protocol and is documented with each device; the client-visible
effect is always one a real device can produce (timeout, late answer, integrity error, garbage, a value
that stops moving or leaves its range). Disconnecting clients happens once, so it is a device method
(``disconnect_clients()``), not a flag here.
"""

from __future__ import annotations

import math
import random
import threading
from collections import Counter
from collections.abc import Mapping


class Faults:
    """Faults of one device.

    Reply faults (the device's answers, or its periodic frames for a CAN module):

    - ``drop_replies``: the device stays silent; a client times out.
    - ``reply_delay_s``: wall seconds added before every answer (late answers).
    - ``corrupt_replies``: the frame's integrity check fails where the protocol has one (bad CRC on
      Modbus RTU, bad checksum on DCON, a bad protocol id on Modbus TCP, a malformed slcan line).
    - ``garbage_replies``: every answer is replaced by random bytes of the same length.

    Value faults (per channel, engineering units, applied before encoding):

    - :meth:`freeze`: the channel sticks at the last value the device reported.
    - :meth:`force`: the channel reads a fixed value, e.g. one beyond the encoding's range.

    ``counts`` tells how many answers each reply fault has affected, so a test can check that the fault
    it set up really fired.
    """

    def __init__(self, *, seed: int = 0) -> None:
        self.drop_replies = False
        self.reply_delay_s = 0.0
        self.corrupt_replies = False
        self.garbage_replies = False
        self.counts: Counter[str] = Counter()
        self._lock = threading.Lock()
        self._overrides: dict[str, float | None] = {}
        self._last: dict[str, float] = {}
        self._random = random.Random(seed)  # seeded: a failing test shows the same garbage again

    def freeze(self, channel: str) -> None:
        """Stick ``channel`` at the last value the device reported (or at its next value if none yet)."""
        with self._lock:
            self._overrides[channel] = self._last.get(channel)

    def force(self, channel: str, value: float) -> None:
        """Make ``channel`` read ``value`` (engineering units) until released."""
        if math.isnan(value):
            raise ValueError(f"force() needs a number, not NaN, for channel {channel!r}")
        with self._lock:
            self._overrides[channel] = float(value)

    def release(self, channel: str | None = None) -> None:
        """Let ``channel`` (or every channel when ``None``) follow the machine again."""
        with self._lock:
            if channel is None:
                self._overrides.clear()
            else:
                self._overrides.pop(channel, None)

    def clear(self) -> None:
        """Switch every fault off (the counts stay)."""
        self.drop_replies = False
        self.reply_delay_s = 0.0
        self.corrupt_replies = False
        self.garbage_replies = False
        self.release()

    # -- used by the devices ----------------------------------------------------------------------------
    def apply(self, values: Mapping[str, float]) -> dict[str, float]:
        """The machine's ``values`` with the value faults applied (remembers what was reported)."""
        with self._lock:
            out = dict(values)
            for channel, value in self._overrides.items():
                if value is None:  # frozen before anything was reported: stick at this value
                    value = out.get(channel, math.nan)
                    self._overrides[channel] = value
                out[channel] = value
            self._last = out
            return out

    def garbage(self, n_bytes: int) -> bytes:
        """``n_bytes`` random bytes."""
        with self._lock:
            return bytes(self._random.randrange(256) for _ in range(n_bytes))

    def note(self, fault: str) -> None:
        """Count one answer affected by ``fault``."""
        with self._lock:
            self.counts[fault] += 1
