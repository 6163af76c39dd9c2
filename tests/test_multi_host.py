"""A room on two hosts (issue 25): the camera PC (grabber, segmentation) in a network
namespace of its own, joined to the processing PC (this namespace: the launcher's hub,
reconstruction, recorder) by a veth pair and nothing else, the two talking only
through zenoh endpoints. Results equal a one-host run; the link cut for 5 s and for
90 s is waited out by itself, and the launcher says the link was down. Skipped where
network namespaces cannot be made (not root, no ``ip``)."""
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time

import pytest
import yaml

from tests.conftest import ROOT, start_smartroom
from tests.runs import stats_of, voxel_frames, wait_for, worker_pid, write_layout
from tests.synthetic import write_tiny_recording

pytestmark = pytest.mark.integration

FRAMES = 500   # 20 s at 25 fps, paced: the link is cut while frames flow


def _ip(*args, ns=None) -> subprocess.CompletedProcess:
    cmd = ["ip", "netns", "exec", ns, "ip", *args] if ns else ["ip", *args]
    return subprocess.run(cmd, capture_output=True, text=True)


@pytest.fixture
def camera_host():
    """A namespace ``ns`` with address ``remote``, linked to this one's ``local`` by a veth pair
    whose end here is ``link`` (set down to cut the link)."""
    if shutil.which("ip") is None or os.geteuid() != 0:
        pytest.skip("network namespaces need root and iproute2 (ip)")
    tag = f"{os.getpid() % 10000}{random.randint(0, 99)}"
    ns, here, there = f"srcam{tag}", f"sra{tag}", f"srb{tag}"
    net = random.randint(1, 250)
    local, remote = f"10.233.{net}.1", f"10.233.{net}.2"
    if _ip("netns", "add", ns).returncode:
        pytest.skip("cannot create a network namespace here")
    try:
        steps = [(None, ("link", "add", here, "type", "veth", "peer", "name", there)),
                 (None, ("link", "set", there, "netns", ns)),
                 (None, ("addr", "add", f"{local}/24", "dev", here)), (None, ("link", "set", here, "up")),
                 (ns, ("addr", "add", f"{remote}/24", "dev", there)), (ns, ("link", "set", there, "up")),
                 (ns, ("link", "set", "lo", "up"))]
        for where, args in steps:
            r = _ip(*args, ns=where)
            if r.returncode:
                pytest.skip(f"cannot set up the veth pair: ip {' '.join(args)}: {r.stderr.strip()}")
        yield {"ns": ns, "link": here, "local": local, "remote": remote}
    finally:
        _ip("link", "del", here)
        _ip("netns", "del", ns)


def _layout(tmp_path, name, listen, hosts: bool):
    path = write_layout(tmp_path / f"{name}.yaml")
    doc = yaml.safe_load(path.read_text())
    doc["bus"]["listen"] = [listen]
    for w in doc["workers"]:
        if hosts and w["name"] in ("grabber", "segmentation"):
            w["host"] = "camera-pc"
    path.write_text(yaml.safe_dump(doc))
    return path


def _two_host_run(tmp_path, rec, host, name, cut_at=None, cut_s=0.0, share=False):
    """The hub's host here; the camera PC's workers started in the namespace by hand
    (``smartroom worker``) or, with ``share``, by its own launcher (``smartroom run --host``)."""
    port = random.randint(20000, 40000)
    layout = _layout(tmp_path, name, f"tcp/{host['local']}:{port}", hosts=True)
    out = tmp_path / name
    proc = start_smartroom("run", "--recording", rec, "--headless", "--layout", layout, "--out", out)
    remote = []
    try:
        assert wait_for(lambda: (out / "layout.yaml").is_file(), timeout=30)
        hub = f"tcp/{host['local']}:{port}"
        commands = ([["run", "--host", "camera-pc", "--headless", "--out", str(tmp_path / f"{name}-camera-pc")]]
                    if share else [["worker", "grabber"], ["worker", "segmentation"]])
        for command in commands:   # the camera PC's share
            remote.append(subprocess.Popen(
                ["ip", "netns", "exec", host["ns"], sys.executable, "-m", "app.cli", *command,
                 "--layout", str(out / "layout.yaml"), "--connect", hub],
                cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                env=dict(os.environ, PYTHONUNBUFFERED="1")))
        if share == "kill":   # a crash on the camera PC: its launcher restarts the worker
            seg = wait_for(lambda: worker_pid(tmp_path / f"{name}-camera-pc", "segmentation"), timeout=60)
            assert seg, "the camera PC's segmentation never reported"
            time.sleep(1.0)
            os.kill(seg, signal.SIGKILL)
        if cut_at is not None:
            assert wait_for(lambda: ((stats_of(out) or {}).get("stages", {}).get("recorder", {})
                                     .get("frames_out", 0) >= cut_at), timeout=90), "frames never flowed"
            assert _ip("link", "set", host["link"], "down").returncode == 0
            time.sleep(cut_s)
            assert _ip("link", "set", host["link"], "up").returncode == 0
        _, err = proc.communicate(timeout=cut_s + 180)
        remote_err = [p.communicate(timeout=60)[1] for p in remote]
    finally:
        for p in [proc, *remote]:
            if p.poll() is None:
                p.kill()
    return out, proc.returncode, err, [p.returncode for p in remote], remote_err


