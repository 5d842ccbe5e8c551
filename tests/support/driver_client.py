"""The RCM agent's side of an rcm_driver's TCP port (CONTRACTS §4), for the tests of rcm_driver."""

import json
import socket


class AgentClient:
    """The RCM agent's side of the driver's TCP port: JSON lines out, JSON lines in."""

    def __init__(self, port):
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=10)
        self.buffer = b""

    def send(self, obj_or_bytes):
        data = obj_or_bytes if isinstance(obj_or_bytes, bytes) else (json.dumps(obj_or_bytes) + "\n").encode()
        self.sock.sendall(data)

    def announce(self, command, name):
        self.send({"rcm_d_cmd": command, "r_name": name})

    def read_line(self, timeout=10.0):
        """The next line as a dict; a blocking read with a deadline (the socket timeout)."""
        self.sock.settimeout(timeout)
        while b"\n" not in self.buffer:
            chunk = self.sock.recv(4096)
            assert chunk, "the driver closed the connection"
            self.buffer += chunk
        line, self.buffer = self.buffer.split(b"\n", 1)
        return json.loads(line)

    def at_eof(self, timeout=10.0):
        self.sock.settimeout(timeout)
        try:
            return self.sock.recv(4096) == b""
        except ConnectionResetError:
            return True

    def close(self):
        self.sock.close()
