"""The emulator's sockets: RTDE on 30004, the dashboard on 29999, script upload on 30003, and the 500 Hz
tick that steps the controller and streams data packages to every started RTDE connection.

Plain threads and blocking sockets: the emulator is its own process (the client's constructors hold the
GIL while they wait for data, so an emulator in the client's process would deadlock).
"""

from __future__ import annotations

import contextlib
import json
import logging
import socket
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from common.runtime.storage import atomic_write
from services.ur_emulator import rtde
from services.ur_emulator.controller import Controller

Handler = Callable[[socket.socket, str], None]  # one connection of one interface

log = logging.getLogger("cadence.ur_emulator")

RTDE_PORT, DASHBOARD_PORT, SCRIPT_PORT = 30004, 29999, 30003
CONTROLLER_VERSION = (5, 15, 0, 0)
TICK_S = 0.002


@dataclass
class Recipe:
    names: list[str]
    types: list[str]
    packer: struct.Struct


@dataclass
class RtdeConnection:
    sock: socket.socket
    peer: str
    outputs: Recipe | None = None
    output_id: int = 0
    every: int = 1  # send on every n-th tick (500 Hz / requested frequency)
    inputs: dict[int, Recipe] = field(default_factory=dict)
    started: bool = False
    control: bool = False  # the control interface's connection (its outputs hold the script's registers)
    send_lock: threading.Lock = field(default_factory=threading.Lock)
    backlog: bytes = b""  # what the client has not taken yet (it stopped reading)
    stalled_since: float | None = None  # monotonic, while the backlog waits


STALL_S = 10.0  # the controller drops an RTDE client that has not read its outputs for this long
RESTART_S = 3.0  # after an emergency stop the RTDE server takes this long to take clients again
SCRIPT_QUIET_S = 0.5  # a program on port 30003 without its closing "end" runs after this long without data


