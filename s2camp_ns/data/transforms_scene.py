"""A nerfstudio scene (``transforms.json``) read through nerfstudio's parser, validated: the file checked first
(``transforms_file``), missing images named, intrinsics fitted to the images (``scene_formats``)."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import torch
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.data.dataparsers.nerfstudio_dataparser import Nerfstudio, NerfstudioDataParserConfig

from s2camp_ns.data.image_check import decoded_sizes
from s2camp_ns.data.scene_config import SceneConfig
from s2camp_ns.data.scene_formats import (
    ParsedSplit,
    fit_intrinsics_to_images,
    nerfstudio_parser_options,
    resolve_downscale,
)
from s2camp_ns.data.transforms_file import read_transforms


def transforms_declared_sizes(source: Path, k: int) -> dict[str, tuple[int, int]]:
    """Full-size (w, h) of every frame, by the image path nerfstudio reads at downscale factor k; the top-level
    ``w``/``h`` win over a frame's, as in nerfstudio's parser."""
    meta = read_transforms(source)
    data_dir = source.parent
    sizes = {}
    for frame in meta.get("frames", []):
        file_path = Path(frame["file_path"])
        path = data_dir / file_path if k == 1 else data_dir / f"images_{k}" / file_path.name
        w, h = meta["w"] if "w" in meta else frame["w"], meta["h"] if "h" in meta else frame["h"]
        sizes[os.path.normpath(path)] = (int(w), int(h))
    return sizes


def parse_transforms(config: SceneConfig, source: Path, split: str) -> tuple[DataparserOutputs, ParsedSplit]:
    """The split of the transforms.json ``source``: nerfstudio's outputs, cameras fitted to the images read, and the
    ``ParsedSplit``."""
    read_transforms(source)  # the file's own errors named before nerfstudio's parser reads it
    k = resolve_downscale(source.parent, config.images_path, config.downscale_factor)
    ns_config = NerfstudioDataParserConfig(
        data=source, downscale_factor=k, load_3D_points=False, **nerfstudio_parser_options(config)
    )
    outputs = Nerfstudio(ns_config).get_dataparser_outputs(split=split)
    missing = [p for p in outputs.image_filenames if not Path(p).is_file()]
    if missing:
        raise FileNotFoundError(
            f"{source} lists image '{missing[0]}', which does not exist ({len(missing)} of "
            f"{len(outputs.image_filenames)} {split} images missing)"
        )
    sizes = transforms_declared_sizes(source, k)
    declared = [(*sizes[os.path.normpath(p)], f"the w x h in {source}") for p in outputs.image_filenames]
    cameras = fit_intrinsics_to_images(outputs.cameras, outputs.image_filenames, declared, k, source)
    if outputs.mask_filenames:
        decoded_sizes(outputs.mask_filenames, source, "masks")
    full_size = torch.tensor([declared_size[:2] for declared_size in declared], dtype=torch.int64)
    names = [Path(p).name for p in outputs.image_filenames]
    parsed = ParsedSplit(image_names=names, full_image_size=full_size, downscale_factor=k)
    return dataclasses.replace(outputs, cameras=cameras), parsed


__all__ = ["parse_transforms", "transforms_declared_sizes"]
