"""The HTTP layer's sections of ``omnisplat-bench reliability`` (see :mod:`bench.reliability`): raw-socket
protocol abuse, slow request bodies against the upload slots, and PNG chunk bombs. Every client talks to
127.0.0.1 only, few and bounded in time; ``srv`` is a :class:`bench.reliability.Server`.
"""

from __future__ import annotations

import collections
import socket
import struct
import threading
import time
import zlib
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import numpy as np


def _chunk(kind: bytes, payload: bytes) -> bytes:
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", zlib.crc32(kind + payload))


def png_rows(width: int, height: int, rows: int) -> bytes:
    """An 8-bit RGB PNG declaring ``width`` x ``height`` whose compressed data holds ``rows`` rows."""
    stream = zlib.compress((b"\x00" + b"\x40" * (3 * width)) * rows)
    return (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0))
            + _chunk(b"IDAT", stream) + _chunk(b"IEND", b""))


def _chunk_bomb(png: bytes, chunks: int) -> bytes:
    """``png`` with ``chunks`` empty private ancillary chunks (``prVt``) between IHDR and the image data."""
    ihdr_end = 8 + 25
    return png[:ihdr_end] + _chunk(b"prVt", b"") * chunks + png[ihdr_end:]


def multipart(parts: list[tuple[str, bytes]], close: bool = True) -> tuple[bytes, dict]:
    body = b""
    for name, data in parts:
        filename = f'; filename="{name}.png"' if name.startswith("image") else ""
        body += f'--bnd\r\nContent-Disposition: form-data; name="{name}"{filename}\r\n\r\n'.encode() + data + b"\r\n"
    return body + (b"--bnd--\r\n" if close else b""), {"content-type": "multipart/form-data; boundary=bnd"}


def _raw(srv, request: bytes, within: float = 5.0) -> bytes:
    """Send raw bytes to 127.0.0.1, read until the server closes (or ``within`` s); what came back."""
    data = b""
    with socket.create_connection(("127.0.0.1", srv.port), timeout=10) as s:
        try:
            s.sendall(request)
        except OSError:
            pass
        end = time.monotonic() + within
        while time.monotonic() < end:
            s.settimeout(max(0.01, end - time.monotonic()))
            try:
                chunk = s.recv(65536)
            except (socket.timeout, OSError):
                break
            if not chunk:
                break
            data += chunk
    return data


def _status_of(raw: bytes) -> int:
    try:
        return int(raw.split(b" ", 2)[1]) if raw.startswith(b"HTTP/1.1 ") else 0
    except ValueError:
        return 0


def protocol(srv) -> dict:
    """Raw-socket abuse: a 1 MB header, Content-Length with Transfer-Encoding, a 500's keep-alive; and HEAD."""
    host = b"Host: 127.0.0.1\r\n"
    big = _raw(srv, b"GET /v1/info HTTP/1.1\r\n" + host + b"X-Big: " + b"a" * (1 << 20) + b"\r\n\r\n")
    smuggle = _raw(srv, b"POST /v1/scenes HTTP/1.1\r\n" + host + b"Content-Length: 4\r\nTransfer-Encoding: chunked\r\n"
                   b"\r\n0\r\n\r\nGET /v1/info HTTP/1.1\r\n" + host + b"\r\n")
    out = {"header_1mb": {"status": _status_of(big), "json": b"application/json" in big.lower()},
           "content_length_and_transfer_encoding": {"status": _status_of(smuggle),
                                                    "answers": smuggle.count(b"HTTP/1.1 ")}}
    with httpx.Client(base_url=srv.url, timeout=30) as c:
        for path in ("/healthz", "/readyz", "/v1/info", "/openapi.json", "/docs"):
            r = c.head(path)
            out[f"head_{path.strip('/').replace('/', '_').replace('.', '_')}"] = {"status": r.status_code,
                                                                              "body_bytes": len(r.content)}
    return out


