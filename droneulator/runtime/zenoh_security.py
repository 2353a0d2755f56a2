"""Zenoh across hosts with TLS and access control: file checks and a router configuration with an ACL.

TLS is configured in the simulator's own config (``bridge.tls_ca``, ``tls_cert``, ``tls_key``,
``tls_mtls``: :func:`droneulator.ros.zenoh_node.tls_entries` turns them into Zenoh's
``transport/link/tls`` settings); :func:`check_tls_files` checks them before a run starts any process.

Access control is Zenoh's own ``access_control`` section, enforced by the router the simulator and its
remote clients connect to. :func:`access_control` builds it from a simulator config, telling the sides
apart by the common name of the certificate each presents (mutual TLS): the simulator may publish its
sensor keys and subscribe to its command keys only, a client may subscribe to the sensor keys and
publish the commands of its own vehicle only. :func:`router_config` wraps it in a whole router
configuration (``zenohd -c``, or ``bridge.zenoh_config`` when the simulator's session is the router);
``python -m droneulator.runtime.zenoh_security`` prints one (docs/security.md).

:class:`RouterLink` is ``sweep --zenoh-router``: the TLS router every job links to, with the simulator's
certificate files read once where the command starts and carried to each job's node (docs/cluster.md).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from droneulator.config import BridgeConfig, SimConfig
from droneulator.ros.publishers import fleet_names
from droneulator.ros.topics import (
    VehicleNames,
    battery_state_topic,
    faults_topic,
    spray_deposit_topic,
    spray_state_topic,
)
from droneulator.ros.zenoh_node import tls_entries

#: the topics (keys of :func:`droneulator.ros.topics.vehicle_topics`) a vehicle is commanded on
COMMAND_TOPICS = ("cmd_vel", "goal_pose", "position_cmd", "attitude_target", "motor_speed", "fault")
#: liveliness keys of the ROS graph (rmw_zenoh's and zenoh-bridge-ros2dds' tokens): names, no data
GRAPH_KEYS = ("@ros2_lv/**", "@/*/@ros2_lv/**")
_LIVELINESS = ["liveliness_token", "declare_liveliness_subscriber", "liveliness_query", "reply"]


def check_tls_files(ca: str, cert: str, key: str, prefix: str = "bridge") -> None:
    """A ValueError of one line naming the first TLS file that is missing, unreadable or not PEM.

    Checked before any process starts: Zenoh reports a bad file only when a ``tls/`` link opens, deep
    in a child process's log."""
    files = (("tls_ca", ca, "CERTIFICATE"), ("tls_cert", cert, "CERTIFICATE"))
    for name, path, marker in (*files, ("tls_key", key, "PRIVATE KEY")):
        if not path:
            continue
        try:
            text = Path(path).read_text(errors="replace")
        except OSError as exc:
            raise ValueError(f"{prefix}.{name} {path}: cannot be read ({exc.strerror or exc})") from None
        if "-----BEGIN " not in text or f"{marker}-----" not in text:  # "EC PRIVATE KEY-----" too
            raise ValueError(f"{prefix}.{name} {path}: not a PEM file holding a {marker.lower()}")


def check_tls_endpoint(endpoint: str, option: str = "--zenoh-router") -> str:
    """``tls/HOST:PORT`` (an IPv6 host in brackets), else a one-line ValueError naming the form."""
    host, sep, port = endpoint.removeprefix("tls/").rpartition(":")
    ok = endpoint.startswith("tls/") and bool(sep and host.strip("[]")) and port.isdigit()
    if not ok or not 0 < int(port) < 65536 or any(c in host for c in "/ "):
        raise ValueError(
            f"{option} {endpoint!r}: give the TLS router's endpoint as tls/HOST:PORT, e.g. "
            "tls/192.168.1.10:7447 (docs/cluster.md)"
        )
    return endpoint


