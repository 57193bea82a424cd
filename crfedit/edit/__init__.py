"""Editing one instance of a trained category (Liu et al., ICCV 2021, Sec. 4).

Every edit trains a copy of the tensors that render the edited instance and is recorded as a
delta (crfedit/delta.py); see docs/editing.md.

* :func:`edit_color` — recolour a scribbled part (F_rad + colour code, cached features).
* :func:`remove` — remove a scribbled part (F_fuse + F_dens, cached F_fuse inputs).
* :func:`add` — paste a part of another instance (F_fuse + F_dens).
* :func:`transfer` / :func:`swap_codes` — take another instance's shape or colour code.
"""

from .color import edit_color
from .core import EditOptions, EditResult, InstanceEdit
from .params import CODES, STRATEGIES, TRAINED, trained_prefixes
from .shape import ADD_METHODS, add, remove
from .transfer import swap_codes, transfer

__all__ = [
    "ADD_METHODS",
    "CODES",
    "EditOptions",
    "EditResult",
    "InstanceEdit",
    "STRATEGIES",
    "TRAINED",
    "add",
    "edit_color",
    "remove",
    "swap_codes",
    "trained_prefixes",
    "transfer",
]
