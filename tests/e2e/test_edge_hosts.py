"""Two hosts made of Linux network namespaces joined by a veth link (slow; needs root, as in CI).

The test creates and removes everything itself: namespaces ``cs<pid>cell`` and ``cs<pid>edge``, a
veth pair with addresses it assigns to its own two ends (10.213.7.0/24: nothing leaves them). The
cell host runs a router and the estimator; the edge host runs ``cellsight run`` with
``[cell] role = "edge"``: its own router, peered with the cell's over the link, and a simulated
camera's driver. Proved: the camera's markers reach the estimator across the link and it
localises; images stay on the edge host (the link carries kilobytes, not video) unless someone on
the cell host subscribes to them; with the link down for 5 s the camera goes stale and comes back
by itself once it is up, and the recorder on the cell host marks the gap in its log. Namespaces share /dev/shm, through which zenoh would pass images between
the routers; the cell host turns shared memory off, as a second machine has none to share.

With the secure profile, router to router: the edge host's router (``edge_router.json5``) joins the
cell's over mutual TLS and its camera's messages arrive; an edge router whose certificates come from
another authority never joins, though its own camera runs beside it.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from cellsight.config import load_config
from cellsight.scenario_config import cell_config_of
from drivers.sim.scenario import load_scenario
from schemas.log import ReadReport, read_log
from schemas.security import EDGE_LISTEN, write_profile
from tests.helpers import wait_until
from tests.hosts import CELL_DEV, CELL_IP, EDGE_DEV, can_make_hosts, in_ns, ip, rx_bytes, stop_all, two_hosts

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not can_make_hosts(), reason="needs root and iproute2 (CI has both)"),
]
CELL_ROUTER = f"tcp/{CELL_IP}:7447"
CLI = [sys.executable, "-m", "cellsight.cli"]


@pytest.fixture()
def hosts() -> Iterator[tuple[str, str]]:
    with two_hosts() as pair:
        yield pair


def test_an_edge_hosts_camera_localises_across_the_link_and_survives_it_dropping(
    hosts: tuple[str, str], tmp_path: Path
) -> None:
    cell, edge = hosts
    scenario = load_scenario()
    (tmp_path / "base.toml").write_text(
        f'[cell]\nname = "net"\n[transport]\nconnect = ["{CELL_ROUTER}"]\nshared_memory = false\n'
    )
    cell_cfg = cell_config_of(scenario, None, load_config(tmp_path / "base.toml"))
    (tmp_path / "cell.toml").write_text(cell_cfg.to_toml())
    edge_cfg = cell_cfg.model_copy(
        update={
            "cell": cell_cfg.cell.model_copy(update={"role": "edge", "upstream": [CELL_ROUTER]}),
            "transport": cell_cfg.transport.model_copy(
                update={"connect": ["tcp/127.0.0.1:7447"], "shared_memory": True}
            ),
            "cameras": [c for c in cell_cfg.cameras if c.id == "cam1"],
        }
    )
    (tmp_path / "edge.toml").write_text(edge_cfg.to_toml())
    procs = [in_ns(cell, CLI + ["router", "--listen", CELL_ROUTER, "--no-shared-memory"], tmp_path / "cell_router.log")]
    wait_listening(tmp_path / "cell_router.log")
    procs.append(
        in_ns(cell, CLI + ["estimator", "--cell-config", str(tmp_path / "cell.toml")], tmp_path / "estimator.log")
    )
    echo = in_ns(
        cell,
        CLI + ["bus", "echo", "cellsight/net/estimate/status", "--json", "--cell-config", str(tmp_path / "cell.toml")],
        tmp_path / "echo.log",
        stdout=subprocess.PIPE,
        text=True,
    )
    procs.append(echo)
    states: list[tuple[float, str]] = []  # (monotonic s, cam1's state)

    def read() -> None:
        for line in echo.stdout:
            try:
                msg = json.loads(line)["message"]
            except (ValueError, KeyError):
                continue
            cams = {c.get("camera_id"): c.get("state") for c in msg.get("cameras", [])}
            if "cam1" in cams:
                states.append((time.monotonic(), cams["cam1"]))

    threading.Thread(target=read, daemon=True).start()
    procs.append(
        in_ns(
            edge, CLI + ["run", str(tmp_path / "edge.toml"), "--out", str(tmp_path / "edge_run")], tmp_path / "edge.log"
        )
    )
    try:
        wait_until(
            lambda: states and states[-1][1] == "LOCALIZED",
            90.0,
            "cam1 localised by the cell's estimator across the link",
        )
        # Images stay on the edge host: with nobody on the cell host asking, the link carries the
        # markers, camera info, status and the simulator's truth (~220 kB/s at 30 Hz), not 640x480
        # RGB-D (1.5 MB a frame: over 1 MB/s at even 1 frame/s).
        before, t0 = rx_bytes(cell, CELL_DEV), time.monotonic()
        time.sleep(3.0)
        rate = (rx_bytes(cell, CELL_DEV) - before) / (time.monotonic() - t0)
        assert rate < 1_000_000, f"{rate / 1e3:.0f} kB/s crossed the link: images are leaving the edge host"
        # ... and they do cross when someone on the cell host asks (the measurement can tell).
        viewer = in_ns(
            cell,
            CLI + ["bus", "echo", "cellsight/net/cam1/depth/image_raw", "--cell-config", str(tmp_path / "cell.toml")],
            tmp_path / "viewer.log",
        )
        time.sleep(2.0)
        before, t0 = rx_bytes(cell, CELL_DEV), time.monotonic()
        time.sleep(3.0)
        asked = (rx_bytes(cell, CELL_DEV) - before) / (time.monotonic() - t0)
        viewer.terminate()
        viewer.wait(20)
        assert asked > 10 * rate and asked > 1_000_000, (
            f"{asked / 1e3:.0f} kB/s with a depth subscriber on the cell host"
        )
        recorder = in_ns(
            cell,
            CLI
            + [
                "record",
                "--out",
                str(tmp_path / "cell.mcap"),
                "--keys",
                "cellsight/net/*/status",
                "--keys",
                "cellsight/net/*/markers",
                "--cell-config",
                str(tmp_path / "cell.toml"),
            ],
            tmp_path / "recorder.log",
        )
        procs.append(recorder)
        # Heard before the link drops, or there is no silence to mark: the recorder's file appears once
        # it has started (its imports took over 3 s on a loaded machine), then a few statuses come.
        wait_until(lambda: (tmp_path / "cell.mcap").exists(), 60.0, "the recorder to start")
        time.sleep(3.0)
        ip("-n", edge, "link", "set", EDGE_DEV, "down")
        down_at = time.monotonic()
        wait_until(lambda: states[-1][1] == "STALE", 5.0, "cam1 stale while its host's link is down")
        time.sleep(max(5.0 - (time.monotonic() - down_at), 0.0))
        ip("-n", edge, "link", "set", EDGE_DEV, "up")
        wait_until(lambda: states[-1][1] == "LOCALIZED", 60.0, "cam1 back once the link is up")
        # The recorder on the cell host marked the silence in its log.
        time.sleep(1.0)
        recorder.terminate()
        assert recorder.wait(20) == 0
        report = ReadReport()
        for _ in read_log(tmp_path / "cell.mcap", report=report):
            pass
        assert [(g.camera, 4.0 <= g.seconds <= 30.0) for g in report.gaps()] == [("cam1", True)], report.gaps()
        edge_run = json.loads((tmp_path / "edge_run" / "processes.json").read_text())
        assert {p["name"] for p in edge_run} == {
            "router",
            "driver/cam1",
        }  # no estimator, recognition or recorder on the edge
        assert not any(p["restarts"] for p in edge_run), f"edge processes restarted instead of reconnecting: {edge_run}"
    finally:
        stop_all(procs)


def wait_listening(log: Path) -> None:
    """Until a ``cellsight router`` logs that it listens: a bus echo started before gives up at once."""
    wait_until(
        lambda: log.exists() and "router listening" in log.read_text(errors="replace"),
        30.0,
        f"{log.name}: router listening",
    )


def _statuses(echo: subprocess.Popen, seen: dict[str, float], other: list[str] | None = None) -> None:
    """Record, per camera, when its first status message came out of ``echo`` (a --json bus echo);
    the last lines that were not statuses (its errors) go to ``other``."""
    for line in echo.stdout:
        try:
            camera = json.loads(line)["key"].split("/")[2]
        except (ValueError, KeyError, IndexError):
            if other is not None:
                other[:] = (other + [line.rstrip()])[-20:]
            continue
        seen.setdefault(camera, time.monotonic())


def _what_ran(procs: dict[str, subprocess.Popen], logs: list[Path], lines: int = 15) -> str:
    """For a failure message: which processes still run, and the tails of their logs."""
    out = [f"{name}: {'running' if p.poll() is None else f'exited {p.returncode}'}" for name, p in procs.items()]
    for log in logs:
        tail = log.read_text(errors="replace").splitlines()[-lines:] if log.exists() else ["(no log)"]
        out += [f"--- {log.name}", *tail]
    return "\n".join(out)


def test_with_the_secure_profile_only_an_edge_router_of_the_cells_authority_joins(
    hosts: tuple[str, str], tmp_path: Path
) -> None:
    cell, edge = hosts
    secure_router = f"tls/{CELL_IP}:7447"
    pki = write_profile(tmp_path / "pki", "net", listen=secure_router, hosts=(CELL_IP,))
    rogue = write_profile(tmp_path / "rogue", "net", listen=secure_router, hosts=(CELL_IP,))  # same names, another CA
    (tmp_path / "base.toml").write_text('[cell]\nname = "net"\n')
    base = cell_config_of(load_scenario(), None, load_config(tmp_path / "base.toml"))
    edge_cfg = base.model_copy(
        update={
            "cell": base.cell.model_copy(
                update={"role": "edge", "upstream": [secure_router], "router_config": pki.edge_router_config}
            ),
            "transport": base.transport.model_copy(
                update={"zenoh_config": pki.role_configs["driver"], "connect": [EDGE_LISTEN]}
            ),
            "cameras": [c for c in base.cameras if c.id == "cam1"],
        }
    )
    (tmp_path / "edge.toml").write_text(edge_cfg.to_toml())
    rogue_listen = EDGE_LISTEN.replace("7447", "7448")
    rogue_cfg = base.model_copy(
        update={
            "transport": base.transport.model_copy(
                update={"zenoh_config": rogue.role_configs["driver"], "connect": [rogue_listen]}
            )
        }
    )
    (tmp_path / "rogue.toml").write_text(rogue_cfg.to_toml())

    procs = [
        in_ns(
            cell,
            CLI + ["router", "--config", str(pki.router_config), "--no-shared-memory"],
            tmp_path / "cell_router.log",
        )
    ]
    wait_listening(tmp_path / "cell_router.log")
    at_cell: dict[str, float] = {}
    echo = in_ns(
        cell,
        CLI + ["bus", "echo", "cellsight/net/*/status", "--json", "--config", str(pki.role_configs["viewer"])],
        tmp_path / "echo.log",
        stdout=subprocess.PIPE,
        text=True,
    )
    procs.append(echo)
    threading.Thread(target=_statuses, args=(echo, at_cell), daemon=True).start()
    # The rogue edge host: its router and a camera, all with certificates of the other authority.
    # The echo gives up at once if the router does not listen yet, and the simulated camera runs
    # for only ~15 s: router first, then the echo, then the camera.
    rogue_router_log = tmp_path / "rogue_router.log"
    rogue_procs = {
        "rogue router": in_ns(
            edge,
            CLI
            + [
                "router",
                "--config",
                str(rogue.edge_router_config),
                "--listen",
                rogue_listen,
                "--connect",
                secure_router,
            ],
            rogue_router_log,
        )
    }
    procs += rogue_procs.values()
    wait_listening(rogue_router_log)
    rogue_procs["rogue echo"] = in_ns(
        edge,
        CLI
        + [
            "bus",
            "echo",
            "cellsight/net/*/status",
            "--json",
            "--config",
            str(rogue.role_configs["viewer"]),
            "--connect",
            rogue_listen,
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    procs.append(rogue_procs["rogue echo"])
    at_rogue: dict[str, float] = {}
    rogue_echo_errors: list[str] = []
    threading.Thread(
        target=_statuses, args=(rogue_procs["rogue echo"], at_rogue, rogue_echo_errors), daemon=True
    ).start()
    rogue_procs["rogue driver"] = in_ns(
        edge,
        CLI + ["driver", "sim", "--camera", "cam2", "--cell-config", str(tmp_path / "rogue.toml")],
        tmp_path / "rogue_driver.log",
    )
    procs.append(rogue_procs["rogue driver"])
    procs.append(
        in_ns(
            edge, CLI + ["run", str(tmp_path / "edge.toml"), "--out", str(tmp_path / "edge_run")], tmp_path / "edge.log"
        )
    )
    try:
        wait_until(
            lambda: "cam1" in at_cell,
            90.0,
            "the legitimate edge camera's status at the cell, over mutual TLS router to router",
        )
        try:
            wait_until(lambda: "cam2" in at_rogue, 60.0, "the rogue camera running on its own router")
        except AssertionError as e:
            logs = [rogue_router_log, tmp_path / "rogue_driver.log"]
            raise AssertionError(
                f"{e}\n{_what_ran(rogue_procs, logs)}\n--- rogue echo\n" + "\n".join(rogue_echo_errors)
            ) from None
        time.sleep(5.0)  # several of its 1 Hz status messages, had the rogue router been let in
        assert "cam2" not in at_cell, "an edge router with another authority's certificate got its camera into the cell"
    finally:
        stop_all(procs)
