"""From pairs bags to a model directory: split, targets, the two nets, test metrics and the manifest."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np

from hybrid_kinematics_ros.calibration import train
from hybrid_kinematics_ros.calibration.alignment import AlignOptions, AlignResult, align
from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.calibration.evaluate import evaluate
from hybrid_kinematics_ros.calibration.hybrid import HybridModel
from hybrid_kinematics_ros.calibration.parametric import identify
from hybrid_kinematics_ros.calibration.referencing import Referencing, anchor_base, reference
from hybrid_kinematics_ros.io.model_dir import save_model_dir
from hybrid_kinematics_ros.io.pairs import (
    JOINTS_TOPIC,
    RAW_JOINTS_TOPIC,
    RAW_POSE_TOPIC,
    Pairs,
    bag_topics,
    read_pairs,
)
from hybrid_kinematics_ros.io.raw_bag import RawRecording, read_raw
from hybrid_kinematics_ros.kinematics.chain import Chain
from hybrid_kinematics_ros.kinematics.elastic import ElasticChain

COVERAGE_SPACING = 0.005  # rad: the grid the stored training configurations are thinned on


def align_raw(
    bag: str | Path,
    chain: Chain,
    options: AlignOptions | None = None,
    frame_id: str | None = None,
    joints_topic: str = RAW_JOINTS_TOPIC,
    tracker_topic: str = RAW_POSE_TOPIC,
) -> tuple[AlignResult, RawRecording]:
    rec = read_raw(bag, joints_topic, tracker_topic)
    return align(chain, rec, options, frame_id), rec


def load_pairs(
    bags: Sequence[str | Path],
    chain: Chain,
    raw_frame_id: str | None = None,
    referencing: Referencing | None = None,
    allow_tracker_frame: bool = False,
) -> Pairs:
    """Pairs from pairs bags, or from raw recordings, which are aligned on the fly.

    ``raw_frame_id`` names the frame of raw recordings' pairs (e.g. the base link when the tracker frame
    is the robot base, as in the simulated cell). Pairs in a tracker frame are moved into the base frame
    with ``referencing``; without one they are an error unless ``allow_tracker_frame`` (training, which
    references them itself).
    """
    parts = []
    for bag in bags:
        topics = bag_topics(bag)
        if JOINTS_TOPIC not in topics and RAW_JOINTS_TOPIC in topics and RAW_POSE_TOPIC in topics:
            parts.append(align_raw(bag, chain, frame_id=raw_frame_id)[0].pairs)
        else:
            parts.append(read_pairs(bag, chain.joint_names))
    pairs = Pairs.concatenate(parts)
    if pairs.frame_id != chain.base_link and referencing is not None and pairs.frame_id == referencing.frame_id:
        return referencing.to_base(pairs, chain.base_link)
    if pairs.frame_id != chain.base_link and not allow_tracker_frame:
        raise CalibrationError(
            f"the pairs are in frame '{pairs.frame_id}', not the base link '{chain.base_link}'; "
            "train a model on them first (training references them) or evaluate with a model referenced to that frame"
        )
    return pairs


SPLIT_BLOCKS = 100  # time blocks a split cuts the pairs into, by default


def split(
    pairs: Pairs, seed: int, fractions: tuple[float, float] = (0.1, 0.1), blocks: int | None = SPLIT_BLOCKS
) -> tuple[Pairs, Pairs, Pairs]:
    """Reproducible train/validation/test split (validation and test fractions given), by time blocks.

    Pairs recorded along a trajectory are milliseconds apart and nearly equal: a split by single pairs
    puts the neighbours of every test pair into training, and the test error measures interpolation
    between them. So the pairs, as read (bag by bag, each in stamp order), are cut into ``blocks``
    contiguous blocks, and whole blocks are drawn for validation and test. ``blocks=None`` draws single
    pairs (the old, optimistic split). :func:`split_summary` says which was used, for ``model.json``.
    """
    n = len(pairs)
    if n < 10:
        raise CalibrationError(f"only {n} pairs: at least 10 are needed to train, validate and test")
    rng = np.random.default_rng(seed)
    n_val = max(1, int(n * fractions[0])) if fractions[0] > 0 else 0
    n_test = max(1, int(n * fractions[1])) if fractions[1] > 0 else 0
    if blocks is None or blocks >= n:
        perm = rng.permutation(n)
    else:
        chunks = np.array_split(np.arange(n), blocks)  # pairs come in bag order, each bag in stamp order
        perm = np.concatenate([chunks[i] for i in rng.permutation(len(chunks))])
    val, test = perm[:n_val], perm[n_val : n_val + n_test]
    train = np.sort(perm[n_val + n_test :])
    return pairs.subset(train), pairs.subset(np.sort(val)), pairs.subset(np.sort(test))


def split_summary(blocks: int | None, separate_val: bool, separate_test: bool) -> dict[str, Any]:
    """How the validation and test sets were chosen, for ``model.json``."""

    def how(separate: bool) -> str:
        if separate:
            return "separate bags"
        return "random pairs" if blocks is None else f"contiguous time blocks (1 in {blocks} of the pairs each)"

    return {"validation": how(separate_val), "test": how(separate_test)}


def fit(
    chain: Chain,
    train_pairs: Pairs,
    val_pairs: Pairs,
    test_pairs: Pairs,
    out: Path,
    preset: train.Preset,
    max_minutes: float,
    seed: int = 0,
    arch: dict[str, str] | None = None,
    data_summary: dict[str, Any] | None = None,
    progress: Callable[[dict], None] | None = None,
    parallel: bool = True,
    parametric: bool = False,
    payload: tuple[float, np.ndarray] = (0.0, np.zeros(3)),
    log: Callable[[str], None] = lambda _: None,
) -> tuple[HybridModel, dict[str, Any]]:
    """Reference, identify, train both nets within ``max_minutes`` (side by side), write the model directory.

    Pairs in a tracker frame are referenced first (:func:`referencing.reference`); with ``parametric``
    the elasto-geometric stage is identified next, and the nets learn what it leaves. Position-only
    pairs train the position net alone.
    """
    manifest: dict[str, Any] = {}
    ref = None
    raw = train_pairs, val_pairs, test_pairs
    if train_pairs.frame_id != chain.base_link:
        ref = reference(chain, train_pairs, seed=seed)
        log(f"referenced frame '{ref.frame_id}': rms {ref.rms_position_mm:.4f} mm ({ref.outliers} outliers)")
        train_pairs, val_pairs, test_pairs = (ref.to_base(p, chain.base_link) for p in raw)
    position_only = train_pairs.position_only
    target = ref.target_offset if ref is not None else None  # position-only: the models predict that point
    base = ElasticChain.rigid(chain)
    if parametric:
        start = time.perf_counter()
        result = identify(
            chain, train_pairs.q, train_pairs.T, *payload, position_only=position_only, seed=seed, target=target
        )
        if ref is not None:
            ref, result = anchor_base(chain, ref, result)
            train_pairs, val_pairs, test_pairs = (ref.to_base(p, chain.base_link) for p in raw)
        base = result.model
        manifest["parametric"] = {**result.manifest(), "seconds": round(time.perf_counter() - start, 1)}
        log(
            f"parametric stage: {int(result.identifiable.sum())} of {len(result.params)} parameters identifiable; "
            f"rms {result.rms_before['position_mm']:.4f} -> {result.rms_after['position_mm']:.4f} mm"
        )
    if ref is not None:
        manifest["referencing"] = ref.manifest()
    lower, upper = train_pairs.q.min(axis=0), train_pairs.q.max(axis=0)
    norm_lower, norm_upper = (chain.lower, chain.upper) if preset.full_range else (lower, upper)
    norm_lower = np.where(np.isfinite(norm_lower), norm_lower, lower)
    norm_upper = np.where(np.isfinite(norm_upper), norm_upper, upper)
    y_train = train.residual_targets(base, train_pairs.q, train_pairs.T, target)
    y_val = train.residual_targets(base, val_pairs.q, val_pairs.T, target)
    arch = arch or {}
    kinds = ("position",) if position_only else train.KINDS
    jobs = {}
    for seed_offset, kind in enumerate(kinds):
        p = replace(preset, arch=arch.get(kind) or preset.arch)
        jobs[kind] = train.NetJob(
            kind,
            p,
            train_pairs.q,
            y_train[kind],
            val_pairs.q,
            y_val[kind],
            norm_lower,
            norm_upper,
            train.joint1_axis(chain),
            60.0 * max_minutes,
            seed + seed_offset,
        )
    start = time.perf_counter()
    nets, histories = train.train_pair(jobs, progress=progress, parallel=parallel)
    seconds = time.perf_counter() - start
    manifest.update(
        {
            "base_link": chain.base_link,
            "tip_link": chain.tip_link,
            "joint_names": list(chain.joint_names),
            "tool": chain.tool.tolist(),
            "joint_limits": {"lower": chain.lower.tolist(), "upper": chain.upper.tolist()},
            "trained_range": {"lower": lower.tolist(), "upper": upper.tolist()},
            "position_only": position_only,
        }
    )
    model = HybridModel(chain, nets, manifest)
    metrics = evaluate(model, test_pairs)  # eager nets here; the saved TorchScript is checked against them
    manifest.update(
        {
            "nets": {
                kind: {"arch": job.preset.arch, "epochs": len(histories[kind]), **_best(histories[kind])}
                for kind, job in jobs.items()
            },
            "preset": asdict(preset),
            "seed": seed,
            "training_seconds": round(seconds, 1),
            "data": {
                **(data_summary or {}),
                "train": len(train_pairs),
                "val": len(val_pairs),
                "test": len(test_pairs),
                "frame_id": manifest.get("referencing", {}).get("frame_id", chain.base_link),
            },
            "metrics": {"test": metrics},
        }
    )
    if position_only:
        manifest["note"] = "position-only data: orientation is not corrected (no orientation net)"
    save_model_dir(out, manifest, chain.urdf_text, nets, coverage=thinned(train_pairs.q))
    return HybridModel.load(out), manifest


def thinned(q: np.ndarray, spacing: float = COVERAGE_SPACING) -> np.ndarray:
    """One configuration per ``spacing``-sided cell of joint space: a slow trajectory repeats itself."""
    _, keep = np.unique(np.round(q / spacing), axis=0, return_index=True)
    return q[np.sort(keep)]


def _best(history: list[dict]) -> dict[str, float]:
    last = history[-1]
    return {k: v for k, v in last.items() if k.startswith("best_val_")}
