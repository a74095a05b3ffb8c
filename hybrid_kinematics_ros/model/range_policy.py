"""What a served model does outside the joint range its nets were trained on (``HybridModel.range_policy``,
the node's ``out_of_range_policy``, the CLI's ``--out-of-range``): one description of each, for all three.
Its own module, free of torch, so that the CLI's help needs nothing heavy."""

from __future__ import annotations

RANGE_POLICIES = {
    "warn": "use the nets, flag it",
    "parametric": "the parametric stage without the nets there",
    "refuse": "fail such FK and IK requests",
    "bound": "each net only where its error bound is below the parametric stage's alone",
}


def described() -> str:
    """The policies and what each does, as one phrase for help texts."""
    return ", ".join(f"{name} ({what})" for name, what in RANGE_POLICIES.items())