def slow_bodies(srv, sid: str, n: int, seconds: float) -> dict:
    """``n`` clients announce a 200-byte body to scene ``sid`` and send one byte every 3 s (all on 127.0.0.1,
    stopped after ``seconds``); meanwhile renders, info, metadata and /readyz are polled one after another."""
    eye = ",".join(str(v) for v in np.eye(4).ravel())
    socks = []
    head = (f"POST /v1/scenes/{sid}/selections HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
            "Content-Length: 200\r\n\r\n").encode()
    for _ in range(n):
        s = socket.create_connection(("127.0.0.1", srv.port), timeout=10)
        s.sendall(head)
        socks.append(s)
    stop = threading.Event()

    def trickle():
        while not stop.wait(3.0):
            for s in socks:
                try:
                    s.sendall(b" ")
                except OSError:
                    pass

    t = threading.Thread(target=trickle, daemon=True)
    t.start()
    answers: dict[str, collections.Counter] = {k: collections.Counter() for k in ("render", "info", "meta", "readyz")}
    latency: dict[str, float] = {k: 0.0 for k in answers}
    calls = {"render": lambda c: c.get(f"/v1/scenes/{sid}/render", params={"c2w": eye, "width": 64}),
             "info": lambda c: c.get("/v1/info"), "meta": lambda c: c.get(f"/v1/scenes/{sid}"),
             "readyz": lambda c: c.get("/readyz")}
    t0 = time.monotonic()
    with httpx.Client(base_url=srv.url, timeout=30) as c:
        while time.monotonic() - t0 < seconds:
            for kind, call in calls.items():
                start = time.monotonic()
                try:
                    answers[kind][call(c).status_code] += 1
                except httpx.TransportError:
                    answers[kind][0] += 1
                latency[kind] = max(latency[kind], time.monotonic() - start)
            time.sleep(0.2)
    stop.set()
    t.join(5)
    outcomes: collections.Counter = collections.Counter()
    for s in socks:
        s.settimeout(0.2)
        try:
            got = s.recv(4096)
            outcomes[str(_status_of(got)) if got else "closed"] += 1
        except socket.timeout:
            outcomes["still_open"] += 1
        except OSError:
            outcomes["reset"] += 1
        s.close()
    polled = {k: {str(code): n for code, n in sorted(v.items())} for k, v in answers.items()}
    not_ok = sum(n for k in ("render", "info", "meta") for code, n in answers[k].items() if code != 200)
    return {"slow_clients": n, "seconds": round(time.monotonic() - t0, 1), "answers": polled,
            "max_latency_s": {k: round(v, 3) for k, v in latency.items()},
            "render_info_meta_not_200": not_ok, "slow_client_outcomes": dict(sorted(outcomes.items())),
            "server_errors": [f"{k} {code}" for k, v in answers.items() for code in v if code >= 500 and code != 503]}


def _rss_mb(pid: int) -> tuple[float, float]:
    """(current, peak) resident memory of a process in MB, from /proc."""
    fields = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        fields[key] = value
    return int(fields["VmRSS"].split()[0]) / 1024, int(fields["VmHWM"].split()[0]) / 1024


def chunk_bombs(srv, post, a: bytes, b: bytes, copies: int, chunks: int) -> dict:
    """``copies`` PNGs (``a`` with ``chunks`` empty private chunks each) posted at once with ``post(client,
    image_a, image_b)``; and a PNG declaring 8192x4096 with 3 rows of data. Status, seconds and the server's
    RSS (current and peak) before and after."""
    bomb = _chunk_bomb(a, chunks)
    rss0, peak0 = _rss_mb(srv.proc.pid)

    def one(_):
        with httpx.Client(base_url=srv.url, timeout=300) as c:
            t = time.monotonic()
            r = post(c, bomb, b)
            return r.status_code, r.json()["error"]["code"] if r.status_code >= 400 else None, time.monotonic() - t

    with ThreadPoolExecutor(copies) as pool:
        results = list(pool.map(one, range(copies)))
    rss1, peak1 = _rss_mb(srv.proc.pid)
    with httpx.Client(base_url=srv.url, timeout=120) as c:
        short = post(c, a, png_rows(8192, 4096, 3))
    return {"bomb_mb": round(len(bomb) / 1e6, 1), "chunks": chunks, "copies": copies,
            "statuses": sorted(r[0] for r in results), "codes": sorted({str(r[1]) for r in results}),
            "seconds_max": round(max(r[2] for r in results), 2),
            "server_rss_mb_before_after": [round(rss0), round(rss1)], "server_peak_rss_mb_before_after": [round(peak0),
                                                                                                        round(peak1)],
            "png_8192x4096_3_rows": {"status": short.status_code,
                                     "message": short.json()["error"]["message"][:120] if short.status_code >= 400 else ""}}
