"""Start-up checks: every failure a user can cause is found here, before any simulator process starts,
and reported as one line (:class:`StartupError`) that names the port, setting or file and the option
that changes it.

Exit codes: 2 for usage and configuration errors (bad ``--config`` file or ``--set`` value, unknown
scene or vehicle); 1 for the machine (a port already in use or not bindable, no EGL/OpenGL, an output
folder that cannot be written).

Port checks bind the way the servers will: the same host (every address it resolves to, IPv6 sockets
v6-only, as asyncio's ``create_server`` does) with ``SO_REUSEADDR``, which the WebSocket server
(asyncio), Zenoh (Rust ``mio``) and the PX4 link all set on Linux. So a port held by a listening
socket is reported, and one left in ``TIME_WAIT`` by an earlier run is not.
"""

from __future__ import annotations

import errno
import importlib.util
import json
import os
import re
import signal
import socket
import ssl
import subprocess
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from droneulator.config import SimConfig, from_dict, load_config, to_dict
from droneulator.config.loading import ConfigError, file_format, parse_text
from droneulator.runtime.spawn import code_command

#: exit status for usage and configuration errors (as argparse uses), and for everything else
USAGE, FAILURE = 2, 1

EGL_PACKAGES = "libegl1 libgl1 libegl-mesa0 libgl1-mesa-dri"
#: the render server's context: a standalone moderngl context through EGL (droneulator.render.renderer)
_EGL_PROBE = "import moderngl\nctx = moderngl.create_context(standalone=True, backend='egl')\nctx.release()\n"
EGL_PROBE_TIMEOUT_S = 60.0


class StartupError(Exception):
    """A start-up failure the user can fix: ``str(err)`` is the one-line message, ``exit_code`` the
    process exit status (:data:`USAGE` or :data:`FAILURE`)."""

    def __init__(self, message: str, exit_code: int = FAILURE) -> None:
        super().__init__(" ".join(message.split()))  # one line, whatever the wrapped error held
        self.exit_code = exit_code


@dataclass(frozen=True)
class Listen:
    """A TCP (or UDP) port a server will listen on, and how the user chooses another."""

    #: the server: "API", "Zenoh", "PX4 SITL", "ArduPilot SITL"
    what: str
    host: str
    port: int
    #: the options that set the port, e.g. "--api-port or --set runtime.api_port=N"
    port_option: str
    #: the option that sets the host
    host_option: str
    #: where the port comes from when that is not obvious, e.g. "bridge.listen tcp/127.0.0.1:7448"
    source: str = ""
    #: "TCP", or "UDP" (ArduPilot's JSON physics port)
    protocol: str = "TCP"

    @property
    def label(self) -> str:
        return f"{self.what} port {self.port}" + (f" ({self.source})" if self.source else "")


# --------------------------------------------------------------------------- configuration
def load(path: str | Path | None, overrides: list[str] | None = None, **top: Any) -> SimConfig:
    """:func:`droneulator.config.load_config`, with each failure as a :class:`StartupError` naming the
    file or the option."""
    if path is not None:
        _check_config_file(Path(path))
    try:
        return load_config(path, overrides, **top)
    except ValueError as exc:
        raise StartupError(f"--set: {exc}" if overrides else str(exc), USAGE) from exc


_JSON_HINT = " (files not named *.toml, *.yaml or *.yml are read as JSON)"


def _check_config_file(path: Path) -> None:
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise StartupError(f"--config {path}: no such file", USAGE) from None
    except IsADirectoryError:
        raise StartupError(f"--config {path}: is a folder, not a JSON, TOML or YAML file", USAGE) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise StartupError(f"--config {path}: cannot be read ({_reason(exc)})", USAGE) from None
    fmt = file_format(path)
    try:
        data = parse_text(text, fmt)
    except ConfigError as exc:
        message = str(exc)
        if fmt == "json" and path.suffix != ".json":
            message = message.replace("not valid JSON", f"not valid JSON{_JSON_HINT}", 1)
        raise StartupError(f"--config {path}: {message}", USAGE) from None
    if data is not None and not isinstance(data, dict):
        raise StartupError(f"--config {path}: expected a table of options, got {type(data).__name__}", USAGE)
    try:
        load_config(path)
    except ValueError as exc:
        raise StartupError(f"--config {path}: {exc}", USAGE) from None


