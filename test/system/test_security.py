"""SROS2 (docs/security.md): config/security/policy.xml is what the nodes do, and it makes a working keystore.

* The policy against the live graph: a simulated stack (sim.launch.py's process list plus the DDS link check)
  runs with every node in its policy enclave (``--enclave``, inert without ROS_SECURITY_ENABLE), and
  ``ros2 security generate_policy`` of that graph must equal the policy, node by node.
* The keystore: ``ros2 security create_keystore`` / ``create_enclave`` / ``create_permission`` from the policy,
  one enclave per node; a malformed policy is refused.
* The launch files' ``keystore:=``: every node gets its policy enclave and the SROS2 environment.
* Fail-closed start: enforced, a deployment node whose enclave is missing never joins the graph.

The ``ros2 security`` verbs come from sros2 (a ROS install, or ../shared/ros-security through
tools/bootstrap.sh); those tests skip where it is missing. Enforcement itself needs the DDS security plugins,
which the PyPI Fast DDS lacks.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
import importlib.util
import os
from pathlib import Path
import shutil
import signal
import subprocess
import sys
import time
import xml.etree.ElementTree as ET

import pytest
import yaml

REPO = Path(__file__).resolve().parents[2]
POLICY = REPO / "config" / "security" / "policy.xml"
DEPLOYMENT = {"gsrmr-robot": "gsrmr_robot", "gsrmr-server": "gsrmr_server", "gsrmr-scheduler": "gsrmr_scheduler",
              "gsrmr-limo-base": "gsrmr_limo_base"}
# rclpy's own entities: every node publishes these and serves these (Kilted: with the type description service)
RCLPY_PUBLISHES = ("/parameter_events", "/rosout")
RCLPY_SERVES = ("describe_parameters", "get_parameter_types", "get_parameters", "get_type_description",
                "list_parameters", "set_parameters", "set_parameters_atomically")
# The one rule for nodes that generate_policy may report and the policy does not name: ros2cli's own nodes
# (the command's `_ros2cli_<pid>`, the daemon's). generate_policy leaves hidden nodes (a leading `_`) out already;
# this test starts no other node of its own in the stack's domain.
IGNORED_NODE_PREFIX = "/_ros2cli"
SECURITY_LIBRARIES_MISSING = "doesn't have the security libraries"  # the PyPI Fast DDS, at participant creation

Grant = tuple[str, str, str]  # (topic | service, publish | subscribe | reply | request, absolute name)


# ------------------------------------------------------------------------------------------------ the policy
def resolve(name: str, ns: str, node: str) -> str:
    """A policy name made absolute as sros2's permissions.xsl does: ``/x`` stays, ``~/x`` is ``<ns>/<node>/x``,
    ``x`` is ``<ns>/x`` (generate_policy writes a root node's one-level names relative, ``~`` for its own)."""
    prefix = ns if ns.endswith("/") else ns + "/"
    if name.startswith("/"):
        return name
    if name.startswith("~"):
        return prefix + node + name[1:]
    return prefix + name


def read_policy(path: Path) -> dict[str, tuple[str, set[Grant]]]:
    """Node FQN → (its enclave, its grants with absolute names); ValueError for a node named twice."""
    profiles: dict[str, tuple[str, set[Grant]]] = {}
    for enclave in ET.parse(path).getroot().iter("enclave"):
        for profile in enclave.iter("profile"):
            ns, node = profile.get("ns"), profile.get("node")
            fqn = resolve(node, ns, node)
            if fqn in profiles:
                raise ValueError(f"{path.name}: {fqn} has two profiles")
            grants = set()
            for block in profile:
                qualifier = next(q for q in ("publish", "subscribe", "reply", "request") if block.get(q) == "ALLOW")
                for item in block:
                    grants.add((item.tag, qualifier, resolve(item.text.strip(), ns, node)))
            profiles[fqn] = (enclave.get("path"), grants)
    return profiles


def dds_topics(grants: set[Grant]) -> dict[str, set[str]]:
    """The DDS topic names a profile's grants become in permissions.xml (``rt/``, ``rq/…Request``, ``rr/…Reply``):
    "publish" and "subscribe" → names."""
    out: dict[str, set[str]] = {"publish": set(), "subscribe": set()}
    for kind, qualifier, name in grants:
        if kind == "topic":
            out[qualifier].add("rt" + name)
        else:  # a server reads requests and writes replies; a client the other way round
            writes, reads = ("rr" + name + "Reply", "rq" + name + "Request")
            if qualifier == "request":
                writes, reads = reads, writes
            out["publish"].add(writes)
            out["subscribe"].add(reads)
    return out


def test_policy_grants_each_node_its_enclave_and_rclpy_entities():
    """One enclave per node, ``/gsrmr/<node without gsrmr_>`` (the launch files' rule), for every node of the
    simulated stack and the link check; each profile holds rclpy's own topics and services."""
    from gsrmr_sim.sim_stack import sim_stack

    policy = read_policy(POLICY)
    stack_nodes = {spec.name for spec in sim_stack(model_path="/m.ply")} | {"gsrmr_link_echo", "gsrmr_link_probe"}
    assert set(policy) == {"/" + name for name in stack_nodes}
    for fqn, (enclave, grants) in policy.items():
        assert enclave == "/gsrmr/" + fqn.removeprefix("/gsrmr_"), fqn
        assert {("topic", "publish", t) for t in RCLPY_PUBLISHES} <= grants, fqn
        assert {("service", "reply", f"{fqn}/{s}") for s in RCLPY_SERVES} <= grants, fqn
    assert len({enclave for enclave, _ in policy.values()}) == len(policy)


def test_policy_names_resolve_as_sros2_does():
    assert resolve("uplink/pose_key", "/", "gsrmr_robot") == "/uplink/pose_key"
    assert resolve("uplink/pose_key", "/robot2", "gsrmr_robot") == "/robot2/uplink/pose_key"
    assert resolve("~/get_parameters", "/robot2/", "gsrmr_robot") == "/robot2/gsrmr_robot/get_parameters"
    assert resolve("/diagnostics", "/robot2", "gsrmr_robot") == "/diagnostics"
    assert dds_topics({("service", "request", "/link/stats")}) == {"publish": {"rq/link/statsRequest"},
                                                                   "subscribe": {"rr/link/statsReply"}}


# ---------------------------------------------------------------------------------------- ros2 security CLI
def sros2_missing() -> str | None:
    """Why the ``ros2 security`` verbs cannot run here (None when they can)."""
    for module in ("sros2", "lxml", "cryptography", "ros2cli"):
        if importlib.util.find_spec(module) is None:
            return f"{module} is not installed: no ROS 2 install and no ../shared/ros-security (tools/bootstrap.sh)"
    if ros2_command() is None:
        return "the ros2 command is not found"
    prefixes = [*os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep), sys.prefix]
    if not any(Path(p, "share/ament_index/resource_index/packages/sros2").is_file() for p in prefixes if p):
        return "sros2 has no ament index entry (AMENT_PREFIX_PATH, or this interpreter's prefix)"
    return None


