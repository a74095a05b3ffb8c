"""Shared fixtures. Every test session gets its own ROS domain and stays on localhost.

``trained`` is a small hybrid model, trained for real once per session on the virtual UR10.
"""

from __future__ import annotations

import fcntl
import os
import shutil

# One BLAS thread per process: on the 2-core machine the suite's processes (nodes, CLI runs, net workers)
# share the cores, and multithreaded OpenBLAS then makes least squares 10-20× slower (measured on the
# alignment tests: 280 s against 26 s). Set before numpy loads; subprocesses inherit it.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
# Under pytest-xdist (``make test`` runs a worker per core) torch's intra-op threads would oversubscribe the
# cores the same way: one thread per worker and per process it starts.
if "PYTEST_XDIST_WORKER" in os.environ:
    os.environ.setdefault("OMP_NUM_THREADS", "1")

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from bench.bench_bounds import shoulder_configurations
from hybrid_kinematics_ros.calibration import train
from hybrid_kinematics_ros.calibration.fit import fit, split
from hybrid_kinematics_ros.calibration.recipe import Recipe
from hybrid_kinematics_ros.io.pairs import Pairs
from hybrid_kinematics_ros.kinematics.approach import channel_names
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.model.hybrid import HybridModel
from hybrid_kinematics_ros.simulation.backlash import BacklashCell
from hybrid_kinematics_ros.simulation.cell import VirtualCell

# Under pytest-xdist each worker is a process of its own, with domains of its own: every domain a worker uses
# (this one and test/nodes/conftest.py's per module) is its index modulo the number of workers, so two workers
# of one run never share one. ROS_DOMAIN_ID must stay below 233 with Fast DDS: DOMAIN_WRAP keeps the residue.
DOMAIN_STRIDE = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
_slots = 232 // DOMAIN_STRIDE  # domains per worker; a session starts in the upper half, by its process id
DOMAIN_WRAP = DOMAIN_STRIDE * _slots
_worker = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw") or 0)
_slot = _slots // 2 + os.getpid() % (_slots - _slots // 2)
os.environ["ROS_DOMAIN_ID"] = str(DOMAIN_STRIDE * _slot + _worker)  # a shell's own would be every worker's
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE_ROBOT_DATA = "cmeel.prefix/share/example-robot-data/robots"


# ``make test`` runs the suite on a pytest-xdist worker per core, a test module at a time (``--dist loadfile``:
# a module's own module-scoped fixtures are built once), and these modules on one worker, one after the other
# (``module_groups``):
# - the recorder's: each test streams tracker poses at 3 kHz in real time, and two at once overload 2 cores;
# - those that name the same expensive session fixture (each trains models for about a minute): each
#   worker builds the session fixtures its own tests use.
REAL_TIME_MODULES = (
    "test/nodes/test_recorder.py",
    "test/nodes/test_recorder_real_cell.py",
    "test/nodes/test_kinematics_node_monitor.py",
)
ONE_WORKER_FIXTURES = ("shoulder_model", "thermal_models", "backlash_models")
# the longest test (it runs every command of README.md and docs/ in turn) starts first, then the real-time
# group, so that no worker waits for either at the end
FIRST = "test_readme_and_docs_commands_run_as_written"


def module_of(nodeid: str) -> str:
    """A test's module, as its node id names it (the path from the repository root)."""
    return nodeid.split("::")[0]


def module_groups() -> dict[str, str]:
    """Test module (its path from the repository root, as in node ids) → the group it runs in, for the modules
    that share a worker; the others are their own."""
    modules = {p.relative_to(ROOT).as_posix(): p.read_text() for p in sorted((ROOT / "test").rglob("test_*.py"))}
    group = dict.fromkeys(REAL_TIME_MODULES, "real-time")
    for name in ONE_WORKER_FIXTURES:
        users = [m for m, text in modules.items() if name in text]
        label = next((group[m] for m in users if m in group), name)
        for old in {group[m] for m in users if m in group} - {label}:  # joins a group that shares another
            group = {m: label if g == old else g for m, g in group.items()}
        group.update(dict.fromkeys(users, label))
    return group


