"""Optional API keys: when any are configured, every route but liveness and readiness needs one.

Keys come from RAFD_API_KEYS (comma-separated) and/or the file RAFD_API_KEYS_FILE (one per line, # comments),
each "KEY" or "NAME:KEY"; the name (default: "key-" + 8 hex digits of the key's sha256) is what logs and stream
namespaces use, so the key itself is never stored or echoed. A request presents its key as `X-API-Key: KEY` or
`Authorization: Bearer KEY`; it is compared with every configured key in constant time (hmac.compare_digest of
sha256 digests, no early exit). Each key has its own stream namespace (service/pipeline/streams.py): another key's
`car-7` is another stream, and nothing tells a key whether another key's id exists.
"""

from __future__ import annotations

import hashlib
import hmac
import re
from dataclasses import dataclass
from pathlib import Path

from starlette.types import ASGIApp, Receive, Scope, Send

from service.http.errors import send_refusal
from service.settings import Settings

KEY_PATTERN = re.compile(r"[A-Za-z0-9._~+/=-]{16,256}")
NAME_PATTERN = re.compile(r"[A-Za-z0-9._-]{1,64}")
# Probes of an orchestrator or load balancer carry no key.
OPEN_PATHS = frozenset({"/health/live", "/health/ready"})
CALLER = "api_key_name"  # scope["state"] key holding the caller's key name


def _digest(key: str) -> bytes:
    return hashlib.sha256(key.encode("utf-8", "surrogateescape")).digest()


@dataclass(frozen=True)
class ApiKeys:
    keys: tuple[tuple[str, bytes], ...] = ()  # (name, sha256 of the key)

    @property
    def enabled(self) -> bool:
        return bool(self.keys)

    @property
    def count(self) -> int:
        return len(self.keys)

    def identify(self, presented: str | None) -> str | None:
        """The name of the key presented, or None; the same work whichever key (if any) matches."""
        if not presented:
            return None
        digest = _digest(presented)
        found = None
        for name, expected in self.keys:
            if hmac.compare_digest(digest, expected) and found is None:
                found = name
        return found


def parse_key(text: str, where: str) -> tuple[str, str]:
    """'KEY' or 'NAME:KEY' -> (name, key); ValueError naming `where` when malformed."""
    name, _, key = text.rpartition(":")
    if not KEY_PATTERN.fullmatch(key):
        raise ValueError(f"{where}: an API key must be 16-256 characters from A-Z a-z 0-9 . _ ~ + / = -")
    if name and not NAME_PATTERN.fullmatch(name):
        raise ValueError(f"{where}: a key name must be 1-64 characters from A-Z a-z 0-9 . _ -")
    return name or "key-" + hashlib.sha256(key.encode()).hexdigest()[:8], key


def load_api_keys(settings: Settings) -> ApiKeys:
    """All configured keys; ValueError on a malformed entry, a missing file or a repeated key or name."""
    entries = [
        parse_key(secret.get_secret_value().strip(), f"RAFD_API_KEYS entry {i + 1}")
        for i, secret in enumerate(settings.api_keys)
    ]
    if settings.api_keys_file is not None:
        path = Path(settings.api_keys_file)
        try:
            lines = path.read_text().splitlines()
        except OSError as exc:
            raise ValueError(f"RAFD_API_KEYS_FILE={path} cannot be read: {exc.strerror}") from exc
        for number, line in enumerate(lines, 1):
            line = line.strip()
            if line and not line.startswith("#"):
                entries.append(parse_key(line, f"{path} line {number}"))
    names = [name for name, _ in entries]
    if len(set(names)) != len(names) or len({key for _, key in entries}) != len(entries):
        raise ValueError("API keys and key names must be unique")
    return ApiKeys(tuple((name, _digest(key)) for name, key in entries))


def presented_key(scope: Scope) -> str | None:
    headers = dict(scope.get("headers", ()))
    key = headers.get(b"x-api-key")
    if key is None:
        scheme, _, token = headers.get(b"authorization", b"").partition(b" ")
        key = token.strip() if scheme.lower() == b"bearer" else None
    return key.decode("latin-1") if key else None


class ApiKeyMiddleware:
    """401 before anything is read when keys are configured and none valid is presented (missing_api_key without a
    key, invalid_api_key with a wrong one); else records the key's name."""

    def __init__(self, app: ASGIApp, keys: ApiKeys) -> None:
        self.app = app
        self.keys = keys

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or not self.keys.enabled or scope["path"] in OPEN_PATHS:
            await self.app(scope, receive, send)
            return
        presented = presented_key(scope)
        name = self.keys.identify(presented)
        if name is None:
            # Two answers, one for each mistake, and neither says anything about the keys that exist.
            if presented:
                code, message = "invalid_api_key", "the API key sent is not valid for this service"
            else:
                code, message = (
                    "missing_api_key",
                    "this service requires an API key: send it as 'X-API-Key: KEY' or 'Authorization: Bearer KEY'",
                )
            # A body still arriving gets its `Connection: close` from the server's protocol
            # (service/http/head_limits.py).
            await send_refusal(send, code, message, headers={"WWW-Authenticate": 'Bearer realm="rafd"'})
            return
        scope.setdefault("state", {})[CALLER] = name
        await self.app(scope, receive, send)


def caller_of(scope: Scope) -> str | None:
    """The key name the request was authenticated with (None without API keys)."""
    caller: str | None = scope.get("state", {}).get(CALLER)  # the ASGI scope's values are Any
    return caller
