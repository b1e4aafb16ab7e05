"""Zenoh TLS, user/password authentication and access control through --zenoh-config, on loopback.

The configs under test are the ready-to-use examples of docs/security/ with their /etc/tacf/ paths pointed at a
tmp dir, which holds certificates made by docs/security/make-certs.sh and the example users file. One service
(in-process, TLS only) runs one session on a camera feed; the example access control lets the "ground" user call
tacf/*/control/* and read results, the "viewer" user only read results, and denies everything else.
"""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

zenoh = pytest.importorskip("zenoh")

from tacf.zenoh_options import ZenohOptions
from tacf_clients.local_service import free_port
from tacf_clients.zconfig import make_config
from tacf_schemas import StartRequest, StopRequest
from tacf_service.app import ServiceOptions, TrackingService
from tacf_service.loopback import FramePublisher, SessionResults, wait_until
from tacf_service.probe import ControlError, call, list_all
from tacf_service.scene import MovingTargetScene

pytestmark = pytest.mark.zenoh

DOCS = Path(__file__).resolve().parents[1] / "docs" / "security"
NODE = "secure-edge"
SID = "watched"
FEED = "uav1/camera/front"       # a camera key the example access control lets the ground station read


@pytest.fixture(scope="module")
def etc(tmp_path_factory) -> Path:
    if shutil.which("openssl") is None:
        pytest.skip("needs the openssl command to make certificates")
    etc = tmp_path_factory.mktemp("etc")
    subprocess.run(["sh", str(DOCS / "make-certs.sh"), str(etc / "certs")], check=True, capture_output=True)
    shutil.copy(DOCS / "users.txt.example", etc / "users.txt")
    for name in ("service", "ground", "viewer", "camera"):
        text = (DOCS / f"{name}.json5").read_text().replace("/etc/tacf/", f"{etc}/")
        (etc / f"{name}.json5").write_text(text)
    return etc


@pytest.fixture(scope="module")
def endpoint() -> str:
    return f"tls/127.0.0.1:{free_port()}"


@pytest.fixture(scope="module")
def service(etc, endpoint):
    zenoh_options = ZenohOptions(listen=(endpoint,), config_file=str(etc / "service.json5"))
    svc = TrackingService(ServiceOptions(node=NODE, zenoh=zenoh_options, spare_workers=1)).open()
    assert wait_until(lambda: svc.manager.idle_spares() >= 1, 60), "no warm worker after 60 s"
    yield svc
    svc.close()


def open_client(etc: Path, endpoint: str, role: str, mode: str | None = None, settings: dict | None = None):
    """A session made the way `tacf list --zenoh-config <role>.json5 --connect <endpoint>` makes it, with
    settings (Zenoh key path -> value) on top."""
    extra = tuple((key, json.dumps(value)) for key, value in (settings or {}).items())
    return zenoh.open(make_config(ZenohOptions(connect=(endpoint,), config_file=etc / f"{role}.json5", mode=mode,
                                               extra=extra)))


def derive(source: Path, target: Path, settings: dict) -> Path:
    """Write `source` with settings (Zenoh key path -> value) applied to `target`."""
    conf = zenoh.Config.from_file(str(source))
    for key, value in settings.items():
        conf.insert_json5(key, json.dumps(value))
    target.write_text(str(conf))      # str(Config) is JSON that Config.from_file reads back
    return target


@pytest.fixture(scope="module")
def camera(etc, endpoint, service):
    """A camera with camera.json5 (user "camera"), its session made as `tacf publish --zenoh-config` makes it.
    service.json5, which the README once offered cameras, kept its access control in the camera's session:
    that denied the camera's link to the service, and `tacf publish` sent its frames nowhere."""
    session = open_client(etc, endpoint, "camera")
    with FramePublisher(session, FEED, MovingTargetScene(640, 360, speed=2.0), fps=10) as feed:
        assert wait_until(lambda: feed.seq >= 3, 10)
        yield feed
    session.close()


