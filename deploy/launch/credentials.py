"""A run's credentials, made by the launcher before anything starts (docs/security.md).

V2X (``--sign``): the launcher is the run's authority (``protocol.security.Authority``).
It gives each connected vehicle a key pair and a certificate valid for the run's sim
time, written to ``<run>/credentials/agent<vid>.v2x.json`` (readable by its owner
only); the world gets the authority's public key on its command line.

Zenoh (``--lock-down``; on by default for ``autocast deploy``): one user name and a
random password per process and per router, a dictionary of them for the routers
(``transport.auth.usrpwd``), and an access-control list (``access_control``) that
lets every process subscribe, query and receive on the run's keys but put, reply and
hold liveliness tokens only on its own: an agent on its ``cmd``, ``report``,
``rejected`` and ``net/.../tx|up/<vid>`` keys (in each scheduler domain of the map) and
its token, the world on the world's keys and the scans, the proxy on ``net/.../rx`` (each
domain's), ``net/stats``, the EMP downlinks and
its token, a participant the world is told to wait for (``--wait-for NAME``) on its
token ``alive/p/NAME`` alone, the launcher only its liveliness token (a compose run's
world waits for it), the recorder on nothing. A session without a password from the
dictionary cannot connect at all. Each process's Zenoh config is
``<run>/credentials/<name>.zenoh.json5`` (a participant's: ``participant-NAME``); each router's (or the single-host hub's)
``<run>/credentials/router-<name>.zenoh.json5`` with the dictionary beside it.

Routers link to each other over mutual TLS (``transport.link.tls``, a certificate per
router from the run's own CA, its name as common name): a password proves who opened a
link to the router that accepted it, not the other way round, so the router that
connected could not tell the other router from a stranger and its ACL (default deny)
would cut the link; a certificate names both ends (measured: with passwords alone a
put never crossed from one router to the other).
"""

from __future__ import annotations

import datetime
import ipaddress
import json
import secrets
from dataclasses import dataclass, replace
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

from deploy.launch import table
from protocol import keys
from protocol.security import Authority

VALIDITY_MARGIN_S = 60.0  # certificates outlive the run's sim-time limit by this much
LAUNCHER = "launcher"
HUB = "hub"  # the single-host hub's router (the launcher's own session)
PARTICIPANT = "participant-"  # + NAME: the Zenoh user of a participant the world waits for (--wait-for NAME)
ALL_MESSAGES = ("put", "delete", "declare_subscriber", "query", "declare_queryable", "reply", "liveliness_token",
                "declare_liveliness_subscriber", "liveliness_query")
ASKING = ("declare_subscriber", "query", "declare_liveliness_subscriber", "liveliness_query")


def _private_dir(path: Path) -> Path:
    path.mkdir(mode=0o700, parents=True, exist_ok=True)
    return path


def _write_private(path: Path, text: str) -> Path:
    path.touch(mode=0o600, exist_ok=True)
    path.chmod(0o600)
    path.write_text(text)
    return path


def issue_v2x(cfg: table.RunConfig) -> table.RunConfig:
    """The run's authority and every connected vehicle's credentials; ``cfg`` with the
    authority's public key (which turns signing on in the table's command lines)."""
    authority = Authority(cfg.run_id)
    d = _private_dir(table.credentials_dir(cfg))
    until = cfg.params.duration_s + VALIDITY_MARGIN_S
    for vid in table.connected_vids(cfg.params):
        _write_private(table.v2x_credentials_path(cfg, vid), authority.issue(vid, 0.0, until).to_json())
    (d / "authority.pub").write_text(authority.public_key.hex() + "\n")
    return replace(cfg, authority=authority.public_key.hex())


# ---------------------------------------------------------------------------- Zenoh


@dataclass(frozen=True, slots=True)
class ZenohUsers:
    """User name -> password of every process and router of a run."""

    passwords: dict[str, str]

    @staticmethod
    def new(names: list[str]) -> ZenohUsers:
        return ZenohUsers({name: secrets.token_hex(16) for name in names})

    def dictionary(self) -> str:
        """The routers' ``dictionary_file``: one ``user:password`` per line."""
        return "".join(f"{u}:{p}\n" for u, p in sorted(self.passwords.items()))

    def client_config(self, name: str) -> str:
        return json.dumps({"transport": {"auth": {"usrpwd": {"user": name, "password": self.passwords[name]}}}},
                          indent=1) + "\n"

    def router_config(self, name: str, dictionary_file: Path, acl: dict, extra: dict | None = None) -> str:
        conf = {"transport": {"auth": {"usrpwd": {"user": name, "password": self.passwords[name],
                                                  "dictionary_file": str(dictionary_file)}}},
                "access_control": acl}
        return json.dumps(_merged(conf, extra or {}), indent=1) + "\n"


