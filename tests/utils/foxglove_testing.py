"""A Foxglove WebSocket viewer for tests: connect as the Foxglove app does (subprotocol foxglove.sdk.v1), wait for a
topic to be advertised, subscribe, and decode the protobuf messages with the schema the server advertised."""

from __future__ import annotations

import base64
import json
import struct
import time
from typing import Any

MESSAGE_DATA = 0x01  # the server's binary opcode for a subscribed channel's message


class Viewer:
    def __init__(self, port: int, timeout: float = 10.0) -> None:
        from websockets.sync.client import connect

        self.timeout = timeout
        self.socket = connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"], open_timeout=timeout)
        self.channels: dict[str, dict[str, Any]] = {}  # topic -> advertised channel
        self.subscriptions: dict[int, dict[str, Any]] = {}  # subscription id -> channel

    def close(self) -> None:
        self.socket.close()

    def _receive(self, deadline: float) -> Any:
        message = self.socket.recv(timeout=max(0.01, deadline - time.monotonic()))
        if isinstance(message, str):
            control = json.loads(message)
            if control.get("op") == "advertise":
                for channel in control["channels"]:
                    self.channels[channel["topic"]] = channel
            return control
        return message

    def wait_for_topic(self, topic: str) -> dict[str, Any]:
        deadline = time.monotonic() + self.timeout
        while topic not in self.channels:
            self._receive(deadline)
        return self.channels[topic]

    def subscribe(self, topic: str) -> int:
        channel = self.wait_for_topic(topic)
        subscription = len(self.subscriptions) + 1
        self.subscriptions[subscription] = channel
        self.socket.send(
            json.dumps({"op": "subscribe", "subscriptions": [{"id": subscription, "channelId": channel["id"]}]})
        )
        return subscription

    def next_message(self, subscription: int) -> Any:
        """The next message of that subscription, decoded (a protobuf message of the advertised schema)."""
        deadline = time.monotonic() + self.timeout
        while True:
            message = self._receive(deadline)
            if isinstance(message, bytes) and message[0] == MESSAGE_DATA:
                got, _ = struct.unpack_from("<IQ", message, 1)
                if got == subscription:
                    return decode(self.subscriptions[subscription], message[13:])


def decode(channel: dict[str, Any], payload: bytes) -> Any:
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    files = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
    pool = descriptor_pool.DescriptorPool()
    for file in files.file:
        pool.Add(file)
    cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"]))
    return cls.FromString(payload)