@pytest.fixture(scope="module")
def ground(etc, endpoint, service):
    session = open_client(etc, endpoint, "ground")
    yield session
    session.close()


@pytest.fixture(scope="module")
def tracked(service, camera, ground):
    """The authorised ground station starts a session on the feed and sees its boxes."""
    results = SessionResults(ground, NODE, SID)
    info = call(ground, NODE, "start", StartRequest(image_key=FEED, box=camera.truth[camera.seq], seq=camera.seq,
                                                    sid=SID, profile="kcc"), timeout=10)
    assert (info.node, info.sid) == (NODE, SID)
    assert wait_until(lambda: len(results.results()) >= 3, 30), "the ground station saw no boxes"
    yield results
    results.close()


def boxes_grow(results: SessionResults, by: int = 3) -> bool:
    start = len(results.results())
    return bool(wait_until(lambda: len(results.results()) >= start + by, 10))


def test_ground_station_calls_the_control_queryable_and_reads_boxes(ground, tracked):
    [sessions] = list_all(ground)                                   # tacf/*/control/list
    assert (sessions.node, [s.sid for s in sessions.sessions]) == (NODE, [SID])
    assert boxes_grow(tracked)


@pytest.mark.parametrize("spoil", [
    pytest.param({"transport/auth/usrpwd/password": "wrong"}, id="wrong-password"),
    pytest.param({"transport/auth/usrpwd": {"user": None, "password": None}}, id="no-credentials"),
    pytest.param({"transport/link/tls/root_ca_certificate": None}, id="no-ca"),   # the system's CAs instead
])
def test_without_ca_or_credentials_nothing_gets_through(etc, endpoint, tracked, spoil):
    # As a client (what the example configs use), the session does not even open.
    with pytest.raises(zenoh.ZError):
        open_client(etc, endpoint, "ground", settings=spoil)
    # As a peer it opens (peers retry in the background) but reaches nothing.
    with open_client(etc, endpoint, "ground", "peer", spoil) as intruder:
        seen = SessionResults(intruder, "*", "*")
        with pytest.raises(ControlError) as err:
            call(intruder, NODE, "list", timeout=1.0)
        assert err.value.code == "no_service"
        assert boxes_grow(tracked)                                  # boxes flowed meanwhile...
        assert seen.results() == [] and seen.last_health() is None  # ...but not to the intruder
        seen.close()


def test_viewer_reads_boxes_but_cannot_call_control(etc, endpoint, ground, tracked):
    with open_client(etc, endpoint, "viewer") as viewer:
        boxes = SessionResults(viewer, NODE, SID)
        assert wait_until(lambda: len(boxes.results()) >= 3, 10), "the viewer saw no boxes"
        assert list_all(viewer, timeout=1.0) == []
        for op, request in (("stop", StopRequest(sid=SID)), ("start", StartRequest(image_key=FEED, box=(1, 1, 9, 9)))):
            with pytest.raises(ControlError) as err:
                call(viewer, NODE, op, request, timeout=1.0)
            assert err.value.code == "no_service"
        boxes.close()
    [sessions] = list_all(ground)
    assert [(s.sid, s.state) for s in sessions.sessions] == [(SID, "tracking")]


def test_camera_publishes_frames_but_cannot_call_control_or_read_boxes(etc, endpoint, tracked):
    with open_client(etc, endpoint, "camera") as camera:
        seen = SessionResults(camera, "*", "*")
        assert list_all(camera, timeout=1.0) == []
        with pytest.raises(ControlError) as err:
            call(camera, NODE, "start", StartRequest(image_key=FEED, box=(1, 1, 9, 9)), timeout=1.0)
        assert err.value.code == "no_service"
        assert boxes_grow(tracked)
        assert seen.results() == [] and seen.last_health() is None
        seen.close()


def tacf(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "tacf.cli", *args], capture_output=True, text=True, timeout=60)


