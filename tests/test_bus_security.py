"""Bus security: zenoh TLS with the room's certificates (mutual TLS) and user/password
admit the room's own hosts and refuse others; the layout's bus section is checked with
one-line errors, bad endpoints included. Real zenoh sessions on loopback; certificates
made by deploy/tls/make_certs.sh (openssl) into a temporary folder."""
from __future__ import annotations

import dataclasses
import json
import shutil
import subprocess
import threading
import time
from pathlib import Path

import pytest
import yaml

from app.bus import BusConfig, Keys, free_port, open_session
from app.bus_section import AuthConfig, TlsConfig, endpoint_problem
from app.config import LayoutError, load_layout, parse_layout
from app.errors import InputError
from tests.conftest import start_smartroom

ROOT = Path(__file__).resolve().parent.parent
MAKE_CERTS = ROOT / "deploy" / "tls" / "make_certs.sh"
KEY = "smartroom/secure/probe"
ADMIT_WITHIN = 5.0     # s: a delivery normally takes ~50 ms
REFUSE_FOR = 1.0       # s: a refused host sees nothing in this time (zenoh's handshake fails at once)

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl is needed to make certificates")


@pytest.fixture(scope="module")
def certs(tmp_path_factory) -> Path:
    """room/ca.pem signs hub and cam; other/ca.pem (another CA) signs intruder."""
    d = tmp_path_factory.mktemp("tls")
    for folder, host in (("room", "hub"), ("room", "cam"), ("other", "intruder"), ("room", "camera-pc"),
                         ("room", "stranger"), ("room", "viewer-pc")):
        subprocess.run(["sh", str(MAKE_CERTS), str(d / folder), host], check=True, capture_output=True, timeout=30)
    return d


def _tls(folder: Path, host: str, ca: Path | None = None, **kw) -> TlsConfig:
    return TlsConfig(ca=str(ca or folder / "ca.pem"), cert=str(folder / f"{host}.pem"),
                     key=str(folder / f"{host}.key"), **kw)


def _delivered(hub, client_bus: BusConfig, wait: float, mode: str = "peer", key: str = KEY) -> bool:
    """Does a put on ``key`` from a session opened with ``client_bus`` (as a zenoh ``mode``)
    reach ``hub`` (a session) within ``wait``? (An intruder opens a peer: it does not wait
    for the hub.)"""
    got = threading.Event()
    sub = hub.declare_subscriber(key, lambda sample: got.set())
    client = open_session(client_bus, mode)
    try:
        deadline = time.monotonic() + wait
        while not got.is_set() and time.monotonic() < deadline:
            client.put(key, b"hello")
            got.wait(0.05)
        return got.is_set()
    finally:
        client.close()
        sub.undeclare()


def test_mutual_tls_admits_the_rooms_certificate_and_refuses_another(certs):
    room, other = certs / "room", certs / "other"
    hub_bus = BusConfig(listen=[f"tls/127.0.0.1:{free_port()}"], tls=_tls(room, "hub"))
    hub = open_session(hub_bus, mode="router")
    try:
        # a worker of the room, as the launcher starts it: a client of the hub, listening nowhere
        cam = dataclasses.replace(hub_bus.for_worker(), tls=_tls(room, "cam"))
        assert cam.listen == [] and cam.connect == hub_bus.listen
        assert _delivered(hub, cam, ADMIT_WITHIN, mode="client")
        # another CA's certificate, trusting its own CA or (wrongly) the room's: refused
        assert not _delivered(hub, dataclasses.replace(cam, tls=_tls(other, "intruder")), REFUSE_FOR)
        assert not _delivered(hub, dataclasses.replace(cam, tls=_tls(other, "intruder", ca=room / "ca.pem")),
                              REFUSE_FOR)
        # no certificate at all: plain TCP to the TLS port
        plain = BusConfig(connect=[hub_bus.listen[0].replace("tls/", "tcp/")])
        assert not _delivered(hub, plain, REFUSE_FOR)
        # and the room's host is still admitted afterwards
        assert _delivered(hub, cam, ADMIT_WITHIN, mode="client")
    finally:
        hub.close()


