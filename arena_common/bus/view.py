"""A part of an open bus session that closes alone: what one vehicle of a process serving several declares.

A :class:`BusView` shares its parent's Zenoh session; the publishers, subscriptions, queryables and tokens
declared through it are its own, undeclared by :meth:`BusView.close` while the session and everything else
on it go on.  Its losses count in its parent's :meth:`~arena_common.bus.session.Bus.lost`, also after it
closed.  ``with BusView(bus) as part: Gateway(cfg, name, part)`` is how a vehicle of
:class:`~arena_common.gateway.host.GatewayHost` restarts without touching the others.
"""

from __future__ import annotations

from arena_common.bus.session import Bus

__all__ = ["BusView"]


class BusView(Bus):
    """Endpoints on ``parent``'s session that close together, without closing the session."""

    def __init__(self, parent: Bus) -> None:
        super().__init__(parent.session)
        self.opened = parent.opened  # discovery: as old as the session, not as the view
        self._parent: Bus | None = parent
        with parent._lock:
            parent._views.append(self)
            parent._closables.append(self)  # closed with its parent at the latest

    def close(self) -> None:
        """Undeclare what was declared through this view; the session stays open.  Its losses so far stay
        counted by the parent."""
        parent, self._parent = self._parent, None
        if parent is None:
            return
        self._undeclare_all()
        lost = self.lost()
        with parent._lock:
            if self in parent._views:
                parent._views.remove(self)
            if self in parent._closables:
                parent._closables.remove(self)
            for key, n in lost.items():
                parent._retired_lost[key] = max(parent._retired_lost.get(key, 0), n)
