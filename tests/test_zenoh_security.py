"""Zenoh across hosts with TLS and access control (docs/security.md, "Zenoh across hosts").

Certificates are made here with the ``openssl`` CLI: a CA, a router's (with 127.0.0.1 in its
subjectAltName) and one per client identity, plus a rogue CA's for the refusals. Every session is a real
Zenoh session in this process on ``tls/127.0.0.1:PORT`` links, shared memory and multicast scouting
off, so samples cross TLS as they would between hosts. The simulator's side is its own session
(``open_zenoh_hub`` and the camera bridge's ``open_bridge_node``) opened from ``--set bridge.tls_*``,
or a ``sweep capture --ray local --zenoh-router`` job's simulator (docs/cluster.md).
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import stat
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh
from rosbags.typesys import Stores, get_typestore

from droneulator.cli import main as cli_main
from droneulator.config import BridgeConfig, load_config
from droneulator.runtime import zenoh_security
from droneulator.runtime.bridge import open_bridge_node
from droneulator.runtime.dynamics_server import open_zenoh_hub
from droneulator.runtime.launch import free_port
from droneulator.runtime.preflight import StartupError, check_ports, check_simulation, run_ports

TS = get_typestore(Stores.ROS2_JAZZY)
T = TS.types
EC = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]
LEAF_EXT = "\n".join(
    [
        "subjectAltName=IP:127.0.0.1,DNS:localhost",
        "basicConstraints=CA:FALSE",
        "extendedKeyUsage=serverAuth,clientAuth",
    ]
)
FLEET = 'vehicles=[{"name": "uav1"}, {"name": "uav2"}]'
#: the negative cases wait this long for a connection that must not open
REFUSE_MS = 800


def _openssl(*args: str) -> None:
    subprocess.run(["openssl", *args], check=True, capture_output=True)


def make_ca(folder: Path, name: str) -> tuple[Path, Path]:
    """A self-signed CA: its certificate and key."""
    cert, key = folder / f"{name}.pem", folder / f"{name}.key"
    _openssl(
        "req", "-x509", *EC, "-days", "2", "-keyout", str(key), "-out", str(cert), "-subj", f"/CN={name}"
    )
    return cert, key


def make_leaf(folder: Path, ca: tuple[Path, Path], common_name: str) -> tuple[Path, Path]:
    """A certificate for ``common_name`` (also valid for 127.0.0.1) signed by ``ca``, and its key."""
    cert, key, csr = (folder / f"{common_name}.{ext}" for ext in ("pem", "key", "csr"))
    ext = folder / "leaf.ext"
    ext.write_text(LEAF_EXT)
    _openssl("req", *EC, "-keyout", str(key), "-out", str(csr), "-subj", f"/CN={common_name}")
    _openssl(
        "x509", "-req", "-in", str(csr), "-CA", str(ca[0]), "-CAkey", str(ca[1]), "-CAcreateserial",
        "-days", "2", "-out", str(cert), "-extfile", str(ext),
    )  # fmt: skip
    return cert, key


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """name -> PEM path: ``ca``, ``<identity>.pem`` / ``.key`` for router, droneulator, ground-uav1,
    ground-uav2 (signed by the CA) and ``rogue.pem`` / ``.key`` (CN droneulator, another CA)."""
    folder = tmp_path_factory.mktemp("pki")
    ca = make_ca(folder, "test-ca")
    files = {"ca": ca[0]}
    for name in ("router", "droneulator", "ground-uav1", "ground-uav2"):
        files[f"{name}.pem"], files[f"{name}.key"] = make_leaf(folder, ca, name)
    rogue_dir = folder / "rogue"
    rogue_dir.mkdir()
    files["rogue.pem"], files["rogue.key"] = make_leaf(
        rogue_dir, make_ca(rogue_dir, "rogue-ca"), "droneulator"
    )
    return files


def config(
    mode: str,
    listen: list[str] | None = None,
    connect: list[str] | None = None,
    tls: dict[str, Any] | None = None,
    timeout_ms: int = 5000,
) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("listen/endpoints", json.dumps(listen or []))
    conf.insert_json5("connect/endpoints", json.dumps(connect or []))
    conf.insert_json5("connect/timeout_ms", str(timeout_ms))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("transport/shared_memory/enabled", "false")
    for name, value in (tls or {}).items():
        conf.insert_json5(f"transport/link/tls/{name}", json.dumps(value))
    return conf


def client_tls(pki: dict[str, Path], identity: str | None, ca: bool = True) -> dict[str, Any]:
    """A client's TLS settings: trusting the CA (or not), presenting ``identity``'s certificate (mTLS)."""
    tls: dict[str, Any] = {"root_ca_certificate": str(pki["ca"])} if ca else {}
    if identity is not None:
        tls |= {
            "connect_certificate": str(pki[f"{identity}.pem"]),
            "connect_private_key": str(pki[f"{identity}.key"]),
            "enable_mtls": True,
        }
    return tls


def wait(condition: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.02)


def twist_cdr(forward: float) -> bytes:
    v = T["geometry_msgs/msg/Vector3"]
    msg = T["geometry_msgs/msg/Twist"](linear=v(x=forward, y=0.0, z=0.0), angular=v(x=0.0, y=0.0, z=0.0))
    return bytes(TS.serialize_cdr(msg, "geometry_msgs/msg/Twist"))


class Inbox:
    """Payloads received per key, thread-safe (subscriber callbacks run on Zenoh's threads)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._got: dict[str, list[bytes]] = {}

    def on(self, key: str) -> Callable[[zenoh.Sample], None]:
        def cb(sample: zenoh.Sample) -> None:
            with self._lock:
                self._got.setdefault(key, []).append(sample.payload.to_bytes())

        return cb

    def get(self, key: str) -> list[bytes]:
        with self._lock:
            return list(self._got.get(key, []))


def test_tls_round_trip_between_two_routers(pki: dict[str, Path]) -> None:
    """A publisher on router A, a subscriber on router B, B connected to A's only (TLS) endpoint."""
    listen = f"tls/127.0.0.1:{free_port()}"
    a = zenoh.open(config("router", [listen], tls=router_tls(pki, mtls=False)))
    try:
        b = zenoh.open(config("router", connect=[listen], tls={"root_ca_certificate": str(pki["ca"])}))
        try:
            inbox = Inbox()
            sub = b.declare_subscriber("demo/tls", inbox.on("demo/tls"))
            pub = a.declare_publisher("demo/tls")
            deadline = time.monotonic() + 10
            while not inbox.get("demo/tls"):
                assert time.monotonic() < deadline, "nothing crossed the TLS link in 10 s"
                pub.put(b"over tls")
                time.sleep(0.02)
            assert inbox.get("demo/tls")[0] == b"over tls"
            assert [str(z) for z in b.info.routers_zid()] == [str(a.zid())]
            sub.undeclare()
        finally:
            b.close()
    finally:
        a.close()


def router_tls(pki: dict[str, Path], mtls: bool) -> dict[str, Any]:
    tls: dict[str, Any] = {
        "root_ca_certificate": str(pki["ca"]),
        "listen_certificate": str(pki["router.pem"]),
        "listen_private_key": str(pki["router.key"]),
    }
    return tls | {"enable_mtls": True} if mtls else tls


@pytest.fixture(scope="module")
def mtls_router(pki: dict[str, Path]) -> Iterator[str]:
    """A router with mutual TLS and the simulator's ACL for a two-vehicle config (the simulator's
    certificate CN ``droneulator``, ``ground-uav1`` commands uav1, ``ground-uav2`` uav2), its
    configuration printed by ``python -m droneulator.runtime.zenoh_security`` as docs/security.md
    shows; yields its endpoint."""
    listen = f"tls/127.0.0.1:{free_port()}"
    args = ["--set", FLEET, "--listen", listen, "--ca", str(pki["ca"]), "--cert", str(pki["router.pem"])]
    args += ["--key", str(pki["router.key"]), "--client", "ground-uav1=uav1", "--client", "ground-uav2=uav2"]
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        zenoh_security.main(args)
    path = pki["ca"].parent / "router.json5"
    path.write_text(out.getvalue())
    session = zenoh.open(zenoh.Config.from_file(str(path)))
    yield listen
    session.close()


@pytest.mark.parametrize(
    ("case", "ca", "identity"),
    [
        ("no CA", False, "ground-uav1"),
        ("no certificate", True, None),
        ("another CA's certificate", True, "rogue"),
    ],
)
def test_refused_without_the_ca_or_a_certificate_it_signed(
    pki: dict[str, Path], mtls_router: str, case: str, ca: bool, identity: str | None
) -> None:
    """A client that does not trust the router's CA, or under mutual TLS presents no certificate or one
    signed by another CA (with the simulator's very common name), never opens a session."""
    with pytest.raises(zenoh.ZError, match="Unable to connect"):
        zenoh.open(
            config("client", connect=[mtls_router], tls=client_tls(pki, identity, ca), timeout_ms=REFUSE_MS)
        )


@pytest.mark.parametrize("mode", ["client", "router"])
def test_acl_lets_each_side_through_only_on_its_keys(
    pki: dict[str, Path], mtls_router: str, mode: str
) -> None:
    """The simulator's own sessions, from ``--set bridge.tls_*``, and two ground clients behind the ACL
    router: sensor data reaches a client, each client commands its own vehicle; a command for the other
    vehicle never arrives, a subscription to another vehicle's commands gets nothing, and a key outside
    the rules crosses in neither direction. ``client``: the run's sessions are leaves of the ACL router;
    ``router``: the run's hub is a router of its own linked to it (what a ``sweep --ray`` job does, its
    listen endpoint its own)."""
    sets = [
        FLEET,
        f"bridge.mode={mode}",
        f'bridge.listen=["tcp/127.0.0.1:{free_port()}"]',
        f'bridge.connect=["{mtls_router}"]',
        f"bridge.tls_ca={pki['ca']}",
        f"bridge.tls_cert={pki['droneulator.pem']}",
        f"bridge.tls_key={pki['droneulator.key']}",
        "bridge.tls_mtls=true",
    ]
    cfg = load_config(overrides=sets)
    check_simulation(cfg)
    hub = open_zenoh_hub(cfg, None)
    cams = open_bridge_node(cfg, None)
    grounds = {
        v: zenoh.open(config("client", connect=[mtls_router], tls=client_tls(pki, f"ground-{v}")))
        for v in ("uav1", "uav2")
    }
    try:
        at_sim: dict[str, list[float]] = {"uav1": [], "uav2": []}
        for v in at_sim:
            hub.subscribe(
                f"/droneulator/{v}/cmd_vel",
                "geometry_msgs/msg/Twist",
                lambda m, v=v: at_sim[v].append(m.linear.x),
            )
        at_ground = Inbox()
        g1 = grounds["uav1"]
        watched = [
            "droneulator/uav1/odom",
            "droneulator/uav1/front/color/image_raw/compressed",
            "droneulator/uav2/cmd_vel",
            "secret/x",
        ]
        subs = [g1.declare_subscriber(k, at_ground.on(k)) for k in watched]

        odom = hub.publisher("/droneulator/uav1/odom", "nav_msgs/msg/Odometry")
        image = cams.publisher(
            "/droneulator/uav1/front/color/image_raw/compressed", "sensor_msgs/msg/CompressedImage"
        )
        secret = hub.session.declare_publisher("secret/x")
        deadline = time.monotonic() + 10
        while not (at_ground.get(watched[0]) and at_ground.get(watched[1])):
            assert time.monotonic() < deadline, "the simulator's sensor keys did not reach the ground client"
            secret.put(b"outside the rules")  # before each allowed sample on the same link
            odom.publish(b"odom")
            image.publish(b"jpeg")
            time.sleep(0.02)

        pubs = {  # remote only: not to uav1's client's own subscription of uav2's commands
            (g, v): grounds[g].declare_publisher(
                f"droneulator/{v}/cmd_vel", allowed_destination=zenoh.Locality.REMOTE
            )
            for g in grounds
            for v in ("uav1", "uav2")
        }
        wait(
            lambda: pubs["uav1", "uav1"].matching_status.matching,
            5,
            "the simulator's uav1 cmd_vel via the router",
        )
        pubs["uav1", "uav2"].put(twist_cdr(9.0))  # forbidden: uav1's client, uav2's command
        pubs["uav1", "uav1"].put(twist_cdr(1.0))
        pubs["uav2", "uav2"].put(twist_cdr(2.0))
        wait(lambda: at_sim["uav1"] == [1.0] and at_sim["uav2"] == [2.0], 5, "both clients' own commands")
        time.sleep(0.3)  # the refused ones were sent first, on the same links: give them time anyway
        assert at_sim == {"uav1": [1.0], "uav2": [2.0]}
        assert at_ground.get("droneulator/uav2/cmd_vel") == []  # uav2's command, not for uav1's client
        assert at_ground.get("secret/x") == []
        for s in subs:
            s.undeclare()
    finally:
        for g in grounds.values():
            g.close()
        cams.close()
        hub.close()


def test_a_bad_certificate_path_is_one_clear_error(
    pki: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    """``droneulator run`` with a missing CA file, or a key file that holds no key, stops before any
    child starts with one line naming the setting and the file."""
    missing = pki["ca"].parent / "missing.pem"
    code = cli_main(["run", "--set", f"bridge.tls_ca={missing}"])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert err.splitlines() == [err]
    assert f"bridge.tls_ca {missing}: cannot be read (No such file or directory)" in err
    sets = [f"bridge.tls_cert={pki['droneulator.pem']}", f"bridge.tls_key={pki['droneulator.pem']}"]
    with pytest.raises(
        StartupError, match=r"bridge\.tls_key .*droneulator\.pem: not a PEM file holding a private key"
    ):
        check_simulation(load_config(overrides=sets))


def test_simulator_as_the_router_listens_on_tls(pki: dict[str, Path]) -> None:
    """Deployment 1 of docs/ros2.md over TLS: the simulator's session is the router, listening on
    ``tls/`` with mutual TLS; a remote router presenting a certificate the CA signed connects to it and
    gets /clock."""
    listen = f"tls/127.0.0.1:{free_port()}"
    sets = [
        f'bridge.listen=["{listen}"]',
        f"bridge.tls_ca={pki['ca']}",
        f"bridge.tls_cert={pki['droneulator.pem']}",
        f"bridge.tls_key={pki['droneulator.key']}",
        "bridge.tls_mtls=true",
    ]
    cfg = load_config(overrides=sets)
    check_simulation(cfg)
    check_ports(run_ports(cfg))  # the tls/ port is checked like a tcp/ one
    hub = open_zenoh_hub(cfg, None)
    remote = zenoh.open(config("router", connect=[listen], tls=client_tls(pki, "ground-uav1")))
    try:
        inbox = Inbox()
        sub = remote.declare_subscriber("clock", inbox.on("clock"))
        clock = hub.publisher("/clock", "rosgraph_msgs/msg/Clock")
        deadline = time.monotonic() + 10
        while not inbox.get("clock"):
            assert time.monotonic() < deadline, "no /clock across the simulator's TLS listener in 10 s"
            clock.publish(b"tick")
            time.sleep(0.02)
        assert [str(z) for z in remote.info.routers_zid()] == [hub.zid]
        sub.undeclare()
    finally:
        remote.close()
        hub.close()


def test_the_documented_example_is_what_the_helper_writes_and_zenoh_reads() -> None:
    """examples/zenoh/router_acl.json5 (docs/security.md's ready-to-use router) is the helper's output for
    the default run, and a valid Zenoh configuration."""
    path = Path(__file__).resolve().parents[1] / "examples" / "zenoh" / "router_acl.json5"
    text = "\n".join(line for line in path.read_text().splitlines() if not line.startswith("//"))
    acl = zenoh_security.access_control(load_config(), "droneulator", {"ground": "uav0"})
    expected = zenoh_security.router_config(["tls/0.0.0.0:7447"], "ca.pem", "router.pem", "router.key", acl)
    assert json.loads(text) == expected
    conf = zenoh.Config.from_file(str(path))
    assert json.loads(conf.get_json("access_control/default_permission")) == "deny"


#: a small capture (test_ray.py's): two views at 160x120
SMALL_CAPTURE = [
    "capture.width=160", "capture.height=120", "capture.arc_deg=20", "capture.speed=2",
    "capture.pitch_deg=10", "render.shadow_map_size=512", "capture.accept_after_s=0.5",
]  # fmt: skip


def tls_sets(pki: dict[str, Path], key: str = "droneulator.key") -> list[str]:
    """``--set`` values naming the simulator's certificate files (``key``: which file as its key)."""
    return [
        f"bridge.tls_ca={pki['ca']}",
        f"bridge.tls_cert={pki['droneulator.pem']}",
        f"bridge.tls_key={pki[key]}",
    ]


def set_flags(values: list[str]) -> list[str]:
    return [a for v in values for a in ("--set", v)]


def test_zenoh_router_option_is_checked_before_ray_starts(
    pki: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``sweep --zenoh-router``: a bad endpoint, missing or unreadable certificate settings and files, a
    client-mode bridge or a planning sweep are each one line and exit status 2, before Ray starts."""
    out = ["--out", str(tmp_path / "s"), "--ray", "local", "--no-progress"]
    sets = set_flags(tls_sets(pki))
    missing = tmp_path / "missing.pem"
    client_link = 'bridge.connect=["tcp/10.0.0.2:7447"]'
    cases = [
        (["--zenoh-router", "tcp/127.0.0.1:7447", *sets], "give the TLS router's endpoint as tls/HOST:PORT"),
        (["--zenoh-router", "tls/127.0.0.1", *sets], "tls/HOST:PORT"),
        (["--zenoh-router", "tls/:7447", *sets], "tls/HOST:PORT"),
        (["--zenoh-router", "tls/127.0.0.1:70000", *sets], "tls/HOST:PORT"),
        (["--zenoh-router", "tls/127.0.0.1:7447"], "set bridge.tls_ca, bridge.tls_cert and bridge.tls_key"),
        (
            ["--zenoh-router", "tls/127.0.0.1:7447", *sets, "--set", f"bridge.tls_ca={missing}"],
            f"bridge.tls_ca {missing}: cannot be read (No such file or directory); expected PEM files",
        ),
        (
            ["--zenoh-router", "tls/127.0.0.1:7447", *set_flags(tls_sets(pki, key="droneulator.pem"))],
            "droneulator.pem: not a PEM file holding a private key; expected PEM files",
        ),
        (
            ["--zenoh-router", "tls/127.0.0.1:7447", *sets, *set_flags(["bridge.mode=client", client_link])],
            "not with bridge.mode=client",
        ),
    ]
    for args, message in cases:
        code = cli_main(["sweep", "capture", *out, *args])
        err = capsys.readouterr().err
        assert code == 2, (args, err)
        assert message in err and err.count("\n") == 1, (args, err)
    code = cli_main(["sweep", "plan", *out, "--zenoh-router", "tls/127.0.0.1:7447"])
    assert code == 2 and "--zenoh-router goes with sweep capture" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()
    assert "ray" not in sys.modules or not sys.modules["ray"].is_initialized()


def test_router_link_carries_the_files_to_a_job(pki: dict[str, Path], tmp_path: Path) -> None:
    """The files read where the sweep starts are written, unchanged, for the job (the key private to the
    user), and the job's bridge links to the router with mutual TLS on them, keeping its own links."""
    cfg = load_config(overrides=[*tls_sets(pki), 'bridge.connect=["tcp/10.0.0.2:7447"]'])
    link = zenoh_security.RouterLink.load("tls/[::1]:7447", cfg.bridge)
    bridge = BridgeConfig(connect=["tcp/10.0.0.2:7447"])
    link.apply(bridge, tmp_path / "tls")
    assert bridge.connect == ["tcp/10.0.0.2:7447", "tls/[::1]:7447"] and bridge.tls_mtls
    for name, source in (("tls_ca", "ca"), ("tls_cert", "droneulator.pem"), ("tls_key", "droneulator.key")):
        path = Path(getattr(bridge, name))
        assert path.parent == tmp_path / "tls" and path.read_bytes() == pki[source].read_bytes()
    assert stat.S_IMODE(os.stat(bridge.tls_key).st_mode) == 0o600
    assert stat.S_IMODE(os.stat(tmp_path / "tls").st_mode) == 0o700
    zenoh_security.check_tls_files(bridge.tls_ca, bridge.tls_cert, bridge.tls_key)


def test_a_ray_sweep_job_publishes_through_the_tls_router_under_its_acl(
    pki: dict[str, Path], tmp_path: Path
) -> None:
    """``sweep capture --ray local --zenoh-router tls/...``, one small capture: its simulator links to a
    router with mutual TLS and the simulator's ACL (written by ``python -m droneulator.runtime.
    zenoh_security`` for the sweep's config, then narrowed to refuse the simulator's ``tf``); a ground
    client of that router, over TLS with its own certificate, gets the job's odometry and clock, and
    never its ``tf``. The job ran on the carried copies of the certificate files, since removed."""
    pytest.importorskip("ray")
    listen = f"tls/127.0.0.1:{free_port()}"
    args = ["--listen", listen, "--ca", str(pki["ca"]), "--cert", str(pki["router.pem"])]
    args += ["--key", str(pki["router.key"]), "--client", "ground-uav1=uav0"]
    args += set_flags(SMALL_CAPTURE)
    text = io.StringIO()
    with contextlib.redirect_stdout(text):
        zenoh_security.main(args)
    conf = json.loads(text.getvalue())
    rule = next(r for r in conf["access_control"]["rules"] if r["id"] == "simulator_publishes_sensors")
    assert "tf" in rule["key_exprs"] and "droneulator/odom" in rule["key_exprs"]
    rule["key_exprs"].remove("tf")
    path = tmp_path / "router.json5"
    path.write_text(json.dumps(conf))
    router = zenoh.open(zenoh.Config.from_file(str(path)))
    ground = zenoh.open(config("client", connect=[listen], tls=client_tls(pki, "ground-uav1")))
    inbox = Inbox()
    subs = [ground.declare_subscriber(k, inbox.on(k)) for k in ("droneulator/odom", "clock", "tf")]
    out = tmp_path / "sweep"
    cmd = [sys.executable, "-m", "droneulator.cli", "sweep", "capture", "--out", str(out), "--views", "2"]
    cmd += ["--ray", "local", "--cpus-per-job", "1", "--no-progress", "--zenoh-router", listen]
    cmd += set_flags([*SMALL_CAPTURE, *tls_sets(pki)])
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stdout + done.stderr
        summary = json.loads((out / "tree_inspection-seed0-views2" / "job.json").read_text())
        assert summary["zenoh_router"] == listen and summary["views_captured"] == 2
        assert inbox.get("droneulator/odom") and inbox.get("clock"), "the job's data did not reach the client"
        assert inbox.get("tf") == []  # refused by the ACL at the router
        bridge = json.loads((out / "tree_inspection-seed0-views2" / "config.json").read_text())["bridge"]
        assert bridge["connect"] == [listen] and bridge["tls_mtls"]
        carried = Path(bridge["tls_cert"])
        assert carried.name == "cert.pem" and carried != pki["droneulator.pem"] and not carried.exists()
        for s in subs:
            s.undeclare()
    finally:
        ground.close()
        router.close()
