"""Joining a Ray cluster, for the commands that spread work over machines (``train --ray``, ``sweep``).

Ray is an optional extra (``pip install 'droneulator[ray]'``): nothing here imports it until a command
asks for a cluster, so the base install and its start-up time do not grow. ``--ray`` takes

* ``local``: start a one-machine Ray for this command (stopped when it ends);
* ``auto``: join the cluster this machine belongs to (``ray start`` ran here: its address file);
* ``HOST:PORT`` or ``ray://HOST:PORT``: the head node of a running cluster (``ray start --head``
  printed it).

The cluster must run the same Droneulator, Python and Ray versions as this machine: tasks and env
runners import ``droneulator`` on whichever node Ray places them.
"""

from __future__ import annotations

import contextlib
import logging
import socket
from collections.abc import Iterator
from typing import Any

log = logging.getLogger("droneulator.cluster")

#: the Ray the project is tested with (the ``ray`` extra pins it)
RAY_EXTRA = "pip install 'droneulator[ray]' (or bash scripts/setup.sh --dev)"


class ClusterError(RuntimeError):
    """Ray is not installed, or the cluster named by ``--ray`` cannot be reached."""


def import_ray() -> Any:
    """The ``ray`` module, or a :class:`ClusterError` that says how to install it."""
    try:
        import ray
    except ImportError:
        raise ClusterError(f"--ray needs Ray: {RAY_EXTRA}") from None
    return ray


def check_address(address: str) -> str:
    """``local``, ``auto``, ``HOST:PORT`` or ``ray://HOST:PORT``, else a ValueError naming the forms."""
    if address in ("local", "auto"):
        return address
    rest = address.removeprefix("ray://")
    host, sep, port = rest.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(
            f"--ray {address!r}: give 'local' (start Ray here), 'auto' (the cluster this machine belongs "
            "to) or the head node's HOST:PORT"
        )
    return address


def _probe(address: str, timeout: float = 3.0) -> None:
    """Fail at once when nothing listens at ``address`` (Ray itself retries for minutes)."""
    host, _, port = address.removeprefix("ray://").rpartition(":")
    try:
        socket.create_connection((host, int(port)), timeout=timeout).close()
    except OSError as e:
        raise ClusterError(f"--ray {address}: no Ray head node answers there ({e.strerror or e})") from None


@contextlib.contextmanager
def connect(
    address: str, num_cpus: int | None = None, worker_env: dict[str, str] | None = None
) -> Iterator[Any]:
    """Connect this process to Ray (see the module docstring) for the ``with`` block; yields ``ray``.

    ``num_cpus`` limits a ``local`` Ray (default: every core). ``worker_env``: environment variables of
    every worker this process's job starts (Ray's ``runtime_env``), on whichever node. A process already
    connected (a test's cluster, a notebook) is used as it is and left connected.
    """
    ray = import_ray()
    address = check_address(address)
    if ray.is_initialized():
        yield ray
        return
    kwargs: dict[str, Any] = {
        "include_dashboard": False,
        "log_to_driver": False,
        "logging_level": logging.WARNING,
        "runtime_env": {"env_vars": dict(worker_env)} if worker_env else None,
    }
    if address == "local":
        kwargs["num_cpus"] = num_cpus
    else:
        if address != "auto":
            _probe(address)
        kwargs["address"] = address
    try:
        ray.init(**{k: v for k, v in kwargs.items() if v is not None})
    except ConnectionError as e:
        raise ClusterError(f"--ray {address}: no Ray cluster answers there ({e})") from None
    log.info("Ray: %s CPUs, %d node(s)", ray.cluster_resources().get("CPU", 0), len(ray.nodes()))
    try:
        yield ray
    finally:
        ray.shutdown()
