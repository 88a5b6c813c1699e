"""Security: a real secure router (mutual TLS + access control, and TLS + user/password), real services as its
clients, real Zenoh on loopback; certificates made here with ``cryptography``. Plus unit tests of the ACL builder
and of the router's security config."""

from __future__ import annotations

import datetime
import ipaddress
import itertools
import json
import re
import subprocess
import sys
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import yaml
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID
from support.env import child_env as clean_env
from support.processes import Processes
from support.waits import wait_for, wait_for_subscribers

from orchestrator.stack.launcher import free_loopback_port
from protocol import codec, keys
from protocol.bus import ANSWER_TIMEOUT_S, Bus, BusConfig, BusError, Inbox, Received, Traffic
from protocol.deploy.config import ConfigError
from protocol.deploy.security import ROLES, Identity, build_access_control, check_users_file, router_settings
from protocol.episode_spec import CameraSpec, EpisodeSpec
from protocol.messages import (
    CameraFrame,
    Command,
    ControlReply,
    ControlRequest,
    EndReason,
    EpisodeScore,
    Header,
    Pose,
    ReplyCode,
)

ROOT = Path(__file__).resolve().parent.parent
SPEC = EpisodeSpec(circuit="simple", max_sim_seconds=3.0, seed=5, camera=CameraSpec(width_px=160, height_px=120))
INTRUDER_YAW_RATE = 4.321  # rad/s: absurd, and recognisable in the poses (they carry the applied command)
# Stopped by the test. Real time, many laps: it lasts its 600 s of wall time, so a swap lands in it however fast
# the machine (in lock-step a fast one could drive its lap while the new brain's process started).
SPEC_LONG = EpisodeSpec(circuit="simple", laps=100, max_sim_seconds=600.0, realtime=True, seed=5, camera=SPEC.camera)
FAILED_OPEN_MS = 1500  # connect timeout of the buses that must fail to open
# How long a test that expects no answer (a query the router drops) waits: a slow answer would pass as a refusal,
# which the positive controls beside each such check (the same query answered for a role allowed it) rule out.
REFUSED_WAIT_S = 2.0


# -- certificates --


def _key():
    return ec.generate_private_key(ec.SECP256R1())


def _write(folder: Path, name: str, key, certificate) -> None:
    (folder / f"{name}.key").write_bytes(
        key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())
    )
    (folder / f"{name}.pem").write_bytes(certificate.public_bytes(serialization.Encoding.PEM))


def make_pki(folder: Path, names: list[str]) -> Path:
    """A CA (``ca.pem``) and, per name, ``NAME.pem`` / ``NAME.key`` with common name NAME, valid for ``localhost``
    and 127.0.0.1 (the router's name check), usable as server and client certificates."""
    folder.mkdir(parents=True, exist_ok=True)
    now = datetime.datetime.now(datetime.timezone.utc)
    ca_key = _key()
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "drivebench test CA")])
    ca = (
        x509.CertificateBuilder()
        .subject_name(ca_name)
        .issuer_name(ca_name)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(hours=1))
        .not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .add_extension(
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
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    _write(folder, "ca", ca_key, ca)
    for name in names:
        key = _key()
        certificate = (
            x509.CertificateBuilder()
            .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)]))
            .issuer_name(ca_name)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(hours=1))
            .not_valid_after(now + datetime.timedelta(days=1))
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(
                x509.SubjectAlternativeName(
                    [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
                ),
                critical=False,
            )
            .add_extension(
                x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                critical=False,
            )
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
            .sign(ca_key, hashes.SHA256())
        )
        _write(folder, name, key, certificate)
    return folder


# -- processes --


def tls_env(pki: Path, identity: str) -> dict[str, str]:
    return {
        "DRIVEBENCH_TLS_ROOT_CA": str(pki / "ca.pem"),
        "DRIVEBENCH_TLS_CERT": str(pki / f"{identity}.pem"),
        "DRIVEBENCH_TLS_KEY": str(pki / f"{identity}.key"),
    }


def start_router(processes: Processes, folder: Path, name: str, config: dict) -> None:
    path = folder / f"{name}.yaml"
    path.write_text(json.dumps(config))  # YAML is a superset of JSON
    processes.start(name, ["services.router", "--config", str(path)], clean_env())
    processes.wait_for_log(name, "router listening on")