class Emulator:
    def __init__(
        self,
        controller: Controller,
        host: str,
        recipes_out: str | None = None,
        stall_s: float = STALL_S,
        restart_s: float = RESTART_S,
    ) -> None:
        self.controller, self.host, self.recipes_out = controller, host, recipes_out
        self.stall_s, self.restart_s = stall_s, restart_s
        self.refuse_until = 0.0  # monotonic: RTDE refuses clients until then (restarting after an e-stop)
        self.connections: list[RtdeConnection] = []
        self.recipes_seen: list[tuple[str, list[str]]] = []  # ('O' | 'I', names), for the contract test
        self._stop = threading.Event()
        self._listeners: list[socket.socket] = []
        self._served: set[socket.socket] = set()  # every open connection, closed on stop
        self._threads: list[threading.Thread] = []

    # --- lifecycle ----------------------------------------------------------------------------------

    def start(self) -> None:
        for port, handler in (
            (RTDE_PORT, self._rtde),
            (DASHBOARD_PORT, self._dashboard),
            (SCRIPT_PORT, self._script),
        ):
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind((self.host, port))
            s.listen(8)
            self._listeners.append(s)
            self._spawn(self._accept, s, handler)
        self._spawn(self._ticks)

    def stop(self) -> None:
        self._stop.set()
        for s in self._listeners:
            s.close()
        for sock in list(self._served):
            sock.close()

    def _spawn(self, target: Callable[..., None], *args: object) -> None:
        t = threading.Thread(target=target, args=args, daemon=True)
        t.start()
        self._threads.append(t)

    def _accept(self, listener: socket.socket, handler: Handler) -> None:
        while not self._stop.is_set():
            try:
                sock, addr = listener.accept()
            except OSError:
                return
            if handler == self._rtde and time.monotonic() < self.refuse_until:
                sock.close()  # restarting after an emergency stop: the client must try again later
                continue
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            # a controller's buffers, not loopback's megabytes: a client that stops reading shows soon
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 32768)
            self._spawn(self._serve, handler, sock, f"{addr[0]}:{addr[1]}")

    def _serve(self, handler: Handler, sock: socket.socket, peer: str) -> None:
        self._served.add(sock)
        try:
            handler(sock, peer)
        except (OSError, ConnectionError, struct.error) as exc:
            log.info("%s: connection ended (%s)", peer, exc)
        except Exception:  # a bad request ends its connection, never the emulator
            log.exception("%s: request failed; closing the connection", peer)
        finally:
            self._served.discard(sock)
            sock.close()

    # --- RTDE ---------------------------------------------------------------------------------------

    def _rtde(self, sock: socket.socket, peer: str) -> None:
        conn = RtdeConnection(sock, peer)
        self.connections.append(conn)
        try:
            while True:
                kind, payload = _read_frame(sock)
                reply = self._rtde_request(conn, kind, payload)
                if reply is not None:
                    with conn.send_lock:
                        sock.sendall(reply)
        finally:
            conn.started = False
            self.connections.remove(conn)

    def _rtde_request(self, conn: RtdeConnection, kind: int, payload: bytes) -> bytes | None:
        if kind == rtde.V:
            return rtde.frame(rtde.V, b"\x01")
        if kind == rtde.v:
            return rtde.frame(rtde.v, struct.pack(">IIII", *CONTROLLER_VERSION))
        if kind == rtde.O:
            (freq,) = struct.unpack_from(">d", payload)
            names = [n for n in payload[8:].decode().split(",") if n]
            types = [rtde.type_of(n) for n in names]
            self._seen("O", names)
            conn.output_id = len(conn.inputs) + 1 if conn.outputs is None else conn.output_id
            conn.outputs = Recipe(names, types, rtde.recipe_struct(types))
            conn.control = "output_int_register_0" in names and "actual_q" not in names
            conn.every = max(1, round(1.0 / (freq * TICK_S))) if freq > 0 else 1
            return rtde.frame(rtde.O, bytes([conn.output_id]) + ",".join(types).encode())
        if kind == rtde.I:
            names = [n for n in payload.decode().split(",") if n]
            types = [rtde.type_of(n) for n in names]
            self._seen("I", names)
            rid = len(conn.inputs) + 1
            conn.inputs[rid] = Recipe(names, types, rtde.recipe_struct(types))
            return rtde.frame(rtde.I, bytes([rid]) + ",".join(types).encode())
        if kind == rtde.S:
            conn.started = True
            return rtde.frame(rtde.S, b"\x01")
        if kind == rtde.P:
            conn.started = False
            return rtde.frame(rtde.P, b"\x01")
        if kind == rtde.U:
            recipe = conn.inputs.get(payload[0])
            if recipe is None:
                return None
            values = rtde.regroup(recipe.types, recipe.packer.unpack_from(payload, 1))
            self.controller.write_inputs(
                payload[0], dict(zip(recipe.names, values, strict=True)), conn.control
            )
            return None
        return None

    def _seen(self, kind: str, names: list[str]) -> None:
        """Recorded before the reply goes out, so a client that has connected has been recorded."""
        self.recipes_seen.append((kind, names))
        if self.recipes_out is not None:
            atomic_write(self.recipes_out, json.dumps(self.recipes_seen).encode())

    def _ticks(self) -> None:
        tick, start = 0, time.monotonic()
        c = self.controller
        while not self._stop.is_set():
            tick += 1
            delay = start + tick * TICK_S - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            c.tick()
            for conn in list(self.connections):
                if not conn.started or conn.outputs is None or tick % conn.every:
                    continue
                r = conn.outputs
                with c.lock:
                    values = [_or_zero(c.value(n), t) for n, t in zip(r.names, r.types, strict=True)]
                data = rtde.frame(rtde.U, bytes([conn.output_id]) + r.packer.pack(*rtde.flatten(values)))
                self._send(conn, data)

    def _send(self, conn: RtdeConnection, data: bytes) -> None:
        """One output package, without waiting on a client that stopped reading (a blocking send once
        stalled every other client): what it has not taken waits, newer packages are dropped meanwhile,
        and after ``stall_s`` the controller drops the client, as a real one does after about 10 s."""
        with conn.send_lock:
            try:
                if not conn.backlog:
                    conn.backlog = data
                n = conn.sock.send(conn.backlog, socket.MSG_DONTWAIT)
                conn.backlog = conn.backlog[n:]
            except BlockingIOError:
                pass
            except OSError:
                conn.started = False
                return
            if not conn.backlog:
                conn.stalled_since = None
                return
            now = time.monotonic()
            conn.stalled_since = conn.stalled_since or now
            if now - conn.stalled_since >= self.stall_s:
                log.warning("%s: not read for %.0f s: dropped", conn.peer, now - conn.stalled_since)
                self.controller.log.append(f"RTDE client {conn.peer} dropped: it stopped reading")
                conn.started = False
                with contextlib.suppress(OSError):
                    conn.sock.shutdown(socket.SHUT_RDWR)

    def emergency_stop(self) -> None:
        """The e-stop pressed and released: the program stops, and the RTDE server takes no new client
        for ``restart_s`` (a reconnect right after fails: try again with back-off)."""
        self.controller.emergency_stop()
        self.refuse_until = time.monotonic() + self.restart_s

    # --- dashboard and script -----------------------------------------------------------------------

    def _dashboard(self, sock: socket.socket, peer: str) -> None:
        sock.sendall(b"Connected: Universal Robots Dashboard Server\n")
        buf = b""
        while True:
            data = sock.recv(4096)
            if not data:
                return
            buf += data
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                sock.sendall(self.controller.dashboard(line.decode(errors="replace")).encode() + b"\n")

    def _script(self, sock: socket.socket, peer: str) -> None:
        """Port 30003 as a real controller keeps it: open for as long as the client keeps it, and every
        program that comes on it runs. ur_rtde opens it early in its set-up and uploads at the end, after
        some 25 round trips on RTDE (0.1–0.2 s here): a connection closed after 0.5 s without data lost
        the upload whenever a loaded host made the set-up longer ("Failed to start control script")."""
        buf = b""
        while True:
            sock.settimeout(SCRIPT_QUIET_S if buf else None)
            try:
                data: bytes | None = sock.recv(65536)
            except TimeoutError:
                data = None  # the client went quiet within a program that never ended: run what came
            programs, buf = take_programs(buf + (data or b""), flush=not data)
            for text in programs:
                self.controller.load_script(text.decode(errors="replace"))
            if data == b"":
                return


