"""`fae send` against something that is not a fae server: a clear error, exit 2.

Each case is a one-connection TCP server in a thread that reads whatever it is sent and
answers as a wrong server would; `fae send` then says what was wrong instead of printing a
summary of nothing ("0/0 frames ok", "100/48 frames ok").
"""

from __future__ import annotations

import socket
import threading
from pathlib import Path

import pytest

from fae.cli import main

STREAM = Path(__file__).resolve().parents[1] / "fap_streams" / "visemes.fap"


def _wrong_server(reply: bytes) -> tuple[int, threading.Thread]:
    """A port where one client is answered `reply` while everything it sends is read, then
    the connection closes."""
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]

    def serve() -> None:
        with listener:
            listener.settimeout(20)
            conn, _ = listener.accept()
            with conn:
                conn.settimeout(5)
                conn.sendall(reply)
                try:
                    while conn.recv(65536):  # until the client half-closes
                        pass
                except OSError:
                    pass

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    return port, thread


@pytest.mark.parametrize("reply, expected", [
    (bytes(range(256)) * 40, "no reply to the stream's header for 2 s: not a fae server"),
    (b"ok header 25\n" + b"ok 1 1\n" * 100, "frames acknowledged of 48 sent: not a fae server"),
    (b"ok header 25\n", "closed after 0 of 48 frames were acknowledged, without the server's closing `done`"),
    (b"ok header 25\ndone 0 frames 0 steps 0 errors\n", "said `done` after acknowledging 0 of 48 frames"),
    (b"HTTP/1.1 400 Bad Request\r\n\r\n", "not a fae server, or it closed the connection (it sent 'HTTP/1.1 400"),
])
def test_send_to_a_wrong_server_says_so_with_status_2(reply, expected, capsys):
    port, thread = _wrong_server(reply)
    code = main(["send", str(STREAM), "--port", str(port), "--rate", "max", "--timeout", "2"])
    thread.join(10)
    err = capsys.readouterr().err
    assert code == 2
    assert f"fae send: 127.0.0.1:{port}: " in err and expected in err
