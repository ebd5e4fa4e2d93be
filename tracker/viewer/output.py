"""The rerun outputs of a command: an ``.rrd`` file, a viewer (connected to or spawned), a gRPC
server with rerun's web viewer next to it, or several at once, from the usual rerun flags.

:func:`add_rerun_args` adds the flags to a parser and :func:`open_rerun_output` opens what they
ask for on an explicit :class:`rerun.RecordingStream` (never the global one); a viewer that is
not running is reported once and skipped, and :class:`ViewerWatch` notices one that goes away.
:class:`WebViewer` hosts rerun's web viewer over HTTP on the address asked for (rerun's own
``serve_web_viewer`` listens on every interface): it runs the ``rerun`` command line.
"""

from __future__ import annotations

import atexit
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import timedelta
from pathlib import Path
from urllib.parse import quote, urlsplit

import rerun as rr
import rerun.blueprint as rrb
import rerun_cli

DEFAULT_VIEWER_PORT = 9876
DEFAULT_VIEWER_URL = f"rerun+http://127.0.0.1:{DEFAULT_VIEWER_PORT}/proxy"
DEFAULT_WEB_VIEWER_PORT = 9090
LOOPBACK = "127.0.0.1"
EVERY_INTERFACE = ("0.0.0.0", "::", "")


def _report_stderr(message: str) -> None:
    print(f"cathtrack: {message}", file=sys.stderr, flush=True)


def parse_viewer_url(url: str) -> tuple[str, int]:
    """Host and port of a rerun gRPC URL (``rerun+http://127.0.0.1:9876/proxy``)."""
    parts = urlsplit(url)
    if parts.scheme not in ("rerun", "rerun+http", "rerun+https") or not parts.hostname:
        raise ValueError(f"not a rerun viewer URL: {url!r} (expected e.g. {DEFAULT_VIEWER_URL})")
    port = parts.port
    if port is None:
        port = 443 if parts.scheme in ("rerun", "rerun+https") else 80
    return parts.hostname, port


def viewer_reachable(url: str, timeout_s: float = 0.5) -> tuple[bool, str]:
    """Whether something accepts TCP connections at a viewer URL, and why not.

    rerun's own connection does not say: it blocks for seconds and then drops the data
    silently when nothing listens.
    """
    host, port = parse_viewer_url(url)
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            return True, ""
    except OSError as exc:
        return False, exc.strerror or str(exc) or type(exc).__name__


class ViewerWatch:
    """Checks in a background thread that a gRPC viewer still accepts connections.

    ``lost`` turns True when a check fails and False again when one succeeds.

    Parameters
    ----------
    url : str
    interval_s, timeout_s : float
    """

    def __init__(self, url: str, interval_s: float = 1.0, timeout_s: float = 0.5) -> None:
        self.url = url
        self.interval_s = float(interval_s)
        self.timeout_s = float(timeout_s)
        self.lost = False
        self.reason = ""
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="viewer-watch", daemon=True)

    def start(self) -> ViewerWatch:
        self._thread.start()
        return self

    def check(self) -> bool:
        """One check now; True when the viewer is reachable."""
        ok, reason = viewer_reachable(self.url, self.timeout_s)
        self.lost, self.reason = not ok, reason
        return ok

    def _run(self) -> None:
        while not self._stop.wait(self.interval_s):
            self.check()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(self.interval_s + self.timeout_s + 1.0)


def reachable_host(bind: str) -> str:
    """The host name to put in URLs for a server bound to ``bind``: 127.0.0.1 on loopback,
    this machine's name when bound to every interface, else the address itself."""
    if bind in ("localhost", LOOPBACK, "::1"):
        return LOOPBACK
    if bind in EVERY_INTERFACE:
        return socket.gethostname()
    return bind


def web_viewer_url(host: str, web_port: int, grpc_url: str) -> str:
    """The address to open in a browser: rerun's web viewer, connecting to ``grpc_url``."""
    return f"http://{host}:{int(web_port)}/?url={quote(grpc_url, safe='')}"


