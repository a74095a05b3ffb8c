"""The command blocks of README.md and docs/*.md run as written, or say why they do not.

Every shell block (```bash, ```sh, ```shell, ```console) has a marker comment on the line before it (blank
lines between are allowed):

- ``<!-- readme-test: ... -->``: the README's command block, which trains the models the docs reuse;
- ``<!-- test: NAME -->``: a block that runs after the README's block, in the same scratch folder and in
  reading order (README, then the docs pages in ``PAGES`` order), so it may use that block's outputs
  (``data/``, ``model/``, ``model_from_recording/``, ``joints.csv``, ...);
- ``<!-- not-run: REASON -->``: a block no test runs, and why (hardware, ros2cli, minutes of training).

A block without a marker, or a ``not-run`` without a reason, fails ``test_every_shell_block_is_run_or_says_why``.
Each block runs as one ``bash`` script with ``set -e``, from a scratch folder holding links to the repository's
``bags``, ``config`` and ``test`` folders, so commands written "from the repository root" run unchanged
(``. ./env.sh`` lines are skipped: the test runs inside that environment already).
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import subprocess
from dataclasses import dataclass
from pathlib import Path

from test.conftest import ROOT

SHELL_FENCE = re.compile(r"^```(bash|sh|shell|console)\s*$")
MARKER = re.compile(r"^<!--\s*(readme-test|test|not-run)\s*:\s*(.*?)\s*-->\s*$")
# the docs pages whose `test:` blocks run, in this order, after the README's block (a page not listed here
# runs after these, in name order)
PAGES = ("tutorial-virtual-cell.md", "calibrate-a-real-cell.md", "tracker-exports.md", "nodes.md")
LINKED = ("bags", "config", "test")  # repository folders the commands read, linked into the scratch folder
BLOCK_TIMEOUT_S = 600


@dataclass(frozen=True)
class Block:
    path: Path
    line: int  # of the opening fence, 1-based
    kind: str | None  # readme-test, test or not-run; None: no marker
    label: str  # the test's name, or the reason it is not run
    text: str

    def where(self) -> str:
        return f"{self.path.relative_to(ROOT)}:{self.line}"


def documents() -> list[Path]:
    pages = sorted((ROOT / "docs").glob("*.md"))
    listed = [p for name in PAGES for p in pages if p.name == name]
    return [ROOT / "README.md", *listed, *(p for p in pages if p not in listed)]


def shell_blocks(path: Path) -> list[Block]:
    lines = path.read_text().splitlines()
    blocks, i = [], 0
    while i < len(lines):
        fence = SHELL_FENCE.match(lines[i])
        if not fence:
            if lines[i].startswith("```"):  # another language's block: skip to its end
                i = next((j for j in range(i + 1, len(lines)) if lines[j].startswith("```")), len(lines))
            i += 1
            continue
        end = next((j for j in range(i + 1, len(lines)) if lines[j].startswith("```")), len(lines))
        before = next((lines[j] for j in range(i - 1, -1, -1) if lines[j].strip()), "")
        marker = MARKER.match(before.strip())
        kind, label = (marker.group(1), marker.group(2)) if marker else (None, "")
        blocks.append(Block(path, i + 1, kind, label, "\n".join(lines[i + 1 : end]) + "\n"))
        i = end + 1
    return blocks


def all_blocks() -> list[Block]:
    return [b for path in documents() for b in shell_blocks(path)]


def test_every_shell_block_is_run_or_says_why() -> None:
    blocks = all_blocks()
    assert len(blocks) >= 10, "the block parser found too few blocks"
    unmarked = [b.where() for b in blocks if b.kind is None]
    assert not unmarked, f"shell blocks with neither <!-- test: NAME --> nor <!-- not-run: REASON -->: {unmarked}"
    no_reason = [b.where() for b in blocks if b.kind == "not-run" and len(b.label) < 10]
    assert not no_reason, f"not-run blocks must say why: {no_reason}"
    readme = [b for b in blocks if b.kind == "readme-test"]
    assert [b.path.name for b in readme] == ["README.md"], "exactly one readme-test block, in README.md"
    names = [b.label for b in blocks if b.kind == "test"]
    assert all(re.fullmatch(r"[a-z0-9-]+", n) for n in names), f"test names: lower case and dashes: {names}"
    assert len(set(names)) == len(names), f"test names must be unique: {names}"


def test_the_checker_sees_an_unmarked_block(tmp_path) -> None:
    """The marker check itself: a block after prose, or after a marker of another kind, has no marker."""
    page = tmp_path / "page.md"
    page.write_text(
        "Text.\n\n```bash\necho a\n```\n\n<!-- not-run: needs a tracker -->\n\n```sh\necho b\n```\n"
        "<!-- note: nothing -->\n```console\necho c\n```\n```yaml\n# ```bash inside yaml is no block\n```\n"
    )
    assert [(b.kind, b.label, b.text) for b in shell_blocks(page)] == [
        (None, "", "echo a\n"),
        ("not-run", "needs a tracker", "echo b\n"),
        (None, "", "echo c\n"),
    ]


LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")


def anchors(path: Path) -> set[str]:
    """GitHub's heading anchors of a Markdown file: lower case, punctuation dropped, spaces to dashes."""
    seen: dict[str, int] = {}
    out = set()
    in_code = False
    for line in path.read_text().splitlines():
        if line.startswith("```"):
            in_code = not in_code
        if in_code or not line.startswith("#"):
            continue
        slug = re.sub(r"[^\w\- ]", "", line.lstrip("#").strip().lower()).replace(" ", "-")
        count = seen.get(slug, 0)
        seen[slug] = count + 1
        out.add(slug if count == 0 else f"{slug}-{count}")
    return out


