"""Screenshots of the real rerun viewer, without a display: the default layout of the demo and of
a replay at the start, the middle and the end (``docs/figures/{demo,replay}_*.png``, shown in
the README), and with ``--web`` the web viewer of ``cathtrack demo --serve`` in headless
Chromium (``docs/figures/web_viewer.png``).

The viewer is rerun's own (a wgpu app) on mesa's software Vulkan under a virtual X display;
the recordings are made by the commands themselves from the current code. Set-up, once per
machine (Debian packages)::

    apt-get update
    apt-get install -y xvfb mesa-vulkan-drivers libvulkan1 libgl1-mesa-dri chromium

Then::

    python benchmarks/screenshots.py          # demo and replay: about 2 minutes on 2 cores
    python benchmarks/screenshots.py --web    # and the web viewer: about 2 minutes more

An Xvfb display is started unless ``DISPLAY`` is set. The native viewer is driven with
``rerun.experimental.ViewerClient`` (``rerun --headless``, then ``set_time`` and
``take_screenshot``); Chromium over the DevTools protocol on a pipe (``--remote-debugging-pipe``:
no extra package). Rendering in software is slow: every picture waits a few seconds for the
viewer to settle, and the web viewer needs tens of seconds to load.
"""

from __future__ import annotations

import argparse
import base64
import fcntl
import io
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import _common  # noqa: F401  (puts the repository on sys.path)
import rerun.experimental as rre
from PIL import Image

from tracker.viewer.output import rerun_executable

ROOT = Path(__file__).resolve().parents[1]
FIGURES = ROOT / "docs" / "figures"
WINDOW = (1600, 1000)
SETTLE_S = 4.0  # after a time change, for the software renderer to draw every view
LOAD_TIMEOUT_S = 60.0
CHROMIUM_FLAGS = [
    "--headless=new",
    "--no-sandbox",
    "--use-angle=swiftshader",  # WebGL2 in software (WebGPU finds no adapter here)
    "--enable-unsafe-swiftshader",
    "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1",  # offline: nothing outside
    "--remote-debugging-pipe",
    f"--window-size={WINDOW[0]},{WINDOW[1]}",
]


def log(message: str) -> None:
    print(f"screenshots: {message}", flush=True)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def cathtrack_command(*argv: str) -> list[str]:
    return [sys.executable, "-m", "replay.cli", *argv]


def cathtrack(*argv: str) -> None:
    """Run a cathtrack command in a child process."""
    subprocess.run(cathtrack_command(*argv), cwd=ROOT, check=True, stdout=subprocess.DEVNULL)


def save_png(png: bytes, path: Path) -> Path:
    """A 256-colour PNG (a few hundred kB at most); octree keeps the small saturated marks."""
    image = Image.open(io.BytesIO(png)).convert("RGB")
    if image.width > WINDOW[0]:
        image = image.resize(WINDOW, Image.LANCZOS)
    image = image.quantize(256, method=Image.Quantize.FASTOCTREE, dither=Image.Dither.NONE)
    image.save(path, optimize=True)
    log(f"wrote {path.relative_to(ROOT)} ({path.stat().st_size // 1000} kB)")
    return path