def client_bus(pki: Path, endpoint: str, identity: str | None, *, name: str, **config) -> Bus:
    """A bus of this test process with ``identity``'s certificate (None: the CA only, no certificate of its own).
    TLS set and no mode: a client."""
    files = {"tls_root_ca": str(pki / "ca.pem")}
    if identity is not None:
        files |= {"tls_cert": str(pki / f"{identity}.pem"), "tls_key": str(pki / f"{identity}.key")}
    return Bus(BusConfig(connect=[endpoint], **files, **config), name=name)


@dataclass
class SecureStack:
    pki: Path
    endpoint: str
    run_id: str
    processes: Processes
    orchestrator: Bus

    def bus(self, identity: str | None, *, name: str, **config) -> Bus:
        return client_bus(self.pki, self.endpoint, identity, name=name, **config)

    def control(
        self, bus: Bus, request: ControlRequest, *, key: str | None = None, timeout_s: float = ANSWER_TIMEOUT_S
    ) -> ControlReply | None:
        """The simulator's answer, or None. Where an answer is expected, wait as long as the product does (a loaded
        machine answered after the 2 s this used to wait); a test expecting None passes :data:`REFUSED_WAIT_S`."""
        payload = bus.request(key or keys.sim_control(self.run_id), codec.encode(request), timeout_s=timeout_s)
        return None if payload is None else codec.decode(payload, ControlReply)

    def wait_idle(self) -> None:
        """Until the simulator says idle: it publishes an episode's score before it leaves the episode, so a start
        sent the moment a score arrives could be refused busy (seen at load 8-20)."""
        wait_for(lambda: self.status().state == "idle", timeout_s=60, what="the simulator to be idle")

    def status(self) -> ControlReply:
        reply = self.control(self.orchestrator, ControlRequest(action="status"), key=keys.sim_status(self.run_id))
        assert reply is not None, "the simulator's status did not answer"
        return reply

    def run_episode(self, spec: EpisodeSpec = SPEC) -> tuple[EpisodeScore, np.ndarray]:
        """Start an episode as the orchestrator; its score and its poses (seq, x, y, yaw, applied yaw rate)."""
        inbox = Inbox()
        subscriptions = [
            self.orchestrator.subscribe(keys.pose(self.run_id), Pose, inbox=inbox),
            self.orchestrator.subscribe(keys.score(self.run_id), EpisodeScore, inbox=inbox),
        ]
        try:
            self.wait_idle()
            reply = self.control(self.orchestrator, ControlRequest(action="start", spec=spec))
            assert reply is not None and reply.ok, reply
            episode, poses = reply.episode, []
            deadline = time.monotonic() + 60
            while True:
                assert (dead := self.processes.dead()) is None, dead
                assert time.monotonic() < deadline, f"episode {episode} not scored in 60 s"
                received = inbox.recv(timeout_s=0.2)
                if received is None or received.message.header.episode != episode:
                    continue
                message = received.message
                if isinstance(message, EpisodeScore):
                    score = message
                    break
                poses.append((message.header.seq, message.x_m, message.y_m, message.yaw_rad, message.yaw_rate_radps))
            # Poses and the score arrive on two subscriptions, each called back on its own thread: the last pose may
            # come in just after the score. Take every pose up to the last step the score counted.
            late = time.monotonic() + 5
            while poses[-1][0] < score.metrics.steps and time.monotonic() < late:
                received = inbox.recv(timeout_s=0.2)
                if received is not None and isinstance(received.message, Pose):
                    pose = received.message
                    if pose.header.episode == episode:
                        poses.append((pose.header.seq, pose.x_m, pose.y_m, pose.yaw_rad, pose.yaw_rate_radps))
        finally:
            for subscription in subscriptions:
                subscription.close()
        return score, np.array(sorted(poses))