def test_user_password_admits_the_right_password_and_refuses_others(tmp_path):
    users = tmp_path / "room.users"
    users.write_text("hub:hub-secret\ncam:cam-secret\n")
    for name, secret in (("hub", "hub-secret"), ("cam", "cam-secret"), ("wrong", "guess")):
        (tmp_path / f"{name}.password").write_text(secret + "\n")

    def auth(user, password):
        return AuthConfig(user=user, password_file=str(tmp_path / f"{password}.password"),
                          dictionary_file=str(users))

    hub_bus = BusConfig(listen=[f"tcp/127.0.0.1:{free_port()}"], auth=auth("hub", "hub"))
    hub = open_session(hub_bus, mode="router")
    try:
        cam = hub_bus.for_worker()
        assert _delivered(hub, dataclasses.replace(cam, auth=auth("cam", "cam")), ADMIT_WITHIN, mode="client")
        assert not _delivered(hub, dataclasses.replace(cam, auth=auth("cam", "wrong")), REFUSE_FOR)
        assert not _delivered(hub, dataclasses.replace(cam, auth=None), REFUSE_FOR)
    finally:
        hub.close()


# -- the layout's bus section ---------------------------------------------------------------

def _layout(bus: dict) -> dict:
    return {"room": "r", "bus": bus,
            "workers": [{"name": "g", "kind": "grabber"}, {"name": "s", "kind": "segmentation"}]}


@pytest.fixture()
def room_files(certs, tmp_path) -> Path:
    """A layout folder with tls/ (room certificates) and secret/ (password, users)."""
    shutil.copytree(certs / "room", tmp_path / "tls")
    (tmp_path / "secret").mkdir()
    (tmp_path / "secret" / "room.password").write_text("s3cret\n")
    (tmp_path / "secret" / "room.users").write_text("smartroom:s3cret\n")
    return tmp_path


SECURE_BUS = {"listen": ["tls/0.0.0.0:7447"],
              "tls": {"ca": "tls/ca.pem", "cert": "tls/hub.pem", "key": "tls/hub.key"},
              "auth": {"user": "smartroom", "password_file": "secret/room.password",
                       "dictionary_file": "secret/room.users"}}


def test_layout_tls_and_auth_paths_are_relative_to_the_layout_and_survive_the_resolved_layout(room_files):
    path = room_files / "layout.yaml"
    path.write_text(yaml.safe_dump(_layout(SECURE_BUS)))
    bus = load_layout(path).bus
    assert bus.tls == TlsConfig(ca=str(room_files / "tls/ca.pem"), cert=str(room_files / "tls/hub.pem"),
                                key=str(room_files / "tls/hub.key"), mtls=True, verify_name=True)
    assert bus.auth.password_file == str(room_files / "secret/room.password")
    # what zenoh gets
    conf = bus.to_zenoh()
    link = json.loads(conf.get_json("transport/link/tls"))
    assert link["root_ca_certificate"] == bus.tls.ca and link["enable_mtls"] is True
    assert link["listen_certificate"] == link["connect_certificate"] == bus.tls.cert
    assert link["listen_private_key"] == link["connect_private_key"] == bus.tls.key
    assert json.loads(conf.get_json("transport/auth/usrpwd")) == {
        "user": "smartroom", "password": "s3cret", "dictionary_file": bus.auth.dictionary_file}
    # workers get the same certificate and credentials, and connect to the hub (clients listen nowhere)
    worker = bus.for_worker()
    assert worker.listen == [] and worker.connect == bus.listen and worker.tls == bus.tls and worker.auth == bus.auth
    # the resolved layout written elsewhere (next to the results) names the same files
    out = room_files / "out"
    out.mkdir()
    layout = load_layout(path)
    layout.save(out / "layout.yaml")
    assert load_layout(out / "layout.yaml").bus == bus
    # without tls/auth the default stays loopback TCP, no TLS
    plain = parse_layout(_layout({})).bus
    assert plain.listen == ["tcp/127.0.0.1:0"] and plain.tls is None and plain.auth is None
    assert json.loads(plain.to_zenoh().get_json("transport/link/tls"))["root_ca_certificate"] is None


