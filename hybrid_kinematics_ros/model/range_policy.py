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

# what FK did with configurations outside the calibrated range, per policy (the node's message, the CLI's warning)
OUTSIDE = {
    "warn": "their correction is extrapolated",
    "parametric": "they got the parametric model without the nets",
    "refuse": "",
    "bound": "each got a net's correction only where its error bound is below the parametric stage's alone",
}


def described() -> str:
    """The policies and what each does, as one phrase for help texts."""
    return ", ".join(f"{name} ({what})" for name, what in RANGE_POLICIES.items())
