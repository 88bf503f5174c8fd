#!/usr/bin/env python3
"""Drive a world model step by step over `dojo serve`'s WebSocket (/ws), standard library only.

    python3 examples/step_client.py --url ws://127.0.0.1:8080/ws --steps 8 --out frames/

This is the loop a policy in another process runs for closed-loop evaluation: send one step's
actions, get that step's frames back, decide the next actions. The CLI below scripts a sweep of
the first joint around the start command; `WorldModelSession` is the part to reuse:

    s = WorldModelSession("ws://127.0.0.1:8080/ws", token=None)
    ready = s.start()                    # {"actions_per_step": 4, "command": [...], ...}; s.start_frames
    frames = s.step([ready["command"]] * ready["actions_per_step"])  # [{"seq", "step", "jpeg", ...}]
    s.close()

The WebSocket client is a minimal RFC 6455 one: no extensions, no subprotocols.
"""
import argparse, base64, hashlib, json, math, os, socket, ssl, statistics, struct, sys, time, urllib.parse

GUID = b"258EAFA5-E914-47DA-95CA-C5AB0DC85B11"  # RFC 6455 4.2.2: the accept key's suffix
TEXT, BINARY, CLOSE, PING, PONG = 0x1, 0x2, 0x8, 0x9, 0xA


