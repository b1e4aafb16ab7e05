"""MjpegCamera: an HTTP camera on loopback (multipart/x-mixed-replace JPEGs, the format of IP cameras and phone
camera apps), read through OpenCV as a stream URL."""
from __future__ import annotations

import http.server
import signal
import socket
import subprocess
import threading
import time

import cv2
import numpy as np

from tacf_clients.local_service import free_port


class MjpegCamera:
    """An HTTP camera serving multipart/x-mixed-replace JPEGs at `fps` (20). Each connection sends
    `frames_per_connection` frames, then closes (or, with `stall`, goes silent while keeping the connection);
    `down()` closes the port (connection refused), `up()` reopens it. Frame i of connection k shows a white bar at
    x = 8 i on a background of grey level 40 k, so a frame tells which connection delivered it."""

    def __init__(self, frames_per_connection: int = 5, stall: bool = False, fps: float = 20.0):
        self.frames_per_connection, self.stall, self.fps = frames_per_connection, stall, fps
        self.connections = 0
        self._lock = threading.Lock()
        self.port = free_port()  # stays this camera's across down() / up()
        self.url = f"http://127.0.0.1:{self.port}/video.mjpg"
        self._server: http.server.ThreadingHTTPServer | None = None
        self.up()

    def _handler(self):
        camera = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self):
                with camera._lock:
                    camera.connections += 1
                    connection = camera.connections
                self.send_response(200)
                self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
                self.end_headers()
                for i in range(camera.frames_per_connection):
                    jpeg = cv2.imencode(".jpg", camera.frame(connection, i))[1].tobytes()
                    try:
                        self.wfile.write(b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: %d\r\n\r\n%b\r\n"
                                         % (len(jpeg), jpeg))
                        self.wfile.flush()
                    except OSError:
                        return
                    time.sleep(1 / camera.fps)
                if camera.stall:
                    time.sleep(30)  # the link is dead but the connection lives: only a read timeout notices

            def log_message(self, *args):
                pass

        return Handler

    @staticmethod
    def frame(connection: int, index: int) -> np.ndarray:
        image = np.full((96, 128, 3), min(40 * connection, 240), np.uint8)
        image[40:60, 8 * index:8 * index + 8] = 255
        return image

    @staticmethod
    def connection_of(image: np.ndarray) -> int:
        return int(round(float(np.median(image[:30])) / 40))

    def up(self) -> None:
        self._server = http.server.ThreadingHTTPServer(("127.0.0.1", self.port), self._handler())
        self._server.daemon_threads = True
        threading.Thread(target=self._server.serve_forever, daemon=True).start()

    def down(self) -> None:
        self._server.shutdown()
        self._server.server_close()

    def close(self) -> None:
        self.down()


def interrupted_while_a_stream_opens(command_for_url) -> tuple[subprocess.CompletedProcess, float]:
    """Run the command `command_for_url(url)` on the URL of a server that takes connections and never answers, send
    it SIGINT once FFmpeg is opening the stream (the connection came), and return how it ended and how many seconds
    after the SIGINT."""
    with socket.create_server(("127.0.0.1", 0)) as silent:
        proc = subprocess.Popen(command_for_url(f"http://127.0.0.1:{silent.getsockname()[1]}/video.mjpg"),
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            silent.settimeout(30)
            connection, _ = silent.accept()
            proc.send_signal(signal.SIGINT)
            started = time.monotonic()
            out, err = proc.communicate(timeout=30)
            connection.close()
        finally:
            proc.kill()
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err), time.monotonic() - started
