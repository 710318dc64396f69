"""Try every cell of the access matrix against a running secure router, with each role's certificate.

``probe(profile)`` connects one client per role (the ``edge`` role through a real edge router
peered with the cell's), and then, for every cell of ``schemas.security.access_matrix``: puts on
the key and sees whether a reader got it, checks that each role's reader got every allowed put,
declares a liveliness token and lists what the cell sees, and queries ``estimate/map`` with every
role answering. A cell whose outcome is not what the matrix says is a violation. The test suite
and ``benchmarks.fuzz`` call it on a profile made for the purpose (the probe puts junk on real keys).
"""

from __future__ import annotations

import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field

from schemas import keys
from schemas.bus import Bus, TransportConfig, open_session
from schemas.security import ROLES, AccessCell, Profile, access_matrix

SETTLE_S = 0.5  # after the last expected message: time for a wrongly delivered one to arrive too


@dataclass
class ProbeResult:
    """Cells tried and the ones whose outcome differed from the matrix (``what``: what happened)."""

    cells: int = 0
    violations: list[tuple[AccessCell, str]] = field(default_factory=list)

    def judge(self, cell: AccessCell, happened: bool, what: str) -> None:
        """Count a cell; a violation where what happened (``what``, or its negation) is not what it allows."""
        self.cells += 1
        if happened != cell.allowed:
            self.violations.append((cell, what if happened else f"not {what}"))


def _wait(pred, timeout_s: float) -> None:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and not pred():
        time.sleep(0.02)


def probe(profile: Profile, cell: str, edge_listen: str, timeout_s: float = 10.0) -> ProbeResult:
    """Try every cell of the matrix; ``edge_listen``: a free TLS endpoint for the edge router."""
    matrix = access_matrix(cell)
    edge_router = open_session(TransportConfig(zenoh_config=profile.edge_router_config, listen=[edge_listen]))
    buses: dict[str, Bus] = {}
    subs = []
    try:
        for role in ROLES:
            config = profile.role_configs["driver" if role == "edge" else role]
            connect = [edge_listen] if role == "edge" else None
            buses[role] = Bus(TransportConfig(zenoh_config=config, connect=connect), cell)
        got: dict[str, set[tuple[str, str]]] = defaultdict(set)  # reader role -> (key, putting role)
        lock = threading.Lock()

        def reader(role: str):
            def seen(key: str, payload: bytes, _ns: int) -> None:
                with lock:
                    got[role].add((key, payload.decode(errors="replace")))

            return seen

        # A session's own puts and tokens reach its own subscribers without the router: every judgement
        # is made by another session, and the observer (a viewer) only reads.
        buses["observer"] = Bus(TransportConfig(zenoh_config=profile.role_configs["viewer"]), cell)
        for role, bus in buses.items():
            subs.append(bus.subscribe_raw(f"{keys.ROOT}/{cell}/**", reader(role)))
        time.sleep(0.5)  # subscriptions reach the routers (the edge one too)
        result = ProbeResult()
        _puts(buses, matrix, got, lock, timeout_s, result)
        _tokens(buses, matrix, cell, timeout_s, result)
        _queries(buses, matrix, result)
        return result
    finally:
        for sub in subs:
            sub.undeclare()
        for bus in buses.values():
            bus.close()
        edge_router.close()


def _puts(buses: dict[str, Bus], matrix: list[AccessCell], got, lock, timeout_s: float, result: ProbeResult) -> None:
    puts = [c for c in matrix if c.operation == "put"]
    # Denied puts first: zenoh keeps one session's order, so one that got through arrives before the last allowed one.
    for c in sorted(puts, key=lambda c: c.allowed):
        buses[c.role].session.put(c.key, c.role.encode())
    allowed = {(c.key, c.role) for c in puts if c.allowed}
    _wait(lambda: all({(k, r) for k, r in allowed if r != reader} <= got[reader] for reader in buses), timeout_s)
    time.sleep(SETTLE_S)
    with lock:
        delivered = got["observer"]
        for c in puts:
            result.judge(c, (c.key, c.role) in delivered, "delivered")
        for c in (c for c in matrix if c.operation == "subscribe"):
            result.cells += 1
            owners = {(k, r) for k, r in allowed if k == c.key and r != c.role}
            if not owners <= got[c.role]:
                result.violations.append((c, f"missed {sorted(r for _, r in owners - got[c.role])}'s put"))


def _tokens(buses: dict[str, Bus], matrix: list[AccessCell], cell: str, timeout_s: float, result: ProbeResult) -> None:
    cells = [c for c in matrix if c.operation == "liveliness"]
    tokens = [buses[c.role].session.liveliness().declare_token(c.key) for c in cells]
    try:
        expected = {c.key for c in cells if c.allowed}
        seen: set[str] = set()

        def look() -> bool:
            seen.clear()
            seen.update(buses["observer"].alive(timeout_s=1.0))
            return expected <= seen

        _wait(look, timeout_s)
        time.sleep(SETTLE_S)
        look()
        for c in cells:
            result.judge(c, c.key in seen, "token seen")
    finally:
        for t in tokens:
            t.undeclare()


def _queries(buses: dict[str, Bus], matrix: list[AccessCell], result: ProbeResult) -> None:
    answering = [c for c in matrix if c.operation == "answer"]
    queryables = [
        buses[c.role].session.declare_queryable(c.key, lambda q, role=c.role: q.reply(q.key_expr, role.encode()))
        for c in answering
    ]
    try:
        time.sleep(SETTLE_S)
        answers: dict[str, set[str]] = {}
        for c in (c for c in matrix if c.operation == "query"):
            replies = buses[c.role].session.get(c.key, timeout=2.0)
            answers[c.role] = {r.ok.payload.to_bytes().decode() for r in replies if r.ok is not None}
            result.cells += 1
            if not answers[c.role]:
                result.violations.append((c, "no answer"))
        every = set().union(*(got - {role} for role, got in answers.items()))  # a session's own answer is local
        for c in answering:
            result.judge(c, c.role in every, "answer delivered")
    finally:
        for q in queryables:
            q.undeclare()