@pytest.fixture(scope="module")
def secure_stack(tmp_path_factory):
    """Router (mTLS + drivebench roles), simulator, explicit brain host and scorer, each with its own certificate;
    the test process is the orchestrator."""
    folder = tmp_path_factory.mktemp("secure")
    pki = make_pki(folder / "pki", ["router", "sim", "brain", "scorer", "orchestrator", "viewer", "stranger"])
    (folder / "logs").mkdir()
    processes = Processes(folder / "logs")
    port = free_loopback_port()
    endpoint, run_id = f"tls/localhost:{port}", f"s{uuid.uuid4().hex[:8]}"
    orchestrator = None
    try:
        start_router(
            processes,
            folder,
            "router",
            {
                "bus": {
                    "listen": [f"tls/127.0.0.1:{port}"],
                    "tls_cert": str(pki / "router.pem"),
                    "tls_key": str(pki / "router.key"),
                    "tls_root_ca": str(pki / "ca.pem"),
                },
                "mtls": True,
                "roles": {
                    "brain": ["brain"],
                    "orchestrator": ["orchestrator"],
                    "service": ["sim", "scorer"],
                    "observer": ["viewer"],
                },
            },
        )
        common = ["--router", endpoint, "--run-id", run_id]
        processes.start("simulator", ["services.simulator", *common], clean_env(**tls_env(pki, "sim")))
        processes.start(
            "brain",
            ["brains", "--brain", "explicit", "--set", "camera=raw", *common],
            clean_env(**tls_env(pki, "brain")),
        )
        processes.start("scorer", ["services.scorer", *common], clean_env(**tls_env(pki, "scorer")))
        orchestrator = client_bus(pki, endpoint, "orchestrator", name="orchestrator")
        assert orchestrator.resolved.mode == "client"
        watch = orchestrator.watch_alive(keys.alive_all(run_id))
        wanted = {
            keys.alive(run_id, "simulator", "sim"),
            keys.alive(run_id, "brain", "explicit"),
            keys.alive(run_id, "scorer", "scorer"),
        }
        missing = watch.wait_for(wanted, timeout_s=40, abort=processes.dead)
        assert (dead := processes.dead()) is None, dead
        assert not missing, f"not alive: {missing}"
        yield SecureStack(pki=pki, endpoint=endpoint, run_id=run_id, processes=processes, orchestrator=orchestrator)
    finally:
        if orchestrator is not None:
            orchestrator.close()
        processes.stop()
    for name, process in processes.children.items():
        assert process.poll() is not None, f"{name} still running"


class Intruder:
    """Answers every camera frame at once, from Zenoh's callback (ahead of the real brain), with an absurd command
    under the active brain's name and key; and declares a brain liveliness token of its own."""

    def __init__(self, bus: Bus, run_id: str, *, brain: str = "explicit", key_brain: str | None = None):
        self.sent = 0
        publisher = bus.publisher(keys.command(run_id, key_brain or brain), Command, Traffic.COMMANDS)
        intruder = self

        class AnswerAtOnce(Inbox):
            def put(self, item: Received) -> None:
                frame: CameraFrame = item.message
                h = frame.header
                publisher.publish(
                    Command(
                        header=Header(run_id=run_id, episode=h.episode, seq=intruder.sent, stamp_ns=h.stamp_ns),
                        brain=brain,
                        frame_seq=h.seq,
                        speed_mps=3.0,
                        yaw_rate_radps=INTRUDER_YAW_RATE,
                    )
                )
                intruder.sent += 1

        bus.subscribe(keys.camera_raw(run_id), CameraFrame, inbox=AnswerAtOnce())
        bus.declare_alive(keys.alive(run_id, "brain", "intruder"))


def wait_until_alive_seen(stack, name: str) -> None:
    """Until the orchestrator sees the intruder's brain token. The intruder declares it after its camera
    subscription, on the same session, so the router has taken (and passed to the simulator) the subscription
    before the orchestrator's next start can reach the simulator: an event, not a guess of how long that takes."""
    key = keys.alive(stack.run_id, "brain", name)
    watch = stack.orchestrator.watch_alive(key)
    try:
        assert not watch.wait_for({key}, timeout_s=60), f"the intruder's token {key} never reached the orchestrator"
    finally:
        watch.close()


# -- the secure stack --


@pytest.mark.integration
def test_a_client_without_a_certificate_cannot_connect(secure_stack):
    started = time.monotonic()
    with pytest.raises(BusError) as error:
        secure_stack.bus(None, name="anonymous", connect_timeout_ms=FAILED_OPEN_MS)
    message = str(error.value)
    assert "\n" not in message
    assert message.startswith(f"cannot open the bus (client, connect=['{secure_stack.endpoint}']")
    assert "Timeout" in message and "refused or missing certificate" in message
    assert time.monotonic() - started < 10


