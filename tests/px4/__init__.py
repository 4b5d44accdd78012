"""The real-PX4 tier: the arena against PX4 v1.16 SITL (``make test-px4``)."""
