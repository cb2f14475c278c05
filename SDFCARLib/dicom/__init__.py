"""X-ray angiography DICOM input: frames, frame choice and the C-arm geometry from the tags.

One module per job; the names below are re-exported so that ``from SDFCARLib.dicom import X``
works for all of them.

``read``
    ``load_xa`` and ``XARun`` (XA/XRF and enhanced objects, decoders, rescale, MONOCHROME1),
    ``check_decodable``, the SOP classes, ``tag_label`` and ``DicomInputError``.
``intensity``
    The grey levels against the X-ray intensity (0028,1040 and its Sign): ``IntensityTags``,
    ``intensity_tags_of_file`` (header only) and ``linearised`` (LOG frames, or frames with an enhanced
    object's TO_LINEAR LUT, on a linear scale).
``frames``
    Frame times, end diastole (ECG tags and waveforms), ``contrast_scores`` and ``choose_frame``.
``geometry``
    ``view_from_dicom`` / ``geometry_from_dicom_runs`` (the C-arm views of any number of runs from
    the positioner tags, with user overrides and the provenance of every value; ``geometry_from_dicom``
    for two) and ``write_geometry_json``.
``cli``
    ``add_dicom_arguments``, ``dicom_runs_from_args`` and ``cli_geometry_from_args`` for the command
    line (``--dicom A B C …`` or ``--dicom1/--dicom2``).

SDFCARLib reads DICOM only; the tests build their XA objects with ``Testing/xa_writer.py``.
"""

from .cli import DicomRun, add_dicom_arguments, cli_geometry_from_args, dicom_runs_from_args
from .frames import (CONTRAST_MAX_SIDE_PX, CONTRAST_NOISE_K, CONTRAST_TOPHAT_PX, FrameChoice, check_frame_index,
                     choose_frame, contrast_scores, end_diastolic_frames, frame_times_ms)
from .geometry import (DEFAULT_VOLUME, OVERRIDE_KEYS, burned_in_annotation_note, geometry_from_dicom,
                       geometry_from_dicom_runs, view_from_dicom, write_geometry_json)
from .intensity import IntensityTags, intensity_tags_of_file, linearised
from .read import (ENHANCED_SOP_CLASSES, XA_SOP_CLASS, XA_SOP_CLASSES, XRF_SOP_CLASS, DicomInputError, PathLike,
                   XARun, check_decodable, load_xa, tag_label)

__all__ = [
    "CONTRAST_MAX_SIDE_PX", "CONTRAST_NOISE_K", "CONTRAST_TOPHAT_PX", "DEFAULT_VOLUME", "ENHANCED_SOP_CLASSES",
    "IntensityTags", "OVERRIDE_KEYS", "XA_SOP_CLASS", "XA_SOP_CLASSES", "XRF_SOP_CLASS", "DicomInputError", "DicomRun", "FrameChoice",
    "PathLike",
    "XARun", "add_dicom_arguments", "burned_in_annotation_note", "check_decodable", "check_frame_index", "choose_frame", "cli_geometry_from_args",
    "contrast_scores", "dicom_runs_from_args", "end_diastolic_frames", "frame_times_ms", "geometry_from_dicom",
    "geometry_from_dicom_runs", "intensity_tags_of_file", "linearised", "load_xa",
    "tag_label", "view_from_dicom", "write_geometry_json",
]