@pytest.mark.integration
def test_an_intruder_without_the_brain_role_changes_nothing_and_the_same_one_with_it_does(secure_stack):
    """(2) a viewer's commands for every frame are not applied: poses identical to a run without it, and none with
    its yaw rate; its brain token is not seen. (3) the same intruder with brain credentials drives the car."""
    stack = secure_stack
    baseline_score, baseline = stack.run_episode()
    assert baseline_score.reason == EndReason.TIME_LIMIT
    assert len(baseline) == 61 and np.ptp(baseline[:, 1]) > 5  # 3 s at 20 Hz plus the start pose; it moved

    stranger_inbox = Inbox()
    with stack.bus("viewer", name="viewer") as viewer, stack.bus("stranger", name="stranger") as stranger:
        intruder = Intruder(viewer, stack.run_id)
        viewer_poses = viewer.subscribe(keys.pose(stack.run_id), Pose)
        stranger.subscribe(keys.pose(stack.run_id), Pose, inbox=stranger_inbox)
        time.sleep(1.0)  # ample for a token or a subscription to reach the router (milliseconds when allowed)
        assert keys.alive(stack.run_id, "brain", "intruder") not in stack.orchestrator.alive_now(
            keys.alive_all(stack.run_id)
        )
        refused = stack.control(
            stack.orchestrator,
            ControlRequest(action="start", spec=EpisodeSpec(active_brain="intruder", camera=SPEC.camera)),
        )
        assert refused is not None and (refused.ok, refused.code) == (False, ReplyCode.NOT_ALIVE)
        score, poses = stack.run_episode()
        assert intruder.sent >= 60  # it saw every frame (an observer may subscribe) and answered each
        assert viewer_poses.inbox.received >= 61
    assert score.reason == baseline_score.reason
    assert np.array_equal(poses, baseline)  # lock-step is deterministic: not one command of the intruder applied
    assert INTRUDER_YAW_RATE not in poses[:, 4]
    assert stranger_inbox.received == 0  # a certificate of the CA in no role gets nothing at all

    # Positive control: the same intruder code with a brain's certificate is obeyed.
    with stack.bus("brain", name="rogue-brain") as rogue:
        intruder = Intruder(rogue, stack.run_id)
        wait_until_alive_seen(stack, "intruder")
        score, poses = stack.run_episode()
    assert intruder.sent > 0
    applied = int(np.count_nonzero(poses[:, 4] == INTRUDER_YAW_RATE))
    assert applied > 0, "the positive control failed: a brain identity's commands were not applied"
    assert not np.array_equal(poses[:, 1:4], baseline[: len(poses), 1:4])


def logged_bus(log_text: str) -> dict:
    """The ``bus`` section of the "resolved config" a service logged at start."""
    block = log_text.split("resolved config:\n", 1)[1]
    lines = itertools.takewhile(lambda line: not re.match(r"\d\d:\d\d:\d\d ", line), block.splitlines())
    return yaml.safe_load("\n".join(lines))["bus"]


@pytest.mark.integration
def test_a_tls_client_logs_the_bus_it_joins_from_its_options_or_its_environment(secure_stack, tmp_path):
    """Issue 34: a TLS client logged ``mode: ''``, ``connect: []``, ``tls_cert: ''`` (its config before the
    environment and the defaults), not how it joined the bus."""
    pki, endpoint = secure_stack.pki, secure_stack.endpoint
    simulator = logged_bus(secure_stack.processes.log("simulator"))  # --router, TLS from the environment
    assert simulator["mode"] == "client" and simulator["connect"] == [endpoint] and simulator["listen"] == []
    assert (simulator["tls_cert"], simulator["tls_key"]) == (str(pki / "sim.pem"), str(pki / "sim.key"))
    assert simulator["tls_root_ca"] == str(pki / "ca.pem") and simulator["connect_timeout_ms"] == 10_000

    # everything from the environment: the router too
    processes = Processes(tmp_path)
    env = clean_env(**tls_env(pki, "scorer"), DRIVEBENCH_ROUTER=endpoint)
    processes.start("scorer", ["services.scorer", "--run-id", "logged"], env)
    try:
        processes.wait_for_log("scorer", "scorer ready")
    finally:
        processes.stop()
    scorer = logged_bus(processes.log("scorer"))
    assert (scorer["mode"], scorer["connect"], scorer["tls_cert"]) == ("client", [endpoint], str(pki / "scorer.pem"))