def check_port_free(bind: str, port: int, what: str, advice: str) -> None:
    """Raise a one-line OSError when a TCP port cannot be listened on (rerun's gRPC server
    would only log the failure and drop the data)."""
    family = socket.AF_INET6 if ":" in bind else socket.AF_INET
    with socket.socket(family) as probe:
        try:
            probe.bind((bind, int(port)))
        except OSError as exc:
            reason = exc.strerror or str(exc)
            raise OSError(f"cannot {what} on {bind}:{port} ({reason}): {advice}") from None


def rerun_executable() -> Path:
    """The ``rerun`` command line that the rerun-sdk wheel installs (``rerun_cli``)."""
    folder = Path(rerun_cli.__file__).parent
    bundled = folder / "Rerun.app" / "Contents" / "MacOS" / "Rerun"
    if sys.platform == "darwin" and bundled.exists():
        return bundled
    return folder / ("rerun.exe" if sys.platform.startswith("win") else "rerun")


class WebViewer:
    """rerun's web viewer hosted over HTTP on ``bind``:``web_port`` for browsers, which then
    connect to the gRPC server at ``grpc_url`` (``rerun --serve-web --bind ...``, a child
    process; :meth:`close`, or the end of this process, stops it).

    Parameters
    ----------
    bind : str
        Address to listen on (127.0.0.1: this machine only; 0.0.0.0: every interface).
    web_port : int
    grpc_url : str
        The gRPC server as the browser reaches it, ``rerun+http://HOST:PORT/proxy``.
    """

    def __init__(self, bind: str, web_port: int, grpc_url: str) -> None:
        self.bind, self.web_port, self.grpc_url = bind, int(web_port), grpc_url
        self.url = web_viewer_url(reachable_host(bind), self.web_port, grpc_url)
        self._process: subprocess.Popen | None = None

    def start(self, timeout_s: float = 15.0) -> WebViewer:
        """Start the web server; return once it accepts connections.

        Raises
        ------
        OSError
            The port is taken, or the server did not start (with its last message).
        """
        advice = "choose another --web-viewer-port"
        check_port_free(self.bind, self.web_port, "host the rerun web viewer", advice)
        log = tempfile.TemporaryFile()
        command = [
            str(rerun_executable()),
            "--serve-web",
            "--bind",
            self.bind,
            "--web-viewer-port",
            str(self.web_port),
            self.grpc_url,
        ]
        try:
            self._process = subprocess.Popen(
                command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=log
            )
        except OSError as exc:
            log.close()
            raise OSError(f"cannot start rerun's web viewer ({exc})") from None
        atexit.register(self.close)
        connect_to = LOOPBACK if self.bind in EVERY_INTERFACE else self.bind
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self._process.poll() is not None:
                log.seek(0)
                lines = log.read().decode(errors="replace").strip().splitlines()
                log.close()
                last = lines[-1] if lines else f"exit code {self._process.returncode}"
                raise OSError(f"rerun's web viewer did not start: {last}")
            try:
                with socket.create_connection((connect_to, self.web_port), timeout=0.2):
                    log.close()
                    return self
            except OSError:
                time.sleep(0.1)  # polling a child process's port: nothing to wait on instead
        log.close()
        self.close()
        raise OSError(f"rerun's web viewer did not start within {timeout_s:g} s")

    def close(self) -> None:
        """Stop the web server (nothing happens twice)."""
        process, self._process = self._process, None
        if process is None:
            return
        process.terminate()
        try:
            process.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def add_rerun_args(parser, save_default: str | None = None, bind_option: bool = False) -> None:
    """The usual rerun flags (``rr.script_add_args``) in an argument group, ``--spawn`` and
    ``--web-viewer-port``; ``bind_option`` adds ``--bind`` for a command that has no
    listener of its own (its ``dest`` is ``viewer_bind``).

    ``--save PATH`` writes an ``.rrd``; ``--connect`` (to ``--url``, default
    127.0.0.1:9876) logs to a running viewer; ``--spawn`` starts one; ``--serve`` hosts a
    gRPC server and rerun's web viewer next to it, both on the bind address (loopback by
    default), and the command prints the URL to open; with ``--headless`` only the gRPC
    server (``rerun rerun+http://127.0.0.1:9876/proxy`` connects to it). They combine:
    ``--save`` next to a viewer writes the file too. ``--stdout`` is not supported (the
    commands print their results there).
    """
    # "resolve": --serve and --headless are rerun's, with help saying what they do here.
    group = parser.add_argument_group("rerun output", conflict_handler="resolve")
    rr.script_add_args(group)
    group.add_argument(
        "--serve",
        action="store_true",
        help="host rerun's gRPC server (port 9876) and web viewer (--web-viewer-port) on the"
        " bind address and print the URL to open in a browser",
    )
    group.add_argument(
        "--headless",
        action="store_true",
        help="with --serve: the gRPC server only, no web viewer",
    )
    group.add_argument("--spawn", action="store_true", help="start a rerun viewer and log to it")
    group.add_argument(
        "--web-viewer-port",
        type=int,
        default=DEFAULT_WEB_VIEWER_PORT,
        metavar="PORT",
        help=f"port of the web viewer of --serve (default {DEFAULT_WEB_VIEWER_PORT})",
    )
    if bind_option:
        group.add_argument(
            "--bind",
            dest="viewer_bind",
            default=LOOPBACK,
            metavar="HOST",
            help="address of the gRPC server and web viewer of --serve (default 127.0.0.1:"
            " this machine only; 0.0.0.0: every interface, docs/live.md)",
        )
    if save_default is not None:
        parser.set_defaults(save=save_default)


