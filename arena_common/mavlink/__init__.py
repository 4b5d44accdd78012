"""MAVLink out: the link to one autopilot (:mod:`.link`, UDP/TCP/serial, frames split and checked),
MAVLink 2 signing (:mod:`.signing`), PX4's numbers and parameter encoding (:mod:`.px4`), the command and
parameter protocols (:mod:`.protocols`), and PX4's own parameter metadata over MAVLink FTP
(:mod:`.metadata`).  **Where a pose is sent**: :func:`.px4.odometry_args`, used by the gateway."""
