"""A robot (or server VM) agent at the protocol level, as an attacker would write one: a real TCP connection from a
chosen source address to a real master, speaking the frames of docs/PROTOCOL.md from a thread of the test.

``FakeAgent(port, name, source, answers={op: fn(body) -> answer body}, robot=True)``: ``hello()`` connects, says
hello and returns the master's answer frame (``kind`` ``res`` or ``err``); from then on a thread answers every
request of the master: ``heartbeat`` with ``{}``, an op in ``answers`` with what its function returns, any other
op with ``{}``. ``requests`` records ``(op, body)`` of each. ``close()`` ends the connection and the thread (also
when the test fails: use it as a context manager).
"""

import json
import socket
import struct
import threading

MASTER = "127.0.0.1"


class FakeAgent:

    def __init__(self, port, name, source, answers=None, robot=True, master=MASTER):
        self.port = port
        self.name = name
        self.source = source
        self.answers = dict(answers or {})
        self.robot = robot
        self.master = master
        self.requests = []
        self.sock = None
        self.thread = None
        self.closed = threading.Event()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def _send(self, message):
        data = json.dumps(message).encode()
        self.sock.sendall(struct.pack("!I", len(data)) + data)

    def _read_exactly(self, size):
        data = b""
        while len(data) < size:
            chunk = self.sock.recv(size - len(data))
            if not chunk:
                raise ConnectionError("the master closed the connection")
            data += chunk
        return data

    def _read(self):
        size = struct.unpack("!I", self._read_exactly(4))[0]
        return json.loads(self._read_exactly(size))

    def hello(self, timeout=10.0):
        """Connect and say hello; the master's answer frame."""
        self.sock = socket.create_connection((self.master, self.port), timeout=timeout,
                                             source_address=(self.source, 0))
        body = {"name": self.name, "address": self.source, "robot": self.robot, "version": 1}
        self._send({"v": 1, "id": 1, "kind": "req", "op": "hello", "body": body})
        while True:
            frame = self._read()
            if frame.get("kind") in ("res", "err") and frame.get("id") == 1:
                break
            self._answer(frame)                     # a heartbeat may come before the answer
        if frame["kind"] == "res":
            self.sock.settimeout(None)               # close() shuts the socket down to end the thread
            self.thread = threading.Thread(target=self._serve, name=f"fake-agent-{self.name}", daemon=True)
            self.thread.start()
        return frame

    def _answer(self, frame):
        if frame.get("kind") != "req":
            return
        op, body = frame.get("op"), frame.get("body") or {}
        self.requests.append((op, body))
        answer = self.answers[op](body) if op in self.answers else {}
        self._send({"v": 1, "id": frame["id"], "kind": "res", "op": op, "body": answer})

    def _serve(self):
        while not self.closed.is_set():
            try:
                frame = self._read()
            except (OSError, ValueError, struct.error):
                return
            try:
                self._answer(frame)
            except OSError:
                return

    def ops(self):
        return [op for op, _ in self.requests]

    def close(self):
        self.closed.set()
        if self.sock is not None:
            try:
                self.sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            self.sock.close()
        if self.thread is not None:
            self.thread.join(timeout=5)
