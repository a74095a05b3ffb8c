"""train's progress off a terminal: plain lines every few seconds, no carriage returns or cursor moves."""

from __future__ import annotations

import subprocess

from hybrid_kinematics_ros.cli.main import main
from hybrid_kinematics_ros.cli.train import PLAIN_INTERVAL_S

SECONDS = 8.0  # long enough for a line or two between the first and the last


def test_train_writes_plain_progress_lines_into_a_log(tmp_path):
    bag = tmp_path / "bag"
    assert main(["simulate", "--robot", "ur10", "--samples", "1200", "--out", str(bag), "--seed", "4"]) == 0
    args = ["--bag", str(bag), "--robot", "ur10", "--out", str(tmp_path / "model"), "--no-parametric"]
    arch = ["--arch-position", "mlp:32x2", "--arch-orientation", "mlp:32x2"]
    result = subprocess.run(
        ["hybrid-kinematics", "train", *args, *arch, "--max-minutes", str(SECONDS / 60)],
        capture_output=True,  # pipes: not a terminal
        text=True,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    log = result.stdout + result.stderr
    assert "\r" not in log and "\x1b[" not in log
    progress = [line for line in result.stderr.splitlines() if line.startswith("train: ")]
    # one line every PLAIN_INTERVAL_S while training, one at the end; tqdm wrote hundreds
    assert 2 <= len(progress) <= SECONDS / PLAIN_INTERVAL_S + 2, progress
    assert all("position" in line and "orientation" in line and "epoch" in line for line in progress[-1:])
    assert len(result.stderr.splitlines()) < 25, result.stderr