def _merged(a: dict, b: dict) -> dict:
    """``a`` with ``b``'s entries, tables merged key by key."""
    out = dict(a)
    for k, v in b.items():
        out[k] = _merged(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def own_keys(cfg: table.RunConfig, name: str) -> tuple[list[str], list[str]]:
    """What process ``name`` may put on, and the liveliness tokens it may hold."""
    run = cfg.run_id
    if name == table.WORLD:
        return [keys.world_tick(run), keys.world_truth(run), keys.world_outcome(run), keys.scan(run, "*"),
                keys.in_shm(keys.scan(run, "*")), keys.world_map(run), keys.mission(run, "*")], []
    net = table.net_domains(cfg.params)  # each scheduler domain has its own net keys
    if name == table.PROXY:
        rx = [k for c, d in net for k in (keys.net_ctrl_rx(run, c, d), keys.net_data_rx(run, c, d))]
        return [*rx, *map(keys.in_shm, rx), keys.net_stats(run), keys.net_emp_down(run, "*")], [keys.proxy_alive(run)]
    if name.startswith("agent"):
        vid = int(name[len("agent"):])
        tx = [k for c, d in net for k in (keys.net_ctrl_tx(run, vid, c, d), keys.net_data_tx(run, vid, c, d))]
        return [keys.cmd(run, vid), keys.report(run, vid), keys.rejected(run, vid), *tx,
                keys.net_emp_up(run, vid)], [keys.alive(run, vid)]
    if name == LAUNCHER:  # its token tells the world that the recorder is up (deploy.multihost.compose_launcher)
        return [], [keys.participant_alive(run, LAUNCHER)]
    if name.startswith(PARTICIPANT):  # its token, so the world may start; nothing else
        return [], [keys.participant_alive(run, name[len(PARTICIPANT):])]
    return [], []  # the recorder: it only listens


def participant_user(name: str) -> str:
    """The Zenoh user (and credentials file) of participant ``name`` (``--wait-for NAME``)."""
    return PARTICIPANT + name


def users_of(cfg: table.RunConfig) -> list[str]:
    """Every process of the run that gets a Zenoh password: the table's and the
    participants the world waits for."""
    return [spec.name for spec in table.processes(cfg)] + [participant_user(n) for n in cfg.wait_for]


def access_control(cfg: table.RunConfig, processes: list[str], routers: list[str]) -> dict:
    """The run's ACL: default deny; everyone may listen, ask and receive on the run's
    keys (and the routers' admin space); routers may do anything between themselves;
    each process may put (reply, hold a token) only on its own keys."""
    everything = [keys.everything(cfg.run_id), "@/**"]
    rules = [
        {"id": "receive", "permission": "allow", "flows": ["egress"], "messages": list(ALL_MESSAGES),
         "key_exprs": everything},
        {"id": "ask", "permission": "allow", "flows": ["ingress"], "messages": list(ASKING), "key_exprs": everything},
    ]
    subjects = [{"id": name, "usernames": [name]} for name in processes]
    subjects += [{"id": name, "cert_common_names": [name]} for name in routers]  # mutual TLS: known at both ends
    policies = [{"rules": ["receive", "ask"], "subjects": [*processes, *routers]}]
    if routers:
        rules.append({"id": "relay", "permission": "allow", "flows": ["ingress"], "messages": list(ALL_MESSAGES),
                      "key_exprs": everything})
        policies.append({"rules": ["relay"], "subjects": list(routers)})
    for name in processes:
        puts, tokens = own_keys(cfg, name)
        if puts:
            rules.append({"id": f"own-{name}", "permission": "allow", "flows": ["ingress"],
                          "messages": ["put", "delete", "declare_queryable", "reply"], "key_exprs": puts})
            policies.append({"rules": [f"own-{name}"], "subjects": [name]})
        if tokens:
            rules.append({"id": f"token-{name}", "permission": "allow", "flows": ["ingress"],
                          "messages": ["liveliness_token"], "key_exprs": tokens})
            policies.append({"rules": [f"token-{name}"], "subjects": [name]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def lock_down(cfg: table.RunConfig, routers: dict[str, str]) -> dict[str, Path]:
    """Write the Zenoh credentials of every process of ``cfg`` (and of the launcher) and
    the config of each router (name -> the address the others reach it at: its TLS
    certificate's subject alternative name); returns every config file by name."""
    processes = users_of(cfg) + [LAUNCHER]
    users = ZenohUsers.new(processes + list(routers))
    d = _private_dir(table.credentials_dir(cfg))
    dictionary = _write_private(d / "zenoh-users.txt", users.dictionary())
    acl = access_control(cfg, processes, list(routers))
    tls = router_certificates(cfg, routers)
    out = {name: _write_private(table.zenoh_config_path(cfg, name), users.client_config(name)) for name in processes}
    for router in routers:
        out[router] = _write_private(table.zenoh_config_path(cfg, router),
                                     users.router_config(router, dictionary, acl, {"transport": {"link": tls[router]}}))
    return out


def tls_files(cfg: table.RunConfig, router: str) -> list[Path]:
    """The run's CA certificate, the router's certificate and its key."""
    d = table.credentials_dir(cfg)
    return [d / "ca.pem", d / f"{router}.tls.pem", d / f"{router}.tls.key"]


def router_certificates(cfg: table.RunConfig, routers: dict[str, str], valid_days: float = 7.0) -> dict[str, dict]:
    """The run's own CA (its key is dropped once the routers' certificates are signed)
    and one certificate per router, common name its name, subject alternative name its
    address; returns each router's ``transport.link`` config."""
    now = datetime.datetime.now(datetime.timezone.utc)
    valid = (now - datetime.timedelta(minutes=10), now + datetime.timedelta(days=valid_days))
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"autocast run {cfg.run_id}")])
    ca = _certificate(ca_name, ca_name, ca_key.public_key(), ca_key, valid, ca=True)
    out = {}
    for router, address in routers.items():
        ca_pem, pem, key_path = tls_files(cfg, router)
        key = ec.generate_private_key(ec.SECP256R1())
        try:
            san: x509.GeneralName = x509.IPAddress(ipaddress.ip_address(address))
        except ValueError:
            san = x509.DNSName(address)
        cert = _certificate(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, router)]), ca_name, key.public_key(),
                            ca_key, valid, san=san)
        pem.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
        _write_private(key_path, key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                                   serialization.NoEncryption()).decode())
        out[router] = {"tls": {"root_ca_certificate": str(ca_pem), "enable_mtls": True,
                               "listen_certificate": str(pem), "listen_private_key": str(key_path),
                               "connect_certificate": str(pem), "connect_private_key": str(key_path)}}
    tls_files(cfg, "")[0].write_bytes(ca.public_bytes(serialization.Encoding.PEM))
    return out