@pytest.fixture(scope="module")
def rec(tmp_path_factory):
    return write_tiny_recording(tmp_path_factory.mktemp("rec") / "r", frames=FRAMES)


@pytest.fixture(scope="module")
def one_host(rec, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("one")
    out = tmp / "out"
    layout = _layout(tmp, "one", "tcp/127.0.0.1:0", hosts=False)
    r = subprocess.run([sys.executable, "-m", "app.cli", "run", "--recording", str(rec), "--headless", "--no-pace",
                        "--layout", str(layout), "--out", str(out)], cwd=ROOT, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    return _voxels(out / "voxels.bin")


def _voxels(path):
    """Each frame's voxels (frame, cameras, indices, colours, surface): what the run found,
    without the capture times."""
    from app.results import iter_voxels
    return [(m.frame, tuple(m.cameras), m.indices.tobytes(), m.colours.tobytes(), m.surface.tobytes())
            for m in iter_voxels(path)]


@pytest.mark.parametrize("cut_s", [0.0, 5.0, 90.0], ids=["no cut", "cut 5 s", "cut 90 s"])
def test_two_hosts_in_two_namespaces(rec, one_host, camera_host, tmp_path, cut_s):
    out, rc, err, remote_rc, remote_err = _two_host_run(tmp_path, rec, camera_host, "two",
                                                        cut_at=100 if cut_s else None, cut_s=cut_s)
    assert rc == 0, err[-3000:]
    assert remote_rc == [0, 0], remote_err
    s = stats_of(out)
    assert s["complete"] is True, s.get("reasons")
    assert [f for f, _ in voxel_frames(out / "voxels.bin")] == list(range(FRAMES))
    assert _voxels(out / "voxels.bin") == one_host               # the same results as on one host
    if cut_s >= 30:   # longer than zenoh's lease: the workers left the bus and came back
        assert "link to host camera-pc down" in err and "link to host camera-pc back after" in err
        outage = [o for o in s["outages"] if o["host"] == "camera-pc"]
        assert outage and outage[0]["s"] >= cut_s - 20, s["outages"]
        assert all("link to the hub back after" in e for e in remote_err), remote_err
    print(json.dumps(s.get("outages")))


@pytest.mark.parametrize("kill", [False, True], ids=["share", "share, segmentation killed"])
def test_the_camera_pc_share_started_by_run_host(rec, one_host, camera_host, tmp_path, kill):
    """``smartroom run --host camera-pc`` on the camera PC starts its workers (and restarts
    one killed there); the run equals a one-host run, and the share says what it sees. (A
    restarted segmentation runs its background models through the frames before again:
    the masks, and so the voxels, used to differ after it.)"""
    out, rc, err, remote_rc, remote_err = _two_host_run(tmp_path, rec, camera_host, "two",
                                                        share="kill" if kill else True)
    assert rc == 0, err[-3000:]
    assert remote_rc == [0], remote_err
    assert "every worker of the other hosts is on the bus (hub-host: reconstruction, recorder)" in remote_err[0]
    assert "every worker of the other hosts is on the bus (camera-pc: grabber, segmentation)" in err
    s = stats_of(out)
    assert s["complete"] is True, s.get("reasons")
    assert [f for f, _ in voxel_frames(out / "voxels.bin")] == list(range(FRAMES))
    assert _voxels(out / "voxels.bin") == one_host
    share = stats_of(tmp_path / "two-camera-pc")
    assert share["complete"] is True and set(share["exits"]) == {"grabber", "segmentation"}
    assert share["stages"]["segmentation"]["frames_out"] == FRAMES
    assert share["stages"]["segmentation"]["restarts"] == (1 if kill else 0)


def test_run_host_refuses_a_host_the_layout_does_not_name(tmp_path):
    from tests.conftest import smartroom
    layout = _layout(tmp_path, "l", "tcp/127.0.0.1:0", hosts=True)
    r = smartroom("run", "--host", "nowhere", "--layout", layout, "--connect", "tcp/127.0.0.1:9", "--out",
                  tmp_path / "o", "--headless")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "--host nowhere: no worker of the layout is on that host (hosts: camera-pc, local)" in r.stderr


def test_a_skewed_clock_of_another_host_is_said_once():
    """Heartbeats of the camera PC's workers stamped 100 ms behind this host's clock (more
    than half a frame at 25 fps): said once, and kept for stats.json's clock_skew_s."""
    from app.hosts import Hosts

    said = []
    hosts = Hosts({"camera-pc": ["grabber"]}, 600.0, 25.0, wall=lambda: 1000.0, say=said.append)
    for _ in range(4):
        hosts.heartbeat("grabber", 1000.0 - 0.010)      # 10 ms: within half a frame (20 ms)
    hosts.heartbeat("reconstruction", 990.0)            # a worker of this host: not another clock
    assert not said
    for _ in range(20):
        hosts.heartbeat("grabber", 1000.0 - 0.100)
    assert said == ["the clock of host camera-pc is 100 ms behind this one's (more than half a frame, 20 ms): "
                    "synchronise them (NTP, chrony)"]
    assert hosts.figures() == {"clock_skew_s": {"camera-pc": 0.1}}


def test_links_down_and_back_are_said_kept_and_end_the_run_after_peer_timeout():
    from app.hosts import HUB, Hosts

    clock, said = [0.0], []
    hosts = Hosts({"camera-pc": ["grabber", "segmentation"]}, 300.0, 25.0, clock=lambda: clock[0],
                  wall=lambda: 5000.0, say=said.append)
    assert hosts.check(set()) is None and not said              # not started there yet: no outage
    clock[0] = 12.0
    assert hosts.check(set()) is None
    assert said[-1].startswith("workers of other hosts on the bus: camera-pc: -; not yet: grabber, segmentation")
    hosts.alive("grabber", True)
    hosts.alive("segmentation", True)
    assert hosts.check(set()) is None
    assert said[-1] == "every worker of the other hosts is on the bus (camera-pc: grabber, segmentation)"
    hosts.alive("grabber", False)
    hosts.alive("segmentation", False)
    assert hosts.check(set()) is None                            # the link is cut
    clock[0] = 42.0
    assert hosts.check(set()) is None
    assert said[-1] == "link to host camera-pc down for 30 s (waiting up to 300 s)"
    hosts.alive("segmentation", True)
    clock[0] = 50.0
    assert hosts.check(set()) is None and said[-1] == "link to host camera-pc back after 38 s"
    assert hosts.figures()["outages"] == [{"host": "camera-pc", "until": 5000.0, "s": 38.0}]
    hosts.alive("segmentation", False)
    assert hosts.check({"grabber", "segmentation"}) is None       # they ended their stream: not an outage
    assert hosts.check({"grabber"}) is None
    clock[0] = 351.0
    assert hosts.check({"grabber"}) == ("host camera-pc (grabber, segmentation) gone from the bus for 301 s "
                                        "(restarts: peer_timeout_s 300 s)")
    never = Hosts({"camera-pc": ["grabber"]}, 300.0, 25.0, clock=lambda: clock[0], say=said.append)
    clock[0] += 301.0
    assert never.check(set()) == "host camera-pc (grabber) never came on the bus in 301 s (restarts: peer_timeout_s)"
    share = Hosts({"hub-host": ["reconstruction"]}, 300.0, 25.0, clock=lambda: clock[0], say=said.append)
    assert share.check(set(), hub_linked=False) is None
    clock[0] += 301.0
    assert share.check(set(), hub_linked=False).startswith("the hub unreachable for 301 s")
    assert HUB in {o["host"] for o in share.figures()["outages"]}
