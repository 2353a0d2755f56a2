"""Opening ``wss://`` connections to the API server, many times, and counting the ones that hang.

Each round starts an :class:`~droneulator.api.ApiServer` with TLS (a self-signed certificate made
by the openssl CLI), opens a :class:`~droneulator.api.DroneulatorClient`, pings, and closes. The
figure is the count of rounds that failed (a hang ends at ``--timeout``), with the server's TLS 1.3
session tickets off (as shipped, ``server_ssl_context``) and, for comparison in the same run, on
(``--tickets N``, OpenSSL's default 2). Run it with cores kept busy to see the race tickets cause:
``python3 -c 'while 1: pass' &`` twice.
"""

from __future__ import annotations

import argparse
import subprocess
import tempfile
import time
from pathlib import Path

from _common import write
from tqdm import tqdm

from droneulator.api import ApiServer, DroneulatorClient
from droneulator.api.access import server_ssl_context
from droneulator.commands import CommandPath
from droneulator.config import load_config
from droneulator.world import World

TOKEN = "benchmark-token"


def certificate(d: Path) -> tuple[str, str]:
    cert, key = d / "cert.pem", d / "key.pem"
    subprocess.run(
        ["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
         "-keyout", str(key), "-out", str(cert), "-days", "1", "-subj", "/CN=localhost",
         "-addext", "subjectAltName=DNS:localhost,IP:127.0.0.1"],
        check=True, capture_output=True,
    )  # fmt: skip
    return str(cert), str(key)


def rounds(world: World, cert: str, key: str, n: int, tickets: int | None, timeout: float) -> dict:
    ctx = server_ssl_context(cert, key)
    assert ctx is not None
    if tickets is not None:
        ctx.num_tickets = tickets
    failed: list[str] = []
    t0 = time.perf_counter()
    for _ in tqdm(range(n), desc=f"tickets {ctx.num_tickets}", unit="conn"):
        with ApiServer(CommandPath(world), port=0, token=TOKEN, ssl_context=ctx) as s:
            try:
                with DroneulatorClient(f"wss://127.0.0.1:{s.port}", timeout=timeout, token=TOKEN,
                                       cafile=cert) as c:  # fmt: skip
                    c.ping()
            except Exception as e:  # noqa: BLE001 - every failure is the figure
                failed.append(repr(e))
    return {"tickets": ctx.num_tickets, "rounds": n, "failed": len(failed), "errors": sorted(set(failed)),
            "seconds": time.perf_counter() - t0}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rounds", type=int, default=1000, help="connections per setting (default 1000)")
    ap.add_argument("--tickets", type=int, default=2,
                    help="session tickets of the comparison run (default 2, OpenSSL's; -1: no comparison)")
    ap.add_argument("--timeout", type=float, default=5.0, help="the client's open timeout, s (default 5)")
    ap.add_argument("--out", help="JSON path (default benchmarks/results/tls_handshakes.json)")
    a = ap.parse_args()
    world = World(load_config())
    with tempfile.TemporaryDirectory() as d:
        cert, key = certificate(Path(d))
        runs = [rounds(world, cert, key, a.rounds, None, a.timeout)]
        if a.tickets >= 0:
            runs.append(rounds(world, cert, key, a.rounds, a.tickets, a.timeout))
    for r in runs:
        print(f"tickets {r['tickets']}: {r['failed']} of {r['rounds']} connections failed "
              f"({r['seconds']:.0f} s) {r['errors']}")  # fmt: skip
    write("tls_handshakes", {"runs": runs})


if __name__ == "__main__":
    main()