def test_the_deploy_example_parses_with_generated_certificates(room_files):
    text = (ROOT / "deploy/tls/secure_two_hosts.yaml").read_text()
    etc = room_files / "etc"
    (etc / "tls").mkdir(parents=True)
    for src, dst in (("tls/ca.pem", "tls/ca.pem"), ("tls/hub.pem", "tls/host.pem"), ("tls/hub.key", "tls/host.key"),
                     ("secret/room.password", "room.password"), ("secret/room.users", "room.users")):
        shutil.copy(room_files / src, etc / dst)
    path = room_files / "secure_two_hosts.yaml"
    path.write_text(text.replace("/etc/smartroom/", f"{etc}/"))
    bus = load_layout(path).bus
    assert bus.listen == ["tls/0.0.0.0:7447"] and bus.tls.mtls and bus.auth.user == "smartroom"


def _bus_with(**changes) -> dict:
    bus = json.loads(json.dumps(SECURE_BUS))
    for dotted, value in changes.items():
        *parents, last = dotted.split("__")
        node = bus
        for p in parents:
            node = node[p]
        if value is None:
            node.pop(last, None)
        else:
            node[last] = value
    return bus


BAD_BUS = [
    (_bus_with(tls__cert="tls/missing.pem"), "bus.tls.cert", "does not exist"),
    (_bus_with(tls__key="tls"), "bus.tls.key", "cannot read"),                  # a folder: unreadable
    (_bus_with(tls__key="tls/hub.pem"), "bus.tls.key", "is not a PEM private key"),
    (_bus_with(tls__ca="secret/room.users"), "bus.tls.ca", "is not a PEM certificate"),
    (_bus_with(tls__key=None), "bus.tls.key", "is required"),
    (_bus_with(tls__mtls="yes"), "bus.tls.mtls", "true or false"),
    (_bus_with(tls__cipher="x"), "bus.tls", "unknown key 'cipher'"),
    (_bus_with(listen=["tcp/0.0.0.0:7447"]), "bus.listen", "is not a tls/ endpoint"),
    (_bus_with(connect=["tcp/10.0.0.1:7447"]), "bus.connect", "is not a tls/ endpoint"),
    (_bus_with(tls=None), "bus.listen", "needs a bus.tls section"),
    (_bus_with(auth__password_file="secret/none"), "bus.auth.password_file", "does not exist"),
    (_bus_with(auth__user="a:b"), "bus.auth.user", "without ':'"),
    (_bus_with(auth__dictionary_file="secret/room.password"), "bus.auth.dictionary_file", "is not user:password"),
    (_bus_with(auth__dictionary_file=None), "bus.auth.dictionary_file", "is required"),
    (_bus_with(passwd="x"), "bus", "unknown key 'passwd'"),
    ({"listen": ["tcp/nonsense"]}, "bus.listen", "needs HOST:PORT"),
    ({"listen": ["upd/127.0.0.1:7447"]}, "bus.listen", "unknown protocol 'upd'"),
    ({"listen": ["tcp/127.0.0.1:70000"]}, "bus.listen", "not a number from 0 to 65535"),
    ({"listen": ["tcp/127.0.0.1:port"]}, "bus.listen", "not a number from 0 to 65535"),
    ({"listen": ["tcp/300.1.2.3:7447"]}, "bus.listen", "not an IPv4 address"),
    ({"listen": ["tcp/[::zz]:7447"]}, "bus.listen", "not an IPv6 address"),
    ({"connect": ["tcp/bad_host!:7447"]}, "bus.connect", "not a host name or address"),
    ({"connect": ["tcp/10.0.0.1:0"]}, "bus.connect", "port 0"),
    ({"connect": "tcp/10.0.0.1:7447"}, "bus.connect", "must be a list"),
    ({"multicast": "no"}, "bus.multicast", "true or false"),
    (_bus_with(acl={"readers": "viewer-pc"}), "bus.acl.readers", "list of certificate common names"),
    (_bus_with(acl={"writers": ["x"]}), "bus.acl", "unknown key 'writers'"),
    (_bus_with(acl=True, tls__mtls=False), "bus.acl", "needs bus.tls with mtls: true"),
    ({"acl": True}, "bus.acl", "needs bus.tls with mtls: true"),
]


