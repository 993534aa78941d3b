"""A local Rerun web viewer process (`rerun --serve-web`), bound to 127.0.0.1, that a run streams to."""

from __future__ import annotations

import atexit
import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import quote


def free_port(preferred: int) -> int:
    """`preferred` when it is free on 127.0.0.1, else any free port."""
    for port in (preferred, 0):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return int(s.getsockname()[1])
    raise RuntimeError("no free TCP port on 127.0.0.1")


def _rerun_cli() -> list[str]:
    """The `rerun` viewer binary shipped with rerun-sdk (or its Python launcher)."""
    import rerun_cli

    exe = Path(rerun_cli.__file__).parent / "rerun"
    return [str(exe)] if exe.is_file() else [sys.executable, "-m", "rerun_cli"]


def _wait_listening(port: int, timeout_s: float) -> bool:
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return True
        time.sleep(0.1)
    return False


@dataclass
class RerunWebViewer:
    process: subprocess.Popen
    grpc_url: str  # where a RecordingStream sends (rr.GrpcSink)
    url: str  # what a browser opens

    @classmethod
    def start(cls, grpc_port: int = 9876, web_port: int = 9090) -> RerunWebViewer:
        """Start the viewer (web page + gRPC proxy) on free ports near the preferred ones."""
        grpc_port, web_port = free_port(grpc_port), free_port(web_port)
        cmd = [*_rerun_cli(), "--serve-web", "--bind", "127.0.0.1"]
        cmd += ["--port", str(grpc_port), "--web-viewer-port", str(web_port)]
        # Its own process group, so that stop() ends the viewer and nothing else.
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        grpc_url = f"rerun+http://127.0.0.1:{grpc_port}/proxy"
        viewer = cls(proc, grpc_url, f"http://127.0.0.1:{web_port}/?url={quote(grpc_url, safe='')}")
        atexit.register(viewer.stop)
        if not (_wait_listening(grpc_port, 20.0) and _wait_listening(web_port, 20.0)):
            viewer.stop()
            raise RuntimeError("the Rerun web viewer did not start (is `rerun` installed in this environment?)")
        return viewer

    def stop(self) -> None:
        if self.process.poll() is not None:
            return
        os.killpg(self.process.pid, signal.SIGTERM)
        try:
            self.process.wait(timeout=5)
        except subprocess.TimeoutExpired:
            os.killpg(self.process.pid, signal.SIGKILL)
            self.process.wait(timeout=5)
