"""Geometry: Motive's frames to the arena's NED/FRD (:mod:`.frames`), quaternions, and the filters that
turn poses into velocities and decimate them (:mod:`.filters`)."""