def revalidate(cfg: SimConfig) -> None:
    """Rebuild ``cfg`` from JSON the way the child processes do, so settings changed after loading
    (``--px4-instance``, ``--api-port``) are validated here rather than in a child."""
    try:
        from_dict(SimConfig, json.loads(json.dumps(to_dict(cfg))))
    except ValueError as exc:
        raise StartupError(str(exc), USAGE) from exc


def check_scene(name: str) -> None:
    """The scene exists (without building it)."""
    from droneulator.scenes import list_scenes

    known = list_scenes()
    if name not in known:
        raise StartupError(
            f"unknown scene {name!r}; known scenes: {', '.join(known)} (choose with --scene NAME)", USAGE
        )


def check_vehicle(cfg: SimConfig) -> None:
    """The vehicle parameter set exists, every vehicle's sensors are known kinds (with those PX4 needs
    when PX4 flies), and the wind model's dependencies are installed."""
    from droneulator.vehicles.params import PARAMETER_SETS

    if cfg.vehicle.params not in PARAMETER_SETS:
        raise StartupError(
            f"unknown vehicle parameter set {cfg.vehicle.params!r}; known: {', '.join(PARAMETER_SETS)} "
            "(choose with --set vehicle.params=NAME)",
            USAGE,
        )
    from droneulator.sensors.suite import PX4_SENSORS, check_kinds

    for spec in cfg.vehicle_specs():
        assert spec.sensors is not None
        px4 = spec.controlled_by == "px4"
        where = "vehicle.sensors" if not cfg.vehicles else f"vehicle {spec.name!r}: sensors"
        try:
            check_kinds(spec.sensors)
        except ValueError as exc:
            raise StartupError(f"{where}: {exc}", USAGE) from None
        missing = [k for k in PX4_SENSORS if k not in spec.sensors]
        if px4 and missing:
            raise StartupError(
                f"{where}: PX4 needs {', '.join(PX4_SENSORS)}; {', '.join(missing)} missing", USAGE
            )
        if spec.controlled_by == "ardupilot" and "imu" not in spec.sensors:
            raise StartupError(f"{where}: ArduPilot's JSON interface needs an imu", USAGE)
    if cfg.vehicle.wind == "dryden" and importlib.util.find_spec("torch") is None:
        raise StartupError(
            "vehicle.wind=dryden needs torch: pip install 'droneulator[rl]', or choose another wind model "
            "with --set vehicle.wind=NAME",
            USAGE,
        )


