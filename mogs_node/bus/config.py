"""Bus configuration and security: endpoints, topic policies, CURVE keys (see ``mogs_node.bus``)."""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

import zmq
import zmq.auth

from mogs_node import msgs, shm
from mogs_node.errors import BusError, ConfigError


@dataclass(frozen=True)
class CurveConfig:
    """CURVE key files (``zmq.auth`` certificate format) for tcp endpoints."""

    server_public_key: str  # broker's public certificate (clients need it)
    client_secret_key: str = ""  # this client's secret certificate (nodes, tools)
    server_secret_key: str = ""  # broker only
    authorized_keys_dir: str = ""  # broker only: folder of accepted client public certificates

    @staticmethod
    def from_dict(d: dict[str, Any], base_dir: Path | None = None) -> CurveConfig:
        def p(key: str) -> str:
            v = d.get(key, "")
            if not v:
                return ""
            path = Path(v).expanduser()
            if base_dir is not None and not path.is_absolute():
                path = base_dir / path
            return str(path)

        unknown = set(d) - set(_CURVE_KEYS)
        if unknown:
            raise ConfigError(f"bus.curve: unknown key(s) {sorted(unknown)}")
        if not d.get("server_public_key"):
            raise ConfigError("bus.curve.server_public_key is required")
        return CurveConfig(**{k: p(k) for k in _CURVE_KEYS})


@dataclass(frozen=True)
class BusConfig:
    """Where the broker is and how sockets behave."""

    pub_endpoint: str  # broker binds XSUB here; publishers connect
    sub_endpoint: str  # broker binds XPUB here; subscribers connect
    reliable_hwm: int = 100_000  # high-water mark (messages) of reliable topics
    best_effort_hwm: int = 10  # high-water mark of best-effort sockets
    max_message_bytes: int = msgs.DEFAULT_MAX_MESSAGE_BYTES
    linger_ms: int = 2000  # how long closing sockets keep flushing queued messages
    # kernel socket buffers (SO_SNDBUF of senders, SO_RCVBUF of receivers, broker included);
    # 0 = the OS default. Capped by net.core.wmem_max / rmem_max. See docs/architecture.md.
    socket_buffer_bytes: int = 0
    # messages with at least this many bytes of arrays go through shared memory, not the broker,
    # when every peer is on this host (ipc:// endpoints, no CURVE); 0 = never (mogs_node/shm.py)
    shm_min_bytes: int = 256 * 1024
    shm_ring_bytes: int = 32 << 20  # shared memory per publisher and topic (a bounded history)
    curve: CurveConfig | None = None

    @property
    def uses_shm(self) -> bool:
        """Whether large payloads bypass the broker through ``/dev/shm`` on this bus."""
        return (
            self.shm_min_bytes > 0
            and self.curve is None
            and self.pub_endpoint.startswith("ipc://")
            and self.sub_endpoint.startswith("ipc://")
            and shm.shm_available()
        )

    def to_dict(self) -> dict[str, Any]:
        d = {k: getattr(self, k) for k in _ENDPOINT_KEYS + _COUNT_KEYS}
        if self.curve is not None:
            d["curve"] = {k: getattr(self.curve, k) for k in _CURVE_KEYS}
        return d

    @staticmethod
    def from_dict(d: dict[str, Any], base_dir: Path | None = None) -> BusConfig:
        allowed = {*_ENDPOINT_KEYS, *_COUNT_KEYS, "curve"}
        unknown = set(d) - allowed
        if unknown:
            raise ConfigError(f"bus: unknown key(s) {sorted(unknown)}; allowed {sorted(allowed)}")
        for key in ("pub_endpoint", "sub_endpoint"):
            v = d.get(key)
            if not isinstance(v, str) or not v.startswith(("tcp://", "ipc://", "inproc://")):
                raise ConfigError(
                    f"bus.{key}: expected a tcp://, ipc:// or inproc:// endpoint, got {v!r}"
                )
        kwargs: dict[str, Any] = {
            "pub_endpoint": d["pub_endpoint"],
            "sub_endpoint": d["sub_endpoint"],
        }
        for key in _COUNT_KEYS:
            if key in d:
                v = d[key]
                if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                    raise ConfigError(f"bus.{key}: expected a non-negative int, got {v!r}")
                kwargs[key] = v
        if d.get("curve"):
            kwargs["curve"] = CurveConfig.from_dict(d["curve"], base_dir)
        return BusConfig(**kwargs)


