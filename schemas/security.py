"""The secure deployment profile: mutual TLS between every process and the router, and access control.

``write_profile`` makes a small certificate authority, a certificate for the router and one per
role (the certificate's common name is the role), and one zenoh JSON5 config per process kind:
the router's (TLS listen, client certificates required, access control) and each role's (TLS
connect with its own certificate). Processes then take ``--config ROLE.json5``.

Who may do what is decided at the router, by the common name of the client certificate:

- ``driver`` publishes camera topics (images, camera_info, markers, status) and ``truth/`` (the
  simulator's; a real driver has none);
- ``estimator`` publishes ``tf`` and ``estimate/``, and answers ``estimate/map`` queries;
- ``recognition`` publishes ``objects`` and ``points``;
- ``recorder``, ``viewer`` (Foxglove, ``cellsight status``) and ``robot`` only subscribe and query;
- ``edge`` is an edge host's router (``edge_router.json5``), peered with the cell's: it may put what
  a driver may. The cell's router enforces that; the edge router only authenticates its own
  clients (the host's drivers, with ``driver.json5`` pointed at it), so a compromised edge host
  reaches no further than its cameras' topics.

Every role may subscribe and query under its own cell, and hold a liveliness token only under its
own component's prefix (``alive/<component>/``, ``ALIVE``): a robot cannot pretend to be the
estimator. Camera topics are granted by wildcard (``*/markers``), and a wildcard also matches a
cell-wide key (``estimate/markers``); so each publishing role is also denied, explicitly, every
cell-wide family it does not own (``OWNS``), and zenoh's deny rules win over its allow rules. With a ROS 2
domain (``ros2_domain``), the same split holds on rmw_zenoh's keys (``<domain>/<topic>/...``):
only ``estimator`` may put ``/tf``, ``/tf_static`` and ``/cellsight/<camera>/pose``, only
``recognition`` ``/cellsight/objects`` and ``/cellsight/points``; every role, ``robot`` being the
one a ROS 2 node uses, may subscribe there and hold graph tokens (``@ros2_lv/<domain>/**``, what
``ros2 node list`` reads). Anything else is denied (the ACL's default), and a client without a
certificate from this authority never gets past the TLS handshake.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import json
from dataclasses import dataclass
from pathlib import Path

import zenoh
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from schemas import keys
from schemas.errors import BusError

#: What each role may publish, as key expressions relative to ``cellsight/<cell>/``.
_CAMERA_HOST = [f"*/{topic}" for topic in keys.CAMERA_TOPICS] + ["truth/**"]
PUBLISH: dict[str, list[str]] = {
    "driver": _CAMERA_HOST,
    "estimator": ["tf", "estimate/**"],
    "recognition": ["objects", "objects/scene", "points"],
    "recorder": [],
    "viewer": [],
    "robot": [],
    "edge": _CAMERA_HOST,  # an edge host's router: what its drivers may put
}
#: What each role may publish on rmw_zenoh's keys, relative to ``<domain>/`` (topic, then type and hash).
PUBLISH_ROS2: dict[str, list[str]] = {
    "estimator": ["tf/**", "tf_static/**", "cellsight/*/pose/**"],
    "recognition": ["cellsight/objects/**", "cellsight/points/**"],
}
#: The cell-wide first key chunks (``keys.RESERVED``, never a camera id) each publishing role owns;
#: it is denied puts under every other one, whatever its wildcards match.
OWNS: dict[str, frozenset[str]] = {
    "driver": frozenset({"truth"}),
    "estimator": frozenset({"tf", "estimate"}),
    "recognition": frozenset({"objects", "points"}),
    "edge": frozenset({"truth"}),
}
#: The liveliness component each role may hold tokens under (``alive/<component>/<id>``); none for the rest.
ALIVE: dict[str, str] = {
    "driver": "driver",
    "estimator": "estimator",
    "recognition": "recognition",
    "recorder": "recorder",
    "edge": "driver",
}
ROLES = tuple(PUBLISH)
#: The roles whose processes are zenoh clients (``edge`` is a router).
CLIENT_ROLES = tuple(role for role in ROLES if role != "edge")
#: Where an edge host's router listens for the drivers beside it.
EDGE_LISTEN = "tls/127.0.0.1:7447"
VALID_DAYS = 825


@dataclass(frozen=True)
class Profile:
    """Where ``write_profile`` put things: the CA certificate, and the zenoh config of each process kind."""

    directory: Path
    endpoint: str  # the router's TLS endpoint, as clients connect to it
    ca_certificate: Path
    router_config: Path
    role_configs: dict[str, Path]
    edge_router_config: Path  # an edge host's router: TLS to the cell's router and to its own drivers


def _key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def _write_key(path: Path, key: ec.EllipticCurvePrivateKey) -> None:
    path.write_bytes(
        key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())
    )
    path.chmod(0o600)


def _certificate(
    subject: str,
    key: ec.EllipticCurvePrivateKey,
    issuer: x509.Certificate | None,
    issuer_key: ec.EllipticCurvePrivateKey,
    *,
    ca: bool = False,
    hosts: tuple[str, ...] = (),
) -> x509.Certificate:
    now = dt.datetime.now(dt.UTC)
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, subject)])
    builder = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(issuer.subject if issuer else name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=VALID_DAYS))
        .add_extension(x509.BasicConstraints(ca=ca, path_length=0 if ca else None), critical=True)
    )
    if ca:
        builder = builder.add_extension(
            x509.KeyUsage(
                digital_signature=True,
                key_cert_sign=True,
                crl_sign=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
    else:
        builder = builder.add_extension(
            x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False
        )
        names: list[x509.GeneralName] = []
        for host in hosts:
            try:
                names.append(x509.IPAddress(ipaddress.ip_address(host)))
            except ValueError:
                names.append(x509.DNSName(host))
        names = names or [x509.DNSName(subject)]
        builder = builder.add_extension(x509.SubjectAlternativeName(names), critical=False)
    return builder.sign(issuer_key, hashes.SHA256())


def _issue(
    directory: Path, name: str, ca: x509.Certificate, ca_key: ec.EllipticCurvePrivateKey, hosts: tuple[str, ...] = ()
) -> tuple[Path, Path]:
    key = _key()
    cert = _certificate(name, key, ca, ca_key, hosts=hosts)
    cert_path, key_path = directory / f"{name}.pem", directory / f"{name}.key"
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    _write_key(key_path, key)
    return cert_path, key_path


def acl(cell: str, ros2_domain: int | None = None) -> dict:
    """The router's ``access_control`` section for one cell (zenoh 1.x schema); with ``ros2_domain``,
    rmw_zenoh's keys of that ROS 2 domain too."""
    base = f"{keys.ROOT}/{keys.check_name(cell, 'cell name')}"
    readable = [f"{base}/**"]
    if ros2_domain is not None:
        readable += [f"{int(ros2_domain)}/**", f"@ros2_lv/{int(ros2_domain)}/**"]
    ros2_graph = [f"@ros2_lv/{int(ros2_domain)}/**"] if ros2_domain is not None else []
    rules = [
        {
            "id": "read",
            "permission": "allow",
            "flows": ["ingress"],
            "messages": ["declare_subscriber", "query", "declare_liveliness_subscriber", "liveliness_query"],
            "key_exprs": readable,
        },
        # What the router hands out to subscribers and queriers.
        {
            "id": "deliver",
            "permission": "allow",
            "flows": ["egress"],
            "messages": [
                "put",
                "delete",
                "reply",
                "query",
                "liveliness_token",
                "declare_subscriber",
                "declare_queryable",
                "declare_liveliness_subscriber",
                "liveliness_query",
            ],
            "key_exprs": readable,
        },
        {
            "id": "answer_map",
            "permission": "allow",
            "flows": ["ingress"],
            "messages": ["declare_queryable", "reply"],
            "key_exprs": [keys.estimate_map(cell)],
        },
    ]
    own_rules: dict[str, list[str]] = {role: [] for role in ROLES}
    for role, topics in PUBLISH.items():
        ros2 = [f"{int(ros2_domain)}/{t}" for t in PUBLISH_ROS2.get(role, [])] if ros2_domain is not None else []
        if topics:
            rules.append(
                {
                    "id": f"publish_{role}",
                    "permission": "allow",
                    "flows": ["ingress"],
                    "messages": ["put", "delete"],
                    "key_exprs": [f"{base}/{t}" for t in topics] + ros2,
                }
            )
            foreign = sorted(keys.RESERVED - OWNS.get(role, frozenset()))
            rules.append(
                {
                    "id": f"deny_foreign_{role}",
                    "permission": "deny",
                    "flows": ["ingress"],
                    "messages": ["put", "delete"],
                    "key_exprs": [f"{base}/{r}/**" for r in foreign],
                }
            )
            own_rules[role] += [f"publish_{role}", f"deny_foreign_{role}"]
        tokens = ([f"{base}/alive/{ALIVE[role]}/*"] if role in ALIVE else []) + ros2_graph
        if tokens:
            rules.append(
                {
                    "id": f"alive_{role}",
                    "permission": "allow",
                    "flows": ["ingress"],
                    "messages": ["liveliness_token"],
                    "key_exprs": tokens,
                }
            )
            own_rules[role].append(f"alive_{role}")
    subjects = [{"id": role, "cert_common_names": [role]} for role in ROLES]
    policies = [{"rules": ["read", "deliver"], "subjects": list(ROLES)}]
    policies += [{"rules": names, "subjects": [role]} for role, names in own_rules.items() if names]
    policies.append({"rules": ["answer_map"], "subjects": ["estimator"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


#: The operations of the access matrix: put on a key, subscribe to it (receive what was put),
#: hold a liveliness token on it, query ``estimate/map`` and answer that query.
OPERATIONS = ("put", "subscribe", "liveliness", "query", "answer")


@dataclass(frozen=True)
class AccessCell:
    """Whether ``role`` may do ``operation`` on ``key`` (one representative key of a family)."""

    role: str
    family: str  # as the docs name it, e.g. "<camera>/markers", "estimate/status", "alive/driver"
    key: str
    operation: str
    allowed: bool


def _may_put(role: str, cell: str, key: str) -> bool:
    base = f"{keys.ROOT}/{cell}"
    first = key[len(base) + 1 :].split("/")[0]
    if first in keys.RESERVED and first not in OWNS.get(role, frozenset()):
        return False
    return any(zenoh.KeyExpr(f"{base}/{t}").intersects(zenoh.KeyExpr(key)) for t in PUBLISH[role])


def access_matrix(cell: str, camera: str = "cam1") -> list[AccessCell]:
    """Every cell of the access matrix the ACL grants, derived from the role definitions (``PUBLISH``,
    ``OWNS``, ``ALIVE``): put on each camera and cell-wide topic, subscribe to each (every role
    reads the whole cell), a token under each component's liveliness prefix, and the ``estimate/map``
    query (anyone asks, only the estimator answers). ``docs/deployment.md`` prints it; the
    access test tries each cell against the real router."""
    families = {f"<camera>/{t}": keys.camera_topic(cell, camera, t) for t in keys.CAMERA_TOPICS}
    families |= {t: keys.cell_topic(cell, t) for t in keys.CELL_TOPICS}
    components = sorted(set(ALIVE.values()))
    out = []
    for role in ROLES:
        for family, key in families.items():
            out.append(AccessCell(role, family, key, "put", _may_put(role, cell, key)))
            out.append(AccessCell(role, family, key, "subscribe", True))
        for comp in components:
            out.append(
                AccessCell(
                    role,
                    f"alive/{comp}",
                    keys.alive(cell, comp, f"probe_{role}"),
                    "liveliness",
                    ALIVE.get(role) == comp,
                )
            )
        out.append(AccessCell(role, "estimate/map", keys.estimate_map(cell), "query", True))
        out.append(AccessCell(role, "estimate/map", keys.estimate_map(cell), "answer", role == "estimator"))
    return out


def matrix_markdown(cell: str = "demo") -> str:
    """The access matrix as a Markdown table: a row per key family, a column per role; each cell
    lists the operations allowed (p put, s subscribe, l liveliness token, q query, a answer)."""
    letters = {"put": "p", "subscribe": "s", "liveliness": "l", "query": "q", "answer": "a"}
    cells = access_matrix(cell)
    families = list(dict.fromkeys(c.family for c in cells))
    grid = {(c.family, c.role): "" for c in cells}
    for c in cells:
        if c.allowed:
            grid[c.family, c.role] += letters[c.operation]
    lines = ["| key family | " + " | ".join(f"`{r}`" for r in ROLES) + " |", "|---" * (len(ROLES) + 1) + "|"]
    lines += [f"| `{f}` | " + " | ".join(grid[f, r] or "-" for r in ROLES) + " |" for f in families]
    return "\n".join(lines)


def write_profile(
    directory: Path,
    cell: str,
    listen: str = "tls/127.0.0.1:7447",
    hosts: tuple[str, ...] = ("127.0.0.1", "localhost"),
    ros2_domain: int | None = None,
) -> Profile:
    """Write a CA, the router's and every role's certificate and zenoh config into ``directory``.

    listen: the router's TLS endpoint; hosts: the names and addresses clients reach it by (they
    go into its certificate); ros2_domain: the ROS 2 domain whose rmw_zenoh keys the ACL covers
    (None: no ROS 2 traffic passes). Refuses to overwrite an existing authority.
    """
    directory = Path(directory).resolve()  # the configs name their files by absolute path
    if (directory / "ca.pem").exists():
        raise BusError(f"{directory} already holds a certificate authority (ca.pem); use a new directory")
    directory.mkdir(parents=True, exist_ok=True)
    ca_key = _key()
    ca = _certificate(f"cellsight {cell} CA", ca_key, None, ca_key, ca=True)
    ca_path = directory / "ca.pem"
    ca_path.write_bytes(ca.public_bytes(serialization.Encoding.PEM))
    _write_key(directory / "ca.key", ca_key)

    router_cert, router_key = _issue(directory, "router", ca, ca_key, hosts)
    router = {
        "mode": "router",
        "listen": {"endpoints": [listen]},
        "connect": {"endpoints": []},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {
            "link": {
                "protocols": ["tls"],
                "tls": {
                    "root_ca_certificate": str(ca_path),
                    "listen_certificate": str(router_cert),
                    "listen_private_key": str(router_key),
                    "enable_mtls": True,
                },
            }
        },
        "access_control": acl(cell, ros2_domain),
    }
    router_config = directory / "router.json5"
    router_config.write_text(json.dumps(router, indent=2))
    endpoint = listen.replace("0.0.0.0", hosts[0]) if hosts else listen
    role_configs = {}
    for role in CLIENT_ROLES:
        cert, key = _issue(directory, role, ca, ca_key)
        cfg = {
            "mode": "client",
            "connect": {"endpoints": [endpoint]},
            "scouting": {"multicast": {"enabled": False}},
            "transport": {
                "link": {
                    "protocols": ["tls"],
                    "tls": {
                        "root_ca_certificate": str(ca_path),
                        "connect_certificate": str(cert),
                        "connect_private_key": str(key),
                        "enable_mtls": True,
                    },
                }
            },
        }
        role_configs[role] = directory / f"{role}.json5"
        role_configs[role].write_text(json.dumps(cfg, indent=2))
    edge_cert, edge_key = _issue(directory, "edge", ca, ca_key, ("127.0.0.1", "localhost"))
    edge = {
        "mode": "router",
        "listen": {"endpoints": [EDGE_LISTEN]},
        "connect": {"endpoints": [endpoint]},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {
            "link": {
                "protocols": ["tls"],
                "tls": {
                    "root_ca_certificate": str(ca_path),
                    "enable_mtls": True,
                    "listen_certificate": str(edge_cert),
                    "listen_private_key": str(edge_key),
                    "connect_certificate": str(edge_cert),
                    "connect_private_key": str(edge_key),
                },
            }
        },
    }
    edge_config = directory / "edge_router.json5"
    edge_config.write_text(json.dumps(edge, indent=2))
    return Profile(directory, endpoint, ca_path, router_config, role_configs, edge_config)
