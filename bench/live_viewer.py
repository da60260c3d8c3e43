"""A Foxglove viewer for benchmarks: connects to the live view's WebSocket server (subprotocol foxglove.sdk.v1),
subscribes to every channel as it is advertised and reads every message, so the server does the work a real viewer
makes it do. Needs the `websockets` package (the dev extra)."""

from __future__ import annotations

import json
import threading
import time


class SubscribeAll:
    """A thread subscribed to every advertised channel until stop(); counts the messages received."""

    def __init__(self, port: int, host: str = "127.0.0.1", timeout: float = 10.0) -> None:
        from websockets.sync.client import connect
        from websockets.typing import Subprotocol

        self.socket = connect(
            f"ws://{host}:{port}", subprotocols=[Subprotocol("foxglove.sdk.v1")], open_timeout=timeout
        )
        self.messages = 0
        self._stop = threading.Event()
        self._subscribed: set[int] = set()
        self._thread = threading.Thread(target=self._run, name="live-viewer", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                message = self.socket.recv(timeout=0.2)
            except TimeoutError:
                continue
            except Exception:  # the server went away
                return
            if isinstance(message, bytes):
                self.messages += 1
                continue
            control = json.loads(message)
            if control.get("op") == "advertise":
                new = [c["id"] for c in control["channels"] if c["id"] not in self._subscribed]
                self._subscribed.update(new)
                if new:
                    subscriptions = [{"id": channel, "channelId": channel} for channel in new]
                    self.socket.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))

    def stop(self) -> int:
        """Stop reading -> the messages received."""
        self._stop.set()
        self._thread.join(timeout=5.0)
        self.socket.close()
        time.sleep(0)  # let the socket's own thread finish
        return self.messages