@pytest.mark.parametrize("bus, field, problem", BAD_BUS, ids=[f"{f}:{p}" for _, f, p in BAD_BUS])
def test_a_bad_bus_section_is_one_line_naming_the_file_and_field(room_files, bus, field, problem):
    path = room_files / "layout.yaml"
    path.write_text(yaml.safe_dump(_layout(bus)))
    with pytest.raises(LayoutError) as info:
        load_layout(path)
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith(f"{path}: ") and f"{field}" in msg and problem in msg, msg


def test_good_endpoints_pass_the_syntax_check():
    for ep in ("tcp/127.0.0.1:0", "tcp/0.0.0.0:7447", "tls/camera-pc.local:7447", "tcp/[::1]:7447",
               "udp/10.0.0.2:7447", "tcp/localhost:7447?prio=1-7", "unixsock-stream//tmp/zenoh.sock"):
        assert endpoint_problem(ep) is None, ep


def test_open_session_turns_bad_endpoints_into_one_line_input_errors():
    cases = [
        (BusConfig(connect=["tcp/no-such-host.invalid:7447"]), "does not resolve"),
        (BusConfig(connect=["tcp/nonsense"]), "needs HOST:PORT"),               # e.g. a bad --connect
        (BusConfig(listen=["tcp/192.0.2.1:7447"]), "zenoh cannot open a session"),  # not this host's address
    ]
    for bus, problem in cases:
        with pytest.raises(InputError) as info:
            open_session(bus).close()
        msg = str(info.value)
        assert "\n" not in msg and problem in msg and (bus.connect or bus.listen)[0] in msg, msg
        assert "/root/.cargo" not in msg


# -- a whole run over TLS ---------------------------------------------------------------------

@pytest.mark.integration
def test_a_run_over_mutual_tls_with_a_remote_worker_admits_it_and_not_an_intruder(certs, tiny_recording, tmp_path):
    """The launcher's hub and its workers over mutual TLS and user/password, segmentation
    started by hand as on another host; a session with another CA's certificate sees nothing."""
    shutil.copytree(certs / "room", tmp_path / "tls")
    layout = yaml.safe_load((ROOT / "deploy/layouts/local.yaml").read_text())
    # the spine (the bus is the matter here, not the later stages' first-frame kernels)
    layout["workers"] = [w for w in layout["workers"] if w["kind"] in ("grabber", "segmentation", "reconstruction",
                                                                       "recorder", "monitor")]
    for w in layout["workers"]:
        if w["name"] == "segmentation":
            w["host"] = "camera-pc"        # started by hand below, as on another host
    port = free_port()
    (tmp_path / "room.password").write_text("s3cret\n")
    (tmp_path / "room.users").write_text("smartroom:s3cret\n")
    layout["bus"] = {"listen": [f"tls/127.0.0.1:{port}"],
                     "tls": {"ca": "tls/ca.pem", "cert": "tls/hub.pem", "key": "tls/hub.key"},
                     "auth": {"user": "smartroom", "password_file": "room.password", "dictionary_file": "room.users"}}
    path = tmp_path / "secure.yaml"
    path.write_text(yaml.safe_dump(layout))
    intruder = open_session(BusConfig(connect=[f"tls/127.0.0.1:{port}"], listen=["tls/127.0.0.1:0"],
                                      tls=_tls(certs / "other", "intruder", ca=certs / "room" / "ca.pem")))
    seen = []
    sub = intruder.declare_subscriber(Keys(layout["room"]).root + "/**", lambda s: seen.append(str(s.key_expr)))
    out = tmp_path / "out"
    proc = start_smartroom("run", "--recording", tiny_recording, "--frames", 50, "--headless", "--layout", path,
                           "--out", out)
    try:
        for _ in range(400):
            if (out / "layout.yaml").is_file():
                break
            time.sleep(0.05)
        remote = start_smartroom("worker", "segmentation", "--layout", out / "layout.yaml")
        try:
            _, err = proc.communicate(timeout=240)
            remote.communicate(timeout=30)
        finally:
            for p in (proc, remote):
                if p.poll() is None:
                    p.kill()
    finally:
        sub.undeclare()
        intruder.close()
    assert proc.returncode == 0, err
    assert remote.returncode == 0
    stats = json.loads((out / "stats.json").read_text())
    assert stats["stages"]["segmentation"]["frames_out"] >= 48      # the room's remote worker took part
    assert stats["stages"]["reconstruction"]["frames_out"] >= 48
    assert load_layout(out / "layout.yaml").bus.listen == [f"tls/127.0.0.1:{port}"]
    assert seen == []                                                  # the intruder saw nothing