def test_docs_links_resolve() -> None:
    """Every relative link of README.md and docs/*.md names a file that exists, and a heading in it."""
    broken = []
    for page in documents():
        for target in LINK.findall(page.read_text()):
            if re.match(r"[a-z]+:", target):
                continue
            file, _, anchor = target.partition("#")
            path = (page.parent / file).resolve() if file else page
            if not path.exists() or (anchor and path.suffix == ".md" and anchor not in anchors(path)):
                broken.append(f"{page.relative_to(ROOT)}: {target}")
    assert not broken, f"broken links: {broken}"


def script(block: Block) -> str:
    """The block as a bash script: stop at the first failing command, and name it."""
    body = "\n".join(line for line in block.text.splitlines() if not line.lstrip().startswith(". ./env.sh"))
    return "set -eo pipefail\ntrap 'echo \"failed: $BASH_COMMAND\" >&2' ERR\n" + body + "\n"


def run_block(block: Block, cwd: Path) -> subprocess.CompletedProcess:
    """Run in a session of its own; whatever the block leaves running (a node) is ended afterwards."""
    proc = subprocess.Popen(
        ["bash", "-c", script(block)],
        cwd=cwd,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        out, err = proc.communicate(timeout=BLOCK_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


def check_readme_outputs(work: Path) -> None:
    solutions = (work / "solutions.csv").read_text().splitlines()
    assert solutions[0].startswith("pose_index,solution,shoulder_pan_joint") and len(solutions) >= 2
    assert re.search(r'"hybrid"', (work / "eval.json").read_text())
    assert (work / "model_from_recording" / "model.json").is_file()


def check_docs_output(name: str, work: Path, stdout: str) -> None:
    """What some of the docs blocks must have produced, beyond exiting 0."""
    if name == "tutorial-coverage":
        assert "coverage" in json.loads((work / "away.json").read_text())
    elif name == "tutorial-radius":
        assert (work / "served.csv").read_text().splitlines()[0].startswith("x,y,z")
    elif name == "tutorial-serve":
        assert "FK: True" in stdout and "IK: " in stdout, stdout
    elif name == "real-cell-align":
        summary = json.loads(stdout.strip().splitlines()[-1])
        assert summary["pairs"] > 1000 and abs(summary["clock_offset_ms"] - 12.3) < 1e-6, summary
    elif name == "real-cell-plan":
        assert len((work / "plan" / "poses.csv").read_text().splitlines()) == 31
    elif name == "real-cell-plan-prior":  # the README's model chose harmonics on the virtual cell's gear ripple
        summary = json.loads((work / "plan_again" / "plan.json").read_text())
        assert summary["cyclic_prior"]["harmonics"] >= 1 and "capacity" in summary["predicted"], summary
        assert all("capacity" in row for row in summary["curve"]), summary["curve"]
    elif name.startswith("tracker-exports-"):
        imported = [json.loads(line) for line in stdout.splitlines() if line.startswith("{")]
        assert imported and all(i["imported"] == i["rows"] == 40 for i in imported), stdout


def test_readme_and_docs_commands_run_as_written(tmp_path) -> None:
    work = tmp_path / "work"
    work.mkdir()
    for name in LINKED:
        (work / name).symlink_to(ROOT / name)
    blocks = all_blocks()
    (readme,) = [b for b in blocks if b.kind == "readme-test"]
    assert len([line for line in readme.text.splitlines() if line.startswith("hybrid-kinematics")]) >= 8
    result = run_block(readme, work)
    assert result.returncode == 0, f"{readme.where()}\n{result.stderr[-3000:]}"
    check_readme_outputs(work)
    for block in (b for b in blocks if b.kind == "test"):
        result = run_block(block, work)
        assert result.returncode == 0, (
            f"{block.where()} ({block.label})\n{result.stdout[-2000:]}\n{result.stderr[-3000:]}"
        )
        check_docs_output(block.label, work, result.stdout)
