"""ODOMETRY frames packed without pymavlink objects are byte for byte pymavlink's."""

from __future__ import annotations

import math
import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import all as mavlink2

from arena_common.mavlink import px4
from arena_common.mavlink.fastframe import ODOMETRY, odometry_payload

finite = st.floats(-1e4, 1e4, allow_nan=False, width=32)
unit = st.floats(-1.0, 1.0, allow_nan=False)


@settings(max_examples=300, deadline=None)
@given(
    usec=st.integers(0, 2**63 - 1),
    p=st.tuples(finite, finite, finite),
    q=st.tuples(unit, unit, unit, unit).filter(lambda q: sum(c * c for c in q) > 0.01),
    v=st.none() | st.tuples(finite, finite, finite),
    rc=st.integers(0, 1000),
    seq=st.integers(0, 255),
    system=st.integers(1, 255),
    component=st.integers(0, 255),
    frame_id=st.sampled_from([px4.MAV_FRAME_LOCAL_NED, px4.MAV_FRAME_LOCAL_FRD]),
)
def test_odometry_frames_equal_pymavlinks(
    usec: int,
    p: tuple[float, float, float],
    q: tuple[float, float, float, float],
    v: tuple[float, float, float] | None,
    rc: int,
    seq: int,
    system: int,
    component: int,
    frame_id: int,
) -> None:
    args = px4.odometry_args(usec, p, q, v, reset_counter=rc, frame_id=frame_id, angular_velocity_frd=v)
    mav = mavlink2.MAVLink(None, srcSystem=system, srcComponent=component)
    mav.seq = seq
    reference = mav.odometry_encode(**args).pack(mav)
    assert ODOMETRY.frame(odometry_payload(args), seq, system, component) == reference
    # And pymavlink reads it back as the same values.
    back = mavlink2.MAVLink(None).decode(bytearray(reference))
    assert back.time_usec == usec and back.reset_counter == rc & 0xFF


def test_a_payload_of_zeros_keeps_one_byte_and_a_value_beyond_its_type_raises() -> None:
    zeros = bytes(ODOMETRY.payload.size)
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    msg = mavlink2.MAVLink_odometry_message(
        *([0] * 3), 0.0, 0.0, 0.0, [0.0] * 4, *([0.0] * 6), [0.0] * 21, [0.0] * 21, 0, 0, 0
    )
    assert ODOMETRY.frame(zeros, 0, 1, 1) == msg.pack(mav)
    args = px4.odometry_args(0, (1e39, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0))
    with pytest.raises((struct.error, OverflowError)):
        odometry_payload(args)
    assert math.isnan(
        struct.unpack_from("<f", odometry_payload(px4.odometry_args(0, (0, 0, 0), (1, 0, 0, 0))), 40)[0]
    )