def pytest_xdist_make_scheduler(config: pytest.Config, log):
    """``--dist loadfile`` with the modules of :func:`module_groups` joined."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadScopeScheduling

    groups = module_groups()

    class ModuleGroups(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return groups.get(module_of(nodeid), module_of(nodeid))

    return ModuleGroups(config, log)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    # stable: the rest keep their order (pytest-xdist's --no-loadscope-reorder keeps this one)
    items.sort(key=lambda item: (item.name != FIRST, module_of(item.nodeid) not in REAL_TIME_MODULES))


@pytest.fixture(scope="session")
def example_robot_data() -> Path:
    import site

    for base in site.getsitepackages():
        path = Path(base) / EXAMPLE_ROBOT_DATA
        if path.is_dir():
            return path
    raise RuntimeError("example-robot-data is not installed; run make bootstrap")


SAMPLES = 4000
# A fixed schedule, not a time budget: the model every test sees is the same on a loaded machine (800 epochs
# take about 15 s on 2 shared cores; the budget only stops a machine that is far slower). The models below are
# one net of a size given (no ladder of sizes, no ensemble rung): the tests that use them measure the IK, the
# nodes and the bounds on a fixed model; the ladder has its own tests and the portfolio guard trains `fast`.
EPOCHS = 800
BUDGET_MINUTES = 5.0


@pytest.fixture(scope="session")
def ur10():
    return load_robot_config("ur10")


@pytest.fixture(scope="session")
def virtual_pairs(ur10):
    cell = VirtualCell.from_config(ur10, noise=False)
    q, T = next(cell.samples(SAMPLES, seed=5, block=SAMPLES))
    return Pairs(q, T, 10**9 + 10**7 * np.arange(SAMPLES), ur10.chain.joint_names, "base_link")


def built_once(tmp_path_factory: pytest.TempPathFactory, name: str, build: Callable[[Path], object]) -> Path:
    """The directory ``name`` that ``build(path)`` fills once per test run: under pytest-xdist the first worker
    that asks builds it while any other waits, and then every worker reads the same files."""
    base = tmp_path_factory.getbasetemp()
    root = base.parent if "PYTEST_XDIST_WORKER" in os.environ else base  # the run's, shared by its workers
    out, done = root / f"shared-{name}", root / f"shared-{name}.done"
    with open(root / f"shared-{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        if not done.exists():
            shutil.rmtree(out, ignore_errors=True)  # what a failed build left
            build(out)
            done.touch()
    return out


@pytest.fixture(scope="session")
def trained(ur10, virtual_pairs, tmp_path_factory):
    """The small model (its directory, the model, its manifest) and its test pairs, trained once per run."""
    tr, va, te = split(virtual_pairs, seed=0)
    preset = replace(train.PRESETS["fast"], arch="mlp:64x2:silu", max_epochs=EPOCHS, ensemble=1)
    recipe = Recipe(preset, BUDGET_MINUTES, parametric=False)
    out = built_once(tmp_path_factory, "small", lambda path: fit(ur10.chain, tr, va, te, path, recipe))
    model = HybridModel.load(out)
    return out, model, model.manifest, te


# A model that knows one radian of the UR10's shoulder: its error bounds grow beyond it.
@pytest.fixture(scope="session")
def shoulder_model(ur10, tmp_path_factory):
    """A model trained with the shoulder within one radian (its directory and the model), its test pairs, and
    pairs with the shoulder 0.2-0.8 rad beyond that range."""
    cell = VirtualCell.from_config(ur10, noise=False)
    tr, va, te = split(cell.pairs(shoulder_configurations(2000, (-2.0, -1.0), seed=1), seed=1), seed=0)
    beyond = cell.pairs(shoulder_configurations(400, (-0.8, -0.2), seed=2), seed=2)
    preset = replace(train.PRESETS["fast"], arch="mlp:64x2:silu", max_epochs=400, ensemble=1)
    out = tmp_path_factory.mktemp("shoulder")
    # no joint error map (the selection takes a coarse one on these noise-free pairs): the compiled pose, tested
    # with this model's elastic stage and payload, does not take a map
    recipe = Recipe(
        preset, 5.0, payload_mass=ur10.payload_mass, payload_com=tuple(ur10.payload_com), capacity={"map_step": 0.0}
    )
    model, _ = fit(ur10.chain, tr, va, te, out, recipe)
    return out, model, te, beyond


# A cell whose robot grows with its temperature: models trained with and without that channel.
EXPANSION_PER_K = 2e-4  # a strong thermal growth of the whole arm about its base, so the test is quick
THERMAL_PRESET = replace(train.PRESETS["fast"], arch="mlp:64x2:silu", max_epochs=300, ensemble=1)
# The capacity the selection chooses for the virtual UR10's pairs, fixed where a test is about something else
# (test_portfolio and test_capacity test the selection): the selection is most of a fit's time.
UR10_STAGE = {"elastic": "bending", "harmonics": 2, "harmonic_prior": 30.0, "map_step": 0.0}
# with or without the temperature channel: the channel is under test, not the capacity
THERMAL_STAGE = Recipe(THERMAL_PRESET, 5.0, capacity=UR10_STAGE, choose_capacity=False)


def thermal_pairs(ur10, count: int, seed: int) -> Pairs:
    cell = VirtualCell.from_config(ur10, noise=False)
    rng = np.random.default_rng(seed)
    q = rng.uniform(0.9 * ur10.chain.lower, 0.9 * ur10.chain.upper, (count, 6))
    temperature = rng.uniform(18.0, 28.0, count)
    T = cell.measure(q, rng)
    T[:, :3, 3] *= (1.0 + EXPANSION_PER_K * (temperature - 23.0))[:, None]
    stamps = 10**9 + 10**7 * np.arange(count)
    return Pairs(q, T, stamps, ur10.chain.joint_names, "base_link", conditions={"temperature": temperature})


@pytest.fixture(scope="session")
def thermal_models(ur10, tmp_path_factory):
    tr, va, _ = split(thermal_pairs(ur10, 3000, seed=1), seed=0)
    test = thermal_pairs(ur10, 500, seed=2)
    out = {}
    for name, conditions in (("plain", ()), ("thermal", ("temperature",))):
        path = tmp_path_factory.mktemp("conditions") / name
        # "plain": without the channel, which the pairs would offer the nets (test_offered_conditions)
        fit(ur10.chain, tr, va, test, path, replace(THERMAL_STAGE, conditions=conditions, offered=()))
        out[name] = HybridModel.load(path)
    return out, test


# A cell whose joints have backlash: models trained with and without the approach directions.
def backlash_pairs(ur10, count: int, seed: int) -> Pairs:
    """A random walk of the joints (as a measurement program visits poses), measured with backlash."""
    return BacklashCell.from_config(ur10).walk(count, seed)


@pytest.fixture(scope="session")
def backlash_models(ur10, tmp_path_factory):
    tr, va, _ = split(backlash_pairs(ur10, 3000, seed=1), seed=0)
    test = backlash_pairs(ur10, 500, seed=2)
    out = {}
    for name, conditions in (("plain", ()), ("approach", channel_names(ur10.chain.joint_names))):
        path = tmp_path_factory.mktemp("approach") / name
        # "plain" without the directions, which the data would choose; the rest of the stage fixed, since
        # capacity is not what these models are for
        given = {"approach": bool(conditions), "elastic": "bending", "harmonics": 0, "map_step": 0.0}
        recipe = Recipe(THERMAL_PRESET, 5.0, conditions=conditions, capacity=given, choose_capacity=False)
        fit(ur10.chain, tr, va, test, path, recipe)
        out[name] = HybridModel.load(path)
    return out, test
