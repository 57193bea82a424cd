"""Category datasets: the on-disk format (EditNeRF / NeRF-synthetic per instance) and procedural chairs."""

from .format import Frame, TwinSpec, read_mask, write_instances_txt, write_parts, write_split, write_twins_json
from .loading import (
    Category,
    InstanceData,
    TrainingRays,
    View,
    dataset_info,
    load_category,
    load_instance_dir,
    load_twins,
    parse_view_spec,
    training_rays,
)
from .synth import SynthConfig, SynthResult, make_chair, render_chair, write_synth_category

__all__ = [
    "Category",
    "Frame",
    "InstanceData",
    "SynthConfig",
    "SynthResult",
    "TrainingRays",
    "TwinSpec",
    "View",
    "dataset_info",
    "load_category",
    "load_instance_dir",
    "load_twins",
    "make_chair",
    "parse_view_spec",
    "read_mask",
    "render_chair",
    "training_rays",
    "write_instances_txt",
    "write_parts",
    "write_split",
    "write_synth_category",
    "write_twins_json",
]
