"""FK of one configuration as straight-line Python float code, generated once per chain.

Why: a service answers one configuration at a time, and its process wakes up with cold caches, where each
numpy call costs more than the arithmetic it does; the chain's product in numpy takes about twenty of them.
The product ``A_0(q_0) ··· A_{n-1}(q_{n-1}) · post`` (see ``chain.py``), written out entry by entry with the
chain's constants as literals and the zeros and ones of its fixed transforms folded away, needs no numpy at
all: a UR10 takes 12 ``math`` calls and about 100 multiplications.

The source holds only names and float literals (``repr`` of a float reads back exactly) and is compiled
with ``exec``, as :func:`collections.namedtuple` once did. The association of the products differs from
:func:`fk.fk`'s and generator entries below ``ZERO`` (the ``6e-17`` of ``cos(π/2)``) are dropped, so the
pose agrees with it to rounding (~1e-15), not bit for bit.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from hybrid_kinematics_ros.kinematics.chain import Chain

ZERO = 1e-15  # generator entries this small are rounding of a structural zero (e.g. cos(π/2) in an rpy)

Rows = list[list[float]]  # the top three rows of a 4x4 pose, as nested lists (``T[:3].tolist()``)
Entry = float | str  # a known constant, or the name of a variable of the generated code
Form = dict[str, float]  # a linear form over symbols ('' is the constant 1)


def _factor_forms(chain: Chain, k: int) -> list[list[Form]]:
    """``A_k`` as linear forms: ``(G0 + G2) + s G1 - c G2`` (revolute) or ``G0 + q G1`` (prismatic), rows 0-2."""
    g0, g1, g2 = chain.generators[k]
    parts = (("", g0 + g2), (f"s{k}", g1), (f"c{k}", -g2)) if chain.revolute[k] else (("", g0), (f"q{k}", g1))
    return [[{sym: float(g[i, j]) for sym, g in parts if abs(g[i, j]) > ZERO} for j in range(4)] for i in range(3)]


class _Writer:
    def __init__(self) -> None:
        self.lines: list[str] = []
        self.count = 0

    def assign(self, expr: str) -> str:
        self.count += 1
        name = f"v{self.count}"
        self.lines.append(f"    {name} = {expr}")
        return name


def _product(const: float, terms: list[tuple[float, str]]) -> Entry:
    """A constant plus ``coef * factors`` terms as an entry: the constant itself when no term is left."""
    terms = [(c, f) for c, f in terms if c != 0.0]
    if not terms:
        return const
    out = []
    for coef, factors in terms:
        sign = "-" if coef < 0 else "+"
        mag = abs(coef)
        out.append(f"{sign} {factors}" if mag == 1.0 else f"{sign} {mag!r} * {factors}")
    if const != 0.0:
        out.append(f"{'-' if const < 0 else '+'} {abs(const)!r}")
    text = " ".join(out)
    return text[2:] if text.startswith("+ ") else "-" + text[2:]


def _entry_of_form(form: Form, w: _Writer) -> tuple[float, list[tuple[float, str]]] | str:
    """A factor's entry: ``(constant, [(coef, symbol)])`` kept inline when it has at most one symbol,
    else a variable computed once (it is used by three rows)."""
    const = form.get("", 0.0)
    terms = [(c, s) for s, c in form.items() if s]
    if len(terms) <= 1:
        return const, terms
    expr = _product(const, terms)
    return w.assign(expr) if isinstance(expr, str) else expr


def _multiply(T: list[list[Entry]], A: list[list[Form]], w: _Writer) -> list[list[Entry]]:
    """``T · A`` for affine ``T`` and ``A`` (their bottom rows are ``0 0 0 1``), constants folded."""
    entries = [[_entry_of_form(A[j][c], w) for c in range(4)] for j in range(3)]
    out: list[list[Entry]] = []
    for i in range(3):
        row: list[Entry] = []
        for c in range(4):
            const, terms = 0.0, []
            for j in range(3):
                t, a = T[i][j], entries[j][c]
                if isinstance(a, str):  # a variable
                    a_const, a_terms = 0.0, [(1.0, a)]
                else:
                    a_const, a_terms = a
                if isinstance(t, str):
                    if a_const != 0.0:
                        terms.append((a_const, t))
                    terms += [(coef, f"{t} * {s}") for coef, s in a_terms]
                else:
                    const += t * a_const
                    terms += [(t * coef, s) for coef, s in a_terms]
            if c == 3:
                if isinstance(T[i][3], str):
                    terms.append((1.0, T[i][3]))
                else:
                    const += T[i][3]
            entry = _product(const, terms)
            row.append(w.assign(entry) if isinstance(entry, str) and not entry.isidentifier() else entry)
        out.append(row)
    return out


def unrolled_source(chain: Chain) -> str:
    """The generated function's source, ``fk_rows(q) -> rows`` (see :func:`unrolled_fk`)."""
    w = _Writer()
    n = chain.dof
    names = ", ".join(f"q{k}" for k in range(n))
    w.lines.append(f"    {names}{',' if n == 1 else ''} = q")
    for k in range(n):
        if chain.revolute[k]:
            w.lines.append(f"    s{k} = sin(q{k})")
            w.lines.append(f"    c{k} = cos(q{k})")
    T: list[list[Entry]] = [[float(i == j) for j in range(4)] for i in range(3)]
    for k in range(n):
        T = _multiply(T, _factor_forms(chain, k), w)
    post = [[{"": float(chain.post[i, j])} for j in range(4)] for i in range(3)]
    T = _multiply(T, post, w)
    rows = ", ".join("[" + ", ".join(e if isinstance(e, str) else repr(float(e)) for e in row) + "]" for row in T)
    return "\n".join(["def fk_rows(q):", *w.lines, f"    return [{rows}]", ""])


def unrolled_fk(chain: Chain) -> Callable[[Sequence[float]], Rows] | None:
    """``fk_rows(q)``: the tip pose of one configuration (``n`` finite floats, a list is fastest) as the
    top three rows of its 4x4 matrix, nested lists of Python floats. None when the chain's constants are
    not all finite (then use :func:`fk.fk_single`)."""
    if not (np.all(np.isfinite(chain.generators)) and np.all(np.isfinite(chain.post))):
        return None
    namespace: dict = {"sin": math.sin, "cos": math.cos}
    exec(compile(unrolled_source(chain), f"<unrolled FK {chain.base_link} -> {chain.tip_link}>", "exec"), namespace)
    return namespace["fk_rows"]
