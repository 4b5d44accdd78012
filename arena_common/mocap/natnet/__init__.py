"""NatNet, the streaming protocol of OptiTrack Motive: decode and encode its messages, without any I/O.

Every NatNet datagram is ``u16 message id, u16 payload length, payload`` (little-endian). Use
:func:`split_packet` to get the id and payload of a received datagram, then the ``decode_*`` function of that
message; the ``encode_*`` functions return whole datagrams, ready to send.

Frames and model definitions depend on the server's NatNet version (taken from its SERVERINFO): pass it as a
:class:`Version`. Versions 2.0 through 4.x are understood (the layouts of 2.5, 2.7, 2.9 and 3.0 are checked
against real Motive captures, 4.0 and 4.1 follow the protocol description).

The decoders never raise anything but :class:`NatNetError`, whatever the input; its message names the message,
the section and the byte offset (counted from the start of the payload) where decoding failed.

:func:`decode_frame` is on the hot path (120–360 Hz): by default it decodes the rigid bodies and the frame's
timing and only counts and steps over the other sections; ``full=True`` also keeps markers, skeletons, assets,
force plates and devices, which is what :func:`encode_frame` needs to reproduce a frame byte for byte.

Modules: :mod:`._common` (ids, versions, layouts), :mod:`.packets` (handshake, text, echo), :mod:`.models`
(model definitions), :mod:`.frames` (frames of data).
"""

from __future__ import annotations

from arena_common.mocap.natnet._common import (
    COMMAND_PORT,
    DATA_PORT,
    MULTICAST_GROUP,
    MessageId,
    NatNetError,
    Quat,
    Vec3,
    Version,
)
from arena_common.mocap.natnet.frames import (
    Analog,
    Asset,
    Frame,
    LabeledMarker,
    MarkerSet,
    RigidBody,
    RigidBodyMarker,
    Skeleton,
    decode_frame,
    encode_frame,
)
from arena_common.mocap.natnet.models import (
    AssetDef,
    CameraDef,
    DataSetDef,
    DeviceDef,
    ForcePlateDef,
    MarkerDef,
    MarkerSetDef,
    ModelDefs,
    RigidBodyDef,
    SkeletonDef,
    decode_model_defs,
    encode_model_defs,
)
from arena_common.mocap.natnet.packets import (
    ConnectRequest,
    Response,
    ServerInfo,
    decode_connect,
    decode_echo_request,
    decode_echo_response,
    decode_message_string,
    decode_request_text,
    decode_response,
    decode_server_info,
    encode_connect,
    encode_disconnect,
    encode_discovery,
    encode_echo_request,
    encode_echo_response,
    encode_keepalive,
    encode_message_string,
    encode_packet,
    encode_request,
    encode_request_frame,
    encode_request_model_defs,
    encode_response,
    encode_server_info,
    encode_unrecognized,
    split_packet,
)

__all__ = [
    "COMMAND_PORT",
    "DATA_PORT",
    "MULTICAST_GROUP",
    "Analog",
    "Asset",
    "AssetDef",
    "CameraDef",
    "ConnectRequest",
    "DataSetDef",
    "DeviceDef",
    "ForcePlateDef",
    "Frame",
    "LabeledMarker",
    "MarkerDef",
    "MarkerSet",
    "MarkerSetDef",
    "MessageId",
    "ModelDefs",
    "NatNetError",
    "Quat",
    "Response",
    "RigidBody",
    "RigidBodyDef",
    "RigidBodyMarker",
    "ServerInfo",
    "Skeleton",
    "SkeletonDef",
    "Vec3",
    "Version",
    "decode_connect",
    "decode_echo_request",
    "decode_echo_response",
    "decode_frame",
    "decode_message_string",
    "decode_model_defs",
    "decode_request_text",
    "decode_response",
    "decode_server_info",
    "encode_connect",
    "encode_disconnect",
    "encode_discovery",
    "encode_echo_request",
    "encode_echo_response",
    "encode_frame",
    "encode_keepalive",
    "encode_message_string",
    "encode_model_defs",
    "encode_packet",
    "encode_request",
    "encode_request_frame",
    "encode_request_model_defs",
    "encode_response",
    "encode_server_info",
    "encode_unrecognized",
    "split_packet",
]
