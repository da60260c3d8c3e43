"""Service settings from RAFD_* environment variables (pydantic-settings), cached per process."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, SecretStr, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from rafd.cpu import usable_cpus


class Settings(BaseSettings):
    """Everything an operator may tune; each field reads RAFD_<NAME> (e.g. RAFD_MAX_STREAMS)."""

    # `model_path` would clash with pydantic's protected "model_" namespace without this.
    model_config = SettingsConfigDict(env_prefix="RAFD_", protected_namespaces=(), extra="forbid")

    model_path: Path | None = Field(
        default=None,
        description="ONNX file; None serves the model shipped in the package (rafd.assets.default_onnx()).",
    )
    threads: int = Field(
        default_factory=usable_cpus,
        ge=1,
        description=(
            "Threads of one model run when it runs alone (lowest latency for one stream): the CPUs the container "
            "may use."
        ),
    )
    concurrent_runs: int = Field(
        default_factory=usable_cpus,
        ge=1,
        description=(
            "Model runs executing at once. Runs that overlap get threads // concurrent_runs threads each (a "
            "second compilation of the model), so several streams run side by side instead of contending for one "
            "thread pool; more requests wait. Default: one run per CPU. 1 = one run at a time."
        ),
    )
    runtime: Literal["auto", "onnxruntime", "openvino"] = Field(
        default="auto",
        description=(
            'Inference runtime (rafd.runtime.create_runner): "auto" times every supported runtime and precision on '
            "the model at start-up and keeps the fastest; onnxruntime fp32 is the reference path."
        ),
    )
    precision: Literal["auto", "fp32", "bf16", "int8"] = Field(
        default="auto",
        description=(
            "Inference precision: auto (timed with the runtime at start-up), fp32, bf16 (OpenVINO, CPUs with "
            "avx512_bf16 or AMX) or int8 (OpenVINO on the quantized MODEL.int8.onnx, CPUs with VNNI or AMX). auto "
            "chooses bf16 or int8 only for a model whose accuracy gate (rafd gate) passed for it."
        ),
    )
    foxglove_port: int | None = Field(
        default=None,
        ge=0,
        le=65535,
        description=(
            "The live view (service/pipeline/live.py): publish every answered frame to a Foxglove WebSocket "
            "server on this port (0: any free port, logged), in the MCAP logs' channels, one topic prefix per "
            "stream; off when unset. Needs the `live` extra (foxglove-sdk)."
        ),
    )
    foxglove_host: str = Field(
        default="127.0.0.1",
        description="Interface of the live view's WebSocket server (0.0.0.0 to reach it from other machines).",
    )
    foxglove_queue_frames: int = Field(
        default=32,
        ge=1,
        description=(
            "Answered frames waiting to be published to the live view; beyond it a frame is dropped (counted), "
            "never waited for."
        ),
    )
    foxglove_key: str | None = Field(
        default=None,
        min_length=1,
        max_length=64,
        description=(
            "With API keys: the NAME of the one key whose streams the live view publishes (required then: its "
            "WebSocket has no authentication, so whoever reaches it sees these streams; other keys' streams are "
            "never published). Unset without keys: every stream."
        ),
    )
    max_streams: int = Field(
        default=32,
        ge=1,
        description=(
            "Live streams held at once (streams with an accepted frame; a stream whose frames were all refused or "
            "are still in flight counts toward no cap). A key over its quota or over this cap evicts its OWN "
            "least recently used idle stream, never another key's. Each stream of whole scans holds about 36 MB "
            "(the state of every tile), of model-size crops about 2.4 MB: size the memory for this many."
        ),
    )
    max_streams_per_key: int | None = Field(
        default=None,
        ge=1,
        description=(
            "Live streams of one API key (its namespace: with keys, A's `car-7` and B's `car-7` are different "
            "streams). None: max_streams // the number of keys configured (all of max_streams without keys), so "
            "that no key can take another's room."
        ),
    )
    stream_ttl_s: float = Field(
        default=300.0,
        gt=0,
        description="A stream idle for longer than this is forgotten (its next frame starts a new buffer).",
    )
    stream_gap_restart_s: float = Field(
        default=1.0,
        ge=0,
        description=(
            "The MAXIMUM timestamp gap a stream's chain survives: a frame more than this many seconds (of its own "
            "timestamps) after the stream's last accepted frame starts a new buffer and odometry world frame, and "
            'its answer says `stream_restarted: "gap"`. A replica that held a stream, lost it to another in a '
            "failover and gets it back must not stack the new frame on frames from before. 1.0 s is 4 periods of "
            "a 4 Hz radar: one or two dropped frames (gaps of 0.5, 0.75 s) keep the chain. 0 turns the rule off."
        ),
    )
    max_request_bytes: int = Field(
        default=5 * 512 * 1024,
        ge=1024,
        description=(
            "Request bodies above this many bytes get 413. A 1152 px RADIATE scan is ~0.65 MB as a PNG (~0.9 MB "
            "in base64); the worst a valid one can be (incompressible pixels, 64 KiB of ancillary chunks) is 1.40 "
            "MB, 1.87 MB in base64: 2.5 MiB leaves 40% headroom over that."
        ),
    )
    max_inflight_requests: int = Field(
        default=64,
        ge=1,
        description=(
            "/detect requests whose body has arrived, running at once (each holds a body of up to "
            "max_request_bytes); beyond it 503 + Retry-After. A request counts here only once its body has "
            "arrived: a slow body never holds a slot the model needs."
        ),
    )
    max_receiving_requests: int = Field(
        default=64,
        ge=1,
        description=(
            "/detect requests receiving their body at once (their own pool, apart from max_inflight_requests); "
            "beyond it 503 + Retry-After before the body is read."
        ),
    )
    max_requests_per_client: int = Field(
        default=16,
        ge=1,
        description=(
            "Unfinished requests of one client (by address; behind a trusted proxy, its X-Forwarded-For) at once, "
            "on every route but the health probes; beyond it 429 `too_many_client_requests` before anything else "
            "is read."
        ),
    )
    stream_queue_limit: int = Field(
        default=8,
        ge=1,
        description="Frames of one stream queued at once (they run in arrival order); beyond it 429 + Retry-After.",
    )
    body_timeout_s: float = Field(
        default=30.0,
        gt=0,
        description=(
            "Seconds a request's body may take to arrive (a frame holds its stream's place while it does); beyond "
            "it 408."
        ),
    )
    min_body_bytes_per_s: int = Field(
        default=64 * 1024,
        ge=0,
        description=(
            "Slowest body accepted: after its first body_rate_grace_s seconds, a body must have kept up this many "
            "bytes per second on average since its request arrived, else 408 `body_too_slow` (counted by the "
            "refusal penalty). 0 turns the rate check off (body_timeout_s still applies)."
        ),
    )
    body_rate_grace_s: float = Field(
        default=1.0,
        ge=0,
        description=(
            "Seconds from a request's arrival before min_body_bytes_per_s is checked (a body's first bytes may be "
            "slow to start)."
        ),
    )
    max_request_line_bytes: int = Field(
        default=8 * 1024,
        ge=256,
        description=(
            "Bytes of a request's first line, checked by the HTTP server before anything reaches the app "
            "(service/http/head_limits.py); 414 beyond."
        ),
    )
    max_headers: int = Field(
        default=100,
        ge=8,
        description=(
            "Header fields a request's head may carry, checked by the HTTP server before anything reaches the app "
            "(service/http/head_limits.py); 431 beyond."
        ),
    )
    max_header_bytes: int = Field(
        default=32 * 1024,
        ge=1024,
        description="Total bytes of a request's header fields (service/http/head_limits.py); 431 beyond.",
    )
    header_timeout_s: float = Field(
        default=10.0,
        gt=0,
        description=(
            "Seconds a request's head may take from the connection's first byte (on a kept-alive connection, from "
            "the request's first byte); 408 `request_header_timeout` beyond (service/http/head_limits.py)."
        ),
    )
    order_hold_s: float = Field(
        default=0.5,
        ge=0,
        description=(
            "A frame named only in its body is placed in its stream by its arrival; a frame of the same client "
            "that arrived after it waits, at most this many seconds, before its turn while that body is still "
            "being read and parsed."
        ),
    )
    shutdown_timeout_s: float = Field(
        default=10.0,
        ge=0,
        description="On SIGTERM, seconds the server waits for requests in progress before it drops them and exits.",
    )
    keep_alive_timeout_s: float = Field(
        default=75.0,
        gt=0,
        description=(
            "Seconds an idle kept-alive connection stays open (uvicorn's timeout_keep_alive; its own default is 5 "
            "s). It must exceed the keep-alive of any proxy in front (deploy/nginx.conf's upstream "
            "`keepalive_timeout` 60 s, ingress-nginx's `upstream-keepalive-timeout` 60 s): the proxy then always "
            "closes an idle connection first and never sends a request on one the service is closing at that "
            "moment (a 502 of a frame the proxy cannot retry)."
        ),
    )
    parse_workers: int = Field(
        default=1,
        ge=1,
        description=(
            "Threads of the parse stage: JSON bodies are parsed there (off the event loop), after a bounded "
            "structural check. Each stage (parse, decode, odometry, model) has its own threads and queue limit."
        ),
    )
    parse_queue_limit: int = Field(
        default=16,
        ge=0,
        description=(
            "JSON bodies waiting for the parse stage beyond the running ones; a full queue answers 503 + Retry- "
            "After at once."
        ),
    )
    decode_workers: int = Field(
        default=1,
        ge=1,
        description="Threads of the decode stage (a scan's PNG inflated and made the model's input).",
    )
    decode_queue_limit: int = Field(
        default=16,
        ge=0,
        description=(
            "Scans waiting for the decode stage beyond the running ones; a full queue answers 503 + Retry-After "
            "at once."
        ),
    )
    odometry_workers: int = Field(
        default=1,
        ge=1,
        description="Threads of the odometry stage (a frame's pose estimated when its request carries none).",
    )
    odometry_queue_limit: int = Field(
        default=16,
        ge=0,
        description=(
            "Frames waiting for the odometry stage beyond the running ones; a full queue answers 503 + Retry- "
            "After at once."
        ),
    )
    model_queue_limit: int = Field(
        default=16,
        ge=0,
        description=(
            "Model steps waiting beyond the concurrent_runs running ones (the runner shares the threads out among "
            "those); a full queue answers 503 + Retry-After at once."
        ),
    )
    retry_after_s: int = Field(
        default=1,
        ge=1,
        description="Seconds a 503 / 429 asks the client to wait (the Retry-After header).",
    )
    refusal_penalty_s: float = Field(
        default=0.5,
        ge=0.0,
        le=30.0,
        description=(
            "A client refused more than REFUSAL_PENALTY_AFTER times within a second (invalid or oversized bodies "
            "and images, refused fields, slow bodies, its own request limit: service/http/errors.py "
            "PENALISED_CODES) gets each further refusal only after REFUSAL_PENALTY_S seconds "
            "(service/http/penalty.py); 0 turns this off."
        ),
    )
    refusal_penalty_after: int = Field(
        default=3,
        ge=0,
        description="Refusals of one client within a second before each further one waits refusal_penalty_s.",
    )
    api_keys: Annotated[list[SecretStr], NoDecode] = Field(
        default_factory=list,
        description=(
            'API keys, "KEY" or "NAME:KEY", comma-separated (e.g. RAFD_API_KEYS=car-fleet:4f9c...); empty: no keys.'
        ),
    )
    api_keys_file: Path | None = Field(
        default=None,
        description='A file of API keys, one "KEY" or "NAME:KEY" per line (# comments); read once at start-up.',
    )

    @field_validator("api_keys", mode="before")
    @classmethod
    def _split_keys(cls, value: object) -> object:
        if isinstance(value, str):
            return [key.strip() for key in value.split(",") if key.strip()]
        return value

    buffer_length: int | None = Field(
        default=None,
        ge=1,
        description="Frames per stream buffer; must equal the model's num_frames (None: take it from the model).",
    )
    score_threshold: float | None = Field(
        default=None,
        ge=0.0,
        le=1.0,
        description=(
            "Detections with a score below this are dropped from the answer, at every range. None: the model's "
            'operating threshold (ONNX metadata "operating_threshold", chosen on validation data by `rafd-eval '
            '--calibrate`, and "operating_threshold_far" for detections far from the radar, by `--calibrate-far`), '
            "else 0.3."
        ),
    )
    detect_range_m: float | None = Field(
        default=None,
        gt=0.0,
        le=1000.0,
        description=(
            "Detect only within this distance of the radar (metres); None: over the whole posted scan. The model's "
            "input is stepped as tiles over the smallest square holding that disc (rafd.runtime.view): fewer tiles, "
            "less CPU per frame; a value within the model's own crop (22 m for the shipped model) is one tile, the "
            "cheapest."
        ),
    )
    tracks_answer_tentative: bool = Field(
        default=True,
        description=(
            "Answer the boxes of tracks not yet confirmed (detected in one scan only so far). False drops a lone "
            "detection until its vehicle is seen again: fewer false positives, a scan later for every new vehicle "
            "(docs/tracking.md)."
        ),
    )
    tracks_answer_coasting: bool = Field(
        default=False,
        description=(
            "Also answer a confirmed track's predicted box for up to 3 scans without a detection (status coasting, "
            "its score decayed), so a vehicle missed in one scan stays in the answer."
        ),
    )
    native_max_azimuths: int = Field(
        default=400,
        ge=100,
        le=4096,
        description=(
            "Native scans (Oxford / Boreas polar PNGs) accepted: at most this many azimuth rows (with "
            "native_max_range_bins), checked from the PNG's header before anything is inflated (the documented "
            "sensors have 400). Raise them for another sensor; the inflate and the conversion grow with rows x bins "
            '(docs/api.md, "Image").'
        ),
    )
    native_max_range_bins: int = Field(
        default=6848,
        ge=256,
        le=65536,
        description=(
            "Range bins of a native scan accepted (see native_max_azimuths): 3768 for Oxford's CTS350-X, at most "
            "6848 for Boreas' CIR304-H."
        ),
    )
    min_frame_gap_s: float = Field(
        default=0.01,
        ge=0.0,
        le=10.0,
        description=(
            "Frames of a stream at least this many seconds apart (the last accepted frame to the next; 422 "
            "`timestamp_gap_too_small` closer): no radar scans faster than 100 Hz (Navtech: 4 Hz), and a gap of "
            "1e-300 s would make every speed meaningless."
        ),
    )
    max_speed_mps: float = Field(
        default=70.0,
        ge=0.0,
        le=1000.0,
        description=(
            "A frame whose pose (the request's, or odometry's) moved faster than this since the stream's last "
            "accepted frame is refused (422 `implausible_motion`) rather than bending the chain: 70 m/s is 252 "
            "km/h, beyond a road vehicle. 0 turns the check off."
        ),
    )


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """The process-wide settings, read from the environment once."""
    return Settings()
