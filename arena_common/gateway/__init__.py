"""The MAVLink gateway of one vehicle, one module per concern: the wiring and threads
(:mod:`.gateway`), the command queryable (:mod:`.commands`), the offboard setpoint stream and its safety
rules (:mod:`.setpoints`), and the parts (:mod:`.events`, :mod:`.state`, :mod:`.timesync`, :mod:`.origin`,
:mod:`.vision`, :mod:`.telemetry`)."""

from arena_common.gateway.gateway import Gateway, GatewayOptions

__all__ = ["Gateway", "GatewayOptions"]