def _xor(data, mask):
    """RFC 6455 masking: XOR with the 4-byte key repeated, as one big integer (fast for MBs)."""
    key = (mask * (len(data) // 4 + 1))[: len(data)]
    return (int.from_bytes(data, "big") ^ int.from_bytes(key, "big")).to_bytes(len(data), "big")


class WorldModelError(Exception):
    """The server answered with {"type": "error"}, or the connection broke."""


class ConnectionClosed(WorldModelError):
    """The server closed the connection (a policy evaluation does when it is done with the policy)."""


class WebSocket:
    def __init__(self, url, headers=None, insecure=False, timeout=300):
        u = urllib.parse.urlsplit(url)
        if u.scheme not in ("ws", "wss"):
            raise WorldModelError(f"url must be ws:// or wss://, got {url!r}")
        port = u.port or (443 if u.scheme == "wss" else 80)
        sock = socket.create_connection((u.hostname, port), timeout=timeout)
        if u.scheme == "wss":
            ctx = ssl.create_default_context()
            if insecure:  # a self-signed certificate (`serve --tls-cert`): skip verification
                ctx.check_hostname, ctx.verify_mode = False, ssl.CERT_NONE
            sock = ctx.wrap_socket(sock, server_hostname=u.hostname)
        self.sock, self.buf = sock, bytearray()  # bytes received and not yet parsed
        # The upgrade request: a random key the server must hash into Sec-WebSocket-Accept.
        key = base64.b64encode(os.urandom(16)).decode()
        lines = [f"GET {u.path or '/'}{'?' + u.query if u.query else ''} HTTP/1.1",
                 f"Host: {u.hostname}:{port}", "Upgrade: websocket", "Connection: Upgrade",
                 f"Sec-WebSocket-Key: {key}", "Sec-WebSocket-Version: 13"]
        lines += [f"{k}: {v}" for k, v in (headers or {}).items()]
        sock.sendall(("\r\n".join(lines) + "\r\n\r\n").encode())
        while b"\r\n\r\n" not in self.buf:
            self._fill()
        head, _, rest = bytes(self.buf).partition(b"\r\n\r\n")
        self.buf = bytearray(rest)  # what follows the headers is already frames
        status, *fields = head.decode("latin-1").split("\r\n")
        fields = {k.strip().lower(): v.strip() for k, v in (f.split(":", 1) for f in fields if ":" in f)}
        if status.split(" ")[1:2] != ["101"]:  # e.g. 401 wrong token, 503 full: show the body
            n = int(fields.get("content-length", 0))
            while len(self.buf) < n:
                self._fill()
            raise WorldModelError(f"handshake refused: {status} {self.buf[:n].decode(errors='replace')}")
        accept = base64.b64encode(hashlib.sha1(key.encode() + GUID).digest()).decode()
        if fields.get("sec-websocket-accept") != accept:
            raise WorldModelError("handshake: wrong Sec-WebSocket-Accept")

    def _fill(self):
        chunk = self.sock.recv(1 << 16)
        if not chunk:
            raise ConnectionClosed("connection closed by the server")
        self.buf += chunk

    def _read(self, n):
        while len(self.buf) < n:
            self._fill()
        out = bytes(self.buf[:n])
        del self.buf[:n]
        return out

    def send(self, opcode, payload):
        """One masked, unfragmented frame (clients must mask: RFC 6455 5.3)."""
        n, head = len(payload), bytes([0x80 | opcode])  # FIN + opcode
        if n < 126:
            head += bytes([0x80 | n])
        elif n < 1 << 16:
            head += bytes([0x80 | 126]) + struct.pack(">H", n)
        else:
            head += bytes([0x80 | 127]) + struct.pack(">Q", n)
        mask = os.urandom(4)
        self.sock.sendall(head + mask + _xor(payload, mask))

    def _frame(self):
        """One frame off the wire: (fin, opcode, payload); 16- and 64-bit lengths."""
        b0, b1 = self._read(2)
        n = b1 & 0x7F
        if n == 126:
            n = struct.unpack(">H", self._read(2))[0]
        elif n == 127:
            n = struct.unpack(">Q", self._read(8))[0]
        mask = self._read(4) if b1 & 0x80 else None  # servers do not mask; accept it anyway
        data = self._read(n)
        return bool(b0 & 0x80), b0 & 0x0F, _xor(data, mask) if mask else data

    def recv(self):
        """The next whole message as (TEXT | BINARY, payload): continuation frames are joined,
        pings answered, a close answered and raised."""
        opcode, parts = None, []
        while True:
            fin, op, data = self._frame()
            if op == PING:  # control frames may come between a message's fragments
                self.send(PONG, data)
            elif op == CLOSE:  # echo the status code back, then give up on this connection
                code = struct.unpack(">H", data[:2])[0] if len(data) >= 2 else 1005
                try:
                    self.send(CLOSE, data[:2])
                except OSError:
                    pass
                self.sock.close()
                reason = data[2:].decode(errors="replace")
                raise ConnectionClosed(f"server closed the connection: {code} {reason}".rstrip())
            elif op in (TEXT, BINARY, 0x0):  # 0x0: continuation of the message in progress
                if op != 0x0:
                    opcode, parts = op, []
                parts.append(data)
                if fin:
                    return opcode, b"".join(parts)
            # PONG and unknown opcodes: ignored

    def close(self, code=1000):
        """Send a close, wait briefly for the server's, and close the socket."""
        try:
            self.send(CLOSE, struct.pack(">H", code))
            self.sock.settimeout(5)
            while self._frame()[1] != CLOSE:  # skip what is still in flight
                pass
        except (OSError, WorldModelError):
            pass
        self.sock.close()


class WorldModelSession:
    """One step-mode session. Frames are dicts: seq, step, client_t, server_ms, jpeg (bytes)."""

    def __init__(self, url, token=None, insecure=False, timeout=300):
        self.ws = WebSocket(url, {"Authorization": f"Bearer {token}"} if token else None, insecure, timeout)
        self.ready, self.start_frames, self.events, self.last_step_done = None, [], [], None

    def _send_json(self, message):
        self.ws.send(TEXT, json.dumps(message, allow_nan=False).encode())  # NaN: ValueError here

    def _next(self):
        """The next message: a dict (text) or a frame dict (binary); an error raises."""
        opcode, payload = self.ws.recv()
        if opcode == TEXT:
            message = json.loads(payload)
            if message.get("type") == "error":
                raise WorldModelError(f"server: {message.get('message')}")
            return message
        magic, seq, step, _, client_t, server_ms = struct.unpack("<4sIIIdd", payload[:32])
        if magic != b"DJF1":
            raise WorldModelError(f"binary message without the DJF1 header: {payload[:4]!r}")
        return {"seq": seq, "step": step, "client_t": client_t, "server_ms": server_ms, "jpeg": payload[32:]}

    def _wait_ready(self):
        """'ready', then the start frame; other texts ("recording", "recorded") go to events."""
        while (m := self._next()).get("type") != "ready":
            self.events.append(m)
        while "jpeg" not in (f := self._next()):
            self.events.append(f)  # a reset ends a recording: "recorded" comes before the frame
        self.ready, self.start_frames = m, [f]
        return m

    def start(self, model=None, episode=None, image_jpeg=None, seed=0):
        """Start (or restart) in step mode; returns the 'ready' message. With image_jpeg the
        session starts from that picture instead of a dataset episode."""
        message = {"type": "start", "mode": "step", "seed": seed}
        message.update({k: v for k, v in (("model", model), ("episode", episode)) if v})
        if image_jpeg is not None:
            self.ws.send(BINARY, image_jpeg)  # the upload comes first, then "image": true
            message["image"] = True
        self._send_json(message)
        return self._wait_ready()

    def step(self, actions):
        """One step: actions_per_step rows (raw commands or 384-d). Returns this step's frames."""
        self._send_json({"type": "step", "actions": actions})
        frames = []
        while True:
            m = self._next()
            if "jpeg" in m:
                (self.start_frames if m["step"] == 0 else frames).append(m)
            elif m.get("type") == "step_done":  # policy evaluation: "done": true ends an episode
                self.last_step_done = m
                return frames
            else:
                self.events.append(m)

    def reset(self):
        """Back to the start frame; returns the new 'ready'."""
        self._send_json({"type": "reset"})
        return self._wait_ready()

    def close(self):
        self.ws.close()


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--url", default="ws://127.0.0.1:8080/ws", help="ws://HOST:PORT/ws or wss://...")
    p.add_argument("--token", help="sent as Authorization: Bearer TOKEN")
    p.add_argument("--insecure", action="store_true", help="wss: accept any certificate (self-signed)")
    p.add_argument("--model", help="model name (default: the server's first)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--episode", help="start episode id (default: the server's first)")
    g.add_argument("--image", help="start from this JPEG instead of an episode")
    p.add_argument("--steps", type=int, default=8)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", help="write every frame (the start frame first) as DIR/frame_00000.jpg ...")
    p.add_argument("--timeout", type=float, default=300, help="seconds to wait for the server")
    a = p.parse_args()
    try:
        image = open(a.image, "rb").read() if a.image else None
        s = WorldModelSession(a.url, a.token, a.insecure, a.timeout)
        ready = s.start(a.model, a.episode, image, a.seed)
        n, command = ready["actions_per_step"], ready.get("command")
        frames, ms = list(s.start_frames), []
        for k in range(a.steps):
            if command:  # raw commands (radians for DojoSim): sweep joint 0 by +-0.2 around the start
                actions = [list(command) for _ in range(n)]
                for i, row in enumerate(actions):
                    row[0] += 0.2 * math.sin((k * n + i) / 6)
            else:  # a model without a raw action space: 384-d rows of zeros
                actions = [[0.0] * 384 for _ in range(n)]
            t0 = time.perf_counter()
            frames += s.step(actions)
            ms.append((time.perf_counter() - t0) * 1000)
        s.close()
        if a.out:
            os.makedirs(a.out, exist_ok=True)
            for i, f in enumerate(frames):
                with open(os.path.join(a.out, f"frame_{i:05d}.jpg"), "wb") as out:
                    out.write(f["jpeg"])
    except WorldModelError as e:
        sys.exit(f"step_client: {e}")
    except (OSError, ValueError, KeyError, struct.error) as e:  # network, TLS, bad JSON, ...
        sys.exit(f"step_client: {type(e).__name__}: {e}")
    print(json.dumps({"steps": a.steps, "frames": len(frames),
                      "ms_per_step_p50": round(statistics.median(ms), 1) if ms else None,
                      "first_seq": frames[0]["seq"] if frames else None,
                      "last_seq": frames[-1]["seq"] if frames else None}))


if __name__ == "__main__":
    main()
