"""Attack a real `fae serve` and measure what a well-behaved client still gets.

Starts `python -m fae serve --port 0` (the shipped head, or --head) on 127.0.0.1, then runs
each attack in turn. During every attack a well-behaved native client streams a real
.fap file at its own frame rate (25 fps) and times each frame: sent -> `ok` read. The
baseline is the same client alone, in the same run. For each attack the table gives
the good client's latency p50/p99, whether it was served at all, and the server's
resident memory (VmRSS) before the attack and after it ended.

Attacks:
  idle-horde     200 sockets from the good client's own address that connect and say nothing
  idle-horde-2   200 silent sockets from another address (127.0.0.2): its per-address cap
  gaps           2 clients each sending frame 0, 12500, 25000, ... (dt = 500 s at 25 fps)
  tiny-fps       2 clients with a header fps of 0.01 (dt = 100 s per frame), frames 0, 1, 2, ...
  upload-gap     an Xface UPLOAD_FAP of 2 frames numbered 0 and 10**7, then RESUME_PLAYBACK
  flood          4 clients streaming frames as fast as the server takes them
  garbage        4 clients sending malformed lines as fast as the server reads them
  long-ids       Xface tasks with 5,000-digit ownerIds (the server's log must stay small)

    .venv/bin/python tools/attack_serve.py                   # all attacks
    .venv/bin/python tools/attack_serve.py gaps upload-gap   # some
    .venv/bin/python tools/attack_serve.py --json out.json   # also write the numbers
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import subprocess
import sys
import threading
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fae.net.client import send_fap  # noqa: E402

FAP = next(p for p in (ROOT.parent / "shared" / "data" / "fap" / "xface_anger.fap",
                       ROOT / "fap_streams" / "expressions.fap") if p.is_file())
ATTACK_WARMUP = 1.5  # seconds an attack runs before the good client starts


class Server:
    """`python -m fae serve --port 0` in a process of its own; its port and stderr."""

    def __init__(self, *args: str) -> None:
        env = dict(os.environ, PYTHONUNBUFFERED="1", PYTHONPATH=str(ROOT))
        self.proc = subprocess.Popen([sys.executable, "-m", "fae", "serve", "--port", "0", *args], cwd=ROOT,
                                     stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True, env=env)
        self.log: list[str] = []
        self.port = 0
        ready = threading.Event()

        def read() -> None:
            for line in self.proc.stderr:
                self.log.append(line)
                if "listening on " in line:
                    self.port = int(line.split("listening on ", 1)[1].split()[0].rsplit(":", 1)[1])
                    ready.set()
            ready.set()

        threading.Thread(target=read, daemon=True).start()
        if not ready.wait(300) or not self.port:
            self.proc.kill()
            raise SystemExit("fae serve did not start:\n" + "".join(self.log))

    def rss_mb(self) -> float:
        for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
        return float("nan")

    @property
    def log_bytes(self) -> int:
        return sum(len(line) for line in self.log)

    def stop(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(60)
        except subprocess.TimeoutExpired:
            self.proc.kill()


def mask_and_values(number: int, open_jaw: int) -> str:
    mask = ["0"] * 68
    mask[2] = "1"
    return " ".join(mask) + f"\n{number} {open_jaw}\n"


async def good_client(port: int) -> dict:
    """The well-behaved client: FAP at its own rate; its latencies, or why it failed."""
    try:
        report = await send_fap(FAP.read_text(), port=port, rate="realtime", timeout=60)
    except (OSError, asyncio.TimeoutError) as exc:
        return {"served": False, "why": f"{type(exc).__name__}: {exc}"}
    return {"served": report.complete, "frames_ok": report.frames_ok, "frames_sent": report.frames_sent,
            "p50_ms": report.latency_ms(50), "p99_ms": report.latency_ms(99),
            "why": "; ".join(report.errors[:2])}


async def hold_open(port: int, count: int, stop: asyncio.Event, source: str = "127.0.0.1") -> None:
    """`count` sockets that connect and say nothing until `stop`."""
    writers = []
    for _ in range(count):
        try:
            _, w = await asyncio.open_connection("127.0.0.1", port, local_addr=(source, 0))
            writers.append(w)
        except OSError:
            pass
    await stop.wait()
    for w in writers:
        w.close()


async def native_attacker(port: int, stop: asyncio.Event, header: str, frame_number, *, lockstep: bool) -> None:
    """One native client: header, then frames numbered frame_number(k) until `stop`;
    lockstep: each frame waits for the previous one's `ok` (else as fast as TCP takes them)."""
    try:
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
    except OSError:
        return
    async def drain() -> None:  # read the acks, so the server never waits on this client
        while await reader.read(65536):
            pass

    writer.write(header.encode() + b"\n")
    drainer = None if lockstep else asyncio.create_task(drain())
    k = 0
    try:
        while not stop.is_set():
            writer.write(mask_and_values(frame_number(k), 100 * (k % 5)).encode())
            await writer.drain()
            k += 1
            while lockstep:
                line = await asyncio.wait_for(reader.readline(), 30)
                if not line:
                    return
                if line.startswith(b"ok ") and not line.startswith(b"ok header"):
                    break
    except (OSError, asyncio.TimeoutError):
        pass
    finally:
        if drainer is not None:
            drainer.cancel()
        writer.close()