@dataclass
class RerunOutput:
    """Where a command's rerun stream goes (:func:`open_rerun_output`)."""

    stream: rr.RecordingStream
    targets: list[str]  # human-readable, e.g. "file out/demo.rrd"
    rrd_path: Path | None = None
    viewer_url: str | None = None  # a gRPC viewer logged to (connected or spawned)
    served_url: str | None = None  # the gRPC server web viewers connect to
    web_viewer: WebViewer | None = field(default=None, repr=False)

    @property
    def web_viewer_url(self) -> str | None:
        """The address to open in a browser (``--serve``), or None."""
        return None if self.web_viewer is None else self.web_viewer.url

    def watch(self) -> ViewerWatch | None:
        """A started :class:`ViewerWatch` of the viewer logged to, if any."""
        return None if self.viewer_url is None else ViewerWatch(self.viewer_url).start()

    def close(self) -> None:
        """Stop the web viewer, if one was started (the stream is closed by its sink)."""
        if self.web_viewer is not None:
            self.web_viewer.close()


def serve_until_interrupted(output: RerunOutput, out: Callable[[str], None] = print) -> None:
    """Keep the gRPC server (and the web viewer) up for viewers until Ctrl-C or SIGTERM
    (even where a shell started the process with SIGINT ignored)."""
    where = f"rerun {output.served_url}"
    if output.web_viewer_url:
        where += f" or a browser at {output.web_viewer_url}"
    out(f"serving the session to rerun viewers: {where}  (Ctrl-C to stop)")
    stop = threading.Event()
    previous = {
        signum: signal.signal(signum, lambda *_: stop.set())
        for signum in (signal.SIGINT, signal.SIGTERM)
    }
    try:
        while not stop.wait(0.5):  # short waits: the handlers run between them
            pass
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


