"""The model directory: self-contained, checked on load, no pickle anywhere.

Layout: ``model.json`` (the manifest), ``robot.urdf`` (a copy of the URDF the model was trained for),
``position.pt`` and ``orientation.pt`` (TorchScript residual nets; either may be absent, e.g. position-only),
and ``coverage.npy`` (the training configurations, float32 ``(N, n)``, for the distance to the data; absent in
older model directories).
"""

from __future__ import annotations

import hashlib
import json
import platform
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hybrid_kinematics_ros.io.errors import DataError
from hybrid_kinematics_ros.kinematics.errors import KinematicsError
from hybrid_kinematics_ros.kinematics.paths import resolve_path

SCHEMA_VERSION = 1
MANIFEST = "model.json"
URDF_FILE = "robot.urdf"
NET_FILES = {"position": "position.pt", "orientation": "orientation.pt"}
COVERAGE_FILE = "coverage.npy"
REQUIRED = (
    "schema_version",
    "urdf_sha256",
    "base_link",
    "tip_link",
    "joint_names",
    "tool",
    "joint_limits",
    "trained_range",
    "nets",
)


def sha256_file(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    try:
        ours = version("hybrid_kinematics_ros")
    except PackageNotFoundError:
        ours = "source"
    return {
        "hybrid_kinematics_ros": ours,
        "torch": torch.__version__,
        "numpy": np.__version__,
        "python": platform.python_version(),
    }


@dataclass
class ModelFiles:
    """A loaded model directory: the manifest, the URDF text, the TorchScript nets and the training
    configurations (None for models without ``coverage.npy``)."""

    path: Path
    manifest: dict[str, Any]
    urdf_text: str
    nets: dict[str, torch.jit.ScriptModule]
    coverage: np.ndarray | None = None


def save_model_dir(
    path: Path,
    manifest: dict[str, Any],
    urdf_text: str,
    nets: dict[str, torch.nn.Module],
    coverage: np.ndarray | None = None,
) -> None:
    """Write a model directory atomically: into a temporary sibling, then renamed into place."""
    path = Path(path)
    if path.exists() and any(path.iterdir()):
        raise DataError(f"{path} exists already and is not empty, not overwriting")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
    try:
        (tmp / URDF_FILE).write_text(urdf_text)
        files = {}
        for kind, net in nets.items():
            module = net if isinstance(net, torch.jit.ScriptModule) else torch.jit.script(net)
            module.save(str(tmp / NET_FILES[kind]))
            _check_saved(net, tmp / NET_FILES[kind], net_inputs(manifest))
            files[kind] = {"file": NET_FILES[kind], "sha256": sha256_file(tmp / NET_FILES[kind])}
        extra = {}
        if coverage is not None:
            np.save(tmp / COVERAGE_FILE, np.asarray(coverage, dtype=np.float32), allow_pickle=False)
            extra["coverage"] = {
                "file": COVERAGE_FILE,
                "sha256": sha256_file(tmp / COVERAGE_FILE),
                "configurations": len(coverage),
            }
        full = {
            "schema_version": SCHEMA_VERSION,
            "urdf_file": URDF_FILE,
            "urdf_sha256": hashlib.sha256(urdf_text.encode()).hexdigest(),
            **manifest,
            "nets": {
                **manifest.get("nets", {}),
                **{k: {**manifest.get("nets", {}).get(k, {}), **v} for k, v in files.items()},
            },
            **extra,
            "versions": versions(),
        }
        (tmp / MANIFEST).write_text(json.dumps(full, indent=2, default=_json_default) + "\n")
        if path.exists():
            path.rmdir()
        tmp.rename(path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def net_inputs(manifest: dict[str, Any]) -> int:
    """Input columns of the nets: the joints, then the condition channels (``train --condition``)."""
    return len(manifest.get("joint_names", [])) + len(manifest.get("conditions") or {})


def _check_saved(net: torch.nn.Module, file: Path, dof: int) -> None:
    """The saved TorchScript must reproduce the net it came from (``dof``: its input columns)."""
    if not dof:
        return
    q = torch.linspace(-2.0, 2.0, 7 * dof, dtype=torch.float64).reshape(7, dof)
    with torch.no_grad():
        expected = net(q)
        got = torch.jit.load(str(file))(q)
    if not torch.allclose(expected, got, rtol=0, atol=1e-12):
        raise DataError(f"{file}: the saved TorchScript does not reproduce the trained net")


def _json_default(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"cannot store {type(value).__name__} in model.json")


def load_model_dir(path: Path | str) -> ModelFiles:
    """Load and check a model directory (a path or ``package://``). Raises :class:`DataError` naming the
    file and the problem."""
    try:
        path = resolve_path(path)
    except KinematicsError as exc:
        raise DataError(f"model directory {path}: {exc}") from exc
    manifest_path = path / MANIFEST
    if not manifest_path.is_file():
        raise DataError(
            f"{manifest_path} does not exist: not a model directory (train one with `hybrid-kinematics train`)"
        )
    try:
        manifest = json.loads(manifest_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataError(f"{manifest_path} is not valid JSON: {exc}") from exc
    if not isinstance(manifest, dict):
        raise DataError(f"{manifest_path}: expected a JSON object")
    missing = [k for k in REQUIRED if k not in manifest]
    if missing:
        raise DataError(f"{manifest_path}: missing field(s) {', '.join(missing)}")
    if manifest["schema_version"] != SCHEMA_VERSION:
        raise DataError(
            f"{manifest_path}: schema_version {manifest['schema_version']} is not {SCHEMA_VERSION}; "
            "retrain with this version"
        )
    urdf_path = path / manifest.get("urdf_file", URDF_FILE)
    if not urdf_path.is_file():
        raise DataError(f"{urdf_path} does not exist")
    urdf_text = urdf_path.read_text()
    if hashlib.sha256(urdf_text.encode()).hexdigest() != manifest["urdf_sha256"]:
        raise DataError(f"{urdf_path} does not match urdf_sha256 in {manifest_path}: the URDF copy was changed")
    nets = {}
    for kind, entry in manifest["nets"].items():
        if kind not in NET_FILES:
            raise DataError(f"{manifest_path}: unknown net '{kind}' (expected {', '.join(NET_FILES)})")
        file = path / entry.get("file", NET_FILES[kind])
        if not file.is_file():
            raise DataError(f"{file} does not exist (listed in {manifest_path})")
        if sha256_file(file) != entry.get("sha256"):
            raise DataError(f"{file} is corrupt: its sha256 does not match {manifest_path}")
        try:
            nets[kind] = torch.jit.load(str(file), map_location="cpu")
            with torch.no_grad():
                out = nets[kind](torch.zeros(1, net_inputs(manifest), dtype=torch.float64))
        except Exception as exc:  # TorchScript raises RuntimeError and others
            raise DataError(f"{file} is not a usable TorchScript residual net: {exc}") from exc
        if tuple(out.shape) != (1, 3) or not torch.all(torch.isfinite(out)):
            raise DataError(f"{file} returns {tuple(out.shape)} or non-finite values for zero joints; expected (1, 3)")
    return ModelFiles(path, manifest, urdf_text, nets, _load_coverage(path, manifest, manifest_path))


def _load_coverage(path: Path, manifest: dict[str, Any], manifest_path: Path) -> np.ndarray | None:
    entry = manifest.get("coverage")
    if entry is None:
        return None
    file = path / entry.get("file", COVERAGE_FILE)
    if not file.is_file():
        raise DataError(f"{file} does not exist (listed in {manifest_path})")
    if sha256_file(file) != entry.get("sha256"):
        raise DataError(f"{file} is corrupt: its sha256 does not match {manifest_path}")
    try:
        configs = np.load(file, allow_pickle=False)
    except ValueError as exc:
        raise DataError(f"{file} is not a numpy array file: {exc}") from exc
    if configs.ndim != 2 or configs.shape[1] != len(manifest["joint_names"]) or not np.all(np.isfinite(configs)):
        raise DataError(f"{file}: expected finite configurations ({len(manifest['joint_names'])} joints per row)")
    return configs.astype(float)
