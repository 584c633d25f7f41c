"""Every command that docker-compose.yml and the Dockerfile run exists here, with the options they pass.

Each command runs with `--help` appended: the executable must exist and the parser must accept every
option it is given (an unknown option fails before `--help` is handled), so a renamed subcommand
or a dropped flag fails this test.
"""

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from conftest import REPO


def _compose_commands() -> list[list[str]]:
    compose = yaml.safe_load((REPO / "docker-compose.yml").read_text())
    commands = []
    for name, service in compose["services"].items():
        command = service.get("command")
        if command is None:
            continue
        assert isinstance(command, list), f"{name}: use the exec (list) form, got {command!r}"
        commands.append(command)
    return commands


def _dockerfile_commands() -> list[list[str]]:
    text = (REPO / "Dockerfile").read_text()
    commands = []
    for keyword in ("CMD", "ENTRYPOINT"):
        for match in re.finditer(rf"^{keyword}\s+(\[.*\])\s*$", text, re.MULTILINE):
            command = json.loads(match.group(1))
            if command:
                commands.append(command)
    return commands


def test_the_deploy_files_name_the_commands_we_expect():
    programs = {c[0] for c in _compose_commands()} | {c[0] for c in _dockerfile_commands()}
    assert programs == {"prefect", "capvector", "dask"}, programs
    assert any(c[:3] == ["prefect", "server", "start"] for c in _compose_commands())
    assert any(c[:2] == ["capvector", "schedule"] for c in _compose_commands())
    assert any(c[:2] == ["dask", "scheduler"] for c in _compose_commands())  # the `cluster` profile
    assert any(c[:2] == ["dask", "worker"] for c in _compose_commands())


def _executable(program: str) -> str:
    found = Path(sys.executable).parent / program
    if found.exists():
        return str(found)
    which = shutil.which(program)
    assert which, f"{program} is not installed"
    return which


@pytest.mark.parametrize(
    "command", _compose_commands() + _dockerfile_commands(), ids=lambda c: " ".join(c)[:60]
)
def test_command_exists_with_its_options(command, tmp_path):
    env = {**os.environ, "CAPVECTOR_HOME": str(tmp_path / "home"), "PREFECT_HOME": str(tmp_path / "prefect")}
    env.pop("PREFECT_API_URL", None)
    proc = subprocess.run(
        [_executable(command[0]), *command[1:], "--help"],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, (
        f"{' '.join(command)} --help: {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    )
    assert "Usage" in proc.stdout, proc.stdout