@pytest.mark.integration
def test_a_brain_cannot_answer_for_another_brain_by_naming_it(secure_stack):
    """The brain role may put on every brain's command key; the simulator takes a command only from the key of the
    brain it names, so an impostor publishing "explicit" commands on its own key changes nothing."""
    stack = secure_stack
    _, baseline = stack.run_episode()
    with stack.bus("brain", name="impostor") as impostor:
        intruder = Intruder(impostor, stack.run_id, key_brain="impostor")
        wait_until_alive_seen(stack, "intruder")
        _, poses = stack.run_episode()
    assert intruder.sent >= 60
    assert np.array_equal(poses, baseline)


@pytest.mark.integration
def test_only_the_orchestrator_may_start_an_episode(secure_stack):
    stack = secure_stack
    before = stack.status()
    assert before.state == "idle"
    for identity in ("brain", "viewer"):
        with stack.bus(identity, name=f"{identity}-starter") as bus:
            # Its read-only status query is answered: the simulator is reachable for it...
            status = stack.control(bus, ControlRequest(action="status"), key=keys.sim_status(stack.run_id))
            assert status is not None and status.state == "idle"
            # ... but its start is dropped by the router: no reply at all, and nothing starts.
            assert stack.control(bus, ControlRequest(action="start", spec=SPEC), timeout_s=REFUSED_WAIT_S) is None
            # sim/control entirely
            assert stack.control(bus, ControlRequest(action="status"), timeout_s=REFUSED_WAIT_S) is None
    time.sleep(0.5)
    after = stack.status()
    assert (after.state, after.episode) == ("idle", before.episode)


@pytest.mark.integration
def test_a_brain_may_put_commands_only(secure_stack):
    """A brain identity cannot publish a pose, not even through a wildcard key that includes the pose key."""
    stack = secure_stack
    run = stack.run_id
    with stack.bus("brain", name="spoofer") as brain:
        inbox = stack.orchestrator.subscribe(keys.pose(run), Pose).inbox
        commands = stack.orchestrator.subscribe(keys.command(run, "spoofer"), Command).inbox
        command = brain.publisher(keys.command(run, "spoofer"), Command, Traffic.COMMANDS)
        # Both subscriptions were declared in this order on one session: once the second has reached the brain
        # (through the router), the first has reached the router too.
        wait_for_subscribers(command)
        pose = Pose(header=Header(run_id=run, episode=99, seq=0, stamp_ns=0), x_m=1.0, y_m=2.0, yaw_rad=0.0)
        for key in (keys.pose(run), keys.run_all(run), f"{keys.run_prefix(run)}/sim/*"):
            brain.publisher(key, Pose, Traffic.EVENTS).publish(pose)
        command.publish(Command(header=pose.header, brain="spoofer", frame_seq=0, speed_mps=0.0, yaw_rate_radps=0.0))
        assert commands.recv(timeout_s=3.0) is not None  # the allowed put arrives...
        assert inbox.recv(timeout_s=0.5) is None  # ... the forbidden ones never did


def drivebench_cli(args: list[str], env: dict[str, str], *, timeout_s: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", *args],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout_s,
    )


