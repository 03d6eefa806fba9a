"""Image and file I/O: reading (:mod:`~d2turb.io.read`), atomic writes and stale temp files
(:mod:`~d2turb.io.atomic`), the PNG encoder and ``write_image`` (:mod:`~d2turb.io.png`), the background writer
of the batch jobs (:mod:`~d2turb.io.writer`) and their skeleton over input files (:mod:`~d2turb.io.jobs`). Every
name is importable from ``d2turb.io``."""

from d2turb.defaults import DEFAULT_PNG_LEVEL
from d2turb.io.atomic import (
    LOCK_NAME,
    NAME_MAX,
    FolderLock,
    atomic_path,
    check_output_dir,
    remove_stale_temp_files,
    temp_name,
    write_bytes,
    write_json,
    write_npy,
    write_text,
)
from d2turb.io.jobs import FileJob, JobOptions, named_error
from d2turb.io.png import SharedUint8, encode_png, float_array, to_uint8, write_image
from d2turb.io.read import (
    FLOAT_TOLERANCE,
    IMAGE_SUFFIXES,
    cache_dir,
    check_unique_stems,
    expand_inputs,
    image_size,
    list_images,
    open_image,
    read_frame,
    read_image,
    set_max_pixels,
)
from d2turb.io.writer import BackgroundWriter
from d2turb.ops.checks import check_image_tensor  # a tensor check, kept importable from here

__all__ = [
    "DEFAULT_PNG_LEVEL",
    "FLOAT_TOLERANCE",
    "IMAGE_SUFFIXES",
    "LOCK_NAME",
    "NAME_MAX",
    "BackgroundWriter",
    "FileJob",
    "JobOptions",
    "FolderLock",
    "atomic_path",
    "cache_dir",
    "check_image_tensor",
    "check_output_dir",
    "check_unique_stems",
    "encode_png",
    "expand_inputs",
    "float_array",
    "image_size",
    "list_images",
    "named_error",
    "open_image",
    "read_frame",
    "read_image",
    "remove_stale_temp_files",
    "set_max_pixels",
    "temp_name",
    "to_uint8",
    "SharedUint8",
    "write_bytes",
    "write_image",
    "write_json",
    "write_npy",
    "write_text",
]
