"""``drape acl``: the Zenoh access-control section for a Drape router, generated from a users file.

The users file (TOML, see ``deploy/users.example.toml``) lists every Zenoh user (the user name of
Zenoh's user/password authentication) with its role and Drape id::

    namespace = "drape"
    [[user]]
    name = "eu-1"         # Zenoh user name (transport/auth/usrpwd/user)
    role = "server"       # server | client
    id = "eu-1"           # the server id (role server) or the client id (role client)
    # password = "..."    # only read by --dictionary
    # cert_common_name = "eu-1.drape.example"   # with mutual TLS: the subject also needs this CN

The generated ``access_control`` section (Zenoh 1.x: rules, subjects, policies, default deny) binds
each user to the keys of its id (protocol 1.4's client-scoped keys, PROTOCOL.md 2 and 11.2). It lets

- a ``server`` user ``S`` declare its client-scoped request queryables
  ``{ns}/server/S/client/*/{submit,control,control_batch,remove}`` and ``{ns}/server/S/info`` and
  reply on them, publish bundles ``{ns}/client/*/states``, per-cloth states
  ``{ns}/client/*/cloth/*/state`` and its stats, declare its own server liveliness token and watch
  client liveliness tokens;
- a ``client`` user ``C`` query only its own request keys ``{ns}/server/*/client/C/{...}`` (and
  every server's info), subscribe only to ``{ns}/client/C/**`` (its bundle and its cloths' states)
  and the servers' stats, declare only its own client liveliness token and watch server tokens.

The server-wide request keys of 1.0-1.3 (``{ns}/server/S/submit``...), whose client id is only in
the payload, are denied to everyone: a deployment behind this router needs 1.4 clients, and its
servers should run with ``identity = "keys"`` (an ``open`` server's server-wide queryables are
simply never reached). The server takes a request's client id from its key, which the router has
bound to the user, so bob cannot submit, control or remove as alice (docs/reliability.md 3-4).

``--cloth-states`` is deprecated and has no effect: per-cloth states now live under their
client's key, readable by their owner only (1.3 had ``any``, which let every client read every
cloth's state).

Writes the section as JSON (``--out``, default stdout), or a whole router configuration
(``--router-config deploy/zenoh-router.json5 --out router.json5``), and optionally the
user/password dictionary file of Zenoh's usrpwd authentication (``--dictionary``).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from drape.client.protocol import CLIENT_REQUESTS, DEFAULT_NAMESPACE, ID_RE, NAMESPACE_RE, Keys

log = logging.getLogger(__name__)

ROLES = ("server", "client")
CLOTH_STATE_POLICIES = ("deny", "any")  # --cloth-states: deprecated, no effect since protocol 1.4
USER_RE = ID_RE  # Zenoh user names used as rule and subject ids: keep them to the id alphabet


@dataclass(frozen=True)
class User:
    name: str  # Zenoh usrpwd user name
    role: str  # server | client
    id: str  # server id or client id
    password: str | None = None
    cert_common_name: str | None = None


@dataclass(frozen=True)
class UsersFile:
    namespace: str
    users: tuple[User, ...]


def load_users(path: str | Path) -> UsersFile:
    """Read and check a users file; raises ValueError naming the entry and field at fault."""
    with open(path, "rb") as fh:
        try:
            data = tomllib.load(fh)
        except tomllib.TOMLDecodeError as err:
            raise ValueError(f"{path}: not valid TOML: {err}") from None
    unknown = set(data) - {"namespace", "user"}
    if unknown:
        raise ValueError(f"{path}: unknown top-level key(s) {sorted(unknown)}")
    ns = data.get("namespace", DEFAULT_NAMESPACE)
    if not isinstance(ns, str) or not NAMESPACE_RE.match(ns):
        raise ValueError(f"{path}: invalid namespace {ns!r}")
    entries = data.get("user", [])
    if not isinstance(entries, list) or not entries:
        raise ValueError(f"{path}: no [[user]] entries")
    users: list[User] = []
    names: set[str] = set()
    ids: dict[tuple[str, str], str] = {}
    for i, e in enumerate(entries):
        where = f"{path}: user[{i}]"
        if not isinstance(e, dict):
            raise ValueError(f"{where}: must be a table")
        extra = set(e) - {"name", "role", "id", "password", "cert_common_name"}
        if extra:
            raise ValueError(f"{where}: unknown key(s) {sorted(extra)}")
        name, role, id_ = e.get("name"), e.get("role"), e.get("id", e.get("name"))
        if not isinstance(name, str) or not USER_RE.match(name):
            raise ValueError(f"{where}: name must be 1-64 characters of [A-Za-z0-9_.-], got {name!r}")
        if role not in ROLES:
            raise ValueError(f"{where} ({name}): role must be one of {ROLES}, got {role!r}")
        if not isinstance(id_, str) or not ID_RE.match(id_):
            raise ValueError(f"{where} ({name}): id must be 1-64 characters of [A-Za-z0-9_.-], got {id_!r}")
        for opt in ("password", "cert_common_name"):
            if opt in e and not (isinstance(e[opt], str) and e[opt]):
                raise ValueError(f"{where} ({name}): {opt} must be a non-empty string")
        if name in names:
            raise ValueError(f"{where}: user name {name!r} appears twice")
        if (role, id_) in ids:
            raise ValueError(f"{where}: {role} id {id_!r} already belongs to user {ids[(role, id_)]!r}")
        names.add(name)
        ids[(role, id_)] = name
        users.append(User(name, role, id_, e.get("password"), e.get("cert_common_name")))
    return UsersFile(ns, tuple(users))


def _rules(rid: str, messages: list[str], flow: str, keys: list[str]) -> list[dict[str, Any]]:
    """One allow rule per message kind, ``{rid}-{message}``: each permission reads (and is audited)
    on its own."""
    return [
        {"id": f"{rid}-{m}", "messages": [m], "flows": [flow], "permission": "allow", "key_exprs": sorted(set(keys))}
        for m in messages
    ]


def server_queryables(keys: Keys, server: str, client: str = "*") -> list[str]:
    """The queryables of ``server`` a ``client`` (``*``: any) may reach: its client-scoped request
    keys and its info."""
    return [keys.client_request(k, server, client) for k in CLIENT_REQUESTS] + [keys.info(server)]


def server_rules(keys: Keys, user: User) -> list[dict[str, Any]]:
    """What a server user may do (ingress: from it into the router; egress: from the router to it)."""
    sid, p = user.id, f"u-{user.name}"
    queryables = server_queryables(keys, sid)
    states = [keys.client_state("*", "*"), keys.bundle("*")]
    states += [keys.every(k) for k in states]  # 1.8: the decimated keys (every k-th state)
    publications = [*states, keys.stats(sid)]
    keyframes = states  # 1.5: keyframe queries on what it publishes
    return [
        *_rules(f"{p}-serve", ["declare_queryable", "reply"], "ingress", queryables),
        *_rules(f"{p}-keyframes", ["declare_queryable", "reply"], "ingress", keyframes),
        *_rules(f"{p}-publish", ["put"], "ingress", publications),
        *_rules(f"{p}-token", ["liveliness_token"], "ingress", [keys.alive_server(sid)]),
        *_rules(
            f"{p}-watch", ["declare_liveliness_subscriber", "liveliness_query"], "ingress", [keys.all_clients_alive]
        ),
        # to the server: the queries, the subscriptions that make its publications matched (a client's
        # {ns}/client/C/** too, or the server would never send it anything), client tokens
        *_rules(f"{p}-queries", ["query"], "egress", queryables + keyframes),
        # (stats: the placement's {ns}/server/*/stats too: a subscription to the exact key only
        # would never reach the server, whose stats then went to nobody behind the router)
        *_rules(f"{p}-matched", ["declare_subscriber"], "egress", [keys.client_all("*"), keys.stats("*")]),
        # (the answers to a liveliness query travel as liveliness_query messages)
        *_rules(f"{p}-clients", ["liveliness_token", "liveliness_query"], "egress", [keys.all_clients_alive]),
    ]


def client_rules(keys: Keys, user: User, cloth_states: str = "deny", stats: bool = True) -> list[dict[str, Any]]:
    """What a client user may do: query its own request keys on any server (and info), read what
    is published for it (``{ns}/client/C/**``: its bundle and cloths) and the stats, declare only
    its own client token. ``cloth_states`` is deprecated and ignored (1.4)."""
    cid, p = user.id, f"u-{user.name}"
    requests = server_queryables(keys, "*", cid)
    readable = [keys.client_all(cid)]
    if stats:
        readable.append(keys.stats("*"))
    own = [keys.client_all(cid)]  # 1.5: keyframe queries on its own bundle and cloth state keys
    return [
        *_rules(f"{p}-request", ["query"], "ingress", requests + own),
        *_rules(f"{p}-subscribe", ["declare_subscriber"], "ingress", readable),
        *_rules(f"{p}-token", ["liveliness_token"], "ingress", [keys.alive_client(cid)]),
        *_rules(
            f"{p}-discover", ["declare_liveliness_subscriber", "liveliness_query"], "ingress", [keys.all_servers_alive]
        ),
        # to the client: replies on its own keys; the servers' queryables (declared for any client:
        # knowing one exists is harmless, only servers may declare them); what it may read; servers' tokens
        *_rules(f"{p}-replies", ["reply"], "egress", requests + own),
        *_rules(f"{p}-queryables", ["declare_queryable"], "egress", server_queryables(keys, "*") + own),
        *_rules(f"{p}-receive", ["put"], "egress", readable),
        *_rules(f"{p}-servers", ["liveliness_token", "liveliness_query"], "egress", [keys.all_servers_alive]),
    ]


def access_control(users: UsersFile, cloth_states: str = "deny", stats: bool = True) -> dict[str, Any]:
    """The router's ``access_control`` section (Zenoh 1.x format), default deny. ``cloth_states``:
    deprecated, no effect (per-cloth states are readable by their owner only since 1.4)."""
    if cloth_states not in CLOTH_STATE_POLICIES:
        raise ValueError(f"cloth_states must be one of {CLOTH_STATE_POLICIES}")
    if cloth_states != "deny":
        log.warning("--cloth-states is deprecated and has no effect: a client reads its own cloths' states only")
    keys = Keys(users.namespace)
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for u in users.users:
        mine = server_rules(keys, u) if u.role == "server" else client_rules(keys, u, cloth_states, stats)
        rules += mine
        subject: dict[str, Any] = {"id": f"s-{u.name}", "usernames": [u.name]}
        if u.cert_common_name:
            subject["cert_common_names"] = [u.cert_common_name]
        subjects.append(subject)
        policies.append({"id": f"p-{u.name}", "rules": [r["id"] for r in mine], "subjects": [subject["id"]]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def dictionary(users: UsersFile) -> str:
    """Zenoh's usrpwd dictionary file: one ``user:password`` line per user that has a password."""
    missing = [u.name for u in users.users if not u.password]
    if missing:
        raise ValueError(f"no password for user(s) {missing}: --dictionary needs one for every user")
    for u in users.users:
        if ":" in (u.password or "") or "\n" in (u.password or ""):
            raise ValueError(f"password of user {u.name!r} must not contain ':' or a newline")
    return "".join(f"{u.name}:{u.password}\n" for u in users.users)


def router_config(template: str | Path, section: dict[str, Any]) -> str:
    """A whole router configuration: the template (JSON5) with ``access_control`` replaced, as JSON."""
    import zenoh

    cfg = zenoh.Config.from_file(str(template))
    cfg.insert_json5("access_control", json.dumps(section))
    return json.dumps(json.loads(str(cfg)), indent=2) + "\n"


def listening_router(template: str | Path, users: UsersFile, endpoint: str, dictionary_file: str | Path) -> Any:
    """A ``zenoh.Config`` for a router from ``template`` listening on ``endpoint``, with the users'
    password dictionary written to ``dictionary_file`` and their generated access control (what
    the tests open to stand in for a deployment's ``zenohd``)."""
    import zenoh

    Path(dictionary_file).write_text(dictionary(users))
    cfg = zenoh.Config.from_file(str(template))
    cfg.insert_json5("listen/endpoints", json.dumps([endpoint]))
    cfg.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(dictionary_file)))
    cfg.insert_json5("access_control", json.dumps(access_control(users)))
    return cfg


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("users", help="users file (TOML), e.g. deploy/users.example.toml")
    parser.add_argument("--out", "-o", help="write here instead of stdout")
    parser.add_argument(
        "--router-config",
        metavar="JSON5",
        help="write this router configuration with the generated access_control inserted "
        "(e.g. deploy/zenoh-router.json5) instead of the section alone",
    )
    parser.add_argument(
        "--cloth-states",
        choices=CLOTH_STATE_POLICIES,
        default="deny",
        help="deprecated, no effect: since protocol 1.4 a client reads its own cloths' states "
        "({ns}/client/C/**) and no one else's",
    )
    parser.add_argument(
        "--no-stats", dest="stats", action="store_false", help="do not let clients subscribe to the servers' stats"
    )
    parser.add_argument(
        "--dictionary",
        metavar="FILE",
        help="also write Zenoh's user:password dictionary (mode 0600) from the users' passwords",
    )


def run(args: argparse.Namespace) -> int:
    try:
        users = load_users(args.users)
        section = access_control(users, args.cloth_states, args.stats)
        text = (
            router_config(args.router_config, section)
            if args.router_config
            else json.dumps({"access_control": section}, indent=2) + "\n"
        )
        secrets_text = dictionary(users) if args.dictionary else None
    except (OSError, ValueError) as e:
        log.error("%s", e)
        return 2
    except Exception as e:  # zenoh refusing the template or the section
        log.error("the configuration does not load in Zenoh: %s", e)
        return 2
    if args.out:
        Path(args.out).write_text(text)
        log.info("wrote %s (%d users, %d rules)", args.out, len(users.users), len(section["rules"]))
    else:
        sys.stdout.write(text)
    if secrets_text is not None:
        fd = os.open(args.dictionary, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w") as fh:
            fh.write(secrets_text)
        log.info("wrote %s", args.dictionary)
    return 0


if __name__ == "__main__":
    _p = argparse.ArgumentParser(prog="drape acl", description=__doc__.splitlines()[0])
    configure(_p)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    sys.exit(run(_p.parse_args()))