def open_rerun_output(
    args,
    application_id: str = "cathtrack",
    *,
    blueprint: rrb.Blueprint | None = None,
    recording_id: str | None = None,
    recording_name: str | None = None,
    start_time_ns: int | None = None,
    bind: str = LOOPBACK,
    report: Callable[[str], None] = _report_stderr,
    flush_tick_s: float | None = None,
) -> RerunOutput | None:
    """Open the rerun outputs the flags of :func:`add_rerun_args` ask for (None: none).

    Like ``rr.script_setup``, but on an explicit :class:`rerun.RecordingStream` rather than
    the global one, with several outputs at once (``rr.RecordingStream.set_sinks``), the
    gRPC server and the web viewer bound to ``bind`` (loopback by default, not every
    interface; the flags' ``--bind`` of a command without listeners of its own wins), and a
    viewer that is not running reported once (``report``) instead of blocking the command
    for seconds and losing the data silently: the command goes on without it.

    Parameters
    ----------
    recording_name : str, optional
        Shown by the viewer instead of ``<unknown>``.
    start_time_ns : int, optional
        Wall-clock start of the session (ns since the Unix epoch), shown with the recording.
    flush_tick_s : float, optional
        The period of the stream's own flushes, s (rerun's default, 0.2 s for a file and
        8 ms for a viewer, when None). A caller that flushes the stream itself when it has
        time to spare (the live loop's viewer sink) sets a long one.

    Raises
    ------
    ValueError
        ``--stdout``, or a malformed ``--url``.
    OSError
        The ``.rrd`` file cannot be created; the web viewer cannot be hosted.
    """
    if getattr(args, "stdout", False):
        raise ValueError("--stdout is not supported: use --save PATH, --connect or --serve")
    bind = getattr(args, "viewer_bind", None) or bind
    sinks: list = []
    targets: list[str] = []
    output = {}
    save = getattr(args, "save", None)
    if save:
        path = Path(save)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            sinks.append(rr.FileSink(path))
        except Exception as exc:  # rerun raises its own error types for unwritable files
            raise OSError(f"cannot write the rerun recording {path}: {exc}") from None
        targets.append(f"file {path}")
        output["rrd_path"] = path
    url = None
    if getattr(args, "spawn", False):
        try:
            rr.spawn(port=DEFAULT_VIEWER_PORT, connect=False)
            url = DEFAULT_VIEWER_URL
        except Exception as exc:  # no rerun executable, no display...
            report(f"cannot start a rerun viewer ({exc}); going on without it")
    if getattr(args, "connect", False) or getattr(args, "url", None):
        url = args.url or DEFAULT_VIEWER_URL
    if url is not None:
        reachable, reason = viewer_reachable(url)
        if reachable:
            sinks.append(rr.GrpcSink(url))
            targets.append(f"viewer {url}")
            output["viewer_url"] = url
        else:
            report(f"no rerun viewer at {url} ({reason}); going on without it")
    web_viewer = None
    if getattr(args, "serve", False):
        served_url = f"rerun+http://{reachable_host(bind)}:{DEFAULT_VIEWER_PORT}/proxy"
        check_port_free(
            bind, DEFAULT_VIEWER_PORT, "serve rerun", "is another rerun server or viewer running?"
        )
        if not getattr(args, "headless", False):
            web_port = getattr(args, "web_viewer_port", DEFAULT_WEB_VIEWER_PORT)
            web_viewer = WebViewer(bind, web_port, served_url).start()
        sinks.append(rr.GrpcServerSink(bind_ip=bind, port=DEFAULT_VIEWER_PORT))
        targets.append(f"server {served_url}")
        output["served_url"] = served_url
        if web_viewer is not None:
            targets.append(f"web viewer {web_viewer.url}")
            output["web_viewer"] = web_viewer
    if not sinks:
        return None
    batcher = None
    if flush_tick_s is not None:
        batcher = rr.ChunkBatcherConfig(flush_tick=timedelta(seconds=float(flush_tick_s)))
    stream = rr.RecordingStream(application_id, recording_id=recording_id, batcher_config=batcher)
    stream.set_sinks(*sinks, default_blueprint=blueprint)
    describe_recording(stream, recording_name, start_time_ns)
    return RerunOutput(stream, targets, **output)


def describe_recording(
    stream: rr.RecordingStream, name: str | None = None, start_time_ns: int | None = None
) -> None:
    """The recording's name and wall-clock start, for the viewer's recording list."""
    if name:
        stream.send_recording_name(name)
    if start_time_ns is not None:
        stream.send_recording_start_time_nanos(int(start_time_ns))


def file_stream(
    path,
    application_id: str = "cathtrack",
    recording_id: str | None = None,
    blueprint: rrb.Blueprint | None = None,
    recording_name: str | None = None,
    start_time_ns: int | None = None,
) -> rr.RecordingStream:
    """A recording stream that writes a ``.rrd`` file (call before logging anything)."""
    stream = rr.RecordingStream(application_id, recording_id=recording_id)
    stream.save(str(path), default_blueprint=blueprint)
    describe_recording(stream, recording_name, start_time_ns)
    return stream
