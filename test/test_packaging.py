"""package.xml and requirements.txt declare every third-party module the package imports.

A ROS user installs the package's dependencies with rosdep, which reads only package.xml; this project's
own machines install requirements.txt with pip. An import that one of them misses works on the machine
where it was written and fails with ModuleNotFoundError on the other, so the imports are read from the
source (with ``ast``, without importing anything) and held against both files.

``colcon build`` installs only the data files setup.py lists, and the installed package reads ``config/``
from its share directory: a file setup.py leaves out exists in the checkout and is missing where the package
is installed, so every file under ``config/`` is held against setup.py's ``data_files``.
"""

from __future__ import annotations

import ast
import contextlib
import re
import runpy
import sys
import xml.etree.ElementTree as ET
from functools import cache
from importlib.metadata import packages_distributions
from pathlib import Path
from unittest import mock

from test.conftest import ROOT

PACKAGE = "hybrid_kinematics_ros"
# rosdep keys whose PyPI name is not the key without its "python3-" prefix (ros/rosdistro rosdep/python.yaml).
ROSDEP_TO_PYPI = {"python3-yaml": "PyYAML"}
# Import names of distributions that may not be installed where the test runs, for the fallback below.
IMPORT_TO_PYPI = {"yaml": "PyYAML"}


def normalize(name: str) -> str:
    """A distribution name as pip compares them (PEP 503): case and runs of -_. do not matter."""
    return re.sub(r"[-_.]+", "-", name).lower()


