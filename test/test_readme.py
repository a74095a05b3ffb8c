"""The README's command-line block runs as written."""

from __future__ import annotations

import re
import subprocess

from test.conftest import ROOT


def readme_block() -> list[str]:
    text = (ROOT / "README.md").read_text()
    block = text.split("<!-- readme-test", 1)[1].split("```bash\n", 1)[1].split("```", 1)[0]
    return [line.split("   #")[0].strip() for line in block.splitlines() if not line.startswith(". ./env.sh")]


def test_readme_commands_run_as_written(tmp_path):
    (tmp_path / "bags").symlink_to(ROOT / "bags")
    commands = readme_block()
    assert len(commands) >= 8
    for command in commands:
        result = subprocess.run(["bash", "-c", command], cwd=tmp_path, capture_output=True, text=True, check=False)
        assert result.returncode == 0, f"{command}\n{result.stderr[-2000:]}"
    solutions = (tmp_path / "solutions.csv").read_text().splitlines()
    assert solutions[0].startswith("pose_index,solution,shoulder_pan_joint") and len(solutions) >= 2
    assert re.search(r'"hybrid"', (tmp_path / "eval.json").read_text())
    assert (tmp_path / "model_from_recording" / "model.json").is_file()