async def garbage_attacker(port: int, stop: asyncio.Event) -> None:
    """Reconnects and sends malformed lines until `stop` (each connection is closed by the
    server after its error budget)."""
    while not stop.is_set():
        try:
            reader, writer = await asyncio.open_connection("127.0.0.1", port)
            writer.write(b"2.1 junk 25 10\n" + b"1 2 3 x y z\n" * 64)
            await writer.drain()
            await asyncio.wait_for(reader.read(), 5)
            writer.close()
        except (OSError, asyncio.TimeoutError):
            await asyncio.sleep(0.01)


def xface_task(name: str, owner: str, task_id: int, *params: str) -> bytes:
    body = "".join(f"<param>{p}</param>" for p in params)
    return f'<task name="{name}" ownerId="{owner}" taskId="{task_id}">{body}</task>'.encode() + b"\0"


async def xface_attacker(port: int, stop: asyncio.Event, messages: list[bytes], repeat: bool) -> None:
    try:
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
    except OSError:
        return
    try:
        while True:
            for m in messages:
                writer.write(m)
                await writer.drain()
                await asyncio.sleep(0.001)
            if not repeat or stop.is_set():
                break
        await stop.wait()
    except OSError:
        pass
    finally:
        writer.close()


def upload_gap_text(gap: int) -> str:
    return "2.1 gap 25 2\n" + mask_and_values(0, 300) + mask_and_values(gap, 600)


def attacks(port: int, stop: asyncio.Event) -> dict:
    header = "2.1 attack 25 1000000"
    return {
        "idle-horde": lambda: [hold_open(port, 200, stop)],
        "idle-horde-2": lambda: [hold_open(port, 200, stop, source="127.0.0.2")],
        "gaps": lambda: [native_attacker(port, stop, header, lambda k: 12500 * k, lockstep=True) for _ in range(2)],
        "tiny-fps": lambda: [native_attacker(port, stop, "2.1 slow 0.01 1000000", lambda k: k, lockstep=True)
                             for _ in range(2)],
        "upload-gap": lambda: [xface_attacker(port, stop, [xface_task("UPLOAD_FAP", "1", 1, upload_gap_text(10 ** 7)),
                                                           xface_task("RESUME_PLAYBACK", "1", 2)], repeat=False)],
        "flood": lambda: [native_attacker(port, stop, header, lambda k: k, lockstep=False) for _ in range(4)],
        "garbage": lambda: [garbage_attacker(port, stop) for _ in range(4)],
        "long-ids": lambda: [xface_attacker(port, stop, [xface_task("STOP_PLAYBACK", "5" * 5000, 1),
                                                         xface_task("NO_SUCH_TASK" + "x" * 5000, "1", 2)], repeat=True)],
    }


async def run_attack(server: Server, name: str | None) -> dict:
    stop = asyncio.Event()
    rss_before, log_before = server.rss_mb(), server.log_bytes
    tasks = [asyncio.create_task(c) for c in attacks(server.port, stop)[name]()] if name else []
    if tasks:
        await asyncio.sleep(ATTACK_WARMUP)
    good = await good_client(server.port)
    rss_during = server.rss_mb()
    stop.set()
    if tasks:
        await asyncio.wait(tasks, timeout=30)
    await asyncio.sleep(1.0)
    return {"attack": name or "none (baseline)", **good, "rss_before_mb": rss_before, "rss_during_mb": rss_during,
            "rss_after_mb": server.rss_mb(), "log_bytes": server.log_bytes - log_before}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("attacks", nargs="*", help="attacks to run (default: all)")
    parser.add_argument("--head", help="head for the server (default: the shipped one)")
    parser.add_argument("--json", help="also write the results here")
    args = parser.parse_args()
    names = args.attacks or list(attacks(0, asyncio.Event()))
    unknown = [n for n in names if n not in attacks(0, asyncio.Event())]
    if unknown:
        parser.error(f"unknown attacks {unknown}; expected some of {list(attacks(0, asyncio.Event()))}")
    server = Server(*(["--head", args.head] if args.head else []))
    rows = []
    try:
        asyncio.run(good_client(server.port))  # the first face's set-up is not part of any row
        for name in [None, *names]:
            row = asyncio.run(run_attack(server, name))
            rows.append(row)
            served = "yes" if row["served"] else f"NO ({row.get('why', '')})"
            print(f"{row['attack']:16s} served {served:4s} p50 {row.get('p50_ms', float('nan')):8.1f} ms  "
                  f"p99 {row.get('p99_ms', float('nan')):8.1f} ms  server RSS {row['rss_before_mb']:6.0f} -> "
                  f"{row['rss_during_mb']:6.0f} (during) -> {row['rss_after_mb']:6.0f} MB (after)  "
                  f"log +{row['log_bytes']} B", flush=True)
    finally:
        server.stop()
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0 if all(r["served"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