def test_a_publisher_waits_until_the_bus_routes_its_key_to_a_subscriber():
    """A worker learns of the room's subscribers only once the hub has told it of them
    (a consumer that joins later, from another host); offline, its first message waits
    for that (Publisher.await_subscriber) instead of going nowhere."""
    from app.bus import Publisher
    port = free_port()
    hub_bus = BusConfig(listen=[f"tcp/127.0.0.1:{port}"])
    hub = open_session(hub_bus, mode="router")
    sender = open_session(hub_bus.for_worker(), mode="client")
    late = None
    try:
        pub = Publisher(sender, "room/test/mask/cam0", droppable=False)
        t0 = time.monotonic()
        assert pub.await_subscriber(0.3) is False            # nobody there: it says so after the wait
        assert time.monotonic() - t0 >= 0.3
        got = []
        late = open_session(hub_bus.for_worker(), mode="client")
        late.declare_subscriber("room/test/mask/*", lambda s: got.append(s.payload.to_bytes()))
        assert pub.await_subscriber(10.0) is True            # the subscriber's declaration reached the sender
        pub.put_payload(b"first")
        deadline = time.monotonic() + 5
        while not got and time.monotonic() < deadline:
            time.sleep(0.01)
        assert got == [b"first"]
    finally:
        for s in (late, sender, hub):
            if s is not None:
                s.close()


# -- the hub's access control (bus.acl) -------------------------------------------------

def test_the_hub_lets_each_host_publish_only_what_its_workers_publish(room_files, certs):
    """bus.acl: the hub (zenoh's access control, made from the layout) tells hosts apart by
    the certificates they show: the camera PC may publish its grabber's frames and its
    segmentation's masks, and their stats and ends, but not voxels nor another stage's
    stats or end of stream; a room certificate of a host outside the layout publishes
    nothing; a reader subscribes and publishes nothing; the hub's own host publishes all."""
    from app.bus_acl import room_access_control

    port = free_port()
    layout_doc = {"room": "r", "bus": {**SECURE_BUS, "listen": [f"tls/127.0.0.1:{port}"],
                                      "acl": {"readers": ["viewer-pc"]}},
                  "workers": [{"name": "grabber", "kind": "grabber", "host": "camera-pc"},
                              {"name": "segmentation", "kind": "segmentation", "host": "camera-pc"},
                              {"name": "reconstruction", "kind": "reconstruction"},
                              {"name": "recorder", "kind": "recorder"}]}
    path = room_files / "layout.yaml"
    path.write_text(yaml.safe_dump(layout_doc))
    layout = load_layout(path)
    assert layout.bus.acl.readers == ["viewer-pc"]
    layout.save(room_files / "resolved.yaml")                  # the resolved layout keeps it
    assert load_layout(room_files / "resolved.yaml").bus.acl == layout.bus.acl
    keys = Keys("r")
    hub = open_session(layout.bus, "router", access_control=room_access_control(layout, "hub"))
    local = open_session(layout.bus.for_worker(), "client")   # a worker on the hub's host

    def as_host(host: str) -> BusConfig:
        return dataclasses.replace(layout.bus.for_worker(), tls=_tls(room_files / "tls", host))

    def delivered(host: str, key: str, wait: float) -> bool:
        return _delivered(local, as_host(host), wait, "client", key)

    try:
        assert delivered("camera-pc", keys.frame("cam0"), ADMIT_WITHIN)
        assert delivered("camera-pc", keys.mask("cam1"), ADMIT_WITHIN)
        assert delivered("camera-pc", keys.stats("segmentation"), ADMIT_WITHIN)
        assert delivered("hub", keys.voxels(), ADMIT_WITHIN)
        for host, key in (("camera-pc", keys.voxels()), ("camera-pc", keys.stats("reconstruction")),
                          ("camera-pc", keys.eos("reconstruction")), ("camera-pc", keys.tracks()),
                          ("stranger", keys.frame("cam0")), ("stranger", keys.stats("grabber")),
                          ("viewer-pc", keys.frame("cam0"))):
            assert not delivered(host, key, REFUSE_FOR), (host, key)
        # the reader receives what the room publishes
        seen = threading.Event()
        reader = open_session(as_host("viewer-pc"), "client")
        try:
            reader.declare_subscriber(keys.voxels(), lambda s: seen.set())
            deadline = time.monotonic() + ADMIT_WITHIN
            while not seen.is_set() and time.monotonic() < deadline:
                local.put(keys.voxels(), b"v")
                seen.wait(0.05)
            assert seen.is_set()
        finally:
            reader.close()
    finally:
        local.close()
        hub.close()


