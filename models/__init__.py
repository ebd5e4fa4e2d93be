"""Pure mathematics of the two-segment steerable catheter and of bi-plane imaging."""

from models.catheter import Catheter, Frames, ShapeVectors, check_joints, default_catheter
from models.modal import ModalSegment, PowerBasis
from models.model_file import ModelFileError, load_catheter
from models.rotations import deg_from_rad, wrap_angle

__all__ = [
    "Catheter",
    "Frames",
    "ModalSegment",
    "ModelFileError",
    "PowerBasis",
    "ShapeVectors",
    "check_joints",
    "default_catheter",
    "load_catheter",
    "deg_from_rad",
    "wrap_angle",
]
