"""A network link between two Linux network namespaces made of two TUN devices and a forwarder that delays
and drops packets as `tc netem` would (tests/test_netns_split.py, where the kernel has no netem; tests only).

Each namespace gets a point-to-point TUN interface (no packet information header); the forwarder, a thread of
the test process holding both devices' file descriptors, carries every IP packet from one to the other after
`delay_s` and drops each with probability `loss`, independently per packet and direction (netem's
`delay D loss P` on both ends). Both can change while the link runs. A device set down with `ip link` stops
its end as a pulled cable would: packets to it are dropped. Needs root (CAP_NET_ADMIN) and /dev/net/tun.
"""
from __future__ import annotations

import ctypes
import fcntl
import heapq
import os
import random
import select
import struct
import threading
import time

TUNSETIFF = 0x400454ca
IFF_TUN, IFF_NO_PI = 0x0001, 0x1000
CLONE_NEWNET = 0x40000000
MAX_PACKET = 65536


def _setns(fd: int) -> None:
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.setns(fd, CLONE_NEWNET) != 0:
        err = ctypes.get_errno()
        raise OSError(err, f'setns: {os.strerror(err)}')


def open_tun_in(netns: str, name: str) -> int:
    """A TUN device `name` created inside the named network namespace (/var/run/netns/<netns>); its fd.
    The device lives as long as the fd is open. The namespace switch happens on a short-lived thread, so
    no other thread of this process changes namespace."""
    result: dict = {}

    def create() -> None:
        here = os.open('/proc/thread-self/ns/net', os.O_RDONLY)
        target = os.open(f'/var/run/netns/{netns}', os.O_RDONLY)
        try:
            _setns(target)
            try:
                fd = os.open('/dev/net/tun', os.O_RDWR)
                fcntl.ioctl(fd, TUNSETIFF, struct.pack('16sH', name.encode(), IFF_TUN | IFF_NO_PI))
                result['fd'] = fd
            finally:
                _setns(here)
        except OSError as exc:
            result['error'] = exc
        finally:
            os.close(here)
            os.close(target)
    t = threading.Thread(target=create, name=f'tun-{name}')
    t.start()
    t.join()
    if 'error' in result:
        raise result['error']
    return result['fd']


class TunLink:
    """Two TUN fds joined by a forwarding thread with netem-like delay and loss; start() / close()."""

    def __init__(self, fd_a: int, fd_b: int, delay_s: float = 0.0, loss: float = 0.0, seed: int = 0) -> None:
        self.fds = (fd_a, fd_b)
        self.delay_s, self.loss = delay_s, loss
        self._rng = random.Random(seed)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name='tun-link', daemon=True)
        self.carried = self.dropped = self.undeliverable = 0

    def start(self) -> TunLink:
        """Start forwarding."""
        self._thread.start()
        return self

    def impair(self, delay_s: float, loss: float) -> None:
        """Set the one-way delay and the loss probability of both directions (packets in flight keep theirs)."""
        self.delay_s, self.loss = delay_s, loss

    def _run(self) -> None:
        poller = select.poll()
        for fd in self.fds:
            poller.register(fd, select.POLLIN)
        queue: list[tuple[float, int, int, bytes]] = []
        seq = 0
        while not self._stop.is_set():
            now = time.monotonic()
            while queue and queue[0][0] <= now:
                _, _, dst, pkt = heapq.heappop(queue)
                try:
                    os.write(dst, pkt)
                    self.carried += 1
                except OSError:             # that end is down (EIO): the packet is lost, as on a cut cable
                    self.undeliverable += 1
            timeout_ms = 50 if not queue else max(0, int((queue[0][0] - time.monotonic()) * 1000))
            for fd, _ in poller.poll(timeout_ms):
                try:
                    pkt = os.read(fd, MAX_PACKET)
                except OSError:
                    continue
                if self.loss and self._rng.random() < self.loss:
                    self.dropped += 1
                    continue
                dst = self.fds[1] if fd == self.fds[0] else self.fds[0]
                seq += 1
                heapq.heappush(queue, (time.monotonic() + self.delay_s, seq, dst, pkt))

    def close(self) -> None:
        """Stop forwarding and close both devices (they disappear)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(5)
        for fd in self.fds:
            os.close(fd)
