"""OpenIGTLink output for 3D Slicer (docs/design.md section 7): the tip frame and the bending plane.

An OpenIGTLink server (pyigtl) on 127.0.0.1:18944 by default sends, for every frame with a
valid estimate, two TRANSFORM messages in the world frame {W} (mm):

- ``CathTip``: the tip frame {4}, ``T_w_4 = [R_w_b R_b_4, o_b_w + R_w_b o_4_b]`` from
  :meth:`models.catheter.Catheter.frames` at the estimated delta_L;
- ``BendingPlane``: the base origin with ``R_w_b Rz(delta_1)``, whose x axis is the bending
  direction and whose xz plane is the bending plane of the proximal segment.

3D Slicer connects as a client (OpenIGTLinkIF module) and shows them as linear transforms.
Failures never stop the loop: a port in use is one clear OSError when the sink is created;
frames without a connected client, or with an invalid estimate, are skipped and counted; a
client that disconnects is dropped and the next one is served (one client at a time).

pyigtl's own server installs SIGINT/SIGTERM handlers and prints tracebacks when a client
goes away; the small subclass here binds and serves without either, so the live loop keeps
its clean Ctrl-C shutdown.
"""

from __future__ import annotations

import select
import socket
import socketserver
import threading
import time
from collections.abc import Callable

import numpy as np
import pyigtl
from pyigtl.comm import OpenIGTLinkBase

from models.catheter import Catheter
from models.rotations import rot_z
from tracker.types import Estimate

Array = np.ndarray

DEFAULT_IGTL_PORT = 18944
TIP_DEVICE = "CathTip"
PLANE_DEVICE = "BendingPlane"
_DEVICE_NAME_BYTES = 20  # OpenIGTLink header field


def homogeneous(R: Array, t: Array) -> Array:
    """The 4x4 transform [[R, t], [0, 1]]."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def tip_transform_w(
    catheter: Catheter, q: Array, delta_L_rad: float, R_w_b: Array, o_b_w_mm: Array
) -> Array:
    """T_w_4: the tip frame {4} in the world frame, shape (4, 4), mm.

    Parameters
    ----------
    catheter : Catheter
    q : array, shape (3,)
        Joint values (q_r [rad], q_p [mm], q_d [mm]).
    delta_L_rad : float
        Torsional loss, rad.
    R_w_b, o_b_w_mm : arrays (3, 3), (3,)
        Registered base pose in {W}.
    """
    frames = catheter.frames(np.asarray(q, dtype=float), float(delta_L_rad))
    R_w_b = np.asarray(R_w_b, dtype=float)
    return homogeneous(R_w_b @ frames.R_b_4, np.asarray(o_b_w_mm, float) + R_w_b @ frames.o_4_b)


def bending_plane_transform_w(delta_1_rad: float, R_w_b: Array, o_b_w_mm: Array) -> Array:
    """The bending-plane frame in {W}: origin at the base, rotation R_w_b Rz(delta_1), (4, 4)."""
    return homogeneous(np.asarray(R_w_b, float) @ rot_z(float(delta_1_rad)), o_b_w_mm)


def _closed_by_peer(sock: socket.socket) -> bool:
    readable, _, _ = select.select([sock], [], [], 0)
    if not readable:
        return False
    try:
        return sock.recv(1, socket.MSG_PEEK) == b""
    except (BlockingIOError, TimeoutError):
        return False
    except OSError:
        return True


class _Handler(socketserver.BaseRequestHandler):
    """Serves one client: reads what it sends (and drops it), sends what is queued."""

    def handle(self) -> None:
        server = self.server
        sock = self.request
        sock.settimeout(0.01)
        with server.lock_outgoing_messages:
            server.outgoing_messages.clear()  # nothing stale for a new client
        server._connected = True
        server.clients += 1
        try:
            while not server.communication_thread_stop_requested:
                while server._receive_message_from_socket(sock):
                    pass
                if _closed_by_peer(sock):
                    break
                while server._send_queued_message_from_socket(sock):
                    pass
        except (OSError, ValueError) as exc:  # connection reset, broken pipe, bad header
            server.last_error = exc
        finally:
            server._connected = False


class _Server(pyigtl.OpenIGTLinkServer):
    """pyigtl's server without its signal handlers and console thread."""

    allow_reuse_address = True

    def __init__(self, host: str, port: int) -> None:  # noqa: D107 - bypasses the base init
        OpenIGTLinkBase.__init__(self)
        self.host = host
        self.clients = 0
        self.last_error: Exception | None = None
        socketserver.TCPServer.__init__(self, (host, port), _Handler)
        self.port = self.server_address[1]
        self._thread = threading.Thread(
            target=self.serve_forever,
            kwargs={"poll_interval": 0.05},
            name=f"openigtlink-{self.port}",
            daemon=True,
        )
        self._thread.start()

    def queue_size(self) -> int:
        with self.lock_outgoing_messages:
            return len(self.outgoing_messages)

    def close(self, timeout_s: float = 2.0) -> None:
        self.communication_thread_stop_requested = True
        self.shutdown()
        self.server_close()
        self._thread.join(timeout_s)


