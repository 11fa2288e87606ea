"""docker-compose.yml, read as Compose reads it (no Docker engine runs on the test machine): the
four services, their health checks and volumes, settings that exist, commands the CLI accepts."""

from __future__ import annotations

import shutil
import subprocess
from urllib.parse import urlsplit

import pytest
import yaml

from pwlreg.service.cli import build_parser
from pwlreg.service.settings import Settings
from tests.service.helpers import REPO

COMPOSE = REPO / "docker-compose.yml"


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load(COMPOSE.read_text())


def test_the_services_and_their_health_checks(compose: dict) -> None:
    services = compose["services"]
    assert set(services) == {"api", "worker", "redis", "postgres"}
    for name, service in services.items():
        test = service["healthcheck"]["test"]
        assert test[0] in ("CMD", "CMD-SHELL") and len(test) > 1, name
        for other, condition in service.get("depends_on", {}).items():
            assert condition["condition"] == "service_healthy", (name, other)
            assert "healthcheck" in services[other]
    # The worker scales: no fixed name, no host port, replicas of its own.
    worker = services["worker"]
    assert "container_name" not in worker and "ports" not in worker
    assert worker["deploy"]["replicas"] >= 2
    assert "pwlreg-1@$$HOSTNAME" in worker["healthcheck"]["test"][1]  # pid 1: `pwlreg worker`


def test_api_and_workers_share_their_settings_and_files(compose: dict) -> None:
    services = compose["services"]
    fields = {f"PWLREG_{name.upper()}" for name in Settings.model_fields}
    api, worker = services["api"], services["worker"]
    for service in (api, worker):
        env = service["environment"]
        assert set(env) <= fields, set(env) - fields  # no misspelt setting
        assert env["PWLREG_QUEUE"] == "celery"
        assert urlsplit(env["PWLREG_BROKER_URL"]).hostname == "redis"
        database = urlsplit(env["PWLREG_DATABASE_URL"])
        assert database.scheme == "postgresql+psycopg" and database.hostname == "postgres"
        mounts = dict(v.split(":")[::-1] for v in service["volumes"])
        assert mounts[env["PWLREG_DATA_DIR"]] == "jobs"
    assert api["environment"] == {k: v for k, v in worker["environment"].items()
                                  if k != "PWLREG_WORKER_THREADS"}
    named = set(compose["volumes"])
    for service in services.values():
        for volume in service.get("volumes", []):
            assert volume.split(":")[0] in named
    assert services["postgres"]["environment"]["POSTGRES_DB"] == "pwlreg"


def test_the_commands_are_pwlreg_commands(compose: dict) -> None:
    parser = build_parser()
    for name, command in (("api", "serve"), ("worker", "worker")):
        argv = compose["services"][name]["command"]
        assert argv[0] == "pwlreg"
        assert parser.parse_args(argv[1:]).command == command
    # The image has the scale-out extra (Celery, the PostgreSQL driver).
    assert 'pip install ".[scaleout]"' in (REPO / "Dockerfile").read_text()


def _compose_command() -> list[str] | None:
    """``docker compose`` (the plugin) or ``docker-compose`` (the standalone program), if
    either is installed; neither needs a running engine to check a file."""
    docker = shutil.which("docker")
    if docker and subprocess.run([docker, "compose", "version"], capture_output=True,
                                 check=False).returncode == 0:
        return [docker, "compose"]
    standalone = shutil.which("docker-compose")
    return [standalone] if standalone else None


def test_docker_compose_accepts_the_file() -> None:
    command = _compose_command()
    if command is None:
        pytest.skip("neither `docker compose` nor `docker-compose` is installed (the file is "
                    "checked above)")
    result = subprocess.run([*command, "-f", str(COMPOSE), "config", "--quiet"],
                            capture_output=True, text=True, check=False)
    assert result.returncode == 0, result.stderr