@pytest.mark.integration
def test_a_live_swap_on_the_secure_stack_runs_as_the_orchestrator_and_starts_a_brain_identity(secure_stack, tmp_path):
    """``drivebench swap`` as docs/security.md says: the orchestrator's certificate for the swap (it switches and stops
    brains), a brain's for the host it starts. Last of the secure stack's tests: the stack's brain is retired."""
    stack, run = secure_stack, secure_stack.run_id
    env = clean_env(**tls_env(stack.pki, "orchestrator"))
    swap = ["swap", "explicit", "--router", stack.endpoint, "--run", run, "--runs-dir", str(tmp_path)]
    # Without a brain identity the new host would inherit the orchestrator's, which may not declare a brain's token:
    # refused at once, in one line, before anything starts.
    refused = drivebench_cli(swap, env, timeout_s=60)
    assert refused.returncode == 2, refused.stderr
    assert "--brain-cert and --brain-key" in refused.stderr and len(refused.stderr.strip().splitlines()) == 1
    assert stack.status().state == "idle"

    scores = stack.orchestrator.subscribe(keys.score(run), EpisodeScore).inbox
    started = stack.control(stack.orchestrator, ControlRequest(action="start", spec=SPEC_LONG))
    assert started is not None and started.ok, started
    brain_cert = ["--brain-cert", str(stack.pki / "brain.pem"), "--brain-key", str(stack.pki / "brain.key")]
    try:
        swapped = drivebench_cli([*swap, *brain_cert, "--timeout", "90"], env)
        assert swapped.returncode == 0, swapped.stderr
        assert "explicit-2 (explicit, pid" in swapped.stdout and "in place of explicit (stopped)" in swapped.stdout
    finally:
        stack.control(stack.orchestrator, ControlRequest(action="stop"))
    score = scores.recv(timeout_s=60)
    assert score is not None and score.message.header.episode == started.episode
    assert score.message.brain == "explicit-2"
    assert [(s.from_brain, s.to_brain) for s in score.message.switches] == [("explicit", "explicit-2")]
    assert stack.processes.children["brain"].wait(timeout=10) == 0  # the old brain stopped on request
    stopped = stack.control(
        stack.orchestrator, ControlRequest(action="stop"), key=keys.brain_control(run, "explicit-2")
    )
    assert stopped is not None and stopped.ok  # the new host answers its control key: it holds the brain role


# -- TLS without mutual TLS, with user names and passwords --


@pytest.mark.integration
def test_tls_with_user_password_lets_known_users_in_and_refuses_a_wrong_password(tmp_path, monkeypatch):
    pki = make_pki(tmp_path / "pki", ["router"])
    users = tmp_path / "users.txt"
    users.write_text("pilot:pilot-pw\nsimuser:sim-pw\nwatcher:watch-pw\n")
    processes = Processes(tmp_path)
    port = free_loopback_port()
    endpoint, run = f"tls/localhost:{port}", "tlsrun"

    def bus(user: str, password: str, **config) -> Bus:
        secret = tmp_path / f"{user}-{password}.pw"
        secret.write_text(password + "\n")
        return Bus(
            BusConfig(
                connect=[endpoint], tls_root_ca=str(pki / "ca.pem"), user=user, password_file=str(secret), **config
            ),
            name=user,
        )

    try:
        start_router(
            processes,
            tmp_path,
            "router",
            {
                "bus": {
                    "listen": [f"tls/127.0.0.1:{port}"],
                    "tls_cert": str(pki / "router.pem"),
                    "tls_key": str(pki / "router.key"),
                },
                "users_file": str(users),
                "roles": {"brain": [{"username": "pilot"}], "service": ["simuser"], "observer": ["watcher"]},
            },
        )
        with pytest.raises(BusError, match="wrong user/password") as error:
            bus("pilot", "not-the-password", connect_timeout_ms=FAILED_OPEN_MS)
        assert "\n" not in str(error.value)
        with pytest.raises(BusError, match="Timeout"):  # TLS alone, no credentials
            Bus(
                BusConfig(connect=[endpoint], tls_root_ca=str(pki / "ca.pem"), connect_timeout_ms=FAILED_OPEN_MS),
                name="nobody",
            )
        monkeypatch.setenv("DRIVEBENCH_USER", "watcher")  # credentials from the environment work the same
        monkeypatch.setenv("DRIVEBENCH_PASSWORD", "watch-pw")
        with (
            bus("pilot", "pilot-pw") as pilot,
            bus("simuser", "sim-pw") as sim,
            Bus(BusConfig(connect=[endpoint], tls_root_ca=str(pki / "ca.pem")), name="watcher") as watcher,
        ):
            assert watcher.resolved.user == "watcher"
            inbox = sim.subscribe(keys.commands_all(run), Command).inbox
            publishers = {
                brain: source.publisher(keys.command(run, brain), Command, Traffic.COMMANDS)
                for source, brain in ((watcher, "watcher"), (pilot, "pilot"))
            }
            wait_for_subscribers(publishers["pilot"])  # the simulator's subscription reached the brain user
            for brain, publisher in publishers.items():
                publisher.publish(
                    Command(
                        header=Header(run_id=run, episode=0, seq=0, stamp_ns=0),
                        brain=brain,
                        frame_seq=0,
                        speed_mps=1.0,
                        yaw_rate_radps=0.0,
                    )
                )
            received = inbox.recv(timeout_s=3.0)
            assert received is not None and received.message.brain == "pilot"  # the brain user's command arrives
            assert inbox.recv(timeout_s=0.5) is None  # the observer's never does
    finally:
        processes.stop()


