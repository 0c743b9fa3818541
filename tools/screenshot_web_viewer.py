"""Screenshot of a Rerun recording in the *web* viewer, in headless Chromium, to check that a .rrd really displays.

    python tools/screenshot_web_viewer.py runs/quick/<ts>/capture.rrd --out viewer.png [--wait 60] [--seek-ms 120]

Serves the web viewer on 127.0.0.1 with the ``rerun`` binary of the rerun-sdk wheel (``rerun FILE --serve-web``),
starts Debian's ``chromium`` headless and drives it over the DevTools protocol through a pipe
(``--remote-debugging-pipe``: JSON messages separated by NUL bytes on file descriptors 3 and 4, so no websocket
client is needed), waits for the viewer's WebAssembly to load and render (WebGL2 through SwiftShader: a plain
``chromium --screenshot`` fires before it has drawn anything), and saves a PNG. Both processes are stopped at the end.
Not a test: it needs chromium (``apt-get install chromium``) and takes about a minute.
"""

from __future__ import annotations

import argparse
import base64
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path


class DevTools:
    """A minimal DevTools protocol client over Chromium's --remote-debugging-pipe."""

    def __init__(self, proc: subprocess.Popen, write_fd: int, read_fd: int):
        self.proc, self.w, self.r = proc, write_fd, read_fd
        self.next_id, self.buf = 0, b""

    def _read_message(self, timeout_s: float) -> dict:
        end = time.monotonic() + timeout_s
        while b"\0" not in self.buf:
            if time.monotonic() > end:
                raise TimeoutError("no answer from chromium over the DevTools pipe")
            chunk = os.read(self.r, 1 << 20)
            if not chunk:
                raise RuntimeError("chromium closed the DevTools pipe (did it crash? see its stderr)")
            self.buf += chunk
        msg, _, self.buf = self.buf.partition(b"\0")
        return json.loads(msg)

    def call(self, method: str, params: dict | None = None, session: str | None = None, timeout_s: float = 60) -> dict:
        self.next_id += 1
        msg = {"id": self.next_id, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = session
        os.write(self.w, json.dumps(msg).encode() + b"\0")
        while True:
            got = self._read_message(timeout_s)
            if got.get("id") == self.next_id:
                if "error" in got:
                    raise RuntimeError(f"{method}: {got['error']}")
                return got.get("result", {})


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("rrd", type=Path)
    ap.add_argument("--out", type=Path, default=Path("viewer.png"))
    ap.add_argument("--wait", type=float, default=60.0, help="seconds to let the viewer load and render")
    ap.add_argument("--port", type=int, default=9090, help="web viewer port (HTTP)")
    ap.add_argument("--grpc-port", type=int, default=9876, help="the viewer's data port (gRPC)")
    ap.add_argument("--width", type=int, default=1600)
    ap.add_argument("--height", type=int, default=1000)
    ap.add_argument("--chromium", default=shutil.which("chromium") or "chromium")
    ap.add_argument("--click", type=float, nargs=2, metavar=("X", "Y"), action="append", default=[],
                    help="after loading, click at these page coordinates (e.g. on the time bar to seek), then wait "
                         "5 s; repeatable")
    args = ap.parse_args(argv)

    rerun = shutil.which("rerun") or str(Path(sys.executable).with_name("rerun"))
    env = dict(os.environ, RERUN_ANALYTICS="0")
    # its own process group: the `rerun` script starts the native binary as a child, stopped with it at the end
    server = subprocess.Popen([rerun, str(args.rrd), "--serve-web", "--bind", "127.0.0.1", "--web-viewer-port",
                               str(args.port), "--port", str(args.grpc_port)], stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True, env=env, start_new_session=True)
    lines: list[str] = []
    threading.Thread(target=lambda: [lines.append(line) for line in server.stdout], daemon=True).start()
    url = None
    t0 = time.monotonic()
    while url is None and time.monotonic() - t0 < 30:
        for line in lines:
            m = re.search(r"(http://127\.0\.0\.1:%d\?url=\S+)" % args.port, line)  # with the data's address
            if m:
                url = m.group(1)
        if server.poll() is not None:
            raise SystemExit(f"rerun exited: {''.join(lines)}")
        time.sleep(0.2)
    url = url or f"http://127.0.0.1:{args.port}"
    print(f"web viewer: {url}", file=sys.stderr)
    print("".join(lines[-5:]), file=sys.stderr)

    profile = tempfile.mkdtemp(prefix="chromium-profile-")
    chrome_log = open(Path(profile) / "chromium.log", "wb")
    to_chrome_r, to_chrome_w = os.pipe()
    from_chrome_r, from_chrome_w = os.pipe()

    def child_fds():  # chromium reads commands on fd 3 and writes answers on fd 4
        a, b = os.dup(to_chrome_r), os.dup(from_chrome_w)  # above 4, so neither is overwritten by the other
        os.dup2(a, 3)
        os.dup2(b, 4)

    chrome = subprocess.Popen(
        [args.chromium, "--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader",
         "--use-angle=swiftshader", "--remote-debugging-pipe", "--no-first-run", "--disable-dev-shm-usage",
         f"--user-data-dir={profile}", f"--window-size={args.width},{args.height}", "about:blank"],
        close_fds=False, preexec_fn=child_fds, stdout=subprocess.DEVNULL, stderr=chrome_log, start_new_session=True)
    os.close(to_chrome_r)
    os.close(from_chrome_w)
    try:
        dt = DevTools(chrome, to_chrome_w, from_chrome_r)
        target = dt.call("Target.createTarget", {"url": "about:blank"})["targetId"]
        session = dt.call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        dt.call("Emulation.setDeviceMetricsOverride", {"width": args.width, "height": args.height,
                                                       "deviceScaleFactor": 1, "mobile": False}, session)
        dt.call("Page.enable", {}, session)
        dt.call("Page.navigate", {"url": url}, session)
        print(f"loading for {args.wait:.0f} s ...", file=sys.stderr)
        time.sleep(args.wait)
        for x, y in args.click:
            for kind in ("mousePressed", "mouseReleased"):
                dt.call("Input.dispatchMouseEvent", {"type": kind, "x": x, "y": y, "button": "left", "clickCount": 1},
                        session)
            time.sleep(5)
        shot = dt.call("Page.captureScreenshot", {"format": "png"}, session, timeout_s=120)
        args.out.write_bytes(base64.b64decode(shot["data"]))
        print(f"wrote {args.out}", file=sys.stderr)
    finally:
        for p in (chrome, server):  # each leads its own process group (chromium's helpers, rerun's binary)
            try:
                os.killpg(p.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
        for p in (chrome, server):
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
        chrome_log.close()
        if chrome.returncode not in (0, -15, None):
            print((Path(profile) / "chromium.log").read_text(errors="replace")[-3000:], file=sys.stderr)
        shutil.rmtree(profile, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