def top_level_imports(source_root: Path) -> dict[str, set[str]]:
    """Top-level module name -> the files (relative to the repository) that import it, relative imports left out.

    Imports inside functions count too: a lazily imported module (matplotlib, ik_geo) is still a dependency.
    """
    found: dict[str, set[str]] = {}
    for path in sorted(source_root.rglob("*.py")):
        tree = ast.parse(path.read_text(), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                found.setdefault(name.split(".")[0], set()).add(path.relative_to(source_root.parent).as_posix())
    return found


def package_xml_dependencies(package_xml: Path) -> tuple[set[str], set[str]]:
    """(ROS package names, PyPI names) that package.xml declares.

    Python dependencies are the ``python3-*`` rosdep keys of any ``*depend`` tag, translated to their PyPI
    names, and the ``<export><pip_depend>`` entries (PyPI names without a rosdep key); every other
    dependency is a ROS package, whose import name is its package name.
    """
    root = ET.parse(package_xml).getroot()
    ros: set[str] = set()
    pypi: set[str] = set()
    for element in root:
        if not element.tag.endswith("depend") or not element.text:
            continue
        key = element.text.strip()
        if key.startswith("python3-"):
            pypi.add(ROSDEP_TO_PYPI.get(key, key.removeprefix("python3-")))
        else:
            ros.add(key)
    pypi.update(e.text.strip() for e in root.iterfind("export/pip_depend") if e.text)
    return ros, pypi


def requirement_names(requirements: Path) -> set[str]:
    """The distribution names in a pip requirements file (pins, comments and options stripped)."""
    names = set()
    for line in requirements.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line and not line.startswith("-"):
            names.add(re.split(r"[\s\[<>=!~;@]", line, maxsplit=1)[0])
    return names


@cache
def installed_distributions() -> dict[str, list[str]]:
    """Import name -> distribution names, from the installed packages' metadata (read once: about 0.5 s)."""
    return packages_distributions()


def distributions_of(module: str) -> list[str]:
    """The distributions that may provide ``module``: the installed ones, else its likely PyPI name.

    The fallback keeps the check meaningful for a module that is not installed here: ``pandas`` is then
    looked up as the distribution ``pandas`` and, being declared nowhere, reported.
    """
    return installed_distributions().get(module) or [IMPORT_TO_PYPI.get(module, module)]


def undeclared_imports(source_root: Path, package_xml: Path, requirements: Path) -> list[str]:
    """One line per third-party import that package.xml or requirements.txt does not declare."""
    ros, xml_pypi = package_xml_dependencies(package_xml)
    xml_pypi = {normalize(n) for n in xml_pypi}
    pinned = {normalize(n) for n in requirement_names(requirements)}
    problems = []
    for module, files in sorted(top_level_imports(source_root).items()):
        if module in sys.stdlib_module_names or module == source_root.name or module in ros:
            continue
        dists = sorted({normalize(d) for d in distributions_of(module)})
        missing = []
        if not set(dists) & xml_pypi:
            missing.append(
                f"not in {package_xml.name} (a ROS package: <exec_depend>{module}</exec_depend>; else its "
                f"python3-* rosdep key, or <export><pip_depend>{dists[0]}</pip_depend> if it has none)"
            )
        if not set(dists) & pinned:
            missing.append(f"not pinned in {requirements.name}")
        if missing:
            where = ", ".join(sorted(files)[:3]) + (", ..." if len(files) > 3 else "")
            problems.append(f"{module} (imported in {where}): " + "; ".join(missing))
    return problems


def unpinned_python_dependencies(package_xml: Path, requirements: Path) -> list[str]:
    """package.xml's Python dependencies that requirements.txt does not pin."""
    _, xml_pypi = package_xml_dependencies(package_xml)
    pinned = {normalize(n) for n in requirement_names(requirements)}
    return sorted(name for name in xml_pypi if normalize(name) not in pinned)


def test_every_third_party_import_is_declared() -> None:
    problems = undeclared_imports(ROOT / PACKAGE, ROOT / "package.xml", ROOT / "requirements.txt")
    assert not problems, "undeclared dependencies:\n" + "\n".join(problems)


def test_package_xml_python_dependencies_are_pinned() -> None:
    missing = unpinned_python_dependencies(ROOT / "package.xml", ROOT / "requirements.txt")
    assert not missing, f"package.xml declares Python dependencies that requirements.txt does not pin: {missing}"


def test_the_check_reports_an_undeclared_import(tmp_path: Path) -> None:
    """The checker itself: a new ``import pandas`` fails, declared and ROS imports pass."""
    source = tmp_path / PACKAGE
    (source / "sub").mkdir(parents=True)
    (source / "sub" / "mod.py").write_text(
        "import os\nimport numpy as np\nimport rclpy\nfrom . import sibling\n"
        f"from {PACKAGE}.sub import other\n\ndef lazy():\n    import pandas\n    from yaml import safe_load\n"
    )
    (tmp_path / "package.xml").write_text(
        "<package format='3'><exec_depend>rclpy</exec_depend><exec_depend>python3-numpy</exec_depend>"
        "<exec_depend>python3-yaml</exec_depend><export><pip_depend>rosbags</pip_depend></export></package>"
    )
    (tmp_path / "requirements.txt").write_text("numpy==2.4.6  # arrays\npyyaml==6.0.3\n-c constraints.txt\n")

    problems = undeclared_imports(source, tmp_path / "package.xml", tmp_path / "requirements.txt")

    assert len(problems) == 1 and problems[0].startswith(f"pandas (imported in {PACKAGE}/sub/mod.py): not in")
    assert problems[0].endswith("not pinned in requirements.txt")
    assert unpinned_python_dependencies(tmp_path / "package.xml", tmp_path / "requirements.txt") == ["rosbags"]


def data_files_of(setup_py: Path) -> dict[str, str]:
    """Each data file setup.py installs (relative to its folder) -> the folder it goes to, from running setup.py
    with ``setuptools.setup`` replaced by a recorder."""
    captured: dict = {}
    with mock.patch("setuptools.setup", lambda **kwargs: captured.update(kwargs)), contextlib.chdir(setup_py.parent):
        runpy.run_path(str(setup_py))
    return {Path(f).as_posix(): folder for folder, files in captured.get("data_files", []) for f in files}


def uninstalled_config_files(root: Path) -> list[str]:
    """The files under ``config/`` that setup.py does not install into the same folder of the share directory."""
    installed = data_files_of(root / "setup.py")
    problems = []
    for path in sorted((root / "config").rglob("*")):
        if not path.is_file():
            continue
        relative = path.relative_to(root).as_posix()
        expected = f"share/{PACKAGE}/{path.parent.relative_to(root).as_posix()}"
        if installed.get(relative) != expected:
            problems.append(f"{relative}: installed to {installed.get(relative)}, expected {expected}")
    return problems


def test_every_config_file_is_installed() -> None:
    problems = uninstalled_config_files(ROOT)
    assert not problems, "setup.py's data_files miss config files:\n" + "\n".join(problems)


def test_the_check_reports_an_uninstalled_config_file(tmp_path: Path) -> None:
    (tmp_path / "config" / "extra").mkdir(parents=True)
    (tmp_path / "config" / "robot.yaml").write_text("name: r\n")
    (tmp_path / "config" / "extra" / "more.yaml").write_text("a: 1\n")
    (tmp_path / "setup.py").write_text(
        "from glob import glob\nfrom setuptools import setup\n"
        f"setup(data_files=[('share/{PACKAGE}/config', glob('config/*.yaml'))])\n"
    )
    assert uninstalled_config_files(tmp_path) == [
        f"config/extra/more.yaml: installed to None, expected share/{PACKAGE}/config/extra"
    ]