# -- units: the ACL builder and the router's security config --


def _rules_of(acl: dict, subject_match: dict) -> list[dict]:
    ids = {s["id"] for s in acl["subjects"] if {k: v for k, v in s.items() if k != "id"} == subject_match}
    rule_ids = {r for p in acl["policies"] if ids & set(p["subjects"]) for r in p["rules"]}
    return [rule for rule in acl["rules"] if rule["id"] in rule_ids]


def _allowed(acl: dict, subject_match: dict, flow: str, message: str) -> set[str]:
    return {
        key
        for rule in _rules_of(acl, subject_match)
        if flow in rule["flows"] and message in rule["messages"]
        for key in rule["key_exprs"]
    }


def test_acl_is_default_deny_with_one_subject_per_identity():
    acl = build_access_control(
        {
            "brain": ["gpu-box", Identity(cert_common_name="b2", username="alice")],
            "orchestrator": ["orchestrator"],
            "observer": ["viewer", "gpu-box"],
        }
    )
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    assert all(rule["permission"] == "allow" for rule in acl["rules"])
    subjects = [{k: v for k, v in s.items() if k != "id"} for s in acl["subjects"]]
    assert {"cert_common_names": ["gpu-box"]} in subjects and {"usernames": ["gpu-box"]} in subjects
    assert {"cert_common_names": ["b2"], "usernames": ["alice"]} in subjects  # both must match
    assert len(subjects) == len({json.dumps(s, sort_keys=True) for s in subjects}) == 7  # gpu-box once, twice named
    assert len({s["id"] for s in acl["subjects"]}) == 7 and len({r["id"] for r in acl["rules"]}) == len(acl["rules"])


def test_acl_grants_each_role_its_own_keys_only():
    acl = build_access_control({"brain": ["b"], "orchestrator": ["o"], "service": ["s"], "observer": ["v"]})
    cn = lambda name: {"cert_common_names": [name]}  # noqa: E731
    assert _allowed(acl, cn("b"), "ingress", "put") == {"drivebench/run/*/brain/*/cmd"}
    assert _allowed(acl, cn("b"), "ingress", "liveliness_token") == {"drivebench/alive/*/brain/*"}
    assert _allowed(acl, cn("b"), "ingress", "declare_queryable") == {"drivebench/run/*/brain/*/control"}
    assert _allowed(acl, cn("o"), "ingress", "liveliness_token") == {
        "drivebench/alive/*/driver/*",
        "drivebench/alive/*/claim/*",  # a swap reserves its new brain's name (keys.name_claim)
    }
    assert _allowed(acl, cn("o"), "ingress", "query") == {
        "drivebench/run/*/sim/control",
        "drivebench/run/*/sim/status",
        "drivebench/run/*/brain/*/control",
        "drivebench/run/*/recorder/control",  # a warm matrix stack's recorder: one file per episode
    }
    assert "drivebench/run/*/recorder/control" in _allowed(acl, cn("s"), "ingress", "declare_queryable")
    for name in ("b", "v", "s"):
        assert "drivebench/run/*/sim/control" not in _allowed(acl, cn(name), "ingress", "query")
        assert _allowed(acl, cn(name), "ingress", "query") == {"drivebench/run/*/sim/status"}
    assert _allowed(acl, cn("v"), "ingress", "put") == set()
    assert _allowed(acl, cn("v"), "ingress", "liveliness_token") == set()
    assert _allowed(acl, cn("v"), "ingress", "declare_subscriber") == {"drivebench/**"}
    assert _allowed(acl, cn("v"), "egress", "put") == {"drivebench/**"}
    assert "drivebench/run/*/brain/*/cmd" not in _allowed(acl, cn("s"), "ingress", "put")
    assert {
        "drivebench/run/*/sim/camera",
        "drivebench/run/*/noise/camera",
        "drivebench/run/*/scorer/score",
    } <= _allowed(acl, cn("s"), "ingress", "put")
    assert _allowed(acl, {"cert_common_names": ["nobody"]}, "ingress", "declare_subscriber") == set()


