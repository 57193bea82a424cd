"""Names that the library and the CLI share, importable without torch (the CLI builds its
choices from them and imports torch only when a command runs)."""

from __future__ import annotations

MODULES = ("F_share", "F_inst", "F_fuse", "F_dens", "bottleneck", "F_rad")
"""The paper's modules of one network in data-flow order (each is a state-dict prefix)."""
SHAPE_CODES = "shape_codes"
COLOR_CODES = "color_codes"
CODE_TABLES = (SHAPE_CODES, COLOR_CODES)
"""State-dict names of the per-instance code tables [K, code_dim]."""
INSTANCE_TABLES = (*CODE_TABLES, "occupancy")
"""State-dict names of the tables with one row per instance (codes [K, D], grids [K, R, R, R])."""

NO_MASK = "none"
"""``select --scribble none`` / ``--keep none``: this view has no such strokes (a further view
that only holds keep strokes, or a view without keep strokes beside one with them)."""

MODEL_FORMAT = "crfedit-model"
EDIT_FORMAT = "crfedit-edit"
SELECTION_FORMAT = "crfedit-selection"
"""The ``format`` metadata of crfedit's three kinds of safetensors file."""

STRATEGIES = ("hybrid", "codes", "all")
"""What an edit trains.  hybrid: ``edit.params.TRAINED``; codes: the instance's code row only;
all: every network weight that renders (not the part head F_part) and the instance's code rows."""
ADD_METHODS = ("selection", "composite", "density")
"""How ``add`` supervises the pasted part: the donor's density and features at 3-D points of a
selection of the part moved into place (the default), or, with the paper's one-view
supervision, its rendered image or the donor's density along the pasted rays."""
PENALTIES = ("tensor", "element")
"""How an edit's weight penalty weighs a tensor's drift (:func:`crfedit.edit.losses.weight_penalty`):
``element`` (every trained number alike, the default) or ``tensor`` (per-tensor means)."""

RECOLOR_RULES = ("shading", "ratio")
"""A selection recolour's target inside S (:class:`crfedit.edit.supervised.RecolorTarget`):
``shading`` (the new colour × each point's shading, the default) or ``ratio`` (each point's
colour × new / old per channel)."""

EDIT_METHODS = ("selection", "paper")
"""How remove and edit-color use the scribbles.  selection: lift them to a 3-D selection and
supervise the edit with it (``edit.selection``, ``edit.supervised``); paper: the paper's losses
on the scribbled view's rays alone."""

JOIN_MODES = ("auto", "always", "never")
"""Whether a selection joins what the scribbled colour's chromaticity alone selects
(``edit.selection``, ``SelectOptions.chroma_union``): as the edit kind does (recolours and
removals unless it would take over 4.5× the cells the features chose, 3.5× for a recolour's
pale part; additions never), always, or never."""

MIRROR_MODES = ("off", "views", "values")
"""How a selection reads the instance's mirror symmetry (``edit.symmetry``): not at all, the
scribbled views' mirror images lending their strokes, or the selection taking its own mirror
image."""


def whole_number(value) -> int | None:
    """``value`` as an ``int`` when it is an integer of Python's, NumPy's or torch's kinds (a
    0-d tensor too), None otherwise: a bool (NumPy's, torch's), a float, a string."""
    import operator

    if isinstance(value, bool) or "bool" in str(getattr(value, "dtype", "")):
        return None
    try:
        return operator.index(value)
    except TypeError:
        return None


def real_number(value) -> float | None:
    """``value`` as a ``float`` when it is a number of Python's or NumPy's kinds (an integer or a
    float, NaN and infinities included), None otherwise: a bool (NumPy's too), a string, a list.
    The test an option given from a script meets (a ``np.float32`` threshold, an ``np.int64``
    focal), beside :func:`whole_number`."""
    import numpy as np

    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):  # np.bool_ is neither
        return None
    return float(value)


def is_digits(text: str) -> bool:
    """Whether ``text`` is a whole number in ASCII digits ("12", not "" or "²"): ``str.isdigit``
    also passes superscripts and other digit characters that ``int`` refuses."""
    return text.isascii() and text.isdigit()


def did_you_mean(key: str, names: list[str] | tuple[str, ...]) -> str:
    """A hint for an unknown name: "; did you mean 'x'?" naming the names that contain ``key`` (or
    that ``key`` contains) or, failing that, the closest spellings; "" when nothing is near. Users
    type the short end of long names (``chair_with_cushion`` for ``blendswap_cc_0_chair_with_cushion``)."""
    import difflib

    folded = key.strip().lower()
    near = [n for n in names if folded and (folded in n.lower() or n.lower() in folded)] if len(folded) >= 3 else []
    if not near:
        near = difflib.get_close_matches(key, list(names), n=3, cutoff=0.75)
    if not near or len(near) > 3:
        return ""
    return "; did you mean " + " or ".join(repr(n) for n in near) + "?"


MIN_PIECE = 0.005
"""``export mesh --min-piece``'s default: pieces (connected components) with fewer faces than
this share of the largest piece's are dropped (:func:`~crfedit.export.drop_small_pieces`).  A
tester's quickstart chair at --res 128: the chair 98 472 faces and 55 floaters of 8–172
(≤ 0.17 %), which also widened the reported extent."""