def test_a_run_with_access_control_takes_the_remote_host_s_worker(certs, tiny_recording, tmp_path):
    """bus.acl in a real run: segmentation on host camera-pc, started by hand with that
    host's own certificate (the resolved layout with its files, as each host keeps its own
    under the same names), publishes its masks, stats, acknowledgements, heartbeats and end
    through the hub's access control, and the run completes with it."""
    shutil.copytree(certs / "room", tmp_path / "tls")
    layout = yaml.safe_load((ROOT / "deploy/layouts/local.yaml").read_text())
    layout["workers"] = [w for w in layout["workers"] if w["kind"] in ("grabber", "segmentation", "reconstruction",
                                                                       "recorder")]
    for w in layout["workers"]:
        if w["name"] == "segmentation":
            w["host"] = "camera-pc"
    port = free_port()
    layout["bus"] = {"listen": [f"tls/127.0.0.1:{port}"], "acl": True,
                     "tls": {"ca": "tls/ca.pem", "cert": "tls/hub.pem", "key": "tls/hub.key"}}
    path = tmp_path / "secure.yaml"
    path.write_text(yaml.safe_dump(layout))
    out = tmp_path / "out"
    proc = start_smartroom("run", "--recording", tiny_recording, "--frames", 50, "--headless", "--layout", path,
                           "--out", out)
    remote = None
    try:
        for _ in range(400):
            if (out / "layout.yaml").is_file():
                break
            time.sleep(0.05)
        camera_pc = yaml.safe_load((out / "layout.yaml").read_text())
        camera_pc["bus"]["tls"].update(cert=str(tmp_path / "tls/camera-pc.pem"),
                                       key=str(tmp_path / "tls/camera-pc.key"))
        (tmp_path / "camera-pc.yaml").write_text(yaml.safe_dump(camera_pc))
        remote = start_smartroom("worker", "segmentation", "--layout", tmp_path / "camera-pc.yaml")
        _, err = proc.communicate(timeout=240)
        _, remote_err = remote.communicate(timeout=30)
    finally:
        for p in (proc, remote):
            if p is not None and p.poll() is None:
                p.kill()
    assert proc.returncode == 0, err[-2000:]
    assert remote.returncode == 0, remote_err[-2000:]
    stats = json.loads((out / "stats.json").read_text())
    assert stats["complete"]
    assert stats["stages"]["segmentation"]["frames_out"] == 50 and stats["stages"]["reconstruction"]["frames_out"] == 50
    assert load_layout(out / "layout.yaml").bus.acl is not None
