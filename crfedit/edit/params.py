"""What each edit trains: one table, read by the edits, the deltas and the tests.

Parameters are selected by state-dict prefix (module names equal checkpoint keys).  A prefix
naming a code table (``color_codes``, ``shape_codes``) means *the edited instance's row* of it:
gradients reach only that row, the weight penalty reads only that row, and the delta stores only
that row's difference.
"""

from __future__ import annotations

from ..errors import CrfError
from ..field import ConditionalRadianceField
from ..names import CODE_TABLES, COLOR_CODES, SHAPE_CODES, STRATEGIES

TRAINED: dict[str, tuple[str, ...]] = {
    "color": ("F_rad.", COLOR_CODES),
    "shape": ("F_fuse.", "F_dens.", "coarse.F_fuse.", "coarse.F_dens."),
}
"""The paper's hybrid update per edit group: a colour edit trains the radiance network and the
instance's colour code; a shape edit trains the fusion and density layers (of both networks of
the paper preset)."""

CODES: dict[str, str] = {"color": COLOR_CODES, "shape": SHAPE_CODES}
"""The code table the ``codes`` strategy trains (row k only) per edit group."""


GROUP = {"color": "color", "remove": "shape", "add": "shape"}
"""Edit kind → the group of :data:`TRAINED` it uses."""


def used_code_tables(field: ConditionalRadianceField) -> list[str]:
    """Names of the code tables the field's architecture actually reads."""
    s, c = field.code_tables()
    return [name for name in CODE_TABLES if getattr(field, name) is s or getattr(field, name) is c]


def trained_prefixes(field: ConditionalRadianceField, group: str, strategy: str) -> tuple[str, ...]:
    """The state-dict prefixes an edit of ``group`` trains with ``strategy``.

    Prefixes that match no parameter of this field are dropped (``coarse.`` exists only with the
    paper's hierarchical sampler; a code table the architecture does not read is not trained).
    """
    if strategy not in STRATEGIES:
        raise CrfError(f"--strategy {strategy}: expected one of {', '.join(STRATEGIES)}")
    names = [n for n, _ in field.named_parameters()]
    codes = used_code_tables(field)
    if strategy == "codes":
        table = CODES[group]
        if table not in codes:
            raise CrfError(
                f"--strategy codes: a model of arch {field.arch!r} has no separate {group} code to edit "
                "(use --strategy hybrid or all)"
            )
        return (table,)
    if strategy == "all":
        tops = []
        for n in names:
            if n in CODE_TABLES or n.startswith("F_part."):  # no render reads the part head
                continue
            top = n.split(".")[0] + "."
            if top not in tops:
                tops.append(top)
        return (*tops, *codes)
    out = []
    for prefix in TRAINED[group]:
        if prefix in CODE_TABLES:
            if prefix in codes:
                out.append(prefix)
        elif any(n.startswith(prefix) for n in names):
            out.append(prefix)
    return tuple(out)


def trained_names(field: ConditionalRadianceField, prefixes: tuple[str, ...]) -> list[str]:
    """Parameter names under ``prefixes``."""
    return [n for n, _ in field.named_parameters() if n.startswith(prefixes)]
