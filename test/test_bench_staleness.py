"""bench/staleness.py on a real git history: a section goes stale when, and only when, a commit after the one
it ran at touches a file it measures."""

from __future__ import annotations

import subprocess

import pytest

from bench.staleness import mark, measured_paths, sections


def commit(root, message: str) -> str:
    subprocess.run(["git", "add", "-A"], cwd=root, check=True)
    subprocess.run(["git", "commit", "-qm", message], cwd=root, check=True)
    return subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True).stdout.strip()


def section(key: str, commit_line: str) -> str:
    return (
        f"<!-- section:{key} -->\n## {key}\n\nCommand: `python -m bench.bench_x`  \nMachine: here  \n"
        f"Run: 2026-11-25 12:00 UTC{commit_line}\n\n| a |\n|---|\n| 1 |\n<!-- end:{key} -->\n"
    )


@pytest.fixture
def repo(tmp_path, monkeypatch):
    for var, value in (("NAME", "t"), ("EMAIL", "t@example.com")):
        monkeypatch.setenv(f"GIT_AUTHOR_{var}", value)
        monkeypatch.setenv(f"GIT_COMMITTER_{var}", value)
    files = {
        "hybrid_kinematics_ros/__init__.py": "",
        "hybrid_kinematics_ros/kinematics/__init__.py": "",
        "hybrid_kinematics_ros/kinematics/fk.py": "from .se3 import compose\n",
        "hybrid_kinematics_ros/kinematics/se3.py": "def compose(): ...\n",
        "hybrid_kinematics_ros/ik/__init__.py": "",
        "hybrid_kinematics_ros/ik/solver.py": "def solve(): ...\n",
        "bench/__init__.py": "",
        "bench/bench_x.py": "def run():\n    from hybrid_kinematics_ros.kinematics.fk import compose\n",
        "config/robot.yaml": "joints: 6\n",
    }
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    subprocess.run(["git", "init", "-q"], cwd=tmp_path, check=True)
    return tmp_path


def test_the_measured_code_is_the_closure_of_the_scripts_imports(repo):
    paths = measured_paths("bench_x", repo)
    assert "hybrid_kinematics_ros/kinematics/se3.py" in paths  # through fk.py's relative import
    assert "hybrid_kinematics_ros/kinematics/__init__.py" in paths and "config" in paths
    assert not any("/ik/" in path for path in paths)


def test_a_section_is_stale_after_a_change_to_what_it_measures_and_only_then(repo):
    head = commit(repo, "code")
    benchmarks = repo / "BENCHMARKS.md"
    benchmarks.write_text(section("recorded", f"  \nCommit: {head[:12]}") + "\n" + section("legacy", ""))
    written = commit(repo, "benchmarks")
    assert [(s.key, s.ran_at, s.stale_since) for s in sections(benchmarks, repo)] == [
        ("recorded", head, None),
        ("legacy", written, None),  # no Commit line: the commit that brought its Run line in
    ]
    (repo / "hybrid_kinematics_ros/ik/solver.py").write_text("def solve(): return 1\n")
    commit(repo, "unrelated")
    assert all(s.stale_since is None for s in sections(benchmarks, repo))
    (repo / "hybrid_kinematics_ros/kinematics/se3.py").write_text("def compose(): return 2\n")
    changed = commit(repo, "se3 changed")
    assert {s.stale_since for s in sections(benchmarks, repo)} == {changed}
    mark(benchmarks, repo)
    once = benchmarks.read_text()
    assert once.count("**Stale:**") == 2 and "se3 changed" in once
    mark(benchmarks, repo)
    assert benchmarks.read_text() == once  # marking again changes nothing
    commit(repo, "marked")  # the marks do not move the Run lines: still stale, since the same change
    assert {s.stale_since for s in sections(benchmarks, repo)} == {changed}
