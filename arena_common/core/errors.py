"""The arena's exception hierarchy: one small typed tree, every message names what was wrong and where."""

from __future__ import annotations


class ArenaError(Exception):
    """Base of every error the arena raises on purpose."""


class InvalidName(ArenaError, ValueError):
    """A vehicle, host, service or message name that would break a key expression."""


class ConfigError(ArenaError, ValueError):
    """A configuration file that is missing, unreadable or wrong; the message names file and field."""


class MissingExtra(ArenaError, ImportError):
    """An optional extra this needs is not installed; the message names it and its ``pip install`` line."""


class PayloadError(ArenaError, ValueError):
    """A payload that does not decode to its type: names the key, the type and the field."""

    def __init__(self, message: str, *, key: str = "", type_name: str = "", field: str = "") -> None:
        self.key = key
        self.type_name = type_name
        self.field = field
        where = " ".join(
            p
            for p in (
                f"key={key}" if key else "",
                f"type={type_name}" if type_name else "",
                f"field={field}" if field else "",
            )
            if p
        )
        super().__init__(f"{message} ({where})" if where else message)


class BusError(ArenaError):
    """The Zenoh bus could not be opened or a request could not be made."""


class CommandError(ArenaError):
    """A command to a vehicle did not succeed. Subclasses say why."""

    def __init__(self, message: str, *, result: str = "", drone: str = "") -> None:
        self.result = result
        self.drone = drone
        super().__init__(message)


class CommandRejected(CommandError):
    """The autopilot answered, and its answer was not ACCEPTED (DENIED, TEMPORARILY_REJECTED…)."""


class CommandTimeout(CommandError):
    """No answer from the gateway or the autopilot in time, after retries."""


class SafetyRefused(CommandError):
    """The gateway refused the command or setpoint under the arena's safety rules."""


class NotPermitted(CommandError):
    """On a secured arena, this host is no ``command_hosts`` entry: the router drops its commands."""


class VehicleNotPresent(CommandError):
    """No gateway for that vehicle is alive on the bus."""


class GatewayError(ArenaError, ValueError):
    """A gateway part configured with a value it cannot use (an origin out of range, an unknown message)."""


class WaitTimeout(ArenaError, TimeoutError):
    """A bounded wait ran out before its condition held; ``what`` names the condition."""

    def __init__(self, message: str, *, what: str = "", timeout: float = 0.0) -> None:
        self.what = what
        self.timeout = timeout
        super().__init__(message)