class IgtlSink:
    """Live-loop sink: TRANSFORM messages of the tip frame and of the bending plane.

    Parameters
    ----------
    catheter : Catheter
    R_w_b, o_b_w_mm : arrays (3, 3), (3,)
        Registered base pose in {W}.
    host, port : str, int
        Where to listen (loopback by default; port 0 picks a free port, see ``port``).
    tip_name, plane_name : str
        Device names (at most 20 bytes): the transform node names in 3D Slicer.
    report : callable, optional
        Called once per kind of problem (no client yet, client lost).

    Raises
    ------
    OSError
        When the port cannot be bound (in use), naming it.
    """

    name = "openigtlink"

    def __init__(
        self,
        catheter: Catheter,
        R_w_b: Array,
        o_b_w_mm: Array,
        *,
        host: str = "127.0.0.1",
        port: int = DEFAULT_IGTL_PORT,
        tip_name: str = TIP_DEVICE,
        plane_name: str = PLANE_DEVICE,
        report: Callable[[str], None] | None = None,
    ) -> None:
        for device in (tip_name, plane_name):
            if not 0 < len(device.encode("utf8")) <= _DEVICE_NAME_BYTES:
                raise ValueError(f"OpenIGTLink device name {device!r} must have 1 to 20 bytes")
        self.catheter = catheter
        self.R_w_b = np.asarray(R_w_b, dtype=float)
        self.o_b_w_mm = np.asarray(o_b_w_mm, dtype=float)
        self.tip_name, self.plane_name = tip_name, plane_name
        self.report = report
        self.sent = 0  # frames whose two transforms were queued
        self.skipped_no_client = 0
        self.skipped_invalid = 0
        self._warned: set[str] = set()
        self._clients_seen = 0
        try:
            self._server: _Server | None = _Server(host, port)
        except OSError as exc:
            raise OSError(
                f"cannot serve OpenIGTLink on {host}:{port}: {exc.strerror or exc}"
                " (is another tracker or server using the port?)"
            ) from exc
        self.host, self.port = host, self._server.port

    @property
    def connected(self) -> bool:
        return self._server is not None and self._server.is_connected()

    def wait_for_client(self, timeout_s: float) -> bool:
        """Wait (polling every 10 ms) until a client is connected; whether one is."""
        deadline = time.monotonic() + timeout_s
        while not self.connected and time.monotonic() < deadline:
            time.sleep(0.01)
        return self.connected

    def _warn(self, key: str, message: str) -> None:
        if key not in self._warned and self.report is not None:
            self._warned.add(key)
            self.report(message)

    def transforms(self, q: Array, delta_L_rad: float, q_r_rad: float | None = None):
        """(T_w_4, T_w_plane) for joint values q and torsional loss delta_L."""
        q = np.asarray(q, dtype=float)
        q_r = float(q[0]) if q_r_rad is None else float(q_r_rad)
        T_tip = tip_transform_w(self.catheter, q, delta_L_rad, self.R_w_b, self.o_b_w_mm)
        T_plane = bending_plane_transform_w(q_r + delta_L_rad, self.R_w_b, self.o_b_w_mm)
        return T_tip, T_plane

    def handle(
        self, frame, observation, estimate: Estimate, latency_s: float, status: int = 0
    ) -> None:
        server = self._server
        if server is None:
            return
        if not estimate.valid:
            self.skipped_invalid += 1
            return
        if not server.is_connected():
            self.skipped_no_client += 1
            lost = self._clients_seen > 0
            self._warn(
                "lost" if lost else "none",
                f"OpenIGTLink client {'disconnected' if lost else 'not connected yet'} on"
                f" {self.host}:{self.port}; transforms resume when one connects",
            )
            return
        self._clients_seen = server.clients
        T_tip, T_plane = self.transforms(frame.q, estimate.delta_L_rad, estimate.q_r_rad)
        stamp = time.time()
        for device, T in ((self.tip_name, T_tip), (self.plane_name, T_plane)):
            message = pyigtl.TransformMessage(T, timestamp=stamp, device_name=device)
            server.send_message(message, wait=False)
        self.sent += 1

    def close(self, flush_timeout_s: float = 1.0) -> None:
        """Send what is queued (bounded wait) and stop the server."""
        server, self._server = self._server, None
        if server is None:
            return
        deadline = time.monotonic() + flush_timeout_s
        while server.is_connected() and server.queue_size() and time.monotonic() < deadline:
            time.sleep(0.005)
        server.close()

    def __enter__(self) -> IgtlSink:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