def test_the_cli_takes_the_configs(etc, endpoint, tracked):
    """`tacf list` works with ground.json5; `tacf stop` with viewer.json5 is refused and stops nothing."""
    listed = tacf("list", "--json", "--zenoh-config", str(etc / "ground.json5"), "--connect", endpoint)
    assert listed.returncode == 0, listed.stderr
    assert SID in listed.stdout
    refused = tacf("stop", SID, "--node", NODE, "--timeout", "1", "--zenoh-config", str(etc / "viewer.json5"),
                   "--connect", endpoint)
    assert refused.returncode != 0
    assert boxes_grow(tracked)


def test_make_certs_takes_ipv6_addresses_and_keeps_keys_private_on_a_rerun(tmp_path):
    """An IPv6 address became a DNS name (useless to a client connecting by address), and a re-run left keys
    whose permissions had been opened up readable by all (umask only covers new files)."""
    if shutil.which("openssl") is None:
        pytest.skip("needs the openssl command to make certificates")
    certs = tmp_path / "certs"
    make = ["sh", str(DOCS / "make-certs.sh"), str(certs), "edge.local", "10.0.0.5", "2001:db8::5"]
    subprocess.run(make, check=True, capture_output=True)
    names = subprocess.run(["openssl", "x509", "-in", str(certs / "service.pem"), "-noout", "-ext",
                            "subjectAltName"], check=True, capture_output=True, text=True).stdout
    assert "DNS:edge.local" in names and "IP Address:10.0.0.5" in names and "IP Address:2001:DB8:" in names, names
    (certs / "service.key").chmod(0o644)
    subprocess.run(make, check=True, capture_output=True)
    assert all(key.stat().st_mode & 0o077 == 0 for key in certs.glob("*.key"))


