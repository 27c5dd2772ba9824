"""Issue 28: ``scan3d status`` and ``scan3d trigger`` trust no reply. A socket that answers the wrong shape,
too much, too slowly or without a newline gives exit status 2 and one line, within the client's timeout."""

from __future__ import annotations

import contextlib
import io
import json
import socket
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from appliance import cli
from appliance.service import client


@contextlib.contextmanager
def fake_service(reply: bytes, *, trickle: bool = False, hold_s: float = 3.0) -> Iterator[Path]:
    """A unix socket that answers every connection with ``reply`` (byte by byte when ``trickle``)."""
    folder = Path(tempfile.mkdtemp(prefix="s3d", dir="/tmp"))  # short: AF_UNIX paths end at 107 bytes
    path = folder / "c.sock"
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    srv.bind(str(path))
    srv.listen(4)
    srv.settimeout(0.2)
    stop = threading.Event()

    def serve() -> None:
        while not stop.is_set():
            try:
                conn, _ = srv.accept()
            except TimeoutError:
                continue
            with conn:
                conn.settimeout(1.0)
                with contextlib.suppress(OSError):
                    conn.recv(65536)
                    if trickle:
                        for b in reply:
                            if stop.wait(0.1):
                                break
                            conn.sendall(bytes([b]))
                    else:
                        conn.sendall(reply)
                    stop.wait(hold_s)  # keep the connection open: no end of file to stop the client

    t = threading.Thread(target=serve, daemon=True)
    t.start()
    try:
        yield path
    finally:
        stop.set()
        t.join(5)
        srv.close()
        path.unlink(missing_ok=True)
        folder.rmdir()


CASES = [
    ("status_is_a_string", ["status"], b'{"status": "x"}\n', "not what scan3d's service answers"),
    ("status_not_json", ["status"], b"HTTP/1.1 400 Bad Request\r\n\r\n\n", "not JSON"),
    ("status_a_list", ["status"], b"[1, 2]\n", "unexpected reply"),
    ("status_bad_devices", ["status"], b'{"status": {"state": "ready", "devices": [{"role": 1}]}}\n',
     "not what scan3d's service answers"),
    ("trigger_empty_scan", ["trigger", "--wait"], b'{"ok": true, "scan": {}}\n', "not what scan3d's service"),
    ("trigger_no_ok", ["trigger"], b'{"result": "started"}\n', "not what scan3d's service answers"),
    ("no_newline", ["status"], b'{"status": {"state": "ready"}}', "no complete reply within 1 s"),
    ("trickle", ["status"], b'{"status": {"state": "ready", "pad": "' + b"x" * 200, "no complete reply within 1 s"),
    ("too_long", ["status"], b'{"status": "' + b"x" * (9 * 1024 * 1024), "longer than"),
    # the second sweep: what json.loads and int() raise besides JSONDecodeError, and a tune's reply
    ("nested_too_deeply", ["status"], b"[" * 100_000 + b"]" * 100_000 + b"\n", "not JSON"),
    ("not_utf8", ["status"], b'{"status": "\xff\xfe"}\n', "not JSON"),
    ("uptime_infinite", ["status"], b'{"status": {"state": "ready", "uptime_s": Infinity}}\n',
     "not what scan3d's service answers"),
    ("uptime_1e400", ["status"], b'{"status": {"state": "ready", "uptime_s": 1e400}}\n',
     "not what scan3d's service answers"),
    ("uptime_5000_digits", ["status"], b'{"status": {"state": "ready", "uptime_s": 1' + b"0" * 5000 + b"}}\n",
     "not JSON"),
    ("trigger_points_infinite", ["trigger", "--wait"],
     b'{"ok": true, "scan": {"scan_id": "a", "points": Infinity, "location": "share"}}\n',
     "not what scan3d's service answers"),
    ("tune_lines_a_number", ["tune"], b'{"ok": true, "tune": {"lines": 5}}\n', "not what scan3d's service answers"),
    ("tune_lines_not_text", ["tune"], b'{"ok": true, "tune": {"lines": [1, {"a": 2}]}}\n',
     "not what scan3d's service answers"),
]


@pytest.mark.parametrize(("case", "argv", "reply", "words"), CASES, ids=[c[0] for c in CASES])
def test_a_reply_the_client_cannot_use_is_one_line_in_time(monkeypatch: pytest.MonkeyPatch, case: str,
                                                           argv: list[str], reply: bytes, words: str) -> None:
    monkeypatch.setattr(client, "STATUS_TIMEOUT_S", 1.0)
    monkeypatch.setattr(client, "TRIGGER_WAIT_TIMEOUT_S", 1.0)
    monkeypatch.setattr(client, "TUNE_TIMEOUT_S", 1.0)
    with fake_service(reply, trickle=case == "trickle") as path:
        err = io.StringIO()
        start = time.monotonic()
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
            rc = cli.main([*argv, "--socket", str(path)])
        took = time.monotonic() - start
    lines = [ln for ln in err.getvalue().splitlines() if ln.strip()]
    assert rc == 2 and len(lines) == 1, err.getvalue()
    assert words in lines[0] and "Traceback" not in err.getvalue(), lines[0]
    assert took < 5.0, f"{case}: {took:.1f} s"


def test_a_socket_path_too_long_is_one_line(tmp_path: Path) -> None:
    path = Path("/tmp") / ("x" * 120) / "control.sock"
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        rc = cli.main(["status", "--socket", str(path)])
    lines = [ln for ln in err.getvalue().splitlines() if ln.strip()]
    assert rc == 2 and len(lines) == 1 and "Traceback" not in err.getvalue(), err.getvalue()


def test_escape_sequences_in_a_reply_are_shown_not_obeyed() -> None:
    """A reply's text goes to a person's terminal: an escape sequence (clear screen, colours) or a carriage
    return from whatever listens on the socket is printed as '?', never sent to the terminal as is."""
    reply = b'{"status": {"state": "ready", "detail": "\\u001b[2J\\u001b[31mall good\\r\\u009b"}}\n'
    with fake_service(reply, hold_s=0.0) as path:
        out = io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
            rc = cli.main(["status", "--socket", str(path)])
    text = out.getvalue()
    assert rc == 0, text
    assert "?[2J?[31mall good??" in text
    assert not any((ord(c) < 0x20 and c != "\n") or 0x7F <= ord(c) < 0xA0 for c in text), repr(text)


def test_status_json_is_strict_json_where_a_value_is_not_a_number() -> None:
    """A status value that is NaN (no measurement yet) or infinite is printed as null by ``status --json``:
    Python's ``NaN`` token is not JSON, and jq, browsers and strict parsers refuse the whole document."""
    reply = b'{"status": {"state": "ready", "last_scan": {"rms_mm": NaN, "sigma": [1.5, -Infinity]}}}\n'
    with fake_service(reply, hold_s=0.0) as path:
        out = io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
            rc = cli.main(["status", "--json", "--socket", str(path)])

    def refuse(token: str) -> None:
        raise AssertionError(f"not JSON: {token}")

    doc = json.loads(out.getvalue(), parse_constant=refuse)
    assert rc == 0 and doc["state"] == "ready"
    assert doc["last_scan"] == {"rms_mm": None, "sigma": [1.5, None]}
