"""What the README shows against what the code has: its command lines parse with the real `tacf` parser, and
every optional dependency the package declares is one the README gives a reason for."""
from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from tacf.cli import build_parser

ROOT = Path(__file__).resolve().parent.parent
README = (ROOT / "README.md").read_text()


def _readme_command_lines() -> list[str]:
    """The `tacf ...` lines of the README's bash blocks, continuation lines joined, comments and `&` cut."""
    lines = []
    for block in re.findall(r"```bash\n(.*?)```", README, re.S):
        for line in re.sub(r"\\\n\s*", " ", block).splitlines():
            line = line.split(" #")[0].strip().rstrip("&").strip()
            if line.startswith("tacf "):
                lines.append(line)
    return lines


@pytest.mark.parametrize("line", _readme_command_lines())
def test_readme_command_lines_parse(line):
    build_parser().parse_args(shlex.split(line)[1:])      # a misspelt subcommand or flag exits with status 2


def test_every_extra_is_named_in_the_readme():
    """A `pyinstrument` extra (`profile`) outlived the README text that used it, and nothing imported it."""
    table = (ROOT / "pyproject.toml").read_text().split("[project.optional-dependencies]")[1].split("\n[")[0]
    extras = re.findall(r"^([A-Za-z0-9_-]+)\s*=", table, re.M)      # tomllib is Python 3.11+
    assert extras and [extra for extra in extras if f"[{extra}]" not in README] == []


def test_every_lower_bound_is_the_version_the_floor_tests_pin():
    """.ci/run tests the oldest versions pyproject.toml allows (.ci/floors.txt): a bound raised or lowered without
    its pin would claim a version nobody tested. The pin may carry more parts (5.0 -> 5.0.0.93)."""
    project = (ROOT / "pyproject.toml").read_text().split("\n[project]")[1]       # not the build system's
    bounds = dict(re.findall(r'"([A-Za-z0-9_.-]+)>=([0-9.]+)', project))
    pins = dict(re.findall(r"^([A-Za-z0-9_.-]+)==([0-9.]+)$", (ROOT / ".ci" / "floors.txt").read_text(), re.M))
    assert bounds and set(bounds) == set(pins)
    assert [name for name, bound in bounds.items()
            if pins.get(name, "").split(".")[:len(bound.split("."))] != bound.split(".")] == []


def test_the_readme_gives_every_floor_of_the_package_and_its_extras():
    """The README gives each lower bound of the package and of its extras at its version (the floors' list of
    "Dependencies", or a pin such as foxglove-sdk's): the list written when the bounds were raised left out the
    mavlink extra's pyserial 3.5. The test extra's bounds are .ci/floors.txt's to list."""
    project = (ROOT / "pyproject.toml").read_text().split("\n[project]")[1]
    extras = project.split("[project.optional-dependencies]")[1].split("\n[")[0]
    declared = project.split("\ndependencies = [")[1].split("\n]")[0] + re.sub(r"^test = \[.*?^\]", "", extras,
                                                                                   flags=re.M | re.S)
    bounds = re.findall(r'"([A-Za-z0-9_.-]+)>=([0-9.]+)', declared)
    shown_as = {"opencv-contrib-python-headless": "OpenCV"}
    assert bounds and [f"{name}>={bound}" for name, bound in bounds if not re.search(
        rf"{re.escape(shown_as.get(name, name))}(?:\s+|>=){re.escape(bound)}(?![0-9]|\.[0-9])", README)] == []


def test_the_docker_image_gets_the_files_the_package_metadata_names():
    """pyproject's readme and license-files must reach `pip install .` in docker/Dockerfile: LICENSE was left out
    of the build context, so the image's package carried no licence and setuptools warned that the build will
    fail from 2027-02-18 ("Pattern 'LICENSE' did not match any files")."""
    pyproject = (ROOT / "pyproject.toml").read_text()
    named = re.findall(r'^readme = "([^"]+)"', pyproject, re.M)
    named += re.findall(r'"([^"]+)"', re.search(r"^license-files = \[(.*)\]", pyproject, re.M).group(1))
    let_in = (ROOT / ".dockerignore").read_text().split()
    copied = " ".join(re.findall(r"^COPY (.*)$", (ROOT / "docker" / "Dockerfile").read_text(), re.M)).split()
    assert named and [name for name in named if f"!{name}" not in let_in or name not in copied] == []


def test_the_docker_build_fetches_nothing_but_its_base_image():
    """BASE lets a machine that cannot reach Docker Hub build on a mirror's copy of python:3.11-slim, but a
    `# syntax=docker/dockerfile:1` line makes BuildKit (Docker's builder since Engine 23) fetch that frontend image
    from Docker Hub before it reads anything else, so such a build failed at its first line. The builder's own
    frontend reads every instruction the Dockerfile uses."""
    dockerfile = (ROOT / "docker" / "Dockerfile").read_text()
    assert not re.search(r"^#\s*syntax\s*=", dockerfile, re.M | re.I)