# the keys of a bus block in a launch file, as the dataclasses name them
_CURVE_KEYS = tuple(f.name for f in fields(CurveConfig))
_ENDPOINT_KEYS = ("pub_endpoint", "sub_endpoint")
_COUNT_KEYS = tuple(  # non-negative ints
    f.name for f in fields(BusConfig) if f.name not in (*_ENDPOINT_KEYS, "curve")
)


def tune_malloc_for_large_messages(threshold_bytes: int = 64 << 20) -> bool:
    """Serve large message buffers from the heap instead of fresh ``mmap`` pages (glibc only).

    ZeroMQ allocates one buffer per received message; above glibc's mmap threshold each one is a
    new mapping, zero-filled page by page and unmapped after use. For megabyte keyframes that page
    faulting, not copying, bounds throughput: the broker forwarded ~0.8k 1.5 MB messages/s with
    the default and ~1.2k/s with this (bench/bus_throughput.py). Called once at process start by
    ``mogs broker`` and ``mogs node``. Returns False where mallopt is unavailable.
    """
    import ctypes

    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return False
    m_trim_threshold, m_mmap_threshold = -1, -3
    ok = libc.mallopt(m_mmap_threshold, min(threshold_bytes, 32 << 20)) == 1
    ok &= libc.mallopt(m_trim_threshold, 2 * threshold_bytes) == 1
    return bool(ok)


def default_bus_config(name: str = "default") -> BusConfig:
    """ipc endpoints in a per-user runtime folder; ``MOGS_BUS_DIR`` overrides the folder."""
    base = Path(os.environ.get("MOGS_BUS_DIR") or f"/tmp/mogs-{os.getuid()}")
    base.mkdir(mode=0o700, parents=True, exist_ok=True)
    return BusConfig(
        pub_endpoint=f"ipc://{base}/{name}-pub.ipc", sub_endpoint=f"ipc://{base}/{name}-sub.ipc"
    )


def generate_keys(
    keys_dir: str | Path, names: Iterable[str] = ("broker", "client")
) -> dict[str, Path]:
    """Write a CURVE key pair per name into ``keys_dir`` (``NAME.key``, ``NAME.key_secret``).

    Client public keys are also copied into ``keys_dir/authorized`` (the broker's accept list).
    """
    d = Path(keys_dir)
    d.mkdir(parents=True, exist_ok=True)
    auth = d / "authorized"
    auth.mkdir(exist_ok=True)
    out = {}
    for name in names:
        public, secret = zmq.auth.create_certificates(str(d), name)
        os.chmod(secret, 0o600)
        out[name] = Path(secret)
        if name != "broker":
            (auth / Path(public).name).write_bytes(Path(public).read_bytes())
    return out


def _load_secret(path: str) -> tuple[bytes, bytes]:
    try:
        public, secret = zmq.auth.load_certificate(path)
    except (OSError, ValueError) as err:
        raise BusError(f"cannot read CURVE key {path}: {err}") from err
    if secret is None:
        raise BusError(f"{path} holds no secret key")
    return public, secret


def _load_public(path: str) -> bytes:
    try:
        public, _ = zmq.auth.load_certificate(path)
    except (OSError, ValueError) as err:
        raise BusError(f"cannot read CURVE key {path}: {err}") from err
    return public


def _apply_client_curve(sock: zmq.Socket, curve: CurveConfig | None, endpoint: str) -> None:
    if curve is None:
        return
    if not curve.client_secret_key:
        raise BusError("bus.curve.client_secret_key is required for a client on a CURVE bus")
    public, secret = _load_secret(curve.client_secret_key)
    sock.curve_publickey = public
    sock.curve_secretkey = secret
    sock.curve_serverkey = _load_public(curve.server_public_key)


def _check_bind_address(endpoint: str, allow_remote: bool) -> None:
    """Refuse to listen on a non-loopback tcp address unless configured to (DESIGN.md section 5)."""
    if not endpoint.startswith("tcp://"):
        return
    host = endpoint[len("tcp://") :].rsplit(":", 1)[0].strip("[]")
    if host in ("127.0.0.1", "localhost", "::1") or host.startswith("127."):
        return
    if not allow_remote:
        raise BusError(
            f"refusing to listen on non-loopback address {endpoint}; pass allow_remote (launch file "
            "`bus.allow_remote: true`, with CURVE keys) to expose the bus"
        )


def with_endpoints(config: BusConfig, pub_endpoint: str, sub_endpoint: str) -> BusConfig:
    """A copy of ``config`` with other endpoints."""
    return replace(config, pub_endpoint=pub_endpoint, sub_endpoint=sub_endpoint)