@dataclass(frozen=True)
class RouterLink:
    """A TLS router with the simulator's ACL that every job of a Ray command links to, and the PEM files
    of ``bridge.tls_ca``, ``tls_cert`` and ``tls_key`` themselves: read where the command starts, so the
    jobs' nodes need no copy of them at the same paths (they share no file system)."""

    endpoint: str
    ca: bytes
    cert: bytes
    key: bytes

    @classmethod
    def load(cls, endpoint: str, bridge: BridgeConfig) -> RouterLink:
        """Check ``endpoint`` and the bridge's three TLS files (a one-line ValueError for the first bad
        one), then read them. Mutual TLS needs all three: the router's ACL knows the jobs by the common
        name of the certificate they present."""
        check_tls_endpoint(endpoint)
        if not (bridge.tls_ca and bridge.tls_cert and bridge.tls_key):
            raise ValueError(
                f"--zenoh-router {endpoint}: set bridge.tls_ca, bridge.tls_cert and bridge.tls_key (the CA "
                "and the simulator's certificate and key, PEM files; docs/security.md)"
            )
        if bridge.mode == "client":
            raise ValueError(
                "--zenoh-router links each job's own router to it: not with bridge.mode=client (a job's "
                "capture reads its run's topics on the run's listen endpoint)"
            )
        try:
            check_tls_files(bridge.tls_ca, bridge.tls_cert, bridge.tls_key)
        except ValueError as exc:
            raise ValueError(f"{exc}; expected PEM files (docs/security.md)") from None
        files = (Path(bridge.tls_ca), Path(bridge.tls_cert), Path(bridge.tls_key))
        return cls(endpoint, *(f.read_bytes() for f in files))

    def apply(self, bridge: BridgeConfig, folder: Path) -> None:
        """Write the carried files into ``folder`` (the key readable by this user only) and link
        ``bridge`` to the router with mutual TLS on them; the bridge keeps its own listen endpoint."""
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
        paths = {name: folder / name for name in ("ca.pem", "cert.pem", "cert.key")}
        for (name, path), data in zip(paths.items(), (self.ca, self.cert, self.key), strict=True):
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600 if name == "cert.key" else 0o644)
            with os.fdopen(fd, "wb") as f:
                f.write(data)
        bridge.tls_ca, bridge.tls_cert, bridge.tls_key = (str(p) for p in paths.values())
        bridge.tls_mtls = True
        if self.endpoint not in bridge.connect:
            bridge.connect = [*bridge.connect, self.endpoint]


def key_expr(cfg: SimConfig, topic: str) -> str:
    """The Zenoh key expression covering ROS ``topic`` (absolute; may end in ``/**``) in the run's key
    mode: ``droneulator/odom`` (ros2dds, after ``bridge.ros2dds_namespace``) or ``0/droneulator/odom/**``
    (rmw_zenoh: type name and hash follow the topic)."""
    b = cfg.bridge
    name = topic.strip("/")
    if b.key_mode == "rmw_zenoh":
        return f"{b.domain_id}/{name}" if name.endswith("**") else f"{b.domain_id}/{name}/**"
    prefix = b.ros2dds_namespace.strip("/")
    return f"{prefix}/{name}" if prefix else name


def command_keys(cfg: SimConfig, names: VehicleNames) -> list[str]:
    """The keys one vehicle is commanded on."""
    topics = names.topics()
    return [key_expr(cfg, topics[t]) for t in COMMAND_TOPICS]


def sensor_keys(cfg: SimConfig) -> list[str]:
    """Every key the simulator publishes for ``cfg``'s vehicles: clock, TF, each vehicle's state, sensor,
    spray, battery and fault topics and its cameras' topics, and the spray deposit grid."""
    rigs = cfg.camera_rigs()
    topics: list[str] = [spray_deposit_topic(cfg.bridge.namespace)]
    for vehicle, names in fleet_names(cfg).items():
        own = names.topics()
        topics += [t for k, t in own.items() if k not in COMMAND_TOPICS]
        topics += [spray_state_topic(names.namespace), battery_state_topic(names.namespace)]
        topics += [faults_topic(names.namespace)]
        topics += [f"/{names.namespace}/{cam.name}/**" for cam in rigs.get(vehicle, [])]
    return sorted({key_expr(cfg, t) for t in topics})


def _rule(rule_id: str, messages: list[str], flows: list[str], keys: list[str]) -> dict[str, Any]:
    return {"id": rule_id, "messages": messages, "flows": flows, "permission": "allow", "key_exprs": keys}