def ros2_command() -> str | None:
    """``ros2`` beside this interpreter (a venv's bin, also when it is not activated), else on PATH."""
    beside = Path(sys.executable).with_name("ros2")
    return str(beside) if beside.is_file() else shutil.which("ros2")


SROS2_MISSING = sros2_missing()
needs_sros2 = pytest.mark.skipif(SROS2_MISSING is not None, reason=SROS2_MISSING or "")


def sros2_env(env: dict[str, str]) -> dict[str, str]:
    """``env`` with this interpreter's prefix on AMENT_PREFIX_PATH: the sros2 wheel indexes itself (and finds its
    schemas) under the venv's ``share/``, which no ``setup.bash`` adds (the README beside the sros2 wheel)."""
    paths = [p for p in env.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    return {**env, "AMENT_PREFIX_PATH": os.pathsep.join([*paths, sys.prefix] if sys.prefix not in paths else paths)}


def ros2(*args: str, env: dict[str, str], timeout_s: float = 60.0) -> subprocess.CompletedProcess:
    return subprocess.run([ros2_command() or "ros2", *args], capture_output=True, text=True, env=env,
                          timeout=timeout_s)


# ------------------------------------------------------------------------------------- the policy, live
READY = {  # what each node logs once its constructor created every entity (the link probe: once it has stats)
    "gsrmr_mock_limo": "true pose on", "gsrmr_limo_base": "LIMO base on", "gsrmr_mock_camera": "mock camera ready",
    "gsrmr_route_follower": "route follower:", "gsrmr_sim_channel": "simulated radio:",
    "gsrmr_robot": "robot uplink:", "gsrmr_server": "server: model", "gsrmr_sim_scorer": "scorer: model",
    "gsrmr_scheduler": "replan (start)", "gsrmr_link_echo": "echoing link/ping", "gsrmr_link_probe": "echo stats:"}


def _imports(module: str) -> bool:
    return importlib.util.find_spec(module) is not None


def _params(spec) -> dict:
    """The parameters a spec starts its node with: its files' ``/**`` values, then its overrides."""
    values: dict = {}
    for path in spec.param_files:
        values.update((yaml.safe_load(Path(path).read_text()) or {}).get("/**", {}).get("ros__parameters", {}))
    return {**values, **spec.params}


def _remapped(spec, name: str) -> str | None:
    return next((dst for src, dst in spec.remappings if src == name), None)


# Grants whose entity exists only in some runs. Each says whether it must be on the graph in a run of these specs
# here (True / False; None: it may or may not be), from the specs and what imports: the comparison is exact.
CONDITIONAL: dict[tuple[str, Grant], tuple[str, Callable[[dict], bool | None]]] = {
    ("/gsrmr_robot", ("topic", "publish", "/tf_static")):
        ("base_link → camera: only where tf2_ros imports", lambda specs: _imports("tf2_ros")),
    ("/gsrmr_robot", ("topic", "publish", "/tf")):
        ("map → odom: only where tf2_ros imports", lambda specs: _imports("tf2_ros")),
    ("/gsrmr_robot", ("topic", "subscribe", "/gsrmr/map_correction")):
        ("the server's corrections: localization server (config/robot.yaml's default)",
         lambda specs: _params(specs["gsrmr_robot"]).get("localization", "server") == "server"),
    ("/gsrmr_robot", ("topic", "subscribe", "/amcl_pose")):
        ("another localizer's pose: localization pose",
         lambda specs: _params(specs["gsrmr_robot"]).get("localization", "server") == "pose"),
    ("/gsrmr_robot", ("topic", "subscribe", "/tf")):
        ("another localizer's map → odom: localization tf (where tf2_msgs imports)",
         lambda specs: _params(specs["gsrmr_robot"]).get("localization", "server") == "tf"),
    ("/gsrmr_limo_base", ("topic", "publish", "/tf")):
        ("odom → base_link with publish_tf, where tf2_ros or tf2_msgs imports",
         lambda specs: bool(_params(specs["gsrmr_limo_base"]).get("publish_tf"))
         and (_imports("tf2_ros") or _imports("tf2_msgs"))),
    **{("/gsrmr_robot", ("topic", "subscribe", f"/camera/{leaf}")):
       ("the simulated camera: the robot's camera topic not remapped",
        lambda specs, leaf=leaf: _remapped(specs["gsrmr_robot"], f"camera/{leaf}") is None)
       for leaf in ("image_raw", "camera_info")},
    **{("/gsrmr_robot", ("topic", "subscribe", f"/camera/color/{leaf}")):
       ("robot.launch.py's camera remapping (its defaults)",
        lambda specs, leaf=leaf: _remapped(specs["gsrmr_robot"], f"camera/{leaf}") == f"/camera/color/{leaf}")
       for leaf in ("image_raw", "camera_info")},
    ("/gsrmr_route_follower", ("topic", "subscribe", "/mr/slot_info")):
        ("wait_for_server (sim.launch.py): held until the server composes its first slot",
         lambda specs: None if _params(specs["gsrmr_route_follower"]).get("wait_for_server") else False),
    ("/gsrmr_sim_scorer", ("topic", "subscribe", "/camera/image_raw")):
        ("the truth over DDS, not through truth_dir (two hosts)",
         lambda specs: not _params(specs["gsrmr_sim_scorer"]).get("truth_dir")),
    **{(fqn, ("service", "reply", f"{fqn}/get_type_description")):
       ("rclpy's type description service: Jazzy and later (Humble has none)",
        lambda specs: _imports("type_description_interfaces"))
       for fqn in read_policy(POLICY)},
}


def expected_graph(policy: dict[str, tuple[str, set[Grant]]], specs: dict) -> dict[str, tuple[str, set[Grant]]]:
    """The policy as the graph of ``specs`` must show it: grants whose entity is absent in this run dropped."""
    out = {fqn: (enclave, set(grants)) for fqn, (enclave, grants) in policy.items()}
    for (fqn, grant), (_why, present) in CONDITIONAL.items():
        assert grant in policy[fqn][1], f"conditional grant {grant} is not in {fqn}'s profile"
        if present(specs) is False:
            out[fqn][1].discard(grant)
    return out


def graph_differences(expected: dict, live: dict, undecided: set[tuple[str, Grant]]) -> list[str]:
    """What differs between the expected and the live profiles, one line each (empty: equal)."""
    diffs = []
    for fqn in sorted(set(expected) | set(live)):
        if fqn not in live:
            diffs.append(f"{fqn}: not on the graph")
            continue
        if fqn not in expected:
            diffs.append(f"{fqn}: on the graph, not in the policy")
            continue
        (enclave, want), (live_enclave, got) = expected[fqn], live[fqn]
        if enclave != live_enclave:
            diffs.append(f"{fqn}: enclave {live_enclave} on the graph, {enclave} in the policy")
        skip = {grant for node, grant in undecided if node == fqn}
        diffs += [f"{fqn}: granted, not created: {g}" for g in sorted(want - got - skip)]
        diffs += [f"{fqn}: created, not granted: {g}" for g in sorted(got - want - skip)]
    return diffs


def live_policy(env: dict[str, str], out: Path) -> dict[str, tuple[str, set[Grant]]]:
    """``ros2 security generate_policy`` of the graph in ``env``'s domain, read as :func:`read_policy` reads the
    policy (ros2cli's own nodes left out)."""
    out.unlink(missing_ok=True)  # generate_policy adds to an existing file
    done = ros2("security", "generate_policy", "--no-daemon", "--spin-time", "3", str(out), env=env)
    if done.returncode != 0:
        return {}
    return {fqn: p for fqn, p in read_policy(out).items() if not fqn.startswith(IGNORED_NODE_PREFIX)}


def _wait_ready(stack, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    waiting = dict(READY)
    while waiting and time.monotonic() < deadline:
        stack.processes.check()
        waiting = {name: text for name, text in waiting.items() if text not in stack.log(name)}
        time.sleep(0.5)
    assert not waiting, f"not ready in {timeout_s} s: {sorted(waiting)}"


@needs_sros2
@pytest.mark.ros
@pytest.mark.slow
def test_policy_is_the_live_graph(tmp_path):
    """Every node's grants equal what it creates: ``generate_policy`` of the running stack, each node started with
    ``--enclave <its policy enclave>``, is the policy node by node (enclave, topics published and subscribed,
    services served and called). Names are compared absolute (:func:`resolve`: generate_policy writes a root
    node's one-level names relative and its own services as ``~/…``; the rt/rq/rr DDS prefixes never appear in a
    policy). Grants of entities that exist only in other runs are listed in :data:`CONDITIONAL`; nodes of
    ros2cli itself are ignored (:data:`IGNORED_NODE_PREFIX`). Discovery on a loaded machine can report a node
    before all its endpoints: the graph is read again until it matches, within a bound."""
    from conftest import ros_env
    from support.stack_harness import Stack, make_point_model

    from gsrmr_sim.sim_stack import ProcessSpec, command_line

    policy = read_policy(POLICY)
    link_check = (ProcessSpec("gsrmr-link-echo", "gsrmr_link_echo"),
                  ProcessSpec("gsrmr-link-probe", "gsrmr_link_probe"))
    stack = Stack(tmp_path, make_point_model(tmp_path, n=1000), ros_env(), extra=link_check)
    expected = expected_graph(policy, stack.specs)
    undecided = {key for key, (_why, present) in CONDITIONAL.items() if present(stack.specs) is None}
    env = sros2_env(stack.env)
    live: dict = {}
    try:
        for name, spec in stack.specs.items():
            argv = command_line(spec, None, stack.processes.params_dir)
            assert "--ros-args" in argv, argv  # --enclave joins the spec's ROS arguments
            stack.processes.start(name, [*argv, "--enclave", policy["/" + name][0]],
                                  wait_for_path=stack.link if name == "gsrmr_mock_limo" else None)
        _wait_ready(stack, 90.0)
        deadline, readings = time.monotonic() + 40.0, 0
        while True:
            live = live_policy(env, tmp_path / "live_policy.xml")
            diffs, readings = graph_differences(expected, live, undecided), readings + 1
            if not diffs or time.monotonic() > deadline:
                break
    finally:
        stack.stop()
    assert not diffs, f"policy ≠ live graph ({readings} readings of the graph):\n" + "\n".join(diffs)


# ------------------------------------------------------------------------------------------- the keystore
@pytest.fixture(scope="module")
def keystore(tmp_path_factory) -> tuple[Path, dict[str, str]]:
    """A keystore with one enclave per policy enclave and its permissions, made by the ``ros2 security`` verbs
    in a ROS domain of its own; (keystore, the environment it was made in)."""
    from conftest import ros_env

    env = sros2_env(ros_env())
    ks = tmp_path_factory.mktemp("sros2") / "keystore"

    def run(*commands: tuple[str, ...]) -> list[tuple[tuple[str, ...], subprocess.CompletedProcess]]:
        return [(args, ros2("security", *args, env=env)) for args in commands]

    done = run(("create_keystore", str(ks)))
    if done[0][1].returncode == 0:
        # each enclave's two commands in turn, the enclaves a few at once: each writes only its own folder (and
        # sros2 makes the shared parents with exist_ok); one after the other, the 22 CLI processes took 15 s
        with ThreadPoolExecutor(max_workers=max(2, os.cpu_count() or 1)) as pool:
            for results in pool.map(lambda enclave: run(("create_enclave", str(ks), enclave),
                                                        ("create_permission", str(ks), enclave, str(POLICY))),
                                    [enclave for enclave, _grants in read_policy(POLICY).values()]):
                done += results
    for args, result in done:
        assert result.returncode == 0, f"ros2 security {' '.join(args)}:\n{result.stdout}{result.stderr}"
    return ks, env


@needs_sros2
def test_keystore_has_every_enclave_with_its_permissions(keystore):
    """``create_keystore``, ``create_enclave`` and ``create_permission`` from the policy: the CA, the governance,
    and per enclave its certificate, key and signed permissions, whose DDS topics are exactly the policy's grants
    (the rt/rq/rr names of :func:`dds_topics`) in the domain the keystore was made for."""
    ks, env = keystore
    for path in ("public/ca.cert.pem", "public/identity_ca.cert.pem", "public/permissions_ca.cert.pem",
                 "private/ca.key.pem", "enclaves/governance.xml", "enclaves/governance.p7s"):
        assert (ks / path).is_file(), path
    governance = ET.parse(ks / "enclaves/governance.xml").getroot()
    assert {d.text for d in governance.iter("id")} == {env["ROS_DOMAIN_ID"]}  # signed for one domain
    policy = read_policy(POLICY)
    for _fqn, (enclave, grants) in policy.items():
        folder = ks / "enclaves" / enclave.lstrip("/")
        for name in ("cert.pem", "key.pem", "identity_ca.cert.pem", "permissions_ca.cert.pem", "governance.p7s",
                     "permissions.xml", "permissions.p7s"):
            assert (folder / name).is_file(), f"{enclave}: {name}"
        grant = ET.parse(folder / "permissions.xml").getroot().find("permissions/grant")
        assert grant.findtext("subject_name") == f"CN={enclave}"
        rules = grant.findall("allow_rule")
        assert {d.text for rule in rules for d in rule.iter("id")} == {env["ROS_DOMAIN_ID"]}
        allowed = {way: {t.text for rule in rules for t in rule.findall(f"{way}/topics/topic")}
                   - {"ros_discovery_info"} for way in ("publish", "subscribe")}
        assert allowed == dds_topics(grants), enclave
    listed = ros2("security", "list_enclaves", str(ks), env=env)
    assert set(listed.stdout.split()) == {enclave for enclave, _ in policy.values()}, listed.stdout + listed.stderr


@needs_sros2
@pytest.mark.ros
def test_keystore_is_what_rcl_loads(keystore, tmp_path):
    """A node started enforced with its enclave of this keystore gets past rcl's keystore checks (every file it
    needs is there): with the PyPI Fast DDS it then stops at the missing security plugins; on a ROS install with
    them it starts (its ready line) and runs."""
    from gsrmr_sim.sim_stack import executable_path

    ks, env = keystore
    secured = {**env, "ROS_SECURITY_KEYSTORE": str(ks), "ROS_SECURITY_ENABLE": "true",
               "ROS_SECURITY_STRATEGY": "Enforce"}
    log = tmp_path / "link_echo.log"
    with log.open("w") as out:
        proc = subprocess.Popen([str(executable_path("gsrmr-link-echo")), "--ros-args", "--enclave",
                                 "/gsrmr/link_echo"], env=secured, stdout=out, stderr=subprocess.STDOUT,
                                start_new_session=True)
    try:
        deadline = time.monotonic() + 30.0
        while proc.poll() is None and READY["gsrmr_link_echo"] not in log.read_text() and time.monotonic() < deadline:
            time.sleep(0.2)
    finally:
        running = proc.poll() is None
        if running:
            proc.send_signal(signal.SIGINT)
            proc.wait(timeout=15)
    said = log.read_text()
    assert "SECURITY ERROR" not in said, said[-2000:]
    if SECURITY_LIBRARIES_MISSING in said:
        assert proc.returncode != 0, said[-2000:]
    else:
        assert running and READY["gsrmr_link_echo"] in said, said[-2000:]


@needs_sros2
@pytest.mark.parametrize(("breakage", "reason"), [
    (lambda text: text[: len(text) // 2], "XMLSyntaxError"),  # not XML at all
    (lambda text: text.replace("<topic>link/ping</topic>", "<parameter>link/ping</parameter>", 1),
     "Element 'parameter': This element is not expected"),  # XML that sros2's schema refuses
], ids=["truncated", "schema"])
def test_malformed_policy_is_refused(keystore, tmp_path, breakage, reason):
    """``create_permission`` validates the whole policy against sros2's schema: a broken copy is refused with a
    non-zero exit and the reason, and the enclave's signed permissions stay as they were."""
    ks, env = keystore
    broken = tmp_path / "policy.xml"
    broken.write_text(breakage(POLICY.read_text()))
    signed = ks / "enclaves/gsrmr/robot/permissions.p7s"
    before = signed.read_bytes()
    done = ros2("security", "create_permission", str(ks), "/gsrmr/robot", str(broken), env=env)
    assert done.returncode != 0 and reason in done.stderr, done.stderr[-2000:]
    assert signed.read_bytes() == before


# ----------------------------------------------------------------------------------- the launch files' enclaves
def _launch_nodes(path: Path, monkeypatch, **arguments: str) -> tuple[list[dict], object]:
    """The keyword arguments of every ``Node`` a launch file makes, its arguments at their defaults but for
    ``arguments`` (a required one without a value gets a placeholder); and the launch context."""
    import launch
    from launch.actions import DeclareLaunchArgument, OpaqueFunction
    from launch.utilities import perform_substitutions

    made: list[dict] = []
    # gsrmr_sim.launch_nodes first: patching it imports it, and it binds launch_ros's Node at import — were
    # launch_ros's already patched then, undo() would restore the stand-in there for the rest of the session
    monkeypatch.setattr("gsrmr_sim.launch_nodes.Node", lambda **kw: made.append(kw) or kw)
    monkeypatch.setattr("launch_ros.actions.Node", lambda **kw: made.append(kw) or kw)
    monkeypatch.setattr("ament_index_python.packages.get_package_share_directory", lambda _pkg: str(REPO))
    loader = importlib.util.spec_from_file_location(f"launch_{path.name.split('.')[0]}", path)
    module = importlib.util.module_from_spec(loader)
    loader.loader.exec_module(module)
    context = launch.LaunchContext()
    entities = module.generate_launch_description().entities
    for arg in (e for e in entities if isinstance(e, DeclareLaunchArgument)):
        default = perform_substitutions(context, arg.default_value) if arg.default_value else "/placeholder"
        context.launch_configurations[arg.name] = arguments.get(arg.name, default)
    for action in (e for e in entities if isinstance(e, OpaqueFunction)):
        action.execute(context)
    return made, context


LAUNCH_FILES = ["robot.launch.py", "server.launch.py", "sim.launch.py"]


@pytest.mark.parametrize("name", LAUNCH_FILES)
def test_launch_keystore_runs_every_node_in_its_policy_enclave(name, monkeypatch, tmp_path):
    """``keystore:=KS`` gives each Node ``--enclave`` with its enclave in config/security/policy.xml and the SROS2
    environment (KS absolute, security on, Enforce); without it, neither. The arguments are real ``launch_ros``
    Node arguments. robot.launch.py's camera remapping (its defaults) is what the policy grants the robot."""
    pytest.importorskip("launch_ros", reason="no launch_ros: no ROS 2 install and no ../shared/ros-tooling")
    from launch_ros.actions import Node

    enclaves = {fqn.lstrip("/"): enclave for fqn, (enclave, _grants) in read_policy(POLICY).items()}
    secured, context = _launch_nodes(REPO / "launch" / name, monkeypatch, keystore=str(tmp_path / "ks"))
    plain, _context = _launch_nodes(REPO / "launch" / name, monkeypatch)
    assert secured and len(plain) == len(secured)
    for node in secured:
        assert node["ros_arguments"] == ["--enclave", enclaves[node["name"]]], node["name"]
        assert node["additional_env"] == {"ROS_SECURITY_KEYSTORE": str(tmp_path / "ks"), "ROS_SECURITY_ENABLE": "true",
                                          "ROS_SECURITY_STRATEGY": "Enforce"}, node["name"]
    for node in plain:
        assert "ros_arguments" not in node and "additional_env" not in node, node["name"]
    monkeypatch.undo()
    Node(**secured[0])  # launch_ros takes them (an unknown keyword is a TypeError)
    if name == "robot.launch.py":
        robot = next(node for node in secured if node["name"] == "gsrmr_robot")
        targets = {dst.perform(context) for src, dst in robot["remappings"] if src.startswith("camera/")}
        granted = {g for (fqn, g), _ in CONDITIONAL.items() if fqn == "/gsrmr_robot" and "/color/" in g[2]}
        assert {("topic", "subscribe", t) for t in targets} == granted


# ------------------------------------------------------------------------------------------- fail-closed start
@pytest.fixture(scope="module")
def refused_starts(tmp_path_factory):
    """Every deployment node started enforced (ROS_SECURITY_ENABLE=true, ROS_SECURITY_STRATEGY=Enforce) twice: with
    no keystore at all, and with an empty keystore and its enclave (``--enclave /gsrmr/<node>``, as the launch
    files pass it), while an unsecured rclpy node watches the graph of their domain. A node that needs no
    security (the link echo, unsecured) runs beside them: the watcher sees a node that does start.
    Yields {(executable, case): (exit code or None, its output)}, the node names seen on the graph, and the
    keystore path."""
    from conftest import ros_env
    from support.stack_harness import ros_client

    from gsrmr_sim.sim_stack import executable_path

    tmp = tmp_path_factory.mktemp("fail_closed")
    empty = tmp / "empty_keystore"
    empty.mkdir()
    env = ros_env()
    enforced = {**{k: v for k, v in env.items() if not k.startswith("ROS_SECURITY_")},
                "ROS_SECURITY_ENABLE": "true", "ROS_SECURITY_STRATEGY": "Enforce"}
    procs: dict[tuple[str, str], tuple[subprocess.Popen, Path]] = {}

    def start(key: tuple[str, str], argv: list[str], proc_env: dict[str, str]) -> None:
        log = tmp / f"{key[0]}-{key[1]}.log"
        with log.open("w") as out:
            procs[key] = (subprocess.Popen(argv, env=proc_env, stdout=out, stderr=subprocess.STDOUT, cwd=tmp,
                                           start_new_session=True), log)

    seen: set[str] = set()
    with ros_client(env, "security_graph_watch") as (node, ex):
        start(("gsrmr-link-echo", "unsecured"), [str(executable_path("gsrmr-link-echo"))], env)
        for exe, name in DEPLOYMENT.items():
            enclave = ["--ros-args", "--enclave", "/gsrmr/" + name.removeprefix("gsrmr_")]
            start((exe, "no keystore"), [str(executable_path(exe)), *enclave], enforced)
            start((exe, "empty keystore"), [str(executable_path(exe)), *enclave],
                  {**enforced, "ROS_SECURITY_KEYSTORE": str(empty)})
        refused = [p for key, (p, _log) in procs.items() if key[1] != "unsecured"]
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline and (any(p.poll() is None for p in refused)
                                               or "/gsrmr_link_echo" not in seen):
            ex.spin_once(timeout_sec=0.1)
            seen |= {ns.rstrip("/") + "/" + n for n, ns in node.get_node_names_and_namespaces()}
    results = {}
    for key, (proc, log) in procs.items():
        code = proc.poll()  # None: still running (the link echo is meant to)
        if code is None:
            os.killpg(proc.pid, signal.SIGINT if key[1] == "unsecured" else signal.SIGKILL)
            proc.wait(timeout=15)
        results[key] = (code, log.read_text(errors="replace"))
    return results, seen, empty


@pytest.mark.ros
def test_enforced_without_enclave_never_joins_the_graph(refused_starts):
    """With security enforced and no enclave to load, no deployment node appears on the graph (the unsecured
    link echo beside them does: the watcher sees nodes), and every one has ended within 60 s."""
    results, seen, _empty = refused_starts
    assert "/gsrmr_link_echo" in seen, f"the watcher saw no node at all: {seen}"
    assert not {"/" + name for name in DEPLOYMENT.values()} & seen, seen
    running = [key for key, (code, _said) in results.items() if code is None and key[1] != "unsecured"]
    assert not running, f"still running after 60 s: {running}"


@pytest.mark.ros
def test_enforced_without_enclave_exits_nonzero_with_the_reason(refused_starts):
    """Each refused start says why and exits non-zero. rcl looks for the enclave before the DDS layer loads any
    security plugin, so the reason is rcl's on these wheels and on a ROS install alike: with an empty keystore
    "SECURITY ERROR: directory '<keystore>/enclaves/gsrmr/<node>' does not exist"; with no keystore rcl fails its
    init (its message there is "error not set"). The PyPI Fast DDS's own reason, missing security libraries,
    comes only with a complete keystore (test_keystore_is_what_rcl_loads) and is accepted here too."""
    results, _seen, empty = refused_starts
    for (exe, case), (code, said) in results.items():
        if case == "unsecured":
            continue
        assert code not in (None, 0), f"{exe} ({case}): exit code {code}\n{said[-2000:]}"
        enclave_dir = f"directory '{empty}/enclaves/gsrmr/{DEPLOYMENT[exe].removeprefix('gsrmr_')}' does not exist"
        reasons = ([enclave_dir] if case == "empty keystore" else ["failed to initialize rcl"]) \
            + [SECURITY_LIBRARIES_MISSING]
        assert any(r in said for r in reasons), f"{exe} ({case}): none of {reasons} in\n{said[-2000:]}"
