"""Part labels trained into the field: F_part, a linear head on F_fuse's output, and its loss.

A category dataset may ship part maps (``<view>_parts.png``: 0 = background, k = part k) and
depth (``<view>_depth.exr``).  Their labelled pixels lifted to the surface are 3-D points with a
part each.  Training adds :func:`part_contrastive_loss` on F_part's unit-length embedding of
F_fuse's activations at those points, so that the parts of an instance lie apart in that
space; a selection then reads the embedding as one more feature group (``part``,
:mod:`crfedit.edit.selection`), which tells a part from a look-alike neighbour that colour and
the bottleneck do not (docs/selection.md measures it).

The loss is per instance: each point is pulled toward its own part's mean embedding and away
from the means of the instance's other parts.  No part taxonomy across instances is needed (a
real mesh's groups are its own), and a dataset without part maps trains no head
(:attr:`~crfedit.config.Config.part_dim` becomes 0).
"""

from __future__ import annotations

import dataclasses
import json
from typing import NamedTuple, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from .cameras import rays_from_camera
from .config import Config, hidden_part_labels
from .data.loading import Category, read_twin_specs
from .errors import CrfError
from .names import did_you_mean

POINTS_PER_VIEW = 300
"""Labelled surface points drawn per training view (a 64×64 view has ~1 000 object pixels)."""
GROUPS, PER_GROUP = 4, 256
"""Instances per training step, and points per instance, of the part loss."""
TEMPERATURE = 0.1


class PartPoints(NamedTuple):
    """Labelled surface points of a category, grouped by instance."""

    points: Tensor  # [N, 3] world
    labels: Tensor  # [N] int64: the part map's value (1..255)
    instance: Tensor  # [K'] int64: the instances that have any, in order
    offsets: Tensor  # [K'] int64: where each one's points start in ``points``
    counts: Tensor  # [K'] int64: how many it has

    def to(self, device: torch.device | str) -> "PartPoints":
        return PartPoints(*(t.to(device) for t in self))


def labelled_instances(category: Category, labels: str) -> list[int]:
    """The instance indices whose part maps train F_part (``labels``: ``Config.part_labels``):
    ``all``; ``not-twins`` (the sources of the dataset's ground-truth twins left out, so that an
    edit benchmark scores selections of parts the model was never told about); or ``not:NAME,…``
    (those named left out, ``twins`` standing for the twins' sources: chairs held out beyond
    the benchmark's).  A name the dataset does not have is an error."""
    hidden = set(hidden_part_labels(labels) or ())
    if "twins" in hidden:
        hidden = (hidden - {"twins"}) | {t.source for t in read_twin_specs(category.root)}
    unknown = sorted(hidden - set(category.names))
    if unknown:
        raise CrfError(f"part_labels {labels}: {category.root} has no instance {unknown[0]!r}{did_you_mean(unknown[0], category.names)}")
    return [k for k, inst in enumerate(category.instances) if inst.name not in hidden]


def labelled_names(meta: dict[str, str]) -> list[str] | None:
    """The instances whose part maps trained a model's F_part, as its file records them
    (``part_labelled``); None for a file written before the record, or one that does not read."""
    try:
        names = json.loads(meta["part_labelled"])
    except (KeyError, json.JSONDecodeError):
        return None
    return names if isinstance(names, list) and all(isinstance(n, str) for n in names) else None


def has_labels(category: Category, instances: Sequence[int]) -> bool:
    """Whether a training view of ``instances`` has a labelled pixel with a finite depth."""
    for k in instances:
        for view in category.instances[k].splits["train"]:
            if view.parts is not None and view.depth is not None and ((view.parts > 0) & np.isfinite(view.depth)).any():
                return True
    return False


def part_config(category: Category, cfg: Config) -> Config:
    """``cfg`` for a new model of ``category``: ``part_dim`` 0 when no instance it labels
    (:func:`labelled_instances`) has part maps and depth, so no untrained head is stored."""
    if cfg.part_dim and not has_labels(category, labelled_instances(category, cfg.part_labels)):
        return dataclasses.replace(cfg, part_dim=0)
    return cfg


def labelled_points(category: Category, instances: Sequence[int], per_view: int = POINTS_PER_VIEW,
                    seed: int = 0) -> PartPoints | None:
    """Up to ``per_view`` labelled pixels of each training view of ``instances``, lifted to
    the surface along their rays by the view's depth; None when no view has both maps."""
    gen = torch.Generator().manual_seed(seed)
    pts, labs, kept, counts = [], [], [], []
    for k in instances:
        n = 0
        for view in category.instances[k].splits["train"]:
            if view.parts is None or view.depth is None:
                continue
            depth = torch.as_tensor(view.depth.reshape(-1), dtype=torch.float64)
            part = torch.as_tensor(view.parts.reshape(-1).astype("int64"))
            idx = ((part > 0) & torch.isfinite(depth)).nonzero().squeeze(-1)
            if len(idx) > per_view:
                idx = idx[torch.randperm(len(idx), generator=gen)[:per_view]]
            if len(idx) == 0:
                continue
            rays = rays_from_camera(view.camera)
            pts.append((rays.origins[idx].double() + depth[idx, None] * rays.directions[idx].double()).float())
            labs.append(part[idx])
            n += len(idx)
        if n:
            kept.append(k)
            counts.append(n)
    if not kept:
        return None
    counts_t = torch.tensor(counts)
    offsets = torch.cumsum(counts_t, 0) - counts_t
    return PartPoints(torch.cat(pts), torch.cat(labs), torch.tensor(kept), offsets, counts_t)


def sample_parts(parts: PartPoints, generator: torch.Generator, groups: int = GROUPS,
                 per_group: int = PER_GROUP) -> tuple[Tensor, Tensor, Tensor]:
    """``groups`` random instances and ``per_group`` random points of each, drawn on the
    generator's device without a host read: (points [G·P, 3], instance [G·P], labels [G, P])."""
    dev = parts.points.device
    g = torch.randint(len(parts.instance), (groups,), generator=generator, device=generator.device).to(dev)
    u = torch.rand(groups, per_group, generator=generator, device=generator.device).to(dev)
    idx = parts.offsets[g, None] + (u * parts.counts[g, None]).long().clamp_max(parts.counts[g, None] - 1)
    idx = idx.reshape(-1)
    return parts.points[idx], parts.instance[g].repeat_interleave(per_group), parts.labels[idx].view(groups, per_group)


def part_contrastive_loss(embedding: Tensor, labels: Tensor, n_labels: int, temperature: float = TEMPERATURE) -> Tensor:
    """Mean cross-entropy of each point's unit ``embedding`` [G, P, D] against the normalized
    mean embeddings of the parts of its own group (``labels`` [G, P], ints below
    ``n_labels``), its own part being the target: −log softmax(e·c_own / τ) over the group's
    parts.  A group with one part adds 0.  Fixed shapes, no host read."""
    onehot = (labels[..., None] == torch.arange(n_labels, device=labels.device)).to(embedding.dtype)  # [G, P, L]
    present = onehot.sum(dim=1) > 0  # [G, L]
    centres = F.normalize(onehot.transpose(1, 2) @ embedding, dim=-1)  # [G, L, D]
    logits = (embedding @ centres.transpose(1, 2)) / temperature  # [G, P, L]
    logits = logits.masked_fill(~present[:, None, :], float("-inf"))
    return F.cross_entropy(logits.reshape(-1, n_labels), labels.reshape(-1))