# ------------------------------------------------------------------------------ display
def start_display() -> subprocess.Popen | None:
    """An Xvfb display for the viewer, unless one is set (None)."""
    if os.environ.get("DISPLAY"):
        return None
    if shutil.which("Xvfb") is None:
        sys.exit("screenshots: no DISPLAY and no Xvfb: apt-get install -y xvfb (see --help)")
    number = next(n for n in range(90, 200) if not Path(f"/tmp/.X11-unix/X{n}").exists())
    xvfb = subprocess.Popen(
        ["Xvfb", f":{number}", "-screen", "0", f"{WINDOW[0]}x{WINDOW[1]}x24"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.monotonic() + 10
    while not Path(f"/tmp/.X11-unix/X{number}").exists():
        if time.monotonic() > deadline or xvfb.poll() is not None:
            sys.exit("screenshots: Xvfb did not start")
        time.sleep(0.1)
    os.environ["DISPLAY"] = f":{number}"
    return xvfb


# ------------------------------------------------------------------------------ recordings
def demo_recording(work: Path) -> Path:
    path = work / "demo.rrd"
    log("running cathtrack demo (15 s in real time)")
    cathtrack("demo", "--save", str(path))
    return path


def replay_recording(work: Path) -> Path:
    recording = work / "recording.mcap"
    log("simulating a short protocol and replaying it (cathtrack simulate, evaluate)")
    cathtrack(
        "simulate", "--out", str(recording), "--planes", "4", "--configs", "8",
        "--frames", "40", "--no-progress",
    )  # fmt: skip
    cathtrack(
        "evaluate", str(recording), "--out", str(work / "evaluate"),
        "--methods", "tip-position", "body-positions", "ukf",
        "--rrd-image-every", "10", "--no-figures", "--no-progress", "--workers", "1",
    )  # fmt: skip
    return work / "evaluate" / "replay.rrd"


# ------------------------------------------------------------------------------ native viewer
def wait_for_recording(client: rre.ViewerClient):
    """The loaded recording's ``time`` timeline (start and end, ns)."""
    deadline = time.monotonic() + LOAD_TIMEOUT_S
    while time.monotonic() < deadline:
        for recording in client.get_state().recordings:
            for timeline in recording.timelines:
                if timeline.name == "time":
                    return timeline
        time.sleep(0.5)  # the viewer loads the file in the background: poll it
    raise TimeoutError("the viewer did not load the recording")


def native_screenshots(rrd: Path, name: str) -> list[Path]:
    """The default layout at the start, the middle and the end of ``rrd``."""
    port = free_port()
    viewer = subprocess.Popen(
        [
            str(rerun_executable()),
            "--headless",
            "--port",
            str(port),
            "--window-size",
            f"{WINDOW[0]}x{WINDOW[1]}",
        ],
        env={**os.environ, "WGPU_BACKEND": "vulkan"},  # mesa's software Vulkan (llvmpipe)
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    paths = []
    try:
        deadline = time.monotonic() + 30
        while True:
            try:
                client = rre.ViewerClient.connect(f"rerun+http://127.0.0.1:{port}/proxy")
                client.get_state()
                break
            except Exception:  # not listening yet
                if time.monotonic() > deadline or viewer.poll() is not None:
                    raise
                time.sleep(0.5)
        client.open([str(rrd.resolve())])
        timeline = wait_for_recording(client)
        start_s, end_s = timeline.start / 1e9, timeline.end / 1e9
        moments = {
            "start": start_s + 0.5,
            "middle": (start_s + end_s) / 2,
            "end": end_s - 0.5,
        }
        for moment, time_s in moments.items():
            client.set_time("time", duration=time_s, play_state="paused")
            time.sleep(SETTLE_S)
            paths.append(save_png(client.take_screenshot(), FIGURES / f"{name}_{moment}.png"))
    finally:
        viewer.terminate()
        viewer.wait()
    return paths


# ------------------------------------------------------------------------------ web viewer
class Chromium:
    """Headless Chromium driven over the DevTools protocol on a pipe (fds 3 and 4)."""

    def __init__(self) -> None:
        executable = shutil.which("chromium") or shutil.which("chromium-browser")
        if executable is None:
            sys.exit("screenshots: no chromium: apt-get install -y chromium (see --help)")
        to_browser_r, self._to_browser = os.pipe()
        self._from_browser, from_browser_w = os.pipe()

        def pipes() -> None:  # the child's fds 3 and 4 are the protocol's
            high = [fcntl.fcntl(fd, fcntl.F_DUPFD, 10) for fd in (to_browser_r, from_browser_w)]
            os.dup2(high[0], 3)
            os.dup2(high[1], 4)

        self.process = subprocess.Popen(
            [executable, *CHROMIUM_FLAGS, "about:blank"],
            pass_fds=(3, 4),  # kept open after pipes() (the rest is closed after it runs)
            preexec_fn=pipes,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        os.close(to_browser_r)
        os.close(from_browser_w)
        self._buffer = b""
        self._id = 0

    def call(self, method: str, session: str | None = None, **params) -> dict:
        self._id += 1
        message = {"id": self._id, "method": method, "params": params}
        if session is not None:
            message["sessionId"] = session
        os.write(self._to_browser, json.dumps(message).encode() + b"\0")
        while True:
            while b"\0" not in self._buffer:
                chunk = os.read(self._from_browser, 1 << 20)
                if not chunk:
                    raise RuntimeError("chromium closed the DevTools pipe")
                self._buffer += chunk
            raw, self._buffer = self._buffer.split(b"\0", 1)
            reply = json.loads(raw)
            if reply.get("id") == self._id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply.get("result", {})

    def screenshot(self, url: str, wait_s: float) -> bytes:
        target = self.call("Target.createTarget", url=url)["targetId"]
        session = self.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
        log(f"waiting {wait_s:g} s for the web viewer to load and draw")
        time.sleep(wait_s)  # real time: the page loads a large wasm app and then streams
        shot = self.call("Page.captureScreenshot", session=session, format="png")
        return base64.b64decode(shot["data"])

    def close(self) -> None:
        self.process.terminate()
        self.process.wait()
        os.close(self._to_browser)
        os.close(self._from_browser)


def web_screenshot(work: Path, wait_s: float) -> Path:
    """``cathtrack demo --serve`` hosts the web viewer; Chromium opens the URL it prints."""
    demo = subprocess.Popen(
        cathtrack_command("demo", "--serve", "--seconds", "8", "--save", str(work / "web.rrd")),
        cwd=ROOT,
        stdout=subprocess.PIPE,
        text=True,
    )
    url = None
    try:
        # The URL comes first; the browser starts once the run is over and the demo only
        # serves it (software WebGL in Chromium would otherwise starve the real-time loop).
        for line in demo.stdout:
            if url is None and "web viewer http" in line:
                url = "http" + line.split("web viewer http", 1)[1].split(";")[0].strip()
                log(f"cathtrack demo --serve: {url}")
            if line.startswith("serving the session"):
                break
        if url is None:
            raise RuntimeError("cathtrack demo --serve printed no web viewer URL")
        browser = Chromium()
        try:
            png = browser.screenshot(url, wait_s)
        finally:
            browser.close()
        return save_png(png, FIGURES / "web_viewer.png")
    finally:
        demo.send_signal(signal.SIGINT)  # the demo serves until Ctrl-C
        try:
            demo.wait(timeout=20)
        except subprocess.TimeoutExpired:
            demo.kill()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--demo-rrd", type=Path, help="use this demo recording (default: run)")
    parser.add_argument("--replay-rrd", type=Path, help="use this replay.rrd (default: make)")
    parser.add_argument("--web", action="store_true", help="also the web viewer in Chromium")
    parser.add_argument(
        "--web-wait", type=float, default=90.0, help="seconds the web viewer gets to load (90)"
    )
    parser.add_argument("--work", type=Path, help="keep the recordings in this folder")
    args = parser.parse_args(argv)
    FIGURES.mkdir(parents=True, exist_ok=True)
    display = start_display()
    with tempfile.TemporaryDirectory(prefix="cathtrack-screenshots-") as scratch:
        work = args.work or Path(scratch)
        work.mkdir(parents=True, exist_ok=True)
        try:
            native_screenshots(args.demo_rrd or demo_recording(work), "demo")
            native_screenshots(args.replay_rrd or replay_recording(work), "replay")
            if args.web:
                web_screenshot(work, args.web_wait)
        finally:
            if display is not None:
                display.terminate()
                display.wait()
    return 0


if __name__ == "__main__":
    sys.exit(main())