def check_output_dir(path: str | Path, option: str = "--out") -> None:
    """``path`` is (or can be made) a writable folder."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise StartupError(f"{option} {path}: cannot create the folder ({_reason(exc)})") from None
    if not path.is_dir() or not _writable(path):
        raise StartupError(f"{option} {path}: not a writable folder; choose another with {option} DIR")


def _writable(path: Path) -> bool:
    return os.access(path, os.W_OK | os.X_OK)


# --------------------------------------------------------------------------- ports
def run_ports(cfg: SimConfig) -> list[Listen]:
    """The ports ``droneulator run`` will listen on: the WebSocket API, each ``tcp/`` Zenoh listen
    endpoint (other schemes are not checked) and, with PX4 on, the PX4 SITL port; with ArduPilot on, the
    UDP port of its JSON physics."""
    rt, px4 = cfg.runtime, cfg.px4
    ports = [
        Listen(
            "API",
            rt.api_host,
            rt.api_port,
            "--api-port or --set runtime.api_port=N",
            "--set runtime.api_host=HOST",
        )
    ]
    for endpoint in zenoh_listen_endpoints(cfg):
        parsed = parse_tcp_endpoint(endpoint)
        if parsed is not None:
            option = "--set bridge.listen='[\"tcp/HOST:N\"]'"
            ports.append(Listen("Zenoh", *parsed, option, option, f"bridge.listen {endpoint}"))
    for vehicle, instance in cfg.px4_instances().items():
        ports.append(
            Listen(
                f"PX4 SITL ({vehicle})" if len(cfg.vehicle_specs()) > 1 else "PX4 SITL",
                px4.host,
                0 if px4.base_port == 0 else px4.base_port + instance,
                f"--px4-instance N (port {px4.base_port}+N) or --set px4.base_port=N",
                "--set px4.host=HOST",
                f"px4.base_port {px4.base_port} + px4.instance {px4.instance}"
                + (f" + vehicle index {instance - px4.instance}" if instance != px4.instance else ""),
            )
        )
    ap = cfg.ardupilot
    for vehicle, instance in cfg.ardupilot_instances().items():
        ports.append(
            Listen(
                f"ArduPilot SITL ({vehicle})" if len(cfg.vehicle_specs()) > 1 else "ArduPilot SITL",
                ap.host,
                0 if ap.base_port == 0 else ap.base_port + 10 * instance,
                f"--ardupilot-instance N (port {ap.base_port}+10N) or --set ardupilot.base_port=N",
                "--set ardupilot.host=HOST",
                f"ardupilot.base_port {ap.base_port} + 10 x instance {instance}",
                protocol="UDP",
            )
        )
    return ports


def zenoh_listen_endpoints(cfg: SimConfig) -> list[str]:
    """``bridge.listen``, or where it is empty, the endpoints of ``bridge.zenoh_config`` (whose
    readability this checks)."""
    b = cfg.bridge
    if not b.zenoh_config:
        return list(b.listen)
    import zenoh

    try:
        conf = zenoh.Config.from_file(b.zenoh_config)
    except Exception as exc:  # zenoh raises its own ZError for unreadable or invalid files
        raise StartupError(
            f"bridge.zenoh_config {b.zenoh_config}: not a usable Zenoh configuration file ({_reason(exc)}); "
            "fix it or choose another with --set bridge.zenoh_config=FILE",
            USAGE,
        ) from None
    if b.listen:
        return list(b.listen)
    endpoints = json.loads(conf.get_json("listen/endpoints"))
    if isinstance(endpoints, dict):  # per-mode lists: {"router": [...], "peer": [...]}
        mode = json.loads(conf.get_json("mode")) or "peer"
        endpoints = endpoints.get(mode, [])
    return [str(e) for e in endpoints]


def parse_tcp_endpoint(endpoint: str) -> tuple[str, int] | None:
    """``(host, port)`` of a Zenoh ``tcp/HOST:PORT[?metadata][#config]`` endpoint, or a ``tls/`` one (TLS
    on TCP: the same port to bind); None for other schemes."""
    scheme, sep, rest = endpoint.partition("/")
    if scheme not in ("tcp", "tls"):
        return None
    address = rest.split("?", 1)[0].split("#", 1)[0]
    host, colon, port = address.rpartition(":")
    if not sep or not colon or not host or not port.isdigit():
        raise StartupError(
            f"bridge.listen endpoint {endpoint!r} is not {scheme}/HOST:PORT; "
            "fix it with --set bridge.listen='[\"tcp/HOST:N\"]'",
            USAGE,
        )
    return host.strip("[]"), int(port)


def check_ports(ports: list[Listen]) -> None:
    """Each port is in range, not claimed twice, and bindable now."""
    for i, p in enumerate(ports):
        if not 0 <= p.port <= 65535:
            raise StartupError(
                f"{p.label} is not a {p.protocol} port (0-65535); choose another with {p.port_option}",
                USAGE,
            )
        for q in ports[:i]:
            same_host = p.host == q.host or _wildcard(p.host) or _wildcard(q.host)
            if p.port and p.port == q.port and p.protocol == q.protocol and same_host:
                raise StartupError(
                    f"{q.label} and {p.label} are the same port; change one with {q.port_option} "
                    f"or {p.port_option}",
                    USAGE,
                )
    for p in ports:
        check_port(p)


def _wildcard(host: str) -> bool:
    return host in ("", "0.0.0.0", "::")


def check_port(p: Listen) -> None:
    """Bind ``p.host:p.port`` as its server will (TCP with ``SO_REUSEADDR``, UDP without; every address
    the host resolves to) and release it at once. Port 0 (any free port) always succeeds."""
    if p.port == 0:
        return
    udp = p.protocol == "UDP"
    kind = socket.SOCK_DGRAM if udp else socket.SOCK_STREAM
    try:
        infos = socket.getaddrinfo(p.host or None, p.port, type=kind, flags=socket.AI_PASSIVE)
    except socket.gaierror as exc:
        raise StartupError(
            f"{p.what} host {p.host!r} does not resolve ({exc.strerror}); choose another with "
            f"{p.host_option}",
            USAGE,
        ) from None
    for family, kind, proto, _, address in dict.fromkeys(infos):
        with socket.socket(family, kind, proto) as sock:
            if not udp:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            if family == socket.AF_INET6:
                sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
            try:
                sock.bind(address)
            except OSError as exc:
                if exc.errno == errno.EADDRINUSE:
                    raise StartupError(
                        f"{p.label} on {p.host} is already in use; choose another with {p.port_option}"
                    ) from None
                raise StartupError(
                    f"cannot listen on {p.host}:{p.port} for the {p.label} ({_reason(exc)}); "
                    f"choose another port with {p.port_option} or another host with {p.host_option}"
                ) from None


# --------------------------------------------------------------------------- rendering
def check_egl(timeout: float = EGL_PROBE_TIMEOUT_S) -> None:
    """Create and release the renderer's headless EGL OpenGL context in a short subprocess (so a broken
    driver cannot crash the caller and no GL state stays in it); it inherits this environment."""
    try:
        proc = subprocess.run(
            code_command(_EGL_PROBE), capture_output=True, text=True, timeout=timeout
        )
    except subprocess.TimeoutExpired:
        reason = f"creating a context did not finish within {timeout:g} s"
    else:
        if proc.returncode == 0:
            return
        lines = [ln.strip() for ln in proc.stderr.splitlines() if ln.strip()]
        if proc.returncode < 0:
            reason = f"the probe was killed by {signal.Signals(-proc.returncode).name}"
        else:
            reason = lines[-1] if lines else f"the probe exited with code {proc.returncode}"
    raise StartupError(
        f"no OpenGL context through EGL ({reason}); the renderer needs libEGL and a Mesa or GPU "
        f"OpenGL driver: Debian packages {EGL_PACKAGES} (`bash scripts/setup.sh` installs them)"
    )


# --------------------------------------------------------------------------- per command
def check_simulation(cfg: SimConfig) -> None:
    """What every command that builds a simulator needs: a valid config, the scene, the vehicle."""
    revalidate(cfg)
    check_scene(cfg.scene)
    check_vehicle(cfg)
    check_zenoh_tls(cfg)


def check_zenoh_tls(cfg: SimConfig) -> None:
    """``bridge.tls_ca``, ``tls_cert`` and ``tls_key``, where given, are readable PEM files."""
    from droneulator.runtime.zenoh_security import check_tls_files

    b = cfg.bridge
    try:
        check_tls_files(b.tls_ca, b.tls_cert, b.tls_key)
    except ValueError as exc:
        raise StartupError(f"{exc}; expected PEM files (docs/security.md)", USAGE) from None


def check_run(cfg: SimConfig) -> None:
    """Everything ``droneulator run`` can check before starting its child processes, cheapest first."""
    check_simulation(cfg)
    check_ports(run_ports(cfg))
    check_egl()


def prepare_access(cfg: SimConfig, hosts: list[str], announce: Callable[[str], None] = print) -> None:
    """Give ``cfg.access`` a token when a server binds one of ``hosts`` beyond loopback without one,
    announcing it once (the children get it in their configuration); check the TLS files load."""
    from droneulator.api.access import generate_token, is_loopback, server_ssl_context

    access = cfg.access
    try:
        server_ssl_context(access.tls_cert, access.tls_key)
    except (OSError, ssl.SSLError, ValueError) as exc:
        raise StartupError(
            f"access.tls_cert {access.tls_cert} / access.tls_key {access.tls_key}: cannot be loaded "
            f"({_reason(exc)}; expected PEM files: a certificate chain and its private key)",
            USAGE,
        ) from None
    if access.token is None and not all(is_loopback(h) for h in hosts):
        access.token = generate_token()
        beyond = ", ".join(h for h in hosts if not is_loopback(h))
        announce(
            f"access token: {access.token} (generated: {beyond} is beyond loopback; clients add "
            "?token=TOKEN to the WebSocket URL; set access.token to choose it; docs/security.md)"
        )


def _reason(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    text = re.sub(r" at \S+\.rs:\d+\.?", "", str(exc))  # Zenoh errors end with their Rust source line
    return " ".join(text.split()) or type(exc).__name__