def _certificate(subject: x509.Name, issuer: x509.Name, public_key, ca_key, valid: tuple, ca: bool = False,
                 san: x509.GeneralName | None = None) -> x509.Certificate:
    b = (x509.CertificateBuilder().subject_name(subject).issuer_name(issuer).public_key(public_key)
         .serial_number(x509.random_serial_number()).not_valid_before(valid[0]).not_valid_after(valid[1])
         .add_extension(x509.BasicConstraints(ca=ca, path_length=None), critical=True))
    if san is not None:
        b = b.add_extension(x509.SubjectAlternativeName([san]), critical=False)
    return b.sign(ca_key, hashes.SHA256())


def hub_config(cfg: table.RunConfig, extra: dict) -> Path:
    """The single-host hub's config (``autocast run --lock-down``): the launcher's router
    session requires every process's password and applies the run's ACL."""
    processes = users_of(cfg)
    users = ZenohUsers.new(processes + [HUB])
    d = _private_dir(table.credentials_dir(cfg))
    dictionary = _write_private(d / "zenoh-users.txt", users.dictionary())
    for name in processes:
        _write_private(table.zenoh_config_path(cfg, name), users.client_config(name))
    return _write_private(table.zenoh_config_path(cfg, HUB),
                          users.router_config(HUB, dictionary, access_control(cfg, processes, []), extra))
