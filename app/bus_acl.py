"""The hub's access control, made from the layout (issue 25: "stats, acks and frames are
accepted only from workers of the layout ... with TLS, certificate identity or zenoh access
control per key where zenoh offers it").

With ``bus.acl`` (which needs mutual TLS), the hub, a zenoh router, tells every session
that connects to it apart by the common name (CN) of the certificate it shows, and
zenoh's access control (``access_control`` in its configuration, checked on the hub for
every message that enters it) lets each host publish only what the layout's workers on
that host publish:

- the hub's own host (the CN of the hub's certificate, :func:`certificate_name`): all
  of it (its launcher and local workers);
- a host named by the layout's workers (``host: camera-pc``; its certificate's CN must
  be that name, as ``deploy/tls/make_certs.sh DIR camera-pc`` makes it): the data keys of
  the stages its workers produce (per camera: any camera's), and their stats, ends of
  stream, acknowledgements, heartbeats and liveliness tokens under their own names;
- ``bus.acl.readers``: common names that may subscribe and publish nothing;
- any other certificate of the room: nothing at all.

Everyone admitted may subscribe to everything and receive it. A forged frame, stats or
end of stream from a camera PC under a processing stage's name, or from a host that is not
in the layout, is dropped by the hub before it reaches a worker (the workers' own checks,
:mod:`app.admission`, still run behind it).

A room on one host (every worker on the hub's host, no TLS, ``bus.private`` not false: the
default) needs no certificates: the launcher listens on a Unix socket in a directory of its
own (mode 0700) besides ``bus.listen``, its workers connect through that socket, and
:func:`outsiders_read_only` lets a session linked any other way (TCP, UDP, TLS, QUIC,
WebSocket: a viewer, a client of the zenoh feed, or a stray process) subscribe and receive
but publish nothing, declare no liveliness token and answer no query in the room: its
junk is dropped by the hub, and no worker wakes for it.
"""
from __future__ import annotations

from app.bus import Keys
from app.bus_section import certificate_name

__all__ = ["certificate_name", "room_access_control", "published_keys", "outsiders_read_only", "OUTSIDE_LINKS"]

#: zenoh's link protocols other than the private Unix socket (``link_protocols`` subjects)
OUTSIDE_LINKS = ["tcp", "tls", "udp", "quic", "ws"]
WRITE = ["put", "delete", "liveliness_token", "declare_queryable", "reply"]
READ = ["declare_subscriber", "query", "declare_liveliness_subscriber", "liveliness_query"]
EVERYTHING = ["put", "delete", "declare_subscriber", "query", "reply", "declare_queryable", "liveliness_token",
              "liveliness_query", "declare_liveliness_subscriber"]


def published_keys(layout, spec) -> list[str]:
    """The key expressions the worker ``spec`` of ``layout`` publishes on."""
    from workers import worker_class

    keys = Keys(layout.room)
    cls = worker_class(spec.kind)
    out = [keys.stats(spec.name), keys.eos(spec.name), keys.ack(spec.name), keys.heartbeat(spec.name)]
    for stage in sorted(cls.produces(spec)):
        out.append(keys.stage(stage))       # per camera: any camera's ("frame/*")
    if spec.kind == "streamer":
        out.append(keys.poses_json())       # its JSON pose feed (not a stage)
    return out


def room_access_control(layout, hub_name: str) -> dict:
    """zenoh's ``access_control`` section for the hub of ``layout`` whose certificate
    names ``hub_name`` (module docstring)."""
    rules = [{"id": "read", "messages": READ, "flows": ["ingress"], "permission": "allow", "key_exprs": ["**"]},
             {"id": "receive", "messages": EVERYTHING, "flows": ["egress"], "permission": "allow",
              "key_exprs": ["**"]},
             {"id": "hub", "messages": EVERYTHING, "flows": ["ingress"], "permission": "allow", "key_exprs": ["**"]}]
    subjects = [{"id": "hub", "cert_common_names": [hub_name]}]
    policies = [{"rules": ["read", "receive", "hub"], "subjects": ["hub"]}]
    hosts: dict[str, list] = {}   # host -> its workers
    for spec in layout.workers:
        if not spec.local and spec.host != hub_name:
            hosts.setdefault(spec.host, []).append(spec)
    for n, (host, specs) in enumerate(sorted(hosts.items())):
        keys = sorted({k for spec in specs for k in published_keys(layout, spec)})
        alive = [Keys(layout.room).alive(spec.name) for spec in specs]
        rules.append({"id": f"host{n}", "messages": ["put", "delete"], "flows": ["ingress"], "permission": "allow",
                      "key_exprs": keys})
        rules.append({"id": f"host{n}-alive", "messages": ["liveliness_token"], "flows": ["ingress"],
                      "permission": "allow", "key_exprs": alive})
        subjects.append({"id": f"host{n}", "cert_common_names": [host]})
        policies.append({"rules": ["read", "receive", f"host{n}", f"host{n}-alive"], "subjects": [f"host{n}"]})
    readers = [r for r in (layout.bus.acl.readers if layout.bus.acl else []) if r != hub_name and r not in hosts]
    if readers:
        subjects.append({"id": "readers", "cert_common_names": readers})
        policies.append({"rules": ["read", "receive"], "subjects": ["readers"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def outsiders_read_only(room: str) -> dict:
    """zenoh's ``access_control`` section for the hub of a room on one host (module
    docstring): what enters the hub over any link but its private socket may not publish
    under the room's keys."""
    return {"enabled": True, "default_permission": "allow",
            "rules": [{"id": "outsiders", "messages": WRITE, "flows": ["ingress"], "permission": "deny",
                       "key_exprs": [Keys(room).everything()]}],
            "subjects": [{"id": "outsiders", "link_protocols": OUTSIDE_LINKS}],
            "policies": [{"rules": ["outsiders"], "subjects": ["outsiders"]}]}