def access_control(cfg: SimConfig, simulator: str, clients: Mapping[str, str]) -> dict[str, Any]:
    """Zenoh's ``access_control`` section for the router between the simulator and its remote clients.

    ``simulator``: the common name of the simulator's certificate (both of a run's sessions present
    it). ``clients``: certificate common name -> the vehicle that client may command. Flows are the
    router's: ``ingress`` from the subject, ``egress`` to it. Everything not allowed here is denied,
    on every link of the router (so a link between routers needs its own subject and rules).
    """
    names = fleet_names(cfg)
    unknown = sorted(set(clients.values()) - set(names))
    if unknown:
        have = ", ".join(names)
        raise ValueError(f"clients name vehicles not in the config: {', '.join(unknown)} (it has {have})")
    sensors = sensor_keys(cfg)
    commands = sorted({k for n in names.values() for k in command_keys(cfg, n)})
    rules = [
        _rule("simulator_publishes_sensors", ["put"], ["ingress"], sensors),
        _rule("simulator_learns_sensor_subscribers", ["declare_subscriber"], ["egress"], sensors),
        _rule("simulator_subscribes_commands", ["declare_subscriber"], ["ingress"], commands),
        _rule("simulator_receives_commands", ["put"], ["egress"], commands),
        _rule("clients_subscribe_sensors", ["declare_subscriber"], ["ingress"], sensors),
        _rule("clients_receive_sensors", ["put"], ["egress"], sensors),
        _rule("ros_graph", _LIVELINESS, ["ingress", "egress"], list(GRAPH_KEYS)),
    ]
    subjects: list[dict[str, Any]] = [{"id": "simulator", "cert_common_names": [simulator]}]
    policies: list[dict[str, Any]] = [
        {
            "id": "simulator",
            "subjects": ["simulator"],
            "rules": [r["id"] for r in rules if r["id"].startswith("simulator_")] + ["ros_graph"],
        }
    ]
    by_vehicle: dict[str, list[str]] = {}
    for common_name, vehicle in clients.items():
        by_vehicle.setdefault(vehicle, []).append(common_name)
    for vehicle, common_names in sorted(by_vehicle.items()):
        keys = command_keys(cfg, names[vehicle])
        rules.append(_rule(f"commands_{vehicle}", ["put"], ["ingress"], keys))
        rules.append(_rule(f"command_subscribers_{vehicle}", ["declare_subscriber"], ["egress"], keys))
        subjects.append({"id": f"clients_{vehicle}", "cert_common_names": sorted(common_names)})
        policies.append(
            {
                "id": f"clients_{vehicle}",
                "subjects": [f"clients_{vehicle}"],
                "rules": [
                    "clients_subscribe_sensors",
                    "clients_receive_sensors",
                    "ros_graph",
                    f"commands_{vehicle}",
                    f"command_subscribers_{vehicle}",
                ],
            }
        )
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def router_config(
    listen: list[str],
    ca: str,
    cert: str,
    key: str,
    acl: dict[str, Any] | None = None,
    connect: list[str] | None = None,
) -> dict[str, Any]:
    """A whole Zenoh router configuration: ``listen`` (``tls/HOST:PORT``), mutual TLS with the CA
    ``ca`` and the router's ``cert``/``key``, multicast scouting off, and the ``acl`` when given."""
    conf: dict[str, Any] = {
        "mode": "router",
        "listen": {"endpoints": list(listen)},
        "connect": {"endpoints": list(connect or [])},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"link": {"tls": tls_entries(ca, cert, key, mtls=True)}},
    }
    if acl is not None:
        conf["access_control"] = acl
    return conf


def main(argv: list[str] | None = None) -> None:
    """Print a router configuration with the ACL for a simulator config (docs/security.md)."""
    from droneulator.runtime import preflight

    p = argparse.ArgumentParser(
        prog="python -m droneulator.runtime.zenoh_security",
        description="Print a Zenoh router configuration (JSON5) with mutual TLS and the simulator's ACL.",
    )
    p.add_argument("--config", help="the simulator's config file (its vehicles, namespace and key mode)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--listen", action="append", required=True, help="e.g. tls/0.0.0.0:7447")
    p.add_argument("--ca", required=True)
    p.add_argument("--cert", required=True, help="the router's certificate")
    p.add_argument("--key", required=True, help="the router's private key")
    p.add_argument("--simulator", default="droneulator", help="the simulator certificate's common name")
    p.add_argument("--client", action="append", default=[], metavar="CN=VEHICLE")
    args = p.parse_args(argv)
    cfg = preflight.load(args.config, args.overrides)
    clients = dict(c.split("=", 1) for c in args.client)
    try:  # the files are the router host's: not checked here, where the file may only be written
        acl = access_control(cfg, args.simulator, clients)
    except ValueError as exc:
        sys.exit(str(exc))
    json.dump(router_config(args.listen, args.ca, args.cert, args.key, acl), sys.stdout, indent=2)
    print()


if __name__ == "__main__":
    main()
