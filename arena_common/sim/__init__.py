"""The simulated world — only the simulator services (``services.sim_*``) import it: a PX4-like
multicopter over real MAVLink (:mod:`.autopilot` and its parts), its physics (:mod:`.physics`), and a
Motive emulator over real NatNet (:mod:`.natnet_server` and its parts)."""