def take_programs(buf: bytes, flush: bool) -> tuple[list[bytes], bytes]:
    """The whole programs at the head of what came on port 30003, each up to its top-level ``end`` line
    (``def rtde_control(): … end``), and the rest; with ``flush`` (the client closed, or went quiet) the
    rest is a program too, as the controller runs a bare line of script."""
    programs, start, pos = [], 0, 0
    while (nl := buf.find(b"\n", pos)) >= 0:
        if buf[pos:nl].rstrip() == b"end":
            programs.append(buf[start : nl + 1])
            start = nl + 1
        pos = nl + 1
    rest = buf[start:]
    if flush:
        if rest.strip():
            programs.append(rest)
        rest = b""
    return programs, rest


def _or_zero(value: object, kind: str) -> object:
    if value is not None:
        return value
    fmt = rtde.FORMATS[kind]
    n = int(fmt[0]) if fmt[0].isdigit() else 1
    zero = 0.0 if fmt[-1] == "d" else (False if fmt[-1] == "?" else 0)
    return [zero] * n if n > 1 else zero


def _read_frame(sock: socket.socket) -> tuple[int, bytes]:
    head = _read_exact(sock, rtde.HEADER.size)
    size, kind = rtde.HEADER.unpack(head)
    return kind, _read_exact(sock, size - rtde.HEADER.size)


def _read_exact(sock: socket.socket, n: int) -> bytes:
    buf = bytearray()
    while len(buf) < n:
        data = sock.recv(n - len(buf))
        if not data:
            raise ConnectionError("closed by the client")
        buf += data
    return bytes(buf)
