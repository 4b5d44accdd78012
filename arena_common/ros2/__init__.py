"""ROS 2 sees the arena natively: rmw_zenoh's protocol on the arena's own Zenoh router (docs/ros2.md).

- :mod:`~arena_common.ros2.names` — rmw_zenoh's key expressions, liveliness tokens, QoS strings, GIDs and
  attachments;
- :mod:`~arena_common.ros2.types` — message definitions, DDS names, RIHS01 hashes and CDR (``rosbags``);
- :mod:`~arena_common.ros2.frames` — arena NED/FRD ↔ ROS ENU/FLU (REP 103, REP 105);
- :mod:`~arena_common.ros2.messages` — arena payloads as ROS 2 messages, ROS 2 commands as the arena's;
- :mod:`~arena_common.ros2.topics` — the table of topics: name, type, QoS, arena key, conversion;
- :mod:`~arena_common.ros2.node` — a ROS 2 node on a Zenoh session, as rmw_zenoh_cpp makes one;
- :mod:`~arena_common.ros2.bridge` — the ``ros2`` service's work: topics out, goto / cmd_vel in;
- :mod:`~arena_common.ros2.export` — a recording as a ROS 2 MCAP (``ros2msg`` schemas, CDR messages).
"""