def test_acl_patterns_come_from_the_keys_module():
    run = "r1"
    patterns = {key for grants in ROLES.values() for _, _, key_exprs in grants for key in key_exprs}
    concrete = [
        keys.command(run, "x"),
        keys.brain_control(run, "x"),
        keys.sim_control(run),
        keys.sim_status(run),
        keys.recorder_control(run),
        keys.camera_raw(run),
        keys.camera_perturbed(run),
        keys.pose(run),
        keys.events(run),
        keys.live_metrics(run),
        keys.score(run),
        keys.alive(run, "brain", "x"),
    ]
    for key in concrete:
        assert any(_matches(pattern, key) for pattern in patterns), key


def _matches(pattern: str, key: str) -> bool:
    p, k = pattern.split("/"), key.split("/")
    if p and p[-1] == "**":
        return len(k) >= len(p) - 1 and all(a in ("*", b) for a, b in zip(p[:-1], k))
    return len(p) == len(k) and all(a in ("*", b) for a, b in zip(p, k))


def test_unknown_roles_and_unusable_settings_are_one_line(tmp_path):
    known = "brain, noise, observer, orchestrator, recorder, replay, ros2_bridge, scorer, service, simulator, viz"
    with pytest.raises(ConfigError, match=f"roles: unknown role\\(s\\) 'pilot' \\(roles: {known}\\)"):
        build_access_control({"pilot": ["x"]})
    with pytest.raises(ValueError, match="an identity needs a cert_common_name, a username or both"):
        Identity()
    base = dict(
        mtls=False,
        tls_root_ca="",
        tls_cert="",
        listen=["tls/0.0.0.0:7447"],
        users_file="",
        roles={},
        access_control_file="",
    )
    with pytest.raises(ConfigError, match="mtls: true needs the CA"):
        router_settings(**base | {"mtls": True})
    with pytest.raises(ConfigError, match="mtls: true needs a tls/ or quic/ endpoint"):
        router_settings(**base | {"mtls": True, "tls_root_ca": "ca.pem", "listen": ["tcp/0.0.0.0:7447"]})
    with pytest.raises(ConfigError, match="roles need identities to match"):
        router_settings(**base | {"roles": {"brain": ["b"]}})
    with pytest.raises(ConfigError, match=f"users_file: cannot read {tmp_path}/none.txt: No such file or directory"):
        router_settings(**base | {"users_file": str(tmp_path / "none.txt")})
    bad = tmp_path / "users.txt"
    bad.write_text("alice:pw\n# bob\n")
    with pytest.raises(ConfigError, match=f"users_file: {bad}:2: expected user:password"):
        check_users_file(str(bad))
    with pytest.raises(ConfigError, match="access_control_file: cannot read"):
        router_settings(**base | {"access_control_file": str(tmp_path / "acl.json5")})
    assert router_settings(**base) == {}


def test_a_hand_written_access_control_file_is_checked_by_zenoh(tmp_path):
    good = tmp_path / "acl.json5"
    good.write_text("""{ // JSON5: comments and unquoted keys
      enabled: true, default_permission: "deny",
      rules: [{ id: "r", messages: ["put"], flows: ["ingress"], permission: "allow", key_exprs: ["a/**"] }],
      subjects: [{ id: "s", cert_common_names: ["x"] }],
      policies: [{ rules: ["r"], subjects: ["s"] }],
    }""")
    base = dict(
        mtls=True,
        tls_root_ca="ca.pem",
        tls_cert="r.pem",
        listen=["tls/0.0.0.0:7447"],
        users_file="",
        roles={},
        access_control_file=str(good),
    )
    settings = router_settings(**base)
    assert settings["access_control"]["rules"][0]["key_exprs"] == ["a/**"]
    assert settings["transport/link/tls/enable_mtls"] is True
    as_yaml = tmp_path / "acl.yaml"
    as_yaml.write_text("access_control:\n  enabled: true\n  default_permission: deny\n")
    assert router_settings(**base | {"access_control_file": str(as_yaml)})["access_control"]["enabled"] is True
    bad = tmp_path / "bad.json5"
    bad.write_text('{ enabled: true, rules: [{ id: "r", messages: ["publish"] }] }')
    with pytest.raises(ConfigError, match="access_control_file: .*bad.json5: .*unknown variant `publish`"):
        router_settings(**base | {"access_control_file": str(bad)})
    with pytest.raises(ConfigError, match="roles and access_control_file are alternatives"):
        router_settings(**base | {"roles": {"brain": ["b"]}})
