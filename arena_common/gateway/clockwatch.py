"""What the gateway says of its host's clock: whether pose times can be trusted (arming is refused while
they cannot), the state's flags, and a ``clock`` event whenever that changes (:class:`ClockWatch`)."""

from __future__ import annotations

import time
from typing import Any

from arena_common.core.config import ClockSpec
from arena_common.gateway.events import EventSink
from arena_common.runtime.clock import ClockStatus, ClockSync

__all__ = ["ClockWatch"]


class ClockWatch:
    """One gateway's view of its host's clock (``clock`` None: no clock is measured, nothing to say)."""

    def __init__(self, clock: ClockSync | None, spec: ClockSpec, events: EventSink) -> None:
        self.clock = clock
        self.spec = spec
        self.events = events
        self._said: tuple[str, bool] | None = None
        # The first exchanges take a few periods (and the bus may not know its routes yet).
        self._grace = time.monotonic() + 2.0 + 3 * spec.period

    def problem(self) -> str | None:
        """Why pose times cannot be trusted on this host (arming is refused), or None."""
        if self.clock is None:
            return None
        st = self.clock.status()
        if st.state == "no_reference" and not self.spec.require:
            return None
        return st.problem

    def flags(self) -> list[str]:
        """The state's clock flags (``clock_unknown``, ``clock_uncertain``, ``clock_offset``…)."""
        if self.clock is None:
            return []
        st: ClockStatus = self.clock.status()
        if st.state == "no_reference":
            return ["clock_unknown"] if self.spec.require else ["clock_unchecked"]
        flags = {"unknown": ["clock_unknown"], "uncertain": ["clock_uncertain"]}.get(st.state, [])
        return flags + (["clock_offset"] if st.warning else [])

    def check(self) -> None:
        """Emit a ``clock`` event whenever the clock's state or its offset warning changes."""
        if self.clock is None:
            return
        st = self.clock.status()
        if st.state in ("unknown", "no_reference") and time.monotonic() < self._grace:
            return
        problem = self.problem()
        said = (st.state, st.warning is not None)  # the figures change with every exchange
        if said == self._said:
            return
        first = self._said is None
        self._said = said
        est = st.estimate
        data: dict[str, Any] = {"state": st.state, "ref": st.ref, "host": self.clock.host}
        if est is not None:
            data.update(offset=est.offset, unc=est.unc)
        if problem is not None:
            self.events.emit("clock", f"{problem.removeprefix('clock: ')}: arming refused", 3, **data)
        elif st.warning is not None:
            self.events.emit("clock", st.warning.removeprefix("clock: "), 4, **data)
        elif st.state == "no_reference":
            self.events.emit(
                "clock",
                f"no mocap time reference answers on arena/sys/time: pose times are taken as the "
                f"clock of {self.clock.host} (clock.require is false)",
                5,
                **data,
            )
        elif not first and est is not None:
            self.events.emit(
                "clock",
                f"{self.clock.host} is within {self.spec.max_offset * 1e3:.1f} ms of the mocap "
                f"host's clock ({st.ref}): offset {est.offset * 1e3:+.2f} ± {est.unc * 1e3:.2f} ms",
                6,
                **data,
            )