def test_a_client_missing_a_file_its_settings_name_is_told_which(etc, tmp_path):
    """Zenoh reports a client's missing CA or key only as "Unable to connect": the command said no Zenoh node
    was reachable (exit 1), as for a network down."""
    missing = tmp_path / "missing.pem"
    config = derive(etc / "ground.json5", tmp_path / "ground-missing-ca.json5",
                    {"transport/link/tls/root_ca_certificate": str(missing)})
    done = subprocess.run([sys.executable, "-m", "tacf.cli", "list", "--zenoh-config", str(config), "--connect",
                           f"tls/127.0.0.1:{free_port()}"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip() == f"tacf list: transport/link/tls/root_ca_certificate: no such file: {missing}"


def test_a_client_that_may_not_read_a_file_its_settings_name_is_told_which(etc, tmp_path, unprivileged):
    """A mutual-TLS key readable by another user only (make-certs.sh run as root makes every key 600): Zenoh
    reports it as "Unable to connect", and the command said no Zenoh node was reachable (exit 1)."""
    key = tmp_path / "ground.key"
    shutil.copy(etc / "certs" / "ground.key", key)
    key.chmod(0)
    config = derive(etc / "ground.json5", tmp_path / "ground-locked-key.json5",
                    {"transport/link/tls/enable_mtls": True,
                     "transport/link/tls/connect_certificate": str(etc / "certs" / "ground.pem"),
                     "transport/link/tls/connect_private_key": str(key)})
    done = subprocess.run([*unprivileged, sys.executable, "-m", "tacf.cli", "list", "--zenoh-config", str(config),
                           "--connect", f"tls/127.0.0.1:{free_port()}"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip() == \
        f"tacf list: transport/link/tls/connect_private_key: cannot read {key}: permission denied"


def test_a_client_connecting_with_a_protocol_its_settings_leave_out_is_told_so(etc):
    """`--connect tcp/...` with the TLS-only ground.json5: Zenoh skips the endpoint, and the command said no Zenoh
    node was reachable (exit 1) as a client, no service answered as a peer."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    for mode in ("client", "peer"):
        done = subprocess.run([sys.executable, "-m", "tacf.cli", "list", "--zenoh-config", str(etc / "ground.json5"),
                               "--connect", endpoint, "--mode", mode, "--timeout", "1"],
                              capture_output=True, text=True, timeout=60)
        assert done.returncode == 2, done.stderr
        assert done.stderr.strip() == f"tacf list: cannot connect to {endpoint}: transport/link/protocols allows " \
                                      "only tls"


def test_a_service_whose_workers_cannot_log_in_refuses_to_start(etc):
    """Settings only the workers use (here the password they present, changed in users.txt but not in the service's
    file) used to fail in every worker, again and again, while the service said it was ready and accepted starts."""
    config = derive(etc / "service.json5", etc / "service-badpassword.json5",
                    {"transport/auth/usrpwd/password": "not-the-one-in-users-txt"})
    endpoint = f"tls/127.0.0.1:{free_port()}"
    done = subprocess.run([sys.executable, "-m", "tacf.cli", "serve", "--zenoh-config", str(config), "--listen",
                           endpoint, "--node", "badpassword", "--spare-workers", "0"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done.stderr[-2000:]
    assert f"cannot start the service: its worker processes cannot connect to it at {endpoint} with the settings " \
        f"of {config}" in done.stderr, done.stderr[-2000:]
    assert "ready" not in done.stderr


def test_a_service_missing_a_file_only_its_workers_read_is_told_which_at_once(etc, tmp_path):
    """The CA that the workers check the service's certificate with: the worker check failed after its 5 s connect
    timeout with "Unable to connect ... Timeout!", naming no file, as a client once did (the test above it)."""
    missing = tmp_path / "missing-ca.pem"
    config = derive(etc / "service.json5", tmp_path / "service-missing-ca.json5",
                    {"transport/link/tls/root_ca_certificate": str(missing)})
    started = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "tacf.cli", "serve", "--zenoh-config", str(config), "--listen",
                           f"tls/127.0.0.1:{free_port()}", "--node", "missing-ca", "--spare-workers", "0"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done.stderr[-2000:]
    assert f"cannot start the service: its worker processes cannot use the settings of {config}: " \
        f"transport/link/tls/root_ca_certificate: no such file: {missing}" in done.stderr, done.stderr[-2000:]
    assert time.monotonic() - started < 4.5, "waited for the workers' connect timeout"


def test_mutual_tls_with_access_control_by_certificate_common_name(etc):
    """The mutual-TLS variant of the README: every side presents a certificate of make-certs.sh, and the access
    control's subjects are certificate common names instead of user names."""
    certs = etc / "certs"

    def presenting(name: str) -> dict:
        return {"transport/link/tls/enable_mtls": True,
                "transport/link/tls/connect_certificate": str(certs / f"{name}.pem"),
                "transport/link/tls/connect_private_key": str(certs / f"{name}.key")}

    subjects = [{"id": "edge", "cert_common_names": ["tacf-service"]},
                {"id": "ground", "cert_common_names": ["ground"]},
                {"id": "viewer", "cert_common_names": ["viewer"]},
                {"id": "camera", "cert_common_names": ["camera"]}]
    config = derive(etc / "service.json5", etc / "service-mtls.json5",
                    {**presenting("service"), "access_control/subjects": subjects})
    endpoint = f"tls/127.0.0.1:{free_port()}"
    node = "mtls-edge"
    svc = TrackingService(ServiceOptions(node=node, zenoh=ZenohOptions(listen=(endpoint,), config_file=str(config)),
                                         spare_workers=1)).open()
    try:
        # a worker reports idle once its session is open: it got in with the service's certificate
        assert wait_until(lambda: svc.manager.idle_spares() >= 1, 60), "no worker connected after 60 s"
        with open_client(etc, endpoint, "ground", settings=presenting("ground")) as ground:
            assert [reply.node for reply in list_all(ground)] == [node]
        # the ground station's password with the viewer's certificate: the certificate decides
        with open_client(etc, endpoint, "ground", settings=presenting("viewer")) as impostor:
            assert list_all(impostor, timeout=1.0) == []
        with pytest.raises(zenoh.ZError):                               # no client certificate at all
            open_client(etc, endpoint, "ground")
    finally:
        svc.close()
