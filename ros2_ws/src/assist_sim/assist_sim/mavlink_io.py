"""pymavlink helpers shared by the sim's MAVLink vehicle and the bridge (no rclpy)."""
from __future__ import annotations

import os
from typing import Callable

os.environ.setdefault('MAVLINK20', '1')
from pymavlink import mavutil  # noqa: E402

mavlink = mavutil.mavlink


def next_message(conn, on_truncated: Callable[[], None] | None = None):
    """Next parsed message from `conn` or None; on UDP a datagram's leftover partial frame is dropped.

    MAVLink over UDP carries whole frames per datagram, so bytes left after a datagram are a
    truncated frame; keeping them (as a serial parser must) would swallow the next good frame.
    """
    if not isinstance(conn, mavutil.mavudp):
        return conn.recv_msg()
    mav = conn.mav
    while True:
        msg = mav.parse_char(b'')
        if msg is not None:
            return msg
        if mav.buf_len() > 0:
            mav.buf, mav.buf_index, mav.expected_length = bytearray(), 0, mavlink.HEADER_LEN_V1 + 2
            if on_truncated is not None:
                on_truncated()
        data = conn.recv()
        if not data:
            return None
        msg = mav.parse_char(data)
        if msg is not None:
            return msg
