"""What the online loop's tests (``test_live.py``, ``test_live_real_time.py``) share: a
noisy simulated session, and a simulated robot controller on loopback UDP (joint datagrams
out, estimate datagrams in)."""

from __future__ import annotations

import socket

import pytest

from replay.simulation.sources import session_joints, simulated_session
from tracker.io.datagrams import decode_estimate, encode_joints
from tracker.reconstruction import Reconstructor

LOOPBACK = "127.0.0.1"
JOINT_RATE_HZ = 1000


@pytest.fixture(scope="module")
def noisy_session():
    return simulated_session(duration_s=6.0, frame_rate_hz=20.0, noise=0.3, seed=1)


def reconstructor_of(session):
    scene = session.scene
    return Reconstructor(scene.catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm)


class Controller:
    """The robot controller's side: joint datagrams out, estimate datagrams in."""

    def __init__(self):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        self.sock.bind((LOOPBACK, 0))
        self.sock.setblocking(False)
        self.sequence = 0
        self.next_sample = 0  # index of the next joint sample, at k / JOINT_RATE_HZ
        self.estimates = []

    @property
    def address(self):
        return self.sock.getsockname()

    def send_joints_until(self, time_s, to):
        """Joint samples up to ``time_s`` (s, simulated), in one burst."""
        while self.next_sample / JOINT_RATE_HZ <= time_s + 1e-9:
            t = self.next_sample / JOINT_RATE_HZ
            self.sock.sendto(encode_joints(self.sequence, t, *session_joints(t)), to)
            self.sequence += 1
            self.next_sample += 1

    def receive_estimates(self):
        while True:
            try:
                self.estimates.append(decode_estimate(self.sock.recv(256)))
            except BlockingIOError:
                return

    def close(self):
        self.sock.close()


@pytest.fixture
def controller():
    c = Controller()
    yield c
    c.close()
