"""HTTP hardening and transport: the server and its head limits, API keys, intake, body size, the error shape."""
